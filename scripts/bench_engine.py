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
  particle-steps/s = B * N * steps / wall time. ``--device cuda`` runs the torchdem side on a
  GPU (the torch kernels; ``--compile`` to fuse them); the clock waits for the GPU's queued work.
- When ``liggghts`` is on PATH, the same state (member 0) is written as a LIGGGHTS data file
  and input (Hertz, tangential history, rolling_friction epsd2, five primitive walls,
  nve/sphere, skin equal to torchdem's) and run with ``mpirun -np 2`` and
  ``processors 2 1 1``; its "Loop time of X on R procs for S steps" line gives its
  particle-steps/s. ``ratio_b1`` / ``ratio_b16`` are torchdem / LIGGGHTS (> 1: torchdem faster).
  Without LIGGGHTS those keys are null.
- ``--json`` prints one JSON object on stdout (progress goes to stderr) with the keys
  ``particle_steps_per_s_b1``, ``particle_steps_per_s_b16``, ``liggghts_particle_steps_per_s``,
  ``ratio_b1``, ``ratio_b16`` (headline precision, float64 by default because LIGGGHTS runs in
  double) plus per-precision figures and run details, and ``scaling`` / ``stream`` with
  ``--scaling`` / ``--stream`` (below). ``--quick`` is a smoke run: 600
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
  gap being the deepest penetration of the settled spheres into the low wall plus that into the
  high wall (soft walls; some 10-30 um), so two spheres that leant on the two facing walls are at least r1 + r2 apart: tiling adds no
  overlap. Each N case prints the largest overlap over the whole packing (the settled contacts'
  own, the same as the source packing's) and over pairs of spheres from different tiles (seam;
  negative = the closest approach is a gap). The seam spheres lose their wall and settle a little
  during the run; that changes few contacts. JSON key ``scaling``.
  How to read it: if the cost of a step is linear in N and in B, particle-steps/s is constant, and
  the table's ratio to the smallest case is 1. A rise with N or B means fixed per-step costs
  (Python, kernel calls, the neighbour check) that larger cases amortise; a fall means the cost per
  particle grows. The pair kernel reads both partners' rows (position, radius, mass, material,
  velocity, angular velocity, force and torque: 208 bytes per sphere in float64, 112 in float32
  by :func:`pair_bytes_per_step`) for every contact. A member of ~1k spheres (~0.2 MB) keeps them
  in L2, ~3.4k (~0.7 MB) in L2 or L3, ~14k (~3 MB) in L3, ~54k (~11 MB) at or past the L3 of a
  small CPU (L2 is typically 0.5-2 MB per core, L3 a few MB to a few tens of MB): a fall at the
  large N is partner rows missing the cache. The ensemble gives each thread whole members, so
  its working set stays one member's at any B: B should stay flat until the streamed neighbour
  lists and histories (~3 listed pairs per sphere, ~90 bytes each in float64, never reused) meet
  the memory bandwidth, which ``--stream`` measures. The ``pairs/N`` column (listed pairs per
  sphere) shows when a cut or tiled packing is not the same work per sphere.
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

from torchdem.cli import device_from
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
                 time_step_fraction: float | None = None, box: tuple[float, float] | None = None,
                 device: torch.device | str = "cpu"):
    """``(System, State)`` of the scenario on ``device``; position/velocity/angular_velocity are
    ``[B, N, 3]``. ``box``: inner (x, y) size of the open box, m (default the scenario's; walls as high)."""
    B, N, _ = position.shape
    material = bench_material(scenario)
    coefficients = {"mu_s": scenario.mu_s, "mu_r": scenario.mu_r, "restitution": scenario.restitution,
                    "rolling_damping": 0.0}   # epsd2 has no rolling dashpot
    table = interaction_table([material], {(MATERIAL, MATERIAL): coefficients}, batch=B, dtype=dtype,
                              source="bench_engine")
    box_x, box_y = box if box is not None else (scenario.box_x, scenario.box_y)
    walls = box_walls("box", (0.0, 0.0, 0.0), (box_x, box_y, scenario.wall_height), MATERIAL)
    as_t = lambda a: torch.as_tensor(a, dtype=dtype, device=device)  # noqa: E731
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


