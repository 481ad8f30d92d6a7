"""The engine demonstration behind `make run` (until the draw down test lands): spheres
rained into a box settle into a packing; report packing fraction, speed and conservation.

Contract: :func:`pour_and_settle` builds the system from :class:`PourSettings`, runs it
as a batched ensemble (each member with its own random jitter), and returns a plain dict
of figures with units in the key names.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import torch

from torchdem.integrate import sphere_positions
from torchdem.io import VTKWriter
from torchdem.materials import Material, interaction_table
from torchdem.simulation import GuardSettings, Simulation, kinetic_energy
from torchdem.system import build_system
from torchdem.walls import box_walls


@dataclass(frozen=True)
class PourSettings:
    """Settings of the pour (SI units)."""

    n_side: int = 5
    layers: int = 8
    radii: tuple[float, float] = (0.004, 0.005)
    box: tuple[float, float, float] = (0.06, 0.06, 0.15)
    duration: float = 0.3
    ensemble: int = 2
    seed: int = 0
    shear_modulus: float = 1e7
    poisson_ratio: float = 0.25
    density: float = 2500.0
    mu_s: float = 0.5
    mu_r: float = 0.05
    restitution: float = 0.5
    rolling_damping: float = 0.3
    time_step_fraction: float = 0.15
    skin_fraction: float = 0.2
    rolling_stiffness: str = "tangential"
    vtk_interval: int = 0


def packing_fraction(position, radius, lower, upper, n_samples: int = 100_000, seed: int = 0) -> float:
    """Solid fraction inside the box [lower, upper] by Monte Carlo sampling (positions ``[N, 3]``)."""
    g = torch.Generator(device="cpu").manual_seed(seed)
    lo = torch.as_tensor(lower, dtype=torch.float64)
    hi = torch.as_tensor(upper, dtype=torch.float64)
    pts = lo + (hi - lo) * torch.rand(n_samples, 3, generator=g, dtype=torch.float64)
    x, r = position.detach().cpu().double(), radius.detach().cpu().double()
    inside = torch.zeros(n_samples, dtype=torch.bool)
    for chunk in torch.split(torch.arange(n_samples), 20_000):
        inside[chunk] = (torch.cdist(pts[chunk], x) < r).any(-1)
    return float(inside.double().mean())


def pour_and_settle(s: PourSettings, *, device="cpu", dtype=torch.float64, compile: bool = False,
                    guards: GuardSettings = GuardSettings(), output_dir: Path | None = None) -> dict:
    """Run the pour and return a report (see the module docstring)."""
    g = torch.Generator(device="cpu").manual_seed(s.seed)
    B, N = s.ensemble, s.n_side * s.n_side * s.layers
    spacing = min(s.box[0], s.box[1]) / s.n_side
    k = torch.arange(N)
    lattice = torch.stack([k % s.n_side, (k // s.n_side) % s.n_side, k // s.n_side ** 2], -1).double()
    pos = lattice * spacing + spacing / 2
    pos = pos + 0.1 * spacing * (torch.rand(B, N, 3, generator=g, dtype=torch.float64) - 0.5)
    radius = torch.where(torch.rand(B, N, generator=g) < 0.5, s.radii[0], s.radii[1]).double()
    height = max(s.box[2], spacing * s.layers + 2 * max(s.radii))
    mats = [Material("grain", s.shear_modulus, s.poisson_ratio, s.density), Material("steel", 2e11, 0.3, 7800.0)]
    pp = dict(mu_s=s.mu_s, mu_r=s.mu_r, restitution=s.restitution, rolling_damping=s.rolling_damping)
    table = interaction_table(mats, {("grain", "grain"): pp, ("grain", "steel"): pp}, batch=B, dtype=dtype,
                              device=device, source="demo.contact")
    system, state = build_system(
        pos.to(device=device, dtype=dtype), torch.zeros(B, N, dtype=torch.long, device=device), mats, table,
        radius=radius.to(device=device, dtype=dtype),
        walls=box_walls("box", (0, 0, 0), (s.box[0], s.box[1], height), "steel"),
        time_step_fraction=s.time_step_fraction, skin=s.skin_fraction * max(s.radii),
        rolling_stiffness=s.rolling_stiffness, source="demo")
    sim = Simulation(system, state, guards, compile=compile)
    writer = VTKWriter(output_dir / "vtk", s.vtk_interval) if (s.vtk_interval and output_dir) else None
    t0 = time.perf_counter()
    sim.run_until(s.duration, callback=writer, callback_every=s.vtk_interval if writer else 0)
    wall = time.perf_counter() - t0
    xs = sphere_positions(system, sim.state.bodies).reshape(B, system.n_spheres, 3)
    d = 2 * max(s.radii)
    phis = []
    for b in range(B):
        top = float(xs[b, :, 2].max())
        phis.append(packing_fraction(xs[b], system.sphere_radius[b], (d, d, d),
                                     (s.box[0] - d, s.box[1] - d, max(top - d, 2 * d)), seed=b))
    return {
        "spheres_per_member": N,
        "ensemble_members": B,
        "steps": sim.state.step,
        "time_step_s": system.dt,
        "simulated_time_s": sim.time,
        "wall_time_s": wall,
        "particle_steps_per_s": B * N * sim.state.step / wall,
        "neighbour_list_rebuilds": sim.state.rebuilds,
        "contacts_at_end": sim.state.pairs.n + sim.state.walls.n,
        "kinetic_energy_at_end_J": kinetic_energy(system, sim.state).tolist(),
        "packing_fraction_interior": phis,
        "lost_particles": sim.state.lost.tolist(),
        "device": str(device),
        "dtype": str(dtype).replace("torch.", ""),
    }
