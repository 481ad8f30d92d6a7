"""Tests of bo/screening/pipeline.py and the torchdem-screen app (bo/cli/screen.py).

Fast tests check the store assembly, resume and report logic with a known-answer evaluator
(a linear KPI model: the answer in every [run, replicate] cell is known) and the config
checks; the slow test runs the app end to end on real mini draw down tests, then reruns it
with the same store and checks that no DEM evaluation is repeated.
"""
from __future__ import annotations

import functools
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from bo.cli.common import MODEL_KEYS, config_hash, plain_config, screen_settings_from
from bo.cli.screen import screen
from bo.design.dsd import ParameterTable, definitive_screening_design, paper_parameter_table, scale_design
from bo.campaign.executor import EvalOutcome, InProcessExecutor
from bo.screening.pipeline import (analyse_and_report, jammed_screening_runs, measured_for, run_screening,
                                   screening_batch_key)
from bo.screening.stepwise import ScreeningResults
from bo.campaign.store import CampaignStore
from torchdem.cli import CONF_DIR
from torchdem.errors import ConfigError
from torchdem.measured import load_measured

REPO = Path(__file__).resolve().parent.parent

# Short procedure for the slow tests: the mini box with half its fill (~90 bodies), 0.2 s fill,
# 0.45 s discharge (about a quarter of the default profile's simulated time, ~7 s per member
# here). The discharge has not ended by then, so the mass flow rate cannot be measured (NaN:
# the report must flag it, not crash).
FAST_RUN = ["run.fill_time_s=0.2", "run.discharge_time_s=0.45", "run.flow_window_s=[0.05,0.15]",
            "run.final_window_s=0.3", "mixture.total_mass_kg=2.0"]


# -- known-answer evaluator ----------------------------------------------------------------

def linear_kpis(params, seed):
    """shear angle rises with mu_s_pp, mass falls with mu_s_ss; a seed-dependent offset."""
    return {"shear_angle_deg": 30.0 + 20.0 * params["mu_s_pp"] + 0.01 * seed,
            "mass_lower_box_full_kg": 40.0 - 10.0 * params["mu_s_ss"] + 0.02 * seed,
            "angle_of_repose_deg": 25.0 + 0.0 * params["mu_s_pp"] + ((seed * 7919) % 13) * 0.5}


def linear_batch(tasks, *, calls):
    calls.append(len(tasks))
    return [EvalOutcome.success(linear_kpis(t.params, t.seed), 1.0) for t in tasks]


def _table():
    paper = paper_parameter_table()
    idx = [paper.names.index(n) for n in ("mu_s_pp", "mu_s_ss", "mu_r_pp")]
    return ParameterTable(tuple(paper.names[i] for i in idx), tuple(paper.low[i] for i in idx),
                          tuple(paper.mid[i] for i in idx), tuple(paper.high[i] for i in idx), source="test")


KPIS = ["shear_angle_deg", "mass_lower_box_full_kg", "angle_of_repose_deg"]


def test_run_screening_puts_every_value_in_its_cell_and_resumes(tmp_path):
    table = _table()
    store = CampaignStore(tmp_path / "s.sqlite", "h")
    calls = []
    executor = InProcessExecutor(functools.partial(linear_batch, calls=calls), 100)
    results = run_screening(store, executor, table, n_fake=1, seeds=[3, 5], condition="50-50", kpis=KPIS)
    coded = definitive_screening_design(3, 1)
    physical = scale_design(coded, table)
    assert results.n_runs == coded.shape[0] == 9 and results.seeds == (3, 5)
    np.testing.assert_array_equal(results.coded, coded)
    for i, row in enumerate(physical):
        for r, seed in enumerate((3, 5)):
            expected = linear_kpis(dict(zip(table.names, row)), seed)
            np.testing.assert_allclose(results.kpi_values[i, r], [expected[k] for k in KPIS], rtol=1e-12)
    assert sum(calls) == 18
    # rerun: nothing evaluated, same results
    again = run_screening(store, executor, table, n_fake=1, seeds=[3, 5], condition="50-50", kpis=KPIS)
    assert sum(calls) == 18 and again == results
    # a third replicate adds only its own 9 evaluations
    more = run_screening(store, executor, table, n_fake=1, seeds=[3, 5, 8], condition="50-50", kpis=KPIS)
    assert sum(calls) == 27
    np.testing.assert_array_equal(more.kpi_values[:, :2], results.kpi_values)
    assert (("screening", screening_batch_key(table, 1, 8)) in store.batch_keys("screening"))


