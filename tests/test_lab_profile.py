"""profile=lab: the lab calibration's config composes into checked settings and a model on the
lab geometry (mirror, half depth, fill by lobes, the four conditions of Table 2), within the
issue's budget of about 215 lab-geometry runs; ``surrogate.added`` parameters join the
selection with their own bounds, and bad ones are one-line errors naming the key."""
import contextlib
import dataclasses
import sqlite3
from types import SimpleNamespace

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from bo.calibration.pipeline import choose_parameters
from bo.cli.calibrate import calibration_model_from, calibration_settings_from
from bo.cli.common import plain_config
from torchdem.cli import CONF_DIR
from torchdem.errors import ConfigError
from torchdem.measured import load_measured


def _plain(*overrides, profile="lab"):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return plain_config(compose("calibrate", overrides=[f"profile={profile}", *overrides]))


def test_lab_profile_composes_on_the_lab_geometry_within_budget():
    plain = _plain()
    s = calibration_settings_from(plain)
    model, _ = calibration_model_from(plain, load_measured())
    assert model.geometry.mirror and model.geometry.depth_scale == 0.5
    assert model.settings.fill_packing == "lobes"
    # runs go on until the discharge has ended, as the lab photographs; the first campaign stopped at 4 s
    assert model.settings.discharge_time == 4.0 and model.settings.max_discharge_time == 8.0
    first, _ = calibration_model_from(_plain(profile="lab_4s"), load_measured())
    assert first.settings.max_discharge_time is None
    assert first.settings == dataclasses.replace(model.settings, max_discharge_time=None)
    # its screening reached the parted trilobes at 0.3; the lab profile's stops at the whole trilobe
    levels = dict(zip(s.screening.table.names, s.screening.table.levels()))
    assert levels["lobe_spacing_sinter"].tolist() == [0.15, 0.20895, 0.2679]
    s4 = calibration_settings_from(_plain(profile="lab_4s")).screening.table
    assert dict(zip(s4.names, s4.levels()))["lobe_spacing_sinter"].tolist() == [0.15, 0.225, 0.3]
    assert sorted(model.conditions) == ["25-75", "50-50", "50-50-reverse", "75-25"]
    assert "lobe_spacing_sinter" in s.screening.table.names
    screening_runs = (2 * (s.screening.table.k + 2) + 1) * len(s.screening.seeds)
    a = s.surrogate.adaptive
    total = screening_runs + a.budget * len(s.surrogate.seeds) + len(s.verification_seeds) \
        + 3 * len(s.validation_seeds)
    assert total <= 215, total
    # the first campaign's store is complete at its own budget: make run must not extend it
    assert calibration_settings_from(_plain(profile="lab_4s")).surrogate.adaptive.budget == 92
    # single runs with the pooled noise: the stop counts R^2 against the explainable variance
    assert a.target_basis == "explainable" and s.surrogate.noise == "pooled"
    # Eq. 7 over the paper's four KPIs, whatever the screening keeps (Table 2 also has the RSDs)
    assert s.objective_kpis == ("angle_of_repose_deg", "shear_angle_deg", "mass_flow_rate_full_kg_s",
                                "mass_lower_box_full_kg")


def test_added_parameters_join_the_selection_with_their_bounds():
    plain = _plain()
    s = calibration_settings_from(plain).surrogate
    screening = SimpleNamespace(results=SimpleNamespace(levels=lambda: {"mu_s_pp": (0.3, 0.9)}, parameter_names=("mu_s_pp",)),
                                analysis=SimpleNamespace(selected_parameters=("mu_s_pp",)), proposal=None)
    names, bounds, note = choose_parameters(screening, s)
    assert names == ("mu_s_pp", "density_pellet", "density_sinter", "mu_s_pg", "mu_r_pp", "mu_r_pg")
    # the rolling frictions up to the top of the paper's Table 6
    np.testing.assert_allclose(bounds[:, 1:], [[3240.0, 3100.0, 0.285, 0.045, 0.045], [3960.0, 3800.0, 0.9, 0.24, 0.24]])
    assert "added by the config" in note
    with pytest.raises(ConfigError, match=r"surrogate: added.density_pellet"):
        calibration_settings_from(_plain("surrogate.added.density_pellet=[-1,3000]"))


