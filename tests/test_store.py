"""Tests of bo.campaign.store: batches, leases, recording, artifacts, queries, kill/resume and two workers."""
from __future__ import annotations

import collections
import json
import math
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from _campaign_worker import (CAMPAIGN_BATCH_SIZE, CAMPAIGN_CONDITIONS, CAMPAIGN_SEEDS, N_INITIAL,
                              N_ROUND, task_key)
from bo.campaign.executor import EvalOutcome, EvalTask, InProcessExecutor, run_pending
from bo.campaign.store import CampaignStore, copy_store, default_code_version
from torchdem.errors import ConfigError

WORKER = str(Path(__file__).with_name("_campaign_worker.py"))
POINTS = [{"mu_s_pp": 0.3, "e_pp": 0.5}, {"mu_s_pp": 0.6, "e_pp": 0.4}, {"e_pp": 0.45, "mu_s_pp": 0.1}]


def new_store(tmp_path, **kw) -> CampaignStore:
    return CampaignStore(tmp_path / "campaign.sqlite", "cfg-1", code_version="test-1", **kw)


def fill(store, stage="initial", key="k", points=POINTS, seeds=(0, 1), conditions=("50-50",)):
    return store.batch(stage, key, lambda: points, seeds=seeds, conditions=conditions)


def finish(store, tasks, kpis=lambda t: {"angle_of_repose": 30.0 + t.seed}):
    return store.record([(t, EvalOutcome.success(kpis(t), 0.5)) for t in tasks])


# -- batches ----------------------------------------------------------------------------------

def test_batch_stores_points_once_and_reuses_them(tmp_path):
    store = new_store(tmp_path)
    calls = []

    def make_points():
        calls.append(1)
        return POINTS

    first = store.batch("initial", "k", make_points, seeds=[0, 1], conditions=["50-50", "70-30"])
    again = CampaignStore(store.path, "cfg-1").batch("initial", "k", make_points, seeds=[0, 1],
                                                     conditions=["50-50", "70-30"])
    assert len(calls) == 1
    assert first == again == [dict(sorted(p.items())) for p in POINTS]
    assert list(first[0]) == ["e_pp", "mu_s_pp"]  # canonical key order
    recs = store.records("initial")
    assert len(recs) == 3 * 2 * 2 and {r.status for r in recs} == {"pending"}
    assert [r.condition for r in recs] == ["50-50"] * 6 + ["70-30"] * 6  # condition-major
    assert {(r.point_index, r.seed, r.condition) for r in recs} == {
        (i, s, c) for i in range(3) for s in (0, 1) for c in ("50-50", "70-30")}
    assert all(r.config_hash == "cfg-1" and r.code_version == "test-1" for r in recs)
    raw = sqlite3.connect(store.path).execute("SELECT params FROM evaluations ORDER BY task_id LIMIT 1").fetchone()[0]
    assert raw == '{"e_pp":0.5,"mu_s_pp":0.3}'
    assert store.batch_keys() == [("initial", "k")]


def test_copy_store_copies_the_source_as_it_is_now_every_time(tmp_path):
    """A copy made again to the same target holds what the source holds then (a copy is never
    remembered from an earlier call), and the source is left as it was."""
    source, target = tmp_path / "s.sqlite", tmp_path / "copies" / "t.sqlite"
    store = CampaignStore(source, "h")
    store.put_artifact("a", {"v": 1})
    copy_store(source, target)
    assert CampaignStore(target, "h").get_artifact("a", None) == {"v": 1}
    store.put_artifact("b", {"v": 2})
    copy_store(source, target)
    again = CampaignStore(target, "h")
    assert again.get_artifact("a", None) == {"v": 1} and again.get_artifact("b", None) == {"v": 2}
    assert store.get_artifact("b", None) == {"v": 2}


@pytest.mark.parametrize("content", ["text", "empty database"])
def test_copying_what_is_not_a_store_names_the_file_and_leaves_no_copy(tmp_path, content):
    """``store_from=`` a file that is not a campaign store (a text file; an SQLite file without the
    store's tables): one ConfigError naming the file, and no half-made copy for the run to resume."""
    source, target = tmp_path / "shipped.sqlite", tmp_path / "run" / "campaign.sqlite"
    if content == "text":
        source.write_text("not a database\n")
    else:
        sqlite3.connect(source).execute("CREATE TABLE other (x)").connection.close()
    with pytest.raises(ConfigError, match=r"shipped\.sqlite: not a campaign store \((file is not a database|"
                                          r"no such table: evaluations)\)"):
        copy_store(source, target)
    assert not target.exists()


def test_a_store_path_that_cannot_hold_a_store_names_the_path(tmp_path):
    """``store=`` a file that is not SQLite, or a path whose folder cannot be made (it lies under a
    file): a ConfigError naming the path, which the commands print as one line."""
    (tmp_path / "notes.txt").write_text("lab notes\n")
    with pytest.raises(ConfigError, match=r"notes\.txt: not a usable SQLite database"):
        CampaignStore(tmp_path / "notes.txt", "h")
    with pytest.raises(ConfigError, match=r"notes\.txt/c\.sqlite: cannot make the store's folder .*notes\.txt"):
        CampaignStore(tmp_path / "notes.txt" / "c.sqlite", "h")


