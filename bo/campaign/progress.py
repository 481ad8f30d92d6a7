"""How far a campaign store has come, and what the rest of it will cost.

Contract
--------
``store_progress(path)`` reads a campaign store (``bo.campaign.store``; read-only, the file is
never written) and returns a ``StoreProgress``: its tasks per status, the worker time its
finished runs took, and an estimate of the worker time its unfinished ones will take. Runs are
grouped into cost classes, since a run's cost is set by its geometry and particle shape, not by
its friction: a class is the geometry part of the condition (``"mirror=True|slice_depth=0.1"``,
empty for the condition's own geometry) and the task's particle shape: its ``lobe_spacing_*``
and ``clump_scale_*`` parameters, each rounded to the nearest ``SHAPE_BIN``, so that the continuous
values a surrogate or a discovery fit proposes share classes. A flatter trilobe has smaller lobes,
more clumps per kilogram and a shorter Rayleigh step: a lab-geometry run at lobe spacing 0.3 costs
about 4x one at 0.15. A larger clump scale has fewer, larger grains: at 1.32 a lab run had half
the spheres and cost about 0.6 of one at 1. The densities change the step by sqrt(rho) only (about 5 % over the lab surrogate's
+-10 %), so they do not split classes.

Cost of a finished run, in worker seconds: its stored ``wall_time`` divided by the number of runs
finished in the same batch (rows written by one ``record`` call share their owner, finish time
and wall time), so a batch of two members counts half its wall time per run. Rows that took
another run's result (``reused:``) cost nothing and are left out. A store copied from another
(``copy_store``, as ``store_from`` seeds a campaign) notes which rows came with the copy: their cost
stays a figure of their class, but they were made, and are counted as spent, in the source store
(``RunCost.copied``; ``StoreProgress.copied_runs``), so that a sum over stores counts each run once.

Estimate of an unfinished run: the median cost of its class's finished runs. A class without
any takes the median of the nearest class of the same geometry (summed relative difference of the
lobe spacings and clump scales) and is marked ``borrowed``. The cost grows steeply with the lobe
spacing and falls with the clump scale, so a figure borrowed from a cheaper class (smaller spacings,
larger scales) is a lower bound (``bound = "at least"``), one from a costlier class an upper bound
(``"at most"``), not an estimate; the store's total left is then a bound of the same kind
(``"roughly"`` if both kinds enter).
Unfinished rows of the same run (stage, parameters, seed, condition) count once. Runs in
``failed`` are not counted as remaining (``reset_failed`` re-queues them).

Stages a campaign has not reached yet have no rows, so they are not in the estimate: a
calibration's surrogate rounds, verification and validation appear once the stage starts.
"""
from __future__ import annotations

import json
import sqlite3
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from statistics import median
from typing import Sequence

from bo.campaign.store import (COPIED_FROM, RECORD_COLUMNS, EvaluationRecord, affinity_distance, open_read_only,
                               record_from_row, reused_from)
from kpi.loadcell import discharge_jammed, discharge_state
from torchdem.errors import ConfigError

__all__ = ["SHAPE_BIN", "CostClass", "RunCost", "StoreProgress", "run_costs", "store_progress"]

#: The particle-shape parameters that set a run's cost, and which way: +1 costlier as the value grows
#: (a larger lobe spacing, smaller lobes: more spheres and a shorter step), -1 cheaper (a larger
#: clump scale: fewer, larger grains at the same mass).
_SHAPE_COST = {"lobe_spacing_": 1.0, "clump_scale_": -1.0}
#: Width of a cost class in lobe spacing (a fraction of the sieve size) and in clump scale.
SHAPE_BIN = 0.025


def _shape(params: dict) -> tuple[tuple[str, float], ...]:
    return tuple(sorted((k, round(round(float(v) / SHAPE_BIN) * SHAPE_BIN, 6)) for k, v in params.items()
                        if k.startswith(tuple(_SHAPE_COST))))


def _cost_order(shape: tuple[tuple[str, float], ...]) -> float:
    """How costly a class's shape is, up to a monotone map: its values, each signed by ``_SHAPE_COST``."""
    return sum(next(sign for p, sign in _SHAPE_COST.items() if k.startswith(p)) * v for k, v in shape)


@dataclass(frozen=True)
class CostClass:
    """The runs of one geometry and particle shape.

    Attributes:
        geometry: the geometry part of the condition ("" for the condition's own geometry).
        shape: ``(name, value)`` pairs of the ``lobe_spacing_*`` and ``clump_scale_*`` parameters (to
            the nearest ``SHAPE_BIN``), sorted by name.
        done: runs finished (their own, not reused).
        remaining: distinct runs pending or running.
        failed: runs failed.
        seconds_per_run: median worker seconds of a finished run of the class (or of the nearest
            class if ``borrowed``); None if no class of this geometry has a finished run.
        borrowed: whether ``seconds_per_run`` comes from another class.
        bound: ``""`` (the class's own median), ``"at least"`` or ``"at most"`` (borrowed from a
            class of smaller or larger lobe spacings).
    """

    geometry: str
    shape: tuple[tuple[str, float], ...]
    done: int
    remaining: int
    failed: int
    seconds_per_run: float | None
    borrowed: bool
    bound: str = ""

    @property
    def label(self) -> str:
        shape = ", ".join(f"{k} {v:g}" for k, v in self.shape) or "default shape"
        return f"{self.geometry} {shape}".strip() if self.geometry else shape