def test_the_extension_stops_at_the_profiles_limits():
    """profile=lab's screening.limits: sliding friction at most 1 and the lobe spacing in
    [0.15, 0.2679] (where a trilobe's lobes still touch) whatever the Table-6 rule asks; a limit
    that holds fewer than two screened levels, or names a parameter not screened, is an error
    naming the key."""
    from bo.cli.common import screen_settings_from
    from bo.screening.bounds import PhysicalLimit

    s = calibration_settings_from(_plain()).screening
    assert s.physical_limits()["mu_s_pg"] == PhysicalLimit(0.0, 1.0)
    assert s.physical_limits()["lobe_spacing_sinter"] == PhysicalLimit(0.15, 0.2679)
    with pytest.raises(ConfigError, match=r"screening: limits.lobe_spacing_sinter = \[0.25, 0.3\].*at least two of "
                                          r"the screened levels \[0.15, 0.20895, 0.2679\]"):
        screen_settings_from(_plain("screening.limits.lobe_spacing_sinter=[0.25,0.3]"))
    with pytest.raises(ConfigError, match=r"limits.coh_pp .*limits of screened parameters"):
        screen_settings_from(_plain("+screening.limits.coh_pp=[0,1]"))
    with pytest.raises(ConfigError, match=r"limits.mu_s_pp .*low < high"):
        screen_settings_from(_plain("screening.limits.mu_s_pp=[1,0.5]"))


def _shipped_screening(tmp_path):
    """The first lab campaign's settings (profile=lab_4s) and its screening results read from a copy
    of its shipped store (the shipped file is never opened for writing); nothing is sent to the DEM."""
    import shutil
    from pathlib import Path

    from bo.campaign.executor import InProcessExecutor
    from bo.cli.common import MODEL_KEYS, open_store
    from bo.screening.pipeline import run_screening

    plain = _plain(profile="lab_4s")
    settings = calibration_settings_from(plain)
    s = settings.screening
    shipped = Path(__file__).resolve().parents[1] / "campaigns" / "table2" / "lab_4s.sqlite"
    shutil.copy(shipped, tmp_path / "lab.sqlite")
    store = open_store(tmp_path / "lab.sqlite", plain, MODEL_KEYS + ("measured",))  # as calibrate
    assert store.counts("screening")["done"] == 66

    def nothing_runs(tasks):
        raise AssertionError(f"the shipped screening is complete; {len(tasks)} task(s) were sent to the DEM")

    results = run_screening(store, InProcessExecutor(nothing_runs, 1), s.table, n_fake=s.n_fake, seeds=list(s.seeds),
                            condition=s.condition, kpis=list(s.kpis), stage="screening")
    return settings, results


KPIS4 = ["angle_of_repose_deg", "shear_angle_deg", "mass_flow_rate_full_kg_s", "mass_lower_box_full_kg"]


def test_the_lab_screening_has_the_second_stage(tmp_path):
    """profile=lab analyses its screening with the stepwise's second stage: on the shipped store's
    66 runs the pellet friction, masked main effects only by the lobe spacing's curvature and its
    interaction with mu_s_ss, is selected beside them (significant in both replicates of the shear
    angle and the lower-box mass). A bad value is an error naming the key."""
    from bo.cli.common import screen_settings_from
    from bo.screening.stepwise import analyse_screening

    settings, results = _shipped_screening(tmp_path)
    s = settings.screening
    assert s.second_order
    plain_table = analyse_screening(results, s.p_threshold, s.selection_fraction, kpis=KPIS4).table
    second = analyse_screening(results, s.p_threshold, s.selection_fraction, kpis=KPIS4, second_order=True).table
    assert plain_table.selected_parameters == ("e_pp", "mu_s_ss", "lobe_spacing_sinter")  # design order
    assert second.selected_parameters == ("mu_s_pp", "e_pp", "mu_s_ss", "lobe_spacing_sinter")
    assert second.cell("mu_s_pp", "shear_angle_deg") == "+2/2"
    assert second.cell("mu_s_pp", "mass_lower_box_full_kg") == "-2/2"
    with pytest.raises(ConfigError, match=r"screening: second_order = 'maybe' is not allowed; expected true or false"):
        screen_settings_from(_plain("screening.second_order=maybe"))