def contact_counts(system, state) -> ContactCounts:
    """:class:`ContactCounts` of ``state`` (non-periodic systems: plain separations)."""
    p = state.pairs
    touching = None
    if system.spheres_are_bodies:
        x = state.bodies.position.reshape(-1, 3)
        r = system.sphere_radius.reshape(-1)
        dist = (x[p.j] - x[p.i]).norm(dim=-1)
        touching = int((dist < r[p.i] + r[p.j]).sum())
    return ContactCounts(p.n, touching, state.walls.n, system.batch * system.n_spheres,
                         system.batch * system.n_bodies, bool(system.spheres_are_bodies))


def time_torchdem(scenario: BenchScenario, packing: Packing, batch: int, dtype: torch.dtype, dt: float,
                  steps: int, warmup: int, jitter: float, repeat: int = 1, compile: bool = False,
                  backend: str = "cpp", box: tuple[float, float] | None = None,
                  device: torch.device | str = "cpu") -> EngineTiming:
    """Best of ``repeat`` timings, each from the same initial state with a fresh Simulation.

    ``backend``: contact kernels on the CPU, ``"cpp"`` (C++ extension) or ``"torch"`` (see
    ``Kernels``; on a GPU the torch kernels run). ``device``: where the ensemble runs (the clock
    waits for a GPU's queued work before it stops).
    ``box``: see :func:`bench_system` (packings cut or tiled by ``--scaling``)."""
    velocity, omega = ensemble_velocities(packing, batch, jitter, scenario.seed + 1)
    position = np.broadcast_to(packing.position, velocity.shape).copy()
    system, state = bench_system(scenario, position, packing.radius, velocity, omega, dtype, dt=dt, box=box,
                                 device=device)
    name = str(dtype).replace("torch.", "")
    best = None
    for k in range(repeat):
        sim = Simulation(system, state, compile=compile, backend=backend)
        initial = member0_state(system, sim.state)
        log(f"torchdem {name} B = {batch}, N = {packing.position.shape[0]}: {warmup} warm-up + {steps} timed steps"
            f"{f' (repeat {k + 1}/{repeat})' if repeat > 1 else ''} ...")
        sim.advance(warmup)
        _wait(device)
        builds0 = sim.state.rebuilds
        with CpuMonitor() as cpu:
            t0 = time.perf_counter()
            sim.advance(steps)
            _wait(device)
            wall = time.perf_counter() - t0
        if sim.failed:
            raise RuntimeError(f"torchdem {name} B = {batch}: members failed during timing: {sim.failed}")
        timing = EngineTiming("torchdem", name, batch, packing.position.shape[0], steps, wall,
                              sim.state.rebuilds - builds0, initial, member0_state(sim.system, sim.state),
                              cpu.other_cores, contact_counts(sim.system, sim.state))
        log(f"  {wall:.2f} s, {timing.particle_steps_per_s:.4g} particle-steps/s{_busy_note(timing)}")
        if best is None or timing.wall_time < best.wall_time:
            best = timing
    return best


