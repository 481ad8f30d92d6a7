"""Tests of bo.campaign.executor: task/outcome validation, batching, in-process and dask executors."""
from __future__ import annotations

import functools
import json
import logging
import math
import os
import time

import pytest

from _campaign_worker import analytic_batch, analytic_kpis, task_key, threads_seen_batch
from bo.campaign.cores import CoreShare
from bo.campaign.executor import (DaskExecutor, EvalOutcome, EvalTask, InProcessExecutor, evaluate_checked,
                         make_batches, run_pending)
from bo.campaign.store import CampaignStore
from torchdem.errors import ConfigError

CONDITIONS = ("50-50", "70-30")


def tasks_for(n_points=5, seeds=(0, 1), conditions=CONDITIONS):
    out = []
    for condition in conditions:
        for i in range(n_points):
            for seed in seeds:
                params = {"mu_s_pp": 0.2 + 0.1 * i, "e_pp": 0.6 - 0.05 * i}
                out.append(EvalTask(params, seed, condition, len(out) + 1))
    return out


def collect(executor, tasks):
    batches = list(executor.run(tasks))
    return batches, {t.task_id: o for batch in batches for t, o in batch}


# -- value types ------------------------------------------------------------------------------

def test_eval_task_is_canonical_frozen_and_hashable():
    task = EvalTask({"mu_s_pp": 0.5, "e_pp": 1}, 3, "50-50", 7)
    assert list(task.params) == ["e_pp", "mu_s_pp"] and task.params["e_pp"] == 1.0
    assert task == EvalTask({"e_pp": 1.0, "mu_s_pp": 0.5}, 3, "50-50", 7)
    assert len({task, EvalTask({"e_pp": 1.0, "mu_s_pp": 0.5}, 3, "50-50", 7)}) == 1
    with pytest.raises(AttributeError):
        task.seed = 4


@pytest.mark.parametrize("params, seed, condition, match", [
    ({"mu_s_pp": math.nan}, 0, "50-50", r"params\['mu_s_pp'\] = nan .*finite"),
    ({"mu_s_pp": -math.inf}, 0, "50-50", "finite"),
    ({}, 0, "50-50", "at least one parameter"),
    ({"mu_s_pp": 0.5}, 1.5, "50-50", "seed"),
    ({"mu_s_pp": 0.5}, 0, "", "condition"),
])
def test_eval_task_refuses_bad_input(params, seed, condition, match):
    with pytest.raises(ConfigError, match=match):
        EvalTask(params, seed, condition)


def test_eval_outcome_has_exactly_one_of_kpis_and_error():
    assert EvalOutcome.success({"angle_of_repose": 31}, 2.0).ok
    assert not EvalOutcome.failure("blew up").ok
    with pytest.raises(ConfigError, match="exactly one"):
        EvalOutcome({"a": 1.0}, "and an error", 1.0)
    with pytest.raises(ConfigError, match="exactly one"):
        EvalOutcome(None, None, 1.0)
    with pytest.raises(ConfigError, match="wall_time"):
        EvalOutcome.success({"a": 1.0}, -1.0)


@pytest.mark.parametrize("batch_size", [0, -3, 1.5, True, "4"])
def test_bad_batch_size_is_refused(batch_size):
    with pytest.raises(ConfigError, match=r"batch_size = .* expected an int >= 1"):
        InProcessExecutor(analytic_batch, batch_size)
    with pytest.raises(ConfigError, match="batch_size"):
        make_batches(tasks_for(), batch_size)


def test_bad_executor_arguments():
    with pytest.raises(ConfigError, match="evaluate_batch"):
        InProcessExecutor("not callable", 2)
    with pytest.raises(ConfigError, match="executor"):
        run_pending(None, "not an executor")
    with pytest.raises(ConfigError, match="either client or address"):
        DaskExecutor(analytic_batch, 2, client=object(), address="tcp://127.0.0.1:1")


# -- batching ---------------------------------------------------------------------------------

def test_batches_hold_one_condition_and_keep_task_order():
    tasks = tasks_for(n_points=5)  # 10 tasks per condition
    mixed = [t for pair in zip(tasks[:10], tasks[10:]) for t in pair]
    batches = make_batches(mixed, 4)
    assert [len(b) for b in batches] == [4, 4, 2, 4, 4, 2]
    assert [{t.condition for t in b} for b in batches] == [{"50-50"}] * 3 + [{"70-30"}] * 3
    assert [t for b in batches[:3] for t in b] == tasks[:10]
    assert make_batches([], 3) == []


def test_in_process_executor_runs_every_task_once():
    tasks = tasks_for()
    batches, outcomes = collect(InProcessExecutor(analytic_batch, 3), tasks)
    assert [len(b) for b in batches] == [3, 3, 3, 1, 3, 3, 3, 1]
    assert sorted(outcomes) == [t.task_id for t in tasks]
    for task in tasks:
        assert outcomes[task.task_id].kpis == analytic_kpis(task.params, task.seed, task.condition)


