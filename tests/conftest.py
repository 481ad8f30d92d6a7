"""Shared builders for the engine tests (plain functions, imported by the test modules)."""
from __future__ import annotations

import math
import os

# ``make test`` runs two test workers on the two cores. A worker on torch's default two threads
# made four on two cores, and the GP-heavy calibration tests ran 4.7x slower (test_calibrate.py:
# 1,166 s against 250 s; one known-answer campaign: 37 s on one thread alone, 67 s on two alone,
# 237 s on two beside the other worker).
# Each worker gets one thread; the tests of threading set their own counts and restore them.
if os.environ.get("PYTEST_XDIST_WORKER"):
    for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import torch  # noqa: E402

if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))

from torchdem.materials import Material, interaction_table
from torchdem.simulation import GuardSettings, Simulation
from torchdem.system import build_system

F64 = torch.float64


def glass(G: float = 1e8, density: float = 2500.0) -> Material:
    return Material("glass", G, 0.25, density)


def steel() -> Material:
    return Material("steel", 2e11, 0.3, 7800.0)


def two_material_table(B: int, pp: dict, pw: dict | None = None, dtype=F64):
    mats = [glass(), steel()]
    pairs = {("glass", "glass"): pp, ("glass", "steel"): pw or pp}
    return mats, interaction_table(mats, pairs, batch=B, dtype=dtype)


def simulation(position, radius, mats, table, guards: GuardSettings | None = None, **kw) -> Simulation:
    """Simulation of spheres of material 0 (position [B, N, 3], radius [B, N])."""
    B, N, _ = position.shape
    system, state = build_system(position, torch.zeros(B, N, dtype=torch.long), mats, table,
                                 radius=radius, **kw)
    return Simulation(system, state, guards or GuardSettings(check_every=500))


def elastic_spheres_in_a_box(time_step_fraction: float = 0.15) -> Simulation:
    """64 frictionless, elastic glass spheres (radii 4-5 mm, random velocities of ~0.5 m/s) in a
    closed steel box of 56 mm, no gravity: their kinetic + Hertz elastic energy is conserved."""
    from torchdem.walls import box_walls

    g = torch.Generator().manual_seed(0)
    n_side = 4
    N = n_side ** 3
    k = torch.arange(N)
    pos = (torch.stack([k % n_side, (k // n_side) % n_side, k // n_side ** 2], -1).to(F64) * 0.012 + 0.008)[None]
    pos = pos + 0.001 * (torch.rand(pos.shape, generator=g, dtype=F64) - 0.5)
    radius = (0.004 + 0.001 * torch.rand(1, N, generator=g, dtype=F64))
    vel = 0.5 * torch.randn(1, N, 3, generator=g, dtype=F64)
    mats = [glass(), steel()]
    elastic = dict(mu_s=0.0, mu_r=0.0, restitution=1.0)
    table = interaction_table(mats, {("glass", "glass"): elastic, ("glass", "steel"): elastic})
    return simulation(pos, radius, mats, table, velocity=vel, gravity=(0, 0, 0), time_step_fraction=time_step_fraction,
                      walls=box_walls("box", (0, 0, 0), (0.056, 0.056, 0.056), "steel", open_top=False))


def hertz_contact_duration(m_eff: float, r_eff: float, e_eff: float, v: float) -> float:
    """Elastic Hertz contact time 2.9432 delta_max / v, delta_max = (5 m* v^2 / (4 k))^(2/5)."""
    k = 4.0 / 3.0 * e_eff * math.sqrt(r_eff)
    delta_max = (5.0 * m_eff * v * v / (4.0 * k)) ** 0.4
    return 2.9432 * delta_max / v


#: Modules whose tests take the longest (a fresh-clone CI's ``--durations``: the discovery's
#: known-answer test 4 min, the command x extension matrix 3.4 min for calibrate, the calibration
#: campaigns 0.5-1.7 min each), collected first. The two workers take tests in collection order, so
#: the long ones start early and short ones fill in at the end, instead of one worker running a
#: long test alone while the other idles. Each module's tests stay together and in order (its
#: fixtures are set up once).
LONG_MODULES = ("test_discovery.py", "test_commands.py", "test_calibrate.py")


def pytest_collection_modifyitems(session, config, items):
    rank = {name: k for k, name in enumerate(LONG_MODULES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(LONG_MODULES)))  # stable: the rest keep their order