def test_the_pooled_noise_comes_from_the_screening_points_inside_the_bounds(tmp_path):
    """The GP's fixed noise is the replicate scatter of the screening points the calibration keeps
    (18 of 33 inside the lobe-spacing limit): on the shipped runs the parted trilobes at 0.3 scatter
    more in the shear angle (pair sd 1.79 deg against 1.22) and the lower box (0.26 against 0.12 kg)."""
    from bo.calibration.pipeline import pooled_replicate_covariance, screening_points_inside

    settings, results = _shipped_screening(tmp_path)
    names = ("lobe_spacing_sinter", "mu_s_ss")
    bounds = np.array([[0.15, 0.525], [0.2679, 0.875]])
    inside = screening_points_inside(results, names, bounds)
    assert inside.sum() == 18
    s = results.physical[:, results.parameter_names.index("lobe_spacing_sinter")]
    assert (s[~inside] > 0.29).all() and (s[inside] < 0.23).all()
    reps = results.kpi_values[:, :, [results.kpi_index(k) for k in KPIS4]]
    kept, dof = pooled_replicate_covariance(reps[inside])
    every, _ = pooled_replicate_covariance(reps)
    assert dof == 18
    sd, sd_all = np.sqrt(np.diag(kept)), np.sqrt(np.diag(every))
    np.testing.assert_allclose(sd, [0.501, 1.223, 0.219, 0.120], atol=2e-3)
    assert sd[1] < 0.85 * sd_all[1] and sd[3] < 0.7 * sd_all[3]


def test_surrogate_limits_cut_a_calibrated_range():
    """surrogate.limits cuts a calibrated range wherever the proposal or the screened range passes
    it (a trilobe's lobes touch at 1 / (2 + sqrt 3) and have parted at 0.3), names the cut in the
    note, and a limit that leaves nothing is an error naming the key."""
    import math

    from torchdem.mixture import trilobe_template

    for s, parted in ((0.2679, False), (0.3, True)):
        t = trilobe_template(s)
        gap = np.linalg.norm(t.offsets[0] - t.offsets[1]) - 2 * t.radii[0]
        assert (gap > 0) == parted
    assert 1 / (2 + math.sqrt(3)) == pytest.approx(0.2679, abs=1e-4)
    s = calibration_settings_from(_plain("+surrogate.limits.lobe_spacing_sinter=[0.15,0.2679]")).surrogate
    screening = SimpleNamespace(
        results=SimpleNamespace(levels=lambda: {"mu_s_ss": (0.525, 0.875), "lobe_spacing_sinter": (0.15, 0.3)},
                                parameter_names=("mu_s_ss", "lobe_spacing_sinter")),
        analysis=SimpleNamespace(selected_parameters=("mu_s_ss", "lobe_spacing_sinter")), proposal=None)
    names, bounds, note = choose_parameters(screening, s)
    assert names[:2] == ("mu_s_ss", "lobe_spacing_sinter")
    np.testing.assert_allclose(bounds[:, :2], [[0.525, 0.15], [0.875, 0.2679]])
    assert "cut by surrogate.limits: lobe_spacing_sinter [0.15, 0.3] -> [0.15, 0.2679]" in note
    far = calibration_settings_from(_plain("+surrogate.limits.lobe_spacing_sinter=[0.31,0.4]")).surrogate
    with pytest.raises(ConfigError, match=r"surrogate.limits.lobe_spacing_sinter = \[0.31, 0.4\] leaves nothing"):
        choose_parameters(screening, far)
    with pytest.raises(ConfigError, match=r"surrogate: limits.lobe_spacing_sinter = \[0.3, 0.2\]"):
        calibration_settings_from(_plain("+surrogate.limits.lobe_spacing_sinter=[0.3,0.2]"))


