"""Where a discovery campaign stands, read from its store alone: no DEM run, no GP.

A discovery on the lab geometry takes days on a 2-core machine, and ``torchdem-discover`` scores
the candidates only once every one of them has run. What the store already holds answers part of
the question earlier:

* each candidate's design: per condition, how many runs are done and the span of every KPI over
  the design points, beside the measurement (can the candidate reach the lab at all?), and the
  mean over the design points less the calibrated set's mean, with its standard error (does the
  candidate move the KPI at all, on average over its prior?), and a least-squares plane of every
  KPI through the design points on the candidate's parameters (which way, and how far per unit,
  does each parameter push the KPI?);
* each candidate's held-out runs: per left-out condition, the parameters fitted without it, the
  KPI means, their z against the measurement and the condition's chi^2, beside the calibrated
  model's chi^2 on the same condition (does the candidate predict what it was not fitted to?).

Contract: :func:`discovery_status` ``(store path, measured data, KPIs) -> DiscoveryStatus``;
:func:`format_status` turns it into markdown (``scripts/discovery_status.py``). The z and chi^2
are those of the pipeline (``bo.discovery.verdict.cells_of``) with the DEM replicate noise pooled
over the calibrated set's runs and every held-out condition's runs in the store; the pipeline's
final score pools over every run of every candidate, so its figures can differ slightly. Runs
whose discharge jammed are left out of every figure and counted, as the pipeline does
(``kpi.loadcell.discharge_jammed``). The store is opened read-only, so a running campaign is not
disturbed.
"""
from __future__ import annotations

import dataclasses
import json
import math
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from bo.campaign.progress import open_read_only
from bo.discovery.pipeline import _lab, jam_counts
from bo.discovery.verdict import Cell, cells_of
from kpi.loadcell import discharge_jammed
from bo.discovery.replicate_noise import ReplicateNoise
from bo.screening.effects import least_squares
from torchdem.measured import MeasuredData

STAGE_PREFIX = "discovery-"


@dataclass(frozen=True)
class DesignSpan:
    """A candidate's design runs on one condition.

    Attributes:
        runs: runs done. spans: per KPI, (min, max) over the design points' means.
        shifts: per KPI with at least 2 design points and a calibrated-set mean, (mean over the
            design points - the calibrated set's mean, its standard error): ``sqrt(s_d^2 / n_d +
            s^2 / n_c)`` with ``s_d`` the sample sd of the ``n_d`` design points' means (it holds the
            prior's spread as well as the DEM noise) and ``s`` the pooled replicate noise of the
            calibrated set's ``n_c`` runs.
        slopes: per KPI, per parameter varied over the design points, (slope, standard error) of an
            ordinary least-squares plane through the design points' means (an intercept and one
            slope per parameter; only with more points than coefficients), KPI units per unit of
            the parameter. plane_sd: per KPI, that plane's residual sd (compare the DEM noise).
    """

    candidate: str
    condition: str
    runs: int
    spans: Mapping[str, tuple[float, float]]
    shifts: Mapping[str, tuple[float, float]] = dataclasses.field(default_factory=dict)
    jammed: int = 0  # runs done whose discharge jammed (not in runs, spans or shifts)
    slopes: Mapping[str, Mapping[str, tuple[float, float]]] = dataclasses.field(default_factory=dict)
    plane_sd: Mapping[str, float] = dataclasses.field(default_factory=dict)


@dataclass(frozen=True)
class HeldOutStatus:
    """A candidate's runs on a condition left out of its fit.

    Attributes:
        parameters: the candidate's parameters fitted without the condition (those not in the
            calibrated set's runs). runs: runs done. cells: one per measured KPI.
        chi2: sum of z^2 over the cells. baseline_chi2: the same for the calibrated set's runs.
    """

    candidate: str
    condition: str
    parameters: Mapping[str, float]
    runs: int
    cells: tuple[Cell, ...]
    chi2: float
    baseline_chi2: float
    jammed: int = 0  # runs done whose discharge jammed (not in runs or cells)


@dataclass(frozen=True)
class DiscoveryStatus:
    """What a discovery store holds (see the module docstring); ``counts``: stage -> status -> runs."""

    path: str
    kpis: tuple[str, ...]
    baseline: tuple[Cell, ...]
    noise: ReplicateNoise
    designs: tuple[DesignSpan, ...]
    held_out: tuple[HeldOutStatus, ...]
    counts: Mapping[str, Mapping[str, int]]
    baseline_jammed: Mapping[str, int] = dataclasses.field(default_factory=dict)  # condition -> jammed runs