def test_a_run_whose_discharge_jammed_measured_nothing(tmp_path):
    """A jammed run's KPIs (an undrained fill's) are NaN in the stage's results and in the store read
    alone; the other runs keep their values."""
    from bo.screening.pipeline import stored_screening

    high_mu_s_ss = _table().high[1]

    def jam_at_high_mu_s_ss(tasks):  # the runs of seed 3 at mu_s_ss's high level arch over the slot
        return [EvalOutcome.success({**linear_kpis(t.params, t.seed),
                                     "discharge_jammed": float(t.params["mu_s_ss"] == high_mu_s_ss and t.seed == 3)},
                                    1.0) for t in tasks]

    store = CampaignStore(tmp_path / "s.sqlite", "h")
    results = run_screening(store, InProcessExecutor(jam_at_high_mu_s_ss, 100), _table(), n_fake=1, seeds=[3, 5],
                            condition="50-50", kpis=KPIS)
    high = results.physical[:, 1] == high_mu_s_ss
    assert high.sum() == 3  # a DSD of 3 + 1 factors puts 3 of its 9 runs at a factor's high level
    assert np.isnan(results.kpi_values[high, 0]).all() and np.isfinite(results.kpi_values[~high, 0]).all()
    assert np.isfinite(results.kpi_values[:, 1]).all()  # the other replicate flowed
    read = stored_screening(tmp_path / "s.sqlite", KPIS)
    assert read.kpi_names == tuple(KPIS)
    np.testing.assert_array_equal(np.isnan(read.kpi_values), np.isnan(results.kpi_values))
    # the jammed runs with the KPIs they measured, for a surrogate that reuses the screening's points;
    # a seed the store has not run has none
    jammed, values = jammed_screening_runs(store, _table(), n_fake=1, seeds=[3, 5, 7], condition="50-50",
                                           kpis=KPIS[::-1])
    assert jammed[:, 0].tolist() == high.tolist() and not jammed[:, 1:].any()
    names = _table().names
    expected = [[linear_kpis(dict(zip(names, row)), 3)[k] for k in KPIS[::-1]] for row in results.physical[high]]
    np.testing.assert_allclose(values[high, 0], expected)
    assert np.isnan(values[~jammed]).all()


def test_run_screening_rejects_bad_inputs_before_storing(tmp_path):
    store = CampaignStore(tmp_path / "s.sqlite", "h")
    executor = InProcessExecutor(functools.partial(linear_batch, calls=[]), 10)
    with pytest.raises(ConfigError, match=r"n_fake = -1 is not allowed; expected an integer >= 0"):
        run_screening(store, executor, _table(), n_fake=-1, seeds=[0], condition="50-50", kpis=KPIS)
    with pytest.raises(ConfigError, match="seeds"):
        run_screening(store, executor, _table(), n_fake=1, seeds=[], condition="50-50", kpis=KPIS)
    with pytest.raises(ConfigError, match="kpis"):
        run_screening(store, executor, _table(), n_fake=1, seeds=[0], condition="50-50", kpis=["a", "a"])
    assert store.batch_keys() == []
    # a KPI the evaluations never carry is named, with the ones they do carry
    with pytest.raises(ConfigError, match=r"KPIs \['heap_volume_m3'\] are in no finished evaluation"):
        run_screening(store, executor, _table(), n_fake=1, seeds=[0], condition="50-50",
                      kpis=["shear_angle_deg", "heap_volume_m3"])


def test_measured_for_compares_full_box_masses_only():
    measured = load_measured().condition("50-50").kpis
    lab = measured_for(["mass_flow_rate_full_kg_s", "mass_flow_rate_kg_s", "mass_lower_box_full_kg",
                        "shear_angle_deg", "max_heap_height_m"], measured)
    assert set(lab) == {"mass_flow_rate_full_kg_s", "mass_lower_box_full_kg", "shear_angle_deg"}
    assert lab["mass_flow_rate_full_kg_s"].mean == pytest.approx(10.29)
    assert lab["mass_lower_box_full_kg"].mean == pytest.approx(32.32)