def _wait(device: torch.device | str) -> None:
    """Wait for the work queued on a GPU (a no-op on the CPU)."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


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


# --------------------------------------------------------------------------- --scaling


@dataclass(frozen=True)
class ScalingPacking:
    """A packing for ``--scaling``: ``box`` its inner (x, y) box size, m; ``tile`` ``[N]`` the tile
    of every sphere (all 0 unless tiled); ``max_overlap`` the largest r_i + r_j - d over the
    packing, ``max_seam_overlap`` over pairs of spheres from different tiles (None: untiled), m."""

    label: str
    packing: Packing
    box: tuple[float, float]
    tile: np.ndarray
    max_overlap: float | None
    max_seam_overlap: float | None


@dataclass(frozen=True)
class ScalingCase:
    """One ``--scaling`` timing. ``sweep``: ``"N"`` (B = 1, packings of different size) or ``"B"``
    (the packing, B copies). ``ratio``: particle-steps/s over that of the sweep's smallest case
    (same dtype). ``pairs_per_particle``: listed sphere-sphere pairs / (B N)."""

    sweep: str
    label: str
    dtype: str
    n_particles: int
    batch: int
    box_x: float
    box_y: float
    steps: int
    wall_time: float
    particle_steps_per_s: float
    ratio: float
    pairs_per_particle: float
    neighbour_builds: int
    other_cpu_cores: float | None
    max_overlap: float | None
    max_seam_overlap: float | None


def _packing_rows(packing: Packing, rows) -> Packing:
    return Packing(packing.position[rows], packing.radius[rows], packing.velocity[rows],
                   packing.angular_velocity[rows], packing.settle_time, packing.settle_max_speed)


def trim_packing(packing: Packing, box_x: float, fraction: float) -> tuple[Packing, float]:
    """The spheres with x < ``fraction`` box_x and the box x size that just holds them
    (max x + r over them; the y size is unchanged)."""
    keep = packing.position[:, 0] < fraction * box_x
    if keep.sum() < 2:
        raise ConfigError(f"trim_packing: {int(keep.sum())} spheres have x < {fraction} x {box_x} m; expected >= 2")
    trimmed = _packing_rows(packing, keep)
    return trimmed, float((trimmed.position[:, 0] + trimmed.radius).max())


def tile_packing(packing: Packing, box_x: float, box_y: float, nx: int, ny: int
                 ) -> tuple[Packing, tuple[float, float], np.ndarray]:
    """``nx`` x ``ny`` copies of a packing in the box [0, box_x] x [0, box_y], side by side in x
    and y: ``(packing, (box x, box y) around all tiles, [N] tile of every sphere)``.

    Tiles are ``box + gap`` apart per axis, the gap being the deepest penetration of the spheres
    into the low wall plus that into the high wall (soft walls: settled spheres press into them),
    so spheres of neighbouring tiles that leant on the two facing walls are r1 + r2 apart or more.
    Tile (ix, iy) is rows ``(iy nx + ix) N ...``: every tile keeps the source's order."""
    if nx < 1 or ny < 1:
        raise ConfigError(f"tile_packing: {nx} x {ny} tiles; expected at least 1 x 1")
    x, r = packing.position, packing.radius
    pitch = []
    for axis, size in ((0, box_x), (1, box_y)):
        low = max(0.0, float((r - x[:, axis]).max()))
        high = max(0.0, float((x[:, axis] + r - size).max()))
        pitch.append(size + low + high)
    tiles = [(ix, iy) for iy in range(ny) for ix in range(nx)]
    shift = np.array([[ix * pitch[0], iy * pitch[1], 0.0] for ix, iy in tiles])
    n = len(r)
    tiled = Packing((x[None] + shift[:, None]).reshape(-1, 3), np.tile(r, len(tiles)),
                    np.tile(packing.velocity, (len(tiles), 1)), np.tile(packing.angular_velocity, (len(tiles), 1)),
                    packing.settle_time, packing.settle_max_speed)
    box = ((nx - 1) * pitch[0] + box_x, (ny - 1) * pitch[1] + box_y)
    return tiled, box, np.repeat(np.arange(len(tiles)), n)


def max_overlaps(position: np.ndarray, radius: np.ndarray, tile: np.ndarray) -> tuple[float | None, float | None]:
    """Largest r_i + r_j - |x_i - x_j| (m; > 0: overlap) over the sphere pairs closer than
    r_i + r_j + max radius, and over those of them whose spheres are in different tiles (each
    None when there is no such pair), by :func:`torchdem.neighbors.find_pairs`."""
    x = torch.as_tensor(position, dtype=torch.float64)
    r = torch.as_tensor(radius, dtype=torch.float64)
    n = x.shape[0]
    skin = float(r.max())
    grid = cell_grid((x.min(0).values - skin).tolist(), (x.max(0).values + skin).tolist(), 3.0 * skin)
    i, j = find_pairs(x, r, torch.arange(n), torch.ones(n, dtype=torch.bool), n, grid, skin)
    if i.numel() == 0:
        return None, None
    overlap = r[i] + r[j] - (x[i] - x[j]).norm(dim=-1)
    t = torch.as_tensor(tile)
    seam = t[i] != t[j]
    return float(overlap.max()), (float(overlap[seam].max()) if bool(seam.any()) else None)


