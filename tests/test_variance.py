"""Tests for bo/screening/variance.py: the law-of-total-variance split (paper Eqs. 4-6).

Two kinds of check:

* exact: data built so that every run's replicate mean and population variance are known in
  closed form (``y[i, r] = a_i + b * d_r`` with ``d = (-1, +1)``), so the shares are known
  exactly and compared to 1e-12;
* statistical: a linear model on the paper-sized DSD plus Gaussian noise, where the analytic
  shares are ``P = Var_design(m) / (Var_design(m) + sigma^2)`` and ``S = 1 - P``. With
  n = 29 runs and r = 2000 replicates (58 000 values) the plug-in estimator's bias
  (~ sigma^2 / r) is <= 0.2 % of either part, and its standard errors are ~ sqrt(2 / (n r))
  = 0.6 % of sigma^2 for the within part and ~ 2 sqrt(Var(m) sigma^2 / (n r)) for the between
  part (0.6 % of Var(m) for the first KPI, 1.8 % for the noise-dominated second one). The
  tolerances, 5 % on the variances and 0.01 on the shares, are >= 2.8 standard errors.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from bo.design.dsd import definitive_screening_design, paper_parameter_table
from bo.screening.stepwise import ScreeningResults
from bo.screening.variance import decompose_screening_variance, decompose_variance
from torchdem.errors import ConfigError


def exact_values(a: np.ndarray, b: float) -> np.ndarray:
    """``[runs, 2]``: run mean a_i, population variance b^2 in every run."""
    return a[:, None] + b * np.array([-1.0, 1.0])[None, :]


def test_shares_match_a_model_with_known_moments_exactly():
    a = np.array([1.0, 2.0, 3.0, 4.0])  # population variance 1.25
    b = 0.5  # within-run population variance 0.25
    values = np.stack([exact_values(a, b), exact_values(a, 2.0)], axis=-1)
    d = decompose_variance(values, ["mass_flow_rate_kg_s", "segregation_rsd_vertical"])
    assert d.parameter_variance == pytest.approx((1.25, 1.25), abs=1e-12)
    assert d.stochastic_variance == pytest.approx((0.25, 4.0), abs=1e-12)
    assert d.total_variance == pytest.approx((1.5, 5.25), abs=1e-12)
    assert d.parameter_share == pytest.approx((1.25 / 1.5, 1.25 / 5.25), abs=1e-12)
    assert d.stochastic_percent == pytest.approx((100 * 0.25 / 1.5, 100 * 4 / 5.25), abs=1e-10)
    assert d.stochastic_dominated == (False, True)
    assert d.excluded_kpis == ("segregation_rsd_vertical",)
    assert d.calibration_kpis == ("mass_flow_rate_kg_s",)


def test_threshold_is_configurable():
    a = np.array([0.0, 1.0, 2.0, 3.0])  # Var = 1.25
    values = exact_values(a, 1.5)[:, :, None]  # S = 2.25 / 3.5 = 0.643
    assert decompose_variance(values, ["k"]).stochastic_dominated == (True,)
    assert decompose_variance(values, ["k"], stochastic_threshold=0.7).stochastic_dominated \
        == (False,)


def test_shares_match_analytic_shares_of_a_noisy_linear_model():
    coded = definitive_screening_design(12, 2)
    sigma = 1.5
    reps = 2000
    rng = np.random.default_rng(7)
    effects = {"angle_of_repose_deg": (np.array([2.0, 0, 0, -1.0] + [0] * 8), sigma),
               "segregation_rsd_horizontal": (np.array([0.5] + [0] * 11), 1.0)}
    values = np.empty((29, reps, 2))
    analytic = []
    for q, (beta, noise) in enumerate(effects.values()):
        m = coded @ beta
        values[:, :, q] = 10.0 + m[:, None] + rng.normal(0, noise, (29, reps))
        var_m = float(np.mean((m - m.mean()) ** 2))  # exact, over the 29 design points
        analytic.append((var_m, noise**2, var_m / (var_m + noise**2)))
    d = decompose_variance(values, list(effects))
    for q, (var_m, var_noise, share) in enumerate(analytic):
        assert d.parameter_variance[q] == pytest.approx(var_m, rel=0.05)
        assert d.stochastic_variance[q] == pytest.approx(var_noise, rel=0.05)
        assert d.parameter_share[q] == pytest.approx(share, abs=0.01)
    assert d.stochastic_dominated == (False, True)


def test_law_of_total_variance_holds_exactly_with_failed_runs():
    rng = np.random.default_rng(3)
    values = rng.normal(size=(29, 5, 3)) + rng.normal(size=(29, 1, 3)) * [1.0, 3.0, 0.2]
    values[2, 1:4, 0] = np.nan  # a run with one finite replicate left
    values[5, :, 1] = np.nan  # a run that failed entirely
    values[[0, 9, 17], 4, 2] = np.nan
    d = decompose_variance(values, ["a", "b", "c"])
    for q in range(3):
        finite = values[:, :, q][np.isfinite(values[:, :, q])]
        assert d.total_variance[q] == pytest.approx(float(np.var(finite)), rel=1e-12)
        assert d.parameter_share[q] + d.stochastic_share[q] == pytest.approx(1.0, abs=1e-12)
        assert d.n_values_used[q] == finite.size
    assert d.n_runs_used == (29, 28, 29)


def test_constant_kpi_has_undefined_shares_and_is_excluded():
    values = np.stack([np.full((4, 3), 2.0), np.arange(12.0).reshape(4, 3)], axis=-1)
    d = decompose_variance(values, ["constant", "varying"])
    assert math.isnan(d.parameter_share[0]) and math.isnan(d.stochastic_share[0])
    assert d.excluded_kpis == ("constant",)
    text = json.dumps(d.to_dict(), allow_nan=False)
    assert json.loads(text)["kpis"]["constant"]["stochastic_share"] is None
    assert "no variance" in d.to_text()


def test_screening_results_entry_point_and_subset():
    coded = definitive_screening_design(12, 2)
    rng = np.random.default_rng(11)
    values = np.stack([coded[:, :1] + 0.1 * rng.normal(size=(29, 4)),
                       0.2 + 0.05 * rng.normal(size=(29, 4))], axis=-1)
    results = ScreeningResults.from_parameter_table(
        paper_parameter_table(), coded, (1, 2, 3, 4), ("shear_angle_deg",
                                                       "segregation_rsd_vertical"), values)
    d = decompose_screening_variance(results)
    assert d.calibration_kpis == ("shear_angle_deg",)
    assert d.excluded_kpis == ("segregation_rsd_vertical",)
    only = decompose_screening_variance(results, kpis=["segregation_rsd_vertical"])
    assert only.stochastic_share == pytest.approx(d.stochastic_share[1:], abs=1e-15)
    with pytest.raises(ConfigError, match="'flow' is not in the screening results"):
        decompose_screening_variance(results, kpis=["flow"])


@pytest.mark.parametrize("threshold", [0.0, 1.0, 1.5, -0.2])
def test_threshold_outside_unit_interval_is_rejected(threshold):
    with pytest.raises(ConfigError) as err:
        decompose_variance(np.zeros((3, 2, 1)), ["k"], threshold, source="screening.json")
    message = str(err.value)
    assert "screening.json" in message and f"stochastic_threshold = {threshold!r}" in message
    assert "(0, 1)" in message


def test_bad_arrays_are_rejected():
    with pytest.raises(ConfigError, match=r"shape \(3, 2\); expected \[runs, replicates, n_kpi\]"):
        decompose_variance(np.zeros((3, 2)), ["k"])
    with pytest.raises(ConfigError, match=r"shape \(3, 2, 2\).*n_kpi = 1"):
        decompose_variance(np.zeros((3, 2, 2)), ["k"])
    with pytest.raises(ConfigError, match="infinite"):
        decompose_variance(np.full((3, 2, 1), np.inf), ["k"])
    with pytest.raises(ConfigError, match="'k' has 1 finite values; expected at least 2"):
        decompose_variance(np.array([[[1.0], [np.nan]], [[np.nan], [np.nan]]]), ["k"])
    with pytest.raises(ConfigError, match="unique KPI names"):
        decompose_variance(np.zeros((3, 2, 2)), ["k", "k"])
