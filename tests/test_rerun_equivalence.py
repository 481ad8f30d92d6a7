"""``scripts/rerun_equivalence.py``: a store's runs again under config overrides, paired by seed, and
the paired TOST per KPI (the mini box of ``profile=smoke``).

- Rerun under the store's own config, the runs are the stored runs bit for bit: every paired
  difference is 0 and every KPI is equivalent.
- Under a longer discharge step the reruns share the stored fills (the same bulk density as the
  gate opens) and the verdict is printed; run again, nothing is rerun; the same ``--out`` with
  other overrides is refused, naming both.
- The paired test itself: a constant shift inside the margin is equivalent with the exact
  difference; a shift beyond it is not.
"""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bo.campaign.dem import evaluate_batch
from bo.campaign.store import CampaignStore
from bo.cli.calibrate import calibration_model_for
from bo.studies.precision import precision_verdict

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "rerun_equivalence.py"


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, cwd=ROOT,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})


@pytest.mark.slow
def test_reruns_pair_with_the_stored_runs_and_resume(tmp_path):
    _, model, _ = calibration_model_for(["profile=smoke"])
    store = CampaignStore(tmp_path / "s.sqlite", "h")
    params = {"mu_s_pp": 0.5}
    store.batch("verification", "set/x", lambda: [params], seeds=[0, 1], conditions=["50-50"])
    for task in store.claim(2):  # one run per ensemble, as the reruns are made
        store.record([(task, *evaluate_batch(model, [task]))])
    calibration = tmp_path / "cal.json"
    calibration.write_text(json.dumps({"calibrated_parameters": params}))
    base = [str(tmp_path / "s.sqlite"), "--stages", "verification", "--calibration", str(calibration)]

    same = _run(*base, "--out", str(tmp_path / "same.jsonl"), "--", "profile=smoke")
    assert same.returncode == 0, same.stderr
    rows = [json.loads(line) for line in (tmp_path / "same.jsonl").read_text().splitlines()[1:]]
    assert len(rows) == 2 and all(r["kpis"]["shear_angle_deg"] == r["stored_kpis"]["shear_angle_deg"] for r in rows)
    assert "Verdict: rerun is equivalent to stored on every tested KPI." in same.stdout
    assert "+0 (+0, +0)" in same.stdout

    out = str(tmp_path / "longer.jsonl")
    longer = _run(*base, "--out", out, "--workers", "2", "--", "profile=smoke", "sim.discharge_time_step_fraction=0.45")
    assert longer.returncode == 0, longer.stderr
    rows = [json.loads(line) for line in Path(out).read_text().splitlines()[1:]]
    for r in rows:
        assert r["discharge_dt_s"] == pytest.approx(1.5 * r["dt_s"], rel=1e-12)
        assert r["kpis"]["fill_bulk_density_kg_m3"] == r["stored_kpis"]["fill_bulk_density_kg_m3"]
    assert "2 reruns, 0 blew up" in longer.stdout and "Verdict:" in longer.stdout
    again = _run(*base, "--out", out, "--margin-condition", "50-50", "--", "profile=smoke",
                 "sim.discharge_time_step_fraction=0.45")
    assert again.returncode == 0 and "0 to run" in again.stdout
    assert "margins: the lab's 95 % CI half-widths at 50-50" in again.stdout
    other = _run(*base, "--out", out, "--", "profile=smoke", "sim.discharge_time_step_fraction=0.4")
    assert other.returncode != 0 and "0.4" in other.stderr and "0.45" in other.stderr


def test_the_paired_test_sees_a_constant_shift_exactly():
    rng = np.random.default_rng(0)
    a = rng.normal(40.0, 1.0, (8, 1))
    inside = precision_verdict(a, a + 0.3, ["shear_angle_deg"], {"shear_angle_deg": 1.62}, paired=True)
    [row] = inside.rows
    assert row.verdict == "equivalent" and row.difference == pytest.approx(0.3) and row.sd == pytest.approx(0, abs=1e-12)
    noisy = a + 2.5 + rng.normal(0.0, 0.3, (8, 1))
    [row] = precision_verdict(a, noisy, ["shear_angle_deg"], {"shear_angle_deg": 1.62}, paired=True).rows
    assert row.verdict == "not equivalent" and row.ci_low > 1.62
    # pairing takes the replicate scatter out: paired, a small shift is told inside a tight margin; unpaired,
    # the scatter swamps it
    b = a + 0.3 + rng.normal(0.0, 0.05, (8, 1))
    [paired] = precision_verdict(a, b, ["shear_angle_deg"], {"shear_angle_deg": 0.5}, paired=True).rows
    [unpaired] = precision_verdict(a, b, ["shear_angle_deg"], {"shear_angle_deg": 0.5}, paired=False).rows
    assert paired.verdict == "equivalent" and unpaired.verdict != "equivalent"
