"""Tests of the pooled DEM replicate noise (bo/discovery/replicate_noise.py).

- The pooled variance and its degrees of freedom equal a hand computation, with missing
  replicates (NaN) and groups of one run (no degree of freedom) handled.
- Why it exists: with 2 replicates per cell, the chi^2 discrepancy test of bo/discovery/verdict.py under the
  null hypothesis (DEM and lab agree) raises a false alarm far more often than its level alpha
  when each cell divides by its own 2-run standard error; with the noise pooled over the runs of
  a discovery it keeps its level. 4000 simulated tests, Gaussian noise.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from bo.discovery.verdict import discrepancy_of
from bo.discovery.replicate_noise import ReplicateNoise


def test_pooled_variance_and_dof_equal_a_hand_computation():
    a = np.array([[1.0, 10.0], [3.0, 14.0], [np.nan, 12.0]])        # [r = 3, K = 2]
    b = np.array([[[2.0, 7.0], [2.5, np.nan]], [[5.0, 1.0], [5.0, 3.0]]])   # [2 groups, r = 2, K = 2]
    noise = ReplicateNoise.of(("x", "y"), [a, b])
    ss_x = 2.0 + 0.125 + 0.0                       # group a: (1, 3); b0: (2, 2.5); b1: (5, 5)
    ss_y = 8.0 + 0.0 + 2.0                         # a: (10, 14, 12); b0: one run, no dof; b1: (1, 3)
    assert noise.dof == (3, 3)
    assert noise.variance("x") == pytest.approx(ss_x / 3)
    assert noise.variance("y") == pytest.approx(ss_y / 3)
    assert noise.se("y", 4) == pytest.approx(math.sqrt(ss_y / 3 / 4))
    both = noise.pooled(ReplicateNoise.of(("x", "y"), [np.array([[0.0, 0.0], [2.0, 2.0]])]))
    assert both.dof == (4, 4) and both.variance("x") == pytest.approx((ss_x + 2.0) / 4)
    single = ReplicateNoise.of(("x", "y"), [np.ones((1, 2))])
    assert single.dof == (0, 0) and math.isnan(single.variance("x")) and math.isnan(single.se("x", 3))
    with pytest.raises(ValueError, match=r"expected \[\.\.\., r, 2\].*got \(3, 3\)"):
        ReplicateNoise.of(("x", "y"), [np.ones((3, 3))])
    with pytest.raises(ValueError, match="KPIs differ"):
        noise.pooled(ReplicateNoise.of(("x",), []))


def test_pooled_noise_keeps_the_discrepancy_test_at_its_level():
    rng = np.random.default_rng(7)
    conditions, kpis, sigma, alpha = ["a", "b", "c", "d"], ["k1", "k2"], np.array([0.5, 2.0]), 0.05
    lab = {(c, k): (10.0, 0.05 * s, math.inf) for c in conditions for k, s in zip(kpis, sigma)}  # u known exactly
    trials, pooled_alarms, own_alarms = 4000, 0, 0
    for _ in range(trials):
        reps = 10.0 + sigma * rng.standard_normal((len(conditions), 2, len(kpis)))   # [C, r = 2, K]
        design = 10.0 + sigma * rng.standard_normal((20, len(conditions), 2, len(kpis)))
        noise = ReplicateNoise.of(kpis, [reps, design])
        pooled_alarms += discrepancy_of(reps, conditions, kpis, lab, noise, alpha).significant
        # each cell's own 2-run standard error instead (what the pooled noise replaced)
        se = reps.std(axis=1, ddof=1) / math.sqrt(2)
        u = np.array([lab[(conditions[0], k)][1] for k in kpis])
        chi2 = (((reps.mean(axis=1) - 10.0) / np.sqrt(se ** 2 + u ** 2)) ** 2).sum()
        own_alarms += chi2 > 15.507  # chi^2_8 at 0.95
    assert 0.03 < pooled_alarms / trials < 0.08, pooled_alarms / trials
    assert own_alarms / trials > 0.3, own_alarms / trials


def test_gain_noise_sd_is_the_sd_of_the_chi2_difference_of_two_equal_models():
    """Two hypotheses with the same means (one 9 measurement-uncertainties off, as the paper's
    shear angle): the sd of the difference of their held-out chi^2 over 20000 simulated pairs
    of runs matches ``gain_noise_sd`` within 5 %; it is ~20 chi^2 units, far above the
    fixed margin of 4."""
    from bo.discovery.verdict import Cell, gain_noise_sd

    rng = np.random.default_rng(3)
    offsets, u, sd, n = np.array([-12.0, 1.0, 0.3]), np.array([0.8, 0.2, 0.25]), np.array([1.9, 0.6, 0.3]), 2
    se = sd / math.sqrt(n)
    s = np.sqrt(se ** 2 + u ** 2)
    means = 10.0 + offsets + se * rng.standard_normal((2, 20000, 3))     # [hypothesis, trial, cell]
    chi2 = (((means - 10.0) / s) ** 2).sum(-1)
    empirical = float(np.std(chi2[0] - chi2[1]))
    cells = lambda k: [Cell("c", f"k{j}", float(10.0 + offsets[j] + (0.1 if k else -0.1)), float(se[j]), n, 10.0,  # noqa: E731
                            float(u[j]), float((offsets[j] + (0.1 if k else -0.1)) / s[j]), math.nan) for j in range(3)]
    predicted = gain_noise_sd(cells(0), cells(1))
    assert predicted == pytest.approx(empirical, rel=0.05)
    assert predicted > 15  # ~19.6 here
