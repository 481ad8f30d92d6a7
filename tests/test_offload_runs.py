"""``scripts/offload_runs.py``: tasks leased out of a campaign store, run from a file on a machine that
cannot open the store (here: the same one, on the mini box of ``profile=smoke``), and recorded back; the
campaign leaves leased tasks alone; a model-changing override is refused."""
import importlib.util
import json
from pathlib import Path

import pytest

from bo.campaign.dem import evaluate_batch
from bo.campaign.executor import EvalTask
from bo.campaign.store import CampaignStore
from bo.cli.common import config_hash

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("offload_runs", ROOT / "scripts" / "offload_runs.py")
offload = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(offload)

POINTS = [{"mu_s_pp": 0.3, "mu_s_ss": 0.9}, {"mu_s_pp": 0.8, "mu_s_ss": 0.4}]


def test_leased_runs_come_back_as_the_campaign_would_have_run_them(tmp_path, capsys):
    plain = offload.compose_plain(["profile=smoke"])
    digest = config_hash(plain, offload.HASHED["calibrate"])
    path = tmp_path / "c.sqlite"
    store = CampaignStore(path, digest)
    store.batch("screening", "k", lambda: POINTS, seeds=[0], conditions=["50-50"])  # tasks 1, 2
    tasks_file, done = tmp_path / "tasks.json", tmp_path / "done.json"
    offload.main(["lease", str(path), "profile=smoke", "--tasks", "2", "--owner", "gpu:offload", "--hours", "1",
                  "--out", str(tasks_file)])
    assert [t.task_id for t in store.claim(10)] == [1]  # the campaign's claim leaves task 2 alone
    with pytest.raises(SystemExit, match="change the model.*execution settings"):
        offload.main(["run", str(tasks_file), "sim.dtype=float32", "--out", str(done)])
    offload.main(["run", str(tasks_file), "sim.device=cpu", "--out", str(done), "--every", "0.5"])
    out = capsys.readouterr().out
    assert "tasks [2]: 0.0" in out and " s simulated in " in out and "task 2: angle_of_repose_deg " in out
    offload.main(["record", str(path), str(done)])
    (row,) = [r for r in store.records() if r.task_id == 2]
    assert row.status == "done" and row.wall_time > 0
    # the same task run here, in process, as the campaign's executor runs it: the same KPIs
    model = offload.model_from(plain)
    (here,) = evaluate_batch(model, [EvalTask(POINTS[1], 0, "50-50", 2)])
    assert row.kpis == pytest.approx(here.kpis, rel=1e-6, nan_ok=True)
    assert row.kpis["mass_lower_box_kg"] > 0.3  # a real discharge of the mini box's ~0.8 kg


def test_release_gives_back_what_did_not_come_back_and_bad_input_is_named(tmp_path):
    path = tmp_path / "c.sqlite"
    digest = config_hash(offload.compose_plain(["profile=smoke"]), offload.HASHED["calibrate"])
    store = CampaignStore(path, digest)
    store.batch("screening", "k", lambda: POINTS, seeds=[0], conditions=["50-50"])
    offload.main(["lease", str(path), "profile=smoke", "--tasks", "1", "2", "--owner", "gpu:offload",
                  "--out", str(tmp_path / "t.json")])
    assert json.loads((tmp_path / "t.json").read_text())["config_hash"] == digest
    assert store.claim(10) == []
    offload.main(["release", str(path), "--tasks", "1", "2", "--owner", "gpu:offload"])
    assert [t.task_id for t in store.claim(10)] == [1, 2]
    with pytest.raises(SystemExit, match="task id.*pending task of this store"):
        offload.main(["lease", str(path), "profile=smoke", "--tasks", "1", "--out", str(tmp_path / "u.json")])
    with pytest.raises(SystemExit, match="campaign store was created with config hash"):
        offload.main(["lease", str(path), "profile=smoke", "sim.dtype=float32", "--tasks", "1",
                      "--out", str(tmp_path / "u.json")])