def test_near_batch_finds_the_same_experiment_within_the_tolerance_the_closest_first(tmp_path):
    store = new_store(tmp_path)
    fill(store, key="fit/a", points=[{"mu_s_pp": 0.3, "e_pp": 0.5}])
    fill(store, key="fit/b", points=[{"mu_s_pp": 0.3 + 4e-7, "e_pp": 0.5}])
    fill(store, key="other/c", points=[{"mu_s_pp": 0.3, "e_pp": 0.5}])
    near = lambda point, **kw: store.near_batch(  # noqa: E731
        "initial", "fit/", [point], seeds=kw.get("seeds", (0, 1)), conditions=kw.get("conditions", ("50-50",)),
        tolerance={"mu_s_pp": 1e-6})
    # the last digits moved (another machine's floating point): the stored batch and its own points
    assert near({"mu_s_pp": 0.3 + 3e-15, "e_pp": 0.5}) == ("fit/a", [{"e_pp": 0.5, "mu_s_pp": 0.3}])
    assert near({"mu_s_pp": 0.3 + 3.5e-7, "e_pp": 0.5})[0] == "fit/b"  # the closer of two inside the tolerance
    assert near({"mu_s_pp": 0.3 + 2e-6, "e_pp": 0.5}) is None  # beyond it: another experiment
    assert near({"mu_s_pp": 0.3, "e_pp": 0.5 + 1e-12}) is None  # a parameter without tolerance must be equal
    assert near({"mu_s_pp": 0.3, "e_pp": 0.5}, seeds=(0, 1, 2)) is None  # other seeds, other runs
    assert near({"mu_s_pp": 0.3, "e_pp": 0.5}, conditions=("70-30",)) is None
    assert near({"mu_s_pp": 0.3}) is None  # other parameter names
    with pytest.raises(ConfigError, match=r"tolerance\['mu_s_pp'\].*finite float >= 0"):
        store.near_batch("initial", "fit/", [{"mu_s_pp": 0.3}], seeds=(0,), conditions=("50-50",),
                         tolerance={"mu_s_pp": -1.0})


def test_a_batch_asked_for_without_some_of_its_seeds_or_conditions_is_refused(tmp_path):
    store = new_store(tmp_path)
    fill(store, seeds=(0, 1, 2))
    with pytest.raises(ConfigError, match=r"seeds=\[0, 1, 2\].*seeds=\[0, 1\].*never lose any"):
        fill(store, seeds=(0, 1))
    with pytest.raises(ConfigError, match="conditions"):
        fill(store, seeds=(0, 1, 2), conditions=("70-30",))  # 50-50 would be lost
    assert len(store.records("initial")) == 3 * 3  # nothing stored by the refused calls


def test_a_stored_batch_grows_by_seeds_and_conditions_and_runs_only_what_is_new(tmp_path):
    """The paper validates on 5 seeds where a campaign planned 3: the same batch, asked for with
    seeds 0-4, keeps its 3 runs per point and gains pending runs of seeds 3 and 4 only; a new
    condition adds its runs for every seed; a run done in another batch of the stage is taken."""
    store = new_store(tmp_path)
    fill(store, points=POINTS[:2], seeds=(0, 1, 2))
    finish(store, store.claim(100, "initial"))
    fill(store, key="elsewhere", points=[POINTS[0]], seeds=(4,), conditions=("70-30",))
    finish(store, store.claim(100, "initial"), kpis=lambda t: {"angle_of_repose": 99.0})
    before = {r.task_id: r for r in store.records("initial", batch_key="k")}

    assert fill(store, points=POINTS[:2], seeds=(0, 1, 2, 3, 4)) == POINTS[:2]
    grown = store.records("initial", batch_key="k")
    assert all(r == before[r.task_id] for r in grown if r.task_id in before)  # stored runs untouched
    new = [r for r in grown if r.task_id not in before]
    assert sorted((r.point_index, r.seed) for r in new) == [(0, 3), (0, 4), (1, 3), (1, 4)]
    assert {r.status for r in new} == {"pending"} and {r.condition for r in new} == {"50-50"}

    # a condition more, the seeds in another order: the stored order is kept, the new entry appended
    fill(store, points=POINTS[:2], seeds=(4, 3, 2, 1, 0), conditions=("70-30", "50-50"))
    assert store._stored_batch("initial", "k")[1:] == ([0, 1, 2, 3, 4], ["50-50", "70-30"])
    extra = [r for r in store.records("initial", batch_key="k") if r.condition == "70-30"]
    assert sorted((r.point_index, r.seed) for r in extra) == [(i, s) for i in range(2) for s in range(5)]
    taken = [r for r in extra if r.status == "done"]
    assert [(r.point_index, r.seed, r.kpis["angle_of_repose"]) for r in taken] == [(0, 4, 99.0)]
    assert len(store.records("initial", batch_key="k")) == 2 * 5 * 2
    # asked for again as grown: nothing more is stored
    fill(store, points=POINTS[:2], seeds=(0, 1, 2, 3, 4), conditions=("50-50", "70-30"))
    assert len(store.records("initial", batch_key="k")) == 20


