"""Tests of bo.campaign.progress: runs done and left per cost class, worker time spent and left."""
from __future__ import annotations

import hashlib
import subprocess
import sys
from pathlib import Path

import pytest

from bo.campaign.executor import EvalOutcome
from bo.campaign.progress import store_progress
from bo.campaign.store import CampaignStore
from torchdem.errors import ConfigError

LAB = "50-50|mirror=True|slice_depth=0.1"
ROOT = Path(__file__).resolve().parents[1]


def _point(spacing: float, mu: float, density: float = 3449.0) -> dict:
    return {"lobe_spacing_sinter": spacing, "mu_s_pp": mu, "density_sinter": density}


def _store(tmp_path) -> CampaignStore:
    """Four points at lobe spacing 0.15 (densities differ: one class), two at 0.3, one at 0.27
    (the 0.275 class), on the lab geometry, seed 0; a second batch repeats the first point."""
    store = CampaignStore(tmp_path / "s.sqlite", "cfg", code_version="test")
    store.batch("screening", "design", lambda: [_point(0.15, 0.3), _point(0.15, 0.5, 3100.0), _point(0.15, 0.7),
                                                _point(0.15, 0.9), _point(0.3, 0.3), _point(0.3, 0.5),
                                                _point(0.27, 0.4)],
                seeds=[0], conditions=[LAB])
    return store


def _finish(store, tasks, wall, ok=True, ended=None, jammed=None):
    kpis = {"angle_of_repose_deg": 30.0, **({} if ended is None else {"discharge_ended": float(ended)}),
            **({} if jammed is None else {"discharge_jammed": float(jammed)})}
    outcome = EvalOutcome.success(kpis, wall) if ok else EvalOutcome.failure("x", wall)
    store.record([(t, outcome) for t in tasks])


def test_costs_per_class_batches_shared_runs_and_bounds(tmp_path):
    store = _store(tmp_path)
    tasks = {(t.params["lobe_spacing_sinter"], t.params["mu_s_pp"]): t for t in store.claim(7, "screening")}
    _finish(store, [tasks[(0.15, 0.3)], tasks[(0.15, 0.5)]], 100.0)  # one batch of two: 50 s per run
    _finish(store, [tasks[(0.15, 0.7)]], 30.0)
    _finish(store, [tasks[(0.3, 0.3)]], 400.0, ok=False)               # failed: spent, not a cost figure
    store.release([tasks[(0.15, 0.9)].task_id, tasks[(0.3, 0.5)].task_id, tasks[(0.27, 0.4)].task_id])
    # the same run asked for again in its stage, and one more pending copy: the first is done
    # with the stored result at no cost, the second counts once as left
    store.batch("screening", "again", lambda: [_point(0.15, 0.3), _point(0.15, 0.9)], seeds=[0], conditions=[LAB])

    progress = store_progress(store.path)

    assert progress.status == {"screening": {"done": 4, "pending": 4, "failed": 1}}
    assert progress.batches == {"screening": {"design": {"done": 3, "pending": 3, "failed": 1},
                                              "again": {"done": 1, "pending": 1}}}
    by_shape = {c.shape: c for c in progress.classes}
    assert set(by_shape) == {(("lobe_spacing_sinter", 0.15),), (("lobe_spacing_sinter", 0.275),),
                             (("lobe_spacing_sinter", 0.3),)}
    low = by_shape[(("lobe_spacing_sinter", 0.15),)]
    assert (low.geometry, low.done, low.remaining, low.failed) == ("mirror=True|slice_depth=0.1", 3, 1, 0)
    assert low.seconds_per_run == pytest.approx(50.0)  # median of 50, 50, 30
    assert (low.borrowed, low.bound) == (False, "")
    mid = by_shape[(("lobe_spacing_sinter", 0.275),)]
    high = by_shape[(("lobe_spacing_sinter", 0.3),)]
    # no finished run at 0.275 or 0.3: both borrow the only class with one, of smaller spacing
    assert (mid.remaining, mid.seconds_per_run, mid.bound) == (1, pytest.approx(50.0), "at least")
    assert (high.remaining, high.failed, high.seconds_per_run, high.bound) == (1, 1, pytest.approx(50.0), "at least")
    assert progress.spent_s == pytest.approx(100.0 + 30.0 + 400.0)
    assert progress.remaining_runs == 3
    assert progress.remaining_s == pytest.approx(3 * 50.0)
    assert progress.remaining_bound == "at least"

    left = store.claim(4, "screening")
    _finish(store, [t for t in left if t.params["lobe_spacing_sinter"] == 0.3], 900.0)
    store.release([t.task_id for t in left if t.params["lobe_spacing_sinter"] != 0.3])
    again = {c.shape: c for c in store_progress(store.path).classes}
    # 0.275 now borrows from 0.3 (the nearer class), an upper bound
    assert again[(("lobe_spacing_sinter", 0.275),)].bound == "at most"
    assert again[(("lobe_spacing_sinter", 0.275),)].seconds_per_run == pytest.approx(900.0)
    assert again[(("lobe_spacing_sinter", 0.3),)].bound == ""


