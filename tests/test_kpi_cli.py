"""Tests for kpi.cli: the torchdem-kpi command on files written to tmp_path."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from kpi.cli import main
from kpi.io import write_image, write_loadcell_csv
from kpi.loadcell import LoadCellSignal
from test_kpi_angles import draw_funnel, draw_heap
from test_kpi_loadcell import INITIAL_MASS_KG, discharge_record
from test_kpi_segregation import PELLET_SHARE, paint_grid, sample_rsd


def run(argv, capsys) -> tuple[int, dict | None, str]:
    status = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return status, (json.loads(captured.out) if status == 0 else None), captured.err


def test_angles_repose_and_shear(tmp_path, capsys):
    heap, box = draw_heap(29.5, 31.0)
    write_image(tmp_path / "lower.png", heap)
    status, report, _ = run(["angles", tmp_path / "lower.png", "--kind", "repose", "--crop", box.x0, box.y0, box.x1, box.y1], capsys)
    assert status == 0
    assert report["kpi"] == "angle_of_repose"
    assert report["angle_deg"] == pytest.approx(30.25, abs=0.5)
    assert report["left_angle_deg"] == pytest.approx(29.5, abs=0.5)
    assert report["crop_px"] == [box.x0, box.y0, box.x1, box.y1]
    assert report["source"] == str(tmp_path / "lower.png")

    funnel, box = draw_funnel(41.0, 44.0)
    write_image(tmp_path / "upper.png", funnel)
    status, report, _ = run(["angles", tmp_path / "upper.png", "--kind", "shear", "--crop", box.x0, box.y0, box.x1, box.y1], capsys)
    assert status == 0
    assert report["kpi"] == "shear_angle"
    assert report["angle_deg"] == pytest.approx(42.5, abs=0.5)


def test_segregation(tmp_path, capsys):
    write_image(tmp_path / "grid.png", paint_grid())
    status, report, _ = run(["segregation", tmp_path / "grid.png"], capsys)
    assert status == 0
    assert report["ddof"] == 1
    assert report["vertical"]["pellet_rsd"] == pytest.approx(sample_rsd(PELLET_SHARE.mean(axis=1)), abs=1e-9)
    assert report["horizontal"]["sinter_rsd"] == pytest.approx(sample_rsd(1 - PELLET_SHARE.mean(axis=0)), abs=1e-9)
    assert len(report["vertical"]["slice_bounds_px"]) == 3 and len(report["horizontal"]["pellet_fraction"]) == 6


def test_loadcell(tmp_path, capsys):
    time_s, mass_kg, _ = discharge_record(0, noise_kg=0.0)
    write_loadcell_csv(tmp_path / "loadcell.csv", LoadCellSignal(time_s, mass_kg))
    status, report, _ = run(["loadcell", tmp_path / "loadcell.csv", "--initial-mass", INITIAL_MASS_KG], capsys)
    assert status == 0
    assert report["mass_flow_rate_kg_s"] == pytest.approx(10.29, rel=1e-3)
    assert report["lower_box_mass_kg"] == pytest.approx(32.32, rel=1e-6)
    assert report["fit_window_s"] == [0.5, 2.0]


def test_loadcell_custom_columns_and_window(tmp_path, capsys):
    time_s, mass_kg, _ = discharge_record(0, noise_kg=0.0, shift_s=1.0)
    write_loadcell_csv(tmp_path / "run.csv", LoadCellSignal(time_s, mass_kg), time_column="t", mass_column="m")
    status, report, _ = run(
        ["loadcell", tmp_path / "run.csv", "--initial-mass", 40, "--time-column", "t", "--mass-column", "m",
         "--gate-open", 1.0, "--fit-window", 0.6, 1.8],
        capsys,
    )
    assert status == 0
    assert report["fit_window_s"] == [1.6, 2.8]
    assert report["mass_flow_rate_kg_s"] == pytest.approx(10.29, rel=1e-3)


def test_bad_input_exits_2_naming_the_file(tmp_path, capsys):
    missing = tmp_path / "missing.png"
    status, _, err = run(["angles", missing, "--kind", "repose"], capsys)
    assert status == 2
    assert err.strip() == f"torchdem-kpi: error: {missing}: file does not exist"

    write_image(tmp_path / "small.png", np.zeros((20, 30, 3), np.uint8))
    status, _, err = run(["segregation", tmp_path / "small.png", "--crop", 0, 0, 40, 10], capsys)
    assert status == 2 and f"{tmp_path / 'small.png'}: crop box (x0=0, y0=0, x1=40, y1=10) does not fit" in err

    (tmp_path / "short.csv").write_text("time_s,mass_kg\n0,40\n0.02,39.8\n1.0,30\n")
    status, _, err = run(["loadcell", tmp_path / "short.csv", "--initial-mass", 40], capsys)
    assert status == 2 and f"{tmp_path / 'short.csv'}: record is too short" in err


def test_installed_console_script(tmp_path):
    script = Path(sys.executable).parent / "torchdem-kpi"
    if not script.exists():
        pytest.fail(f"{script} not found; run `pip install -e .` so the console script is installed")
    time_s, mass_kg, _ = discharge_record(1)
    write_loadcell_csv(tmp_path / "loadcell.csv", LoadCellSignal(time_s, mass_kg))
    done = subprocess.run(
        [str(script), "loadcell", str(tmp_path / "loadcell.csv"), "--initial-mass", "40"],
        capture_output=True, text=True, timeout=60, check=False,
    )
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["lower_box_mass_kg"] == pytest.approx(32.32, rel=0.01)
    done = subprocess.run([str(script), "loadcell", str(tmp_path / "nope.csv"), "--initial-mass", "40"],
                          capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 2
    assert f"{tmp_path / 'nope.csv'}: file does not exist" in done.stderr
