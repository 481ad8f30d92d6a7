"""The run loop: stepping, blow-up guards, lost particles, energies, checkpoints.

Contract:
- :class:`Simulation` wraps a ``(System, State)`` pair. ``advance(n_steps)`` and
  ``run_until(time)`` step the batched system; every ``check_every`` steps the guards look
  at each ensemble member separately:
    * non-finite positions or velocities          -> "NaN"
    * a speed above ``max_speed``                 -> "runaway speed"
    * mechanical energy (kinetic + gravitational) above its initial value by more than
      ``energy_tolerance`` of the energy scale    -> "energy growth"
  On a guard, ``on_blowup="raise"`` raises :class:`BlowUpError` naming the step, member and
  likely cause; ``"isolate"`` freezes that member (all its bodies inactive), records it in
  ``failed`` and carries on, so the other members are untouched (members never share data).
- Bodies that leave the domain box are deactivated and counted in ``state.lost``.
- ``save(path)`` / ``Simulation.load(path, system)`` write and read the full state, contact
  history included, so a run resumes bit-for-bit. The save records the Verlet skin its lists were
  built with; a system of another skin rebuilds them at load (lists of a thinner skin would miss
  pairs the wider one's criterion waits for); on a grid without periods that changes no bit of the
  run (a whole rebuild on a periodic one wraps the bodies back into the domain, at round-off).
- ``reorder_every = k > 0`` renumbers the bodies along a space-filling curve after every k-th
  neighbour rebuild (:mod:`torchdem.reorder`), so the contact kernels read partners that lie
  close in memory; ``state.body_id`` keeps every body's id as built, and ``load`` maps the system
  as built onto a saved state's order. 0 (default) never reorders.
- Python's cyclic garbage collector is paused while ``advance`` runs (and restored after): a step
  allocates a few hundred short-lived objects, which triggered collections that scanned every
  object of the process (torch, botorch, ...), 2-3 % of a step's time; a step creates no reference
  cycles (tests/test_simulation.py counts them), so nothing accumulates. Reference counting still
  frees everything at once; cycles a callback creates are collected after ``advance`` returns.
"""
from __future__ import annotations

import gc
import math
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch

from torchdem.errors import BlowUpError, ConfigError
from torchdem.heap import keep_freed_memory
from torchdem.integrate import Kernels, body_angular_velocity, evaluate_forces, rebuild, sphere_positions, step
from torchdem.reorder import permute_system, reorder
from torchdem.state import State, state_from_dict, to_dict
from torchdem.system import System

Tensor = torch.Tensor


