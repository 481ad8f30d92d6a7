"""DEM evaluations of draw down tests for campaigns: the ``evaluate_batch`` of the executors.

Contract:
- :func:`evaluate_batch` runs a batch of :class:`~bo.campaign.executor.EvalTask` of one
  condition of a :class:`torchdem.model.DrawDownModel` as one batched ensemble
  (:meth:`torchdem.drawdown.DrawDownTest.run_members`): every distinct parameter set is a
  parameter set of the test, every task a member with its own seed. It returns one
  :class:`~bo.campaign.executor.EvalOutcome` per task with every KPI of
  :data:`torchdem.drawdown.KPI_UNITS` (NaN where the lab method could not measure it, e.g. no
  heap edge) and the wall time of the batch. The blow-up guard runs in isolate mode: a member
  that blows up is frozen and fails alone, with the guard's message. A member whose ensemble
  cannot be built (its fill overflows the column, its clump is too large for a periodic slice)
  fails alone too: when the ensemble's build fails, every member is built by itself, those
  that fail get their own error, and the others run as one ensemble. Bad input common to the
  batch fails the whole batch with the message. Tasks that set different box lengths
  (``geometry_*`` parameters) cannot share walls: a batch of several runs as one ensemble per
  set of lengths, in turn.
- With ``checkpoint_dir`` the ensemble saves its state every 0.5 s of simulated time to
  :func:`checkpoint_path` (a file named by the model, the condition and every task's parameters
  and seed) and, if that file exists when the batch starts, resumes from it: a campaign killed
  during a long run (a lab-geometry batch takes up to two hours on one core) loses at most
  0.5 s of simulated time of it, as long as the store hands the same tasks to one batch again
  (it claims pending tasks in the same order every time). The file is removed when the run ends.
  A resumed batch reports the wall time of the whole run, the part before the checkpoint included.
- A run that blows up is run again, alone (with the others of its batch that blew up), at the
  shorter time steps of the model's ``settings.retry_time_steps`` in turn (``sim.retry_time_steps``,
  e.g. 0.8 and 0.6 of the step), until one gets through; its outcome then carries the step it ran
  at as ``time_step_s`` (and the discharge's as ``discharge_time_step_s`` where it has one of its own,
  ``sim.discharge_time_step_fraction``) beside the KPIs, and its wall time is that of every attempt. A run whose
  last retry blows up too fails with the errors of all its attempts. Soft particles landing from the
  rained fill at ~4 m/s overlap deeply, and the step that is stable for the flow can be marginal for
  that moment alone (a lab run at lobe spacing 0.15 threw bodies off the landing bed at 20-32 m/s
  in float32 and float64, with and without reordering; at 0.8 of the step the fastest body moved
  at 5.0 m/s), so a shorter step recovers the run instead of leaving a hole in a design.
- With ``core_share`` (:class:`bo.campaign.cores.CoreShare`, what a local dask cluster's executor
  publishes) a batch follows the cores its idle neighbours leave: it asks the share at every
  load-cell sample and sets torch's threads to match (same KPIs on any number of threads).
- ``functools.partial(evaluate_batch, model)`` is picklable, so it ships to dask workers.
"""
from __future__ import annotations

import hashlib
import json
import math
import time
from pathlib import Path
from typing import Sequence

from bo.campaign.cores import CoreShare, ThreadFollower
from bo.campaign.executor import EvalOutcome, EvalTask
from torchdem.drawdown import KPI_UNITS
from torchdem.errors import BlowUpError, ConfigError
from torchdem.model import DrawDownModel, geometry_parameters

def checkpoint_path(checkpoint_dir: str | Path, model: DrawDownModel, tasks: Sequence[EvalTask],
                    time_step_scale: float = 1.0) -> Path:
    """The checkpoint file of a batch: named by a hash of the model (its repr), the condition and
    each task's parameters and seed, in order (and the time step's scale of a retry, when not 1).
    The model is named without the settings that decide only how a run goes
    (``torchdem.model.EXECUTION_ONLY``): a checkpoint resumes on another device or with reordering
    switched on (:meth:`Simulation.load` applies a saved order to the system and moves the state to
    its device)."""
    named = model.without_execution()
    runs = [[t.condition, sorted(t.params.items()), int(t.seed)] for t in tasks]
    text = json.dumps([repr(named), runs] + ([] if time_step_scale == 1 else [float(time_step_scale)]))
    return Path(checkpoint_dir) / f"batch-{hashlib.sha256(text.encode()).hexdigest()[:20]}.pt"