def _replicates(runs: Sequence[Mapping[str, float]], kpis: Sequence[str]) -> np.ndarray:
    """``[r, K]`` KPI values of runs (NaN where not measured)."""
    out = np.array([[float(k.get(name, math.nan)) for name in kpis] for k in runs], dtype=np.float64).reshape(-1, len(kpis))
    out[~np.isfinite(out)] = np.nan
    return out


def _mean(values: Sequence[float]) -> float:
    """Mean of the finite values (NaN if none)."""
    finite = [v for v in values if math.isfinite(v)]
    return sum(finite) / len(finite) if finite else math.nan


def _chi2(cells: Sequence[Cell]) -> float:
    return float(sum(c.z ** 2 for c in cells if math.isfinite(c.z)))


def _shifts(means: np.ndarray, base: np.ndarray | None, noise: ReplicateNoise,
            kpis: Sequence[str]) -> dict[str, tuple[float, float]]:
    """Per KPI, (mean of the design points' means - the calibrated set's mean, its standard error)
    (:class:`DesignSpan`); KPIs with fewer than 2 design points or no calibrated-set run are left out."""
    out = {}
    for j, k in enumerate(kpis):
        d = means[:, j][np.isfinite(means[:, j])]
        c = base[:, j][np.isfinite(base[:, j])] if base is not None and len(base) else np.empty(0)
        if len(d) < 2 or len(c) == 0:
            continue
        se = math.sqrt(float(np.var(d, ddof=1)) / len(d) + noise.variance(k) / len(c))
        out[k] = (float(d.mean() - c.mean()), se)
    return out


def _planes(params: Sequence[Mapping[str, float]], means: np.ndarray, kpis: Sequence[str]):
    """Per KPI, the least-squares plane of the design points' means on the parameters that vary
    over them (:class:`DesignSpan`): ``({kpi: {parameter: (slope, se)}}, {kpi: residual sd})``."""
    shared = set.intersection(*(set(p) for p in params)) if params else set()
    names = sorted(k for k in shared if not math.isclose(min(float(q[k]) for q in params),
                                                         max(float(q[k]) for q in params)))
    slopes, sds = {}, {}
    if not names:
        return slopes, sds
    X = np.array([[1.0] + [float(p[n]) for n in names] for p in params])
    for j, k in enumerate(kpis):
        ok = np.isfinite(means[:, j])
        fit = least_squares(X[ok], means[ok, j])
        if fit is None:  # too few points for a plane, or parameters that move together
            continue
        beta, se, s2, _ = fit
        slopes[k] = {n: (float(beta[i + 1]), float(se[i + 1])) for i, n in enumerate(names)}
        sds[k] = math.sqrt(s2)
    return slopes, sds