def scaling_packings(scenario: BenchScenario, packing: Packing) -> list[ScalingPacking]:
    """The N cases of ``--scaling``: the cut packing, then the 1x1, 2x2, 4x4 tilings."""
    def checked(label, p, box, tile):
        overlap, seam = max_overlaps(p.position, p.radius, tile)
        um = lambda v: "none" if v is None else f"{v * 1e6:.1f} um"  # noqa: E731
        log(f"scaling packing {label}: N = {len(p.radius)}, box {box[0]:.4f} x {box[1]:.4f} m, "
            f"max overlap {um(overlap)}{'' if seam is None else f', across tile seams {um(seam)}'}")
        return ScalingPacking(label, p, box, tile, overlap, seam)

    cut, cut_x = trim_packing(packing, scenario.box_x, SCALING_TRIM)
    cases = [checked(f"x < {SCALING_TRIM} box_x", cut, (cut_x, scenario.box_y), np.zeros(len(cut.radius), int))]
    for k in SCALING_TILES:
        tiled, box, tile = tile_packing(packing, scenario.box_x, scenario.box_y, k, k)
        cases.append(checked(f"{k}x{k} tiles", tiled, box, tile))
    return cases


def run_scaling(scenario: BenchScenario, packing: Packing, dtypes: list[str], dt: float, steps: int, warmup: int,
                jitter: float, compile: bool, backend: str, device: torch.device | str = "cpu") -> list[ScalingCase]:
    """Times the N sweep (B = 1) and the B sweep (the 1x1 packing) for every dtype."""
    sizes = scaling_packings(scenario, packing)
    base = next(s for s in sizes if s.label == "1x1 tiles")
    cases = []
    for d in dtypes:
        def timed(sweep, s: ScalingPacking, batch):
            t = time_torchdem(scenario, s.packing, batch, getattr(torch, d), dt, steps, warmup, jitter, 1,
                              compile, backend, box=s.box, device=device)
            return ScalingCase(sweep, s.label if sweep == "N" else f"B = {batch}", d, t.n_particles, batch,
                               s.box[0], s.box[1], steps, t.wall_time, t.particle_steps_per_s, math.nan,
                               t.contacts.listed_pairs / (batch * t.n_particles), t.neighbour_builds,
                               t.other_cpu_cores, s.max_overlap, s.max_seam_overlap)

        by_n = [timed("N", s, 1) for s in sizes]
        by_b = [dataclasses.replace(by_n[sizes.index(base)], sweep="B", label="B = 1") if b == 1
                else timed("B", base, b) for b in SCALING_BATCHES]
        for sweep in (by_n, by_b):
            ref = sweep[0].particle_steps_per_s
            cases += [dataclasses.replace(c, ratio=c.particle_steps_per_s / ref) for c in sweep]
    return cases


def print_scaling(cases: list[ScalingCase]) -> None:
    if not cases:
        return
    c0 = cases[0]
    print(f"scaling: {c0.steps} timed steps per case (best of 1); ratio = particle-steps/s over the first row's; "
          "constant particle-steps/s (ratio 1) = cost linear in N and B")
    for dtype in dict.fromkeys(c.dtype for c in cases):
        for sweep, title in (("N", "B = 1, packing size N"), ("B", "ensemble size B, the 1x1 packing")):
            rows = [c for c in cases if c.dtype == dtype and c.sweep == sweep]
            print(f"  {dtype}, {title}:")
            print(f"    {'case':<17}{'N':>7}{'B':>4}{'B*N':>8}{'pairs/N':>9}{'particle-steps/s':>18}{'ratio':>8}"
                  f"{'nbr builds':>11}{'other cores':>12}{'max overlap um':>16}{'seam um':>9}")
            for c in rows:
                other = f"{c.other_cpu_cores:.2f}" if c.other_cpu_cores is not None else "?"
                overlap = f"{c.max_overlap * 1e6:.1f}" if c.max_overlap is not None else "-"
                seam = f"{c.max_seam_overlap * 1e6:.1f}" if c.max_seam_overlap is not None else "-"
                print(f"    {c.label:<17}{c.n_particles:>7}{c.batch:>4}{c.batch * c.n_particles:>8}"
                      f"{c.pairs_per_particle:>9.2f}{c.particle_steps_per_s:>18.4g}{c.ratio:>8.3f}"
                      f"{c.neighbour_builds:>11}{other:>12}{overlap:>16}{seam:>9}")
    print("  (max overlap: the settled contacts' own; seam: pairs across tiles, < 0 a gap, so tiling made no overlap)")


# --------------------------------------------------------------------------- --stream