def evaluate_batch(model: DrawDownModel, tasks: list[EvalTask], checkpoint_dir: str | None = None,
                   core_share: CoreShare | None = None, progress=None) -> list[EvalOutcome]:
    """Run the tasks (one condition) as one ensemble (one per set of box lengths, ``geometry_*``
    parameters, when they differ); one outcome per task, in order.
    ``checkpoint_dir``: where the batch checkpoints and resumes. A run that blows up is retried
    at ``model.settings.retry_time_steps`` (module docstring). ``core_share``: the batch takes the
    threads the share allows, as they change. ``progress``: called as ``progress(simulated_s, wall_s)``
    while an ensemble runs (:meth:`torchdem.drawdown.DrawDownTest.run`)."""
    threads = None if core_share is None else ThreadFollower(core_share)
    boxes: dict[tuple, list[int]] = {}  # an ensemble has one set of walls: tasks of other box lengths run apart
    for r, t in enumerate(tasks):
        boxes.setdefault(geometry_parameters(t.params), []).append(r)
    if len(boxes) > 1:
        out: list[EvalOutcome | None] = [None] * len(tasks)
        for rows in boxes.values():
            for r, o in zip(rows, evaluate_batch(model, [tasks[r] for r in rows], checkpoint_dir, core_share,
                                                   progress)):
                out[r] = o
        return out
    out = _evaluate(model, tasks, checkpoint_dir, 1.0, threads, progress)
    attempts: dict[int, list[str]] = {}  # task -> the errors of its attempts, in order
    for scale in model.settings.retry_time_steps:
        blown = [r for r, o in enumerate(out) if not o.ok and o.error.startswith("BlowUpError")]
        if not blown:
            break
        for r in blown:
            attempts.setdefault(r, [out[r].error])
        again = _evaluate(model, [tasks[r] for r in blown], checkpoint_dir, scale, threads, progress)
        for r, o in zip(blown, again):
            wall = out[r].wall_time + o.wall_time
            if o.ok:
                out[r] = EvalOutcome.success(o.kpis, wall)
                continue
            attempts[r].append(o.error)
            tried = "; ".join(f"at {f:g} of the time step: {e}"
                              for f, e in zip(model.settings.retry_time_steps, attempts[r][1:]))
            out[r] = EvalOutcome.failure(f"{attempts[r][0]}; run again {tried}", wall)
    return out


def _evaluate(model: DrawDownModel, tasks: list[EvalTask], checkpoint_dir: str | None,
              time_step_scale: float, threads=None, progress=None) -> list[EvalOutcome]:
    """One attempt of :func:`evaluate_batch` at ``time_step_scale`` of the time step (a run at a
    scale other than 1 reports its step as ``time_step_s``)."""
    started = time.perf_counter()
    if not tasks:
        return []
    conditions = {t.condition for t in tasks}
    if len(conditions) != 1:
        raise ConfigError(f"evaluate_batch: a batch must hold one condition, got {sorted(conditions)}")
    keys: dict[tuple, int] = {}
    sets: list[dict[str, float]] = []
    members = []
    for r, t in enumerate(tasks):
        key = tuple(sorted(t.params.items()))
        if key not in keys:
            keys[key] = len(sets)
            sets.append(dict(t.params))
        members.append((keys[key], r, t.seed))
    try:
        test = model.test_for(tasks[0].condition, sets, time_step_scale=time_step_scale)
        checkpoint = None
        if checkpoint_dir is not None:
            Path(checkpoint_dir).mkdir(parents=True, exist_ok=True)
            checkpoint = checkpoint_path(checkpoint_dir, model, tasks, time_step_scale)
        result = test.run_members(members, device=model.device, progress=progress, checkpoint=checkpoint,
                                  threads=threads)
    except (BlowUpError, ConfigError) as exc:
        own = _members_that_fail_alone(model, tasks) if isinstance(exc, ConfigError) and len(sets) > 1 else {}
        if own:  # each failed member keeps its own error; the others run without them
            rest = iter(_evaluate(model, [t for r, t in enumerate(tasks) if r not in own], checkpoint_dir,
                                  time_step_scale, threads, progress))
            wall = time.perf_counter() - started
            return [EvalOutcome.failure(own[r], wall) if r in own else next(rest) for r in range(len(tasks))]
        wall = time.perf_counter() - started
        return [EvalOutcome.failure(f"{type(exc).__name__}: {exc}", wall) for _ in tasks]
    # a resumed batch's cost includes the time spent before its checkpoint (result.wall_time_s)
    wall = max(time.perf_counter() - started, result.wall_time_s)
    out = []
    for m, k in enumerate(result.kpis):
        if m in result.failed:
            out.append(EvalOutcome.failure(f"BlowUpError: member {m} (seed {tasks[m].seed}): {result.failed[m]}", wall))
            continue
        kpis = {name: float(k.get(name, math.nan)) for name in KPI_UNITS}
        if time_step_scale != 1:
            kpis["time_step_s"] = float(result.dt)
            if result.discharge_dt != result.dt:
                kpis["discharge_time_step_s"] = float(result.discharge_dt)
        out.append(EvalOutcome.success(kpis, wall))
    return out


def _members_that_fail_alone(model: DrawDownModel, tasks: list[EvalTask]) -> dict[int, str]:
    """Task index -> error, for the tasks whose one-member ensemble cannot be built (fill and
    system, no stepping)."""
    failed = {}
    for r, t in enumerate(tasks):
        try:
            model.test_for(t.condition, [dict(t.params)]).build([t.seed], [0], device=model.device)
        except ConfigError as exc:
            failed[r] = f"ConfigError: {exc}"
    return failed
