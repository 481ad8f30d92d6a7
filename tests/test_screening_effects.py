"""bo.screening.effects: main effects of a screening against a known linear truth, and
bo.screening.pipeline.stored_screening against run_screening on a shipped store."""
import numpy as np
import pytest
from scipy import stats

from bo.design.dsd import definitive_screening_design
from bo.screening.effects import main_effects
from bo.screening.stepwise import ScreeningResults
from torchdem.errors import ConfigError

NAMES = ("mu_s_pp", "mu_r_pp", "e_pp", "mu_s_ss", "mu_r_ss", "e_ss")
LOW = np.array([0.3, 0.045, 0.5, 0.5, 0.06, 0.25])
HIGH = np.array([0.6, 0.075, 0.9, 0.9, 0.10, 0.45])
# KPI change from low to high of each parameter, two KPIs
EFFECT = np.array([[2.0, -0.5], [3.0, 0.0], [-1.0, 0.2], [0.0, -0.8], [0.5, 0.1], [0.0, 0.0]])
SD = np.array([0.5, 0.1])


def _screening(replicates=6, curvature=0.0, seed=0) -> ScreeningResults:
    coded = definitive_screening_design(len(NAMES), 2)
    physical = (LOW + HIGH) / 2 + coded * (HIGH - LOW) / 2
    rng = np.random.default_rng(seed)
    mean = np.array([30.0, 10.0]) + coded @ (EFFECT / 2)  # [runs, 2]
    mean[:, 0] += curvature * coded[:, 0] ** 2  # a square term on the first KPI only
    values = mean[:, None, :] + rng.normal(size=(len(coded), replicates, 2)) * SD
    values[3, -1, 0] = np.nan  # a failed measurement is left out, not fitted
    return ScreeningResults(parameter_names=NAMES, coded=coded, physical=physical, seeds=tuple(range(replicates)),
                            kpi_names=("angle_of_repose_deg", "mass_flow_rate_full_kg_s"), kpi_values=values)


def test_main_effects_recover_a_linear_truth_within_their_standard_errors():
    fit = main_effects(_screening())
    z = (fit.effect - EFFECT) / fit.effect_se
    assert np.all(np.abs(z) < 4.0), z  # 12 estimates, each a t-variable: |z| < 4 at p ~ 1e-3 overall
    assert fit.n_runs.tolist() == [17 * 6 - 1, 17 * 6]
    # the pure error is one run's sd: chi^2 bounds of its degrees of freedom at 99.9 %
    dof = fit.replicate_dof
    assert dof.tolist() == [17 * 5 - 1, 17 * 5]
    lo, hi = np.sqrt(stats.chi2.ppf([0.0005, 0.9995], dof[:, None]) / dof[:, None]).T
    assert np.all(fit.replicate_sd > SD * lo) and np.all(fit.replicate_sd < SD * hi)
    # a linear truth leaves no lack of fit: the residual is the replicate scatter
    assert np.allclose(fit.residual_sd, fit.replicate_sd, rtol=0.2)
    assert np.all(fit.lack_of_fit_p > 0.001)
    np.testing.assert_allclose(fit.low, LOW)
    np.testing.assert_allclose(fit.high, HIGH)


def test_shift_and_prediction_follow_the_slopes():
    fit = main_effects(_screening())
    k = fit.index("mu_r_pp")
    np.testing.assert_allclose(fit.shift("mu_r_pp", 0.045, 0.075), fit.effect[k])
    # extrapolated to twice the screened range: twice the change, twice the standard error
    np.testing.assert_allclose(fit.shift("mu_r_pp", 0.045, 0.105), 2 * fit.effect[k])
    np.testing.assert_allclose(fit.shift_se("mu_r_pp", 0.105, 0.045), 2 * fit.effect_se[k])
    np.testing.assert_allclose(fit.predict({}), fit.intercept)
    corner = {n: h for n, h in zip(NAMES, HIGH)}
    np.testing.assert_allclose(fit.predict(corner), fit.intercept + fit.effect.sum(0) / 2)
    with pytest.raises(ConfigError, match="lobe_spacing_sinter.*not screened"):
        fit.shift("lobe_spacing_sinter", 0.15, 0.2)