def test_a_fresh_batch_grows_without_taking_stored_runs(tmp_path):
    store = new_store(tmp_path)
    fill(store, key="shared", points=[POINTS[0]], seeds=(0, 1, 2))
    finish(store, store.claim(100, "initial"))
    fresh = lambda seeds: store.batch("initial", "fresh", lambda: [POINTS[0]], seeds=seeds,  # noqa: E731
                                      conditions=("50-50",), share=False)
    fresh((0,))
    fresh((0, 1, 2))
    assert {r.status for r in store.records("initial", batch_key="fresh")} == {"pending"}
    assert len(store.records("initial", batch_key="fresh")) == 3


def test_bad_points_are_refused_and_nothing_is_stored(tmp_path):
    store = new_store(tmp_path)
    with pytest.raises(ConfigError, match=r"mu_s_pp'\] = nan .*finite"):
        fill(store, points=[{"mu_s_pp": 0.3}, {"mu_s_pp": float("nan")}])
    with pytest.raises(ConfigError, match="finite"):
        fill(store, points=[{"mu_s_pp": math.inf}])
    with pytest.raises(ConfigError, match="real number"):
        fill(store, points=[{"mu_s_pp": "0.3"}])
    with pytest.raises(ConfigError, match="real number"):
        fill(store, points=[{"mu_s_pp": True}])
    with pytest.raises(ConfigError, match="names of point 0"):
        fill(store, points=[{"mu_s_pp": 0.3}, {"mu_r_pp": 0.3}])
    assert store.batch_keys() == [] and store.records() == []
    assert fill(store, points=[{"mu_s_pp": np.float64(0.25)}]) == [{"mu_s_pp": 0.25}]


@pytest.mark.parametrize("stage", ["verfication", "round-0", "round-x", "", None, "Initial"])
def test_unknown_stage_is_refused(tmp_path, stage):
    store = new_store(tmp_path)
    with pytest.raises(ConfigError, match=r"'screening', 'initial'.*round-<n>"):
        fill(store, stage=stage)


def test_stage_names(tmp_path):
    store = new_store(tmp_path, extra_stages=["discovery"])
    for stage in ("screening", "initial", "round-1", "round-12", "verification", "validation",
                  "discovery"):
        fill(store, stage=stage)
    assert len(store.batch_keys()) == 7


@pytest.mark.parametrize("seeds, conditions, match", [
    ([], ["50-50"], "seeds"), ([0, 0], ["50-50"], "seeds"), ([0.5], ["50-50"], "seeds"),
    ([0], [], "conditions"), ([0], "50-50", "conditions"), ([0], ["a", "a"], "conditions"),
])
def test_bad_seeds_and_conditions_are_refused(tmp_path, seeds, conditions, match):
    with pytest.raises(ConfigError, match=match):
        fill(new_store(tmp_path), seeds=seeds, conditions=conditions)


# -- config hash, code version, file -----------------------------------------------------------

def test_config_hash_mismatch_names_both_hashes_and_the_path(tmp_path):
    store = new_store(tmp_path)
    fill(store)
    with pytest.raises(ConfigError) as info:
        CampaignStore(store.path, "cfg-2")
    message = str(info.value)
    assert "'cfg-1'" in message and "'cfg-2'" in message and str(store.path) in message
    other = CampaignStore(store.path, "cfg-2", allow_config_mismatch=True)
    assert other.stored_config_hash == "cfg-1" and other.config_hash == "cfg-2"
    finish(other, other.claim(1))
    done = other.records(status="done")
    assert done[0].config_hash == "cfg-2"  # the config the evaluation actually ran under


def test_bad_constructor_arguments(tmp_path):
    with pytest.raises(ConfigError, match="config_hash"):
        CampaignStore(tmp_path / "a.sqlite", "")
    with pytest.raises(ConfigError, match="memory"):
        CampaignStore(":memory:", "cfg")
    with pytest.raises(ConfigError, match="lease_seconds"):
        CampaignStore(tmp_path / "a.sqlite", "cfg", lease_seconds=0)
    (tmp_path / "junk.sqlite").write_bytes(b"this is not a database" * 100)
    with pytest.raises(ConfigError, match="junk.sqlite"):
        CampaignStore(tmp_path / "junk.sqlite", "cfg")


def test_file_is_wal_and_code_version_defaults_to_git_or_package(tmp_path):
    store = CampaignStore(tmp_path / "sub" / "c.sqlite", "cfg")
    mode = sqlite3.connect(store.path).execute("PRAGMA journal_mode").fetchone()[0]
    assert mode == "wal"
    version = default_code_version()
    assert store.code_version == version
    commit = version.removesuffix("+dirty")
    assert (len(commit) == 40 and all(c in "0123456789abcdef" for c in commit)) \
        or version.startswith("torchdem ")


