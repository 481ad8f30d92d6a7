"""Sliding on an incline: a body slides only when tan(theta) > mu_s.

The incline is a plane tilted by theta = 30 degrees; ensemble members carry friction
coefficients mu_s = tan(theta +/- 1 or 2 degrees), so the threshold is located within 1
degree. Spheres get a large rolling friction (mu_r = 1 > tan(theta)) so they cannot roll and
must either stick or slide; a three-sphere clump lying along the slope cannot roll at all.
A sliding body must accelerate at g (sin(theta) - mu_s cos(theta)) within 2%.
"""
import math

import numpy as np
import torch

from conftest import F64, glass, steel
from torchdem.clumps import ClumpTemplate
from torchdem.materials import interaction_table
from torchdem.simulation import GuardSettings, Simulation
from torchdem.system import build_system
from torchdem.walls import plane

THETA = math.radians(30.0)
OFFSETS_DEG = [-2.0, -1.0, 1.0, 2.0]
G = 9.81


def _incline_run(template=None, steps=4000):
    B = len(OFFSETS_DEG)
    mus = [math.tan(THETA + math.radians(d)) for d in OFFSETS_DEG]
    mats = [glass(G=1e7), steel()]
    table = interaction_table(mats, {("glass", "glass"): dict(mu_s=0.5, mu_r=0.0, restitution=0.5),
                                     ("glass", "steel"): dict(mu_s=mus, mu_r=1.0, restitution=0.3,
                                                              rolling_damping=0.3)}, batch=B)
    normal = (0.0, -math.sin(THETA), math.cos(THETA))  # slope descends towards -y
    down = np.array([0.0, -math.cos(THETA), -math.sin(THETA)])  # gravity along the slope
    r = 0.005
    n = np.array(normal)
    kw = {}
    if template is None:
        kw["radius"] = torch.full((B, 1), r, dtype=F64)
        centre = n * (r - 2e-6)
    else:
        kw.update(templates=[template], template_index=torch.zeros(B, 1, dtype=torch.long),
                  scale=torch.ones(B, 1, dtype=F64))
        # lay the clump axis (template x) along the slope direction
        axis = down / np.linalg.norm(down)
        # quaternion rotating x onto `axis`
        x = np.array([1.0, 0.0, 0.0])
        v = np.cross(x, axis)
        w = 1.0 + float(x @ axis)
        q = np.array([w, *v])
        q /= np.linalg.norm(q)
        kw["orientation"] = torch.tensor(q, dtype=F64).expand(B, 1, 4).clone()
        centre = n * (r - 2e-6)
    pos = torch.tensor(centre, dtype=F64).expand(B, 1, 3).clone()
    system, state = build_system(pos, torch.zeros(B, 1, dtype=torch.long), mats, table,
                                 walls=[plane("incline", (0, 0, 0), normal, "steel")],
                                 gravity=(0.0, 0.0, -G), time_step_fraction=0.2,
                                 domain=((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5)), **kw)
    sim = Simulation(system, state, GuardSettings(check_every=1000))
    sim.advance(500)  # settle the elastic contact
    d = torch.tensor(down, dtype=F64)
    x0 = sim.state.bodies.position.clone()
    v0 = (sim.state.bodies.velocity[:, 0] * d).sum(-1)
    t0 = sim.time
    sim.advance(steps)
    along = ((sim.state.bodies.position - x0)[:, 0] * d).sum(-1)
    accel = ((sim.state.bodies.velocity[:, 0] * d).sum(-1) - v0) / (sim.time - t0)
    return mus, along, accel


def _check(mus, along, accel):
    for d, mu, s, a in zip(OFFSETS_DEG, mus, along.tolist(), accel.tolist()):
        if d < 0:  # tan(theta) > mu_s: slides with the Coulomb acceleration
            expected = G * (math.sin(THETA) - mu * math.cos(THETA))
            assert abs(a - expected) / expected < 0.02, (d, a, expected)
            assert s > 1e-3, (d, s)
        else:      # tan(theta) < mu_s: stays (elastic creep only, far below a millimetre)
            assert abs(s) < 1e-5 and abs(a) < 1e-3, (d, s, a)


def test_sphere_on_incline_slides_only_above_friction_angle():
    _check(*_incline_run())


def test_clump_on_incline_rests_below_and_slides_above_friction_angle():
    template = ClumpTemplate("line3", np.array([[-0.006, 0, 0], [0, 0, 0], [0.006, 0, 0]]), np.full(3, 0.005))
    _check(*_incline_run(template))
