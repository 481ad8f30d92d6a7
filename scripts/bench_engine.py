"""Engine throughput benchmark: torchdem (B = 1 and B = 16) against LIGGGHTS on one dense packing.

Prints figures; it is not a test and asserts nothing about speed.

Contract:
- The scenario is fixed (:class:`BenchScenario`): ~3,400 spheres, radii 5.5 and 7.0 mm
  (50/50 by number), density 3600 kg/m^3, G = 1e8 Pa, nu = 0.25, e = 0.7, mu_s = 0.49,
  mu_r = 0.06 (EPSD rolling, LIGGGHTS ``epsd2``: k_r = S_t R*^2, no rolling dashpot), poured
  from a jittered lattice into a 0.2 m x 0.1 m open box and settled. The walls are made of the
  same material as the spheres, so particle-wall and particle-particle contacts share one
  pair of coefficients; LIGGGHTS then needs one atom type and ``primitive type 1`` walls.
- Settling (not timed) runs once in float32 at 0.2 x the Rayleigh time step and is cached in
  ``<repo>/.bench_cache/`` under a key derived from every scenario parameter; later runs load
  the packing (positions, radii, velocities, angular velocities) and skip it. Contact history
  is not cached: both engines start the timed run with empty springs.
- Timing: torchdem advances the packing for ``--steps`` steps at dt = 5.9e-6 s after
  ``--warmup`` untimed steps, through the public ``build_system`` / ``Simulation.advance``
  (blow-up guards on, as in a real run). B = 16 runs 16 copies of the packing, each member
  with its own small velocity jitter so the members are independent. B = 1 is member 0.
  particle-steps/s = B * N * steps / wall time.
- When ``liggghts`` is on PATH, the same state (member 0) is written as a LIGGGHTS data file
  and input (Hertz, tangential history, rolling_friction epsd2, five primitive walls,
  nve/sphere, skin equal to torchdem's) and run with ``mpirun -np 2`` and
  ``processors 2 1 1``; its "Loop time of X on R procs for S steps" line gives its
  particle-steps/s. ``ratio_b1`` / ``ratio_b16`` are torchdem / LIGGGHTS (> 1: torchdem faster).
  Without LIGGGHTS those keys are null.
- ``--json`` prints one JSON object on stdout (progress goes to stderr) with the keys
  ``particle_steps_per_s_b1``, ``particle_steps_per_s_b16``, ``liggghts_particle_steps_per_s``,
  ``ratio_b1``, ``ratio_b16`` (headline precision, float64 by default because LIGGGHTS runs in
  double) plus per-precision figures and run details. ``--quick`` is a smoke run: 600
  spheres settled only to 0.1 m/s, 200 steps; its figures are not the benchmark.

Issue target on the 2-core reference machine: B = 16 at least LIGGGHTS's throughput, B = 1 at
least a quarter of it.

Reading the figures:
- Every timing reports ``other cores``, the CPU that other processes used meanwhile
  (:class:`CpuMonitor`). On 2 cores, torch's 2 intra-op threads and LIGGGHTS's 2 MPI ranks
  both slow down several-fold when anything else runs; figures with other cores > 0.1 are low.
- The Debian LIGGGHTS 3.8 build has no compiled (whitelisted) kernel for
  ``hertz + tangential history + rolling_friction epsd2`` and warns that it runs the generic
  template path ("up to 20% slower"); ``hertz + tangential history`` alone is whitelisted.
- The packing is at rest: neither engine rebuilds its neighbour lists during the timed
  steps, so this measures contact-force and integration throughput, not the neighbour search.
- Physics check: member 0 starts from the same state in both engines (same kinetic energy to
  all printed digits) and should end with kinetic energies and centre-of-mass height close to
  LIGGGHTS's. Remaining model differences: torchdem walls are finite rectangles (LIGGGHTS
  primitive planes are infinite; no sphere reaches an edge here) and torchdem turns the
  rolling spring into the current tangent plane each step (LIGGGHTS epsd2 does not).

- ``--backend cpp`` (default) times the C++ contact kernels of ``torchdem/_ext``; ``--backend torch``
  the torch ones (with ``--compile``: torch.compile'd). With cpp, the drift, and the pair and wall
  contacts with the kick (one fused call per step), are C++ too.

Optional extras (off by default; the default run's cost is unchanged):

- ``--scaling``: particle-steps/s of the settled box against its size N (B = 1) and against the
  ensemble size B (B = 1, 4, 16, 64 of the packing), for every ``--dtypes`` precision,
  ``--scaling-steps`` (300; 60 with --quick) timed steps after ``--scaling-warmup`` (30; 10 with
  --quick) each, best of one. No new packing is settled: the N cases are cut from or tiled out of
  the cached one. ~1k: the spheres with x < 0.3 box_x, the x wall moved to just beyond them
  (max x + r). ~3.4k, ~14k, ~54k: 1x1, 2x2 and 4x4 copies of the packing side by side in x and y
  inside one box around them. Neighbouring tiles are placed one box length plus a gap apart, the
  gap being the deepest wall penetration of the settled spheres at the two facing walls (~10 um),
  so two spheres that leant on the two facing walls are at least r1 + r2 apart: tiling adds no
  overlap. Each N case prints the largest overlap over the whole packing (the settled contacts'
  own, the same as the source packing's) and over pairs of spheres from different tiles (seam;
  negative = the closest approach is a gap). The seam spheres lose their wall and settle a little
  during the run; that changes few contacts. JSON key ``scaling``.
  How to read it: if the cost of a step is linear in N and in B, particle-steps/s is constant, and
  the table's ratio to the smallest case is 1. A rise with N or B means fixed per-step costs
  (Python, kernel calls, the neighbour check) that larger cases amortise; a fall means the cost per
  particle grows. The pair kernel reads both partners' rows (position, velocity, angular
  velocity, force; ~200 bytes per sphere in float64, ~120 in float32, with mass, radius, indices)
  for every contact. A member of ~1k spheres (~0.2 MB) keeps them in L2, ~3.4k (~0.7 MB) in L2
  or L3, ~14k (~3 MB) in L3, ~54k (~11 MB) at or past the L3 of a small CPU: a fall at the large
  N is partner rows missing the cache. The ensemble gives each thread whole members, so its
  working set stays one member's at any B: B should stay flat until the streamed neighbour lists
  and histories (pairs/N x ~100 bytes per sphere, never reused) meet the memory bandwidth, which
  ``--stream`` measures. The ``pairs/N`` column (listed pairs per sphere) shows when a cut or
  tiled packing is not the same work per sphere.
- ``--stream``: a STREAM triad (``a = b + s c``, float64, ``--stream-mib`` 64 MiB per array, far
  past the last-level cache, best of ``--stream-repeat`` 10, on torch's intra-op threads, as the
  timings) gives the machine's memory bandwidth, counted as STREAM does (3 arrays x 8 bytes per
  element: 2 reads, 1 write) and with the write-allocate read of ``a`` (4 arrays: the true
  traffic of ordinary stores). :func:`pair_bytes_per_step` itemises the bytes the C++ pair kernel
  moves per step (``contact_cpu.cpp``: pair_block inside forces_kick's per-member path, which the
  B = 16 ensemble takes) as a lower bound (each byte once: the per-pair streams, plus every
  per-sphere and per-body row once per step) and an upper bound (every gathered partner row a
  full 64-byte cache line from memory, every time). With the contact counts of the B = 16 timing
  (listed pairs, pairs whose spheres overlap, spheres) it prints bytes per listed pair, the
  achieved bytes/s (pair bytes x steps / wall time of the whole step: walls, drift, kick and the
  Python around them included, so this is a floor of the kernel's own rate) and its fraction of
  the triad bandwidth (writes counted once on both sides). A lower-bound fraction near 1 would
  mean the step is bandwidth-bound; an upper-bound fraction above 1 means the cache serves most
  partner rows. JSON key ``stream``. The wall contacts (JSON ``wall_contacts``) are not counted.

Usage: ``python scripts/bench_engine.py [--steps 2000] [--json] [--quick] [--backend cpp|torch]
[--scaling] [--stream]``. Plain argparse, not Hydra: a benchmark with a handful of flags and no
config groups.
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import inspect
import json
import math
import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchdem.cpu_monitor import CpuMonitor
from torchdem.errors import ConfigError
from torchdem.materials import Material, interaction_table, rayleigh_time_step
from torchdem.neighbors import cell_grid, find_pairs
from torchdem.simulation import GuardSettings, Simulation
from torchdem.system import build_system
from torchdem.walls import box_walls

REPO = Path(__file__).resolve().parents[1]
CACHE_FORMAT = 1                      # bump when the cached packing's content changes meaning
MATERIAL = "bench_sphere"             # one material for spheres and walls
STANDARD_GRAVITY = 9.81
B_ENSEMBLE = 16
SCALING_TRIM = 0.3                    # --scaling: the ~1k case keeps the spheres with x < this x box_x
SCALING_TILES = (1, 2, 4)             # --scaling: n x n copies of the packing side by side
SCALING_BATCHES = (1, 4, 16, 64)      # --scaling: ensemble sizes on the packing
CACHE_LINE = 64                       # bytes; --stream's upper bound moves one line per gathered row


@dataclass(frozen=True)
class BenchScenario:
    """The benchmarked packing and how it is made (SI units).

    Attributes:
        n_particles: number of spheres.
        radius_small, radius_large: m; ``small_fraction`` of the spheres (by number) are small.
        density: kg/m^3. shear_modulus: G, Pa. poisson_ratio: nu.
        restitution, mu_s, mu_r: coefficients of restitution, sliding and rolling friction,
            the same for sphere-sphere and sphere-wall contacts.
        box_x, box_y: inner size of the open box, m (walls at 0 and box_x, 0 and box_y, floor z = 0).
        lattice_gap: gap between the largest spheres on the pouring lattice, m.
        lattice_jitter: uniform jitter of lattice positions, m (breaks the lattice symmetry).
        seed: seed of the lattice jitter and of the size assignment.
        settle_time_step_fraction: settling dt as a fraction of the Rayleigh time step.
        settle_speed: the packing is settled when no sphere moves faster than this, m/s.
        settle_max_extra_time: s of settling allowed after the free-fall time of the top layer.
    """

    n_particles: int = 3400
    radius_small: float = 0.0055
    radius_large: float = 0.0070
    small_fraction: float = 0.5
    density: float = 3600.0
    shear_modulus: float = 1.0e8
    poisson_ratio: float = 0.25
    restitution: float = 0.7
    mu_s: float = 0.49
    mu_r: float = 0.06
    box_x: float = 0.2
    box_y: float = 0.1
    lattice_gap: float = 0.0015
    lattice_jitter: float = 0.0004
    seed: int = 20240607
    settle_time_step_fraction: float = 0.2
    settle_speed: float = 0.02
    settle_max_extra_time: float = 2.0

    def validate(self, source: str = "BenchScenario") -> "BenchScenario":
        if self.n_particles < 2:
            raise ConfigError(f"{source}: n_particles = {self.n_particles}; expected an integer >= 2")
        if not 0 < self.radius_small <= self.radius_large:
            raise ConfigError(f"{source}: radii ({self.radius_small}, {self.radius_large}) m; expected "
                              "0 < radius_small <= radius_large")
        if 2 * self.lattice_jitter >= self.lattice_gap:
            raise ConfigError(f"{source}: lattice_jitter = {self.lattice_jitter} m must be below half the "
                              f"lattice_gap = {self.lattice_gap} m, or lattice spheres may overlap")
        nx, ny = self.lattice_shape
        if nx < 1 or ny < 1:
            raise ConfigError(f"{source}: the box ({self.box_x} x {self.box_y} m) holds no lattice column of "
                              f"spacing {self.lattice_spacing} m")
        return self

    @property
    def lattice_spacing(self) -> float:
        return 2.0 * self.radius_large + self.lattice_gap

    @property
    def lattice_shape(self) -> tuple[int, int]:
        s = self.lattice_spacing
        return int(self.box_x // s), int(self.box_y // s)

    @property
    def lattice_top(self) -> float:
        """z of the highest lattice layer, m."""
        nx, ny = self.lattice_shape
        layers = math.ceil(self.n_particles / (nx * ny))
        return self.radius_large + self.lattice_gap + (layers - 1) * self.lattice_spacing

    @property
    def wall_height(self) -> float:
        """Height of the box walls (and top of the LIGGGHTS domain), m."""
        return self.lattice_top + 3.0 * self.radius_large

    def cache_key(self) -> str:
        text = json.dumps({"format": CACHE_FORMAT, **dataclasses.asdict(self)}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


@dataclass(frozen=True)
class Packing:
    """A settled packing, one member, numpy float64 (m, m/s, rad/s).

    Attributes:
        position: ``[N, 3]``. radius: ``[N]``. velocity, angular_velocity: ``[N, 3]``.
        settle_time: simulated settling time, s. settle_max_speed: fastest sphere at the end, m/s.
    """

    position: np.ndarray
    radius: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray
    settle_time: float
    settle_max_speed: float


@dataclass(frozen=True)
class FinalState:
    """Summary of member 0 after the timed steps, for comparing the engines' physics.

    Attributes: translational and rotational kinetic energy (J), fastest sphere (m/s),
    centre-of-mass height (m), spheres still in the domain.
    """

    kinetic_translational: float
    kinetic_rotational: float
    max_speed: float
    com_z: float
    n_particles: int


@dataclass(frozen=True)
class ContactCounts:
    """Neighbour lists after a timed run, all members together.

    Attributes: listed sphere-sphere pairs (``state.pairs.n``), the listed pairs whose spheres
    overlap (the pair kernel runs its contact law on those; None where spheres are not bodies),
    listed sphere-wall contacts (``state.walls.n``), spheres, bodies, and whether every sphere
    is its own body (:attr:`System.spheres_are_bodies`).
    """

    listed_pairs: int
    touching_pairs: int | None
    wall_contacts: int
    spheres: int
    bodies: int
    spheres_are_bodies: bool


@dataclass(frozen=True)
class EngineTiming:
    """One timed run. particle_steps_per_s = batch * n_particles * steps / wall_time.
    ``contacts``: torchdem's neighbour lists at the end (None for LIGGGHTS)."""

    engine: str
    dtype: str
    batch: int
    n_particles: int
    steps: int
    wall_time: float
    neighbour_builds: int
    initial: FinalState
    final: FinalState
    other_cpu_cores: float | None = None
    contacts: ContactCounts | None = None

    @property
    def particle_steps_per_s(self) -> float:
        return self.batch * self.n_particles * self.steps / self.wall_time


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- torchdem side