def test_the_lab_proposal_compares_only_the_runs_where_trilobes_are_whole(tmp_path):
    """On the shipped screening, the Table-6 rule leaves the 15 runs at lobe spacing 0.3 (parted
    lobes) out: inside, the shear angle's run means stop at 30.2 deg (lab 42.5) and the lower box's
    start at 34.1 kg (lab 32.3), so the rule raises the high bounds of the lobe spacing (capped at
    0.2679), mu_s_ss (capped at 1) and mu_s_pp; with every run, all four KPIs were inside."""
    from bo.screening.bounds import propose_extension
    from bo.screening.pipeline import measured_for
    from bo.screening.stepwise import analyse_screening

    settings, results = _shipped_screening(tmp_path)
    s = settings.screening
    table = analyse_screening(results, s.p_threshold, s.selection_fraction, kpis=KPIS4, second_order=True).table
    lab = measured_for(results.kpi_names, load_measured().condition("50-50").kpis)
    everything = propose_extension(results, table, lab, kpis=KPIS4,
                                   limits={k: v for k, v in s.physical_limits().items() if k != "lobe_spacing_sinter"})
    assert all(c.position == "inside" for c in everything.comparisons)
    whole = propose_extension(results, table, lab, kpis=KPIS4, limits=s.physical_limits())
    assert whole.reasoning[0].startswith("15 of the screening's 33 runs lie outside the limits (lobe_spacing_sinter "
                                         "[0.15, 0.2679])")
    position = {c.kpi: c.position for c in whole.comparisons}
    # the lab's shear angle lies above the range, its lower-box mass below
    assert position == {"angle_of_repose_deg": "inside", "shear_angle_deg": "above",
                        "mass_flow_rate_full_kg_s": "inside", "mass_lower_box_full_kg": "below"}
    bounds = dict(whole.proposed_bounds)
    assert bounds["lobe_spacing_sinter"] == pytest.approx((0.15, 0.2679))
    assert bounds["mu_s_ss"] == pytest.approx((0.525, 1.0))
    assert bounds["mu_s_pp"] == pytest.approx((0.368, 0.858))  # one screened range (0.245) up
    assert bounds["e_pp"] == pytest.approx(whole.screened_bounds["e_pp"])


def test_the_pellet_wall_friction_is_calibrated_on_the_evidence_of_both_replicates(tmp_path):
    """profile=lab adds mu_s_pg to the calibration: per replicate it is significant in 1 of 2 (Table 5's
    rule asks 2 of 2), but one regression on both replicates with the second stage's terms finds it on
    the shear angle and the lower box at p < 1e-3, with no effect on the flow."""
    import statsmodels.api as sm

    settings, results = _shipped_screening(tmp_path)
    assert settings.surrogate.added["mu_s_pg"] == (0.285, 0.9)
    names = list(results.parameter_names)
    coded = np.vstack([results.coded] * results.n_replicates)
    s, ss = coded[:, names.index("lobe_spacing_sinter")], coded[:, names.index("mu_s_ss")]
    design = np.column_stack([np.ones(len(coded)), coded, s * s, s * ss])
    j = 1 + names.index("mu_s_pg")
    fits = {}
    for kpi in KPIS4[1:]:
        y = np.concatenate([results.kpi_values[:, r, results.kpi_index(kpi)] for r in range(results.n_replicates)])
        fits[kpi] = sm.OLS(y, design).fit()
    assert fits["shear_angle_deg"].params[j] > 0.5 and fits["shear_angle_deg"].pvalues[j] < 1e-3
    assert fits["mass_lower_box_full_kg"].params[j] < 0 and fits["mass_lower_box_full_kg"].pvalues[j] < 1e-3
    assert fits["mass_flow_rate_full_kg_s"].pvalues[j] > 0.5


