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
  batch fails the whole batch with the message.
- With ``checkpoint_dir`` the ensemble saves its state every 0.5 s of simulated time to
  :func:`checkpoint_path` (a file named by the model, the condition and every task's parameters
  and seed) and, if that file exists when the batch starts, resumes from it: a campaign killed
  during a long run (a lab-geometry batch takes up to two hours on one core) loses at most
  0.5 s of simulated time of it, as long as the store hands the same tasks to one batch again
  (it claims pending tasks in the same order every time). The file is removed when the run ends.
  A resumed batch reports the wall time of the whole run, the part before the checkpoint included.
- ``functools.partial(evaluate_batch, model)`` is picklable, so it ships to dask workers.
"""
from __future__ import annotations

import hashlib
import json
import math
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from bo.campaign.executor import EvalOutcome, EvalTask
from torchdem.drawdown import KPI_UNITS
from torchdem.errors import BlowUpError, ConfigError
from torchdem.model import DrawDownModel

def checkpoint_path(checkpoint_dir: str | Path, model: DrawDownModel, tasks: Sequence[EvalTask]) -> Path:
    """The checkpoint file of a batch: named by a hash of the model (its repr), the condition and
    each task's parameters and seed, in order. The model is named without the settings that decide
    only how a run goes (``torchdem.model.EXECUTION_ONLY``): a checkpoint resumes on another device
    or with reordering switched on (:meth:`Simulation.load` applies a saved order to the system and
    moves the state to its device)."""
    named = model.without_execution()
    text = json.dumps([repr(named), [[t.condition, sorted(t.params.items()), int(t.seed)] for t in tasks]])
    return Path(checkpoint_dir) / f"batch-{hashlib.sha256(text.encode()).hexdigest()[:20]}.pt"


def evaluate_batch(model: DrawDownModel, tasks: list[EvalTask], checkpoint_dir: str | None = None) -> list[EvalOutcome]:
    """Run the tasks (one condition) as one ensemble; one outcome per task, in order.
    ``checkpoint_dir``: where the batch checkpoints and resumes (module docstring)."""
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
        test = model.test_for(tasks[0].condition, sets)
        checkpoint = None
        if checkpoint_dir is not None:
            Path(checkpoint_dir).mkdir(parents=True, exist_ok=True)
            checkpoint = checkpoint_path(checkpoint_dir, model, tasks)
        result = test.run_members(members, device=model.device, checkpoint=checkpoint)
    except (BlowUpError, ConfigError) as exc:
        own = _members_that_fail_alone(model, tasks) if isinstance(exc, ConfigError) and len(sets) > 1 else {}
        if own:  # each failed member keeps its own error; the others run without them
            rest = iter(evaluate_batch(model, [t for r, t in enumerate(tasks) if r not in own], checkpoint_dir))
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


def kpi_matrix(outcomes: Sequence[EvalOutcome], kpis: Sequence[str]) -> np.ndarray:
    """``[n, len(kpis)]`` KPI values (NaN for failures and unmeasured KPIs)."""
    arr = np.full((len(outcomes), len(kpis)), np.nan)
    for i, o in enumerate(outcomes):
        if o.ok:
            arr[i] = [o.kpis.get(k, np.nan) for k in kpis]
    return arr