def test_the_store_is_only_read_and_a_bad_path_is_named(tmp_path):
    store = _store(tmp_path)
    before = hashlib.sha256(Path(store.path).read_bytes()).hexdigest()
    store_progress(store.path)
    assert hashlib.sha256(Path(store.path).read_bytes()).hexdigest() == before
    with pytest.raises(ConfigError, match="does not exist"):
        store_progress(tmp_path / "missing.sqlite")
    (tmp_path / "junk.sqlite").write_text("not a database")
    with pytest.raises(ConfigError, match="not a campaign store"):
        store_progress(tmp_path / "junk.sqlite")


def test_status_script_reports_a_store(tmp_path):
    store = _store(tmp_path)
    tasks = store.claim(1, "screening")
    _finish(store, tasks, 120.0)
    out = subprocess.run([sys.executable, str(ROOT / "scripts" / "campaign_status.py"), str(store.path),
                          "--workers", "2"], capture_output=True, text=True, check=True).stdout
    assert "screening: 1 done, 6 pending" in out
    assert "| mirror=True|slice_depth=0.1 lobe_spacing_sinter 0.15 | 1 | 3 | 0 | 2.0 min |" in out
    # 3 runs at 0.15 (2 min) + 1 at 0.275 + 2 at 0.3 borrowing it: 12 min of worker time, at least
    assert "Left in the store: 6 runs, at least 0.2 h of worker time, at least 0.1 h on 2 workers" in out
    # a surrogate stage of two designs lists each (surrogate.reuse_designs names them); the screening does not
    store.batch("initial", "first", lambda: [_point(0.15, 0.4)], seeds=[0], conditions=[LAB])
    store.batch("initial", "second", lambda: [_point(0.15, 0.6)], seeds=[0], conditions=[LAB])
    store.batch("screening", "more", lambda: [_point(0.15, 0.2)], seeds=[0], conditions=[LAB])
    out = subprocess.run([sys.executable, str(ROOT / "scripts" / "campaign_status.py"), str(store.path)],
                         capture_output=True, text=True, check=True).stdout
    assert "  - batch first: 1 pending\n  - batch second: 1 pending" in out
    assert "batch design" not in out
    assert "All stores" not in out
    # two stores: what each made and the sum; a run taken from another store counts where it was made
    other = CampaignStore(tmp_path / "other.sqlite", "cfg", code_version="test")
    other.batch("screening", "design", lambda: [_point(0.15, 0.4), _point(0.15, 0.6)], seeds=[0], conditions=[LAB])
    _finish(other, other.claim(2, "screening"), 600.0)  # one batch of two: 5 min each
    other.batch("screening", "adopted", lambda: [_point(0.15, 0.3)], seeds=[0], conditions=[LAB])
    assert other.adopt("screening", "adopted", store.records("screening", status="done"), str(store.path)) == 1
    out = subprocess.run([sys.executable, str(ROOT / "scripts" / "campaign_status.py"), str(store.path),
                          str(other.path)], capture_output=True, text=True, check=True).stdout
    assert f"| {store.path} | 1 | 0.0 h |\n| {other.path} | 2 | 0.2 h |\n| all 2 | 3 | 0.2 h |" in out
    assert "Together: 3 DEM runs, 0.2 h of worker time, 0.1 h on 2 workers." in out