# -- claiming and recording -------------------------------------------------------------------

def test_a_claim_adds_other_conditions_in_whole_batches(tmp_path):
    store = new_store(tmp_path)
    fill(store, points=POINTS[:1], conditions=("50-50", "70-30"))  # 2 tasks each: one batch of 3 each
    assert [t.condition for t in store.claim(6, batch_size=3)] == ["50-50"] * 2 + ["70-30"] * 2
    (tmp_path / "b").mkdir()
    store = new_store(tmp_path / "b")
    fill(store, conditions=("50-50", "70-30"))  # 6 tasks each
    assert [t.condition for t in store.claim(8, batch_size=3)] == ["50-50"] * 6   # no batch of 2 of 70-30
    assert [t.condition for t in store.claim(4, batch_size=3)] == ["70-30"] * 4   # the oldest condition fills the claim
    with pytest.raises(ConfigError, match="batch_size = 0 is not allowed"):
        store.claim(4, batch_size=0)


def test_claims_do_not_overlap_and_record_finishes_tasks(tmp_path):
    store = new_store(tmp_path)
    fill(store)
    a, b = store.claim(4), store.claim(4)
    assert len(a) == 4 and len(b) == 2 and not {t.task_id for t in a} & {t.task_id for t in b}
    assert store.claim(4) == []
    assert store.counts() == {"pending": 0, "running": 6, "done": 0, "failed": 0}
    rec = store.records(status="running")[0]
    assert rec.claimed_by == f"{socket.gethostname()}:{os.getpid()}" and rec.attempts == 1
    assert finish(store, a) == 4
    assert store.record([(b[0], EvalOutcome.failure("blew up at step 7", 1.0))]) == 1
    assert finish(store, a + b[:1]) == 0  # finished rows are never overwritten
    assert store.counts() == {"pending": 0, "running": 1, "done": 4, "failed": 1}
    failed = store.records(status="failed")[0]
    assert failed.error == "blew up at step 7" and failed.kpis is None and failed.wall_time == 1.0
    assert store.reset_failed() == 1 and store.counts()["pending"] == 1


def test_claim_batches_tasks_of_one_particle_shape_together(tmp_path):
    """With an affinity (the lobe spacing here), each batch holds tasks of one shape where it can,
    the oldest task left starting each batch, and the nearest shape filling a batch that its own
    cannot; without one, task order."""
    from bo.campaign.executor import make_batches
    from torchdem.model import mixture_parameters

    store = new_store(tmp_path)
    spacing = [0.3, 0.15, 0.3, 0.15, 0.225, 0.15, 0.3]  # a design's order, as a DSD interleaves its levels
    points = [{"mu_s_pp": 0.1 * (k + 1), "lobe_spacing_sinter": s} for k, s in enumerate(spacing)]
    fill(store, points=points, seeds=(0,))
    plain = store.claim(2, batch_size=2)
    assert [t.params["lobe_spacing_sinter"] for t in plain] == [0.3, 0.15]
    store.release([t.task_id for t in plain])
    tasks = store.claim(8, batch_size=2, affinity=mixture_parameters)
    shapes = [[t.params["lobe_spacing_sinter"] for t in b] for b in make_batches(tasks, 2)]
    assert shapes == [[0.3, 0.3], [0.15, 0.15], [0.225, 0.3], [0.15]]  # 0.225 pairs with the nearer 0.3
    assert tasks[0].task_id == plain[0].task_id  # the oldest task goes first
    assert mixture_parameters({"mu_s_pp": 0.5, "lobe_spacing_sinter": 0.2, "density_pellet": 3600}) == (
        ("density_pellet", 3600.0), ("lobe_spacing_sinter", 0.2))


def test_record_refuses_foreign_tasks(tmp_path):
    store = new_store(tmp_path)
    fill(store)
    task = store.claim(1)[0]
    forged = EvalTask({"mu_s_pp": 0.99, "e_pp": 0.5}, task.seed, task.condition, task.task_id)
    with pytest.raises(ConfigError, match="does not match store row"):
        finish(store, [forged])
    assert store.counts()["done"] == 0


def _set_lease(store, owner, claimed_at):
    conn = sqlite3.connect(store.path)
    with conn:
        conn.execute("UPDATE evaluations SET status = 'running', claimed_by = ?, claimed_at = ?",
                     (owner, claimed_at))
    conn.close()


def test_lease_of_a_dead_process_is_claimable(tmp_path):
    store = new_store(tmp_path)
    fill(store)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    _set_lease(store, f"{socket.gethostname()}:{dead.pid}", time.time())
    tasks = store.claim(100)
    assert len(tasks) == 6
    assert {r.attempts for r in store.records()} == {1}