@dataclass(frozen=True)
class StreamResult:
    """Best of ``repetitions`` STREAM triads ``a = b + s c`` on float64 arrays of ``array_bytes``
    each, on ``threads`` torch threads. gb_per_s counts 3 arrays (STREAM's convention: 2 reads,
    1 write); gb_per_s_write_allocate 4 (the write's line is read first)."""

    array_bytes: int
    repetitions: int
    threads: int
    best_time: float
    other_cpu_cores: float | None

    @property
    def gb_per_s(self) -> float:
        return 3 * self.array_bytes / self.best_time / 1e9

    @property
    def gb_per_s_write_allocate(self) -> float:
        return 4 * self.array_bytes / self.best_time / 1e9


def stream_triad(mib: float = 64.0, repetitions: int = 10) -> StreamResult:
    """STREAM triad with torch (``torch.add(b, c, alpha=s, out=a)``: one pass, no temporary) on
    torch's intra-op threads; every page is touched before the first timed pass."""
    n = int(mib * 2 ** 20) // 8
    if n < 1 or repetitions < 1:
        raise ConfigError(f"stream_triad: {mib} MiB, {repetitions} repetitions; expected > 0 and >= 1")
    b = torch.rand(n, dtype=torch.float64)
    c = torch.rand(n, dtype=torch.float64)
    a = torch.zeros(n, dtype=torch.float64)
    s = 3.0
    torch.add(b, c, alpha=s, out=a)                          # warm-up
    best = math.inf
    with CpuMonitor() as cpu:
        for _ in range(repetitions):
            t0 = time.perf_counter()
            torch.add(b, c, alpha=s, out=a)
            best = min(best, time.perf_counter() - t0)
    k = min(n, 1000)
    if not torch.allclose(a[:k], b[:k] + s * c[:k]):
        raise RuntimeError("stream_triad: a != b + s c")
    return StreamResult(8 * n, repetitions, torch.get_num_threads(), best, cpu.other_cores)


