"""Tests of bo/studies/pipeline.py and the torchdem-study app (bo/cli/study.py).

Fast tests use a known-answer evaluator whose KPIs depend on the run-setting variant in the
condition name (``torchdem.model.split_condition``), so the study's assembly, resume and report are
checked against exact values; the slow test runs both studies on real mini draw down tests and
reruns one with the same store.
"""
from __future__ import annotations

import functools
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from bo.cli.common import plain_config
from bo.cli.study import run_study
from torchdem.model import split_condition
from bo.campaign.executor import EvalOutcome, InProcessExecutor
from bo.campaign.store import CampaignStore
from bo.studies.pipeline import (STUDY_STAGES, run_shear_modulus_study, run_time_step_study, shear_modulus_report,
                        time_step_report)
from torchdem.cli import CONF_DIR
from torchdem.drawdown import RunSettings
from torchdem.errors import ConfigError

REPO = Path(__file__).resolve().parent.parent
FAST_RUN = ["run.fill_time_s=0.2", "run.discharge_time_s=0.45", "run.flow_window_s=[0.05,0.15]",
            "run.final_window_s=0.3", "mixture.total_mass_kg=2.0"]
PARAMS = {"mu_s_pp": 0.49, "mu_s_ss": 0.7}


def variant_kpis(condition, seed):
    """Stable up to a fraction 0.2, then the angle drops; the mass slows with sqrt(G)."""
    _, s = split_condition(condition, RunSettings(shear_modulus=1e6))
    noise = (-1) ** seed * 0.1
    return {"angle_of_repose_deg": 30.0 - (40.0 * (s.time_step_fraction - 0.2) if s.time_step_fraction > 0.2
                                           else 0.0) + noise,
            "mass_lower_box_full_kg": 3.0 + 1e-4 * np.sqrt(s.shear_modulus / 1e6) + noise / 10}


def variant_batch(tasks, *, calls):
    calls.append(len(tasks))
    g = split_condition(tasks[0].condition, RunSettings(shear_modulus=1e6))[1].shear_modulus
    return [EvalOutcome.success(variant_kpis(t.condition, t.seed), g / 1e6) for t in tasks]


KPIS = ["angle_of_repose_deg", "mass_lower_box_full_kg"]


def test_time_step_study_assembles_resumes_and_chooses(tmp_path):
    store = CampaignStore(tmp_path / "s.sqlite", "h", extra_stages=STUDY_STAGES)
    calls = []
    executor = InProcessExecutor(functools.partial(variant_batch, calls=calls), 10)
    runs = run_time_step_study(store, executor, condition="50-50", params=PARAMS, fractions=[0.1, 0.2, 0.3],
                               seeds=[0, 1, 2], kpis=KPIS)
    assert calls == [3, 3, 3] and runs.kpi_values.shape == (3, 3, 2)
    assert runs.conditions[1] == "50-50|time_step_fraction=0.2"
    np.testing.assert_allclose(runs.kpi_values[2, :, 0], [26.1, 25.9, 26.1])
    again = run_time_step_study(store, executor, condition="50-50", params=PARAMS, fractions=[0.1, 0.2, 0.3],
                                seeds=[0, 1, 2], kpis=KPIS)
    assert calls == [3, 3, 3]
    np.testing.assert_array_equal(again.kpi_values, runs.kpi_values)
    more = run_time_step_study(store, executor, condition="50-50", params=PARAMS,
                               fractions=[0.1, 0.2, 0.3, 0.15], seeds=[0, 1, 2], kpis=KPIS)
    assert calls == [3, 3, 3, 3]  # only the new fraction ran
    choice, files = time_step_report(more, tmp_path)
    assert choice.chosen_fraction == pytest.approx(0.2)  # 0.3 drops the angle by 4 degrees
    assert {p.name for p in files.values()} == {"fig9_time_step.png", "timestep.md", "timestep.json"}
    doc = json.loads((tmp_path / "timestep.json").read_text())
    assert doc["choice"]["chosen_fraction"] == pytest.approx(0.2)
    assert "fraction 0.3: fails: angle_of_repose_deg mean" in (tmp_path / "timestep.md").read_text()


def test_shear_modulus_study_reports_measured_speedup(tmp_path):
    store = CampaignStore(tmp_path / "s.sqlite", "h", extra_stages=STUDY_STAGES)
    executor = InProcessExecutor(functools.partial(variant_batch, calls=[]), 10)
    runs = run_shear_modulus_study(store, executor, condition="50-50", params=PARAMS,
                                   shear_moduli_pa=[4e6, 1e6], seeds=[0, 1], kpis=KPIS)
    np.testing.assert_allclose(runs.wall_time_s, [4.0, 1.0])  # the evaluator's "wall time" is G / 1e6
    summary, files = shear_modulus_report(runs, tmp_path)
    assert summary.measured_speedup == pytest.approx((1.0, 4.0))
    assert summary.expected_speedup == pytest.approx((1.0, 2.0))
    assert summary.recommended_modulus_pa == pytest.approx(1e6)
    assert json.loads((tmp_path / "shear_modulus.json").read_text())["summary"]["recommended_modulus_pa"] == 1e6