def test_failing_batches_become_failures_and_spare_the_others():
    tasks = tasks_for()
    failing = functools.partial(analytic_batch, fail_condition="70-30")
    _, outcomes = collect(InProcessExecutor(failing, 4), tasks)
    for task in tasks:
        outcome = outcomes[task.task_id]
        assert outcome.ok == (task.condition == "50-50")
        if not outcome.ok:
            assert outcome.error == ("evaluate_batch raised RuntimeError: ensemble blew up for "
                                     "condition 70-30")
    short = evaluate_checked(lambda batch: analytic_batch(batch)[:-1], tasks[:3])
    assert [o.error for o in short] == ["evaluate_batch returned 2 items; expected a list of 3 "
                                        "EvalOutcome (one per task, same order)"] * 3
    assert "returned dict" in evaluate_checked(lambda batch: {}, tasks[:1])[0].error


def test_run_pending_writes_every_outcome(tmp_path):
    store = CampaignStore(tmp_path / "s.sqlite", "cfg", code_version="test")
    store.batch("initial", "a", lambda: [t.params for t in tasks_for(n_points=4, seeds=(0,),
                                                                      conditions=("x",))],
                seeds=[0, 1], conditions=list(CONDITIONS))
    store.batch("round-1", "b", lambda: [{"e_pp": 0.5, "mu_s_pp": 0.5}], seeds=[0], conditions=["50-50"])
    failing = functools.partial(analytic_batch, fail_condition="70-30")
    summary = run_pending(store, InProcessExecutor(failing, 3), "initial")
    assert (summary.n_done, summary.n_failed, summary.n_batches) == (8, 8, 6)  # 3+3+2 each
    assert store.counts("initial") == {"pending": 0, "running": 0, "done": 8, "failed": 8}
    assert store.counts("round-1")["pending"] == 1  # other stages untouched
    assert store.reset_failed("initial") == 8
    summary = run_pending(store, InProcessExecutor(analytic_batch, 3))
    assert (summary.n_done, summary.n_failed) == (9, 0)
    assert store.counts() == {"pending": 0, "running": 0, "done": 17, "failed": 0}
    for rec in store.records():
        assert rec.kpis == analytic_kpis(rec.params, rec.seed, rec.condition)


# -- dask -------------------------------------------------------------------------------------