def pair_bytes_per_step(dtype_bytes: int, spheres_are_bodies: bool) -> dict:
    """Bytes the C++ pair kernel moves per step, stream by stream (``torchdem/_ext/contact_cpu.cpp``,
    ``pair_block`` run from ``forces_kick``'s per-member path; tensors as ``integrate._cpp_pair_tensors``
    passes them).

    ``dtype_bytes``: 8 (float64) or 4 (float32); indices are int64. ``spheres_are_bodies``:
    ``System.spheres_are_bodies``; integrate then passes i, j as body_i, body_j (the same arrays:
    one index stream pair less) and the system is ``spheres_only``, so the kernel runs centred
    (no body centres gathered). False is taken to mean clumps: body indices and centres streamed.

    Returns ``{"streams": [...], "lower": totals, "upper": totals, "dtype_bytes", "spheres_are_bodies",
    "line_bytes"}``. Each stream is ``{"stream", "cpp", "access", "lower", "upper"}`` whose
    ``lower`` and ``upper`` map a unit to bytes per unit and step; ``totals`` sums them per unit.
    Units: ``listed_pair`` (every pair of the Verlet list), ``touching_pair`` (pairs whose spheres
    overlap: ``touching_pairs`` runs the gather and the law on those only), ``sphere``, ``body``.
    Lower bound: each byte once; per-sphere and per-body rows (however many pairs read them) once
    per step. Upper bound: per-pair streams once (contiguous, prefetched), every gathered row of
    either partner a full cache line from memory each time it is read (a scattered row: read and
    written back), the table none. The i side is sorted, so its rows mostly hit in practice: the
    upper bound is far above what a spatially ordered packing costs. Not counted: the ``owns()``
    pre-scan of body_i/body_j (a second read of the index streams, from cache for a member that
    fits); the row buffer (64 contacts on the stack, L1) — at B = 1 ``two_passes`` instead writes
    9 values + an int32 per touching pair to a scratch buffer and reads them back once per thread;
    and the wall contacts, the drift and the kick."""
    T, L, idx = dtype_bytes, CACHE_LINE, 8
    centred = spheres_are_bodies
    streams = []

    def add(stream, cpp, access, lower, upper):
        streams.append({"stream": stream, "cpp": cpp, "access": access, "lower": lower, "upper": upper})

    # --- every listed pair
    add("pair indices i, j", "data.i[p], data.j[p]: PairPass::ok (range check), touching_pairs, gather_pairs; "
        "prefetch_partners re-reads j", "read", {"listed_pair": 2 * idx}, {"listed_pair": 2 * idx})
    if not spheres_are_bodies:
        add("pair body indices body_i, body_j", "data.body_i[p], data.body_j[p]: ok, gather_pairs, add_row "
            "(the same arrays as i, j when spheres are bodies)", "read",
            {"listed_pair": 2 * idx}, {"listed_pair": 2 * idx})
    add("sphere positions x[i], x[j]", "load(data.x, data.i[p]), load(data.x, data.j[p]) in touching_pairs "
        "(every listed pair); gather_pairs kXA/kXB re-reads them from L1", "read",
        {"sphere": 3 * T}, {"listed_pair": 2 * L})
    add("sphere radii radius[i], radius[j]", "data.radius[data.i[p]], data.radius[data.j[p]] in touching_pairs; "
        "gather_pairs kRI/kRJ re-reads them", "read", {"sphere": T}, {"listed_pair": 2 * L})
    add("history read tangential[p], rolling[p]", "data.tangential[3p + c], data.rolling[3p + c] in "
        "gather_pairs (kTG, kRL), touching pairs only; upper: their lines hold non-touching neighbours too",
        "read", {"touching_pair": 6 * T}, {"listed_pair": 6 * T})
    add("history write tangential_new[p], rolling_new[p]", "pair_block stage 3: data.tangential_new[3(p0 + k) "
        "+ c], data.rolling_new[...] for every listed pair (zeros where not touching)", "write",
        {"listed_pair": 6 * T}, {"listed_pair": 6 * T})
    # --- touching pairs: gather_pairs on the selected pairs
    if not centred:
        add("body centres X[body_i], X[body_j]", "data.X[3 ba + c], data.X[3 bb + c] in gather_pairs (kBA, kBB); "
            "skipped when centred", "read", {"body": 3 * T}, {"touching_pair": 2 * L})
    add("body velocities V[body_i], V[body_j]", "data.V[3 ba + c], data.V[3 bb + c] in gather_pairs (kVA, kVB)",
        "read", {"body": 3 * T}, {"touching_pair": 2 * L})
    add("angular velocities W[body_i], W[body_j]", "data.W[3 ba + c], data.W[3 bb + c] in gather_pairs "
        "(kWA, kWB)", "read", {"body": 3 * T}, {"touching_pair": 2 * L})
    add("sphere masses and rolling inertias", "data.mass[a], data.mass[b], data.rolling_inertia[a], "
        "data.rolling_inertia[b] in gather_pairs (kMI, kMJ, kII, kIJ)", "read", {"sphere": 2 * T},
        {"touching_pair": 4 * L})
    add("material lookup pair_row[i], material[j]", "data.pair_row[a] + data.material[b] (int64) in gather_pairs: "
        "the table column", "read", {"sphere": 2 * idx}, {"touching_pair": 2 * L})
    add("material-pair table", "data.table[k R + col], k = 0..5 (6 with cohesion), in gather_pairs (kE ... kCOH): "
        "[6, B M^2], a few lines that stay in L1", "read", {}, {})
    add("force and torque scatter", "add_row: force[3a + c] +=, torque[3a + c] +=, force[3b + c] -=, "
        "torque[3b + c] += (read and write); lower: per_member copies force_in/torque_in into the outputs "
        "(read) and the rows leave once (write)", "read+write", {"body": 12 * T}, {"touching_pair": 4 * 2 * L})
    units = ("listed_pair", "touching_pair", "sphere", "body")
    totals = {bound: {u: sum(s[bound].get(u, 0) for s in streams) for u in units} for bound in ("lower", "upper")}
    return {"dtype_bytes": T, "spheres_are_bodies": spheres_are_bodies, "line_bytes": L, "streams": streams,
            **totals}


def pair_traffic(per_unit: dict, listed: int, touching: int, spheres: int, bodies: int) -> float:
    """Bytes per step of one bound of :func:`pair_bytes_per_step` (its ``lower`` or ``upper``)."""
    return (per_unit["listed_pair"] * listed + per_unit["touching_pair"] * touching
            + per_unit["sphere"] * spheres + per_unit["body"] * bodies)


