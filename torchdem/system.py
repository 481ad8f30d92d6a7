"""The static description of a batched DEM system and the low-level builder.

Contract:
- :class:`System` holds everything that does not change during a run: the spheres of every
  body (their body, body-frame offset, radius, material), body masses and principal
  inertia, per-pair contact constants for every member, walls, gravity, time step, skin and
  the cell grid. All particle tensors carry the leading ensemble axis B.
- :func:`build_system` takes explicit tensors (positions, velocities, clump templates and
  their scale, material ids, walls, materials and interaction tables) and returns a
  validated ``(System, State)``. Bad input raises ConfigError naming value, range and source.
- The time step is ``time_step_fraction`` times the Rayleigh time step of the smallest
  sphere (Eq. 3 of Hadi et al.), or an explicit ``dt`` that must not exceed it.
"""
from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import Sequence

import torch

from torchdem.clumps import SPHERE, ClumpTemplate, PrincipalTemplate, principal_template
from torchdem.errors import ConfigError, out_of_range
from torchdem.materials import InteractionTable, Material, MaterialTables, material_tables, rayleigh_time_step
from torchdem.neighbors import CellGrid, cell_grid, search_grid
from torchdem.state import Bodies, PairContacts, State, WallContacts
from torchdem.walls import Walls, WallSpec, make_walls

Tensor = torch.Tensor

ROLLING_STIFFNESS_MODELS = ("tangential", "ai2011")


