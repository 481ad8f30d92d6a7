"""Tests for bo/studies/timestep.py: time-step choice (paper section 3.2.4) and the shear-modulus study.

Replicate values are built deterministically as ``mean + std * Z`` with a fixed vector ``Z``
of sample mean 0 and sample standard deviation 1, so every fraction's mean and std are exactly
the intended ones and each criterion can be switched on or off on purpose. The Welch tolerance
is checked against scipy's Welch t-test as an independent oracle.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import stats

from bo.studies.timestep import choose_time_step, mean_change_tolerance, summarise_shear_modulus_study
from torchdem.errors import ConfigError

Z = np.array([-2.0, -1.0, 0.0, 1.0, 2.0]) / np.std([-2.0, -1.0, 0.0, 1.0, 2.0], ddof=1)
FRACTIONS = (0.05, 0.10, 0.15, 0.20, 0.30, 0.40)
KPIS = ("angle_of_repose_deg", "mass_flow_rate_kg_s")


def study(means: np.ndarray, stds: np.ndarray) -> np.ndarray:
    """``[n_fractions, 5, n_kpi]`` with exactly the given means and stds."""
    return means[:, None, :] + stds[:, None, :] * Z[None, :, None]


def paper_like() -> np.ndarray:
    """Angle of repose drops and scatters above 15 %, mass flow rate stays put (Fig. 9)."""
    means = np.array([[30.0, 10.3]] * 6)
    stds = np.array([[0.3, 0.1]] * 6)
    means[3:, 0] -= 2.0
    stds[3:, 0] *= 3.0
    return study(means, stds)


def test_chooses_the_largest_stable_fraction_like_the_paper():
    # Rayleigh time step 3.94e-5 s: 15 % of it is the paper's 5.91e-6 s.
    choice = choose_time_step(FRACTIONS, paper_like(), KPIS, rayleigh_time_step_s=3.94e-5)
    assert choice.chosen_fraction == 0.15
    assert choice.chosen_time_step_s == pytest.approx(5.91e-6)
    np.testing.assert_allclose(choice.mean[:, 0], [30, 30, 30, 28, 28, 28])
    np.testing.assert_allclose(choice.std[:, 1], 0.1)
    assert choice.mean_stable[:, 0].tolist() == [True] * 3 + [False] * 3
    assert choice.std_stable[:, 0].tolist() == [True] * 3 + [False] * 3
    assert choice.mean_stable[:, 1].all() and choice.std_stable[:, 1].all()
    text = str(choice)
    assert "fraction 0.2: fails: angle_of_repose_deg mean 28" in text
    assert "chosen: fraction 0.15 = 5.91e-06 s" in text
    json.dumps(choice.to_dict(), allow_nan=False)


def test_deciding_kpis_can_leave_out_a_noisy_kpi():
    choice = choose_time_step(FRACTIONS, paper_like(), KPIS, kpis=["mass_flow_rate_kg_s"])
    assert choice.chosen_fraction == 0.40
    assert choice.deciding_kpis == ("mass_flow_rate_kg_s",)


def test_std_growth_factor_decides_alone():
    means = np.full((6, 1), 10.0)
    stds = np.array([[0.2], [0.2], [0.3], [0.39], [0.5], [0.2]])
    values = study(means, stds)
    # 0.30 fails (0.5 > 2 x 0.2); 0.40 passes again but does not count: the paper asks for
    # stable KPIs "up to the selected time step"
    assert choose_time_step(FRACTIONS, values, ["k"]).chosen_fraction == 0.20
    assert choose_time_step(FRACTIONS, values, ["k"], std_growth_factor=3.0).chosen_fraction \
        == 0.40


def test_relative_tolerance_covers_differences_the_replicates_resolve():
    means = np.array([[10.0], [10.05], [10.15]])  # +0.5 % and +1.5 %
    stds = np.full((3, 1), 0.001)  # tiny CI: only the relative tolerance can accept
    values = study(means, stds)
    fractions = (0.05, 0.1, 0.2)
    assert choose_time_step(fractions, values, ["k"]).chosen_fraction == 0.2  # 2 % default
    strict = choose_time_step(fractions, values, ["k"], relative_tolerance=0.01)
    assert strict.chosen_fraction == 0.1
    assert strict.allowed_change[2, 0] == pytest.approx(0.1)


def test_welch_tolerance_agrees_with_scipy_welch_test():
    rng = np.random.default_rng(4)
    agree = 0
    for _ in range(100):
        a = rng.normal(0.0, 1.0, 5)
        b = rng.normal(rng.uniform(-2, 2), rng.uniform(0.3, 3.0), 7)
        allowed = mean_change_tolerance(a.std(ddof=1), 5, b.std(ddof=1), 7, a.mean(), 1e-12)
        within = abs(b.mean() - a.mean()) <= allowed
        agree += within == (stats.ttest_ind(a, b, equal_var=False).pvalue >= 0.05)
    assert agree == 100


def test_unsorted_fractions_are_sorted_with_their_rows():
    values = paper_like()
    order = [3, 0, 5, 1, 4, 2]
    choice = choose_time_step([FRACTIONS[i] for i in order], values[order], KPIS)
    assert choice.fractions == FRACTIONS and choice.chosen_fraction == 0.15


def test_failed_replicates_are_left_out():
    values = paper_like()
    values[1, :3, 1] = np.nan
    choice = choose_time_step(FRACTIONS, values, KPIS)
    assert choice.n[1].tolist() == [5, 2]
    values[1, :4, 1] = np.nan
    with pytest.raises(ConfigError, match="'mass_flow_rate_kg_s' at fraction 0.1 has 1 finite"):
        choose_time_step(FRACTIONS, values, KPIS)


def test_shear_modulus_summary():
    moduli = (1e8, 1e7, 1e6)
    means = np.array([[30.0, 10.0], [30.1, 10.05], [27.0, 10.1]])
    stds = np.full((3, 2), 0.2)
    walls = [900.0, 300.0, 100.0]
    summary = summarise_shear_modulus_study(moduli[::-1], study(means, stds)[::-1], KPIS,
                                            walls[::-1])
    assert summary.shear_moduli_pa == moduli and summary.reference_modulus_pa == 1e8
    np.testing.assert_allclose(summary.change[:, 0], [0.0, 0.1, -3.0], atol=1e-12)
    np.testing.assert_allclose(summary.relative_change[:, 1], [0.0, 0.005, 0.01], atol=1e-12)
    assert summary.within_tolerance.tolist() == [[True, True], [True, True], [False, True]]
    assert summary.expected_speedup == pytest.approx((1.0, 10**0.5, 10.0))
    assert summary.measured_speedup == pytest.approx((1.0, 3.0, 9.0))
    assert summary.recommended_modulus_pa == 1e7
    assert "G = 1e+06 Pa changes angle_of_repose_deg beyond the tolerance" in str(summary)
    only_flow = summarise_shear_modulus_study(moduli, study(means, stds), KPIS,
                                              kpis=["mass_flow_rate_kg_s"])
    assert only_flow.recommended_modulus_pa == 1e6 and only_flow.measured_speedup is None


# ---------------------------------------------------------------------------- bad input

@pytest.mark.parametrize("fractions", [(0.05,), (0.0, 0.1), (0.1, 1.5), (0.1, 0.1)])
def test_bad_fractions_are_rejected(fractions):
    values = np.zeros((len(fractions), 3, 1))
    with pytest.raises(ConfigError) as err:
        choose_time_step(fractions, values, ["k"])
    message = str(err.value)
    assert "choose_time_step: fractions = " in message and "in (0, 1]" in message


def test_bad_shapes_and_settings_are_rejected():
    with pytest.raises(ConfigError, match=r"shape \(6, 5, 2\); expected \[n_fractions, "
                                          r"replicates, n_kpi\] = \(6, replicates >= 2, 1\)"):
        choose_time_step(FRACTIONS, paper_like(), ["k"])
    with pytest.raises(ConfigError, match="replicates >= 2"):
        choose_time_step(FRACTIONS, paper_like()[:, :1], KPIS)
    with pytest.raises(ConfigError, match="std_growth_factor = 0.5 is not allowed; expected a "
                                          "factor >= 1"):
        choose_time_step(FRACTIONS, paper_like(), KPIS, std_growth_factor=0.5)
    with pytest.raises(ConfigError, match="relative_tolerance = -0.01"):
        choose_time_step(FRACTIONS, paper_like(), KPIS, relative_tolerance=-0.01)
    with pytest.raises(ConfigError, match=r"deciding KPIs \['shear'\] are not allowed"):
        choose_time_step(FRACTIONS, paper_like(), KPIS, kpis=["shear"])
    with pytest.raises(ConfigError, match=r"reference_modulus_pa = 50000000.0 is not allowed; "
                                          r"expected one of the studied moduli"):
        summarise_shear_modulus_study((1e8, 1e7), paper_like()[:2], KPIS,
                                      reference_modulus_pa=5e7)
    with pytest.raises(ConfigError, match="wall_times_s"):
        summarise_shear_modulus_study((1e8, 1e7), paper_like()[:2], KPIS, [1.0, -1.0])
