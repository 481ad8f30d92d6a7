"""The contrast of a mixture's make-up (bo/discovery/contrast.py, scripts/contrast_check.py).

- The lab's contrast between two conditions and its 95 % half-width are recomputed by hand from
  Table 2's 25-75 and 75-25 cells (difference of means, the two CIs in quadrature).
- From a store written through the campaign API, with known KPIs: each parameter set run on both
  conditions gives the difference of its means (rel 1e-12); a set run on one condition only, a
  jammed run and a run that a second store copies are left out; the pooled replicate sd equals the
  textbook pooled sd; a set agrees with the lab exactly when |C - C_lab| <= 1.96 x the combined
  standard error.
- C's fit on the parameters: on sets whose C is exactly linear in two parameters (a third held), the
  change per sd is the slope times the parameter's sd (rel 1e-9) and the held one is left out; on a
  non-linear C the coefficients equal the textbook weighted least squares, (X'WX)^-1 X'Wy with W the
  inverse squared standard errors (rel 1e-9); too few sets is a ConfigError naming the counts.
- Across stages: one parameter set's verification on one condition and validation on the other pair
  up only with ``across_stages`` (stage named ``verification+validation``), and give their difference.
- Bad input (an unknown condition, the same condition twice) names the value and what is allowed.
"""
from __future__ import annotations

import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bo.campaign.executor import EvalOutcome
from bo.campaign.store import CampaignStore
from bo.discovery.contrast import Z95, contrast_check, format_contrast, lab_contrast, regress_contrast
from torchdem.errors import ConfigError
from torchdem.measured import Condition, KPIValue, MeasuredData, load_measured

REPO = Path(__file__).resolve().parent.parent
KPIS = ("angle_of_repose_deg", "shear_angle_deg")


def test_the_labs_contrast_is_the_difference_of_table_2s_means():
    lab = lab_contrast(load_measured(), "25-75", "75-25")
    assert lab["angle_of_repose_deg"] == pytest.approx((29.63 - 28.55, math.hypot(0.75, 0.65)), rel=1e-12)
    assert lab["shear_angle_deg"] == pytest.approx((44.76 - 39.03, math.hypot(1.21, 1.49)), rel=1e-12)
    assert lab["mass_flow_rate_full_kg_s"] == pytest.approx((10.24 - 10.29, math.hypot(0.45, 0.1)), abs=1e-12)


def _measured() -> MeasuredData:
    def cond(name, aor, shear):
        return Condition(name=name, pellet_mass_fraction=0.5, layering=("pellet", "sinter"), fill_mass_kg=40.0,
                         kpis={"angle_of_repose_deg": KPIValue(aor, 0.4, "deg"),
                               "shear_angle_deg": KPIValue(shear, 0.3, "deg")}, replicates=5)
    return MeasuredData(source="test lab", conditions=(cond("A", 30.0, 44.0), cond("B", 29.0, 40.0)))


# runs of each parameter set per condition: (angle of repose, shear angle); None: a jammed run
RUNS = {
    0.1: {"A": [(31.0, 41.0), (31.4, 41.6)], "B": [(27.0, 38.6), (27.2, 39.4), None]},
    0.2: {"A": [(30.2, 43.0)], "B": [(29.0, 39.5)]},
    0.3: {"A": [(32.0, 45.0), (32.5, 44.0), (31.5, 44.5)], "B": []},  # one condition only: no contrast
}


def _store(tmp_path) -> Path:
    path = tmp_path / "store.sqlite"
    store = CampaignStore(path, "hash")
    for condition in ("A", "B"):
        for knob, runs in RUNS.items():
            if not runs[condition]:
                continue
            key = f"{condition}{knob}"
            store.batch("initial", key, lambda: [{"knob": knob}], seeds=list(range(len(runs[condition]))),
                        conditions=[condition])

            def kpis(row):
                if row is None:
                    return {"angle_of_repose_deg": 1.0, "shear_angle_deg": 0.0, "discharge_jammed": 1.0}
                return {"angle_of_repose_deg": row[0], "shear_angle_deg": row[1], "discharge_jammed": 0.0}

            store.record([(t, EvalOutcome.success(kpis(runs[condition][t.seed]), 1.0))
                          for t in store.claim(100, stage="initial", batch_key=key)])
    return path