def _replay_shipped(profile, name, runs, tmp_path, monkeypatch, said=None):
    """`make run`'s command for `profile` on a copy of the shipped store campaigns/table2/`name`.sqlite, with
    an executor that records what reaches the DEM and refuses it, and with the GP cross-validation, the
    GA and the bounds' optimiser made to fail if called: everything the store holds must be read from
    it. The campaign resumes with nothing sent to the DEM, its `runs` runs all there, the shipped file
    untouched, and the calibrated set the one campaigns/table2/calibration_`name`.json (the discovery's
    input) records; with verification.fresh it asks the DEM for the 5 verification runs again, and
    nothing else. Returns the first run's summary and the recorded calibration; the first run's
    console lines are appended to ``said`` when given."""
    import contextlib
    import json
    from pathlib import Path

    from bo.campaign.executor import EvalOutcome, InProcessExecutor
    from bo.cli import calibrate as app

    table2 = Path(__file__).resolve().parents[1] / "campaigns" / "table2"
    shipped = table2 / f"{name}.sqlite"
    before = shipped.stat().st_mtime_ns
    sent = []

    def nothing_runs(tasks):  # records what reaches the DEM and refuses it (stored as failed runs)
        sent.extend(tasks)
        return [EvalOutcome.failure("refused: the test runs no DEM", 0.0) for _ in tasks]

    monkeypatch.setattr(app, "executor_from",
                        lambda *a, **k: contextlib.nullcontext(InProcessExecutor(nothing_runs, 1)))
    # nor is anything the store holds computed again on this machine: the rounds' cross-validations,
    # the GA and what the bounds allow are artifacts whose keys do not see the machine's last bits
    import bo.calibration.pipeline as pipeline

    def computed(what):
        def refuse(*a, **k):
            raise AssertionError(f"{what} computed again instead of read from the shipped store")
        return refuse
    for what in ("best_kernel_cv", "repeated_ga", "attainable_ranges"):
        monkeypatch.setattr(pipeline, what, computed(what))

    def calibrate(run, *overrides, echo=lambda s: None):
        return app.calibrate(_plain(f"store_from={shipped}", f"store={tmp_path / (run + '.sqlite')}", *overrides,
                                    profile=profile), tmp_path / run, echo=echo)
    summary = calibrate("run", echo=(said if said is not None else []).append)
    assert not sent
    assert summary["dem_evaluations"]["total"] == runs
    recorded = json.loads((table2 / f"calibration_{name}.json").read_text())
    assert summary["calibrated_parameters"] == recorded["calibrated_parameters"]
    assert shipped.stat().st_mtime_ns == before                       # the shipped file is left as it is
    calibrate("fresh", "verification.fresh=true")
    assert len(sent) == 5 and len({t.seed for t in sent}) == 5
    assert all(dict(t.params) == recorded["calibrated_parameters"] and t.condition == "50-50" for t in sent)
    return summary, recorded


def test_make_run_finds_the_shipped_lab_campaign_complete(tmp_path, monkeypatch):
    """The lab campaign (profile=lab, store_from=campaigns/table2/lab.sqlite) resumes from a copy of
    the shipped store and sends nothing to the DEM but the verification made again (_replay_shipped);
    what the bounds allow is read from the store too."""
    import json
    from pathlib import Path

    summary, recorded = _replay_shipped("lab", "lab", 224, tmp_path, monkeypatch)
    # what the bounds allow is read from the shipped store too, as calibration_lab.json records it
    written = json.loads(Path(summary["files"]["json"]).read_text())
    assert written["attainable"] == recorded["attainable"]
    assert {a["kpi"]: a["feasible"] for a in written["attainable"]}["shear_angle_deg"]
    # what holds the shear angle at 40 deg is the angle of repose's CI, and the reverse
    from bo.surrogate.attainable import AttainableRange
    held = {a["kpi"]: AttainableRange.from_dict(a).held_by for a in written["attainable"]}
    assert held["shear_angle_deg"] == ("angle_of_repose_deg",) and held["angle_of_repose_deg"] == ("shear_angle_deg",)


def test_make_run_finds_the_shipped_box_campaign_complete(tmp_path, monkeypatch):
    """`make run`'s campaign (profile=lab_box, store_from=campaigns/table2/lab_box.sqlite) resumes from a
    copy of the shipped store and sends nothing to the DEM but the verification made again
    (_replay_shipped): its 74 runs are all there, it calibrates the box's four, and it holds the lab
    campaign's contact parameters."""
    import json
    from pathlib import Path

    _, recorded = _replay_shipped("lab_box", "lab_box", 74, tmp_path, monkeypatch)
    assert set(recorded["calibrated_parameters"]) == {"geometry_upper_width", "fill_friction", "mu_s_pg", "mu_s_sg"}
    lab = json.loads((Path(__file__).resolve().parents[1] / "campaigns" / "table2"
                      / "calibration_lab.json").read_text())["calibrated_parameters"]
    assert all(recorded["held_parameters"][k] == pytest.approx(v, rel=1e-5) for k, v in lab.items() if k != "mu_s_pg")


