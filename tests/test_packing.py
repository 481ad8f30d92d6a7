"""Spheres poured into a box settle to a random packing.

About 500 frictional bidisperse spheres (radii 4 and 5 mm) rain into a box and settle
under gravity. The solid fraction measured in the interior (two diameters away from the
walls and the free surface, by Monte Carlo sampling) must fall in the random-packing range
0.55-0.64 (random loose packing of frictional spheres ~0.55-0.60, random close packing
~0.64; Onoda & Liniger 1990, Scott & Kilgour 1969). The run must also come to rest:
kinetic energy below 1e-3 of the potential energy released.
"""
import pytest
import torch

from conftest import F64, glass, simulation, steel
from torchdem.integrate import sphere_positions
from torchdem.materials import interaction_table
from torchdem.simulation import kinetic_energy
from torchdem.walls import box_walls


@pytest.mark.slow
def test_poured_spheres_settle_to_random_packing_fraction():
    g = torch.Generator().manual_seed(11)
    L, n_side, layers = 0.066, 6, 14
    N = n_side * n_side * layers
    k = torch.arange(N)
    spacing = L / n_side
    pos = torch.stack([k % n_side, (k // n_side) % n_side, k // n_side ** 2], -1).to(F64) * spacing + spacing / 2
    pos = pos + 0.0008 * (torch.rand(N, 3, generator=g, dtype=F64) - 0.5)
    radius = torch.where(torch.rand(N, generator=g) < 0.5, 0.004, 0.005).to(F64)
    mats = [glass(G=1e7), steel()]
    pp = dict(mu_s=0.5, mu_r=0.05, restitution=0.4, rolling_damping=0.3)
    table = interaction_table(mats, {("glass", "glass"): pp, ("glass", "steel"): pp})
    sim = simulation(pos[None], radius[None], mats, table, time_step_fraction=0.25,
                     walls=box_walls("box", (0, 0, 0), (L, L, spacing * layers + 0.01), "steel"))
    z0 = sim.state.bodies.position[..., 2].mean()
    sim.run_until(0.6)
    x = sphere_positions(sim.system, sim.state.bodies)
    m = sim.system.mass.sum()
    released = (m * 9.81 * (z0 - x[:, 2].mean())).item()
    assert kinetic_energy(sim.system, sim.state).item() < 1e-3 * released  # essentially at rest
    top = x[:, 2].max().item()
    d = 0.01
    lo = torch.tensor([2 * d, 2 * d, 2 * d], dtype=F64)
    hi = torch.tensor([L - 2 * d, L - 2 * d, top - 2 * d], dtype=F64)
    assert bool((hi > lo).all())
    pts = lo + (hi - lo) * torch.rand(200_000, 3, generator=g, dtype=F64)
    inside = torch.zeros(pts.shape[0], dtype=torch.bool)
    r = sim.system.sphere_radius.reshape(-1)
    for chunk in torch.split(torch.arange(pts.shape[0]), 20_000):
        dist = torch.cdist(pts[chunk], x)
        inside[chunk] = (dist < r).any(-1)
    phi = inside.double().mean().item()
    assert 0.55 <= phi <= 0.64, phi