def test_study_inputs_are_checked_before_anything_is_stored(tmp_path):
    store = CampaignStore(tmp_path / "s.sqlite", "h", extra_stages=STUDY_STAGES)
    executor = InProcessExecutor(functools.partial(variant_batch, calls=[]), 10)
    with pytest.raises(ConfigError, match=r"fractions = \[0.1, 1.5\] is not allowed"):
        run_time_step_study(store, executor, condition="50-50", params=PARAMS, fractions=[0.1, 1.5],
                            seeds=[0, 1], kpis=KPIS)
    with pytest.raises(ConfigError, match=r"seeds = \[0\] is not allowed; expected at least two"):
        run_shear_modulus_study(store, executor, condition="50-50", params=PARAMS, shear_moduli_pa=[1e6, 2e6],
                                seeds=[0], kpis=KPIS)
    assert store.batch_keys() == []


def _plain(overrides):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return plain_config(compose(config_name="study", overrides=overrides))


@pytest.mark.parametrize("override, message", [
    ("replicates=1", r"replicates = 1 is not allowed; expected an int >= 2"),
    ("study=timesteps", r"study = 'timesteps' is not allowed"),
    ("fractions=[0.1,0.1]", r"fractions = \[0.1, 0.1\] is not allowed"),
    ("study=shear_modulus shear_moduli_pa=[1e6,-1]", r"shear_moduli_pa = \[1000000.0, -1.0\] is not allowed"),
    ("deciding_kpis=[heap]", r"deciding_kpis = \['heap'\] is not allowed"),
])
def test_bad_study_config_fails_before_the_store_is_opened(tmp_path, override, message):
    store = tmp_path / "never.sqlite"
    with pytest.raises(ConfigError, match=message):
        run_study(_plain([*override.split(), f"store={store}"]), tmp_path, echo=lambda s: None)
    assert not store.exists()


def _run_app(args, out):
    proc = subprocess.run([sys.executable, "-m", "bo.cli.study", *args, f"hydra.run.dir={out}"], cwd=REPO,
                          capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"},
                          timeout=1200)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout


@pytest.mark.slow
def test_both_studies_on_real_runs_and_a_rerun_repeats_nothing(tmp_path):
    store = tmp_path / "study.sqlite"
    common = [f"store={store}", *FAST_RUN, "kpis=[shear_angle_deg,mass_lower_box_full_kg,max_heap_height_m]",
              "deciding_kpis=null"]
    out = _run_app(["study=timestep", "fractions=[0.3,0.4]", *common], tmp_path / "ts")
    assert re.search(r"DEM evaluations run now: 4 in", out)
    doc = json.loads((tmp_path / "ts" / "timestep.json").read_text())
    assert doc["choice"]["chosen_fraction"] in (0.3, 0.4)
    assert doc["runs"]["conditions"] == ["50-50|time_step_fraction=0.3", "50-50|time_step_fraction=0.4"]
    assert (tmp_path / "ts" / "fig9_time_step.png").stat().st_size > 1000
    assert np.isfinite(np.array(doc["runs"]["kpi_values"], dtype=float)).all()

    # the same function main() calls, in this process (saves the interpreter start-up)
    lines = []
    run_study(_plain(["study=shear_modulus", "shear_moduli_pa=[1e6,5e5]", *common]), tmp_path / "g", lines.append)
    assert re.search(r"DEM evaluations run now: 4 in", "\n".join(lines))
    doc = json.loads((tmp_path / "g" / "shear_modulus.json").read_text())
    assert doc["summary"]["reference_modulus_pa"] == 1e6
    assert doc["summary"]["expected_speedup"] == pytest.approx([1.0, 2 ** 0.5])
    assert all(s > 0 for s in doc["summary"]["measured_speedup"])
    assert "recommended: G = " in (tmp_path / "g" / "shear_modulus.md").read_text()

    done = sorted(r.task_id for r in CampaignStore(store, "x", allow_config_mismatch=True,
                                                   extra_stages=STUDY_STAGES).records(status="done"))
    assert len(done) == 8
    lines = []
    run_study(_plain(["study=timestep", "fractions=[0.3,0.4]", *common]), tmp_path / "ts2", lines.append)
    assert re.search(r"DEM evaluations run now: 0 in", "\n".join(lines))
    assert json.loads((tmp_path / "ts2" / "timestep.json").read_text())["runs"] == \
        json.loads((tmp_path / "ts" / "timestep.json").read_text())["runs"]


def test_rayleigh_time_step_of_the_paper_model_gives_the_papers_step():
    """Paper section 3.2.4: 15 % of the Rayleigh time step is 5.91e-6 s (G = 1e8 Pa, full sieve)."""
    from bo.cli.common import model_from
    from bo.studies.pipeline import smallest_sphere_rayleigh_time_step

    model = model_from(_plain(["study_profile=paper", "sim.shear_modulus_pa=null", "sim.fines_cut_mm=null"]))
    step = smallest_sphere_rayleigh_time_step(model.conditions["50-50"], model.settings)
    assert 0.15 * step == pytest.approx(5.91e-6, rel=2e-3)
    # Eq. 3: dt ~ G^-1/2, so the CPU profile's G = 1e6 Pa gives a 10x longer step
    soft = model_from(_plain(["study_profile=paper", "sim.shear_modulus_pa=1e6", "sim.fines_cut_mm=null"]))
    assert smallest_sphere_rayleigh_time_step(soft.conditions["50-50"], soft.settings) == pytest.approx(10 * step)
