"""Which geometry can stand for the lab's box? KPIs of reduced geometries against the whole box.

Contract
--------
A geometry study runs one condition in several geometries (condition variants of
``DrawDownGeometry.slice_depth`` and ``mirror``, see :func:`torchdem.model.variant`), the first
being the reference (the whole box), at one or more parameter sets, one run per seed
(``bo.studies.pipeline.run_geometry_study``). :func:`geometry_comparison` compares every other
geometry with the reference, per parameter set and KPI:

* the difference of means and its 95 % confidence interval (Welch's t, so two geometries with
  different scatter are compared fairly);
* ``within noise``: the interval contains 0, i.e. the replicates cannot tell the two geometries
  apart; ``differs``: it does not (the reduced geometry moves the KPI);
* the difference relative to the lab's 95 % CI half-width of the KPI (Table 2), so a difference
  the replicates cannot resolve is also judged against what the lab can resolve;
* the cost per run (the wall time of a run's ensemble divided by its members).

A geometry passes when every KPI is within noise at every parameter set. With few seeds (the
whole box costs minutes per run) "within noise" is a weak statement; the report therefore
prints the interval, which says how large a difference the seeds could have missed.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Mapping, Sequence

import numpy as np
from scipy import stats

from torchdem.errors import ConfigError

__all__ = ["KPIDifference", "GeometryComparison", "geometry_comparison"]


@dataclass(frozen=True)
class KPIDifference:
    """One KPI of one geometry against the reference at one parameter set.

    Attributes:
        parameter_set, geometry, kpi: names. n_ref, n: finite runs. mean_ref, mean: means.
        sd_ref, sd: replicate standard deviations (NaN below 2 runs).
        difference: mean - mean_ref. ci_low, ci_high: its 95 % Welch interval (NaN below 2 runs each).
        relative: difference / |mean_ref|. lab_margin: the lab's 95 % CI half-width (NaN if unknown).
        verdict: ``"within noise"``, ``"differs"`` or ``"too few runs"``.
    """

    parameter_set: str
    geometry: str
    kpi: str
    n_ref: int
    n: int
    mean_ref: float
    mean: float
    sd_ref: float
    sd: float
    difference: float
    ci_low: float
    ci_high: float
    relative: float
    lab_margin: float
    verdict: str


@dataclass(frozen=True)
class GeometryComparison:
    """The study's answer: every :class:`KPIDifference` and the cost per run of each geometry."""

    reference: str
    rows: tuple[KPIDifference, ...]
    cost_per_run_s: Mapping[str, float]

    def passes(self, geometry: str) -> bool:
        """Every KPI of ``geometry`` within noise at every parameter set."""
        mine = [r for r in self.rows if r.geometry == geometry]
        return bool(mine) and all(r.verdict == "within noise" for r in mine)

    def to_dict(self) -> dict:
        return {"reference": self.reference, "rows": [asdict(r) for r in self.rows],
                "cost_per_run_s": dict(self.cost_per_run_s),
                "passes": {g: self.passes(g) for g in sorted({r.geometry for r in self.rows})}}

    def to_text(self) -> str:
        lines = [f"Reduced geometries against {self.reference} (difference of means, 95 % Welch interval; "
                 "'within noise' when the interval contains 0)",
                 "| parameter set | geometry | KPI | n ref / n | mean ref | mean | difference (95 % CI) | relative | "
                 "difference / lab CI | verdict |",
                 "| --- | --- | --- | ---: | ---: | ---: | --- | ---: | ---: | --- |"]
        for r in self.rows:
            lab = f"{r.difference / r.lab_margin:+.2f}" if math.isfinite(r.lab_margin) and r.lab_margin > 0 else "-"
            lines.append(f"| {r.parameter_set} | {r.geometry} | {r.kpi} | {r.n_ref} / {r.n} | {r.mean_ref:.4g} | "
                         f"{r.mean:.4g} | {r.difference:+.3g} ({r.ci_low:+.3g}, {r.ci_high:+.3g}) | "
                         f"{r.relative:+.1%} | {lab} | {r.verdict} |")
        costs = ", ".join(f"{g}: {c:.0f} s" for g, c in self.cost_per_run_s.items() if math.isfinite(c))
        lines.append(f"Cost per run: {costs}")
        for g in sorted({r.geometry for r in self.rows}):
            lines.append(f"Verdict {g}: {'within noise of ' + self.reference + ' on every KPI and parameter set' if self.passes(g) else 'differs or too few runs: see the rows'}")
        return "\n".join(lines)