def test_make_run_finds_the_shipped_round_campaign_complete(tmp_path, monkeypatch):
    """`make run`'s campaign (profile=lab_round, store_from=campaigns/table2/lab_round.sqlite) resumes from a
    copy of the shipped store and sends nothing to the DEM but the verification made again
    (_replay_shipped): its 80 runs are all there, it calibrates the slot and the sinter's three frictions,
    it holds the box campaign's set, and its report sets the validation beside the paper's Table A.6, as
    does its console: each condition's largest error over the four KPIs, then the largest of all."""
    import json
    from pathlib import Path

    said = []
    summary, recorded = _replay_shipped("lab_round", "lab_round", 80, tmp_path, monkeypatch, said)
    assert set(recorded["calibrated_parameters"]) == {"geometry_outlet_width", "mu_r_ss", "mu_s_ss", "mu_s_sg"}
    box = json.loads((Path(__file__).resolve().parents[1] / "campaigns" / "table2"
                      / "calibration_lab_box.json").read_text())["calibrated_parameters"]
    assert recorded["held_parameters"]["fill_friction"] == pytest.approx(box["fill_friction"], rel=1e-5)
    assert recorded["held_parameters"]["mu_s_pg"] == pytest.approx(box["mu_s_pg"], rel=1e-5)
    report = Path(summary["files"]["md"]).read_text()
    assert "Largest validation |error|: this campaign 5.89 %, the paper 7.23 %." in report
    validation = [line for line in said if "validation " in line and "|error|" in line]
    assert validation[:3] == [
        "  validation 75-25          largest |error| 2.45 % (shear_angle_deg); 2 of 4 objective KPIs inside the "
        "lab's 95 % CI",
        "  validation 25-75          largest |error| 5.89 % (mass_flow_rate_full_kg_s); 2 of 4 objective KPIs inside "
        "the lab's 95 % CI",
        "  validation 50-50-reverse  largest |error| 3.46 % (shear_angle_deg); 2 of 4 objective KPIs inside the "
        "lab's 95 % CI"]
    assert validation[3] == ("largest validation |error| 5.89 % (25-75, mass_flow_rate_full_kg_s); "
                             "the paper's (Table A.6) 7.23 %")


def test_the_box_profile_holds_the_lab_calibration_and_varies_the_box():
    """profile=lab_box: every run has the lab calibration's set (conf/contact/table2_lab.yaml equals
    the shipped calibration_lab.json's parameters to 6 digits) under the four it calibrates: the upper
    box's width, the fill's friction share and both wall frictions, whose values reach a run's
    walls and fill; the fill's friction from 0.6 (at 0.45 the reverse layering jammed); the first
    initial design it reuses is in the shipped store, and with its runs the campaign makes at most 74
    lab-geometry runs; the GA caps the wall frictions at 0.9, not the box or the fill."""
    import json
    from pathlib import Path

    from bo.surrogate.ga import GASettings, ga_bounds
    from torchdem.drawdown import FILL_FRICTION_PARAMETER

    plain = _plain(profile="lab_box")
    s = calibration_settings_from(plain)
    model, _ = calibration_model_from(plain, load_measured())
    shipped = json.loads((Path(__file__).resolve().parents[1] / "campaigns" / "table2"
                          / "calibration_lab.json").read_text())["calibrated_parameters"]
    for name, value in shipped.items():
        assert model.fixed[name] == float(f"{value:.6g}"), name
    assert model.fixed["mu_s_sg"] == 0.38  # Table 4, not calibrated by profile=lab
    four = ("geometry_upper_width", "fill_friction", "mu_s_pg", "mu_s_sg")
    assert s.screening.table.names == four and s.surrogate.parameters == four
    test = model.test_for("50-50", [{"geometry_upper_width": 0.324, "fill_friction": 0.55, "mu_s_pg": 0.9,
                                     "mu_s_sg": 0.83}])
    assert test.geometry.upper_width == 0.324 and test.geometry.mirror
    assert test.parameter_sets[0]["mu_s_pg"] == 0.9 and test.parameter_sets[0]["mu_s_pp"] == 0.858
    assert test.parameter_sets[0][FILL_FRICTION_PARAMETER] == 0.55
    a = s.surrogate.adaptive
    assert s.surrogate.bounds["fill_friction"] == (0.6, 1.0)
    screening_runs = (2 * (s.screening.table.k + 2) + 1) * len(s.screening.seeds)
    store = Path(__file__).resolve().parents[1] / "campaigns" / "table2" / "lab_box.sqlite"
    assert s.surrogate.reuse_designs == ("b34a94bf58f6",)
    with contextlib.closing(sqlite3.connect(f"file:{store}?mode=ro", uri=True)) as conn:  # the shipped store, read only
        earlier = conn.execute("SELECT COUNT(*) FROM evaluations WHERE stage = 'initial' AND batch_key = ? "
                               "AND status = 'done'", s.surrogate.reuse_designs).fetchone()[0]
    assert earlier == 4
    assert screening_runs + earlier + a.budget + len(s.verification_seeds) + 3 * len(s.validation_seeds) <= 74
    bounds = np.array([s.surrogate.bounds[n] for n in four]).T
    np.testing.assert_allclose(ga_bounds(bounds, GASettings(), four)[1], [0.35, 1.0, 0.9, 0.9])


