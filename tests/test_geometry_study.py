"""The geometry study (bo/studies/geometry.py, run_geometry_study, torchdem-study study=geometry).

A known-answer evaluator reads the geometry variant from the condition name
(``torchdem.model.condition_geometry``): the mirrored half box gives the whole box's KPIs plus
seed noise, the slice loses 3 degrees of shear angle. The comparison must call the first
"within noise" and the second "differs", count each (parameter set, geometry) once, resume
without rerunning, and report the cost per run; bad study config values are one-line errors.
"""
from __future__ import annotations

import functools
import json

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from bo.campaign.executor import EvalOutcome, InProcessExecutor
from bo.campaign.store import CampaignStore
from bo.cli.common import plain_config
from bo.cli.study import study_settings_from
from bo.studies.geometry import geometry_comparison
from bo.studies.pipeline import STUDY_STAGES, geometry_report, run_geometry_study
from torchdem.cli import CONF_DIR
from torchdem.errors import ConfigError
from torchdem.geometry import DrawDownGeometry
from torchdem.model import condition_geometry

KPIS = ["shear_angle_deg", "mass_lower_box_full_kg"]
GEOMETRIES = {"full": {"slice_depth": None, "mirror": False}, "lab": {"slice_depth": 0.1, "mirror": True},
              "slice": {"slice_depth": 0.04, "mirror": False}}
SETS = {"table8": {"mu_s_pg": 0.9}, "low_wall": {"mu_s_pg": 0.3}}
NOISE = [0.3, -0.2, 0.1, -0.25]


def known_batch(tasks, *, calls):
    calls.append((tasks[0].condition, len(tasks)))
    g = condition_geometry(tasks[0].condition, DrawDownGeometry())
    out = []
    for t in tasks:
        shear = 40.0 + 10 * t.params["mu_s_pg"] + NOISE[t.seed] - (3.0 if g.slice_depth == 0.04 else 0.0)
        out.append(EvalOutcome.success({"shear_angle_deg": shear, "mass_lower_box_full_kg": 32.0 + NOISE[t.seed]},
                                       60.0 * g.depth_scale * len(tasks)))
    return out


def test_geometry_study_tells_the_mirror_from_the_slice_and_resumes(tmp_path):
    store = CampaignStore(tmp_path / "g.sqlite", "h", extra_stages=STUDY_STAGES)
    calls = []
    executor = InProcessExecutor(functools.partial(known_batch, calls=calls), 10)
    kw = dict(condition="50-50", geometries=GEOMETRIES, parameter_sets=SETS, seeds=[0, 1, 2, 3], kpis=KPIS,
              members_per_ensemble=10)
    runs = run_geometry_study(store, executor, **kw)
    assert len(calls) == 3 and all(n == 8 for _, n in calls)  # one ensemble per geometry, both sets
    assert {c for c, _ in calls} >= {"50-50|mirror=True|slice_depth=0.1", "50-50|mirror=False|slice_depth=None"}
    np.testing.assert_allclose(runs.kpi_values["table8"]["slice"][:, 0], 40 + 9 - 3 + np.array(NOISE))
    assert runs.cost_per_run_s == pytest.approx({"full": 60.0, "lab": 30.0, "slice": 12.0})
    again = run_geometry_study(store, executor, **kw)
    assert len(calls) == 3  # nothing reran
    comparison, files = geometry_report(again, tmp_path, lab_margins={"shear_angle_deg": 1.5})
    verdict = {(r.parameter_set, r.geometry, r.kpi): r for r in comparison.rows}
    for pset in SETS:
        assert verdict[pset, "lab", "shear_angle_deg"].verdict == "within noise"
        assert verdict[pset, "lab", "shear_angle_deg"].difference == pytest.approx(0.0, abs=1e-12)
        row = verdict[pset, "slice", "shear_angle_deg"]
        assert row.verdict == "differs" and row.difference == pytest.approx(-3.0)
        assert row.difference / row.lab_margin == pytest.approx(-2.0)
    assert comparison.passes("lab") and not comparison.passes("slice")
    doc = json.loads(files["json"].read_text())
    assert doc["comparison"]["passes"] == {"lab": True, "slice": False}
    assert "Cost per run: full: 60 s, lab: 30 s, slice: 12 s" in files["md"].read_text()


def test_welch_interval_against_scipy():
    from scipy import stats
    a = np.array([[30.1], [29.5], [30.8], [30.2]])
    b = np.array([[31.0], [32.2], [31.4]])
    row = geometry_comparison({"p": {"ref": a, "other": b}}, ["x"], {}).rows[0]
    res = stats.ttest_ind(b[:, 0], a[:, 0], equal_var=False)
    ci = res.confidence_interval(0.95)
    assert row.ci_low == pytest.approx(ci.low) and row.ci_high == pytest.approx(ci.high)
    assert row.verdict == "differs"


def _plain(*overrides):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return plain_config(compose("study", overrides=["study=geometry", "study_profile=geometry", *overrides]))


def test_geometry_study_config_is_checked():
    s = study_settings_from(_plain())
    assert list(s.geometries) == ["full", "lab", "slice"] and s.geometries["lab"] == {"slice_depth": 0.1,
                                                                                      "mirror": True}
    assert s.parameter_sets["table8"]["mu_s_pg"] == 0.9 and s.parameter_sets["low_wall"]["mu_s_sg"] == 0.3
    assert s.parameter_sets["low_wall"]["e_ss"] == 0.35  # pairs not named keep the config's contact values
    with pytest.raises(ConfigError, match=r"parameter_sets.low_wall.mu_s_pg"):
        study_settings_from(_plain("parameter_sets.low_wall.mu_s_pg=-0.1"))
    with pytest.raises(ConfigError, match=r"geometries.lab.slice_depth"):
        study_settings_from(_plain("geometries.lab.slice_depth=-1"))


def test_lab_effects_profile_changes_one_mechanism_per_set():
    """study_profile=lab_effects: the lab geometry first, float32 and lobe packing as profile=lab,
    and every effect set differs from table8 only in its own mechanism's parameters, by the amount
    stated (cohesion at 0.01 E* = 13,333 J/m^3, densities at 90 %, lobe spacing 0.3)."""
    plain = _plain("study_profile=lab_effects")
    s = study_settings_from(plain)
    assert list(s.geometries) == ["lab", "slice"] and s.geometries["lab"] == {"slice_depth": 0.1, "mirror": True}
    assert plain["sim"]["dtype"] == "float32" and plain["run"]["fill_packing"] == "lobes"
    base = s.parameter_sets["table8"]
    changed = {name: {k for k in base if params[k] != base[k]} for name, params in s.parameter_sets.items()}
    assert changed == {"table8": set(), "cohesion": {"coh_pp", "coh_ss"},
                       "density": {"density_pellet", "density_sinter"}, "clump_shape": {"lobe_spacing_sinter"}}
    assert s.parameter_sets["cohesion"]["coh_pp"] == 13333.0
    assert s.parameter_sets["density"]["density_pellet"] == pytest.approx(0.9 * base["density_pellet"], rel=1e-4)
    assert s.parameter_sets["density"]["density_sinter"] == pytest.approx(0.9 * base["density_sinter"], rel=1e-4)
    assert all(set(p) == set(base) for p in s.parameter_sets.values())
