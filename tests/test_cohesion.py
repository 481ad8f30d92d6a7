"""SJKR cohesion (torchdem.contact.sjkr_cohesion) against static equilibria solved analytically.

- A sphere resting on a plane under gravity, with cohesion k_c to the plane, settles where the
  Hertz force balances weight plus cohesion: 4/3 E* sqrt(R) d^1.5 = m g + k_c pi d (2R - d).
  Measured overlap within 0.5 % of the root, for three k_c as three ensemble members (k_c = 0
  gives the plain Hertz overlap).
- Two free spheres (no gravity) placed just touching are pulled together until the Hertz force
  balances k_c times the area of the intersection circle; overlap within 0.5 %, and the net
  force on the pair is zero (the centre of mass does not move, 1e-12 m).
- The contact-area formula equals pi a^2 of the exact intersection circle (1e-12 relative).
Both equilibria are solved with the C++ kernels (cohesion inside their contact law) and with the
torch kernels (cohesion a pass of its own).
"""
import math

import numpy as np
import pytest
import torch
from scipy.optimize import brentq

from conftest import F64, glass, steel
from torchdem.contact import sjkr_contact_area
from torchdem.materials import effective_young_modulus, interaction_table
from torchdem.simulation import GuardSettings, Simulation
from torchdem.system import build_system
from torchdem.walls import plane

R = 0.005
G_MOD = 1e6  # soft spheres: overlaps of ~1e-5 m, resolved to 1e-9 m in float64
DENSITY = 2500.0
# J/m^3. Cohesion grows like d and Hertz like d^1.5, so k_c must be scaled to the stiffness: at
# G = 1e6 Pa, 2e4 J/m^3 about doubles the weight-only overlap (1.4e-5 m); 1e6 J/m^3 would pull a
# sphere in by most of its radius.
KC = [0.0, 2.0e4, 6.0e4]


def test_contact_area_is_the_intersection_circle():
    ri, rj = torch.tensor([0.004, 0.005], dtype=F64), torch.tensor([0.006, 0.005], dtype=F64)
    d = torch.tensor([0.0099, 0.0098], dtype=F64)
    # circle radius a of two intersecting spheres: a^2 = ri^2 - x^2 with x = (d^2 + ri^2 - rj^2) / 2d
    x = (d ** 2 + ri ** 2 - rj ** 2) / (2 * d)
    exact = math.pi * (ri ** 2 - x ** 2)
    area = sjkr_contact_area(ri + rj - d, d, ri, rj)
    torch.testing.assert_close(area, exact, rtol=1e-12, atol=0)
    wall = sjkr_contact_area(torch.tensor([1e-5], dtype=F64), torch.tensor([R - 1e-5], dtype=F64),
                             torch.tensor([R], dtype=F64))
    assert float(wall) == math.pi * (R ** 2 - (R - 1e-5) ** 2)
    assert float(sjkr_contact_area(torch.tensor([-1e-6], dtype=F64), torch.tensor([R + 1e-6], dtype=F64),
                                   torch.tensor([R], dtype=F64))) == 0.0


def _young(a, b):
    return float(effective_young_modulus(torch.tensor(a.young_modulus), torch.tensor(a.poisson_ratio),
                                         torch.tensor(b.young_modulus), torch.tensor(b.poisson_ratio)))


@pytest.mark.parametrize("backend", ["cpp", "torch"])
def test_sphere_on_a_plane_settles_where_hertz_balances_weight_and_cohesion(backend):
    B = len(KC)
    g = 9.81
    mats = [glass(G=G_MOD, density=DENSITY), steel()]
    table = interaction_table(mats, {("glass", "glass"): dict(mu_s=0.5, mu_r=0.0, restitution=0.5),
                                     ("glass", "steel"): dict(mu_s=0.5, mu_r=0.0, restitution=0.2,
                                                              cohesion=KC)}, batch=B)
    pos = torch.tensor([0.0, 0.0, R - 1e-6], dtype=F64).expand(B, 1, 3).clone()
    system, state = build_system(pos, torch.zeros(B, 1, dtype=torch.long), mats, table,
                                 radius=torch.full((B, 1), R, dtype=F64),
                                 walls=[plane("floor", (0, 0, 0), (0, 0, 1), "steel")], gravity=(0, 0, -g),
                                 time_step_fraction=0.1, domain=((-0.1, -0.1, -0.1), (0.1, 0.1, 0.1)))
    assert system.has_cohesion
    sim = Simulation(system, state, GuardSettings(check_every=1000), backend=backend)
    sim.advance(8000)
    overlap = R - sim.state.bodies.position[:, 0, 2].numpy()
    assert float(sim.state.bodies.velocity.norm(dim=-1).max()) < 1e-6  # at rest
    E = _young(mats[0], mats[1])
    m = DENSITY * 4 / 3 * math.pi * R ** 3
    for k, kc in enumerate(KC):
        root = brentq(lambda d: 4 / 3 * E * math.sqrt(R) * d ** 1.5 - m * g - kc * math.pi * d * (2 * R - d),
                      1e-12, 0.1 * R)
        assert abs(overlap[k] - root) < 0.005 * root, (kc, overlap[k], root)
    assert overlap[2] > overlap[1] > overlap[0]


@pytest.mark.parametrize("backend", ["cpp", "torch"])
def test_two_free_spheres_are_pulled_to_the_cohesive_equilibrium(backend):
    kc = 2.0e4  # equilibrium overlap ~1.3e-5 m
    mats = [glass(G=G_MOD, density=DENSITY), steel()]
    table = interaction_table(mats, {("glass", "glass"): dict(mu_s=0.5, mu_r=0.0, restitution=0.2, cohesion=kc),
                                     ("glass", "steel"): dict(mu_s=0.5, mu_r=0.0, restitution=0.5)})
    pos = torch.tensor([[[0.0, 0.0, 0.0], [2 * R - 1e-7, 0.0, 0.0]]], dtype=F64)
    system, state = build_system(pos, torch.zeros(1, 2, dtype=torch.long), mats, table,
                                 radius=torch.full((1, 2), R, dtype=F64), gravity=(0, 0, 0),
                                 time_step_fraction=0.1, domain=((-0.1, -0.1, -0.1), (0.1, 0.1, 0.1)))
    sim = Simulation(system, state, GuardSettings(check_every=1000), backend=backend)
    sim.advance(8000)
    x = sim.state.bodies.position[0].numpy()
    overlap = 2 * R - float(np.linalg.norm(x[1] - x[0]))
    E = _young(mats[0], mats[0])
    r_eff = R / 2

    def balance(d):
        dist = 2 * R - d
        area = float(sjkr_contact_area(torch.tensor([d], dtype=F64), torch.tensor([dist], dtype=F64),
                                       torch.tensor([R], dtype=F64), torch.tensor([R], dtype=F64)))
        return 4 / 3 * E * math.sqrt(r_eff) * d ** 1.5 - kc * area

    root = brentq(balance, 1e-9, 0.1 * R)
    assert abs(overlap - root) < 0.005 * root, (overlap, root)
    assert abs(x.mean(axis=0)[0] - (2 * R - 1e-7) / 2) < 1e-12  # no net force on the pair
