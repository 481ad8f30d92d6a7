"""What the calibration bounds allow: per KPI, the range its surrogate mean spans over the box
while every other objective KPI's mean stays inside the lab's 95 % CI.

A calibration that misses one KPI leaves a question before model discovery: is there a parameter
set in the bounds that matches it together with the others, which the GA passed over because it
weighs all KPIs at once, or is there none? The per-KPI surrogate (one GP per KPI,
:mod:`bo.surrogate.gp`) answers it as two constrained optimisations per KPI k::

    min / max  mu_k(x)   over the box,   subject to   |mu_j(x) - m_j| <= c_j   for every j != k

with ``mu`` the GP posterior means, ``m`` the measured means and ``c`` their 95 % half-widths. If
``[low, high]`` does not meet ``[m_k - c_k, m_k + c_k]``, no set in the bounds matches all the
KPIs by the surrogate, and the paper's workflow has nothing left to tune: the gap is the model's
(``torchdem-discover``). The posterior sd at each extreme says how sure the surrogate is there; an
extreme at a corner of the box with few runs near it is an extrapolation.

Contract:

* :func:`attainable_ranges` ``(surrogate, measured, names=None, bounds=None, settings, seed,
  constraint=None)``: ``surrogate`` a fitted ``per_kpi`` :class:`~bo.surrogate.gp.Surrogate`;
  ``measured`` maps each of its objective's KPIs to ``(mean, ci95)``; ``bounds [2, d]`` the box
  searched (default the surrogate's); ``constraint`` a vectorised ``[n, d] -> [n]`` that a set must
  keep ``<= 0`` besides (the calibration caps the chance that a run jams with it,
  :mod:`bo.surrogate.jam`). Returns one :class:`AttainableRange` per objective KPI, in the objective's order.
  Each optimisation is pymoo's GA with the constraints as inequality constraints (feasible points
  first); its first population holds the surrogate's training points inside the box.
* :func:`format_attainable` turns the ranges into markdown lines; ``AttainableRange.to_dict`` /
  ``from_dict`` into strict JSON (a calibration.json's ``attainable``) and back.

Deterministic for a given surrogate and seed.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Callable, Mapping, Sequence

import gpytorch
import numpy as np
import torch
from pymoo.algorithms.soo.nonconvex.ga import GA
from pymoo.core.problem import Problem
from pymoo.optimize import minimize

from bo.surrogate.gp import Surrogate, as_bounds
from torchdem.errors import ConfigError, out_of_range

__all__ = ["AttainableSettings", "AttainableRange", "attainable_ranges", "format_attainable"]


@dataclass(frozen=True)
class AttainableSettings:
    """Population and generations of each constrained GA (two per KPI)."""

    pop_size: int = 300
    n_generations: int = 150

    def validate(self, source: str = "AttainableSettings") -> "AttainableSettings":
        for name in ("pop_size", "n_generations"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 2:
                raise out_of_range(name, v, "an integer >= 2", source)
        return self


@dataclass(frozen=True)
class AttainableRange:
    """The surrogate mean of ``kpi`` over the box with every other objective KPI inside its CI.

    ``low``/``high``: the extremes (NaN when no point of the box puts the others inside their CIs,
    ``feasible`` False); ``at_low``/``at_high``: the parameter sets there; ``sd_low``/``sd_high``:
    the posterior sd of the KPI's mean at them; ``measured``/``ci95``: the lab's."""

    kpi: str
    measured: float
    ci95: float
    feasible: bool
    low: float
    high: float
    at_low: Mapping[str, float]
    at_high: Mapping[str, float]
    sd_low: float
    sd_high: float

    def to_dict(self) -> dict:
        """Strict-JSON data (NaN, where no set is feasible, as None)."""
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, data: Mapping) -> "AttainableRange":
        """The inverse of :meth:`to_dict`."""
        return cls(**{k: (math.nan if v is None else v) for k, v in data.items()})

    @property
    def reaches(self) -> bool:
        """True when ``[low, high]`` meets the lab's interval ``[measured - ci95, measured + ci95]``."""
        return self.feasible and self.low <= self.measured + self.ci95 and self.high >= self.measured - self.ci95


def _means(surrogate: Surrogate, X) -> np.ndarray:
    """``[n, M]`` posterior means at ``X [n, d]`` from one joint posterior (its covariance is never
    formed)."""
    with torch.no_grad(), gpytorch.settings.skip_posterior_variances(True):
        post = surrogate.model.posterior(torch.as_tensor(np.asarray(X, dtype=np.float64), dtype=torch.float64))
        return post.mean.numpy()


