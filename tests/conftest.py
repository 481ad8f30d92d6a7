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


def hertz_contact_duration(m_eff: float, r_eff: float, e_eff: float, v: float) -> float:
    """Elastic Hertz contact time 2.9432 delta_max / v, delta_max = (5 m* v^2 / (4 k))^(2/5)."""
    k = 4.0 / 3.0 * e_eff * math.sqrt(r_eff)
    delta_max = (5.0 * m_eff * v * v / (4.0 * k)) ** 0.4
    return 2.9432 * delta_max / v