def test_live_lease_is_respected_until_it_times_out(tmp_path):
    store = new_store(tmp_path, lease_seconds=0.5)
    fill(store)
    _set_lease(store, f"{socket.gethostname()}:{os.getppid()}", time.time())  # alive, not us
    assert store.claim(100) == []
    _set_lease(store, "other-host:1234", time.time())  # cannot be checked: timeout only
    assert store.claim(100) == []
    time.sleep(0.6)
    assert len(store.claim(100)) == 6


def test_renew_and_release_touch_only_own_claims(tmp_path):
    store = new_store(tmp_path)
    fill(store)
    mine = store.claim(3)
    conn = sqlite3.connect(store.path)
    with conn:
        conn.execute("UPDATE evaluations SET status = 'running', claimed_by = 'other-host:1', "
                     "claimed_at = 0 WHERE status = 'pending'")
    ids = [r.task_id for r in store.records()]
    assert store.renew(ids) == 3
    assert store.release(ids) == 3
    assert store.counts() == {"pending": 3, "running": 3, "done": 0, "failed": 0}
    assert all(r.claimed_by is None for r in store.records(status="pending"))
    assert {t.task_id for t in mine} == {r.task_id for r in store.records(status="pending")}


def test_a_lease_to_another_machine_holds_until_its_end_and_comes_back_by_record_or_release(tmp_path):
    store = new_store(tmp_path, lease_seconds=60.0)
    fill(store)  # tasks 1-6
    leased = store.lease([2, 5], "gpu-host:offload", time.time() + 0.6)
    assert [(t.task_id, t.seed) for t in leased] == [(2, 1), (5, 0)]
    assert {t.task_id for t in store.claim(100)} == {1, 3, 4, 6}  # the lease outlives the 60 s timeout
    time.sleep(0.7)
    assert [t.task_id for t in store.claim(100)] == [2, 5]  # stale at its end, like any lease
    store.release([2, 5])
    store.lease([2, 5], "gpu-host:offload", time.time() + 3600)
    assert finish(store, leased[:1]) == 1  # an outcome that came back is recorded whoever leased it
    assert store.release([5]) == 0  # not this process's
    assert store.release([5], owner="gpu-host:offload") == 1  # the one that did not come back
    assert store.records(status="pending")[0].task_id == 5
    with pytest.raises(ConfigError, match="task id.*pending task of this store.*it is done"):
        store.lease([2], "gpu-host:offload", time.time() + 60)
    with pytest.raises(ConfigError, match="task id.*it is absent"):
        store.lease([99], "gpu-host:offload", time.time() + 60)
    with pytest.raises(ConfigError, match="owner.*'host:name'"):
        store.lease([5], "gpu-host", time.time() + 60)
    with pytest.raises(ConfigError, match="until.*in the future"):
        store.lease([5], "gpu-host:offload", time.time() - 1)
    assert store.records(status="pending")[0].task_id == 5  # a refused lease takes nothing


def test_run_pending_renews_leases_while_a_batch_runs(tmp_path):
    store = new_store(tmp_path, lease_seconds=0.3)  # renewed every 0.1 s
    fill(store, points=POINTS[:1], seeds=(0,))
    seen = {}

    def slow(tasks):
        start = time.time()
        time.sleep(0.45)
        seen["claimed_at"] = store.records(status="running")[0].claimed_at
        seen["start"] = start
        return [EvalOutcome.success({"angle_of_repose": 30.0}, 0.45) for _ in tasks]

    run_pending(store, InProcessExecutor(slow, batch_size=1))
    # The claim precedes the batch, so a claim time after its start is a renewal made during it. (Not
    # start + 0.1: on a loaded machine the renewing thread's first turn came 0.093 s into the batch.)
    assert seen["claimed_at"] > seen["start"]
    assert store.records()[0].attempts == 1 and store.counts()["done"] == 1


def test_run_pending_releases_claims_on_interrupt(tmp_path):
    store = new_store(tmp_path)
    fill(store)

    def interrupted(tasks):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_pending(store, InProcessExecutor(interrupted, batch_size=2))
    assert store.counts() == {"pending": 6, "running": 0, "done": 0, "failed": 0}


# -- queries and artifacts -------------------------------------------------------------------

