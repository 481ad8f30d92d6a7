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
- ``functools.partial(evaluate_batch, model)`` is picklable, so it ships to dask workers.
"""
from __future__ import annotations

import math
import time
from typing import Sequence

import numpy as np

from bo.campaign.executor import EvalOutcome, EvalTask
from torchdem.drawdown import KPI_UNITS
from torchdem.errors import BlowUpError, ConfigError
from torchdem.model import DrawDownModel

def evaluate_batch(model: DrawDownModel, tasks: list[EvalTask]) -> list[EvalOutcome]:
    """Run the tasks (one condition) as one ensemble; one outcome per task, in order."""
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
        result = test.run_members(members, device=model.device)
    except (BlowUpError, ConfigError) as exc:
        own = _members_that_fail_alone(model, tasks) if isinstance(exc, ConfigError) and len(sets) > 1 else {}
        if own:  # each failed member keeps its own error; the others run without them
            rest = iter(evaluate_batch(model, [t for r, t in enumerate(tasks) if r not in own]))
            wall = time.perf_counter() - started
            return [EvalOutcome.failure(own[r], wall) if r in own else next(rest) for r in range(len(tasks))]
        wall = time.perf_counter() - started
        return [EvalOutcome.failure(f"{type(exc).__name__}: {exc}", wall) for _ in tasks]
    wall = time.perf_counter() - started
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
