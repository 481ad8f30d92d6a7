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

The figures are the test's own: an effect detected is not yet an effect attributed (the power
study, ``bo.discovery.power``, measures that).

Attribution has a bound that needs no twins. If the true mechanism shifts the cells by ``a`` and
another mechanism shifts them along ``b`` by an amount of its own (``c b``, any real ``c``: a
mechanism may move either way within its prior), the other mechanism fits the data as well as its
best ``c`` does, and its lack of fit is non-central chi^2 with ``dof - 1`` degrees of freedom and

    lambda = min_c sum ((a - c b) / sigma)^2 = |a'|^2 - (a'.b')^2 / |b'|^2,   a' = a / sigma, b' = b / sigma.

:func:`distinguishing_power` gives the probability that such a test rejects the other mechanism:
where it is low, no verdict rule can tell the two apart from these cells, and "cannot tell" is
the right answer, unless the other mechanism would need a magnitude outside its prior. Two
idealisations: the shifts are taken as linear in the effect (``b`` is one measured shift of the
other mechanism), and the prior's limits on ``c`` are not applied, which can only lower the power
(a mechanism held inside its prior fits no better).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Mapping, Sequence

import numpy as np
from scipy import optimize, stats

from torchdem.errors import out_of_range

__all__ = ["CellUncertainty", "detection_power", "distinguishing_power", "smallest_detectable", "Addition",
           "what_to_measure_next"]


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
    return float(stats.ncx2.sf(stats.chi2.isf(alpha, dof), dof, lam)) if lam > 0 else float(alpha)


def distinguishing_power(delta_true: Sequence[float], delta_other: Sequence[float], sigma: Sequence[float],
                         alpha: float = 0.05) -> float:
    """Probability that cells shifted by ``delta_true`` reject another mechanism whose shifts lie
    along ``delta_other`` at its best-fitting magnitude (module docstring): a chi^2 test of
    ``len(sigma) - 1`` degrees of freedom at level ``alpha``."""
    a, b, s = (np.asarray(v, dtype=float) for v in (delta_true, delta_other, sigma))
    if not (a.shape == b.shape == s.shape) or a.ndim != 1 or a.size < 2 or not np.all(s > 0) \
            or not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise out_of_range("(delta_true, delta_other, sigma)", (a.shape, b.shape, s.shape),
                           "three equal-length 1-D arrays of at least 2 finite cells, sigma > 0", "distinguishing_power")
    a, b = a / s, b / s
    aa, bb = float(a @ a), float(b @ b)
    lam = aa - (float(a @ b) ** 2 / bb if bb > 0 else 0.0)
    return _chi2_power(lam if lam > 1e-12 * aa else 0.0, a.size - 1, alpha)


def smallest_detectable(shift: Callable[[float], Sequence[float]], sigma: Sequence[float], *, target: float = 0.8,
                        alpha: float = 0.05, grid: int = 41) -> float | None:
    """Smallest effect size ``t`` in [0, 1] whose power reaches ``target`` (None: not reached).
    The power is scanned on ``grid`` points and the first crossing refined by Brent's method."""
    ts = np.linspace(0.0, 1.0, grid)
    power = np.array([detection_power(shift(t), sigma, alpha) for t in ts])
    above = np.flatnonzero(power >= target)
    if not above.size:
        return None
    k = int(above[0])
    if k == 0:
        return 0.0
    f = lambda t: detection_power(shift(t), sigma, alpha) - target  # noqa: E731
    return float(optimize.brentq(f, ts[k - 1], ts[k], xtol=1e-6))


@dataclass(frozen=True)
class Addition:
    """One addition and its effect: the power at the reference effect and the smallest
    detectable effect with it (None: not within the studied range)."""

    name: str
    description: str
    power: float
    smallest: float | None


def what_to_measure_next(cells: Sequence[CellUncertainty], shift: Callable[[float], Mapping[tuple[str, str], float]],
                         *, reference: float = 1.0, factor: int = 2,
                         new_kpis: Mapping[str, tuple[float, float]] | None = None,
                         target: float = 0.8, alpha: float = 0.05) -> list[Addition]:
    """Power at effect ``reference`` and smallest detectable effect now and after each addition
    (``factor`` x the lab repeats, ``factor`` x the DEM replicates, each KPI of ``new_kpis``: name
    -> (DEM standard error, lab standard uncertainty), added on every condition); best first, "as is" kept
    in the list for comparison. ``shift(t)`` maps (condition, KPI) -> shift, for every cell of
    ``cells`` and every new KPI."""
    if not cells:
        raise out_of_range("cells", cells, "at least one measured cell", "what_to_measure_next")

    def evaluate(name: str, description: str, keys: list[tuple[str, str]], sigma: list[float]) -> Addition:
        f = lambda t: [shift(t)[k] for k in keys]  # noqa: E731
        return Addition(name, description, detection_power(f(reference), sigma, alpha),
                        smallest_detectable(f, sigma, target=target, alpha=alpha))

    keys = [(c.condition, c.kpi) for c in cells]
    out = [evaluate("as is", "the data as they are", keys, [c.sigma for c in cells])]
    if all(c.lab_repeats for c in cells):
        sigma = [math.sqrt(c.se ** 2 + c.u ** 2 / factor) for c in cells]
        out.append(evaluate("lab_repeats", f"every test repeated {factor} x as often in the lab", keys, sigma))
    sigma = [math.sqrt(c.se ** 2 / factor + c.u ** 2) for c in cells]
    out.append(evaluate("dem_replicates", f"{factor} x the DEM replicates per condition", keys, sigma))
    conditions = list(dict.fromkeys(c.condition for c in cells))
    for kpi, (se, u) in (new_kpis or {}).items():
        extra = [(c, kpi) for c in conditions]
        out.append(evaluate(f"kpi:{kpi}", f"{kpi} measured on every condition (se {se:g}, u {u:g})", keys + extra,
                            [c.sigma for c in cells] + [math.sqrt(se ** 2 + u ** 2)] * len(conditions)))
    return sorted(out, key=lambda a: (-(a.power), a.smallest if a.smallest is not None else math.inf))