def test_analyse_and_report_flags_noise_and_writes_table5(tmp_path):
    table = _table()
    coded = definitive_screening_design(3, 1)
    physical = scale_design(coded, table)
    rng = np.random.default_rng(0)
    seeds = [0, 1, 2, 3, 4]
    values = np.empty((coded.shape[0], len(seeds), 4))
    for i, row in enumerate(physical):
        for r in range(len(seeds)):
            p = dict(zip(table.names, row))
            values[i, r] = [30 + 20 * p["mu_s_pp"] + rng.normal(0, 0.05),      # + mu_s_pp
                            40 - 10 * p["mu_s_ss"] + rng.normal(0, 0.02),      # - mu_s_ss
                            0.2 + rng.normal(0, 0.05),                          # pure noise
                            np.nan]                                             # never measured
    names = ["shear_angle_deg", "mass_lower_box_full_kg", "segregation_rsd_vertical", "mass_flow_rate_full_kg_s"]
    results = ScreeningResults.from_parameter_table(table, coded, seeds, names, values)
    report = analyse_and_report(results, load_measured().condition("50-50").kpis, tmp_path)
    assert report.unmeasurable_kpis == ("mass_flow_rate_full_kg_s",)
    assert "segregation_rsd_vertical" in report.variance.excluded_kpis
    assert report.calibration_kpis == ("shear_angle_deg", "mass_lower_box_full_kg")
    t5 = json.loads((tmp_path / "table5.json").read_text())
    cells = {row["parameter"]: row["cells"] for row in t5["rows"]}
    assert cells["mu_s_pp"]["shear_angle_deg"] == "+5/5"
    assert cells["mu_s_ss"]["mass_lower_box_full_kg"] == "-5/5"
    assert t5["selected_parameters"] == ["mu_s_pp", "mu_s_ss"]
    doc = json.loads((tmp_path / "screening.json").read_text())
    share = doc["variance"]["kpis"]["shear_angle_deg"]
    assert share["parameter_share"] + share["stochastic_share"] == pytest.approx(1.0)
    assert share["parameter_share"] > 0.99
    # the lab's shear angle (42.5) is above the screened range (~38-42): raise mu_s_pp's high bound
    moves = {(m["parameter"], m["side"]) for m in doc["extension"]["moves"]}
    assert ("mu_s_pp", "high") in moves
    md = (tmp_path / "screening.md").read_text()
    assert "| parameter" in md and "EXCLUDE" in md and "Parameter-space extension" in md
    for name in ("fig10_variance_shares.png", "fig11_screening_vs_measured.png", "table5.md"):
        assert (tmp_path / name).stat().st_size > 1000 or name.endswith(".md")


# -- config checks (no DEM) ----------------------------------------------------------------

def _plain(overrides):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return plain_config(compose(config_name="screen", overrides=overrides))


@pytest.mark.parametrize("override, message", [
    ("replicates=0", r"config: replicates = 0 is not allowed; expected an int >= 1"),
    ("screening.parameters=[mu_s_pp,mu_x_pp]", r"unknown: \['mu_x_pp'\]"),
    ("screening.n_fake=-1", r"screening: n_fake = -1 is not allowed; expected an int >= 0"),
    ("screening.kpis=[shear_angle]", r"screening: kpis = \['shear_angle'\] is not allowed"),
    ("condition=60-40", r"condition = '60-40' is not allowed; expected a condition of the measured data"),
    ("executor.batch_size=0", r"executor: batch_size = 0 is not allowed"),
    # levels the model cannot run (bo.cli.common.check_ranges): refused before the first run
    ("screening.levels.mu_s_pp=[-0.2,0.3,0.6]", r"screening \(parameters and levels\): at the low end of every "
     r"range, \{'mu_s_pp': -0.2, .*\}: contact\[pellet,pellet\]: mu_s = -0.2 is not allowed; expected \[0.0, inf\)"),
    ("screening.parameters=[mu_s_pp,mu_s_ss,mu_r_pp,mu_r_ss,mu_s_zz] +screening.levels.mu_s_zz=[0.2,0.4,0.6]",
     r"at the low end of every range, .*: contact: mu_s_zz names unknown material letter\(s\) in 'zz'"),
])
def test_bad_config_fails_before_the_store_is_opened(tmp_path, override, message):
    store = tmp_path / "never.sqlite"
    plain = _plain([*override.split(" "), f"store={store}"])
    with pytest.raises(ConfigError, match=message):
        screen(plain, tmp_path, echo=lambda s: None)
    assert not store.exists()


