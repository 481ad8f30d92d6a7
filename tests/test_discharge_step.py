"""A longer time step from the gate's opening on (``RunSettings.discharge_time_step_fraction``).

- The clock runs on through a change of step: a sphere falling freely for 400 steps of dt and
  400 of 1.5 dt is where z0 - g t^2 / 2 puts it (velocity Verlet is exact under a constant force)
  to 1e-12 m, at t = 400 dt + 600 dt.
- Frictionless elastic spheres in a closed box keep kinetic + Hertz elastic energy within 0.5 %
  over 5,000 steps at 0.15 of the Rayleigh step and 5,000 at 0.225 (the conservation test's bound).
- A draw down with a discharge step: the fill is the same run as without it, bit for bit, up to
  the gate (its bulk density and settling speed as the gate opens); the load cell still samples
  at its rate; mass is conserved; a run stopped in the discharge resumes from its checkpoint to
  the uninterrupted run's KPIs bit for bit.
- The setting's config: out of range is an error naming it; null is hashed as absent, so stores
  made before it keep their hash; a retry's shorter step shortens both steps.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from conftest import F64, elastic_spheres_in_a_box, glass, simulation, steel
from torchdem.drawdown import DrawDownTest, RunSettings
from torchdem.errors import ConfigError
from torchdem.geometry import DrawDownGeometry
from torchdem.materials import interaction_table
from torchdem.mixture import Mixture, ParticleMaterial, SieveClass
from torchdem.simulation import elastic_energy, kinetic_energy


def test_free_fall_is_exact_across_a_change_of_step():
    mats = [glass(), steel()]
    table = interaction_table(mats, {("glass", "glass"): dict(mu_s=0.5, mu_r=0.05, restitution=0.5)})
    z0 = 50.0
    sim = simulation(torch.tensor([[[0.5, 0.5, z0]]], dtype=F64), torch.full((1, 1), 0.005, dtype=F64), mats, table,
                     domain=((0.0, 0.0, 0.0), (1.0, 1.0, 60.0)))
    dt = sim.system.dt
    sim.advance(400)
    sim.system = sim.system.with_time_step(1.5 * dt, sim.state.step)
    assert sim.time == pytest.approx(400 * dt, rel=1e-14)
    sim.advance(400)
    t = 400 * dt + 400 * 1.5 * dt
    assert sim.state.step == 800 and sim.time == pytest.approx(t, rel=1e-12)
    g = 9.81
    assert float(sim.state.bodies.position[0, 0, 2]) == pytest.approx(z0 - 0.5 * g * t * t, abs=1e-12)
    assert float(sim.state.bodies.velocity[0, 0, 2]) == pytest.approx(-g * t, rel=1e-12)


def test_elastic_spheres_keep_their_energy_when_the_step_grows():
    sim = elastic_spheres_in_a_box(time_step_fraction=0.15)
    e0 = (kinetic_energy(sim.system, sim.state) + elastic_energy(sim.system, sim.state)).item()
    sim.advance(5000)
    in_contact = sim.state.pairs.n
    sim.system = sim.system.with_time_step(1.5 * sim.system.dt, sim.state.step)
    sim.advance(5000)
    e1 = (kinetic_energy(sim.system, sim.state) + elastic_energy(sim.system, sim.state)).item()
    assert in_contact > 0  # the step changes while spheres touch
    assert abs(e1 - e0) / e0 < 0.005, (e0, e1)


def _drawdown(discharge_fraction: float | None) -> DrawDownTest:
    """The tests' scaled-down box (tests/test_drawdown.py), on until the discharge has ended."""
    pellet = ParticleMaterial("pellet", "sphere", (SieveClass(0.012, 0.014, 1.0),), 3602.4, label="pellet")
    sinter = ParticleMaterial("sinter", "sinter_trilobe", (SieveClass(0.014, 0.018, 1.0),), 3449.0, label="sinter")
    mix = Mixture("mini", (pellet, sinter), (0.5, 0.5), ("pellet", "sinter", "pellet", "sinter"), 4.0)
    geometry = DrawDownGeometry(upper_width=0.16, depth=0.2, upper_height=0.3, outlet_width=0.05,
                                upper_bottom_z=0.2, lower_width=0.4, lower_height=0.15, slice_depth=0.04)
    settings = RunSettings(fill_time=0.35, discharge_time=1.2, max_discharge_time=2.6, flow_window=(0.1, 0.5), shear_modulus=1e6,
                           time_step_fraction=0.2, discharge_time_step_fraction=discharge_fraction,
                           metres_per_pixel=0.002)
    return DrawDownTest(mix, geometry, settings=settings)


