"""Tests of bo/surrogate/gp.py.

* CV R^2 is recomputed independently: the same folds, each fold's fitted hyperparameters
  read back as plain data, held-out predictions from the exact GP posterior formulas
  (Eqs. 12, 14-15, normalised inputs, standardised outputs) in NumPy, R^2 by hand; agreement
  within 1e-6 (learned homoscedastic noise, Matern 5/2; fixed
  heteroscedastic noise, rational quadratic).
* Kernel selection picks the generating kernel on GP sample paths (exponential vs squared
  exponential) and R^2 is high on the smooth path.
* per_kpi: the Monte-Carlo composed objective mean agrees with the closed-form mean of a
  weighted sum of folded normals (independent Gaussian KPI posteriors) within 2e-3.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.stats import norm

from bo.surrogate.acquisition import latin_hypercube
from bo.surrogate.objective import ObjectiveSpec
from bo.surrogate.gp import (KERNELS, SurrogateConfig, as_bounds, cross_validate, fit_surrogate,
                          fold_assignment, objective_from_replicates, replicate_mean_and_variance,
                          select_kernel)
from torchdem.errors import ConfigError

torch.set_num_threads(1)

UNIT2 = np.array([[0.0, 0.0], [1.0, 1.0]])
BOX2 = np.array([[0.5, -1.0], [1.0, 2.0]])  # a non-unit box, to exercise the normalisation


def smooth(X: np.ndarray) -> np.ndarray:
    u = (X - BOX2[0]) / (BOX2[1] - BOX2[0])
    return np.sin(3.0 * u[:, 0]) + (u[:, 1] - 0.3) ** 2


# --------------------------------------------------------------------------------------------
# Independent GP posterior in NumPy
# --------------------------------------------------------------------------------------------

def _scaled_dist(a, b, lengthscale):
    diff = a[:, None, :] / lengthscale - b[None, :, :] / lengthscale
    return np.sqrt(np.maximum((diff ** 2).sum(-1), 0.0))


def _kernel(name, a, b, hp):
    r = _scaled_dist(a, b, hp["lengthscale"][0])
    if name == "matern52":
        k = (1 + np.sqrt(5) * r + 5.0 / 3.0 * r ** 2) * np.exp(-np.sqrt(5) * r)
    elif name == "rational_quadratic":
        alpha = hp["alpha"][0]
        k = (1 + r ** 2 / (2 * alpha)) ** (-alpha)
    elif name == "exponential":
        k = np.exp(-r)
    else:
        k = np.exp(-0.5 * r ** 2)
    return hp["outputscale"][0] * k


def numpy_gp_mean(x_tr, y_tr, yvar_tr, x_te, bounds, hp, kernel, noise_floor):
    """Exact posterior mean with normalised inputs and standardised outputs (Eqs. 12, 15)."""
    lo, hi = bounds
    u_tr, u_te = (x_tr - lo) / (hi - lo), (x_te - lo) / (hi - lo)
    mean, std = y_tr.mean(), y_tr.std(ddof=1)
    assert hp["y_mean"][0] == pytest.approx(mean, rel=1e-12)
    assert hp["y_std"][0] == pytest.approx(std, rel=1e-12)
    z = (y_tr - mean) / std
    if yvar_tr is None:
        noise = np.full(len(z), hp["noise"][0])
    else:
        noise = np.maximum(yvar_tr, noise_floor * y_tr.var(ddof=1)) / std ** 2
    c = hp["mean_constant"][0]
    K = _kernel(kernel, u_tr, u_tr, hp) + np.diag(noise)
    alpha = np.linalg.solve(K, z - c)
    return (c + _kernel(kernel, u_te, u_tr, hp) @ alpha) * std + mean


@pytest.mark.parametrize("kernel, with_noise", [("matern52", False),
                                                ("rational_quadratic", True)])
def test_cv_r2_matches_independent_numpy_computation(kernel, with_noise):
    rng = np.random.default_rng(3)
    X = latin_hypercube(BOX2, 18, seed=4)
    y_var = rng.uniform(1e-4, 4e-3, 18) if with_noise else None
    y = smooth(X) + rng.normal(0.0, 0.03, 18)
    config = SurrogateConfig(kernel=kernel)
    cv = cross_validate(X, y, BOX2, config, y_var=y_var, n_folds=3, seed=7)

    folds = fold_assignment(18, 3, 7)
    assert np.array_equal(cv.folds, folds)
    assert sorted(np.bincount(folds)) == [6, 6, 6]
    predicted = np.empty(18)
    for k in range(3):
        tr, te = folds != k, folds == k
        hp = cv.fold_hyperparameters[k]  # fitted on the other folds; read back as plain data
        assert hp["kernel"] == kernel and (hp["noise"] is None) == with_noise
        predicted[te] = numpy_gp_mean(X[tr], y[tr], None if y_var is None else y_var[tr],
                                      X[te], BOX2, hp, kernel, config.noise_floor)
    r2 = 1 - np.sum((y - predicted) ** 2) / np.sum((y - y.mean()) ** 2)
    assert np.allclose(cv.predicted, predicted, rtol=0, atol=1e-6)
    assert cv.r2 == pytest.approx(r2, abs=1e-6)
    assert cv.r2 > 0.5  # 12 noisy training points per fold: a sanity bound only


def _gp_path(kernel: str, X: np.ndarray, seed: int) -> np.ndarray:
    r = np.abs(X[:, None, 0] - X[None, :, 0]) / 0.2
    K = np.exp(-r) if kernel == "exponential" else np.exp(-0.5 * r ** 2)
    L = np.linalg.cholesky(K + 1e-8 * np.eye(len(X)))
    return L @ np.random.default_rng(seed).standard_normal(len(X))


# Path seeds: at this size (24 points, 4 folds) the right kernel won for each of path seeds
# 0-3 when the test was written; the two used here have the widest margins.
@pytest.mark.parametrize("truth, path_seed", [("exponential", 3), ("squared_exponential", 0)])
def test_select_kernel_recovers_generating_kernel(truth, path_seed):
    b = np.array([[0.0], [1.0]])
    X = latin_hypercube(b, 24, seed=1)
    y = _gp_path(truth, X, seed=path_seed)
    sel = select_kernel(X, y, b, kernels=("exponential", "squared_exponential"), n_folds=4,
                        seeds=(0,))
    assert sel.best == truth
    other = "exponential" if truth == "squared_exponential" else "squared_exponential"
    assert sel.summaries[truth].mean > sel.summaries[other].mean
    if truth == "squared_exponential":
        assert sel.best_summary.mean > 0.98  # smooth path: high CV R^2


def test_per_kpi_mc_mean_matches_folded_normal_closed_form():
    spec = ObjectiveSpec(("angle", "flow"), (1.6, 2.1), weights=(0.7, 0.3))
    X = latin_hypercube(UNIT2, 20, seed=2)
    Y = np.stack([1 + np.sin(3 * X[:, 0]), 2 + X[:, 1] - X[:, 0]], axis=1)
    Y_var = np.full_like(Y, 0.02)
    s = fit_surrogate(X, Y, UNIT2, SurrogateConfig(strategy="per_kpi"), y_var=Y_var,
                      objective=spec)
    P = latin_hypercube(UNIT2, 64, seed=5)
    mu, var = s.predict_outputs(P)
    sd = np.sqrt(var)
    assert sd.min() > 0.01  # the kink of |.| matters: a real test of the composition
    e = np.array(spec.measured)
    z = (mu - e) / sd
    folded = sd * np.sqrt(2 / np.pi) * np.exp(-0.5 * z ** 2) + (mu - e) * (1 - 2 * norm.cdf(-z))
    closed = (np.array(spec.weights) * folded / np.abs(e)).sum(axis=1)
    mc = s.predict_mean(P)
    assert np.allclose(mc, closed, rtol=0, atol=2e-3)
    # deterministic (fixed base samples) and vectorised == pointwise
    assert np.array_equal(mc, s.predict_mean(P))
    assert np.allclose(mc[:3], [s.predict_mean(P[i:i + 1])[0] for i in range(3)], atol=1e-12)
    # acquisition objective: negated Eq. 7 on samples [S, b, q, M]
    samples = torch.tensor(Y[None, None], dtype=torch.float64)
    assert torch.allclose(s.mc_objective()(samples), -torch.as_tensor(spec(Y))[None, None])
    assert np.allclose(s.observed_objective(), spec(Y))


def test_per_kpi_cv_r2_is_r2_of_composed_objective():
    spec = ObjectiveSpec(("a", "b"), (1.2, 2.0))
    X = latin_hypercube(UNIT2, 18, seed=6)
    Y = np.stack([1 + np.sin(3 * X[:, 0]), 2 + X[:, 1] - X[:, 0]], axis=1)
    cv = cross_validate(X, Y, UNIT2, SurrogateConfig(strategy="per_kpi"), objective=spec,
                        n_folds=3, seed=0)
    assert np.allclose(cv.actual, spec(Y))
    assert cv.r2 == pytest.approx(
        1 - np.sum((cv.actual - cv.predicted) ** 2) / np.sum((cv.actual - cv.actual.mean()) ** 2))
    assert cv.r2 > 0.9


def test_replicate_helpers():
    reps = np.array([[1.0, 2.0, 3.0], [2.0, 2.0, 2.0]])
    mean, var = replicate_mean_and_variance(reps)
    assert np.allclose(mean, [2.0, 2.0]) and np.allclose(var, [1.0 / 3.0, 0.0])
    spec = ObjectiveSpec(("a", "b"), (1.0, 4.0))
    rng = np.random.default_rng(0)
    kpis = np.array([2.0, 6.0]) + 0.1 * rng.standard_normal((5, 4, 2))  # all above measured
    y, y_var = objective_from_replicates(spec, kpis)
    assert np.allclose(y, spec(kpis.mean(axis=1)))
    # no kink crossed: Eq. 7 is linear over the replicates, so the delta method is exact
    assert np.allclose(y_var, spec(kpis).var(axis=1, ddof=1) / 4)
    with pytest.raises(ConfigError, match=r"\[n, r >= 2, 2\]"):
        objective_from_replicates(spec, kpis[:, :1])


def test_bad_inputs_give_clear_errors():
    X = latin_hypercube(UNIT2, 6, seed=0)
    y = X.sum(axis=1)
    with pytest.raises(ConfigError, match=r"lower = 1.0, upper = 0.0.*inverted"):
        as_bounds([[0.0, 1.0], [1.0, 0.0]], "conf/space.yaml")
    with pytest.raises(ConfigError, match=r"expected \[2, d\]"):
        as_bounds([0.0, 1.0])
    with pytest.raises(ConfigError, match="kernel = 'periodic'.*one of"):
        SurrogateConfig(kernel="periodic")
    with pytest.raises(ConfigError, match="strategy"):
        SurrogateConfig(strategy="multi")
    with pytest.raises(ConfigError, match="needs an ObjectiveSpec"):
        fit_surrogate(X, np.stack([y, y], 1), UNIT2, SurrogateConfig(strategy="per_kpi"))
    with pytest.raises(ConfigError, match=r"expected \[6\] objective values"):
        fit_surrogate(X, y[:5], UNIT2)
    with pytest.raises(ConfigError, match=r"outside the bounds"):
        fit_surrogate(X + 2.0, y, UNIT2)
    with pytest.raises(ConfigError, match="n_folds = 7"):
        cross_validate(X, y, UNIT2, n_folds=7)
    with pytest.raises(ConfigError, match="y_var"):
        fit_surrogate(X, y, UNIT2, y_var=-np.ones(6))
    assert len(KERNELS) == 4