def _welch(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """95 % interval of mean(b) - mean(a) by Welch's t (the difference itself when neither varies)."""
    if a.var() == 0 and b.var() == 0:
        d = float(b.mean() - a.mean())
        return d, d
    ci = stats.ttest_ind(b, a, equal_var=False).confidence_interval(0.95)
    return float(ci.low), float(ci.high)


def geometry_comparison(values: Mapping[str, Mapping[str, np.ndarray]], kpi_names: Sequence[str],
                        cost_per_run_s: Mapping[str, float], *, lab_margins: Mapping[str, float] | None = None
                        ) -> GeometryComparison:
    """Compare geometries with the first one (see the module docstring).

    Args:
        values: parameter set -> geometry -> ``[runs, n_kpi]`` KPI values (NaN for failures);
            every parameter set has the same geometries, the reference first.
        kpi_names: the KPI columns. cost_per_run_s: geometry -> mean wall time per run, s.
        lab_margins: KPI -> the lab's 95 % CI half-width (optional).
    """
    if not values:
        raise ConfigError("geometry_comparison: no parameter set given")
    geometries = [list(v) for v in values.values()]
    if any(g != geometries[0] for g in geometries) or len(geometries[0]) < 2:
        raise ConfigError(f"geometry_comparison: every parameter set needs the same >= 2 geometries, got {geometries}")
    reference, *others = geometries[0]
    margins = dict(lab_margins or {})
    rows = []
    for pset, by_geometry in values.items():
        ref = np.asarray(by_geometry[reference], dtype=float)
        for g in others:
            cur = np.asarray(by_geometry[g], dtype=float)
            if ref.ndim != 2 or cur.ndim != 2 or ref.shape[1] != len(kpi_names) or cur.shape[1] != len(kpi_names):
                raise ConfigError(f"geometry_comparison: values of {pset}/{g} must be [runs, {len(kpi_names)}]")
            for j, kpi in enumerate(kpi_names):
                a, b = ref[:, j][np.isfinite(ref[:, j])], cur[:, j][np.isfinite(cur[:, j])]
                sd = lambda x: float(x.std(ddof=1)) if x.size >= 2 else math.nan  # noqa: E731
                mean = lambda x: float(x.mean()) if x.size else math.nan  # noqa: E731
                if a.size >= 2 and b.size >= 2:
                    lo, hi = _welch(a, b)
                    verdict = "within noise" if lo <= 0 <= hi else "differs"
                else:
                    lo = hi = math.nan
                    verdict = "too few runs"
                diff = mean(b) - mean(a)
                rows.append(KPIDifference(parameter_set=pset, geometry=g, kpi=kpi, n_ref=int(a.size), n=int(b.size),
                                          mean_ref=mean(a), mean=mean(b), sd_ref=sd(a), sd=sd(b), difference=diff,
                                          ci_low=lo, ci_high=hi,
                                          relative=diff / abs(mean(a)) if a.size and mean(a) != 0 else math.nan,
                                          lab_margin=float(margins.get(kpi, math.nan)), verdict=verdict))
    return GeometryComparison(reference=reference, rows=tuple(rows),
                              cost_per_run_s={g: float(cost_per_run_s.get(g, math.nan)) for g in geometries[0]})