def test_profiles_compose_to_the_documented_designs():
    default = screen_settings_from(_plain([]))
    assert default.table.names == ("mu_s_pp", "mu_s_ss", "mu_r_pp", "mu_r_ss") and default.seeds == (0, 1, 2)
    assert default.n_fake == 2 and definitive_screening_design(4, 2).shape == (13, 4)
    assert default.table.low[0] == pytest.approx(0.2) and default.table.high[3] == pytest.approx(0.3)
    mini = screen_settings_from(_plain(["screen=mini"]))
    assert mini.table.names == ("mu_s_pp", "mu_s_ss") and mini.seeds == (0, 1) and mini.n_fake == 0
    paper_plain = _plain(["screen=paper"])
    paper = screen_settings_from(paper_plain)
    assert paper.table.k == 12 and paper.n_fake == 2 and len(paper.seeds) == 5
    assert definitive_screening_design(12, 2).shape == (29, 12)
    assert paper_plain["geometry"]["slice_depth_m"] == pytest.approx(0.04)
    assert paper_plain["geometry"]["upper_width_m"] > 0.3  # the lab box, not the mini box
    # the store hash covers the model, not the number of replicates or the executor
    assert config_hash(_plain(["replicates=5", "executor=dask"])) == config_hash(_plain([]))
    assert config_hash(_plain(["run.fill_time_s=0.3"])) != config_hash(_plain([]))
    # where and how fast a run goes is not part of the model: a GPU adds runs to a CPU's store
    assert config_hash(_plain(["sim.device=cuda", "sim.compile=true"])) == config_hash(_plain([]))
    # so is the bodies' spatial order (round-off only): a store takes runs with and without it
    assert config_hash(_plain(["+sim.reorder_every=10"])) == config_hash(_plain([]))
    assert config_hash(_plain(["+sim.reorder_every=0"])) == config_hash(_plain(["+sim.reorder_every=3"]))
    assert config_hash(_plain(["sim.dtype=float32"])) != config_hash(_plain(["sim.dtype=float64"]))
    # so is the Verlet skin (it changes no bit of a run: tests/test_neighbors.py)
    assert config_hash(_plain(["sim.skin_fraction=0.1"])) == config_hash(_plain([]))


def test_a_store_made_while_the_skin_was_hashed_opens_at_any_skin(tmp_path):
    """Every store made before the Verlet skin became execution-only carries the hash of its config with
    ``sim.skin_fraction`` in it (0.25 on the CPU profiles, 0.5 on the smoke one): a config at another skin
    opens it and writes its runs under that hash, a new store takes the hash without the skin, and a
    store of another model still does not open."""
    from bo.cli.common import HASHED_SKINS, _digest, open_store, store_hashes

    plain = _plain([])
    assert plain["sim"]["skin_fraction"] == 0.5 and HASHED_SKINS == (0.25, 0.5)
    then = _digest(plain, MODEL_KEYS, kept=("skin_fraction",))
    cpu_skin = _digest(_plain(["sim.skin_fraction=0.25"]), MODEL_KEYS, kept=("skin_fraction",))
    assert store_hashes(plain) == (config_hash(plain), cpu_skin, then) and then != config_hash(plain)
    CampaignStore(tmp_path / "then.sqlite", then).batch("screening", "k", lambda: [{"mu_s_pp": 0.5}], seeds=[0],
                                                        conditions=["50-50"])
    store = open_store(tmp_path / "then.sqlite", _plain(["sim.skin_fraction=0.1"]))
    assert store.config_hash == then and store.model_hashes[0] == config_hash(plain)
    [task] = store.claim(1)
    store.record([(task, EvalOutcome(kpis={"shear_angle_deg": 30.0}, error=None, wall_time=1.0))])
    assert [r.config_hash for r in store.records("screening", status="done")] == [then]
    assert open_store(tmp_path / "now.sqlite", _plain(["sim.skin_fraction=0.1"])).config_hash == config_hash(plain)
    with pytest.raises(ConfigError, match="config hash"):
        open_store(tmp_path / "then.sqlite", _plain(["run.fill_time_s=0.3"]))


def test_cli_reports_a_bad_config_and_exits_nonzero(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "bo.cli.screen", "replicates=0", f"store={tmp_path / 's.sqlite'}",
                           f"hydra.run.dir={tmp_path / 'out'}"], cwd=REPO, capture_output=True, text=True,
                          env={**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "1"}, timeout=300)
    assert proc.returncode != 0
    assert "replicates = 0 is not allowed; expected an int >= 1" in proc.stderr
    assert not (tmp_path / "s.sqlite").exists()