@dataclass(frozen=True)
class StoreProgress:
    """Progress of one store.

    Attributes:
        path: the store file.
        status: stage -> status -> number of rows (reused rows included, as stored).
        classes: the cost classes, by geometry and then lobe spacings.
        spent_s: worker seconds of every finished run (failed ones included) made in this store.
        remaining_s: estimated worker seconds of the unfinished runs; None if a class with
            remaining runs has no cost figure at all.
        remaining_bound: ``""`` (an estimate), ``"at least"``, ``"at most"`` or ``"roughly"``
            (classes with remaining runs borrowed their figure, see ``CostClass.bound``).
        discharge: of the done runs, how many ended their discharge (``"ended"``), stopped while
            the upper box still emptied (``"not ended"``: their lower-box mass and photos are not
            the lab's end state), or made before runs recorded it (``"not recorded"``); and how
            many of them jammed (``"jammed"``: less than ``torchdem.drawdown.JAM_FRACTION`` of the
            fill left the upper box).
        batches: stage -> batch key -> status -> number of rows (a stage of several batches holds
            designs asked for before, e.g. an initial design whose bounds then changed).
        copied_from: the store this one was copied from (``bo.campaign.store.copy_store``), else None.
        copied_runs, copied_s: the finished runs that came with that copy and their worker seconds:
            made there, they are counted there and not in ``spent_s``.
    """

    path: str
    status: dict[str, dict[str, int]]
    classes: tuple[CostClass, ...]
    spent_s: float
    remaining_s: float | None
    remaining_bound: str = ""
    discharge: dict[str, int] = field(default_factory=dict)
    batches: dict[str, dict[str, dict[str, int]]] = field(default_factory=dict)
    copied_from: str | None = None
    copied_runs: int = 0
    copied_s: float = 0.0

    @property
    def remaining_runs(self) -> int:
        return sum(c.remaining for c in self.classes)


def finished_runs(path: Path, source: str = "store_progress") -> list[tuple[str, str, int, dict, dict]]:
    """``(stage, condition, seed, parameters, KPIs)`` of every finished run of a store, in task order, read
    only: the numeric parameters as floats, the KPIs as floats (a KPI stored as null is NaN)."""
    return [(r.stage, r.condition, int(r.seed),
             {n: float(v) for n, v in r.params.items() if isinstance(v, (int, float))}, r.kpis)
            for r in done_records(path, None, source)]


def done_records(path: Path, stage: str | None = None, source: str = "store_progress") -> list[EvaluationRecord]:
    """Every finished run (of ``stage``; None: of every stage) in a store, as records, in task order,
    read only (a shipped or running store is not written, and no config hash is asked for: the caller
    compares :func:`config_hash_of` with its own)."""
    where, args = ("", ()) if stage is None else (" AND stage = ?", (stage,))
    conn = open_read_only(path, source)
    try:
        rows = conn.execute(f"SELECT {RECORD_COLUMNS} FROM evaluations WHERE status = 'done' AND kpis IS NOT NULL"
                            f"{where} ORDER BY task_id", args).fetchall()
    finally:
        conn.close()
    return [record_from_row(r) for r in rows]


def config_hash_of(path: Path, source: str = "store_progress") -> str | None:
    """The config hash a store was created with, read only."""
    conn = open_read_only(path, source)
    try:
        row = conn.execute("SELECT value FROM meta WHERE key = 'config_hash'").fetchone()
    finally:
        conn.close()
    return None if row is None else row[0]


def check_same_model(path: Path, hashes: Sequence[str], source: str = "store_progress") -> None:
    """Refuse a store whose runs are of another model than ``hashes`` (the hashes of the model that
    would read them as its own, ``bo.cli.common.store_hashes``), naming them; read only."""
    stored = config_hash_of(path, source)
    if stored not in hashes:
        raise ConfigError(f"{source}: {path} has config hash {stored!r}, this model's "
                          f"{' or '.join(map(repr, hashes))}: its runs are of another model")


@dataclass(frozen=True)
class RunCost:
    """One row of a store with its cost.

    Attributes:
        stage, condition, state: the row's. seconds: worker seconds of the run (its ``wall_time``
            over the runs finished in the same batch); None for a row that has not finished or that
            took another run's result (``reused:``, ``imported:``: no wall time).
    """

    stage: str
    condition: str
    state: str
    seconds: float | None
    copied: bool = False


_COLUMNS = "stage, params, seed, condition, status, wall_time, claimed_by, finished_at, kpis, task_id"