class Interrupt(Exception):
    pass


@pytest.mark.slow
def test_a_drawdown_fills_as_before_and_discharges_at_its_own_step(tmp_path):
    plain = _drawdown(None).run(seeds=[5])
    test = _drawdown(0.3)
    longer = test.run(seeds=[5])
    assert longer.dt == plain.dt == plain.discharge_dt
    assert longer.discharge_dt == pytest.approx(1.5 * longer.dt, rel=1e-12)
    # the fill is the same run up to the gate
    for key in ("fill_bulk_density_kg_m3", "fill_mass_kg"):
        assert longer.kpis[0][key] == plain.kpis[0][key], key
    assert longer.conservation[0]["max_speed_at_gate_open_m_s"] == plain.conservation[0]["max_speed_at_gate_open_m_s"]
    # the load cell samples at 50 Hz through the discharge, from the gate's opening to its end
    t, m = longer.loadcell[0]
    assert t[0] == pytest.approx(0.0, abs=longer.dt) and np.allclose(np.diff(t), 0.02, atol=longer.discharge_dt)
    assert 1.2 - 0.02 < t[-1] < 2.6 and longer.kpis[0]["discharge_ended"] == 1
    c, k = longer.conservation[0], longer.kpis[0]
    assert longer.failed == {} and longer.errors[0] == {} == plain.errors[0]
    assert abs(c["upper_kg"] + c["lower_kg"] + c["in_flight_kg"] - c["fill_kg"]) < 1e-4 * c["fill_kg"]
    assert k["mass_lower_box_kg"] > 0.3 * k["fill_mass_kg"]
    # the discharge took steps of its own length: its steps span the load cell's record
    fill_steps = math.ceil(round(0.35 / longer.dt, 6))
    assert (longer.steps - fill_steps) * longer.discharge_dt == pytest.approx(t[-1], abs=0.021)

    # a run stopped in the discharge resumes from its checkpoint to the same KPIs
    ckpt = tmp_path / "run.pt"

    def stop(simulated, wall):
        if simulated > 0.35 + 0.3:
            raise Interrupt

    with pytest.raises(Interrupt):
        test.run(seeds=[5], checkpoint=ckpt, checkpoint_every=0.25, progress=stop)
    assert ckpt.exists()
    resumed = test.run(seeds=[5], checkpoint=ckpt, checkpoint_every=0.25)
    assert not ckpt.exists()
    assert resumed.kpis[0] == longer.kpis[0]
    np.testing.assert_array_equal(resumed.loadcell[0][1], m)


def test_the_setting_is_checked_hashed_as_absent_while_null_and_scaled_by_a_retry():
    from bo.cli.common import config_hash
    from torchdem import config
    from torchdem.model import DrawDownModel

    with pytest.raises(ConfigError, match=r"discharge_time_step_fraction.*1\.5.*\(0, 1\]"):
        RunSettings(discharge_time_step_fraction=1.5).validate()
    sim = {"device": "cpu", "dtype": "float32", "time_step_fraction": 0.15, "compile": False,
           "guards": {"check_every": 200, "max_speed": 50.0, "energy_tolerance": 0.05, "on_blowup": "raise"}}
    run = {"fill_time_s": 0.8, "discharge_time_s": 3.5, "loadcell_rate_hz": 50.0, "rolling_damping": 0.3,
           "metres_per_pixel": 0.001, "rsd_component": "sinter", "loose_fraction": 0.3}
    with pytest.raises(ConfigError, match=r"sim\.discharge_time_step_fraction.*0"):
        config.run_settings_from({**sim, "discharge_time_step_fraction": 0.0}, run)
    assert config.run_settings_from({**sim, "discharge_time_step_fraction": 0.225}, run) \
        .discharge_time_step_fraction == 0.225
    assert config.run_settings_from(sim, run).discharge_time_step_fraction is None
    assert config_hash({"sim": {**sim, "discharge_time_step_fraction": None}}) == config_hash({"sim": sim})
    assert config_hash({"sim": {**sim, "discharge_time_step_fraction": 0.225}}) != config_hash({"sim": sim})

    test = _drawdown(0.3)
    model = DrawDownModel(conditions={"50-50": test.mixture}, geometry=test.geometry, settings=test.settings,
                          fixed=dict(test.parameter_sets[0]))
    retried = model.test_for("50-50", [{}], time_step_scale=0.8).settings
    assert retried.time_step_fraction == pytest.approx(0.16)
    assert retried.discharge_time_step_fraction == pytest.approx(0.24)