def test_each_set_on_both_conditions_gives_its_difference_of_means(tmp_path):
    path = _store(tmp_path)
    copy = tmp_path / "copy.sqlite"
    shutil.copy(path, copy)  # the same runs again, as a discovery's copy of its baseline: counted once
    before = path.read_bytes()
    check = contrast_check([path, copy], _measured(), "A", "B", kpis=KPIS)
    assert path.read_bytes() == before  # only read
    assert [s.params["knob"] for s in check.sets] == [0.1, 0.2]
    assert check.contrast("angle_of_repose_deg") == pytest.approx([31.2 - 27.1, 30.2 - 29.0], rel=1e-12)
    assert check.contrast("shear_angle_deg") == pytest.approx([41.3 - 39.0, 43.0 - 39.5], rel=1e-12)
    assert [s.runs("b") for s in check.sets] == [2, 1]  # the jammed run left out
    # pooled over the sets with replicates: at A the two sets of 0.1 and 0.3 (2 + 3 runs), at B 0.1 only
    aor_a = [np.array([31.0, 31.4]), np.array([32.0, 32.5, 31.5])]
    ss = sum(float(((g - g.mean()) ** 2).sum()) for g in aor_a)
    assert check.noise[("A", "angle_of_repose_deg")] == pytest.approx((math.sqrt(ss / 3), 3), rel=1e-12)
    assert check.noise[("B", "angle_of_repose_deg")] == pytest.approx((np.std([27.0, 27.2], ddof=1), 1), rel=1e-12)


def test_a_set_agrees_with_the_lab_within_the_combined_standard_error(tmp_path):
    check = contrast_check([_store(tmp_path)], _measured(), "A", "B", kpis=KPIS)
    lab, half = check.lab["shear_angle_deg"]
    assert (lab, half) == pytest.approx((4.0, math.hypot(0.3, 0.3)), rel=1e-12)
    sd_a, sd_b = check.noise[("A", "shear_angle_deg")][0], check.noise[("B", "shear_angle_deg")][0]
    se = np.array([math.sqrt(sd_a ** 2 / 2 + sd_b ** 2 / 2), math.sqrt(sd_a ** 2 + sd_b ** 2)])
    assert check.standard_error("shear_angle_deg") == pytest.approx(se, rel=1e-12)
    expected = np.abs(check.contrast("shear_angle_deg") - lab) <= Z95 * np.sqrt(se ** 2 + (half / Z95) ** 2)
    assert list(check.consistent("shear_angle_deg")) == list(expected)
    assert list(expected) == [False, True]  # 2.3 misses 4.0; 3.5 is within its larger error
    text = format_contrast(check, by_stage=True)
    assert "| shear angle, deg | +4.00 +- 0.42 | +2.90 (0.85) | +2.30 to +3.50 | 1 of 2 |" in text
    assert "| store.sqlite | initial | 2 | +2.65 | +2.90 |" in text


def test_bad_conditions_name_the_value_and_the_known_ones(tmp_path):
    path = _store(tmp_path)
    with pytest.raises(ConfigError, match="condition 'C' is not in .*known conditions: A, B"):
        contrast_check([path], _measured(), "C", "B")
    with pytest.raises(ConfigError, match="both 'A'; expected two different conditions"):
        contrast_check([path], _measured(), "A", "A")
    out = subprocess.run([sys.executable, str(REPO / "scripts" / "contrast_check.py"), str(path),
                          "--between", "25-75", "99-1"], capture_output=True, text=True, cwd=REPO)
    assert out.returncode != 0 and "condition '99-1' is not in" in out.stderr


def test_script_prints_the_table_for_table_2(tmp_path):
    out = subprocess.run([sys.executable, str(REPO / "scripts" / "contrast_check.py"), str(_store(tmp_path))],
                         capture_output=True, text=True, cwd=REPO, check=True).stdout
    assert out.startswith("## Contrast between conditions, C = KPI(25-75) - KPI(75-25)")
    assert "| angle of repose, deg | +1.08 +- 0.99 | - | - | 0 of 0 |" in out  # the store has no 25-75 runs


# sets of (k1, k2): C of the angle of repose is 2 k1 - 0.5 k2 exactly; of the shear angle k1^2 + k2
K_SETS = [(0.1, 1.0), (0.2, 3.0), (0.3, 2.0), (0.4, 5.0), (0.5, 4.0), (0.6, 1.0), (0.7, 2.0), (0.8, 3.0)]


def _linear_store(tmp_path, sets=K_SETS) -> Path:
    path = tmp_path / "linear.sqlite"
    store = CampaignStore(path, "hash")
    for i, (k1, k2) in enumerate(sets):
        for condition in ("A", "B"):
            base = 30.0 + 0.01 * i  # runs of equal values would count as one run copied between stores
            aor, shear = (base + 2 * k1 - 0.5 * k2, base + k1 ** 2 + k2) if condition == "A" else (base, base)
            # replicates symmetric about the mean, so the means are exact; unequal counts give unequal weights
            offsets = [-0.1, 0.1] if (condition == "A" and i % 3 == 0) or (condition == "B" and i % 2) else [0.0]
            key = f"{condition}{i}"
            store.batch("initial", key, lambda: [{"k1": k1, "k2": k2, "held": 7.0}],
                        seeds=list(range(len(offsets))), conditions=[condition])
            store.record([(t, EvalOutcome.success({"angle_of_repose_deg": aor + offsets[t.seed],
                                                   "shear_angle_deg": shear + offsets[t.seed],
                                                   "discharge_jammed": 0.0}, 1.0))
                          for t in store.claim(100, stage="initial", batch_key=key)])
    return path