def test_dask_executor_matches_in_process(tmp_path, caplog):
    """One LocalCluster(n_workers=2, processes=True, threads_per_worker=1) for every dask check
    (one test, so a parallel test run never starts two clusters). The cluster it starts logs no
    INFO lines of dask's (each scheduler, nanny and connection) into the CLIs' log."""
    caplog.set_level(logging.INFO)
    with DaskExecutor(functools.partial(analytic_batch, sleep_per_eval=0.01), batch_size=3,
                      n_workers=2) as executor:
        assert executor.parallelism == 2
        assert sorted(executor.client.nthreads().values()) == [1, 1]
        worker_pids = set(executor.client.run(os.getpid).values())
        assert len(worker_pids) == 2 and os.getpid() not in worker_pids  # worker processes
        # same outcomes as in this process, one condition per batch
        tasks = tasks_for()
        batches, outcomes = collect(executor, tasks)
        _, reference = collect(InProcessExecutor(analytic_batch, 3), tasks)
        assert sorted(len(b) for b in batches) == sorted([3, 3, 3, 1] * 2)
        assert all(len({t.condition for t, _ in b}) == 1 for b in batches)
        assert {i: o.kpis for i, o in outcomes.items()} == {i: o.kpis for i, o in reference.items()}

        # through the store: the same arrays as an in-process campaign
        in_process = CampaignStore(tmp_path / "ref.sqlite", "cfg", code_version="test")
        distributed = CampaignStore(tmp_path / "dask.sqlite", "cfg", code_version="test")
        points = [t.params for t in tasks_for(n_points=4, seeds=(0,), conditions=("x",))]
        for store in (in_process, distributed):
            store.batch("initial", "a", lambda: points, seeds=[0, 1], conditions=list(CONDITIONS))
        run_pending(in_process, InProcessExecutor(analytic_batch, 3))
        run_pending(distributed, executor)
        a, b = in_process.arrays(), distributed.arrays()
        assert (a.X == b.X).all() and (a.kpis == b.kpis).all() and (a.seeds == b.seeds).all()
        assert distributed.counts()["done"] == 16

        # a claim that tops up one condition's short batch with another condition's tasks is cut
        # per condition before it reaches a worker (an ensemble holds one condition)
        mixed = CampaignStore(tmp_path / "mixed.sqlite", "cfg", code_version="test")
        mixed.batch("initial", "a", lambda: [{"mu_s_pp": 0.3}], seeds=[0, 1], conditions=list(CONDITIONS))
        wide = DaskExecutor(analytic_batch, 4, client=executor.client)
        summary = run_pending(mixed, wide)
        assert (summary.n_done, summary.n_failed, summary.n_batches) == (4, 0, 2), mixed.records(status="failed")

        # a long batch does not hold the other worker back: run_pending draws a batch whenever a
        # worker is free, so the three fast tasks claimed after the slow one finish before it
        # (claiming two tasks at a time, the slow one finished before the third was claimed)
        streamed = CampaignStore(tmp_path / "stream.sqlite", "cfg", code_version="test")
        streamed.batch("initial", "a", lambda: [{"mu_s_pp": 0.1 * (k + 1)} for k in range(5)], seeds=[0],
                       conditions=["x"])
        slow = DaskExecutor(functools.partial(analytic_batch, slow_mu=0.1, slow_seconds=3.0), 1,
                            client=executor.client)
        run_pending(streamed, slow)
        finished = {round(r.params["mu_s_pp"], 6): r.finished_at for r in streamed.records()}
        assert finished[0.1] > max(finished[v] for v in (0.3, 0.4, 0.5)), finished

        # the workers share the cluster's cores: while two batches are in flight each may use one
        # thread; the last one of a stage, once the other worker has nothing left, both
        share = CoreShare.create(2, directory=str(tmp_path))
        sharing = DaskExecutor(functools.partial(threads_seen_batch, core_share=share,
                                                 seconds={0.1: 0.4, 0.2: 3.0, 0.3: 0.4}), 1,
                               client=executor.client, core_share=share)
        shared = CampaignStore(tmp_path / "share.sqlite", "cfg", code_version="test")
        shared.batch("initial", "a", lambda: [{"mu_s_pp": 0.1}, {"mu_s_pp": 0.2}, {"mu_s_pp": 0.3}], seeds=[0],
                     conditions=["x"])
        run_pending(shared, sharing)
        seen = {round(r.params["mu_s_pp"], 6): r.kpis for r in shared.records()}
        assert seen[0.1]["high"] == seen[0.3]["high"] == 1, seen       # each beside a running batch
        assert (seen[0.2]["first"], seen[0.2]["high"]) == (1, 2), seen  # the tail takes the freed core
        assert share.busy() == 0
        sharing.close()
        assert not os.path.exists(share.path)

        # a given client or scheduler address: failures per batch, the cluster stays up
        failing = DaskExecutor(functools.partial(analytic_batch, fail_condition="70-30"), 4,
                               client=executor.client)
        _, outcomes = collect(failing, tasks_for())
        assert sum(o.ok for o in outcomes.values()) == 10
        assert {o.error for o in outcomes.values() if not o.ok} == {
            "evaluate_batch raised RuntimeError: ensemble blew up for condition 70-30"}
        failing.close()
        # a worker lost mid-campaign (killed, or restarted after missed heartbeats) costs only the
        # batch it was running: batches whose outcomes were taken are released, not recomputed
        log = tmp_path / "evaluations.log"
        lost = DaskExecutor(functools.partial(analytic_batch, log_path=str(log), slow_mu=0.3, slow_seconds=4.0), 1,
                            client=executor.client)
        stream = lost.run_stream([[t] for t in tasks_for(n_points=3, seeds=(0,), conditions=("x",))])
        first = next(stream)  # mu 0.2; mu 0.3 (slow) and then 0.4 are in flight
        try:
            executor.client.run(os._exit, 1)  # every worker process dies; the nannies restart them
        except Exception:
            pass
        rest = [b for b in stream]
        assert sorted(round(t.params["mu_s_pp"], 6) for b in [first, *rest] for t, _ in b) == [0.2, 0.3, 0.4]
        assert all(o.ok for b in rest for _, o in b)
        time.sleep(1.0)
        evaluated = [json.loads(line)["key"] for line in log.read_text().splitlines()]
        first_key = task_key(first[0][0].params, first[0][0].seed, first[0][0].condition)
        assert evaluated.count(first_key) == 1, evaluated
        executor.client.wait_for_workers(2, timeout=60)
        with DaskExecutor(analytic_batch, 5, address=executor.client.scheduler.address) as remote:
            _, outcomes = collect(remote, tasks)
            assert {i: o.kpis for i, o in outcomes.items()} == {i: o.kpis for i, o in reference.items()}
        assert executor.client.status == "running"
        cluster = executor._cluster
    assert executor.client.status == "closed" and cluster.status.name == "closed"
    chatter = [f"{r.name}: {r.getMessage()}" for r in caplog.records
               if r.name.startswith("distributed") and r.levelno < logging.WARNING]
    assert not chatter, chatter[:5]


def test_executor_factory_serves_every_model_from_one_cluster():
    """Discovery and the power study make an executor per model (hypothesis, twin): with dask they
    share one local cluster, whose worker processes live until the factory closes."""
    from bo.cli.common import ExecutorSettings, executor_factory

    with executor_factory(ExecutorSettings("dask", batch_size=2, n_workers=1)) as executor_for:
        with executor_for("model A") as first:
            pids = set(first.client.run(os.getpid).values())
        with executor_for("model B") as second:
            assert second.client is first.client and set(second.client.run(os.getpid).values()) == pids
        assert first.client.status == "running"                  # an executor leaves the shared client open
    assert first.client.status == "closed"
    with executor_factory(ExecutorSettings("inprocess", batch_size=2)) as executor_for:
        assert isinstance(executor_for("model"), InProcessExecutor)