# -- end to end on real DEM runs -----------------------------------------------------------

def _run_app(args, out):
    started = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "bo.cli.screen", *args, f"hydra.run.dir={out}"], cwd=REPO,
                          capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"},
                          timeout=1200)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout, time.perf_counter() - started


@pytest.mark.slow
def test_screen_app_writes_the_report_and_a_rerun_repeats_no_dem_run(tmp_path):
    store = tmp_path / "screen.sqlite"
    # threshold 0.99: with 2 replicates of the short run most KPIs are noise-dominated; keep
    # them so that Table 5 has columns to check
    args = [f"store={store}", "screen=mini", *FAST_RUN, "screening.stochastic_threshold=0.99",
            "screening.kpis=[shear_angle_deg,mass_lower_box_full_kg,max_heap_height_m,mass_flow_rate_full_kg_s]"]
    stdout, _ = _run_app(args, tmp_path / "run1")
    out = tmp_path / "run1"
    for name in ("screening.json", "screening.md", "table5.md", "table5.json", "fig10_variance_shares.png",
                 "fig11_screening_vs_measured.png"):
        assert (out / name).is_file(), name
    doc = json.loads((out / "screening.json").read_text())
    results = ScreeningResults.from_dict(doc["results"])
    assert results.parameter_names == ("mu_s_pp", "mu_s_ss") and results.kpi_values.shape == (5, 2, 4)
    assert np.isfinite(results.kpi_values).all()  # every run measured every KPI
    for kpi, share in doc["variance"]["kpis"].items():
        assert share["parameter_share"] + share["stochastic_share"] == pytest.approx(1.0), kpi
    assert set(doc["excluded_kpis"]) | set(doc["calibration_kpis"]) == set(results.kpi_names)
    # the discharge has not ended after 0.45 s, but the flow rate needs only its fit window
    # (0.05-0.15 s): measured, not flagged (synthetic unmeasurable KPIs: test above)
    assert doc["unmeasurable_kpis"] == []
    assert doc["calibration_kpis"], doc["variance"]  # S <= 99 % for at least one measured KPI
    table5 = json.loads((out / "table5.json").read_text())
    assert table5 == doc["table5"]
    assert [row["parameter"] for row in table5["rows"]] == ["mu_s_pp", "mu_s_ss"]
    assert table5["kpis"] == doc["calibration_kpis"]
    assert all(set(row["cells"]) == set(table5["kpis"]) for row in table5["rows"])
    assert all(re.fullmatch(r"([+-][0-2]/2(, -[0-2]/2)?)?", cell)
               for row in table5["rows"] for cell in row["cells"].values())
    header = [c.strip() for c in (out / "table5.md").read_text().splitlines()[2].strip("|").split("|")]
    assert header == ["parameter", *table5["kpis"], "selected"]
    assert re.search(r"DEM evaluations run now: 10 in", stdout)

    con = CampaignStore(store, config_hash(_plain(args)))
    done_before = [(r.task_id, r.finished_at) for r in con.records("screening", status="done")]
    assert len(done_before) == 10

    stdout2, _ = _run_app(args, tmp_path / "run2")
    assert re.search(r"DEM evaluations run now: 0 in", stdout2)
    assert [(r.task_id, r.finished_at) for r in con.records("screening", status="done")] == done_before
    assert json.loads((tmp_path / "run2" / "screening.json").read_text())["results"] == doc["results"]


def test_report_without_a_kept_kpi_says_so(tmp_path):
    table = _table()
    coded = definitive_screening_design(3, 1)
    rng = np.random.default_rng(1)
    # pure noise; the plug-in S estimates (r - 1) / r of it, ~0.9 with r = 10 replicates
    values = rng.normal(0.2, 0.05, size=(coded.shape[0], 10, 1))
    results = ScreeningResults.from_parameter_table(table, coded, range(10), ["segregation_rsd_vertical"], values)
    report = analyse_and_report(results, load_measured().condition("50-50").kpis, tmp_path)
    assert report.analysis is None and report.proposal is None and report.calibration_kpis == ()
    assert json.loads((tmp_path / "table5.json").read_text())["rows"] == []
    assert "No Table 5: every KPI ['segregation_rsd_vertical'] is excluded" in (tmp_path / "table5.md").read_text()
    assert json.loads((tmp_path / "screening.json").read_text())["excluded_kpis"] == ["segregation_rsd_vertical"]
    assert (tmp_path / "fig11_screening_vs_measured.png").is_file()