def _read_rows(conn: sqlite3.Connection) -> list[tuple]:
    return conn.execute(f"SELECT {_COLUMNS} FROM evaluations ORDER BY task_id").fetchall()


def copied_from(conn: sqlite3.Connection) -> tuple[str | None, int]:
    """``(source, last_task_id)`` of a store made by ``bo.campaign.store.copy_store`` (its rows up to
    ``last_task_id`` came with the copy), else ``(None, 0)``."""
    row = conn.execute("SELECT value FROM meta WHERE key = ?", (COPIED_FROM,)).fetchone()
    if row is None:
        return None, 0
    note = json.loads(row[0])
    return str(note["source"]), int(note["last_task_id"])


def _costs(rows: list[tuple]) -> list[float | None]:
    """Worker seconds of each row (``RunCost.seconds``): rows written by one ``record`` call share
    their owner, finish time and wall time, and split the wall time."""
    batch_size: dict[tuple, int] = defaultdict(int)
    counted = [state in ("done", "failed") and wall is not None and reused_from(owner) is None
               for _, _, _, _, state, wall, owner, _, _, _ in rows]
    for row, yes in zip(rows, counted):
        if yes:
            batch_size[row[6], row[7], row[5]] += 1
    return [row[5] / batch_size[row[6], row[7], row[5]] if yes else None for row, yes in zip(rows, counted)]


def run_costs(path: str | Path) -> tuple[RunCost, ...]:
    """Every row of the store at ``path`` (read only) with its worker seconds, in task order."""
    conn = open_read_only(Path(path), "run_costs")
    try:
        rows = _read_rows(conn)
        _, last = copied_from(conn)
    finally:
        conn.close()
    return tuple(RunCost(stage, condition, state, cost, task_id <= last)
                 for (stage, _, _, condition, state, *_, task_id), cost in zip(rows, _costs(rows)))


def store_progress(path: str | Path) -> StoreProgress:
    """Tasks per status, worker time spent and the estimated worker time left in a store."""
    path = Path(path)
    conn = open_read_only(path)
    try:
        rows = _read_rows(conn)
        source, last = copied_from(conn)
        keyed = conn.execute("SELECT stage, batch_key, status, COUNT(*) FROM evaluations "
                             "GROUP BY stage, batch_key, status ORDER BY MIN(task_id)").fetchall()
    finally:
        conn.close()
    status: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
    discharge = dict.fromkeys(("ended", "not ended", "not recorded", "jammed"), 0)
    for stage, _, _, _, state, _, _, _, kpis, _ in rows:
        status[stage][state] += 1
        if state == "done":
            k = json.loads(kpis or "{}")
            discharge[discharge_state(k)] += 1
            discharge["jammed"] += discharge_jammed(k)
    costs: dict[tuple, list[float]] = defaultdict(list)
    counts: dict[tuple, dict[str, int]] = {}  # every class seen, with its runs done and failed
    unfinished: dict[tuple, set] = defaultdict(set)
    spent = copied_s = 0.0
    copied_runs = 0
    for (stage, params, seed, condition, state, *_, task_id), cost in zip(rows, _costs(rows)):
        geometry = condition.partition("|")[2]
        key = (geometry, _shape(json.loads(params)))
        counts.setdefault(key, {"done": 0, "failed": 0})
        if state in ("pending", "running"):
            unfinished[key].add((stage, params, seed, condition))
        elif cost is not None:
            if task_id <= last:
                copied_s, copied_runs = copied_s + cost, copied_runs + 1
            else:
                spent += cost
            counts[key][state] += 1
            if state == "done":
                costs[key].append(cost)
    classes, remaining = [], 0.0
    for key in sorted(counts, key=lambda k: (k[0], [v for _, v in k[1]])):
        per_run, bound = (median(costs[key]), "") if costs[key] else (None, "")
        if per_run is None:
            near = [k for k, v in costs.items() if v and k[0] == key[0]]
            if near:
                nearest = min(near, key=lambda k: (affinity_distance(key[1], k[1]), [v for _, v in k[1]]))
                per_run = median(costs[nearest])
                cheaper = _cost_order(nearest[1]) < _cost_order(key[1])
                bound = "at least" if cheaper else "at most"
        n_left = len(unfinished[key])
        classes.append(CostClass(key[0], key[1], counts[key]["done"], n_left, counts[key]["failed"], per_run,
                                 bool(bound), bound))
        if n_left:
            remaining = None if remaining is None or per_run is None else remaining + n_left * per_run
    bounds = {c.bound for c in classes if c.remaining and c.bound}
    total_bound = "" if not bounds else bounds.pop() if len(bounds) == 1 else "roughly"
    batches: dict[str, dict[str, dict[str, int]]] = {}
    for stage, key, state, n in keyed:
        batches.setdefault(stage, {}).setdefault(key, {})[state] = n
    return StoreProgress(str(path), {s: dict(v) for s, v in status.items()}, tuple(classes), spent, remaining,
                         total_bound, discharge, batches, source, copied_runs, copied_s)
