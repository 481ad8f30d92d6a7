"""bo.discovery.gap: the lab's gap between two KPIs against every run of the shipped stores."""
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bo.campaign.progress import done_records, finished_runs
from bo.discovery.gap import GapCheck, GapRun, format_gap, gap_check, lab_gap
from torchdem.errors import ConfigError
from torchdem.measured import load_measured

ROOT = Path(__file__).resolve().parents[1]
BOX = ROOT / "campaigns" / "table2" / "lab_box.sqlite"


def test_the_lab_s_gap_is_table_2_s_face_less_its_heap_with_both_cis_added():
    lab = lab_gap(load_measured(None))
    # Table 2, 25-75: shear angle 44.76 +- 1.21, angle of repose 29.63 +- 0.75
    assert lab["25-75"] == pytest.approx((44.76 - 29.63, 1.21 + 0.75), abs=1e-9)
    # 50-50: 42.51 +- 1.62 and 29.47 +- 0.48
    assert lab["50-50"] == pytest.approx((42.51 - 29.47, 1.62 + 0.48), abs=1e-9)
    assert set(lab) == {"50-50", "75-25", "25-75", "50-50-reverse"}


def test_every_run_that_flowed_counts_once_with_its_own_two_kpis():
    check = gap_check([BOX], load_measured(None))
    expected = {}
    for _, condition, _, _, k in finished_runs(BOX):
        if k.get("discharge_jammed", 0.0) > 0.5 or not math.isfinite(k.get("shear_angle_deg", math.nan)):
            continue
        expected.setdefault(condition, []).append(k["shear_angle_deg"] - k["angle_of_repose_deg"])
    for condition, gaps in expected.items():
        assert np.sort(check.model(condition)) == pytest.approx(np.sort(gaps), abs=1e-12)
    assert len(check.model("25-75")) == 3                   # the box campaign's validation runs
    md = format_gap(check, by_stage=True)
    assert "| 25-75 | 15.13 +- 1.96 | 3 |" in md and "| lab_box.sqlite | validation | 25-75 |" in md


def test_reaching_counts_the_runs_at_the_near_end_of_the_band_and_both_inside_needs_both_cis():
    runs = tuple(GapRun("s", "x", "c", a, b) for a, b in [(40.0, 30.0), (43.0, 30.0), (45.0, 29.0), (44.0, 33.0)])
    check = GapCheck(("s",), ("a", "b"), means={"c": (44.0, 29.5)}, ci={"c": (1.5, 1.0)}, runs=runs)
    assert check.lab == {"c": (14.5, 2.5)}
    assert list(check.model("c")) == [10.0, 13.0, 16.0, 11.0]
    assert check.reaching("c") == 2                         # 13 and 16 are at or above 14.5 - 2.5 (the mean lies below)
    # (43, 30) and (45, 29) have both inside; (40, 30) has b inside but a 4.0 off, (44, 33) a inside but b 3.5 off
    assert check.both_inside("c") == 2
    assert check.reaching("other") == 0 and check.both_inside("other") == 0


def test_a_run_two_stores_hold_counts_once():
    probe = ROOT / "campaigns" / "table2" / "probe_combined.sqlite"     # adopted the box set's 12 runs from BOX
    alone = gap_check([probe], load_measured(None))
    both = gap_check([BOX, probe], load_measured(None))
    box = gap_check([BOX], load_measured(None))
    adopted = 12
    assert len(both.runs) == len(box.runs) + len(alone.runs) - adopted


def test_a_probe_store_s_sets_are_apart_by_batch():
    probe = ROOT / "campaigns" / "table2" / "probe_tetralobe.sqlite"
    groups = gap_check([probe], load_measured(None)).by_stage(by_batch=True)
    runs = {r.condition: r.kpis for r in done_records(probe, "probe") if r.batch_key == "tetralobe"
            and r.condition == "25-75"}
    expected = runs["25-75"]["shear_angle_deg"] - runs["25-75"]["angle_of_repose_deg"]
    assert list(groups[("probe_tetralobe.sqlite", "probe/tetralobe", "25-75")]) == pytest.approx([expected])
    assert len(groups[("probe_tetralobe.sqlite", "probe/base", "25-75")]) == 3
    assert ("probe_tetralobe.sqlite", "probe/tetralobe", "75-25") not in groups    # its fill overflowed: no run


def test_a_kpi_no_run_has_is_refused_by_name():
    with pytest.raises(ConfigError, match="'shear_angle_degrees'.*no run"):
        gap_check([BOX], load_measured(None), "shear_angle_degrees", "angle_of_repose_deg")


def test_the_script_prints_the_table():
    out = subprocess.run([sys.executable, str(ROOT / "scripts" / "gap_check.py"), str(BOX)], capture_output=True,
                         text=True, check=True, cwd=ROOT).stdout
    assert out.startswith("## The gap shear_angle_deg - angle_of_repose_deg") and "| 50-50-reverse |" in out