@dataclass(frozen=True)
class System:
    """Static part of a batched simulation.

    Attributes:
        sphere_body: ``[B, Ns]`` int64 body index (within the member) of each sphere.
        sphere_offset: ``[B, Ns, 3]`` sphere centre in the body's principal frame, m.
        sphere_radius: ``[B, Ns]`` m. sphere_material: ``[B, Ns]`` int64.
        mass: ``[B, Nb]`` kg. inertia: ``[B, Nb, 3]`` principal moments, kg m^2.
        body_material: ``[B, Nb]`` int64.
        tables: per-member, per-material-pair constants.
        walls: the geometry.
        gravity: ``[3]`` m/s^2.
        dt: time step, s. skin: Verlet skin, m.
        time_origin, step_origin: the simulated time (s) at step ``step_origin``; the time at step
            ``k`` is ``time_origin + (k - step_origin) * dt`` (:meth:`time_of`), so a run may change
            its step partway (:meth:`with_time_step`) and its clock runs on.
        grid: cell grid of the domain. domain_lower, domain_upper: ``[3]`` m; bodies that
            leave this box are deactivated and counted as lost.
        rolling_stiffness: ``"tangential"`` or ``"ai2011"`` (see :mod:`torchdem.contact`).
        spheres_only: True when every body is a single centred sphere (skips orientation).
        material_names: names of the M materials.
        wall_events: finite times at which a wall appears or disappears, s.
        walls_move: True if any wall has a non-zero velocity and a move window.
        has_cohesion: True if any pair of any member has a cohesion energy density > 0 (the
            SJKR pass runs only then).
        moved_share: a neighbour rebuild searches anew only the spheres that moved more than this
            share of the skin since they were last searched; the others keep their pairs
            (:func:`torchdem.integrate.moved_spheres`). 0: every rebuild searches every sphere.
            The lists hold the same touching pairs either way, so a run does not change.
    """

    sphere_body: Tensor
    sphere_offset: Tensor
    sphere_radius: Tensor
    sphere_material: Tensor
    mass: Tensor
    inertia: Tensor
    body_material: Tensor
    tables: MaterialTables
    walls: Walls
    gravity: Tensor
    dt: float
    skin: float
    grid: CellGrid
    domain_lower: Tensor
    domain_upper: Tensor
    rolling_stiffness: str
    spheres_only: bool
    material_names: tuple[str, ...]
    wall_events: tuple[float, ...] = ()
    walls_move: bool = False
    has_cohesion: bool = False
    moved_share: float = 0.25
    time_origin: float = 0.0
    step_origin: int = 0

    def time_of(self, step: int) -> float:
        """Simulated time at step ``step``, s (``time_origin + (step - step_origin) * dt``)."""
        return self.time_origin + (step - self.step_origin) * self.dt

    def with_time_step(self, dt: float, step: int) -> "System":
        """This system stepping ``dt`` (s) from step ``step`` on; the time at ``step`` is kept. The
        integrator's step is a complete kick-drift-kick, so changing ``dt`` between two steps keeps it
        second order (the tangential and rolling springs grow by each step's own displacement)."""
        if not dt > 0:
            raise out_of_range("dt", dt, "> 0 s", "System.with_time_step")
        return dataclasses.replace(self, dt=float(dt), time_origin=self.time_of(step), step_origin=int(step))

    @property
    def batch(self) -> int:
        return self.mass.shape[0]

    @property
    def n_bodies(self) -> int:
        return self.mass.shape[1]

    @property
    def n_spheres(self) -> int:
        return self.sphere_radius.shape[1]

    # Per-sphere constants the neighbour rebuild gathers per pair, computed once per system
    # (cached_property writes the instance __dict__, which a frozen dataclass allows): a rebuild
    # then gathers one value per sphere instead of recomputing it per pair.
    @functools.cached_property
    def sphere_body_flat(self) -> Tensor:
        """``[B * Ns]`` flat body index of every sphere."""
        B, Ns = self.sphere_body.shape
        base = torch.arange(B, device=self.sphere_body.device)[:, None] * self.n_bodies
        return (self.sphere_body + base).reshape(-1)

    @functools.cached_property
    def spheres_are_bodies(self) -> bool:
        """True when sphere k is body k (flat indices; single spheres without padding): pair and
        wall lists may then use sphere indices as body indices, one index stream less per step."""
        n = self.sphere_body_flat.numel()
        return self.spheres_only and n == self.batch * self.n_bodies and bool(
            (self.sphere_body_flat == torch.arange(n, device=self.sphere_body_flat.device)).all())

    @functools.cached_property
    def sphere_mass(self) -> Tensor:
        """``[B * Ns]`` mass of the body of every sphere, kg."""
        return self.mass.reshape(-1)[self.sphere_body_flat]

    @functools.cached_property
    def sphere_rolling_inertia(self) -> Tensor:
        """``[B * Ns]`` I + m r^2 of every sphere about its contact point: the body's mean
        principal moment plus its mass times the sphere radius squared, kg m^2."""
        body = self.sphere_body_flat
        radius = self.sphere_radius.reshape(-1)
        inertia = self.inertia.reshape(-1, 3).mean(-1)[body]
        return inertia + self.mass.reshape(-1)[body] * radius * radius

    @functools.cached_property
    def dt_tensor(self) -> Tensor:
        """:attr:`dt` as a 0-d tensor of the state's dtype and device (the kernels' argument)."""
        return torch.tensor(self.dt, dtype=self.mass.dtype, device=self.mass.device)

    @functools.cached_property
    def zero_body_vectors(self) -> Tensor:
        """``[B * Nb, 3]`` zeros: where the contact forces start. Kernels never write into their
        inputs, so one tensor serves every step."""
        return torch.zeros(self.batch * self.n_bodies, 3, dtype=self.mass.dtype, device=self.mass.device)

    @functools.cached_property
    def pair_lookup(self) -> tuple[Tensor, ...]:
        """Where the C++ pair kernel looks up the per-pair constants of a touching pair: per
        sphere ``[B * Ns]`` radius, body mass, rolling inertia, pair-table row and material,
        and the ``[6, B * M * M]`` :attr:`MaterialTables.law_table`, with the cohesion table as a
        7th row when the system has cohesion (:attr:`has_cohesion`)."""
        table = self.tables.law_table
        if self.has_cohesion:
            table = torch.cat([table, self.tables.cohesion.reshape(1, -1)])
        return (self.sphere_radius.reshape(-1).contiguous(), self.sphere_mass, self.sphere_rolling_inertia,
                self.sphere_pair_row, self.sphere_material.reshape(-1).contiguous(), table)

    @functools.cached_property
    def sphere_pair_row(self) -> Tensor:
        """``[B * Ns]`` int64 ``(member * M + material) * M`` of every sphere: plus the other
        side's material id, the flat index into the ``[B, M, M]`` tables."""
        B, Ns = self.sphere_material.shape
        M = self.tables.n_materials
        member = torch.arange(B, device=self.sphere_material.device)[:, None]
        return ((member * M + self.sphere_material) * M).reshape(-1)


def _check_shape(t: Tensor, shape: tuple, name: str, source: str) -> None:
    if tuple(t.shape) != tuple(shape):
        raise ConfigError(f"{source}: {name} has shape {tuple(t.shape)}; expected {tuple(shape)}")