def pair_bandwidth(t: EngineTiming, stream: StreamResult) -> dict:
    """The pair kernel's bytes per listed pair and achieved bytes/s in the timing ``t``, both
    bounds, against ``stream`` (see the module docstring)."""
    c = t.contacts
    counts = pair_bytes_per_step(getattr(torch, t.dtype).itemsize, c.spheres_are_bodies)
    touching = c.touching_pairs if c.touching_pairs is not None else c.listed_pairs
    out = {"dtype": t.dtype, "batch": t.batch, "n_particles": t.n_particles, "steps": t.steps,
           "wall_time": t.wall_time, "neighbour_builds": t.neighbour_builds, "other_cpu_cores": t.other_cpu_cores,
           **dataclasses.asdict(c)}
    for bound in ("lower", "upper"):
        per_step = pair_traffic(counts[bound], c.listed_pairs, touching, c.spheres, c.bodies)
        achieved = per_step * t.steps / t.wall_time
        out[f"bytes_per_step_{bound}"] = per_step
        out[f"bytes_per_listed_pair_{bound}"] = per_step / max(c.listed_pairs, 1)
        out[f"achieved_gb_per_s_{bound}"] = achieved / 1e9
        out[f"fraction_of_stream_{bound}"] = achieved / 1e9 / stream.gb_per_s
        out[f"fraction_of_stream_write_allocate_{bound}"] = achieved / 1e9 / stream.gb_per_s_write_allocate
    out["pair_bytes"] = counts
    return out


