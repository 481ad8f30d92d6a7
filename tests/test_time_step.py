"""The ensemble's time step: the Rayleigh step of its smallest sphere at the lightest member's density.

The Rayleigh time step grows with density (pi r sqrt(rho / G) / (0.1631 nu + 0.8766)), so when
members carry their own densities (calibration, density_per_material) the lightest member sets
the step. It used to be the heaviest: a member 36 % lighter then ran at 0.19 instead of 0.15 of
its own Rayleigh step, and the draw down slice blew up (a body at 824 m/s).
"""
from __future__ import annotations

import pytest
import torch

from conftest import F64, glass
from torchdem.materials import interaction_table, rayleigh_time_step
from torchdem.system import build_system


def test_the_lightest_member_sets_the_time_step():
    mat = glass()
    B, N = 2, 4
    position = torch.tensor([[0.01, 0.01, 0.01], [0.03, 0.01, 0.01], [0.01, 0.03, 0.01], [0.03, 0.03, 0.01]],
                            dtype=F64).expand(B, N, 3).clone()
    radius = torch.tensor([0.004, 0.003, 0.005, 0.004], dtype=F64).expand(B, N).clone()
    densities = [mat.density, 0.6 * mat.density]
    table = interaction_table([mat], {(mat.name, mat.name): dict(mu_s=0.5, mu_r=0.05, restitution=0.5)}, batch=B,
                              density={mat.name: densities})
    system, _ = build_system(position, torch.zeros(B, N, dtype=torch.long), [mat], table, radius=radius,
                             time_step_fraction=0.15, domain=((0.0, 0.0, 0.0), (0.04, 0.04, 0.04)))
    lightest = rayleigh_time_step(0.003, min(densities), mat.shear_modulus, mat.poisson_ratio)
    heaviest = rayleigh_time_step(0.003, max(densities), mat.shear_modulus, mat.poisson_ratio)
    assert heaviest > 1.2 * lightest
    assert system.dt == pytest.approx(0.15 * lightest, rel=1e-12)