def test_runs_whose_discharge_had_not_ended_are_counted(tmp_path):
    """Done runs by ``discharge_ended``: 1, 0, or absent (runs made before it was recorded); and
    those that jammed."""
    store = _store(tmp_path)
    tasks = store.claim(4, "screening")
    _finish(store, tasks[:1], 100.0, ended=True, jammed=False)
    _finish(store, tasks[1:2], 100.0, ended=True, jammed=True)
    _finish(store, tasks[2:3], 100.0, ended=False)
    _finish(store, tasks[3:], 100.0)
    assert store_progress(store.path).discharge == {"ended": 2, "not ended": 1, "not recorded": 1, "jammed": 1}
    out = subprocess.run([sys.executable, str(ROOT / "scripts" / "campaign_status.py"), str(store.path)],
                         capture_output=True, text=True, check=True).stdout
    assert "Discharge of the done runs: 2 ended, 1 stopped while the upper box still emptied" in out
    assert "1 made before runs recorded it; 1 jammed (less than 5% of the fill" in out


def test_a_larger_clump_scale_is_a_cheaper_class(tmp_path):
    """Runs of another clump scale are a class of their own, and a figure borrowed from a larger scale
    (fewer, larger grains: cheaper) is a lower bound, from a smaller one an upper bound."""
    store = CampaignStore(tmp_path / "s.sqlite", "cfg", code_version="test")
    points = [{"lobe_spacing_sinter": 0.25, "clump_scale_sinter": k, "mu_s_pp": mu}
              for k, mu in ((1.0, 0.3), (1.3, 0.3), (1.15, 0.3))]
    store.batch("screening", "design", lambda: points, seeds=[0], conditions=[LAB])
    tasks = {t.params["clump_scale_sinter"]: t for t in store.claim(3, "screening")}
    _finish(store, [tasks[1.3]], 60.0)
    store.release([tasks[1.0].task_id, tasks[1.15].task_id])
    by_scale = {dict(c.shape)["clump_scale_sinter"]: c for c in store_progress(store.path).classes}
    assert set(by_scale) == {1.0, 1.15, 1.3}
    assert (by_scale[1.3].seconds_per_run, by_scale[1.3].bound) == (pytest.approx(60.0), "")
    assert (by_scale[1.0].seconds_per_run, by_scale[1.0].bound) == (pytest.approx(60.0), "at least")
    _finish(store, [store.claim(1, "screening")[0]], 100.0)  # the oldest pending: scale 1.0
    again = {dict(c.shape)["clump_scale_sinter"]: c for c in store_progress(store.path).classes}
    assert again[1.0].seconds_per_run == pytest.approx(100.0) and again[1.0].bound == ""
    # 1.15 is relatively nearer 1.3 (0.15 / 1.3) than 1.0 (0.15 / 1.15): it borrows the cheaper class's figure
    assert (again[1.15].seconds_per_run, again[1.15].bound) == (pytest.approx(60.0), "at least")


def test_status_script_sets_a_profiles_plan_beside_the_store(tmp_path):
    """``--profile``: the calibration's plan, stage by stage, with the store's runs of each condition
    (``bo.calibration.plan``); a condition without runs takes the other store's (``--costs-from``)."""
    store = CampaignStore(tmp_path / "round.sqlite", "cfg", code_version="test")
    store.batch("screening", "design", lambda: [{"mu_r_ss": 0.15}, {"mu_r_ss": 0.4}], seeds=[0], conditions=["50-50"])
    _finish(store, store.claim(1, "screening"), 960.0)
    other = CampaignStore(tmp_path / "probe.sqlite", "cfg", code_version="test")
    other.batch("validation", "set", lambda: [{"mu_r_ss": 0.3}], seeds=[0], conditions=["75-25"])
    _finish(other, other.claim(1, "validation"), 480.0)
    script = [sys.executable, str(ROOT / "scripts" / "campaign_status.py")]
    out = subprocess.run(script + [str(store.path), "--profile", "lab_round", "--costs-from", str(other.path)],
                         capture_output=True, text=True, check=True).stdout
    assert "Plan of profile=lab_round: at most 80 DEM runs: screening 18 (9 points x 2 seeds on 50-50)" in out
    assert "| screening | 50-50 | 18 | 1 | 17 | 16.0 min |" in out
    assert "| surrogate | 75-25 | 21 | 0 | 21 | 8.0 min (--costs-from) |" in out
    assert "| validation | 25-75 | 5 | 0 | 5 | 16.0 min (all conditions) |" in out
    # 17 + 21 + 5 + 5 + 5 runs at 16 min, 21 + 5 at 8 min: 1,056 min of worker time
    assert "Left of the plan: at most 79 runs, 17.6 h of worker time, 8.8 h on 2 workers (a condition" in out
    bad = subprocess.run(script + [str(store.path), str(other.path), "--profile", "lab_round"],
                         capture_output=True, text=True)
    assert bad.returncode != 0 and "give the one store of that campaign, not 2" in bad.stderr