def discovery_status(path: str | Path, measured: MeasuredData, kpis: Sequence[str]) -> DiscoveryStatus:
    """The store's discrepancy, design and held-out runs against ``measured`` (module docstring)."""
    kpis = tuple(kpis)
    conn = open_read_only(Path(path), "discovery_status")
    try:
        rows = conn.execute("SELECT stage, batch_key, point_index, params, condition, status, kpis "
                            "FROM evaluations ORDER BY task_id").fetchall()
    finally:
        conn.close()
    counts: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
    baseline_runs: dict[str, list] = defaultdict(list)
    design: dict[tuple[str, str], dict[tuple[str, int], list]] = defaultdict(lambda: defaultdict(list))
    design_params: dict[tuple[str, str], dict[tuple[str, int], dict[str, float]]] = defaultdict(dict)
    held: dict[tuple[str, str], list] = defaultdict(list)
    params_of: dict[tuple[str, str], dict[str, float]] = {}
    calibrated: dict[str, float] = {}
    jams: dict[tuple[str, str, str], int] = defaultdict(int)  # (what, candidate, condition) -> jammed runs
    for stage, key, point, params, condition, status, values in rows:
        counts[stage][status] += 1
        if status != "done" or values is None:
            continue
        values = {k: math.nan if v is None else float(v) for k, v in json.loads(values).items()}  # null: not measured
        if discharge_jammed(values):
            name = stage[len(STAGE_PREFIX):] if stage.startswith(STAGE_PREFIX) else ""
            what = "baseline" if stage == "discrepancy" else ("held" if key.startswith("held-out/") else "design")
            jams[(what, name, condition)] += 1
            if what == "held":
                params_of[(name, condition)] = json.loads(params)
                held.setdefault((name, condition), [])
            elif what == "design":
                design[(name, condition)]  # listed, though every run of it may have jammed
            continue
        if stage == "discrepancy":
            baseline_runs[condition].append(values)
            calibrated.update(json.loads(params))
        elif stage.startswith(STAGE_PREFIX):
            name = stage[len(STAGE_PREFIX):]
            if key.startswith("held-out/"):
                held[(name, condition)].append(values)
                params_of[(name, condition)] = json.loads(params)
            else:  # the design (lhs/...) and its refinement rounds (refine/...)
                design[(name, condition)][(key, point)].append(values)
                design_params[(name, condition)][(key, point)] = json.loads(params)
    conditions = list(measured.names)
    lab = _lab(measured, kpis)
    baseline = {c: _replicates(baseline_runs.get(c, []), kpis) for c in conditions}
    held_reps = {k: _replicates(v, kpis) for k, v in held.items()}
    groups = [v for v in baseline.values() if len(v) >= 2] + [v for v in held_reps.values() if len(v) >= 2]
    noise = ReplicateNoise.of(kpis, groups) if groups else ReplicateNoise(kpis, (0.0,) * len(kpis), (0,) * len(kpis))
    base_cells = {c: cells_of(baseline[c][None], [c], kpis, lab, noise) for c in conditions}
    order = {c: i for i, c in enumerate(conditions)}

    def in_order(items):  # by candidate, then in the data's order of conditions
        return sorted(items, key=lambda kv: (kv[0][0], order.get(kv[0][1], len(order)), kv[0][1]))

    designs = []
    for (name, condition), points in in_order(design.items()):
        means = _replicates([{k: _mean([run.get(k, math.nan) for run in runs]) for k in kpis}
                             for runs in points.values()], kpis)
        spans = {k: (float(np.nanmin(means[:, j])), float(np.nanmax(means[:, j])))
                 for j, k in enumerate(kpis) if len(means) and np.isfinite(means[:, j]).any()}
        slopes, plane_sd = _planes([design_params[(name, condition)][p] for p in points], means, kpis)
        designs.append(DesignSpan(name, condition, sum(len(r) for r in points.values()), spans,
                                  _shifts(means, baseline.get(condition), noise, kpis),
                                  jams.get(("design", name, condition), 0), slopes, plane_sd))
    held_out = []
    for (name, condition), reps in in_order(held_reps.items()):
        if condition not in conditions:
            continue
        cells = tuple(cells_of(reps[None], [condition], kpis, lab, noise))
        fitted = {k: v for k, v in params_of[(name, condition)].items()
                  if k not in calibrated or not math.isclose(v, calibrated[k], rel_tol=1e-9)}
        held_out.append(HeldOutStatus(name, condition, fitted, len(reps), cells, _chi2(cells),
                                      _chi2(base_cells[condition]), jams.get(("held", name, condition), 0)))
    return DiscoveryStatus(str(path), kpis, tuple(c for cs in base_cells.values() for c in cs), noise,
                           tuple(designs), tuple(held_out), {s: dict(v) for s, v in counts.items()},
                           {c: n for (what, _, c), n in jams.items() if what == "baseline"})


