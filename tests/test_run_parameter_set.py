"""``scripts/run_parameter_set.py``: a parameter set's runs on the calibration's own model (the mini
box of ``profile=smoke`` here), KPIs beside the measurement; the parameters reach the DEM; ``--images``
keeps each run's front views and ``--scenes`` their spheres, which ``scripts/photo_readings.py`` draws
and reads again."""
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from kpi.io import read_image
from torchdem.errors import ConfigError
from kpi.segregation import segment_pellet_sinter

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "run_parameter_set.py"


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, cwd=ROOT)


def test_a_parameter_set_runs_and_reaches_the_dem(tmp_path):
    rows, photos = {}, {}
    for mu in ("0.1", "0.9"):
        out = _run(f"mu_s_pp={mu}", "mu_s_ss=" + mu, "--runs", "50-50:0", "--json", str(tmp_path / f"{mu}.json"),
                   "--images", str(tmp_path / mu), "--scenes", str(tmp_path / mu), "--", "profile=smoke")
        assert out.returncode == 0, out.stderr
        assert "| measured |" in out.stdout and "| 50-50 | 1 |" in out.stdout
        doc = json.loads((tmp_path / f"{mu}.json").read_text())
        assert doc["parameters"] == {"mu_s_pp": float(mu), "mu_s_ss": float(mu)}
        rows[mu] = doc["rows"][0]["kpis"]
        # --images keeps both front views; kpi reads them and finds pellets and sinter in the heap
        photos[mu] = {view: read_image(tmp_path / mu / f"{view}_50-50_0.png") for view in ("upper", "lower")}
        pellet, sinter = segment_pellet_sinter(photos[mu]["lower"])
        assert pellet.sum() > 100 and sinter.sum() > 100
    # the same seed, the particle frictions 0.1 against 0.9: the slippery fill empties further (0.715
    # against 0.672 kg of ~0.8 kg at seed 0, 0.709 against 0.659 at seed 1), so the values reached the contacts
    assert rows["0.1"]["mass_lower_box_kg"] > rows["0.9"]["mass_lower_box_kg"] + 0.02
    assert not np.array_equal(photos["0.1"]["lower"], photos["0.9"]["lower"])  # each run's own photo
    # the kept scene, drawn again without shadows and read as kpi reads it, gives the run's own segregation
    out = subprocess.run([sys.executable, str(ROOT / "scripts" / "photo_readings.py"),
                          str(tmp_path / "0.9" / "lower_50-50_0.npz"), "--shadow-depths", "0", "0.004"],
                         capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    rows = [line.split(" | ") for line in out.stdout.splitlines() if line.startswith("| 50-50 | 0 |")]
    assert [r[2] for r in rows] == ["0", "4"]
    assert float(rows[0][3]) == pytest.approx(doc["rows"][0]["kpis"]["segregation_rsd_vertical"], abs=5e-4)
    assert float(rows[0][4]) == pytest.approx(doc["rows"][0]["kpis"]["segregation_rsd_horizontal"], abs=5e-4)
    assert rows[1][3:] != rows[0][3:]  # the shadowed photo reads otherwise


def test_bad_parameters_name_the_item():
    out = _run("mu_s_pp", "--", "profile=smoke")
    assert out.returncode != 0 and "parameter 'mu_s_pp': expected NAME=NUMBER" in out.stderr
    out = _run("bogus=1", "--", "profile=smoke")
    assert out.returncode != 0 and "contact parameter 'bogus'" in out.stderr and "Traceback" not in out.stderr


def test_photo_readings_refuses_a_file_that_is_no_scene(tmp_path):
    spec = importlib.util.spec_from_file_location("photo_readings", ROOT / "scripts" / "photo_readings.py")
    photo_readings = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(photo_readings)
    bad = tmp_path / "lower_50-50_0.npz"
    bad.write_text("not an archive")
    with pytest.raises(ConfigError, match="lower_50-50_0.npz: not a photo scene of run_parameter_set.py --scenes"):
        photo_readings.load_scene(bad)
