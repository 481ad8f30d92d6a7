"""What could these data have seen? The smallest detectable effect, and what to measure next.

Contract
--------
Discovery's discrepancy test (``bo.discovery.pipeline``, step 1) sums, over the measured cells
(condition x KPI), the squared difference between DEM and lab in units of the cell's combined
standard uncertainty ``sigma = sqrt(se^2 + u^2)`` (DEM standard error and lab standard
uncertainty), and calls it significant above the chi^2 quantile of as many degrees of freedom.
If a mechanism the model lacks shifts the cells by ``delta``, the sum follows a non-central chi^2
with non-centrality ``lambda = sum (delta / sigma)^2``, so the test's power against that effect is

    power = P(chi2_nc(dof, lambda) > chi2_{dof, 1 - alpha}).

:func:`detection_power` computes it; :func:`smallest_detectable` finds, for shifts that grow with
an effect size ``t`` in ``[0, 1]`` (``shift(t) -> [cells]``; from a hypothesis's GP models, or any
model of the mechanism), the smallest ``t`` whose power reaches ``target`` (None: not within
``[0, 1]``). :func:`what_to_measure_next` evaluates the same power after each addition a lab can
make and ranks them:

* ``lab_repeats``: the lab repeats every test ``k`` times instead of ``n`` (``u`` scales as
  ``sqrt(n / k)``);
* ``dem_replicates``: the DEM is run ``k`` times per condition instead of ``r`` (``se`` scales as
  ``sqrt(r / k)``);
* ``kpi:<name>``: a KPI the lab does not report yet (the heap height, say), with the DEM's standard
  error and the lab's standard uncertainty of it, whose shift is part of ``shift`` (the design
  runs measure every KPI).
* ``condition:<name>``: a condition the lab has not measured (another mass ratio, the reverse
  layering), measured on the same KPIs, with the DEM's standard error and the lab's standard
  uncertainty per KPI, whose shift is part of ``shift`` (the design runs it too).

The figures are the test's own: an effect detected is not yet an effect attributed (the power
study, ``bo.discovery.power``, measures that).

Attribution has a bound that needs no twins. If the true mechanism shifts the cells by ``a`` and
another hypothesis can move them along the columns of ``B`` (its free directions: one column per
parameter, the shift from the low to the high end of its range) by amounts ``c`` of its own, that
hypothesis fits the data as well as its best ``c`` does, and its lack of fit is non-central chi^2
with ``dof - rank(B)`` degrees of freedom and

    lambda = min_c sum ((a - B c) / sigma)^2.

:func:`distinguishing_power` gives the probability that such a test rejects the other hypothesis:
where it is low, no verdict rule can tell the two apart from these cells, and "cannot tell" is
the right answer. Without ``bounds`` the magnitudes ``c`` are any real numbers (a mechanism may
move either way), ``lambda = |a'|^2 - |P_B a'|^2`` with ``a' = a / sigma`` and ``P_B`` the
projection on the columns in units of sigma; with ``bounds`` each ``c`` is held inside its
parameter's range (bounded least squares, ``scipy.optimize.lsq_linear``), so a hypothesis cannot
explain a shift with a magnitude its prior forbids. The shifts are taken as linear in each
parameter (a secant over its range), and the degrees of freedom count every free direction, bound
or not, which can only lower the power.

:func:`what_separates` evaluates that power now and after each of the additions above, and the
smallest effect of the true mechanism that is told apart with ``target`` probability; the
discovery report (``bo.discovery.pipeline.separability``) sets every candidate against every
rival with them.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Callable, Mapping, Sequence

import numpy as np
from scipy import optimize, stats

from torchdem.errors import out_of_range

__all__ = ["CellUncertainty", "detection_power", "distinguishing_power", "smallest_detectable", "smallest_effect",
           "Addition", "what_to_measure_next", "what_separates"]


@dataclass(frozen=True)
class CellUncertainty:
    """One measured cell: DEM standard error ``se`` with ``dem_replicates`` runs, lab standard
    uncertainty ``u`` with ``lab_repeats`` repeats (None: not stated, kept fixed)."""

    condition: str
    kpi: str
    se: float
    u: float
    dem_replicates: int
    lab_repeats: int | None = None

    @property
    def sigma(self) -> float:
        return math.sqrt(self.se ** 2 + self.u ** 2)


def detection_power(delta: Sequence[float], sigma: Sequence[float], alpha: float = 0.05) -> float:
    """Power of the chi^2 discrepancy test against shifts ``delta`` of cells with uncertainties
    ``sigma`` (module docstring)."""
    d, s = np.asarray(delta, dtype=float), np.asarray(sigma, dtype=float)
    if d.shape != s.shape or d.ndim != 1 or not d.size or not np.all(s > 0):
        raise out_of_range("(delta, sigma)", (d.shape, s.shape), "two equal-length 1-D arrays, sigma > 0",
                           "detection_power")
    return _chi2_power(float(np.sum((d / s) ** 2)), d.size, alpha)


def _chi2_power(lam: float, dof: int, alpha: float) -> float:
    """P(chi2_nc(dof, lam) > chi2_{dof, 1 - alpha}); alpha where lam is (round-off) zero."""
    return float(stats.ncx2.sf(_critical(alpha, dof), dof, lam)) if lam > 0 else float(alpha)


@functools.lru_cache(maxsize=256)
def _critical(alpha: float, dof: int) -> float:
    return float(stats.chi2.isf(alpha, dof))


def distinguishing_power(delta_true: Sequence[float], delta_other: Sequence[float] | Sequence[Sequence[float]],
                         sigma: Sequence[float], alpha: float = 0.05,
                         bounds: Sequence[tuple[float, float]] | None = None) -> float:
    """Probability that cells shifted by ``delta_true`` reject another hypothesis whose shifts lie
    in the span of ``delta_other`` (``[cells]``, one direction, or ``[k, cells]``, k directions),
    at its best-fitting magnitudes, held inside ``bounds`` (one ``(low, high)`` per direction)
    where given (module docstring): a chi^2 test of ``len(sigma) - rank`` degrees of freedom at
    level ``alpha``; ``alpha`` itself where no degree of freedom is left."""
    a, s = np.asarray(delta_true, dtype=float), np.asarray(sigma, dtype=float)
    b = np.atleast_2d(np.asarray(delta_other, dtype=float))
    if not (a.shape == s.shape and b.shape[1:] == a.shape) or a.ndim != 1 or a.size < 2 or not np.all(s > 0) \
            or not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))) \
            or (bounds is not None and (len(bounds) != b.shape[0] or any(lo > hi for lo, hi in bounds))):
        raise out_of_range("(delta_true, delta_other, sigma, bounds)", (a.shape, b.shape, s.shape, bounds),
                           "delta_true and sigma 1-D of at least 2 finite cells, sigma > 0, delta_other [cells] or "
                           "[k, cells], one (low <= high) bound per direction", "distinguishing_power")
    a, B = a / s, (b / s).T  # [n], [n, k]
    aa = float(a @ a)
    rank = int(np.linalg.matrix_rank(B)) if np.any(B) else 0
    dof = a.size - rank
    if dof < 1:
        return float(alpha)
    if rank == 0:
        lam = aa
    else:
        c, *_ = np.linalg.lstsq(B, a, rcond=None)
        lam = float(np.sum((a - B @ c) ** 2))
        if bounds is not None:
            lo, hi = np.array(bounds, dtype=float).T
            if np.any(c < lo) or np.any(c > hi):  # inside the bounds the free optimum is the bounded one
                hi = np.where(hi > lo, hi, lo + 1e-12 * np.maximum(1.0, np.abs(lo)))  # lsq_linear wants low < high
                lam = 2.0 * float(optimize.lsq_linear(B, a, bounds=(lo, hi), method="bvls").cost)
    return _chi2_power(lam if lam > 1e-12 * aa else 0.0, dof, alpha)


def smallest_effect(power: Callable[[float], float], *, target: float = 0.8, grid: int = 41) -> float | None:
    """Smallest effect size ``t`` in [0, 1] where ``power(t)`` reaches ``target`` (None: not
    reached): ``power`` is scanned on ``grid`` points and the first crossing refined by Brent's
    method."""
    ts = np.linspace(0.0, 1.0, grid)
    k = next((k for k, t in enumerate(ts) if power(float(t)) >= target), None)
    if k is None:
        return None
    if k == 0:
        return 0.0
    return float(optimize.brentq(lambda t: power(t) - target, ts[k - 1], ts[k], xtol=1e-6))


def smallest_detectable(shift: Callable[[float], Sequence[float]], sigma: Sequence[float], *, target: float = 0.8,
                        alpha: float = 0.05, grid: int = 41) -> float | None:
    """Smallest effect size ``t`` in [0, 1] whose detection power reaches ``target`` (None: not
    reached; :func:`smallest_effect`)."""
    return smallest_effect(lambda t: detection_power(shift(t), sigma, alpha), target=target, grid=grid)


@dataclass(frozen=True)
class Addition:
    """One addition and its effect: the power at the reference effect and the smallest
    detectable effect with it (None: not within the studied range)."""

    name: str
    description: str
    power: float
    smallest: float | None


def _additions(cells: Sequence[CellUncertainty], factor: int, new_kpis: Mapping[str, tuple[float, float]] | None,
               new_conditions: Mapping[str, Mapping[str, tuple[float, float]]] | None = None
               ) -> list[tuple[str, str, list[tuple[str, str]], list[float]]]:
    """The data as they are and each addition: (name, description, cell keys, cell sigmas)."""
    if not cells:
        raise out_of_range("cells", cells, "at least one measured cell", "bo.discovery.detectable")
    keys = [(c.condition, c.kpi) for c in cells]
    out = [("as is", "the data as they are", keys, [c.sigma for c in cells])]
    if all(c.lab_repeats for c in cells):
        out.append(("lab_repeats", f"every test repeated {factor} x as often in the lab", keys,
                    [math.sqrt(c.se ** 2 + c.u ** 2 / factor) for c in cells]))
    out.append(("dem_replicates", f"{factor} x the DEM replicates per condition", keys,
                [math.sqrt(c.se ** 2 / factor + c.u ** 2) for c in cells]))
    conditions = list(dict.fromkeys(c.condition for c in cells))
    for kpi, (se, u) in (new_kpis or {}).items():
        out.append((f"kpi:{kpi}", f"{kpi} measured on every condition (se {se:g}, u {u:g})",
                    keys + [(c, kpi) for c in conditions],
                    [c.sigma for c in cells] + [math.sqrt(se ** 2 + u ** 2)] * len(conditions)))
    for condition, per_kpi in (new_conditions or {}).items():
        if per_kpi:
            out.append((f"condition:{condition}", f"condition {condition} measured on {', '.join(per_kpi)}",
                        keys + [(condition, k) for k in per_kpi],
                        [c.sigma for c in cells] + [math.sqrt(se ** 2 + u ** 2) for se, u in per_kpi.values()]))
    return out


def _at(values: Mapping[tuple[str, str], float], keys: Sequence[tuple[str, str]]) -> list[float]:
    return [values[k] for k in keys]


def _ranked(out: list[Addition]) -> list[Addition]:
    return sorted(out, key=lambda a: (-(a.power), a.smallest if a.smallest is not None else math.inf))


def what_to_measure_next(cells: Sequence[CellUncertainty], shift: Callable[[float], Mapping[tuple[str, str], float]],
                         *, reference: float = 1.0, factor: int = 2,
                         new_kpis: Mapping[str, tuple[float, float]] | None = None,
                         new_conditions: Mapping[str, Mapping[str, tuple[float, float]]] | None = None,
                         target: float = 0.8, alpha: float = 0.05) -> list[Addition]:
    """Power at effect ``reference`` and smallest detectable effect now and after each addition
    (``factor`` x the lab repeats, ``factor`` x the DEM replicates, each KPI of ``new_kpis``: name
    -> (DEM standard error, lab standard uncertainty), added on every condition; each condition of
    ``new_conditions``: name -> KPI -> (DEM standard error, lab standard uncertainty)); best
    first, "as is" kept in the list for comparison. ``shift(t)`` maps (condition, KPI) -> shift,
    for every cell of ``cells``, every new KPI and every new condition."""
    out = []
    for name, description, keys, sigma in _additions(cells, factor, new_kpis, new_conditions):
        f = lambda t, keys=keys: _at(shift(t), keys)  # noqa: E731
        out.append(Addition(name, description, detection_power(f(reference), sigma, alpha),
                            smallest_detectable(f, sigma, target=target, alpha=alpha)))
    return _ranked(out)


def what_separates(cells: Sequence[CellUncertainty], shift: Callable[[float], Mapping[tuple[str, str], float]],
                   rival: Sequence[Mapping[tuple[str, str], float]],
                   bounds: Sequence[tuple[float, float]] | None = None, *, reference: float = 1.0, factor: int = 2,
                   new_kpis: Mapping[str, tuple[float, float]] | None = None,
                   new_conditions: Mapping[str, Mapping[str, tuple[float, float]]] | None = None,
                   target: float = 0.8, alpha: float = 0.05) -> list[Addition]:
    """Power to tell a mechanism shifting the cells by ``shift(t)`` from a rival hypothesis with
    free directions ``rival`` (one mapping (condition, KPI) -> shift per direction, magnitudes in
    ``bounds``; :func:`distinguishing_power`) at effect ``reference``, and the smallest effect told
    apart with ``target`` probability, now and after each addition of :func:`what_to_measure_next`;
    best first. An added KPI or condition that a rival direction does not predict is left out."""
    out = []
    for name, description, keys, sigma in _additions(cells, factor, new_kpis, new_conditions):
        if not all(k in col for col in rival for k in keys):
            continue
        B = [[col[k] for k in keys] for col in rival] or [[0.0] * len(keys)]
        f = lambda t, keys=keys, sigma=sigma, B=B: distinguishing_power(  # noqa: E731
            _at(shift(t), keys), B, sigma, alpha, bounds if rival else None)
        out.append(Addition(name, description, f(reference), smallest_effect(f, target=target)))
    return _ranked(out)