@contextmanager
def _cyclic_gc_paused():
    """Pause Python's cyclic garbage collector inside the block, restore its state after."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


@dataclass(frozen=True)
class GuardSettings:
    """Blow-up guard settings.

    Attributes:
        check_every: steps between checks (the checks read values back to the host).
        max_speed: m/s; a body faster than this is a blow-up.
        energy_tolerance: allowed growth of kinetic + gravitational energy, as a fraction of
            the energy scale (initial kinetic energy + m g times the domain height).
        on_blowup: ``"raise"`` or ``"isolate"``.
    """

    check_every: int = 200
    max_speed: float = 50.0
    energy_tolerance: float = 0.05
    on_blowup: str = "raise"

    def validate(self, source: str = "guards") -> "GuardSettings":
        if self.check_every < 1:
            raise ConfigError(f"{source}: check_every = {self.check_every}; expected an integer >= 1")
        if not self.max_speed > 0:
            raise ConfigError(f"{source}: max_speed = {self.max_speed}; expected > 0 m/s")
        if not self.energy_tolerance > 0:
            raise ConfigError(f"{source}: energy_tolerance = {self.energy_tolerance}; expected > 0")
        if self.on_blowup not in ("raise", "isolate"):
            raise ConfigError(f"{source}: on_blowup = {self.on_blowup!r}; expected 'raise' or 'isolate'")
        return self


def kinetic_energy(system: System, state: State) -> Tensor:
    """``[B]`` translational + rotational kinetic energy per member, J."""
    b = state.bodies
    act = b.active.to(b.velocity.dtype)
    trans = 0.5 * (system.mass * b.velocity.square().sum(-1) * act).sum(-1)
    omega = body_angular_velocity(system, b).reshape(b.velocity.shape)
    rot = 0.5 * ((omega * b.angular_momentum).sum(-1) * act).sum(-1)
    return trans + rot


def potential_energy(system: System, state: State) -> Tensor:
    """``[B]`` gravitational potential energy per member relative to the domain floor, J."""
    b = state.bodies
    act = b.active.to(b.position.dtype)
    h = b.position - system.domain_lower
    return -(system.mass * (h * system.gravity).sum(-1) * act).sum(-1)


class Simulation:
    """A batched DEM run (see the module docstring)."""

    def __init__(self, system: System, state: State, guards: GuardSettings = GuardSettings(),
                 compile: bool = False, backend: str = "auto", reorder_every: int = 0):
        """``compile``: torch.compile the torch kernels. ``backend``: contact kernels for CPU
        tensors, ``"auto"`` (C++ when it builds), ``"cpp"`` or ``"torch"`` (see :class:`Kernels`).
        ``reorder_every``: neighbour rebuilds between spatial reorders of the bodies (0: never)."""
        if isinstance(reorder_every, bool) or not isinstance(reorder_every, int) or reorder_every < 0:
            raise ConfigError(f"Simulation: reorder_every = {reorder_every!r} is not allowed; expected an int >= 0 "
                              "(neighbour rebuilds between spatial reorders; 0: never)")
        self.reorder_every = reorder_every
        self.system = system
        self.guards = guards.validate()
        self.kernels = Kernels(compile, backend)
        if state.bodies.position.device.type == "cpu":
            # Contact springs and forces decay through subnormal floats when contacts open;
            # x86 handles subnormals in microcode, 10-20x slower (measured on the pair kernel
            # in float32). Flushing them to zero changes nothing physical (< 1e-38 in float32).
            torch.set_flush_denormal(True)
            # Rebuilds free and reallocate MBs every few steps: keep that memory in the process
            # (torchdem.heap; 20-25 % of a dask worker's CPU went to page faults without it).
            keep_freed_memory()
        if state.rebuilds == 0:
            state = evaluate_forces(system, state, system.time_of(state.step), self.kernels)
        self.state = state
        self.failed: dict[int, str] = {}
        height = float((system.domain_upper - system.domain_lower).abs().max())
        g = float(system.gravity.norm())
        total_mass = (system.mass * state.bodies.active).sum(-1)
        self._energy0 = kinetic_energy(system, state) + potential_energy(system, state)
        self._energy_scale = kinetic_energy(system, state) + total_mass * g * height + 1e-30

    @property
    def time(self) -> float:
        """Simulated time, s."""
        return self.system.time_of(self.state.step)

    def advance(self, n_steps: int, callback: Callable[["Simulation"], None] | None = None,
                callback_every: int = 0) -> "Simulation":
        """Take ``n_steps`` steps; call ``callback(self)`` every ``callback_every`` steps."""
        with _cyclic_gc_paused():
            for _ in range(n_steps):
                rebuilds = self.state.rebuilds
                self.state = step(self.system, self.state, self.kernels)
                if self.reorder_every and self.state.rebuilds != rebuilds \
                        and self.state.rebuilds % self.reorder_every == 0:
                    self.system, self.state = reorder(self.system, self.state)
                k = self.state.step
                if k % self.guards.check_every == 0:
                    self.check()
                if callback is not None and callback_every and k % callback_every == 0:
                    callback(self)
        return self

    def run_until(self, time: float, **kw) -> "Simulation":
        """Step until the simulated time reaches ``time`` (s)."""
        n = int(math.ceil(round((time - self.time) / self.system.dt, 6)))
        return self.advance(max(n, 0), **kw)

    def check(self) -> None:
        """Run the blow-up guards and the domain-loss bookkeeping."""
        sysm, st = self.system, self.state
        b = st.bodies
        finite = torch.isfinite(b.position).all(-1) & torch.isfinite(b.velocity).all(-1)
        nan_member = ~(finite | ~b.active).all(-1)
        speed = torch.nan_to_num(b.velocity.norm(dim=-1), nan=0.0) * b.active
        fast_member = (speed > self.guards.max_speed).any(-1)
        energy = kinetic_energy(sysm, st) + potential_energy(sysm, st)
        growth = (energy - self._energy0) / self._energy_scale
        energy_member = torch.nan_to_num(growth, nan=0.0) > self.guards.energy_tolerance
        for flags, cause in ((nan_member, "positions or velocities became NaN/inf (time step too large "
                                          "for the stiffness, or overlapping initial particles)"),
                             (fast_member, None),
                             (energy_member, None)):
            for m in torch.nonzero(flags).flatten().tolist():
                if m in self.failed:
                    continue
                if flags is fast_member:
                    cause = (f"a body moves at {float(speed[m].max()):.3g} m/s > max_speed "
                             f"{self.guards.max_speed} m/s (time step too large, or initial overlaps)")
                elif flags is energy_member:
                    cause = (f"kinetic + potential energy grew by {100 * float(growth[m]):.1f}% of its "
                             "scale (time step too large for the contact stiffness)")
                self._blowup(m, cause + self._where(m, speed))
        self._remove_lost()

    def _where(self, member: int, speed: Tensor) -> str:
        """Where to look: the time and the fastest body of ``member`` (its id as built, its centre)."""
        k = int(speed[member].argmax())
        x = self.state.bodies.position[member, k].tolist()
        return (f"; at t = {self.time:.4g} s the fastest body is {int(self.state.body_id[member, k])} at "
                f"({x[0]:.4g}, {x[1]:.4g}, {x[2]:.4g}) m")

    def _blowup(self, member: int, cause: str) -> None:
        if self.guards.on_blowup == "raise":
            raise BlowUpError(self.state.step, member, cause)
        self.failed[member] = cause
        b = self.state.bodies
        active = b.active.clone()
        active[member] = False
        zero = torch.zeros_like(b.velocity[member])
        velocity, ang, position = b.velocity.clone(), b.angular_momentum.clone(), b.position.clone()
        velocity[member] = zero
        ang[member] = zero
        position[member] = torch.nan_to_num(position[member], nan=0.0, posinf=0.0, neginf=0.0)
        self.state = self.state.set(bodies=b.set(active=active, velocity=velocity, angular_momentum=ang,
                                                 position=position))
        self.state = self.state.set(rebuilds=0)  # force a clean rebuild without the frozen member
        self.state = evaluate_forces(self.system, self.state, self.time, self.kernels)

    def _remove_lost(self) -> None:
        b = self.state.bodies
        periodic = self.system.grid.period > 0
        outside = (((b.position < self.system.domain_lower) | (b.position > self.system.domain_upper))
                   & ~periodic).any(-1)
        lost = outside & b.active
        if bool(lost.any()):
            self.state = self.state.set(
                bodies=b.set(active=b.active & ~lost, velocity=b.velocity * (~lost)[..., None]),
                lost=self.state.lost + lost.sum(-1))

    def save(self, path: str | Path) -> None:
        """Write the full state (bodies, contact lists with history, counters) to ``path``. A tensor
        over more memory than it uses (a kernel's recycled output buffer) is written as a compact
        copy: torch.save writes a tensor's whole storage."""
        torch.save({"state": _compact(to_dict(self.state)), "failed": self.failed, "skin": self.system.skin},
                   Path(path))

    @classmethod
    def load(cls, path: str | Path, system: System, guards: GuardSettings = GuardSettings(),
             compile: bool = False, backend: str = "auto", reorder_every: int = 0) -> "Simulation":
        """Restore a run saved by :meth:`save`; ``system`` must be the one it was built with (in
        the order it was built: a reordered state's order is applied to it here), up to its Verlet
        skin: lists saved with another skin (or none recorded) are rebuilt with the system's. The
        state is loaded onto the system's device, so a run saved on a GPU resumes on a CPU and back."""
        data = torch.load(Path(path), weights_only=True, map_location=system.mass.device)
        state = state_from_dict(data["state"])
        if state.bodies.position.shape[:2] != system.mass.shape:
            raise ConfigError(f"{path}: saved state has bodies {tuple(state.bodies.position.shape[:2])} but "
                              f"the system has {tuple(system.mass.shape)}")
        identity = torch.arange(system.n_bodies, device=state.body_id.device).expand_as(state.body_id)
        if not torch.equal(state.body_id, identity):
            system = permute_system(system, state.body_id, state.sphere_id)
        sim = cls(system, state, guards, compile, backend, reorder_every)
        sim.failed = dict(data.get("failed", {}))
        if data.get("skin") != system.skin:
            sim.rebuild_lists()
        return sim

    def rebuild_lists(self) -> None:
        """Rebuild both neighbour lists whole at the current positions (contact history carried),
        as a step does when the skin criterion fires; the forces are left as they are."""
        xs = sphere_positions(self.system, self.state.bodies)
        self.state, _ = rebuild(self.system, self.state, xs, self.time,
                                values=self.kernels.extension(xs) is None)


def _compact(d: dict) -> dict:
    """``d`` (nested) with every tensor whose storage holds more than its own elements cloned."""
    def one(v):
        if isinstance(v, dict):
            return _compact(v)
        if isinstance(v, Tensor) and v.untyped_storage().nbytes() != v.numel() * v.element_size():
            return v.clone()
        return v
    return {k: one(v) for k, v in d.items()}


def elastic_energy(system: System, state: State) -> Tensor:
    """``[B]`` Hertz normal elastic energy 8/15 E* sqrt(R*) delta^(5/2) stored in contacts, J.

    Tangential and rolling spring energies are not included (they vanish for frictionless
    contacts, the case where total energy must be conserved).
    """
    from torchdem.integrate import sphere_positions, with_pair_values
    from torchdem.walls import closest_points

    B, Ns = system.batch, system.n_spheres
    xs = sphere_positions(system, state.bodies)
    out = torch.zeros(B, dtype=xs.dtype, device=xs.device)
    p = with_pair_values(system, state.pairs)
    if p.n:
        from torchdem.neighbors import minimum_image
        sep = minimum_image(xs[p.j] - xs[p.i], system.grid.period)
        overlap = (p.radius_i + p.radius_j - sep.norm(dim=-1)).clamp_min(0.0)
        u = (8.0 / 15.0) * p.young_eff * p.radius_eff.sqrt() * overlap ** 2.5
        out.index_add_(0, p.i // Ns, u)
    w = state.walls
    if w.n:
        time = system.time_of(state.step)
        q = closest_points(system.walls, system.walls.shift(time), xs[w.sphere], w.wall)
        present = system.walls.active_at(time)[w.wall]
        overlap = (w.radius - (xs[w.sphere] - q).norm(dim=-1)).clamp_min(0.0) * present
        u = (8.0 / 15.0) * w.young_eff * w.radius.sqrt() * overlap ** 2.5
        out.index_add_(0, w.sphere // Ns, u)
    return out