def test_records_and_arrays(tmp_path):
    store = new_store(tmp_path)
    fill(store, conditions=("50-50", "70-30"))
    first = store.claim(7)  # the oldest condition's tasks, then the next condition's
    assert [t.condition for t in first] == ["50-50"] * 6 + ["70-30"]
    tasks = first + store.claim(100)
    assert [t.condition for t in tasks] == ["50-50"] * 6 + ["70-30"] * 6
    kpis = {t.task_id: {"angle_of_repose": 30.0 + t.task_id, "discharge_rate": 2.0 * t.seed}
            for t in tasks}
    kpis[tasks[-1].task_id]["discharge_rate"] = math.nan  # stored as null, read back as NaN
    finish(store, tasks[:-2], lambda t: kpis[t.task_id])
    finish(store, tasks[-1:], lambda t: kpis[t.task_id])
    arrays = store.arrays("initial")
    assert arrays.X.shape == (11, 2) and arrays.kpis.shape == (11, 2) and arrays.seeds.shape == (11,)
    assert arrays.param_names == ("e_pp", "mu_s_pp")
    assert arrays.kpi_names == ("angle_of_repose", "discharge_rate")
    by_id = {t.task_id: t for t in tasks}
    for row, task_id in enumerate(arrays.task_ids):
        task = by_id[int(task_id)]
        assert arrays.X[row].tolist() == [task.params["e_pp"], task.params["mu_s_pp"]]
        assert arrays.seeds[row] == task.seed and arrays.conditions[row] == task.condition
        assert arrays.kpis[row, 0] == 30.0 + task_id
    assert np.isnan(arrays.kpis[-1, 1]) and np.isfinite(arrays.kpis[:-1]).all()
    sub = store.arrays(condition="70-30", param_names=["mu_s_pp"], kpi_names=["discharge_rate"])
    assert sub.X.shape == (5, 1) and sub.kpis.shape == (5, 1)
    assert store.arrays("round-2").X.shape == (0, 0)
    rec = store.records(condition="50-50", status="done")[0]
    assert rec.task == by_id[rec.task_id] and rec.finished_at >= rec.claimed_at >= rec.created_at
    with pytest.raises(ConfigError, match="status"):
        store.records(status="finished")


def test_artifacts(tmp_path):
    store = new_store(tmp_path)
    assert store.get_artifact("ga", None) is None
    with pytest.raises(KeyError, match="no artifact 'ga'"):
        store.get_artifact("ga")
    result = {"pareto": [[0.1, 0.2], [0.3, 0.4]], "choice": {"mu_s_pp": 0.49}, "n_gen": 100}
    store.put_artifact("ga", result)
    assert CampaignStore(store.path, "cfg-1").get_artifact("ga") == result
    store.put_artifact("ga", {"n_gen": 200})
    assert store.get_artifact("ga") == {"n_gen": 200} and store.artifact_names() == ["ga"]
    with pytest.raises(ConfigError, match="not strict JSON"):
        store.put_artifact("bad", {"x": math.nan})
    with pytest.raises(ConfigError, match="not strict JSON"):
        store.put_artifact("bad", np.zeros(2))


# -- processes -------------------------------------------------------------------------------

def _done_count(db: Path) -> int:
    if not db.exists():
        return 0
    conn = sqlite3.connect(db, timeout=10)
    try:
        return conn.execute("SELECT COUNT(*) FROM evaluations WHERE status = 'done'").fetchone()[0]
    except sqlite3.OperationalError:  # schema not created yet
        return 0
    finally:
        conn.close()


def _executions(log: Path) -> collections.Counter:
    if not log.exists():
        return collections.Counter()
    return collections.Counter(json.loads(line)["key"] for line in log.read_text().splitlines())


def _store_keys(store, **filters) -> set[str]:
    return {task_key(r.params, r.seed, r.condition) for r in store.records(**filters)}


def test_campaign_killed_mid_run_resumes_without_repeating_work(tmp_path):
    db, log, proposals = tmp_path / "c.sqlite", tmp_path / "evals.log", tmp_path / "proposals.log"
    command = [sys.executable, WORKER, "campaign", str(db), str(log), str(proposals)]
    child = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 30
    while _done_count(db) < 8 and child.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    child.send_signal(signal.SIGKILL)
    _, err = child.communicate()
    assert child.returncode == -signal.SIGKILL, err.decode()

    store = CampaignStore(db, "cfg-campaign")
    n_total = (N_INITIAL + N_ROUND) * len(CAMPAIGN_SEEDS) * len(CAMPAIGN_CONDITIONS)
    at_kill = store.counts()
    assert at_kill["done"] >= 8 and at_kill["done"] < n_total, at_kill  # killed mid-run
    done_at_kill = _store_keys(store, status="done")
    in_flight = _store_keys(store, status="running")
    assert len(in_flight) <= CAMPAIGN_BATCH_SIZE
    proposed_before = [json.loads(line) for line in proposals.read_text().splitlines()]
    assert [p["stage"] for p in proposed_before][:1] == ["initial"]

    rerun = subprocess.run(command, capture_output=True, text=True, timeout=60)
    assert rerun.returncode == 0, rerun.stderr
    assert "campaign complete" in rerun.stdout

    assert store.counts() == {"pending": 0, "running": 0, "done": n_total, "failed": 0}
    records = store.records()
    keys = [task_key(r.params, r.seed, r.condition) for r in records]
    assert len(set(keys)) == n_total  # one done row per (params, seed, condition)
    runs = _executions(log)
    assert set(runs) == set(keys)  # every evaluation ran ...
    repeated = {k for k, n in runs.items() if n > 1}
    assert repeated <= in_flight and max(runs.values()) <= 2  # ... once, unless in flight at kill
    assert not repeated & done_at_kill
    assert all(r.attempts == 1 for r in records
               if task_key(r.params, r.seed, r.condition) not in in_flight)
    # proposals made before the kill were reused, not made again
    proposed = [json.loads(line) for line in proposals.read_text().splitlines()]
    assert [p["stage"] for p in proposed] == ["initial", "round-1"]
    assert store.batch("initial", "design", lambda: pytest.fail("re-proposed"),
                       seeds=CAMPAIGN_SEEDS, conditions=CAMPAIGN_CONDITIONS) \
        == proposed_before[0]["points"]
    assert store.get_artifact("summary")["best"].keys() == {"e_pp", "mu_s_pp"}

    again = subprocess.run(command, capture_output=True, text=True, timeout=60)
    assert again.returncode == 0, again.stderr
    assert _executions(log) == runs  # a finished campaign re-runs nothing ...
    assert len(proposals.read_text().splitlines()) == 2  # ... and proposes nothing
    assert store.integrity_check() == "ok"


