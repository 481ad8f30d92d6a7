"""Multistart minimisation of a cheap, smooth, vectorised function over a box: a scrambled Sobol
sample, then L-BFGS-B from the best distinct points of it.

Contract
--------
``multistart_minimum(fn, bounds, samples=1024, starts=3, seed=0)`` minimises ``fn: [n, d] -> [n]``
(a GP's expected chi^2, say) over ``bounds [2, d]``. It evaluates ``fn`` on ``samples`` Sobol
points in one call, picks the ``starts`` best points that lie at least a tenth of the box's
diagonal apart, and polishes each with ``scipy.optimize.minimize(method="L-BFGS-B")`` in the unit
cube, with central-difference gradients computed in one batched call of ``2 d`` points per
iterate (one-sided at a bound). The best polished point wins; a polish that ends worse than its
start keeps the start. ``SearchResult`` holds it, its value, and how many points ``fn`` saw.

Why not the GA of ``bo.surrogate.ga`` here: discovery's fits have one to three parameters and a
smooth surrogate (Matern 5/2 GP means and variances are twice differentiable). On such a function
a GA of 200 individuals spends about 20,000 evaluations per start, and pymoo's bookkeeping half of
its time; the Sobol sample plus local polish needs about 1,000-2,000 and finds the same minimum or
a lower one (``tests/test_search.py``). The calibration keeps the paper's GA (Table A.3).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.optimize import minimize
from scipy.stats import qmc

from torchdem.errors import ConfigError, out_of_range

__all__ = ["SearchResult", "multistart_minimum"]


@dataclass(frozen=True)
class SearchResult:
    """Best point ``x [d]`` (original units), its value ``fitness``, and ``n_evaluations``: points
    passed to ``fn`` in all (sample, gradients and line searches)."""

    x: np.ndarray
    fitness: float
    n_evaluations: int


def multistart_minimum(fn: Callable[[np.ndarray], np.ndarray], bounds, *, samples: int = 1024, starts: int = 3,
                       seed: int = 0, max_iterations: int = 200) -> SearchResult:
    """Minimum of ``fn`` over ``bounds`` (see the module docstring)."""
    src = "multistart_minimum"
    b = np.asarray(bounds, dtype=np.float64)
    if b.ndim != 2 or b.shape[0] != 2 or not np.all(b[1] > b[0]):
        raise out_of_range("bounds", b.tolist(), "[[low...], [high...]] with every high > low", src)
    for name, value, low in (("samples", samples, 2), ("starts", starts, 1), ("max_iterations", max_iterations, 1)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise out_of_range(name, value, f"an integer >= {low}", src)
    d = b.shape[1]
    span = b[1] - b[0]
    count = [0]

    def f(u: np.ndarray) -> np.ndarray:  # u in the unit cube, [n, d]
        u = np.clip(np.atleast_2d(u), 0.0, 1.0)
        count[0] += len(u)
        out = np.asarray(fn(b[0] + u * span), dtype=np.float64).reshape(-1)
        if out.shape != (len(u),):
            raise ConfigError(f"{src}: fn returned shape {out.shape} for {len(u)} points; expected [{len(u)}]")
        return np.where(np.isfinite(out), out, np.inf)

    U = qmc.Sobol(d, scramble=True, seed=seed).random(samples)
    values = f(U)
    order = np.argsort(values, kind="stable")
    chosen: list[int] = []
    for i in order:  # the best points, a tenth of the diagonal apart: distinct basins
        if not np.isfinite(values[i]):
            break
        if all(np.linalg.norm(U[i] - U[j]) >= 0.1 * np.sqrt(d) for j in chosen):
            chosen.append(int(i))
        if len(chosen) == starts:
            break
    if not chosen:
        raise ConfigError(f"{src}: fn is not finite at any of {samples} points of the box {b.tolist()}")

    h = 1e-6

    def value_and_gradient(u: np.ndarray) -> tuple[float, np.ndarray]:
        hi = np.minimum(u + h, 1.0)
        lo = np.maximum(u - h, 0.0)
        probes = np.vstack([u[None, :], np.tile(u, (d, 1)) + np.diag(hi - u), np.tile(u, (d, 1)) - np.diag(u - lo)])
        v = f(probes)
        grad = (v[1:d + 1] - v[d + 1:]) / (hi - lo)
        return float(v[0]), np.where(np.isfinite(grad), grad, 0.0)

    best_u, best_v = U[chosen[0]], float(values[chosen[0]])
    for i in chosen:
        res = minimize(value_and_gradient, U[i], jac=True, method="L-BFGS-B", bounds=[(0.0, 1.0)] * d,
                       options={"maxiter": max_iterations})
        u = np.clip(res.x, 0.0, 1.0)
        v = float(f(u[None, :])[0])
        if not v < values[i]:
            u, v = U[i], float(values[i])
        if v < best_v:
            best_u, best_v = u, v
    return SearchResult(x=b[0] + best_u * span, fitness=best_v, n_evaluations=count[0])