def format_status(status: DiscoveryStatus, measured: MeasuredData) -> str:
    """Markdown: runs per stage, the calibrated set's cells, each candidate's design spans and held-out cells."""
    lab = _lab(measured, status.kpis)
    lines = [f"## {status.path}", ""]
    for stage, c in status.counts.items():
        lines.append(f"- {stage}: " + ", ".join(f"{n} {state}" for state, n in sorted(c.items())))
    sd = ", ".join(f"{k} {v['sd']:.3g} ({v['dof']})" for k, v in status.noise.to_dict().items())
    lines += ["", f"DEM replicate noise, sd (degrees of freedom), pooled over the calibrated set's and the held-out "
              f"runs: {sd}", ""]
    head = "| condition | " + " | ".join(status.kpis) + " | chi^2 |"
    rule = "| --- |" + " ---: |" * (len(status.kpis) + 1)
    lines += ["### The calibrated set (DEM mean, z against the measurement)", "", head, rule]
    by_condition: dict[str, list[Cell]] = defaultdict(list)
    for c in status.baseline:
        by_condition[c.condition].append(c)
    for condition, cells in by_condition.items():
        lines.append(f"| {condition} | " + " | ".join(_cell(cells, k) for k in status.kpis) + f" | {_chi2(cells):.1f} |")
    if status.baseline_jammed:
        lines += ["", "Runs of the calibrated set whose discharge jammed, left out: "
                  + jam_counts(status.baseline_jammed)]
    for name in sorted({d.candidate for d in status.designs} | {h.candidate for h in status.held_out}):
        lines += ["", f"### {name}", ""]
        spans = [d for d in status.designs if d.candidate == name]
        if spans:
            lines += ["Design: runs done and each KPI's range over the design points (the measurement in brackets).", "",
                      "| condition | runs | " + " | ".join(status.kpis) + " |",
                      "| --- | ---: |" + " ---: |" * len(status.kpis)]
            for d in spans:
                lines.append(f"| {d.condition} | {d.runs}{_jammed_note(d.jammed)} | " + " | ".join(
                    (f"{d.spans[k][0]:.4g}-{d.spans[k][1]:.4g}" if k in d.spans else "-")
                    + (f" ({lab[(d.condition, k)][0]:.4g})" if (d.condition, k) in lab else "") for k in status.kpis)
                    + " |")
            lines += ["", "Design mean less the calibrated set's (its standard error): what the candidate does on "
                      "average over its prior.", "",
                      "| condition | " + " | ".join(status.kpis) + " |", "| --- |" + " ---: |" * len(status.kpis)]
            for d in spans:
                lines.append(f"| {d.condition} | " + " | ".join(
                    f"{d.shifts[k][0]:+.3g} ({d.shifts[k][1]:.2g})" if k in d.shifts else "-" for k in status.kpis)
                    + " |")
            planes = [d for d in spans if d.slopes]
            if planes:
                lines += ["", "A least-squares plane through the design points: each KPI's change per unit of each "
                          "parameter (its standard error), and the plane's residual sd (compare the DEM noise above).",
                          "", "| condition | per unit of | " + " | ".join(status.kpis) + " |",
                          "| --- | --- |" + " ---: |" * len(status.kpis)]
                for d in planes:
                    for n in sorted({n for v in d.slopes.values() for n in v}):
                        lines.append(f"| {d.condition} | {n} | " + " | ".join(
                            f"{d.slopes[k][n][0]:+.3g} ({d.slopes[k][n][1]:.2g})" if k in d.slopes else "-"
                            for k in status.kpis) + " |")
                    lines.append(f"| {d.condition} | residual sd | " + " | ".join(
                        f"{d.plane_sd[k]:.3g}" if k in d.plane_sd else "-" for k in status.kpis) + " |")
        held = [h for h in status.held_out if h.candidate == name]
        if held:
            lines += ["", "Held out: each condition run with the parameters fitted without it (DEM mean, z); "
                      "chi^2 against the calibrated set's on the same condition.", "",
                      "| condition | fitted without it | runs | " + " | ".join(status.kpis)
                      + " | chi^2 | calibrated set's chi^2 |",
                      "| --- | --- | ---: |" + " ---: |" * (len(status.kpis) + 2)]
            for h in held:
                fitted = ", ".join(f"{k} {v:.4g}" for k, v in sorted(h.parameters.items())) or "-"
                lines.append(f"| {h.condition} | {fitted} | {h.runs}{_jammed_note(h.jammed)} | "
                             + " | ".join(_cell(h.cells, k) for k in status.kpis)
                             + f" | {h.chi2:.1f} | {h.baseline_chi2:.1f} |")
            lines.append(f"| all {len(held)} conditions | | | " + " | " * (len(status.kpis) - 1)
                         + f" | {sum(h.chi2 for h in held):.1f} | {sum(h.baseline_chi2 for h in held):.1f} |")
    return "\n".join(lines) + "\n"


def _jammed_note(n: int) -> str:
    return f" (+{n} jammed)" if n else ""


def _cell(cells: Sequence[Cell], kpi: str) -> str:
    c = next((c for c in cells if c.kpi == kpi), None)
    if c is None or not math.isfinite(c.dem_mean):
        return "-"
    return f"{c.dem_mean:.4g} ({c.z:+.2f})" if math.isfinite(c.z) else f"{c.dem_mean:.4g}"