def bench_material(scenario: BenchScenario) -> Material:
    return Material(MATERIAL, scenario.shear_modulus, scenario.poisson_ratio, scenario.density)


def bench_system(scenario: BenchScenario, position: np.ndarray, radius: np.ndarray, velocity: np.ndarray,
                 angular_velocity: np.ndarray, dtype: torch.dtype, *, dt: float | None = None,
                 time_step_fraction: float | None = None):
    """``(System, State)`` of the scenario; position/velocity/angular_velocity are ``[B, N, 3]``."""
    B, N, _ = position.shape
    material = bench_material(scenario)
    coefficients = {"mu_s": scenario.mu_s, "mu_r": scenario.mu_r, "restitution": scenario.restitution,
                    "rolling_damping": 0.0}   # epsd2 has no rolling dashpot
    table = interaction_table([material], {(MATERIAL, MATERIAL): coefficients}, batch=B, dtype=dtype,
                              source="bench_engine")
    walls = box_walls("box", (0.0, 0.0, 0.0), (scenario.box_x, scenario.box_y, scenario.wall_height), MATERIAL)
    as_t = lambda a: torch.as_tensor(a, dtype=dtype)  # noqa: E731
    return build_system(
        as_t(position), torch.zeros((B, N), dtype=torch.long), [material], table,
        radius=as_t(np.broadcast_to(radius, (B, N)).copy()), velocity=as_t(velocity),
        angular_velocity=as_t(angular_velocity), walls=walls, dt=dt, time_step_fraction=time_step_fraction,
        rolling_stiffness="tangential", source="bench_engine")


