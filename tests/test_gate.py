"""The gate that slides out (``DrawDownGeometry.gate_opening``) instead of vanishing.

Checks:
- a sphere lying on a plate that starts sliding at V (mu_s 0.3, no rolling friction) is dragged:
  it slips with acceleration mu_s g until its contact point moves with the plate, at
  t = V / (3.5 mu_s g), and then rolls with the plate at 2/7 V (a solid sphere's angular momentum
  about the contact point); both within 3 %;
- the gate's wall: with ``gate_opening`` 0 it is the plate at the floor's height that vanishes at
  the opening, as before; with a time T it lies GATE_CLEARANCE under the floor, slides towards +x
  at outlet_width / T from the opening, is under the floor's right half at the opening + T and
  goes then; the draw down system built with it has moving walls;
- a task parameter ``geometry_gate_opening`` (s) reaches the test's geometry; negative values,
  here and in ``conf/geometry``'s ``gate_opening_s``, are refused by name; null is 0;
- stores: a config with ``gate_opening_s: null`` hashes as one without the key (the shipped
  stores' hashes stand); a time hashes apart.
"""
import dataclasses

import pytest
import torch

from conftest import F64, glass, steel
from bo.cli.common import config_hash
from torchdem.config import geometry_from
from torchdem.drawdown import PAPER_REFERENCE, DrawDownTest
from torchdem.errors import ConfigError
from torchdem.geometry import GATE_CLEARANCE, DrawDownGeometry
from torchdem.materials import interaction_table
from torchdem.model import DrawDownModel
from torchdem.simulation import GuardSettings, Simulation
from torchdem.system import build_system
from torchdem.walls import WallSpec
from test_lab_geometry import SETTINGS, _mini

G = 9.81
MU = 0.3
V = 0.5


def _dragged(steps: int) -> tuple[float, float]:
    """A 5 mm glass sphere at rest on a steel plate that slides at V along x from t = 0:
    (time, sphere's x velocity) after ``steps``."""
    mats = [glass(G=1e8), steel()]
    table = interaction_table(mats, {("glass", "glass"): dict(mu_s=0.5, mu_r=0.0, restitution=0.5),
                                     ("glass", "steel"): dict(mu_s=MU, mu_r=0.0, restitution=0.5,
                                                              rolling_damping=0.0)})
    r = 0.005
    plate = WallSpec("plate", (0.0, 0.0, 0.0), (0, 0, 1), (1, 0, 0), 0.5, 0.1, "steel",
                     velocity=(V, 0.0, 0.0), move_from=0.0, move_until=10.0)
    system, state = build_system(torch.tensor([[[0.0, 0.0, r - 1e-7]]], dtype=F64),
                                 torch.zeros(1, 1, dtype=torch.long), mats, table,
                                 radius=torch.full((1, 1), r, dtype=F64), walls=[plate], gravity=(0.0, 0.0, -G),
                                 time_step_fraction=0.2, domain=((-1.0, -1.0, -0.1), (1.0, 1.0, 0.5)))
    sim = Simulation(system, state, GuardSettings(check_every=5000))
    sim.advance(steps)
    return sim.time, float(sim.state.bodies.velocity[0, 0, 0])


def test_a_sphere_on_a_sliding_plate_slips_at_mu_g_then_rolls_at_two_sevenths_of_its_speed():
    t_roll = V / (3.5 * MU * G)  # 0.0485 s
    dt = _dragged(1)[0]
    t_half, v_half = _dragged(int(0.5 * t_roll / dt))
    assert v_half == pytest.approx(MU * G * t_half, rel=0.03)
    t_end, v_end = _dragged(int(2.0 * t_roll / dt))
    assert t_end > 1.9 * t_roll
    assert v_end == pytest.approx(2.0 / 7.0 * V, rel=0.03)


def _gate(g: DrawDownGeometry, t_open: float) -> WallSpec:
    return next(w for w in g.walls("steel", t_open) if w.name == "gate")


def test_the_gate_vanishes_or_slides_out_under_the_right_floor_in_its_opening_time():
    g = DrawDownGeometry()
    still = _gate(g, 0.8)
    assert still.centre[2] == g.upper_bottom_z and still.active_until == 0.8 and still.velocity == (0.0, 0.0, 0.0)
    T = 0.2
    slid = _gate(dataclasses.replace(g, gate_opening=T), 0.8)
    assert slid.centre[2] == pytest.approx(g.upper_bottom_z - GATE_CLEARANCE)
    assert slid.velocity == (pytest.approx(g.outlet_width / T), 0.0, 0.0)
    assert (slid.move_from, slid.move_until, slid.active_until) == (0.8, pytest.approx(1.0), pytest.approx(1.0))
    # at the end its left edge is the slot's right edge: the slot is open and the plate under the floor
    left_edge_end = slid.centre[0] - slid.half_u + slid.velocity[0] * (slid.move_until - slid.move_from)
    assert left_edge_end == pytest.approx(g.outlet_width / 2)
    with pytest.raises(ConfigError, match="gate_opening.*a time >= 0 s"):
        DrawDownGeometry(gate_opening=-0.1).validate()
    # the draw down system moves it
    mix, mini = _mini(mirror=True)
    system, _, _ = DrawDownTest(mix, dataclasses.replace(mini, gate_opening=T), settings=SETTINGS).build([0], [0])
    assert system.walls_move
    i = system.walls.names.index("gate")
    shift = system.walls.shift(SETTINGS.fill_time + T / 2)[i]
    assert float(shift[0]) == pytest.approx(mini.outlet_width / 2) and float(shift[1:].abs().max()) == 0.0
    assert not DrawDownTest(mix, mini, settings=SETTINGS).build([0], [0])[0].walls_move


def test_the_gate_opening_as_a_task_parameter_and_in_the_config():
    mix, mini = _mini(mirror=True)
    model = DrawDownModel({"50-50": mix}, mini, SETTINGS, fixed=PAPER_REFERENCE)
    assert model.test_for("50-50", [{"geometry_gate_opening": 0.15}]).geometry.gate_opening == 0.15
    assert model.test_for("50-50", [{"geometry_gate_opening": 0.0}]).geometry.gate_opening == 0.0
    with pytest.raises(ConfigError, match="geometry_gate_opening.*a time >= 0 s"):
        model.test_for("50-50", [{"geometry_gate_opening": -0.05}])
    lengths = {"upper_width_m": 0.35, "depth_m": 0.2, "upper_height_m": 0.5, "outlet_width_m": 0.065,
               "upper_bottom_z_m": 0.35, "lower_width_m": 0.8, "lower_height_m": 0.3}
    assert geometry_from({**lengths, "gate_opening_s": None}).gate_opening == 0.0
    assert geometry_from(lengths).gate_opening == 0.0
    assert geometry_from({**lengths, "gate_opening_s": 0.2}).gate_opening == 0.2
    with pytest.raises(ConfigError, match=r"geometry\.gate_opening_s.*a time >= 0 s"):
        geometry_from({**lengths, "gate_opening_s": -1.0})


def test_a_null_gate_opening_hashes_as_a_config_without_it():
    plain = {"geometry": {"outlet_width_m": 0.065}, "sim": {"dtype": "float32"}, "run": {}}
    with_null = {**plain, "geometry": {**plain["geometry"], "gate_opening_s": None}}
    with_time = {**plain, "geometry": {**plain["geometry"], "gate_opening_s": 0.2}}
    assert config_hash(with_null) == config_hash(plain)
    assert config_hash(with_time) != config_hash(plain)
