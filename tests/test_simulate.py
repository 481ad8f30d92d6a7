"""torchdem-simulate end to end on the mini box: the files a user gets, resume after an
interruption, and the Hydra multirun over seeds."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from kpi.io import read_image, read_loadcell_csv
from torchdem import config
from torchdem.cli import CONF_DIR
from torchdem.drawdown import KPI_UNITS, DrawDownTest
from torchdem.simulate import simulate_drawdown

MINI = ["+experiment=mini", "output.progress=false"]


def _test(*overrides) -> DrawDownTest:
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        c = OmegaConf.to_container(compose(config_name="simulate", overrides=MINI + list(overrides)), resolve=True)
    return DrawDownTest(config.mixture_from(c["mixture"]), config.geometry_from(c["geometry"]),
                        config.contact_from(c["contact"]), config.run_settings_from(c["sim"], c["run"]))


class Interrupt(Exception):
    pass


@pytest.mark.slow
def test_interrupted_run_resumes_and_matches_an_uninterrupted_one(tmp_path):
    test = _test()
    whole = simulate_drawdown(test, [7], tmp_path / "whole", checkpoint_every_s=0.5)

    def stop_after_checkpoint(simulated, wall):
        if simulated > 1.3:  # past the checkpoints at 0.5 s and 1.0 s of simulated time
            raise Interrupt

    out = tmp_path / "interrupted"
    with pytest.raises(Interrupt):
        simulate_drawdown(test, [7], out, checkpoint_every_s=0.5, progress=stop_after_checkpoint)
    assert (out / "checkpoint.pt").exists() and not (out / "kpis.json").exists()
    resumed = simulate_drawdown(test, [7], out, checkpoint_every_s=0.5)
    assert not (out / "checkpoint.pt").exists()
    # the resumed run continues from the saved state bit for bit
    assert resumed["members"][0]["kpis"] == whole["members"][0]["kpis"]
    a = read_loadcell_csv(out / "loadcell_7.csv")
    b = read_loadcell_csv(tmp_path / "whole" / "loadcell_7.csv")
    np.testing.assert_array_equal(a.mass_kg, b.mass_kg)

    # what a user gets: every KPI with its unit, a load-cell CSV the KPI tools read, photos
    report = json.loads((tmp_path / "whole" / "kpis.json").read_text())
    assert set(report["units"]) == set(KPI_UNITS)
    kpis = report["members"][0]["kpis"]
    for name in ("angle_of_repose_deg", "shear_angle_deg", "mass_flow_rate_kg_s", "mass_lower_box_kg",
                 "segregation_rsd_vertical", "max_heap_height_m", "mass_flow_rate_full_kg_s"):
        assert np.isfinite(kpis[name]), name
    assert kpis["mass_lower_box_full_kg"] == pytest.approx(5 * kpis["mass_lower_box_kg"])
    assert "x 5" in report["scaling"]
    t = a.time_s
    assert t[0] == pytest.approx(0.0, abs=1e-3) and np.allclose(np.diff(t), 0.02, atol=1e-3)
    for view in ("upper", "lower"):
        assert read_image(tmp_path / "whole" / f"{view}_7.png").shape[2] == 3


@pytest.mark.slow
def test_cli_multirun_over_seeds(tmp_path):
    env = dict(os.environ, OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "torchdem.cli_simulate", "-m", "seed=1,2", *MINI,
           f"hydra.sweep.dir={tmp_path}", "hydra.sweep.subdir=${seed}"]
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    for seed in (1, 2):
        report = json.loads((tmp_path / str(seed) / "kpis.json").read_text())
        assert report["members"][0]["seed"] == seed
        assert (tmp_path / str(seed) / f"loadcell_{seed}.csv").exists()
    assert "angle_of_repose_deg" in done.stdout


def test_cli_rejects_bad_value_with_key_and_range(tmp_path):
    cmd = [sys.executable, "-m", "torchdem.cli_simulate", *MINI, "run.fill_time_s=-1", f"hydra.run.dir={tmp_path}"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode != 0
    assert "fill_time_s" in done.stderr and "-1" in done.stderr and "> 0 s" in done.stderr
