"""Parameter-space extension after screening (paper section 3.4.1, Table 6).

Contract
--------
``compare_ranges(results, measured)`` compares, per KPI, the range the screening runs reached
with the measurement. The simulated range is ``[min, max]`` of the *run means* (each design
run averaged over its finite replicates), because calibration matches replicate means; the
measurement is ``mean +- ci95`` (``torchdem.measured.KPIValue``). The measured mean lies
``"below"``, ``"inside"`` or ``"above"`` the range; ``ci_overlaps`` says whether the measured
confidence interval still touches the range (a marginal case worth a look).

``propose_extension(results, significance, measured)`` applies the paper's rule: for a KPI whose
measured mean lies outside the simulated range, every *selected* parameter that is significant
for that KPI (in at least ``significance.selection_fraction`` of the replicates) has its bound
moved in the direction that moves the KPI toward the measurement, assuming the sign of the
effect holds beyond the screened range (as the paper assumes):

* KPI must rise and the effect is ``+``, or must fall and the effect is ``-``: raise ``high``;
* otherwise lower ``low``.

The move is ``factor * (high - low)`` of the screened range (default ``factor = 1``: one more
screening width). ``mode = "extend"`` (default) keeps the other bound; ``mode = "shift"`` moves
the other bound to the old value of the moved one, so the new range starts where the screened
one ended (the paper does this for mu_s_pp, mu_r_pp and mu_r_pg in Table 6). If two KPIs ask
for opposite moves of one parameter, both bounds are extended (never shifted) and the reasoning
says so. Parameters that no out-of-range KPI asks to move keep their screened bounds; only
selected parameters appear in the proposal (Table 6 lists only the selected seven).

Bounds respect physical limits (``PhysicalLimit``): by default friction coefficients
(``mu_s_*``, ``mu_r_*``) ``>= 0`` and restitution (``e_*``) in ``(0, 1]``. A bound that would cross
a closed limit is set to the limit; one that would reach an open limit is set halfway between
the limit and the old bound. A parameter whose name matches no default and that has to move
needs an entry in ``limits`` (the error names it). A bound already at its limit stays and the
reasoning says the range cannot grow that way.

A limit may also cut the screened range: a screening may look past where the model is physical
(a trilobe's lobes part above a lobe spacing of 0.2679; the lab screening's high level is 0.3).
The runs outside the limits are then left out of the comparison, since a calibration will not
go there: the screening range of each KPI is that of the runs inside, and a limited parameter's
screened bounds are its levels inside. The reasoning says how many runs were left out.

The result, ``ExtensionProposal``, carries the comparisons, the moves, the proposed bounds and
human-readable reasoning lines; ``print(proposal)`` shows them, ``to_dict()`` is JSON-ready.

Reference: A. Hadi, Y. Pang, D. Schott, section 3.4.1, Fig. 11, Tables 5 and 6.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from types import MappingProxyType
from typing import Mapping, Sequence

import numpy as np

from bo.screening.stepwise import ScreeningResults, SignificanceTable
from torchdem.config import parameter_range
from torchdem.errors import ConfigError, out_of_range

__all__ = [
    "PhysicalLimit",
    "FRICTION_LIMIT",
    "RESTITUTION_LIMIT",
    "default_physical_limit",
    "KPIComparison",
    "BoundMove",
    "ExtensionProposal",
    "measured_mean_ci95",
    "compare_ranges",
    "propose_extension",
]


@dataclass(frozen=True)
class PhysicalLimit:
    """Allowed interval of a parameter; an open end may be approached but not reached."""

    low: float = -math.inf
    high: float = math.inf
    low_open: bool = False
    high_open: bool = False

    def __post_init__(self) -> None:
        if not self.low < self.high:
            raise out_of_range("PhysicalLimit", (self.low, self.high), "low < high",
                               "PhysicalLimit")

    def contains(self, value: float) -> bool:
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return above and below

    def describe(self) -> str:
        return (f"{'(' if self.low_open else '['}{self.low:g}, {self.high:g}"
                f"{')' if self.high_open else ']'}")


#: Friction coefficients cannot be negative.
FRICTION_LIMIT = PhysicalLimit(0.0, math.inf)
#: A coefficient of restitution lies in (0, 1].
RESTITUTION_LIMIT = PhysicalLimit(0.0, 1.0, low_open=True)


def default_physical_limit(parameter: str) -> PhysicalLimit | None:
    """Limit of a parameter named in this project's words (:func:`torchdem.config.parameter_range`:
    frictions, restitutions, cohesion, densities, lobe spacings), or None if the name is unknown."""
    low, high, open_low, _ = parameter_range(parameter)
    if math.isinf(low) and math.isinf(high):
        return None
    return PhysicalLimit(low, high, low_open=open_low)


@dataclass(frozen=True)
class KPIComparison:
    """Screening range of one KPI against its measurement.

    Attributes:
        kpi: KPI name.
        simulated_min, simulated_max: range of the run means of the screening runs.
        measured_mean, measured_ci95: the measurement, mean and 95 % CI half-width.
        position: where the measured mean lies: ``"below"``, ``"inside"`` or ``"above"``.
        ci_overlaps: the measured interval ``mean +- ci95`` intersects the simulated range.
    """

    kpi: str
    simulated_min: float
    simulated_max: float
    measured_mean: float
    measured_ci95: float
    position: str
    ci_overlaps: bool

    @property
    def direction(self) -> int:
        """+1 if the KPI must rise to reach the measurement, -1 if it must fall, 0 inside."""
        return {"below": -1, "inside": 0, "above": 1}[self.position]

    def describe(self) -> str:
        where = {"below": "below", "inside": "inside", "above": "above"}[self.position]
        overlap = ("" if self.position == "inside" else
                   "; its CI overlaps the range (marginal)" if self.ci_overlaps else
                   "; its CI does not reach the range")
        return (f"{self.kpi}: measured {self.measured_mean:.4g} +- {self.measured_ci95:.3g} lies "
                f"{where} the screening range [{self.simulated_min:.4g}, "
                f"{self.simulated_max:.4g}] (run means){overlap}")


@dataclass(frozen=True)
class BoundMove:
    """One bound of one parameter moved by the extension.

    Attributes:
        parameter: parameter name.
        side: ``"low"`` or ``"high"``.
        old, new: the bound before and after.
        kpis: the KPIs that asked for the move.
        limited: True if a physical limit stopped the move short of ``factor * range``.
    """

    parameter: str
    side: str
    old: float
    new: float
    kpis: tuple[str, ...]
    limited: bool


@dataclass(frozen=True)
class ExtensionProposal:
    """Proposed calibration bounds for the selected parameters, with the reasoning.

    Attributes:
        comparisons: one ``KPIComparison`` per KPI considered.
        screened_bounds: selected parameter -> (low, high) of the screening design.
        proposed_bounds: selected parameter -> proposed (low, high).
        moves: the bounds that changed.
        reasoning: human-readable lines, in the order the decisions were made.
        factor: move size as a multiple of the screened range.
        mode: ``"extend"`` or ``"shift"``.
    """

    comparisons: tuple[KPIComparison, ...]
    screened_bounds: Mapping[str, tuple[float, float]]
    proposed_bounds: Mapping[str, tuple[float, float]]
    moves: tuple[BoundMove, ...]
    reasoning: tuple[str, ...]
    factor: float
    mode: str

    @property
    def changed_parameters(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(m.parameter for m in self.moves))

    def to_text(self) -> str:
        width = max([len("parameter"), *(len(p) for p in self.proposed_bounds)])
        lines = ["Parameter-space extension (screening range vs measurement)", ""]
        lines += list(self.reasoning)
        lines += ["", f"{'parameter'.ljust(width)}  {'screened':>21}  {'proposed':>21}"]
        for name, (lo, hi) in self.proposed_bounds.items():
            slo, shi = self.screened_bounds[name]
            mark = "  *" if name in self.changed_parameters else ""
            lines.append(f"{name.ljust(width)}  [{slo:9.4g}, {shi:9.4g}]  [{lo:9.4g}, {hi:9.4g}]"
                         f"{mark}")
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.to_text()

    def to_dict(self) -> dict:
        return {
            "factor": self.factor, "mode": self.mode,
            "comparisons": [{"kpi": c.kpi, "simulated_min": c.simulated_min,
                             "simulated_max": c.simulated_max, "measured_mean": c.measured_mean,
                             "measured_ci95": c.measured_ci95, "position": c.position,
                             "ci_overlaps": c.ci_overlaps} for c in self.comparisons],
            "screened_bounds": {k: list(v) for k, v in self.screened_bounds.items()},
            "proposed_bounds": {k: list(v) for k, v in self.proposed_bounds.items()},
            "moves": [{"parameter": m.parameter, "side": m.side, "old": m.old, "new": m.new,
                       "kpis": list(m.kpis), "limited": m.limited} for m in self.moves],
            "reasoning": list(self.reasoning),
        }


def measured_mean_ci95(measured: Mapping, kpi: str, source: str) -> tuple[float, float]:
    """``(mean, ci95)`` of ``measured[kpi]`` (a ``KPIValue`` or ``{"mean", "ci95"}``), checked."""
    if kpi not in measured:
        raise ConfigError(f"{source}: measured data lack KPI {kpi!r}; measured KPIs: "
                          f"{list(measured)}. Pass kpis=... to compare only measured KPIs")
    entry = measured[kpi]
    mean = getattr(entry, "mean", None)
    ci95 = getattr(entry, "ci95", None)
    if mean is None and isinstance(entry, Mapping):
        mean, ci95 = entry.get("mean"), entry.get("ci95")
    try:
        mean, ci95 = float(mean), float(ci95)
    except (TypeError, ValueError):
        raise ConfigError(f"{source}: measured[{kpi!r}] = {entry!r} is not allowed; expected a "
                          f"KPIValue or {{'mean': ..., 'ci95': ...}}") from None
    if not (math.isfinite(mean) and math.isfinite(ci95) and ci95 >= 0):
        raise ConfigError(f"{source}: measured[{kpi!r}] has mean {mean!r}, ci95 {ci95!r}; "
                          f"expected a finite mean and a finite ci95 >= 0")
    return mean, ci95


def compare_ranges(results: ScreeningResults, measured: Mapping,
                   kpis: Sequence[str] | None = None,
                   source: str = "compare_ranges") -> tuple[KPIComparison, ...]:
    """Screening range (run means) versus measured ``mean +- ci95`` for each KPI.

    ``measured`` maps KPI name -> ``KPIValue`` (e.g. ``load_measured().condition("50-50").kpis``)
    or ``{"mean": ..., "ci95": ...}``. ``kpis`` defaults to every screening KPI; each must be
    both simulated and measured.
    """
    chosen = tuple(results.kpi_names if kpis is None else kpis)
    out = []
    for kpi in chosen:
        results.kpi_index(kpi, source)  # raises for an unknown KPI, listing the known ones
        means = results.run_means(kpi)
        mean, ci95 = measured_mean_ci95(measured, kpi, source)
        finite = means[np.isfinite(means)]
        if finite.size == 0:
            raise ConfigError(f"{source}: KPI {kpi!r} has no finite screening value in any run; "
                              f"expected at least one")
        lo, hi = float(finite.min()), float(finite.max())
        position = "below" if mean < lo else "above" if mean > hi else "inside"
        out.append(KPIComparison(kpi=kpi, simulated_min=lo, simulated_max=hi, measured_mean=mean,
                                 measured_ci95=ci95, position=position,
                                 ci_overlaps=bool(mean - ci95 <= hi and mean + ci95 >= lo)))
    return tuple(out)


def _move(old: float, step: float, limit: PhysicalLimit, side: str) -> tuple[float, bool]:
    """New bound ``old +- step`` kept inside ``limit``; returns (new, limited)."""
    if side == "high":
        proposed = old + step
        if limit.contains(proposed):
            return proposed, False
        return (limit.high if not limit.high_open else 0.5 * (limit.high + old)), True
    proposed = old - step
    if limit.contains(proposed):
        return proposed, False
    return (limit.low if not limit.low_open else 0.5 * (limit.low + old)), True


def propose_extension(results: ScreeningResults, significance: SignificanceTable,
                      measured: Mapping, *, factor: float = 1.0, mode: str = "extend",
                      limits: Mapping[str, PhysicalLimit] | None = None,
                      kpis: Sequence[str] | None = None) -> ExtensionProposal:
    """Propose bounds for the selected parameters; see the module docstring for the rule.

    ``kpis`` defaults to the KPIs of ``significance`` (all must be measured). ``limits``
    overrides or adds physical limits by parameter name, e.g. ``{"mu_s_pp": PhysicalLimit(0,
    1.0)}`` to cap sliding friction at 1 as the paper's Table 6 does.
    """
    source = f"propose_extension({results.source})"
    if significance.parameter_names != results.parameter_names:
        missing = [p for p in results.parameter_names if p not in significance.parameter_names]
        extra = [p for p in significance.parameter_names if p not in results.parameter_names]
        raise ConfigError(f"{source}: the significance table's parameters do not match the "
                          f"screening results: missing {missing}, unexpected {extra}; expected "
                          f"{list(results.parameter_names)} in that order")
    if (isinstance(factor, bool) or not isinstance(factor, (int, float, np.floating))
            or not math.isfinite(factor) or factor <= 0):
        raise out_of_range("factor", factor, "a finite number > 0 (multiple of the screened "
                           "range), e.g. 1.0", source)
    if mode not in ("extend", "shift"):
        raise out_of_range("mode", mode, "'extend' or 'shift'", source)
    limits = dict(limits or {})
    unknown = [p for p in limits if p not in results.parameter_names]
    if unknown:
        raise ConfigError(f"{source}: limits given for unknown parameters {unknown}; expected "
                          f"names from {list(results.parameter_names)}")
    chosen = tuple(significance.kpi_names if kpis is None else kpis)
    not_screened = [k for k in chosen if k not in significance.kpi_names]
    if not_screened:
        raise ConfigError(f"{source}: KPIs {not_screened} are not in the significance table; "
                          f"expected a subset of {list(significance.kpi_names)}")
    inside = np.ones(results.n_runs, dtype=bool)
    cutting = []
    for p, limit in limits.items():
        column = results.physical[:, results.parameter_names.index(p)]
        within = np.array([limit.contains(float(v)) for v in column])
        if not within.all():
            cutting.append(f"{p} {limit.describe()}")
        inside &= within
    n_runs = results.n_runs
    if not inside.all():
        try:
            results = ScreeningResults(parameter_names=results.parameter_names, coded=results.coded[inside],
                                       physical=results.physical[inside], seeds=results.seeds,
                                       kpi_names=results.kpi_names, kpi_values=results.kpi_values[inside],
                                       source=f"{results.source}, inside the limits")
        except ConfigError as err:
            raise ConfigError(f"{source}: the limits {', '.join(cutting)} leave {int(inside.sum())} of the "
                              f"screening's {n_runs} runs, too few to compare ranges ({err})") from None
    comparisons = compare_ranges(results, measured, chosen, source)

    selected = significance.selected_parameters
    screened = results.levels()
    requests: dict[str, dict[str, list[str]]] = {p: {"low": [], "high": []} for p in selected}
    reasoning: list[str] = ([f"{n_runs - results.n_runs} of the screening's {n_runs} runs lie outside the limits "
                             f"({'; '.join(cutting)}) and are left out of the ranges compared"]
                            if results.n_runs < n_runs else [])
    if not selected:
        reasoning.append("No parameter was selected by the screening; nothing to extend.")
    for comp in comparisons:
        reasoning.append(comp.describe())
        if comp.position == "inside":
            reasoning.append("  no change needed for this KPI")
            continue
        verb = "raise" if comp.direction > 0 else "lower"
        j = significance.kpi_names.index(comp.kpi)
        drivers = [p for p in selected
                   if significance.significant_for_kpi[significance.parameter_names.index(p), j]]
        if not drivers:
            reasoning.append(f"  no selected parameter is significant for {comp.kpi}; the "
                             f"screening gives no direction to {verb} it")
            continue
        for p in drivers:
            sign = significance.sign(p, comp.kpi)
            i = significance.parameter_names.index(p)
            count = f"{int(significance.significant[i, j])}/{significance.replicates[j]}"
            if sign == 0:
                reasoning.append(f"  {p}: significant ({count}) with mixed signs; not moved")
                continue
            side = "high" if sign * comp.direction > 0 else "low"
            requests[p][side].append(comp.kpi)
            effect = "+" if sign > 0 else "-"
            action = "raise its high bound" if side == "high" else "lower its low bound"
            reasoning.append(f"  {p} has a {effect} effect on {comp.kpi} ({count} replicates): "
                             f"to {verb} the KPI, {action}")

    proposed: dict[str, tuple[float, float]] = {}
    moves: list[BoundMove] = []
    for p in selected:
        lo, hi = screened[p]
        width = hi - lo
        sides = [s for s in ("low", "high") if requests[p][s]]
        if not sides:
            proposed[p] = (lo, hi)
            continue
        limit = limits.get(p, default_physical_limit(p))
        if limit is None:
            raise ConfigError(f"{source}: parameter {p!r} must move but has no known physical "
                              f"limit; pass limits={{{p!r}: PhysicalLimit(low, high)}}")
        new = {"low": lo, "high": hi}
        moved = False
        for side in sides:
            old = lo if side == "low" else hi
            if (old >= limit.high) if side == "high" else (old <= limit.low):
                reasoning.append(f"{p}: the {side} bound {old:g} is already at the physical limit "
                                 f"{limit.describe()}; it cannot move")
                continue
            value, limited = _move(old, factor * width, limit, side)
            new[side] = value
            moved = True
            moves.append(BoundMove(parameter=p, side=side, old=old, new=value,
                                   kpis=tuple(requests[p][side]), limited=limited))
            if limited:
                open_end = limit.high_open if side == "high" else limit.low_open
                how = (f"a move of {factor:g} x the screened range {width:g} would leave the "
                       f"physical limit {limit.describe()}, so it is "
                       + ("set halfway to the open limit" if open_end else "capped at the limit"))
            else:
                how = f"a move of {factor:g} x the screened range {width:g}"
            reasoning.append(f"{p}: {side} bound {old:g} -> {value:g} ({how}); asked by "
                             f"{', '.join(requests[p][side])}")
        if len(sides) == 2:
            reasoning.append(f"{p}: KPIs ask for opposite moves ({', '.join(requests[p]['low'])}"
                             f" a lower low bound, {', '.join(requests[p]['high'])} a higher high "
                             f"bound); both bounds extended, none shifted")
        elif mode == "shift" and moved:
            side = sides[0]
            other = "low" if side == "high" else "high"
            new[other] = hi if side == "high" else lo
            reasoning.append(f"{p}: shift mode, {other} bound -> {new[other]:g} (the old {side} "
                             f"bound)")
        proposed[p] = (new["low"], new["high"])
    return ExtensionProposal(
        comparisons=comparisons,
        screened_bounds=MappingProxyType({p: screened[p] for p in selected}),
        proposed_bounds=MappingProxyType(proposed),
        moves=tuple(moves), reasoning=tuple(reasoning), factor=float(factor), mode=mode)