def test_the_contrasts_fit_on_the_parameters_recovers_its_slopes(tmp_path):
    check = contrast_check([_linear_store(tmp_path)], _measured(), "A", "B", kpis=KPIS)
    k = np.array(K_SETS)
    fit = regress_contrast(check, "angle_of_repose_deg")
    assert fit.parameters == ("k1", "k2")  # "held" does not vary
    assert fit.weighted and fit.n_sets == 8
    sd = k.std(axis=0, ddof=1)
    assert fit.parameter_sd == pytest.approx(sd, rel=1e-12)
    assert fit.effect == pytest.approx([2 * sd[0], -0.5 * sd[1]], rel=1e-9)
    assert fit.mean_c == pytest.approx(2 * k[:, 0].mean() - 0.5 * k[:, 1].mean(), rel=1e-9)
    assert fit.r2 == pytest.approx(1.0, abs=1e-12)
    assert fit.at({"k1": 1.0, "k2": 0.0}) == pytest.approx(2.0, rel=1e-9)
    with pytest.raises(ConfigError, match=r"\['k2'\] are not given"):
        fit.at({"k1": 1.0})

    shear = regress_contrast(check, "shear_angle_deg")  # k1^2 + k2: not linear, so the weights matter
    z = np.column_stack([np.ones(8), (k - k.mean(axis=0)) / sd])
    w = 1.0 / check.standard_error("shear_angle_deg") ** 2
    assert len(set(np.round(w, 9))) > 1  # unequal weights
    beta = np.linalg.solve(z.T @ (w[:, None] * z), z.T @ (w * check.contrast("shear_angle_deg")))
    assert shear.mean_c == pytest.approx(beta[0], rel=1e-9)
    assert shear.effect == pytest.approx(beta[1:], rel=1e-9)
    assert 0.9 < shear.r2 < 1.0

    text = format_contrast(check, regress=True)
    assert "angle of repose, deg: 8 sets, R^2 1.00, C at the sets' mean parameters" in text
    assert "| parameter | per sd (se) | p | the parameter's sd |" in text
    assert "; at the given set +2.00" in format_contrast(check, regress=True, at={"k1": 1.0, "k2": 0.0})


def test_the_fit_needs_more_sets_than_parameters(tmp_path):
    check = contrast_check([_linear_store(tmp_path, K_SETS[:3])], _measured(), "A", "B", kpis=KPIS)
    with pytest.raises(ConfigError, match="3 parameter sets ran on both 'A' and 'B', and they vary 2 parameters"):
        regress_contrast(check, "shear_angle_deg")
    with pytest.raises(ConfigError, match="KPI 'flow' is not one of the check's"):
        regress_contrast(check, "flow")
    assert "No fit: regress_contrast: 3 parameter sets" in format_contrast(check, regress=True)
    empty = tmp_path / "empty.sqlite"
    CampaignStore(empty, "hash")
    with pytest.raises(ConfigError, match="no parameter set ran on both 'A' and 'B' in .*empty.sqlite"):
        regress_contrast(contrast_check([empty], _measured(), "A", "B", kpis=KPIS), "shear_angle_deg")


def test_a_calibrated_sets_verification_and_validation_pair_across_stages(tmp_path):
    path = tmp_path / "calibrated.sqlite"
    store = CampaignStore(path, "hash")
    for stage, condition, rows in (("verification", "A", [(30.0, 42.0), (30.4, 42.6)]),
                                   ("validation", "B", [(29.0, 40.1), (29.2, 40.3), (29.6, 40.2)])):
        store.batch(stage, stage, lambda: [{"knob": 0.5}], seeds=list(range(len(rows))), conditions=[condition])
        store.record([(t, EvalOutcome.success({"angle_of_repose_deg": rows[t.seed][0],
                                               "shear_angle_deg": rows[t.seed][1], "discharge_jammed": 0.0}, 1.0))
                      for t in store.claim(100, stage=stage, batch_key=stage)])
    assert contrast_check([path], _measured(), "A", "B", kpis=KPIS).sets == ()
    check = contrast_check([path], _measured(), "A", "B", kpis=KPIS, across_stages=True)
    assert [s.stage for s in check.sets] == ["verification+validation"]
    assert check.contrast("angle_of_repose_deg") == pytest.approx([30.2 - (29.0 + 29.2 + 29.6) / 3], rel=1e-12)
    assert check.contrast("shear_angle_deg") == pytest.approx([42.3 - 40.2], rel=1e-12)
    out = subprocess.run([sys.executable, str(REPO / "scripts" / "contrast_check.py"), str(path), "--between",
                          "50-50", "75-25", "--across-stages"], capture_output=True, text=True, cwd=REPO, check=True)
    assert "0 parameter sets ran on both conditions" in out.stdout  # the store's conditions are A and B
