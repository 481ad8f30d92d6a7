"""A run ends when its discharge has ended, as the lab photographs "once the discharge is
finished" (``RunSettings.max_discharge_time``, ``run.max_discharge_time_s``).

- The end criterion (:func:`torchdem.drawdown._discharges_ended`) on hand-made load-cell records.
- On the small box of tests/test_drawdown.py, cut to a 0.6 s discharge: a fixed end stops the
  runs while the upper box still empties (``discharge_ended`` 0, the lab method's error kept);
  with ``max_discharge_time`` the same runs go on, bit for bit the same up to 0.6 s, until the
  lab method measures an ended discharge (``discharge_ended`` 1, its duration inside the run),
  and more mass reaches the lower box; measured at 0.6 s on the way (``kpis_at_discharge_time``),
  its KPIs are those of the stopped run.
- The setting's bounds, and the store hash of configs that leave it null (shipped stores keep
  theirs).
"""
import dataclasses

import numpy as np
import pytest

from bo.cli.common import config_hash
from torchdem.config import run_settings_from
from torchdem.drawdown import DISCHARGE_END_TOLERANCE, JAM_FRACTION, DrawDownTest, _discharges_ended
from kpi.loadcell import discharge_jammed, discharge_state
from torchdem.errors import ConfigError

from test_drawdown import small_drawdown


def test_end_criterion_on_hand_made_records():
    steady = np.r_[np.linspace(10.0, 2.0, 20), np.full(11, 2.0)]
    falling = np.linspace(10.0, 2.0, 31)
    # the last 11 samples: steady within 1e-3 kg; falling by 0.27 kg a sample
    ended = _discharges_ended(np.stack([steady, falling, falling]), 11, np.full(3, 1e-3), failed={2: "blow-up"})
    assert ended.tolist() == [True, False, True]
    # a record shorter than the tail has not ended
    assert not _discharges_ended(steady[None, :5], 11, np.full(1, 1.0), failed={}).any()
    # the tolerance bounds the spread of the tail: 2.5e-3 kg of spread against 2e-3 and 3e-3
    wobble = np.r_[np.linspace(10.0, 2.0, 20), 2.0 + 2.5e-3 * (np.arange(11) % 2)]
    assert not _discharges_ended(wobble[None], 11, np.full(1, 2e-3), failed={}).any()
    assert _discharges_ended(wobble[None], 11, np.full(1, 3e-3), failed={}).all()


def test_discharge_state_of_a_runs_kpis():
    assert discharge_state({"discharge_ended": 1.0}) == "ended"
    assert discharge_state({"discharge_ended": 0.0}) == "not ended"
    # runs made before it was reported: absent, or NaN where a store filled the KPI set
    assert discharge_state({}) == discharge_state({"discharge_ended": float("nan")}) == "not recorded"
    assert discharge_jammed({"discharge_jammed": 1.0}) and not discharge_jammed({"discharge_jammed": 0.0})
    assert not discharge_jammed({}) and not discharge_jammed({"discharge_jammed": float("nan")})


def _cut(test: DrawDownTest, max_discharge_time: float | None) -> DrawDownTest:
    s = dataclasses.replace(test.settings, discharge_time=0.6, flow_window=(0.1, 0.3), final_window=0.2,
                            max_discharge_time=max_discharge_time)
    return DrawDownTest(test.mixture, test.geometry, settings=s)