def build_system(
    position: Tensor,
    material: Tensor,
    materials: Sequence[Material],
    interactions: InteractionTable,
    *,
    radius: Tensor | None = None,
    templates: Sequence[ClumpTemplate] = (SPHERE,),
    template_index: Tensor | None = None,
    scale: Tensor | None = None,
    orientation: Tensor | None = None,
    velocity: Tensor | None = None,
    angular_velocity: Tensor | None = None,
    active: Tensor | None = None,
    walls: Sequence[WallSpec] = (),
    gravity: Sequence[float] = (0.0, 0.0, -9.81),
    time_step_fraction: float | None = 0.15,
    dt: float | None = None,
    skin: float | None = None,
    domain: tuple[Sequence[float], Sequence[float]] | None = None,
    periodic: Sequence[bool] = (False, False, False),
    rolling_stiffness: str = "tangential",
    search_split: float = 0.6,
    source: str = "build_system",
) -> tuple[System, State]:
    """Build a validated system and its initial state from explicit tensors.

    Args:
        position: ``[B, N, 3]`` body centres of mass, m (dtype and device of the run).
        material: ``[B, N]`` int64 material id of each body (index into ``materials``).
        materials: the M materials (particles and walls).
        interactions: coefficients ``[B, M, M]`` and densities ``[B, M]``.
        radius: ``[B, N]`` sphere radii, m — shorthand for one-sphere bodies (``scale``).
        templates: clump templates; ``template_index`` ``[B, N]`` picks one per body and
            ``scale`` ``[B, N]`` sizes it (a sphere template has unit radius).
        orientation: ``[B, N, 4]`` unit quaternions (default identity).
        velocity, angular_velocity: ``[B, N, 3]`` m/s and rad/s (default zero).
        active: ``[B, N]`` bool, False for padding (default all True).
        walls: wall specs (materials by name).
        gravity: m/s^2.
        time_step_fraction: fraction of the Rayleigh time step (used when ``dt`` is None).
        dt: explicit time step, s; must not exceed the Rayleigh time step.
        skin: Verlet skin, m (default 0.3 x the smallest sphere radius... at least 10% of the
            largest radius).
        domain: (lower, upper) corners of the simulation box, m (default: bounding box of
            walls with finite extent and particles, padded).
        periodic: per axis, whether the domain is periodic (needs ``domain``; the period is
            the domain extent along that axis, which must be at least 2 largest diameters).
        rolling_stiffness: ``"tangential"`` or ``"ai2011"``.
        search_split: spheres up to this fraction of the largest radius are searched on a finer
            grid of their own when they are at least half of the spheres
            (:func:`torchdem.neighbors.search_grid`; 0: one grid). The pairs found are the same.
    """
    if position.ndim != 3 or position.shape[-1] != 3:
        raise ConfigError(f"{source}: position has shape {tuple(position.shape)}; expected [B, N, 3]")
    B, N, _ = position.shape
    if B < 1 or N < 1:
        raise ConfigError(f"{source}: the system is empty (B = {B}, N = {N}); expected at least one "
                          "ensemble member and one particle")
    dtype, device = position.dtype, position.device
    if dtype not in (torch.float32, torch.float64):
        raise ConfigError(f"{source}: position dtype is {dtype}; expected torch.float32 or torch.float64")
    if not bool(torch.isfinite(position).all()):
        raise ConfigError(f"{source}: position contains non-finite values")
    if interactions.batch != B:
        raise ConfigError(f"{source}: interaction table has B = {interactions.batch} members but "
                          f"position has B = {B}")
    if rolling_stiffness not in ROLLING_STIFFNESS_MODELS:
        raise out_of_range("rolling_stiffness", rolling_stiffness, f"one of {ROLLING_STIFFNESS_MODELS}", source)
    M = len(materials)
    names = tuple(m.name for m in materials)
    material = torch.as_tensor(material, device=device).long()
    _check_shape(material, (B, N), "material", source)
    if bool((material < 0).any()) or bool((material >= M).any()):
        raise out_of_range("material", int(material.max()), f"material ids in [0, {M - 1}] ({names})", source)
    active = torch.ones((B, N), dtype=torch.bool, device=device) if active is None else active.to(device).bool()
    _check_shape(active, (B, N), "active", source)

    # Bodies from templates.
    if radius is not None:
        if scale is not None or template_index is not None:
            raise ConfigError(f"{source}: give either radius (spheres) or templates with template_index and scale")
        scale = torch.as_tensor(radius, dtype=dtype, device=device)
        templates = (SPHERE,)
        template_index = torch.zeros((B, N), dtype=torch.long, device=device)
    if scale is None or template_index is None:
        raise ConfigError(f"{source}: particle sizes missing; give radius [B, N] or template_index and scale")
    scale = torch.as_tensor(scale, dtype=dtype, device=device)
    template_index = torch.as_tensor(template_index, device=device).long()
    _check_shape(scale, (B, N), "scale (radius)", source)
    _check_shape(template_index, (B, N), "template_index", source)
    if bool((scale[active] <= 0).any()) or not bool(torch.isfinite(scale).all()):
        raise out_of_range("radius/scale", float(scale[active].min()), "finite values > 0 m", source)
    if bool((template_index < 0).any()) or bool((template_index >= len(templates)).any()):
        raise out_of_range("template_index", int(template_index.max()), f"[0, {len(templates) - 1}]", source)
    principal: list[PrincipalTemplate] = [principal_template(t) for t in templates]
    K = max(p.template.n_spheres for p in principal)
    # Per-template padded tables: offsets [T, K, 3], radii [T, K] (0 = no sphere).
    T = len(principal)
    off_t = torch.zeros((T, K, 3), dtype=dtype, device=device)
    rad_t = torch.zeros((T, K), dtype=dtype, device=device)
    vol_t = torch.zeros(T, dtype=dtype, device=device)
    inert_t = torch.zeros((T, 3), dtype=dtype, device=device)
    for k, p in enumerate(principal):
        n = p.template.n_spheres
        off_t[k, :n] = torch.as_tensor(p.template.offsets, dtype=dtype)
        rad_t[k, :n] = torch.as_tensor(p.template.radii, dtype=dtype)
        vol_t[k] = p.volume
        inert_t[k] = torch.as_tensor(p.principal_inertia, dtype=dtype)
    density = torch.gather(interactions.density.to(device=device, dtype=dtype), 1, material)  # [B, N]
    if bool((density[active] <= 0).any()):
        bad = int(material[active][density[active] <= 0][0])
        raise out_of_range(f"density[{names[bad]}]", 0.0, "a particle density > 0 kg/m^3", source)
    mass = density * vol_t[template_index] * scale ** 3
    inertia = density[..., None] * inert_t[template_index] * (scale ** 5)[..., None]
    mass = torch.where(active, mass, torch.ones_like(mass))
    inertia = torch.where(active[..., None], inertia, torch.ones_like(inertia))

    sphere_radius_all = rad_t[template_index] * scale[..., None]                   # [B, N, K]
    present = (sphere_radius_all > 0)
    # Flatten spheres: every body gets K slots; empty slots are dropped when the layout is
    # identical across members, otherwise kept as inactive padding via zero radius handling.
    counts = present.sum(-1)                                                        # [B, N]
    Ns_member = counts.sum(-1)
    Ns = int(Ns_member.max())
    sphere_body = torch.zeros((B, Ns), dtype=torch.long, device=device)
    sphere_offset = torch.zeros((B, Ns, 3), dtype=dtype, device=device)
    sphere_radius = torch.zeros((B, Ns), dtype=dtype, device=device)
    sphere_material = torch.zeros((B, Ns), dtype=torch.long, device=device)
    body_ids = torch.arange(N, device=device)[:, None].expand(N, K)
    for b in range(B):
        sel = present[b]
        n = int(sel.sum())
        sphere_body[b, :n] = body_ids[sel]
        sphere_offset[b, :n] = (off_t[template_index[b]] * scale[b, :, None, None])[sel]
        sphere_radius[b, :n] = sphere_radius_all[b][sel]
        sphere_material[b, :n] = material[b][:, None].expand(N, K)[sel]
        if n < Ns:  # padding spheres ride on a padding body slot: body 0 with zero radius
            sphere_body[b, n:] = 0
    sphere_valid = torch.arange(Ns, device=device)[None, :] < Ns_member[:, None]

    # Time step.
    live = sphere_valid & torch.gather(active, 1, sphere_body)  # [B, Ns] spheres of active bodies
    live_radius = sphere_radius[live]
    r_min = float(live_radius.min())
    particle_mats = sorted(set(int(m) for m in material[active].unique()))
    rayleigh = min(
        rayleigh_time_step(r_min, float(interactions.density[:, m].min()), materials[m].shear_modulus,
                           materials[m].poisson_ratio)
        for m in particle_mats
    )
    if dt is None:
        if time_step_fraction is None or not (0 < time_step_fraction <= 1):
            raise out_of_range("time_step_fraction", time_step_fraction, "a fraction in (0, 1] of the Rayleigh time step", source)
        dt = time_step_fraction * rayleigh
    elif not (0 < dt <= rayleigh):
        raise out_of_range("dt", dt, f"(0, {rayleigh:.4g}] s (the Rayleigh time step of the smallest "
                           f"sphere, r = {r_min:.4g} m)", source)
    r_max = float(live_radius.max())
    if skin is None:
        skin = 0.2 * r_max
    if not skin > 0:
        raise out_of_range("skin", skin, "a distance > 0 m", source)

    ids = {n: k for k, n in enumerate(names)}
    wall_t = make_walls(walls, ids, dtype=dtype, device=device, source=f"{source}.walls")
    wall_mats = sorted(set(int(m) for m in wall_t.material.tolist()))
    for a in particle_mats:
        for b in sorted(set(particle_mats) | set(wall_mats)):
            if bool(torch.isnan(interactions.mu_s[:, a, b]).any()):
                raise ConfigError(f"{source}: interaction pair ({names[a]}, {names[b]}) can touch but has no "
                                  "coefficients; add it to the interaction table")
    if domain is None:
        lo = position[active].min(0).values - 4 * r_max
        hi = position[active].max(0).values + 4 * r_max
        fin = torch.isfinite(wall_t.half_u) & torch.isfinite(wall_t.half_v)
        if bool(fin.any()):
            ext = (wall_t.half_u[fin, None] * wall_t.axis_u[fin].abs()
                   + wall_t.half_v[fin, None] * wall_t.axis_v[fin].abs())
            lo = torch.minimum(lo, (wall_t.centre[fin] - ext).min(0).values - 2 * r_max)
            hi = torch.maximum(hi, (wall_t.centre[fin] + ext).max(0).values + 2 * r_max)
    else:
        lo = torch.as_tensor(domain[0], dtype=dtype, device=device)
        hi = torch.as_tensor(domain[1], dtype=dtype, device=device)
        if not bool((hi > lo).all()):
            raise ConfigError(f"{source}: domain lower {domain[0]} must be below upper {domain[1]} on every axis")
        per = torch.tensor([bool(p) for p in periodic], device=device)
        outside = active & (((position < lo) | (position > hi)) & ~per).any(-1)
        if bool(outside.any()):
            b, k = torch.nonzero(outside)[0].tolist()
            raise ConfigError(f"{source}: body {k} of member {b} at {position[b, k].tolist()} starts outside "
                              f"the domain {list(domain[0])}..{list(domain[1])}")
    periodic = tuple(bool(p) for p in periodic)
    if len(periodic) != 3:
        raise ConfigError(f"{source}: periodic = {periodic}; expected three booleans (x, y, z)")
    if any(periodic):
        if domain is None:
            raise ConfigError(f"{source}: periodic = {periodic} needs an explicit domain (the period)")
        # Minimum image is exact when every contact separation (<= 2 r_max) and every lever arm
        # from a body's centre to its contact points (<= its reach, |offset| + r) is below half
        # the period. The skin need not be: the pair search visits every cell of a periodic
        # axis with fewer than 3 cells and keeps a pair by its minimum-image distance, which
        # moves no more than the spheres do, so the skin criterion still holds.
        reach = float((sphere_offset.norm(dim=-1) + sphere_radius)[live].max())
        need = 2 * max(2 * r_max, reach)
        for ax in range(3):
            if periodic[ax] and float(hi[ax] - lo[ax]) <= need:
                raise out_of_range(f"domain extent along periodic axis {'xyz'[ax]}", float(hi[ax] - lo[ax]),
                                   f"> {need:.4g} m (twice the largest contact distance {2 * r_max:.4g} m or "
                                   f"body reach {reach:.4g} m)", source)
    if not 0 <= search_split < 1:
        raise out_of_range("search_split", search_split, "[0, 1) of the largest sphere radius (0: one grid)", source)
    grid = cell_grid(lo, hi, 2 * r_max + skin, periodic=periodic, dtype=dtype, device=device)
    grid = search_grid(grid, live_radius, skin, search_split)

    if orientation is None:
        orientation = torch.zeros((B, N, 4), dtype=dtype, device=device)
        orientation[..., 0] = 1.0
    else:
        orientation = torch.as_tensor(orientation, dtype=dtype, device=device)
        _check_shape(orientation, (B, N, 4), "orientation", source)
        orientation = orientation / orientation.norm(dim=-1, keepdim=True)
    velocity = torch.zeros_like(position) if velocity is None else torch.as_tensor(velocity, dtype=dtype, device=device)
    _check_shape(velocity, (B, N, 3), "velocity", source)
    omega = torch.zeros_like(position) if angular_velocity is None else torch.as_tensor(angular_velocity, dtype=dtype, device=device)
    _check_shape(omega, (B, N, 3), "angular_velocity", source)
    from torchdem.rigid import quat_rotate, quat_rotate_inverse
    ang_mom = quat_rotate(orientation, inertia * quat_rotate_inverse(orientation, omega))
    zero = torch.zeros_like(position)
    act_f = active[..., None].to(dtype)
    bodies = Bodies(position=position.clone(), velocity=velocity * act_f, orientation=orientation,
                    angular_momentum=ang_mom * act_f, force=zero, torque=zero.clone(), active=active)

    spheres_only = bool((sphere_offset == 0).all()) and K == 1
    system = System(
        sphere_body=sphere_body, sphere_offset=sphere_offset, sphere_radius=sphere_radius,
        sphere_material=sphere_material, mass=mass, inertia=inertia, body_material=material,
        tables=_cast_tables(material_tables(materials, interactions), dtype, device),
        walls=wall_t, gravity=torch.as_tensor(gravity, dtype=dtype, device=device),
        dt=float(dt), skin=float(skin), grid=grid, domain_lower=lo, domain_upper=hi,
        rolling_stiffness=rolling_stiffness, spheres_only=spheres_only, material_names=names,
        wall_events=wall_t.events,
        walls_move=bool(((wall_t.velocity.norm(dim=-1) > 0) & (wall_t.move_until > wall_t.move_from)).any()),
        has_cohesion=bool((torch.nan_to_num(interactions.cohesion) > 0).any()),
    )
    state = initial_state(system, bodies)
    return system, state