def test_two_processes_share_one_store(tmp_path):
    db, log, go = tmp_path / "w.sqlite", tmp_path / "evals.log", tmp_path / "go"
    command = [sys.executable, WORKER, "worker", str(db), str(log), str(go)]
    workers = [subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
               for _ in range(2)]
    deadline = time.monotonic() + 30
    while len(list(tmp_path.glob("go.ready.*"))) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)  # both have imported and opened the store: start the race
    go.touch()
    results = []
    for worker in workers:
        out, err = worker.communicate(timeout=60)
        assert worker.returncode == 0, err
        results.append(json.loads(out))
    assert results[0]["points"] == results[1]["points"]  # the batch race has one winner
    assert results[0]["n_done"] + results[1]["n_done"] == 36

    store = CampaignStore(db, "cfg-workers")
    assert store.integrity_check() == "ok"
    assert store.counts() == {"pending": 0, "running": 0, "done": 36, "failed": 0}
    assert store.batch_keys() == [("initial", "shared")]
    records = store.records()
    keys = [task_key(r.params, r.seed, r.condition) for r in records]
    assert len(set(keys)) == len(keys) == 36
    runs = _executions(log)
    assert set(runs) == set(keys) and set(runs.values()) == {1}  # nothing ran twice
    assert len({r.claimed_by for r in records}) == 2  # both processes did work


def test_a_run_asked_for_again_in_another_batch_is_not_computed_again(tmp_path):
    """Shared runs: same parameters, seed and condition -> the stored result, no new DEM run."""
    store = new_store(tmp_path)
    fill(store, key="first", seeds=(0, 1))
    first = store.claim(100, "initial")
    finish(store, first)
    assert store.counts("initial") == {"pending": 0, "running": 0, "done": 6, "failed": 0}
    # a longer seed list and one new point: only the new seed and the new point run
    points = [POINTS[2], {"mu_s_pp": 0.9, "e_pp": 0.3}]  # POINTS[2] with its keys in another order
    fill(store, key="second", points=points, seeds=(0, 1, 2))
    assert store.counts("initial") == {"pending": 4, "running": 0, "done": 8, "failed": 0}
    reused = [r for r in store.records("initial", batch_key="second", status="done")]
    original = {(json.dumps(r.params, sort_keys=True), r.seed): r for r in store.records("initial", batch_key="first")}
    for r in reused:
        src = original[json.dumps(r.params, sort_keys=True), r.seed]
        assert r.reused_from == src.task_id and r.kpis == src.kpis and r.wall_time is None
    # a pending twin is completed when its run finishes elsewhere
    fill(store, key="third", points=[points[1]], seeds=(5,))
    task = [t for t in store.claim(100, "initial") if t.params == points[1] and t.seed == 0]
    finish(store, task)
    assert [r.reused_from for r in store.records("initial", batch_key="third", status="done")] == []  # seed 5: not the same run
    fill(store, key="fourth", points=[points[1]], seeds=(1,))
    twin = store.records("initial", batch_key="fourth")[0]
    assert twin.status == "pending"  # seed 1 of that point is running in round-1, not done
    store.release([t.task_id for t in store.records("initial", status="running")])
    claimed = store.claim(100, "initial")
    store.release([twin.task_id])  # the twin waits pending while its run goes on in "second"
    run_1 = [t for t in claimed if t.params == points[1] and t.seed == 1 and t.task_id != twin.task_id]
    finish(store, run_1)
    twin = store.records("initial", batch_key="fourth")[0]
    assert twin.status == "done" and twin.reused_from == run_1[0].task_id
    # another stage evaluates another model: nothing is shared with it
    fill(store, stage="round-1", key="other", points=[POINTS[0]], seeds=(0,))
    assert store.counts("round-1")["pending"] == 1
    # computed evaluations: 6 + 2 in round-1 (the new point's seeds 0 and 1)
    computed = store.counts("initial", computed_only=True)
    assert computed["done"] == 8 and store.counts("initial")["done"] == 11
    # failures are not shared
    fill(store, stage="round-4", key="fifth", points=[{"mu_s_pp": 0.2, "e_pp": 0.2}], seeds=(0,))
    (t,) = store.claim(100, "round-4")
    store.record([(t, EvalOutcome.failure("BlowUpError: x", 1.0))])
    fill(store, stage="round-4", key="sixth", points=[{"mu_s_pp": 0.2, "e_pp": 0.2}], seeds=(0,))
    assert store.records("round-4", batch_key="sixth")[0].status == "pending"
    # share=False: a fresh rerun (verification on a new machine) runs every task
    fill(store, key="shared", points=[POINTS[0]], seeds=(0, 1))
    assert {r.status for r in store.records("initial", batch_key="shared")} == {"done"}
    store.batch("initial", "fresh", lambda: [POINTS[0]], seeds=(0, 1), conditions=("50-50",), share=False)
    assert {r.status for r in store.records("initial", batch_key="fresh")} == {"pending"}