class _Constrained(Problem):
    """``sign * mu_k(x)`` with ``G_j = |mu_j(x) - m_j| - c_j <= 0`` for the other KPIs."""

    def __init__(self, surrogate: Surrogate, b: np.ndarray, k: int, sign: float,
                 measured: np.ndarray, ci: np.ndarray, constraint: Callable[[np.ndarray], np.ndarray] | None):
        others = [j for j in range(len(measured)) if j != k]
        super().__init__(n_var=b.shape[1], n_obj=1, n_ieq_constr=len(others) + 1, xl=b[0], xu=b[1],
                         elementwise=False)
        self._s, self._k, self._sign, self._others = surrogate, k, sign, others
        self._m, self._c, self._constraint = measured, ci, constraint

    def _evaluate(self, X, out, *args, **kwargs):
        x = np.asarray(X, dtype=np.float64)
        mean = _means(self._s, x)
        out["F"] = self._sign * mean[:, [self._k]]
        o = self._others
        extra = np.zeros(len(x)) if self._constraint is None else np.asarray(self._constraint(x), dtype=np.float64)
        out["G"] = np.column_stack([np.abs(mean[:, o] - self._m[o]) - self._c[o], extra])


def _first_population(surrogate: Surrogate, b: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    inside = surrogate.train_X[((surrogate.train_X >= b[0]) & (surrogate.train_X <= b[1])).all(axis=1)]
    inside = inside[:n]
    fill = b[0] + rng.random((n - len(inside), b.shape[1])) * (b[1] - b[0])
    return np.vstack([inside, fill])


def attainable_ranges(surrogate: Surrogate, measured: Mapping[str, tuple[float, float]],
                      names: Sequence[str] | None = None, bounds=None,
                      settings: AttainableSettings = AttainableSettings(), seed: int = 0,
                      constraint: Callable[[np.ndarray], np.ndarray] | None = None
                      ) -> tuple[AttainableRange, ...]:
    """Per objective KPI, its surrogate mean's range over the box with the others inside their
    CIs (module docstring)."""
    src = "attainable_ranges"
    settings = settings.validate(src)
    if surrogate.config.strategy != "per_kpi" or surrogate.objective is None:
        raise ConfigError(f"{src}: surrogate strategy = {surrogate.config.strategy!r}; expected 'per_kpi' "
                          "(one GP per KPI, with its ObjectiveSpec)")
    kpis = surrogate.objective.kpi_names
    missing = [k for k in kpis if k not in measured]
    if missing:
        raise ConfigError(f"{src}: measured data lack {missing!r}; expected (mean, ci95) for every objective "
                          f"KPI {list(kpis)!r}")
    m = np.array([float(measured[k][0]) for k in kpis])
    c = np.array([float(measured[k][1]) for k in kpis])
    if not (np.isfinite(m).all() and np.isfinite(c).all() and (c >= 0).all()):
        raise ConfigError(f"{src}: measured = {dict(measured)!r}; expected finite means and 95 % half-widths >= 0")
    b = surrogate.bounds.copy() if bounds is None else as_bounds(bounds, src)
    if b.shape[1] != surrogate.d:
        raise ConfigError(f"{src}: bounds have {b.shape[1]} parameters but the surrogate has {surrogate.d}; "
                          "expected the same d")
    names = tuple(names) if names is not None else tuple(f"x{i}" for i in range(surrogate.d))
    if len(names) != surrogate.d:
        raise ConfigError(f"{src}: {len(names)} names for {surrogate.d} parameters; expected one name each")
    out = []
    for k, kpi in enumerate(kpis):
        ends = {}
        for side, sign in (("low", 1.0), ("high", -1.0)):
            rng = np.random.default_rng(seed + 2 * k + (side == "high"))
            start = _first_population(surrogate, b, settings.pop_size, rng)
            problem = _Constrained(surrogate, b, k, sign, m, c, constraint)
            algorithm = GA(pop_size=settings.pop_size, sampling=start, eliminate_duplicates=True)
            res = minimize(problem, algorithm, ("n_gen", settings.n_generations), seed=seed + k, verbose=False)
            if res.X is None:  # no feasible point
                ends[side] = None
                continue
            x = np.asarray(res.X, dtype=np.float64).reshape(1, -1)
            mean, var = surrogate.predict_outputs(x)
            ends[side] = (float(mean[0, k]), math.sqrt(max(float(var[0, k]), 0.0)), dict(zip(names, map(float, x[0]))))
        feasible = ends["low"] is not None and ends["high"] is not None
        lo = ends["low"] or (math.nan, math.nan, {})
        hi = ends["high"] or (math.nan, math.nan, {})
        out.append(AttainableRange(kpi=kpi, measured=float(m[k]), ci95=float(c[k]), feasible=feasible,
                                   low=lo[0], high=hi[0], at_low=lo[2], at_high=hi[2], sd_low=lo[1], sd_high=hi[1]))
    return tuple(out)


def format_attainable(ranges: Sequence[AttainableRange]) -> list[str]:
    """Markdown table: per KPI the lab's interval, the attainable range (with the posterior sd at its
    ends) and whether they meet."""
    lines = ["| KPI | lab (95 % CI) | surrogate range with the others inside their CIs (sd at the ends) | meets the lab |",
             "| --- | ---: | ---: | --- |"]
    for r in ranges:
        span = (f"{r.low:.4g} ({r.sd_low:.2g}) to {r.high:.4g} ({r.sd_high:.2g})" if r.feasible
                else "none: the others cannot all be inside their CIs")
        lines.append(f"| {r.kpi} | {r.measured:.4g} +- {r.ci95:.3g} | {span} | {'yes' if r.reaches else '**no**'} |")
    return lines
