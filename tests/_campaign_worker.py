"""Cheap analytic stand-in for a DEM evaluator, and a tiny campaign script, for the store tests.

As a module: ``analytic_kpis`` (deterministic KPIs with seed-dependent noise) and
``analytic_batch`` (the ``evaluate_batch`` the executors call; module-level so dask can pickle
it, configured with ``functools.partial``). It appends one JSON line per evaluation to
``log_path`` so tests can count how often each (params, seed, condition) really ran.

As a script (run by tests/test_store.py as a subprocess)::

    python tests/_campaign_worker.py campaign DB LOG PROPOSALS   # two-stage campaign
    python tests/_campaign_worker.py worker DB LOG GO            # one worker on a shared batch
"""
from __future__ import annotations

import functools
import json
import os
import sys
import time
import zlib

import numpy as np

from bo.campaign.executor import EvalOutcome, EvalTask, InProcessExecutor, run_pending
from bo.campaign.store import CampaignStore
from torchdem.errors import ConfigError

CAMPAIGN_CONDITIONS = ["50-50", "70-30"]
CAMPAIGN_SEEDS = [1, 2]
N_INITIAL = 10
N_ROUND = 6
CAMPAIGN_BATCH_SIZE = 4


def task_key(params: dict, seed: int, condition: str) -> str:
    return json.dumps([sorted(params.items()), seed, condition])


def analytic_kpis(params: dict, seed: int, condition: str) -> dict[str, float]:
    """Smooth functions of the parameters plus noise fixed by (seed, params, condition)."""
    text = json.dumps(sorted(params.items()))
    rng = np.random.default_rng([seed, zlib.crc32(text.encode()), zlib.crc32(condition.encode())])
    x = np.array([params[k] for k in sorted(params)])
    share = float(condition.split("-")[0]) / 100.0 if condition[0].isdigit() else 0.5
    return {
        "angle_of_repose": float(25.0 + 20.0 * x.sum() * share + rng.normal(0.0, 0.5)),
        "discharge_rate": float(1.0 / (1.0 + (x ** 2).sum()) + rng.normal(0.0, 0.01)),
    }


def analytic_batch(tasks: list[EvalTask], *, log_path: str | None = None,
                   sleep_per_eval: float = 0.0, fail_condition: str | None = None,
                   slow_mu: float | None = None, slow_seconds: float = 0.0) -> list[EvalOutcome]:
    """evaluate_batch: KPIs of every task; raises for ``fail_condition`` (a blown-up batch); a
    batch holding a task with ``mu_s_pp == slow_mu`` takes ``slow_seconds`` more."""
    start = time.perf_counter()
    if len({t.condition for t in tasks}) > 1:  # the contract of torchdem's evaluate_batch: one ensemble
        raise ConfigError(f"a batch must hold one condition, got {sorted({t.condition for t in tasks})}")
    if any(t.condition == fail_condition for t in tasks):
        raise RuntimeError(f"ensemble blew up for condition {fail_condition}")
    time.sleep(sleep_per_eval * len(tasks) + (slow_seconds if any(t.params.get("mu_s_pp") == slow_mu
                                                                   for t in tasks) else 0.0))
    kpis = [analytic_kpis(t.params, t.seed, t.condition) for t in tasks]
    if log_path is not None:
        lines = "".join(json.dumps({"pid": os.getpid(), "key": task_key(t.params, t.seed, t.condition)})
                        + "\n" for t in tasks)
        with open(log_path, "a") as f:  # one write per batch: lines of two processes do not mix
            f.write(lines)
    wall = time.perf_counter() - start
    return [EvalOutcome.success(k, wall) for k in kpis]


def threads_seen_batch(tasks: list[EvalTask], *, core_share, seconds: dict[float, float],
                       every: float = 0.05) -> list[EvalOutcome]:
    """evaluate_batch that runs ``seconds[mu_s_pp]`` s and samples ``core_share.threads()`` every
    ``every`` s: KPIs ``first``, ``low``, ``high`` (the thread counts it was allowed) and the pid."""
    start = time.perf_counter()
    duration = max(seconds.get(t.params["mu_s_pp"], 0.0) for t in tasks)
    seen = [core_share.threads()]
    while time.perf_counter() - start < duration:
        time.sleep(every)
        seen.append(core_share.threads())
    kpis = {"first": float(seen[0]), "low": float(min(seen)), "high": float(max(seen)), "pid": float(os.getpid())}
    return [EvalOutcome.success(kpis, time.perf_counter() - start) for _ in tasks]


def _log_proposal(path: str, stage: str, points: list[dict]) -> None:
    with open(path, "a") as f:
        f.write(json.dumps({"stage": stage, "points": points}) + "\n")


def campaign(db: str, log: str, proposals: str) -> None:
    """Initial random design, then one round around the best point, then a summary artifact."""
    store = CampaignStore(db, "cfg-campaign")
    executor = InProcessExecutor(
        functools.partial(analytic_batch, log_path=log, sleep_per_eval=0.03), CAMPAIGN_BATCH_SIZE)

    def propose_initial():
        rng = np.random.default_rng()  # fresh entropy: a re-proposal would differ
        points = [{"mu_s_pp": float(rng.uniform(0.2, 0.8)), "e_pp": float(rng.uniform(0.3, 0.7))}
                  for _ in range(N_INITIAL)]
        _log_proposal(proposals, "initial", points)
        return points

    store.batch("initial", "design", propose_initial, seeds=CAMPAIGN_SEEDS,
                conditions=CAMPAIGN_CONDITIONS)
    run_pending(store, executor, "initial")
    done = store.arrays("initial")
    best = done.X[int(np.argmin(done.kpis[:, done.kpi_names.index("angle_of_repose")]))]

    def propose_round():
        rng = np.random.default_rng()
        points = [{name: float(value + rng.normal(0.0, 0.02))
                   for name, value in zip(done.param_names, best)} for _ in range(N_ROUND)]
        _log_proposal(proposals, "round-1", points)
        return points

    store.batch("round-1", "q-ei", propose_round, seeds=CAMPAIGN_SEEDS,
                conditions=CAMPAIGN_CONDITIONS)
    run_pending(store, executor, "round-1")
    if store.get_artifact("summary", None) is None:
        store.put_artifact("summary", {"best": dict(zip(done.param_names, best.tolist()))})
    print("campaign complete")


def worker(db: str, log: str, go: str) -> None:
    """Say ready, wait for the go file, propose (or reuse) the shared batch and work on it."""
    store = CampaignStore(db, "cfg-workers")
    open(f"{go}.ready.{os.getpid()}", "w").close()  # imported and opened: ready to race
    deadline = time.monotonic() + 30.0
    while not os.path.exists(go) and time.monotonic() < deadline:
        time.sleep(0.01)
    rng = np.random.default_rng()
    points = store.batch("initial", "shared",
                         lambda: [{"mu_s_pp": float(v)} for v in rng.uniform(0.2, 0.8, 12)],
                         seeds=[0, 1, 2], conditions=["50-50"])
    executor = InProcessExecutor(
        functools.partial(analytic_batch, log_path=log, sleep_per_eval=0.02), batch_size=3)
    summary = run_pending(store, executor, "initial", poll_seconds=0.05)
    print(json.dumps({"points": points, "n_done": summary.n_done}))


if __name__ == "__main__":
    mode, *args = sys.argv[1:]
    {"campaign": campaign, "worker": worker}[mode](*args)