def test_a_run_goes_on_until_the_discharge_has_ended():
    base = small_drawdown()
    fixed = _cut(base, None).run(replicates=2, seeds=[3, 4])
    until = _cut(base, 3.0).run_members([(0, 0, 3), (0, 1, 4)], kpis_at_discharge_time=True)
    # the KPIs at 0.6 s of the run that went on are those of the run stopped there
    assert until.kpis_at_discharge_time == fixed.kpis
    assert fixed.kpis_at_discharge_time == []
    for kf, ku, ef, eu, (tf, mf), (tu, mu) in zip(fixed.kpis, until.kpis, fixed.errors, until.errors,
                                                   fixed.loadcell, until.loadcell):
        # stopped at 0.6 s, the upper box still empties: the lab method says so
        assert kf["discharge_ended"] == 0.0 and "still falling" in ef["discharge_end"]
        assert np.isnan(kf.get("discharge_duration_s", np.nan))
        assert mf[-11] - mf[-1] > 10 * DISCHARGE_END_TOLERANCE * kf["fill_mass_kg"]
        # on until it has ended: the same run up to 0.6 s, bit for bit
        assert len(tu) > len(tf) and np.array_equal(tu[:len(tf)], tf) and np.array_equal(mu[:len(mf)], mf)
        assert eu == {} and ku["discharge_ended"] == 1.0 and ku["discharge_jammed"] == kf["discharge_jammed"] == 0.0
        assert 0.6 < ku["discharge_duration_s"] < tu[-1] <= 3.0 + 1e-9
        # the ensemble stopped soon after its last member's tail became steady (checked every 0.1 s), not at 3 s
        assert tu[-1] < max(k["discharge_duration_s"] for k in until.kpis) + 0.2 + 0.1 + 0.05
        tail = mu[tu >= tu[-1] - 0.2 - 1e-9]
        assert tail.max() - tail.min() <= 0.5 * DISCHARGE_END_TOLERANCE * ku["fill_mass_kg"] + 1e-12
        assert ku["mass_lower_box_kg"] > kf["mass_lower_box_kg"] + 0.05 * kf["fill_mass_kg"]
        # the flow's window ends at 0.3 s: the same samples, but the Gaussian filter of the longer
        # record weighs the window's edges a little otherwise
        assert ku["mass_flow_rate_kg_s"] == pytest.approx(kf["mass_flow_rate_kg_s"], rel=1e-3)


def test_max_discharge_time_bounds_and_store_hash():
    sim = {"time_step_fraction": 0.15, "dtype": "float64", "compile": False,
           "guards": {"check_every": 200, "max_speed": 50.0, "energy_tolerance": 0.05, "on_blowup": "raise"}}
    run = {"fill_time_s": 0.8, "discharge_time_s": 4.0, "loadcell_rate_hz": 50, "rolling_damping": 0.3,
           "metres_per_pixel": 0.001, "rsd_component": "sinter", "loose_fraction": 0.3}
    assert run_settings_from(sim, run).max_discharge_time is None
    assert run_settings_from(sim, {**run, "max_discharge_time_s": 8}).max_discharge_time == 8.0
    with pytest.raises(ConfigError, match=r"max_discharge_time.*3\.0.*>= discharge_time \(4 s\)"):
        run_settings_from(sim, {**run, "max_discharge_time_s": 3.0})
    with pytest.raises(ConfigError, match=r"run\.max_discharge_time_s.*> 0 s or null"):
        run_settings_from(sim, {**run, "max_discharge_time_s": -1})
    # null hashes as the key's absence (the stores shipped before it keep their hash); a time does not
    assert config_hash({"run": {**run, "max_discharge_time_s": None}}) == config_hash({"run": run})
    assert config_hash({"run": {**run, "max_discharge_time_s": 8.0}}) != config_hash({"run": run})


def test_a_slot_narrower_than_the_grains_jams_and_reads_as_level_surfaces():
    """A 10 mm slot under 12-18 mm grains lets nothing through: the run reports a jammed discharge
    (``discharge_jammed`` 1, nothing in the lower box, no flow) whose surfaces read 0 deg (the
    fill's level top, the empty lower box's floor; ``torchdem.drawdown.JAM_FRACTION``) instead of
    failing to measure, so a calibration sees the miss."""
    base = small_drawdown()
    geometry = dataclasses.replace(base.geometry, outlet_width=0.01)
    s = dataclasses.replace(base.settings, discharge_time=0.6, flow_window=(0.1, 0.3), final_window=0.2)
    res = DrawDownTest(base.mixture, geometry, settings=s).run(replicates=1, seeds=[3])
    k, err = res.kpis[0], res.errors[0]
    assert "shear_angle_deg" not in err and "angle_of_repose_deg" not in err
    assert k["discharge_jammed"] == 1.0 and k["discharge_ended"] == 1.0
    assert k["mass_lower_box_kg"] < JAM_FRACTION * k["fill_mass_kg"]
    assert abs(k["mass_flow_rate_kg_s"]) < 0.01 * k["fill_mass_kg"] / 0.2  # 1 % of the fill in the fit window
    assert k["shear_angle_deg"] == 0.0 and k["angle_of_repose_deg"] == 0.0
