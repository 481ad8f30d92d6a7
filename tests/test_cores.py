"""Tests of bo.campaign.cores: the core share of a local cluster's workers, and a draw down run that
changes its threads mid-way. The executor's side (publishing the batches in flight) is checked on
a real cluster in tests/test_executor.py::test_dask_executor_matches_in_process."""
from __future__ import annotations

import os

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from bo.campaign import cores
from bo.campaign.cores import CoreShare, ThreadFollower
from bo.campaign.dem import evaluate_batch
from bo.campaign.executor import EvalTask
from bo.cli.calibrate import calibration_model_from
from bo.cli.common import plain_config
from torchdem.cli import CONF_DIR
from torchdem.errors import ConfigError
from torchdem.measured import load_measured


@pytest.mark.parametrize("cores, busy, threads", [(2, 0, 2), (2, 1, 2), (2, 2, 1), (2, 3, 1), (16, 5, 3),
                                                  (16, 1, 16), (1, 1, 1)])
def test_a_batch_takes_its_share_of_the_cores(tmp_path, cores, busy, threads):
    share = CoreShare.create(cores, directory=str(tmp_path))
    share.publish(busy)
    assert share.busy() == busy and share.threads() == threads


@pytest.mark.parametrize("n_workers, shared", [(3, 2), (2, 2), (1, 1), (None, 2)])
def test_a_local_cluster_shares_no_more_cores_than_the_machine_has(monkeypatch, n_workers, shared):
    """Three workers on two cores share two: a stage's last batch runs on the machine's two, never
    three."""
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    assert cores.local_cores(n_workers) == shared


def test_an_unreadable_share_leaves_a_batch_on_one_thread(tmp_path):
    share = CoreShare.create(4, directory=str(tmp_path))
    assert share.threads() == 4                     # nothing in flight yet
    with open(share.path, "w") as fh:
        fh.write("two")
    assert share.busy() is None and share.threads() == 1
    share.remove()
    assert not os.path.exists(share.path) and share.threads() == 1
    share.remove()                                  # twice is harmless


@pytest.mark.parametrize("cores", [0, -1, 1.5, True, "2"])
def test_bad_core_counts_are_named(cores):
    with pytest.raises(ConfigError, match=r"cores = .* expected an int >= 1"):
        CoreShare("/nonexistent", cores)


def test_a_negative_busy_count_is_refused(tmp_path):
    share = CoreShare.create(2, directory=str(tmp_path))
    with pytest.raises(ConfigError, match=r"busy = -1 .* expected an int >= 0"):
        share.publish(-1)


class _Clock:
    """Stand-ins for the follower's clocks: wall time, the machine's busy CPU seconds and this
    process's own, advanced by hand."""

    def __init__(self, monkeypatch):
        self.now, self.busy, self.own = 100.0, 5000.0, 10.0
        monkeypatch.setattr(cores.time, "monotonic", lambda: self.now)
        monkeypatch.setattr(cores, "machine_busy_seconds", lambda: self.busy)
        monkeypatch.setattr(cores, "own_cpu_seconds", lambda: self.own)

    def advance(self, seconds: float, own_cores: float, other_cores: float) -> None:
        self.now += seconds
        self.own += own_cores * seconds
        self.busy += (own_cores + other_cores) * seconds


def _follower(tmp_path, cores: int) -> tuple[CoreShare, ThreadFollower]:
    """A share of ``cores`` with one batch in flight, and a follower on a machine of as many cores."""
    share = CoreShare.create(cores, directory=str(tmp_path))
    share.publish(1)
    return share, ThreadFollower(share, period_s=1.0, machine_cores=cores)


def test_the_follower_takes_the_share_where_the_cores_are_idle(tmp_path, monkeypatch):
    clock = _Clock(monkeypatch)
    share, follow = _follower(tmp_path, 2)
    assert follow() == 1                            # nothing measured yet
    clock.advance(0.5, own_cores=1.0, other_cores=0.0)
    assert follow() == 1                            # decided at most once a period
    clock.advance(0.5, own_cores=1.0, other_cores=0.05)
    assert follow() == 2                            # the other core idle: take it
    share.publish(2)                                # a batch starts beside it
    clock.advance(1.0, own_cores=2.0, other_cores=0.0)
    assert follow() == 1


def test_the_follower_leaves_cores_that_other_processes_use(tmp_path, monkeypatch):
    """A test suite or another campaign beside the workers: the share says 2, the machine says 1."""
    clock = _Clock(monkeypatch)
    _, follow = _follower(tmp_path, 2)
    follow()
    clock.advance(1.0, own_cores=1.0, other_cores=0.9)
    assert follow() == 1
    clock.advance(1.0, own_cores=1.0, other_cores=0.3)
    assert follow() == 2
    clock.advance(1.0, own_cores=2.0, other_cores=1.0)   # it came back
    assert follow() == 1
    # on 16 cores with 8 taken by others, a share of 16 is capped at the 8 left
    _, wide = _follower(tmp_path, 16)
    wide()
    clock.advance(1.0, own_cores=1.0, other_cores=8.0)
    assert wide() == 8


def test_without_proc_stat_the_share_alone_decides(tmp_path, monkeypatch):
    monkeypatch.setattr(cores, "machine_busy_seconds", lambda: None)
    share = CoreShare.create(2, directory=str(tmp_path))
    share.publish(1)
    assert ThreadFollower(share, period_s=0.0)() == 2


class _Switch:
    """``threads`` callable: 1 thread for the first ``flip`` calls, then 2; counts its calls."""

    def __init__(self, flip: int):
        self.flip, self.calls = flip, 0

    def __call__(self) -> int:
        self.calls += 1
        return 1 if self.calls <= self.flip else 2


def test_a_run_that_takes_more_threads_mid_way_reports_the_same_kpis():
    """The mini box (~3 s of DEM): one run on one thread, the same run switched from one thread to
    two a third of the way in, and back: the KPIs are the same to the last bit, and the caller's
    thread count is restored."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        plain = plain_config(compose(config_name="calibrate", overrides=["profile=cpu", "run.loose_fraction=0.2"]))
    measured = load_measured("mini_box_twin.json")
    model, _ = calibration_model_from({**plain, "measured": "mini_box_twin.json"}, measured)
    task = EvalTask({"mu_s_pp": 0.5}, 0, "50-50")
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        [plain_run] = evaluate_batch(model, [task])
        test = model.test_for("50-50", [dict(task.params)])
        switch = _Switch(flip=40)
        result = test.run_members([(0, 0, 0)], threads=switch)
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
    assert switch.calls > 80                        # asked at the start and at every load-cell sample
    np.testing.assert_equal({k: float(result.kpis[0].get(k, np.nan)) for k in plain_run.kpis}, plain_run.kpis)


def test_share_cores_is_a_flag_of_the_executor_config():
    from bo.cli.common import executor_settings_from

    assert executor_settings_from({"kind": "dask", "batch_size": 1}).share_cores is True
    assert executor_settings_from({"kind": "dask", "batch_size": 1, "share_cores": False}).share_cores is False
    with pytest.raises(ConfigError, match=r"executor: share_cores = 'yes' .* true or false"):
        executor_settings_from({"kind": "dask", "batch_size": 1, "share_cores": "yes"})