def _cast_tables(t: MaterialTables, dtype, device) -> MaterialTables:
    """The tables in the run's dtype, on the run's device (an interaction table built on the CPU
    serves a GPU run)."""
    return MaterialTables(*(getattr(t, f).to(device=device, dtype=dtype) for f in
                            ("young_eff", "shear_eff", "beta", "mu_s", "mu_r", "rolling_damping", "density",
                             "cohesion")))


def _empty_pairs(dtype, device) -> PairContacts:
    li = torch.zeros(0, dtype=torch.long, device=device)
    f = torch.zeros(0, dtype=dtype, device=device)
    v = torch.zeros((0, 3), dtype=dtype, device=device)
    return PairContacts(li, li, li, li, li, v, v, f, f, f, f, f, f, f, f, f, f, f, f)


def _empty_walls(dtype, device) -> WallContacts:
    li = torch.zeros(0, dtype=torch.long, device=device)
    f = torch.zeros(0, dtype=dtype, device=device)
    v = torch.zeros((0, 3), dtype=dtype, device=device)
    return WallContacts(li, li, li, li, v, v, f, f, f, f, f, f, f, f, f, f)


def initial_state(system: System, bodies: Bodies) -> State:
    """State at step 0 with empty neighbour lists (the first step builds them)."""
    dtype, device = bodies.position.dtype, bodies.position.device
    S = system.batch * system.n_spheres
    return State(
        bodies=bodies,
        pairs=_empty_pairs(dtype, device),
        walls=_empty_walls(dtype, device),
        reference=torch.full((S, 3), float("inf"), dtype=dtype, device=device),
        wall_shift=torch.zeros((system.walls.n, 3), dtype=dtype, device=device),
        wall_active=torch.zeros(system.walls.n, dtype=torch.bool, device=device),
        step=0,
        rebuilds=0,
        lost=torch.zeros(system.batch, dtype=torch.long, device=device),
        body_id=torch.arange(system.n_bodies, device=device).expand(system.batch, system.n_bodies).clone(),
        sphere_id=torch.arange(system.n_spheres, device=device).expand(system.batch, system.n_spheres).clone(),
    )