def print_stream(stream: StreamResult, kernels: list[dict]) -> None:
    other = f"{stream.other_cpu_cores:.2f}" if stream.other_cpu_cores is not None else "?"
    print(f"STREAM triad (float64, {stream.array_bytes / 2 ** 20:.0f} MiB per array, best of {stream.repetitions}, "
          f"{stream.threads} threads, other cores {other}): {stream.gb_per_s:.2f} GB/s counting 3 arrays, "
          f"{stream.gb_per_s_write_allocate:.2f} GB/s with write-allocate (4 arrays)")
    for k in kernels:
        c = k["pair_bytes"]
        lo, up = c["lower"], c["upper"]
        touching = k["touching_pairs"]
        frac = f"{touching / max(k['listed_pairs'], 1):.3f}" if touching is not None else "?"
        print(f"pair kernel, {k['dtype']} B = {k['batch']} (N = {k['n_particles']}, {k['steps']} steps, "
              f"{k['wall_time']:.2f} s): {k['listed_pairs']} listed pairs ({k['listed_pairs'] / k['spheres']:.2f} "
              f"per sphere, {frac} touching), {k['wall_contacts']} wall contacts (not counted)")
        print(f"  bytes per step: lower {lo['listed_pair']} per listed pair + {lo['touching_pair']} per touching "
              f"pair + {lo['sphere']} per sphere + {lo['body']} per body; upper {up['listed_pair']} per listed "
              f"pair + {up['touching_pair']} per touching pair")
        for bound in ("lower", "upper"):
            print(f"  {bound}: {k[f'bytes_per_listed_pair_{bound}']:.0f} B per listed pair, "
                  f"{k[f'achieved_gb_per_s_{bound}']:.3f} GB/s achieved = "
                  f"{k[f'fraction_of_stream_{bound}']:.3f} of the triad's {stream.gb_per_s:.2f} GB/s")
    print("  (achieved = pair bytes x steps / wall time of the whole step: a floor of the kernel's own rate)")



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
    parser.add_argument("--device", default="cpu", help="torch device of the torchdem runs (cpu, cuda, cuda:1)")
    parser.add_argument("--ranks", type=int, default=2, help="LIGGGHTS MPI ranks (processors R 1 1)")
    parser.add_argument("--no-liggghts", action="store_true", help="skip the LIGGGHTS run")
    parser.add_argument("--liggghts-repeat", type=int, default=None,
                        help="LIGGGHTS runs, keep the best (default 3; 1 with --quick)")
    parser.add_argument("--liggghts-timeout", type=float, default=3600.0, help="s")
    parser.add_argument("--cache-dir", type=Path, default=REPO / ".bench_cache")
    parser.add_argument("--resettle", action="store_true", help="ignore the cached packing and settle again")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    parser.add_argument("--scaling", action="store_true",
                        help="also time N ~1k/3.4k/14k/54k (B = 1) and B = 1/4/16/64, from the cached packing")
    parser.add_argument("--scaling-steps", type=int, default=None,
                        help="timed steps per --scaling case (default 300; 60 with --quick)")
    parser.add_argument("--scaling-warmup", type=int, default=None,
                        help="untimed steps per --scaling case (default 30; 10 with --quick)")
    parser.add_argument("--stream", action="store_true",
                        help="also measure the STREAM triad bandwidth and the pair kernel's share of it")
    parser.add_argument("--stream-mib", type=float, default=64.0, help="MiB per --stream array (float64)")
    parser.add_argument("--stream-repeat", type=int, default=10, help="--stream triads, keep the best")
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
    scaling_steps = args.scaling_steps if args.scaling_steps is not None else (60 if args.quick else 300)
    scaling_warmup = args.scaling_warmup if args.scaling_warmup is not None else (10 if args.quick else 30)
    if scaling_steps < 1 or scaling_warmup < 0:
        raise ConfigError(f"--scaling-steps = {scaling_steps}, --scaling-warmup = {scaling_warmup}; expected "
                          "steps >= 1 and warmup >= 0")
    if not args.stream_mib > 0 or args.stream_repeat < 1:
        raise ConfigError(f"--stream-mib = {args.stream_mib}, --stream-repeat = {args.stream_repeat}; expected "
                          "> 0 and >= 1")
    if args.compile and "compile" not in inspect.signature(Simulation).parameters:
        raise ConfigError("--compile: this torchdem's Simulation has no compile option")
    if args.threads:
        torch.set_num_threads(args.threads)
    device = device_from(args.device, "--device")
    scenario = BenchScenario(n_particles=n, **({"settle_speed": 0.1} if args.quick else {})).validate("bench_engine")
    rayleigh = rayleigh_time_step(scenario.radius_small, scenario.density, scenario.shear_modulus,
                                  scenario.poisson_ratio)
    if not 0 < args.dt <= rayleigh:
        raise ConfigError(f"--dt = {args.dt}; expected (0, {rayleigh:.4g}] s (Rayleigh time step of the "
                          f"{scenario.radius_small} m spheres)")

    packing = load_or_settle(scenario, args.cache_dir, args.resettle)

    timings = [time_torchdem(scenario, packing, b, getattr(torch, d), args.dt, steps, warmup, args.velocity_jitter,
                             args.repeat, args.compile, args.backend, device=device)
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

    scaling = []
    if args.scaling:
        scaling = run_scaling(scenario, packing, dtypes, args.dt, scaling_steps, scaling_warmup,
                              args.velocity_jitter, args.compile, args.backend, device)

    stream, kernels = None, []
    if args.stream:
        log(f"STREAM triad: {args.stream_mib:g} MiB per array, best of {args.stream_repeat} ...")
        stream = stream_triad(args.stream_mib, args.stream_repeat)
        log(f"  {stream.gb_per_s:.2f} GB/s (3 arrays), {stream.gb_per_s_write_allocate:.2f} GB/s (4 arrays)")
        ensemble = [t for t in timings if t.batch == B_ENSEMBLE]
        if not ensemble:   # --batches without 16: a short B = 16 timing per precision
            ensemble = [time_torchdem(scenario, packing, B_ENSEMBLE, getattr(torch, d), args.dt, steps, warmup,
                                      args.velocity_jitter, 1, args.compile, args.backend, device=device)
                        for d in dtypes]
        kernels = [pair_bandwidth(t, stream) for t in ensemble]

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
            "device": str(device),
            "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
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
        if args.scaling:
            result["scaling"] = {"steps": scaling_steps, "warmup_steps": scaling_warmup,
                                 "cases": [dataclasses.asdict(c) for c in scaling]}
        if stream is not None:
            result["stream"] = {"array_mib": stream.array_bytes / 2 ** 20, "repetitions": stream.repetitions,
                                "threads": stream.threads, "best_time_s": stream.best_time,
                                "other_cpu_cores": stream.other_cpu_cores, "triad_gb_per_s": stream.gb_per_s,
                                "triad_gb_per_s_write_allocate": stream.gb_per_s_write_allocate,
                                "pair_kernel": {k["dtype"]: k for k in kernels}}
        print(json.dumps(result))
    else:
        print_report(scenario, args.dt, steps, warmup, timings, liggghts, note, args.headline_dtype)
        print_scaling(scaling)
        if stream is not None:
            print_stream(stream, kernels)
    return 0


if __name__ == "__main__":
    sys.exit(main())