def pour_lattice(scenario: BenchScenario) -> tuple[np.ndarray, np.ndarray]:
    """Jittered lattice above the box floor and the 50/50 radii: ``([N, 3], [N])``, m."""
    rng = np.random.default_rng(scenario.seed)
    nx, ny = scenario.lattice_shape
    s = scenario.lattice_spacing
    k = np.arange(scenario.n_particles)
    ix, iy, iz = k % nx, (k // nx) % ny, k // (nx * ny)
    x0 = (scenario.box_x - nx * s) / 2 + s / 2
    y0 = (scenario.box_y - ny * s) / 2 + s / 2
    z0 = scenario.radius_large + scenario.lattice_gap
    position = np.stack([x0 + ix * s, y0 + iy * s, z0 + iz * s], axis=1)
    position += rng.uniform(-scenario.lattice_jitter, scenario.lattice_jitter, position.shape)
    n_small = int(round(scenario.small_fraction * scenario.n_particles))
    small = rng.permutation(scenario.n_particles) < n_small
    radius = np.where(small, scenario.radius_small, scenario.radius_large)
    return position, radius


def settle(scenario: BenchScenario) -> Packing:
    """Pour the lattice into the box and run until every sphere is slower than settle_speed."""
    position, radius = pour_lattice(scenario)
    zero = np.zeros_like(position)
    system, state = bench_system(scenario, position[None], radius, zero[None], zero[None], torch.float32,
                                 time_step_fraction=scenario.settle_time_step_fraction)
    sim = Simulation(system, state, GuardSettings(check_every=500))
    free_fall = math.sqrt(2.0 * scenario.lattice_top / STANDARD_GRAVITY)
    chunk = max(1, round(0.02 / system.dt))
    log(f"settling {scenario.n_particles} spheres (float32, dt = {system.dt:.3g} s, free fall "
        f"{free_fall:.2f} s, until every sphere < {scenario.settle_speed} m/s) ...")
    t0 = time.perf_counter()
    speed = math.inf
    while True:
        sim.advance(chunk)
        b = sim.state.bodies
        speed = float((b.velocity.norm(dim=-1) * b.active).max())
        if sim.state.step % (10 * chunk) == 0:
            log(f"  t = {sim.time:.2f} s, fastest sphere {speed:.3g} m/s, {time.perf_counter() - t0:.0f} s wall")
        if sim.time >= free_fall and speed < scenario.settle_speed:
            break
        if sim.time >= free_fall + scenario.settle_max_extra_time:
            log(f"  warning: not settled after {sim.time:.2f} s (fastest sphere {speed:.3g} m/s); using it anyway")
            break
    lost = int(sim.state.lost.sum())
    if lost:
        raise RuntimeError(f"settling lost {lost} spheres out of the domain; the packing is unusable "
                           f"(scenario {dataclasses.asdict(scenario)})")
    b = sim.state.bodies
    omega = b.angular_momentum / system.inertia            # spheres: world L / principal moments
    log(f"  settled at t = {sim.time:.3f} s ({sim.state.step} steps, {time.perf_counter() - t0:.0f} s wall), "
        f"fastest sphere {speed:.3g} m/s, top z = {float(b.position[..., 2].max()):.3f} m")
    as_np = lambda t: t[0].detach().to(torch.float64).numpy().copy()  # noqa: E731
    return Packing(as_np(b.position), radius, as_np(b.velocity), as_np(omega), sim.time, speed)


def load_or_settle(scenario: BenchScenario, cache_dir: Path, resettle: bool) -> Packing:
    path = cache_dir / f"packing_{scenario.cache_key()}.npz"
    if path.exists() and not resettle:
        data = np.load(path)
        meta = json.loads(str(data["meta"]))
        if meta.get("scenario") == dataclasses.asdict(scenario):
            log(f"settled packing loaded from {path}")
            return Packing(data["position"], data["radius"], data["velocity"], data["angular_velocity"],
                           float(meta["settle_time"]), float(meta["settle_max_speed"]))
        log(f"{path}: cached scenario differs from the requested one; settling again")
    packing = settle(scenario)
    cache_dir.mkdir(parents=True, exist_ok=True)
    meta = {"format": CACHE_FORMAT, "scenario": dataclasses.asdict(scenario), "settle_time": packing.settle_time,
            "settle_max_speed": packing.settle_max_speed}
    with tempfile.NamedTemporaryFile(dir=cache_dir, suffix=".npz", delete=False) as f:
        np.savez(f, position=packing.position, radius=packing.radius, velocity=packing.velocity,
                 angular_velocity=packing.angular_velocity, meta=json.dumps(meta))
    os.replace(f.name, path)
    log(f"settled packing cached in {path}")
    return packing


def ensemble_velocities(packing: Packing, batch: int, jitter: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``[B, N, 3]`` velocities (settled + Gaussian jitter of std ``jitter`` m/s per member) and
    angular velocities (settled). Member 0 is the same for every B."""
    rng = np.random.default_rng(seed)
    noise = rng.normal(0.0, jitter, (max(batch, B_ENSEMBLE),) + packing.velocity.shape)[:batch]
    velocity = packing.velocity[None] + noise
    omega = np.broadcast_to(packing.angular_velocity, velocity.shape).copy()
    return velocity, omega


def member0_state(system, state) -> FinalState:
    b = state.bodies
    act = b.active[0]
    v = b.velocity[0][act].to(torch.float64)
    m = system.mass[0][act].to(torch.float64)
    inertia = system.inertia[0][act].to(torch.float64)        # [N, 3] principal moments (equal for spheres)
    omega = b.angular_momentum[0][act].to(torch.float64) / inertia
    z = b.position[0][act][:, 2].to(torch.float64)
    return FinalState(
        kinetic_translational=float(0.5 * (m * v.square().sum(-1)).sum()),
        kinetic_rotational=float(0.5 * (inertia * omega.square()).sum()),
        max_speed=float(v.norm(dim=-1).max()),
        com_z=float((m * z).sum() / m.sum()),
        n_particles=int(act.sum()),
    )


def time_torchdem(scenario: BenchScenario, packing: Packing, batch: int, dtype: torch.dtype, dt: float,
                  steps: int, warmup: int, jitter: float, repeat: int = 1, compile: bool = False,
                  backend: str = "cpp") -> EngineTiming:
    """Best of ``repeat`` timings, each from the same initial state with a fresh Simulation.

    ``backend``: contact kernels, ``"cpp"`` (C++ extension) or ``"torch"`` (see ``Kernels``)."""
    velocity, omega = ensemble_velocities(packing, batch, jitter, scenario.seed + 1)
    position = np.broadcast_to(packing.position, velocity.shape).copy()
    system, state = bench_system(scenario, position, packing.radius, velocity, omega, dtype, dt=dt)
    name = str(dtype).replace("torch.", "")
    best = None
    for k in range(repeat):
        sim = Simulation(system, state, compile=compile, backend=backend)
        initial = member0_state(system, sim.state)
        log(f"torchdem {name} B = {batch}: {warmup} warm-up + {steps} timed steps"
            f"{f' (repeat {k + 1}/{repeat})' if repeat > 1 else ''} ...")
        sim.advance(warmup)
        builds0 = sim.state.rebuilds
        with CpuMonitor() as cpu:
            t0 = time.perf_counter()
            sim.advance(steps)
            wall = time.perf_counter() - t0
        if sim.failed:
            raise RuntimeError(f"torchdem {name} B = {batch}: members failed during timing: {sim.failed}")
        timing = EngineTiming("torchdem", name, batch, packing.position.shape[0], steps, wall,
                              sim.state.rebuilds - builds0, initial, member0_state(system, sim.state),
                              cpu.other_cores)
        log(f"  {wall:.2f} s, {timing.particle_steps_per_s:.4g} particle-steps/s{_busy_note(timing)}")
        if best is None or timing.wall_time < best.wall_time:
            best = timing
    return best


def _busy_note(t: EngineTiming) -> str:
    if t.other_cpu_cores is not None and t.other_cpu_cores > 0.1:
        return f" (other processes used {t.other_cpu_cores:.2f} cores meanwhile: figure is low)"
    return ""


# --------------------------------------------------------------------------- LIGGGHTS side

LIGGGHTS_INPUT = """\
# {n} spheres of scripts/bench_engine.py (scenario {key}); Hertz + tangential history +
# EPSD2 rolling friction; walls of the same material (type 1).
atom_style      granular
atom_modify     map array
boundary        f f f
newton          off
communicate     single vel yes
units           si
processors      {ranks} 1 1

read_data       data.bench

neighbor        {skin:.10g} bin
neigh_modify    delay 0

fix m1 all property/global youngsModulus peratomtype {young:.10g}
fix m2 all property/global poissonsRatio peratomtype {poisson:.10g}
fix m3 all property/global coefficientRestitution peratomtypepair 1 {restitution:.10g}
fix m4 all property/global coefficientFriction peratomtypepair 1 {mu_s:.10g}
fix m5 all property/global coefficientRollingFriction peratomtypepair 1 {mu_r:.10g}

pair_style gran model hertz tangential history rolling_friction epsd2
pair_coeff * *

timestep        {dt:.10g}
fix gravi all gravity {g:.10g} vector 0.0 0.0 -1.0

fix w_bottom all wall/gran model hertz tangential history rolling_friction epsd2 primitive type 1 zplane 0.0
fix w_left   all wall/gran model hertz tangential history rolling_friction epsd2 primitive type 1 xplane 0.0
fix w_right  all wall/gran model hertz tangential history rolling_friction epsd2 primitive type 1 xplane {box_x:.10g}
fix w_front  all wall/gran model hertz tangential history rolling_friction epsd2 primitive type 1 yplane 0.0
fix w_back   all wall/gran model hertz tangential history rolling_friction epsd2 primitive type 1 yplane {box_y:.10g}

fix integr all nve/sphere

compute ke_t all ke
compute ke_r all erotate/sphere
variable speed atom sqrt(vx*vx+vy*vy+vz*vz)
compute vmax all reduce max v_speed
compute com all com
thermo_style    custom step atoms c_ke_t c_ke_r c_vmax c_com[3]
thermo_modify   lost ignore norm no format float %.10g
thermo          {thermo}

run             {warmup}
run             {steps}
"""

LOOP_TIME = re.compile(r"Loop time of ([0-9.eE+-]+) on (\d+) procs for (\d+) steps with (\d+) atoms")


def liggghts_command(ranks: int) -> tuple[list[str], int] | None:
    """The command that runs ``in.bench`` in its directory and its number of ranks (1 when
    mpirun is missing), or None without LIGGGHTS."""
    if shutil.which("liggghts") is None:
        return None
    if shutil.which("mpirun") is None or ranks == 1:
        if ranks != 1:
            log(f"LIGGGHTS: no mpirun on PATH; running 1 rank instead of {ranks}")
        return ["liggghts", "-in", "in.bench"], 1
    root = ["--allow-run-as-root"] if hasattr(os, "geteuid") and os.geteuid() == 0 else []
    return ["mpirun", *root, "-np", str(ranks), "liggghts", "-in", "in.bench"], ranks


def write_liggghts_case(directory: Path, scenario: BenchScenario, packing: Packing, velocity: np.ndarray,
                        omega: np.ndarray, dt: float, skin: float, steps: int, warmup: int, ranks: int) -> None:
    """Write ``data.bench`` and ``in.bench`` for member 0 into ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    margin = 2.0 * scenario.radius_large
    lines = [f"LIGGGHTS data file written by scripts/bench_engine.py (scenario {scenario.cache_key()})", "",
             f"{len(packing.radius)} atoms", "1 atom types", "",
             f"{-margin:.10g} {scenario.box_x + margin:.10g} xlo xhi",
             f"{-margin:.10g} {scenario.box_y + margin:.10g} ylo yhi",
             f"{-margin:.10g} {scenario.wall_height:.10g} zlo zhi", "", "Atoms", ""]
    for k, (x, r) in enumerate(zip(packing.position, packing.radius), start=1):
        lines.append(f"{k} 1 {2 * r:.17g} {scenario.density:.17g} {x[0]:.17g} {x[1]:.17g} {x[2]:.17g}")
    lines += ["", "Velocities", ""]
    for k, (v, w) in enumerate(zip(velocity, omega), start=1):
        lines.append(f"{k} {v[0]:.17g} {v[1]:.17g} {v[2]:.17g} {w[0]:.17g} {w[1]:.17g} {w[2]:.17g}")
    (directory / "data.bench").write_text("\n".join(lines) + "\n")
    young = 2.0 * scenario.shear_modulus * (1.0 + scenario.poisson_ratio)
    (directory / "in.bench").write_text(LIGGGHTS_INPUT.format(
        n=len(packing.radius), key=scenario.cache_key(), ranks=ranks, skin=skin, young=young,
        poisson=scenario.poisson_ratio, restitution=scenario.restitution, mu_s=scenario.mu_s, mu_r=scenario.mu_r,
        dt=dt, g=STANDARD_GRAVITY, box_x=scenario.box_x, box_y=scenario.box_y, thermo=max(steps, warmup, 1),
        warmup=warmup, steps=steps))


def _thermo_rows(output: str) -> list[list[list[float]]]:
    """Numeric thermo rows of every run in LIGGGHTS screen output, one list per run."""
    runs, current = [], None
    for line in output.splitlines():
        if line.strip().startswith("Step") and "Atoms" in line:
            current = []
            runs.append(current)
        elif LOOP_TIME.search(line):
            current = None
        elif current is not None:
            parts = line.split()
            try:
                current.append([float(p) for p in parts])
            except ValueError:
                continue
    return [r for r in runs if r]


def _liggghts_state(row: list[float]) -> FinalState:
    _step, atoms, ke_t, ke_r, vmax, com_z = row[:6]
    return FinalState(ke_t, ke_r, vmax, com_z, int(atoms))


def run_liggghts(directory: Path, command: list[str], steps: int, timeout: float) -> tuple[EngineTiming, str]:
    """Run the case in ``directory``; return the timing of the last run and the screen output."""
    env = dict(os.environ, OMP_NUM_THREADS="1")
    with CpuMonitor() as cpu:
        proc = subprocess.run(command, cwd=directory, capture_output=True, text=True, timeout=timeout, env=env)
    output = proc.stdout + proc.stderr
    (directory / "screen.txt").write_text(output)
    loops = LOOP_TIME.findall(output)
    if proc.returncode != 0 or not loops:
        tail = "\n".join(output.splitlines()[-15:])
        raise RuntimeError(f"LIGGGHTS failed (exit code {proc.returncode}) in {directory}; last lines:\n{tail}")
    loop_time, procs, n_steps, atoms = loops[-1]
    if int(n_steps) != steps:
        raise RuntimeError(f"{directory}/screen.txt: last LIGGGHTS run took {n_steps} steps; expected {steps}")
    runs = _thermo_rows(output)
    timing = EngineTiming(f"LIGGGHTS ({procs} MPI ranks)", "float64", 1, int(atoms), steps, float(loop_time), -1,
                          _liggghts_state(runs[0][0]), _liggghts_state(runs[-1][-1]), cpu.other_cores)
    builds = re.findall(r"Neighbor list builds = (\d+)", output)
    if builds:
        timing = dataclasses.replace(timing, neighbour_builds=int(builds[-1]))
    return timing, output


# --------------------------------------------------------------------------- report


def _fmt_state(s: FinalState) -> str:
    return (f"KE_t {s.kinetic_translational:.4g} J, KE_r {s.kinetic_rotational:.4g} J, "
            f"v_max {s.max_speed:.4g} m/s, z_com {s.com_z:.5f} m, N {s.n_particles}")


def print_report(scenario: BenchScenario, dt: float, steps: int, warmup: int, timings: list[EngineTiming],
                 liggghts: EngineTiming | None, liggghts_note: str, headline: str) -> None:
    ref = liggghts.particle_steps_per_s if liggghts else None
    print(f"scenario: {scenario.n_particles} spheres (r = {scenario.radius_small * 1e3:g}/"
          f"{scenario.radius_large * 1e3:g} mm, 50/50), box {scenario.box_x} x {scenario.box_y} m, "
          f"dt = {dt:.3g} s, {steps} timed steps after {warmup} warm-up, torch threads = {torch.get_num_threads()}")
    print(f"{'engine':<26}{'dtype':<9}{'B':>3}{'wall s':>10}{'particle-steps/s':>19}{'vs LIGGGHTS':>13}"
          f"{'nbr builds':>12}{'other cores':>13}")
    for t in timings + ([liggghts] if liggghts else []):
        ratio = f"{t.particle_steps_per_s / ref:.3f}" if ref and t is not liggghts else "-"
        mark = " *" if t.engine == "torchdem" and t.dtype == headline else ""
        other = f"{t.other_cpu_cores:.2f}" if t.other_cpu_cores is not None else "?"
        print(f"{t.engine + mark:<26}{t.dtype:<9}{t.batch:>3}{t.wall_time:>10.2f}"
              f"{t.particle_steps_per_s:>19.4g}{ratio:>13}{t.neighbour_builds:>12}{other:>13}")
    print(f"(* headline precision {headline}; ratio = torchdem / LIGGGHTS; target: B = 16 >= 1, B = 1 >= 0.25;")
    print(" other cores = CPU used by other processes during the timing; > 0.1 means a busy machine and low figures)")
    if not liggghts:
        print(f"LIGGGHTS: {liggghts_note}")
    print("member 0 before -> after the timed steps:")
    for t in timings + ([liggghts] if liggghts else []):
        if t.batch == 1:
            print(f"  {t.engine} {t.dtype}:")
            print(f"    start {_fmt_state(t.initial)}")
            print(f"    end   {_fmt_state(t.final)}")
    if liggghts:
        print(f"LIGGGHTS: {liggghts_note}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=None, help="timed steps (default 2000; 200 with --quick)")
    parser.add_argument("--warmup", type=int, default=None, help="untimed steps first (default 100; 20 with --quick)")
    parser.add_argument("--dt", type=float, default=5.9e-6, help="time step of the timed runs, s")
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: 600 spheres settled to 0.1 m/s, 200 steps, 1 LIGGGHTS run")
    parser.add_argument("--n-particles", type=int, default=None, help="override the number of spheres")
    parser.add_argument("--dtypes", default="float64,float32", help="precisions to time (comma separated)")
    parser.add_argument("--headline-dtype", default="float64", choices=("float64", "float32"),
                        help="precision reported under the issue's JSON keys (LIGGGHTS is float64)")
    parser.add_argument("--batches", default=f"1,{B_ENSEMBLE}", help="ensemble sizes to time (comma separated)")
    parser.add_argument("--velocity-jitter", type=float, default=1e-3,
                        help="std of the per-member velocity jitter, m/s")
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    parser.add_argument("--repeat", type=int, default=1, help="time each torchdem case this often, keep the best")
    parser.add_argument("--compile", action="store_true",
                        help="Simulation(compile=True) (torch.compile'd torch kernels; compiles in the warm-up)")
    parser.add_argument("--backend", default="cpp", choices=("cpp", "torch"),
                        help="contact kernels: cpp (C++ extension, built on first use; default) or torch")
    parser.add_argument("--ranks", type=int, default=2, help="LIGGGHTS MPI ranks (processors R 1 1)")
    parser.add_argument("--no-liggghts", action="store_true", help="skip the LIGGGHTS run")
    parser.add_argument("--liggghts-repeat", type=int, default=None,
                        help="LIGGGHTS runs, keep the best (default 3; 1 with --quick)")
    parser.add_argument("--liggghts-timeout", type=float, default=3600.0, help="s")
    parser.add_argument("--cache-dir", type=Path, default=REPO / ".bench_cache")
    parser.add_argument("--resettle", action="store_true", help="ignore the cached packing and settle again")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    args = parser.parse_args(argv)

    steps = args.steps if args.steps is not None else (200 if args.quick else 2000)
    warmup = args.warmup if args.warmup is not None else (20 if args.quick else 100)
    n = args.n_particles if args.n_particles is not None else (600 if args.quick else BenchScenario.n_particles)
    dtypes = [d.strip() for d in args.dtypes.split(",") if d.strip()]
    batches = [int(b) for b in args.batches.split(",") if b.strip()]
    for d in dtypes:
        if d not in ("float32", "float64"):
            raise ConfigError(f"--dtypes: {d!r} is not allowed; expected float32 and/or float64")
    if args.headline_dtype not in dtypes:
        raise ConfigError(f"--headline-dtype {args.headline_dtype} is not among --dtypes {dtypes}")
    if steps < 1 or warmup < 0:
        raise ConfigError(f"--steps = {steps}, --warmup = {warmup}; expected steps >= 1 and warmup >= 0")
    if args.liggghts_repeat is None:
        args.liggghts_repeat = 1 if args.quick else 3
    if args.repeat < 1 or args.liggghts_repeat < 1:
        raise ConfigError(f"--repeat = {args.repeat}, --liggghts-repeat = {args.liggghts_repeat}; expected >= 1")
    if args.compile and "compile" not in inspect.signature(Simulation).parameters:
        raise ConfigError("--compile: this torchdem's Simulation has no compile option")
    if args.threads:
        torch.set_num_threads(args.threads)
    scenario = BenchScenario(n_particles=n, **({"settle_speed": 0.1} if args.quick else {})).validate("bench_engine")
    rayleigh = rayleigh_time_step(scenario.radius_small, scenario.density, scenario.shear_modulus,
                                  scenario.poisson_ratio)
    if not 0 < args.dt <= rayleigh:
        raise ConfigError(f"--dt = {args.dt}; expected (0, {rayleigh:.4g}] s (Rayleigh time step of the "
                          f"{scenario.radius_small} m spheres)")

    packing = load_or_settle(scenario, args.cache_dir, args.resettle)

    timings = [time_torchdem(scenario, packing, b, getattr(torch, d), args.dt, steps, warmup, args.velocity_jitter,
                             args.repeat, args.compile, args.backend)
               for d in dtypes for b in batches]

    # LIGGGHTS: member 0, identical state and skin.
    liggghts, note, case_dir, command, ranks = None, "", None, None, None
    found = None if args.no_liggghts else liggghts_command(args.ranks)
    if args.no_liggghts:
        note = "skipped (--no-liggghts)"
    elif found is None:
        note = "not installed (no `liggghts` on PATH; Debian package liggghts); LIGGGHTS keys are null"
    else:
        command, ranks = found
        velocity, omega = ensemble_velocities(packing, 1, args.velocity_jitter, scenario.seed + 1)
        position = packing.position[None]
        skin = bench_system(scenario, position, packing.radius, velocity, omega, torch.float64, dt=args.dt)[0].skin
        case_dir = args.cache_dir / f"liggghts_{scenario.cache_key()}"
        write_liggghts_case(case_dir, scenario, packing, velocity[0], omega[0], args.dt, skin, steps, warmup,
                            ranks)
        log(f"LIGGGHTS: {warmup} warm-up + {steps} timed steps: (cd {case_dir} && {shlex.join(command)}) ...")
        try:
            for _ in range(args.liggghts_repeat):
                run, _ = run_liggghts(case_dir, command, steps, args.liggghts_timeout)
                log(f"  loop time {run.wall_time:.3f} s, {run.particle_steps_per_s:.4g} particle-steps/s"
                    f"{_busy_note(run)}")
                if liggghts is None or run.wall_time < liggghts.wall_time:
                    liggghts = run
            note = f"cd {case_dir} && {shlex.join(command)}  (best of {args.liggghts_repeat})"
        except (RuntimeError, subprocess.TimeoutExpired) as err:
            liggghts, note = None, f"failed: {err}"
            log(f"LIGGGHTS {note}")

    def figure(dtype: str, batch: int) -> float | None:
        for t in timings:
            if t.dtype == dtype and t.batch == batch:
                return t.particle_steps_per_s
        return None

    ref = liggghts.particle_steps_per_s if liggghts else None
    ratio = lambda x: (x / ref) if (x is not None and ref) else None  # noqa: E731
    b1, b16 = figure(args.headline_dtype, 1), figure(args.headline_dtype, B_ENSEMBLE)
    if args.json:
        result = {
            "particle_steps_per_s_b1": b1,
            "particle_steps_per_s_b16": b16,
            "liggghts_particle_steps_per_s": ref,
            "ratio_b1": ratio(b1),
            "ratio_b16": ratio(b16),
            "headline_dtype": args.headline_dtype,
            **{f"particle_steps_per_s_b{t.batch}_{t.dtype}": t.particle_steps_per_s for t in timings},
            "n_particles": scenario.n_particles,
            "steps": steps,
            "warmup_steps": warmup,
            "dt": args.dt,
            "torch_threads": torch.get_num_threads(),
            "quick": args.quick,
            "compile": args.compile,
            "backend": args.backend,
            "other_cpu_cores": {f"{t.engine} {t.dtype} B={t.batch}": t.other_cpu_cores
                                for t in timings + ([liggghts] if liggghts else [])},
            "liggghts_ranks": ranks if liggghts else None,
            "liggghts_command": shlex.join(command) if (liggghts and command) else None,
            "liggghts_case_dir": str(case_dir) if case_dir else None,
            "liggghts_note": note,
            "final_state": {f"{t.engine} {t.dtype} B={t.batch}": dataclasses.asdict(t.final)
                            for t in timings + ([liggghts] if liggghts else []) if t.batch == 1},
            "scenario": dataclasses.asdict(scenario),
        }
        print(json.dumps(result))
    else:
        print_report(scenario, args.dt, steps, warmup, timings, liggghts, note, args.headline_dtype)
    return 0


if __name__ == "__main__":
    sys.exit(main())