def test_retry_failed_puts_failed_runs_back_only_when_asked(tmp_path):
    """``retry_failed: true`` (torchdem-calibrate, -screen, -study, -discover) re-queues the failed
    runs of a resumed store, e.g. after ``sim.retry_time_steps`` was added; false leaves them."""
    from bo.cli.common import requeue_failed

    store = new_store(tmp_path)
    fill(store)
    claimed = store.claim(6)
    assert store.record([(claimed[0], EvalOutcome.failure("BlowUpError: ...", 1.0))]) == 1
    said = []
    assert requeue_failed({"retry_failed": False}, store, said.append) == 0
    assert requeue_failed({}, store, said.append) == 0 and store.counts()["failed"] == 1 and not said
    assert requeue_failed({"retry_failed": True}, store, said.append) == 1
    assert store.counts()["failed"] == 0 and store.counts()["pending"] == 1
    assert said == [f"retry_failed: 1 failed run(s) of {store.path} back in the queue"]
    with pytest.raises(ConfigError, match=r"retry_failed = 'yes'.*true or false"):
        requeue_failed({"retry_failed": "yes"}, store)


def test_a_batch_key_runs_one_design_of_a_stage_and_leaves_the_other_pending(tmp_path):
    """The surrogate's initial design changes when the screening's selection does: the stage then
    holds the old design's pending runs beside the new one. Claimed by batch key, only the design
    asked for runs; the old one stays pending (nothing lost) and runs if the campaign asks for it
    again. A key without its stage is refused."""
    store = new_store(tmp_path)
    fill(store, key="old", points=POINTS[:2], seeds=(0,))
    fill(store, key="new", points=POINTS[2:], seeds=(0, 1))
    ran = []

    def evaluate(tasks):
        ran.extend(tasks)
        return [EvalOutcome.success({"angle_of_repose": 30.0}, 0.1) for _ in tasks]

    summary = run_pending(store, InProcessExecutor(evaluate, batch_size=1), "initial", batch_key="new")
    assert summary.n_done == 2 and {tuple(sorted(t.params.items())) for t in ran} == {
        tuple(sorted(POINTS[2].items()))}
    assert store.counts("initial", batch_key="new") == {"pending": 0, "running": 0, "done": 2, "failed": 0}
    assert store.counts("initial", batch_key="old")["pending"] == 2
    assert store.claim(10, stage="initial", batch_key="new") == []
    run_pending(store, InProcessExecutor(evaluate, batch_size=1), "initial", batch_key="old")
    assert store.counts("initial")["done"] == 4
    with pytest.raises(ConfigError, match="batch_key = 'old' is not allowed; expected a key together with its stage"):
        store.claim(1, batch_key="old")


def test_a_withdrawn_batch_keeps_its_results_and_gets_its_runs_back_when_asked_again(tmp_path):
    """withdraw_batch takes a design's unfinished runs away (they no longer count as work left) and
    keeps what was computed; asked for again, the batch has every run back, pending, the computed
    ones still done. A batch with nothing computed goes whole; a live lease refuses."""
    store = new_store(tmp_path)
    fill(store, key="old", points=POINTS, seeds=(0,))
    fill(store, key="gone", points=POINTS[2:], seeds=(1,))
    finish(store, store.claim(1, stage="initial", batch_key="old"))
    store.claim(1, stage="initial", batch_key="old")  # a live lease of this process
    with pytest.raises(ConfigError, match=r"running under a live lease; stop the campaign"):
        store.withdraw_batch("initial", "old")
    store.release([r.task_id for r in store.records("initial", status="running")])
    assert store.withdraw_batch("initial", "old") == 2
    assert store.counts("initial", batch_key="old") == {"pending": 0, "running": 0, "done": 1, "failed": 0}
    assert store.withdraw_batch("initial", "gone") == 1
    assert [k for _, k in store.batch_keys("initial")] == ["old"]
    with pytest.raises(ConfigError, match=r"no such batch; stored: \['old'\]"):
        store.withdraw_batch("initial", "gone")
    assert fill(store, key="old", points=POINTS, seeds=(0,)) == POINTS
    assert store.counts("initial", batch_key="old") == {"pending": 2, "running": 0, "done": 1, "failed": 0}
    assert sorted(r.point_index for r in store.records("initial", batch_key="old")) == [0, 1, 2]