def test_a_seeded_store_counts_the_copied_runs_where_they_were_made(tmp_path):
    """A store seeded with another campaign's (``copy_store``, as ``store_from`` does) notes the rows
    that came with it: they are spent in the source, not again in the copy, and a sum over both
    stores counts each run once. The plan of a campaign that reads the source's surrogate design as
    data (``reuse_designs``) counts as its own the shared screening, its own design's runs and the
    checks made after them; a copy read as the source's own campaign (``make run``'s) counts
    everything."""
    from bo.calibration.plan import CampaignPlan, StagePlan, plan_progress
    from bo.campaign.progress import run_costs
    from bo.campaign.store import copy_store

    source = CampaignStore(tmp_path / "round.sqlite", "cfg", code_version="test")
    for stage, key, n in (("screening", "dsd", 2), ("initial", "old", 3), ("verification", "set/a", 2)):
        source.batch(stage, key, lambda n=n: [{"mu_r_ss": 0.1 * (i + 1)} for i in range(n)], seeds=[0],
                     conditions=["50-50"])
        _finish(source, source.claim(n, stage), 60.0 * n)  # one batch: 60 s a run
    copy_store(source.path, tmp_path / "split.sqlite")
    split = CampaignStore(tmp_path / "split.sqlite", "cfg", code_version="test")
    split.batch("initial", "new", lambda: [{"mu_r_ss": 0.25, "mu_s_pp": 0.7}], seeds=[0], conditions=["50-50"])
    _finish(split, split.claim(1, "initial"), 500.0)

    costs = run_costs(split.path)
    assert [c.copied for c in costs] == [True] * 7 + [False]
    assert all(c.seconds == pytest.approx(60.0) for c in costs[:7])  # still the class's cost figure
    progress = store_progress(split.path)
    assert progress.spent_s == pytest.approx(500.0)
    assert (progress.copied_from, progress.copied_runs, progress.copied_s) == (
        str(source.path), 7, pytest.approx(420.0))
    out = subprocess.run([sys.executable, str(ROOT / "scripts" / "campaign_status.py"), str(source.path),
                          str(split.path)], capture_output=True, text=True, check=True).stdout
    assert "| all 2 | 8 | 0.3 h |" in out  # 7 runs at 60 s and one of 500 s, each counted once
    assert f"copied from {source.path}: 7 finished runs (0.1 h) came with the copy" in out

    stages = (StagePlan("screening", {"50-50": 2}, ""), StagePlan("surrogate", {"50-50": 4}, "", exact=False),
              StagePlan("verification", {"50-50": 2}, ""))
    done = lambda plan: {r.stage: r.done for r in plan_progress(plan, split.path)}  # noqa: E731
    assert done(CampaignPlan(stages, earlier_designs=("old",))) == {"screening": 2, "surrogate": 1, "verification": 0}
    # a design of its own after the check: the check was of an earlier calibrated set
    assert done(CampaignPlan(stages)) == {"screening": 2, "surrogate": 4, "verification": 0}
    copy_store(source.path, tmp_path / "make_run.sqlite")
    assert {r.stage: r.done for r in plan_progress(CampaignPlan(stages), tmp_path / "make_run.sqlite")} == {
        "screening": 2, "surrogate": 3, "verification": 2}
