"""The gap between two KPIs of one test, the lab's against every run a model has made.

A calibration matches KPIs one at a time; a model can still be unable to produce the lab's
*combination* of two of them. The draw down's case: the shear angle (the face the upper box keeps,
a static slope in a confined box) and the angle of repose (the heap poured into the lower box). In
the lab the face stands higher above the heap the more sinter the mixture holds; if no run of the
model, over every parameter set and candidate mechanism it was ever run with, stands its face that
far above its heap, the mismatch is in the model's structure, not in a value a campaign could find.

    G = KPI_a - KPI_b      (per run; by default shear angle - angle of repose, deg)

Contract:

* :func:`lab_gap` ``(measured data, kpi_a, kpi_b) -> {condition: (G, half-width)}``: the lab's G
  and a 95 % half-width that assumes nothing about how the two KPIs' errors correlate (the sum of
  the two CIs' half-widths: the measurements of one test are not independent, and Table 2 gives no
  covariance), conditions with both KPIs only.
* :func:`gap_check` ``(store paths, measured data, kpi_a, kpi_b) -> GapCheck``: per condition, G of
  every finished run in the stores that did not jam and has both KPIs (a run two stores hold, as a
  probe's or a discovery's copy of its base, counted once: same condition, seed and values), and the
  runs with *both* KPIs inside the lab's own 95 % CIs (a criterion that needs no covariance). A KPI name that no run of
  the stores has raises :class:`~torchdem.errors.ConfigError` naming it and the KPIs they have.
* ``GapCheck.to_dict()`` the same as plain data (the discovery report's ``gap``);
  ``GapCheck.out_of_reach()`` the lab's conditions where no run has both KPIs inside the lab's CIs.
* :func:`format_gap` turns it into markdown (``scripts/gap_check.py``); with ``by_stage`` also G
  per stage and condition, so a discovery store shows which candidate's runs moved it; with
  ``by_batch`` per stage and batch, so a probe store shows each of its sets.

Stores are opened read-only, so a running campaign is not disturbed.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from bo.campaign.progress import done_records
from kpi.loadcell import discharge_jammed
from torchdem.errors import ConfigError
from torchdem.measured import MeasuredData

#: The default pair: the face the upper box keeps above the heap poured into the lower box.
FACE_ABOVE_HEAP = ("shear_angle_deg", "angle_of_repose_deg")


@dataclass(frozen=True)
class GapRun:
    """One finished run: its store, stage, condition, the two KPIs, G = a - b and its batch (a probe
    store's set name)."""

    store: str
    stage: str
    condition: str
    a: float
    b: float
    batch: str = ""

    @property
    def gap(self) -> float:
        return self.a - self.b


@dataclass(frozen=True)
class GapCheck:
    """``means``: condition -> (lab mean of a, of b); ``ci``: condition -> (CI of a, CI of b), the lab's
    95 % half-widths; ``runs``: the model's. ``lab`` (derived): condition -> (G, half-width)."""

    stores: tuple[str, ...]
    kpis: tuple[str, str]
    means: Mapping[str, tuple[float, float]]
    ci: Mapping[str, tuple[float, float]]
    runs: tuple[GapRun, ...]

    @property
    def lab(self) -> dict[str, tuple[float, float]]:
        """Condition -> (mean of a - mean of b, CI of a + CI of b)."""
        return _gaps(self.means, self.ci)

    def conditions(self) -> list[str]:
        """The lab's conditions, then any other the runs have, in order."""
        return list(dict.fromkeys([*self.lab, *(r.condition for r in self.runs)]))

    def model(self, condition: str) -> np.ndarray:
        """``[n]`` G of the model's runs at ``condition``."""
        return np.array([r.gap for r in self.runs if r.condition == condition])

    def reaching(self, condition: str) -> int:
        """Runs whose G is at or beyond the near end of the lab's band (NaN-free count; 0 without a lab value)."""
        lab = self.lab
        if condition not in lab:
            return 0
        g, half = lab[condition]
        model = self.model(condition)
        below = model.mean() < g if len(model) else True
        return int(np.sum(model >= g - half) if below else np.sum(model <= g + half))

    def both_inside(self, condition: str) -> int:
        """Runs with both KPIs inside the lab's own 95 % CIs at ``condition``."""
        if condition not in self.means:
            return 0
        (ma, mb), (ca, cb) = self.means[condition], self.ci[condition]
        return sum(1 for r in self.runs if r.condition == condition and abs(r.a - ma) <= ca and abs(r.b - mb) <= cb)

    def to_dict(self) -> dict:
        """Plain data (the discovery report's ``gap``): the KPIs, the stores and per condition the lab's G
        and band, the model's runs, median, range, runs reaching the band and runs with both inside."""
        per = {}
        for c in self.conditions():
            g = self.model(c)
            per[c] = {"lab": list(self.lab[c]) if c in self.lab else None, "runs": int(len(g)),
                      "median": float(np.median(g)) if len(g) else math.nan,
                      "min": float(g.min()) if len(g) else math.nan, "max": float(g.max()) if len(g) else math.nan,
                      "reaching": self.reaching(c), "both_inside": self.both_inside(c)}
        return {"kpis": list(self.kpis), "stores": list(self.stores), "conditions": per}

    def out_of_reach(self) -> list[str]:
        """The lab's conditions with runs where none has both KPIs inside the lab's CIs."""
        return [c for c in self.lab if len(self.model(c)) and not self.both_inside(c)]

    def by_stage(self, by_batch: bool = False) -> dict[tuple[str, str, str], np.ndarray]:
        """``(store, stage, condition) -> [n]`` G, in the order the stores list them; ``by_batch``: the
        stage's batch after it (``probe/combined``: a probe store's sets apart)."""
        out: dict[tuple[str, str, str], list[float]] = {}
        for r in self.runs:
            stage = f"{r.stage}/{r.batch}" if by_batch else r.stage
            out.setdefault((r.store, stage, r.condition), []).append(r.gap)
        return {k: np.array(v) for k, v in out.items()}


def _lab_pair(measured: MeasuredData, kpi_a: str, kpi_b: str) -> tuple[dict, dict]:
    """``(means, ci)``: condition -> (a, b) of the lab's means and 95 % half-widths, conditions with both."""
    means, ci = {}, {}
    for name in measured.names:
        k = measured.condition(name).kpis
        a, b = k.get(kpi_a), k.get(kpi_b)
        if a is not None and b is not None:
            means[name], ci[name] = (a.mean, b.mean), (a.ci95 or 0.0, b.ci95 or 0.0)
    return means, ci


def _gaps(means: Mapping[str, tuple[float, float]], ci: Mapping[str, tuple[float, float]]
          ) -> dict[str, tuple[float, float]]:
    return {c: (ma - mb, ci[c][0] + ci[c][1]) for c, (ma, mb) in means.items()}


def lab_gap(measured: MeasuredData, kpi_a: str = FACE_ABOVE_HEAP[0],
            kpi_b: str = FACE_ABOVE_HEAP[1]) -> dict[str, tuple[float, float]]:
    """Condition -> (mean of a - mean of b, CI of a + CI of b) (module docstring)."""
    return _gaps(*_lab_pair(measured, kpi_a, kpi_b))


def gap_check(stores: Sequence[str | Path], measured: MeasuredData, kpi_a: str = FACE_ABOVE_HEAP[0],
              kpi_b: str = FACE_ABOVE_HEAP[1]) -> GapCheck:
    """The lab's G and the model's over every run of ``stores`` that flowed (module docstring)."""
    runs, seen, held = [], set(), set()
    for s in stores:
        for r in done_records(Path(s), None, "gap_check"):
            k = {n: math.nan if v is None else float(v) for n, v in (r.kpis or {}).items()}
            seen.update(k)
            a, b = k.get(kpi_a, math.nan), k.get(kpi_b, math.nan)
            key = (r.condition, r.seed, a, b)
            if discharge_jammed(k) or not (math.isfinite(a) and math.isfinite(b)) or key in held:
                continue                # jammed, without the pair, or a copy of a run another store holds
            held.add(key)
            runs.append(GapRun(Path(s).name, r.stage, r.condition, a, b, r.batch_key))
    for name in (kpi_a, kpi_b):
        if seen and name not in seen:
            raise ConfigError(f"gap_check: KPI {name!r} is in no run of {', '.join(map(str, stores))}; "
                              f"their KPIs: {', '.join(sorted(seen))}")
    return GapCheck(tuple(str(s) for s in stores), (kpi_a, kpi_b), *_lab_pair(measured, kpi_a, kpi_b), tuple(runs))


def format_gap(check: GapCheck, by_stage: bool = False, heading: bool = True, by_batch: bool = False) -> str:
    """Markdown: per condition the lab's G and the model's over its runs, how many reach the lab's band
    and how many have both KPIs inside the lab's CIs; ``by_stage``: G per store and stage too
    (``by_batch``: per stage and batch, a probe store's sets apart);
    ``heading``: the section's own title first (a report that titles it itself leaves it out)."""
    a, b = check.kpis
    lines = ([f"## The gap {a} - {b}, the lab's against every run", ""] if heading else []) + [
             "Stores: " + ", ".join(check.stores), "",
             "The lab's band is the sum of the two CIs' half-widths (no assumption on how the two correlate).", "",
             "| condition | lab (95 % band) | model runs | model median | model range | runs reaching the band "
             "| runs with both KPIs inside the lab's CIs |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for c in check.conditions():
        lab = f"{check.lab[c][0]:.2f} +- {check.lab[c][1]:.2f}" if c in check.lab else "-"
        g = check.model(c)
        model = (f"{len(g)} | {np.median(g):.2f} | {g.min():.2f} to {g.max():.2f}" if len(g) else "0 | - | -")
        lines.append(f"| {c} | {lab} | {model} | {check.reaching(c)} | {check.both_inside(c)} |")
    if by_stage or by_batch:
        groups = check.by_stage(by_batch)
        lines += ["", "G per store and stage: median (max, runs)", "",
                  "| store | stage | condition | G |", "| --- | --- | --- | ---: |"]
        for (store, stage, c), g in groups.items():
            lines.append(f"| {store} | {stage} | {c} | {np.median(g):.2f} ({g.max():.2f}, {len(g)}) |")
    return "\n".join(lines) + "\n"