def test_the_fines_profile_holds_the_box_set_keeps_the_fines_and_varies_slot_restitution_and_sliding():
    """profile=lab_fines: every run has the box calibration's set (calibration_lab_box.json's four, at
    full precision, on the lab calibration's contacts) with the sinter's whole sieve analysis (the
    5.6-8 and 8-10 mm classes the other lab profiles scalp); the slot's width, the pellets' restitution
    and the sinter's sliding reach a run's walls and contact sets; the campaign makes at most 50 runs."""
    import json
    from pathlib import Path

    from torchdem.drawdown import FILL_FRICTION_PARAMETER

    plain = _plain(profile="lab_fines")
    s = calibration_settings_from(plain)
    model, _ = calibration_model_from(plain, load_measured())
    box = json.loads((Path(__file__).resolve().parents[1] / "campaigns" / "table2"
                      / "calibration_lab_box.json").read_text())
    assert model.geometry.upper_width == box["calibrated_parameters"]["geometry_upper_width"]
    assert model.geometry.mirror and model.settings.fines_cut is None
    for name in ("fill_friction", "mu_s_pg", "mu_s_sg"):
        assert model.fixed[name] == box["calibrated_parameters"][name], name
    for name, value in box["held_parameters"].items():
        assert model.fixed[name] == value, name
    three = ("geometry_outlet_width", "e_pp", "mu_s_ss")
    assert s.screening.table.names == three and s.surrogate.parameters == three
    test = model.test_for("50-50", [{"geometry_outlet_width": 0.061, "e_pp": 0.7, "mu_s_ss": 0.55}])
    assert test.geometry.outlet_width == 0.061 and test.geometry.upper_width == model.geometry.upper_width
    sets = test.parameter_sets[0]
    assert (sets["e_pp"], sets["mu_s_ss"], sets["mu_s_pg"]) == (0.7, 0.55, box["calibrated_parameters"]["mu_s_pg"])
    assert sets[FILL_FRICTION_PARAMETER] == box["calibrated_parameters"]["fill_friction"]
    sinter = {m.name: m for m in test.mixture.materials}["sinter"]
    assert min(c.d_min for c in sinter.sieve) == pytest.approx(0.0056)  # Table 1's smallest class, kept
    box_model, _ = calibration_model_from(_plain(profile="lab_box"), load_measured())
    scalped = {m.name: m for m in box_model.test_for("50-50", [{}]).mixture.materials}["sinter"]
    assert min(c.d_min for c in scalped.sieve) == pytest.approx(0.010)  # what profile=lab_box runs
    a = s.surrogate.adaptive
    screening_runs = (2 * (s.screening.table.k + s.screening.n_fake) + 1) * len(s.screening.seeds)
    assert screening_runs == 18
    assert screening_runs + a.budget + len(s.verification_seeds) + 3 * len(s.validation_seeds) <= 50


