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

What holds a range that misses the lab: for such a KPI k and each of its constraints c in turn (another
KPI's CI, or the extra ``constraint``), one more optimisation finds the mean of KPI k closest to the
lab's with every constraint but c::

    min  |mu_k(x) - m_k|   over the box,   subject to every constraint of k but c

(``AttainableRange.without[c]``; NaN when the others still cannot hold). The constraints whose
release lets KPI k reach the lab's CI (``AttainableRange.held_by``) name what the model cannot do
at once: a cause of the gap has to move those KPIs apart.

Contract:

* :func:`attainable_ranges` ``(surrogate, measured, names=None, bounds=None, settings, seed,
  constraint=None)``: ``surrogate`` a fitted ``per_kpi`` :class:`~bo.surrogate.gp.Surrogate`;
  ``measured`` maps each of its objective's KPIs to ``(mean, ci95)``; ``bounds [2, d]`` the box
  searched (default the surrogate's); ``constraint`` a vectorised ``[n, d] -> [n]`` that a set must
  keep ``<= 0`` besides (the calibration caps the chance that a run jams with it,
  :mod:`bo.surrogate.jam`). Returns one :class:`AttainableRange` per objective KPI, in the objective's order.
  Each optimisation is pymoo's GA with the constraints as inequality constraints (feasible points
  first); its first population holds the surrogate's training points inside the box.
  ``constraint_name`` names that constraint in ``without``. With ``settings.explain`` every range
  that misses the lab's CI also gets ``without`` (one more GA per constraint).
* :func:`format_attainable` turns the ranges into markdown lines (with a table of what holds the ranges
  that miss, when they were explained); ``AttainableRange.to_dict`` / ``from_dict`` into strict JSON (a
  calibration.json's ``attainable``) and back.

Deterministic for a given surrogate and seed.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
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
    """Population and generations of each constrained GA (two per KPI); ``explain``: also find, for
    every range that misses the lab, what each of its constraints holds it from (one GA per
    constraint, module docstring)."""

    pop_size: int = 300
    n_generations: int = 150
    explain: bool = True

    def validate(self, source: str = "AttainableSettings") -> "AttainableSettings":
        for name in ("pop_size", "n_generations"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 2:
                raise out_of_range(name, v, "an integer >= 2", source)
        if not isinstance(self.explain, bool):
            raise out_of_range("explain", self.explain, "true or false", source)
        return self


@dataclass(frozen=True)
class AttainableRange:
    """The surrogate mean of ``kpi`` over the box with every other objective KPI inside its CI.

    ``low``/``high``: the extremes (NaN when no point of the box puts the others inside their CIs,
    ``feasible`` False); ``at_low``/``at_high``: the parameter sets there; ``sd_low``/``sd_high``:
    the posterior sd of the KPI's mean at them; ``measured``/``ci95``: the lab's. ``without``: for a
    range that misses the lab (and was explained), per constraint (another KPI's name, or the extra
    constraint's), the KPI's mean closest to the lab's with every constraint but that one (NaN where
    the others cannot all hold); empty otherwise."""

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
    without: Mapping[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        """Strict-JSON data (NaN, where no set is feasible, as None)."""
        def strict(v):
            if isinstance(v, Mapping):
                return {k: strict(x) for k, x in v.items()}
            return None if isinstance(v, float) and not math.isfinite(v) else v
        return strict(dataclasses.asdict(self))

    @classmethod
    def from_dict(cls, data: Mapping) -> "AttainableRange":
        """The inverse of :meth:`to_dict` (a range written before ``without`` existed has none)."""
        data = dict(data)
        without = {c: (math.nan if v is None else float(v)) for c, v in (data.pop("without", None) or {}).items()}
        return cls(**{k: (math.nan if v is None else v) for k, v in data.items()}, without=without)

    def meets(self, value: float) -> bool:
        """True when ``value`` lies inside the lab's interval."""
        return math.isfinite(value) and abs(value - self.measured) <= self.ci95

    @property
    def held_by(self) -> tuple[str, ...]:
        """The constraints whose release alone lets the KPI reach the lab's CI (from ``without``)."""
        return tuple(c for c, v in self.without.items() if self.meets(v))

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
    """``sign * mu_k(x)``, or ``|mu_k(x) - m_k|`` with ``sign`` 0, subject to ``G_j = |mu_j(x) - m_j| -
    c_j <= 0`` for the KPIs ``others`` and to the extra constraint when given."""

    def __init__(self, surrogate: Surrogate, b: np.ndarray, k: int, sign: float,
                 measured: np.ndarray, ci: np.ndarray, others: Sequence[int],
                 constraint: Callable[[np.ndarray], np.ndarray] | None):
        super().__init__(n_var=b.shape[1], n_obj=1, n_ieq_constr=len(others) + 1, xl=b[0], xu=b[1],
                         elementwise=False)
        self._s, self._k, self._sign, self._others = surrogate, k, sign, list(others)
        self._m, self._c, self._constraint = measured, ci, constraint

    def _evaluate(self, X, out, *args, **kwargs):
        x = np.asarray(X, dtype=np.float64)
        mean = _means(self._s, x)
        k = self._k
        out["F"] = (np.abs(mean[:, [k]] - self._m[k]) if self._sign == 0 else self._sign * mean[:, [k]])
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
                      constraint: Callable[[np.ndarray], np.ndarray] | None = None,
                      constraint_name: str = "constraint") -> tuple[AttainableRange, ...]:
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
    if constraint is not None and constraint_name in kpis:
        raise ConfigError(f"{src}: constraint_name = {constraint_name!r} is an objective KPI's name; expected "
                          "another name")
    def optimum(k, sign, others, cons, stream):
        """The GA's best feasible point of one problem, or None when none is feasible."""
        start = _first_population(surrogate, b, settings.pop_size, np.random.default_rng(seed + stream))
        problem = _Constrained(surrogate, b, k, sign, m, c, others, cons)
        algorithm = GA(pop_size=settings.pop_size, sampling=start, eliminate_duplicates=True)
        res = minimize(problem, algorithm, ("n_gen", settings.n_generations), seed=seed + k, verbose=False)
        return None if res.X is None else np.asarray(res.X, dtype=np.float64).reshape(1, -1)

    out = []
    for k, kpi in enumerate(kpis):
        others = [j for j in range(len(kpis)) if j != k]
        ends = {}
        for side, sign in (("low", 1.0), ("high", -1.0)):
            x = optimum(k, sign, others, constraint, 2 * k + (side == "high"))
            if x is None:  # no feasible point
                ends[side] = None
                continue
            mean, var = surrogate.predict_outputs(x)
            ends[side] = (float(mean[0, k]), math.sqrt(max(float(var[0, k]), 0.0)), dict(zip(names, map(float, x[0]))))
        feasible = ends["low"] is not None and ends["high"] is not None
        lo = ends["low"] or (math.nan, math.nan, {})
        hi = ends["high"] or (math.nan, math.nan, {})
        r = AttainableRange(kpi=kpi, measured=float(m[k]), ci95=float(c[k]), feasible=feasible,
                            low=lo[0], high=hi[0], at_low=lo[2], at_high=hi[2], sd_low=lo[1], sd_high=hi[1])
        if settings.explain and not r.reaches:
            without = {}
            released = [(kpis[j], [i for i in others if i != j], constraint) for j in others]
            if constraint is not None:
                released.append((constraint_name, others, None))
            for n, (name, kept, cons) in enumerate(released):
                x = optimum(k, 0.0, kept, cons, 2 * len(kpis) + len(released) * k + n)
                without[name] = math.nan if x is None else float(surrogate.predict_outputs(x)[0][0, k])
            r = dataclasses.replace(r, without=without)
        out.append(r)
    return tuple(out)


def format_attainable(ranges: Sequence[AttainableRange]) -> list[str]:
    """Markdown table: per KPI the lab's interval, the attainable range (with the posterior sd at its
    ends) and whether they meet; then, for the ranges that miss and were explained, what holds them:
    per constraint released, the mean closest to the lab's (bold where it meets the lab's CI)."""
    lines = ["| KPI | lab (95 % CI) | surrogate range with the others inside their CIs (sd at the ends) | meets the lab |",
             "| --- | ---: | ---: | --- |"]
    for r in ranges:
        span = (f"{r.low:.4g} ({r.sd_low:.2g}) to {r.high:.4g} ({r.sd_high:.2g})" if r.feasible
                else "none: the others cannot all be inside their CIs")
        lines.append(f"| {r.kpi} | {r.measured:.4g} +- {r.ci95:.3g} | {span} | {'yes' if r.reaches else '**no**'} |")
    explained = [r for r in ranges if r.without]
    if not explained:
        return lines
    kpis = [r.kpi for r in ranges]
    named = dict.fromkeys(c for r in explained for c in r.without)
    released = [c for c in kpis if c in named] + [c for c in named if c not in kpis]  # the KPIs' order first
    lines += ["", "What holds each range that misses: the KPI's mean closest to the lab's with one constraint "
              "released (bold: inside the lab's CI; - where the rest cannot all hold). A KPI held by another "
              "cannot meet the lab together with it: a cause of the gap has to move them apart.", "",
              "| KPI | lab (95 % CI) | " + " | ".join(f"without {c}" for c in released) + " | held by |",
              "| --- | ---: | " + " | ".join("---:" for _ in released) + " | --- |"]
    for r in explained:
        cells = []
        for c in released:
            v = r.without.get(c, math.nan)
            cells.append("" if c not in r.without else "-" if not math.isfinite(v)
                         else f"**{v:.4g}**" if r.meets(v) else f"{v:.4g}")
        held = ", ".join(r.held_by) or "no single constraint"
        lines.append(f"| {r.kpi} | {r.measured:.4g} +- {r.ci95:.3g} | " + " | ".join(cells) + f" | {held} |")
    return lines