def test_curvature_shows_as_lack_of_fit():
    fit = main_effects(_screening(curvature=3.0))
    assert np.all(fit.residual_sd[0] > 2 * fit.replicate_sd[0])  # the quadratic term left out
    assert fit.lack_of_fit_p[0] < 1e-6 and fit.lack_of_fit_p[1] > 0.001
    assert fit.residual_sd[1] < 1.3 * fit.replicate_sd[1]  # the other KPI has none


def test_too_few_runs_is_an_error_naming_the_kpi():
    s = _screening(replicates=1)
    values = s.kpi_values.copy()
    values[:12, :, 1] = np.nan  # 5 finite runs for 7 coefficients
    bad = ScreeningResults(parameter_names=s.parameter_names, coded=s.coded, physical=s.physical, seeds=s.seeds,
                           kpi_names=s.kpi_names, kpi_values=values, source="test screening")
    with pytest.raises(ConfigError, match="test screening: finite runs of mass_flow_rate_full_kg_s = 5"):
        main_effects(bad)


def test_stored_screening_reads_what_run_screening_assembles(tmp_path):
    """On the shipped first lab campaign (a copy), the store read alone gives the same design, seeds
    and KPIs as the screening stage itself."""
    from test_lab_profile import KPIS4, _shipped_screening

    from bo.screening.pipeline import stored_screening

    _, expected = _shipped_screening(tmp_path)
    got = stored_screening(tmp_path / "lab.sqlite", KPIS4)
    assert sorted(got.parameter_names) == sorted(expected.parameter_names)
    order = [expected.parameter_names.index(n) for n in got.parameter_names]  # the store keeps them by name
    assert got.seeds == expected.seeds
    np.testing.assert_array_equal(got.coded, expected.coded[:, order])
    np.testing.assert_allclose(got.physical, expected.physical[:, order], rtol=1e-12)
    np.testing.assert_array_equal(got.kpi_values, expected.kpi_values[..., [expected.kpi_names.index(k) for k in KPIS4]])
    with pytest.raises(ConfigError, match="condition = '75-25'.*'50-50'"):
        stored_screening(tmp_path / "lab.sqlite", KPIS4, condition="75-25")
    with pytest.raises(ConfigError, match="no campaign store"):
        stored_screening(tmp_path / "missing.sqlite", KPIS4)


def test_the_script_reads_a_shipped_screening_and_fits_the_lab(monkeypatch, capsys):
    """scripts/screening_effects.py on the first lab campaign's store (opened read-only): the main
    effects, the detection table and a main-effects fit of Table 2's 50-50 inside given bounds."""
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    sys.path.insert(0, str(root / "scripts"))
    import screening_effects

    store = root / "campaigns" / "table2" / "lab_4s.sqlite"
    before = store.stat().st_mtime_ns
    monkeypatch.setattr(sys, "argv", ["screening_effects.py", str(store), "--lab-fit", "mu_s_pg=0.285:0.9"])
    screening_effects.main()
    out = capsys.readouterr().out
    assert "66 runs, 2 replicates of 33 points" in out
    assert "| lobe_spacing_sinter | 0.15-0.3 |" in out
    fitted = float(out.split("mu_s_pg=0.285:0.9: ")[1].split()[0])
    assert 0.0 <= fitted < 0.2
    assert store.stat().st_mtime_ns == before
    # the verification's objective: the largest miss in CI half-widths, consistent with the table it prints
    monkeypatch.setattr(sys, "argv", ["screening_effects.py", str(store), "--lab-fit", "--objective", "ci"])
    screening_effects.main()
    out = capsys.readouterr().out.split("The largest |model - lab| / CI half-width")[1]
    worst = float(out.split(": ")[1].split()[0])
    rows = [line.split("|") for line in out.splitlines() if line.startswith("| ") and "KPI" not in line and "---" not in line]
    ci = {"AoR": 0.48, "shear": 1.62, "flow": 0.35, "lower box": 0.55}  # Table 2, 50-50
    misses = [abs(float(r[2]) - float(r[3])) / ci[r[1].strip()] for r in rows]
    assert len(misses) == 4 and max(misses) == pytest.approx(worst, abs=0.02)  # the table rounds to 0.01
    monkeypatch.setattr(sys, "argv", ["screening_effects.py", str(store), "--lab-fit", "density_pellet=3000:4000"])
    with pytest.raises(ConfigError, match=r"\['density_pellet'\] were not screened"):
        screening_effects.main()