def test_the_round_profile_holds_the_round_trilobe_and_varies_slot_and_the_sinters_frictions():
    """profile=lab_round: profile=lab_fines's model (the box set, the sinter's whole sieve analysis) with
    the sinter as the default trilobe (lobe spacing 0.15) and the pellets' restitution at the fines
    optimum's 0.71; the slot's width and the sinter's rolling, sliding and wall friction reach a run's
    walls and contact sets; every surrogate point runs at 75-25 too, for the jam classifier; the
    campaign makes at most 80 runs (validation on the paper's 5 seeds)."""
    plain = _plain(profile="lab_round")
    s = calibration_settings_from(plain)
    model, _ = calibration_model_from(plain, load_measured())
    fines, _ = calibration_model_from(_plain(profile="lab_fines"), load_measured())
    assert model.fixed["lobe_spacing_sinter"] == 0.15 and fines.fixed["lobe_spacing_sinter"] == 0.257418
    assert model.fixed["e_pp"] == 0.71 and model.fixed["mu_r_pp"] == fines.fixed["mu_r_pp"] == 0.105828
    for name in ("fill_friction", "mu_s_pg"):
        assert model.fixed[name] == fines.fixed[name], name
    assert model.geometry == fines.geometry and model.settings.fines_cut is None
    four = ("geometry_outlet_width", "mu_r_ss", "mu_s_ss", "mu_s_sg")
    assert s.screening.table.names == four and s.surrogate.parameters == four
    assert s.surrogate.jam_conditions == ("75-25",)
    test = model.test_for("50-50", [{"geometry_outlet_width": 0.062, "mu_r_ss": 0.33, "mu_s_ss": 0.9,
                                     "mu_s_sg": 0.85}])
    assert test.geometry.outlet_width == 0.062
    sets = test.parameter_sets[0]
    assert (sets["mu_r_ss"], sets["mu_s_ss"], sets["mu_s_sg"], sets["e_pp"]) == (0.33, 0.9, 0.85, 0.71)
    a = s.surrogate.adaptive
    screening_runs = (2 * (s.screening.table.k + s.screening.n_fake) + 1) * len(s.screening.seeds)
    assert screening_runs == 18
    surrogate_runs = a.budget * len(s.surrogate.seeds) * (1 + len(s.surrogate.jam_conditions))
    assert len(s.validation_seeds) == 5
    assert screening_runs + surrogate_runs + len(s.verification_seeds) + 3 * len(s.validation_seeds) <= 80


def test_the_priors_profile_starts_from_the_papers_values_and_calibrates_every_value_lab_round_held():
    """profile=lab_priors: lab_round's model (the lab geometry, the fines kept, the default trilobe) with
    the paper's Table 8 and Table 4 for what it does not calibrate, and as parameters every value the
    earlier lab campaigns fitted (slot, box width, fill friction, the four sliding frictions, the
    sinter's rolling, the densities). Each reaches a run; the screening's 21 points lie inside the
    surrogate's bounds, so all are reused; the plan is at most 140 runs, within the issue's 215."""
    from bo.calibration.plan import campaign_plan

    plain = _plain(profile="lab_priors")
    s = calibration_settings_from(plain)
    model, _ = calibration_model_from(plain, load_measured())
    round_model, _ = calibration_model_from(_plain(profile="lab_round"), load_measured())
    held = {"mu_r_pp": 0.12, "e_pp": 0.76, "mu_r_pg": 0.16, "e_ss": 0.35, "e_pg": 0.7, "mu_r_sg": 0.08,
            "e_sg": 0.4, "lobe_spacing_sinter": 0.15}
    assert {k: model.fixed[k] for k in held} == held
    assert model.settings == round_model.settings and model.settings.fines_cut is None
    ten = ("geometry_outlet_width", "geometry_upper_width", "fill_friction", "mu_s_pp", "mu_s_ss", "mu_r_ss",
           "mu_s_pg", "mu_s_sg", "density_pellet", "density_sinter")
    assert s.screening.table.names == ten and s.surrogate.parameters == ten
    point = {"geometry_outlet_width": 0.061, "geometry_upper_width": 0.33, "fill_friction": 0.7, "mu_s_pp": 0.65,
             "mu_s_ss": 0.95, "mu_r_ss": 0.3, "mu_s_pg": 0.5, "mu_s_sg": 0.9, "density_pellet": 3300.0,
             "density_sinter": 3700.0}
    test = model.test_for("50-50", [point])
    assert test.geometry.outlet_width == 0.061 and test.geometry.upper_width == 0.33
    sets = test.parameter_sets[0]
    for name in ("fill_friction", "mu_s_pp", "mu_s_ss", "mu_r_ss", "mu_s_pg", "mu_s_sg"):
        assert sets[name] == point[name], name
    densities = {m.name: m.density for m in test.member_mixtures[0].materials}
    assert densities == {"pellet": 3300.0, "sinter": 3700.0}
    # the screening's levels are the surrogate's bounds: every screening point is surrogate data
    bounds = s.surrogate.bounds
    for name, levels in zip(s.screening.table.names, s.screening.table.levels()):
        assert (levels[0], levels[-1]) == tuple(bounds[name]), name
    plan = campaign_plan(s, load_measured(None))
    assert {st.stage: dict(st.runs) for st in plan.stages} == {
        "screening": {"50-50": 42}, "surrogate": {"50-50": 39, "75-25": 39}, "verification": {"50-50": 5},
        "validation": {"75-25": 5, "25-75": 5, "50-50-reverse": 5}}
    assert plan.total == 140 <= 215
