"""One time step of the batched DEM: velocity Verlet for translation, midpoint quaternion
rotation at fixed angular momentum for orientation.

Contract: ``step(system, state) -> state``. Per step:

1. half kick  v += dt/2 F/m,  L += dt/2 tau    (forces of the previous evaluation)
2. drift      x += dt v,  q <- exp(dt omega_mid) q
3. sphere positions from body pose; neighbour lists rebuilt if the skin criterion fires
   (contact history carried over by key)
4. forces: Hertz-Mindlin + EPSD rolling (+ SJKR cohesion where a pair has it) for sphere pairs
   and sphere-wall pairs, gravity
5. half kick with the new forces

Forces are evaluated with the half-step velocities, as in LIGGGHTS. The wiring here
(gathering per-contact quantities, scattering forces to bodies) is separate from the
contact laws in :mod:`torchdem.contact`, which are pure functions.
"""
from __future__ import annotations

import warnings

import torch

from torchdem import _ext, contact, neighbors
from torchdem.materials import MaterialTables
from torchdem.rigid import advance_orientation, angular_velocity, quat_rotate
from torchdem.state import Bodies, PairContacts, State, WallContacts
from torchdem.system import System

Tensor = torch.Tensor


def sphere_positions(system: System, bodies: Bodies) -> Tensor:
    """``[B * Ns, 3]`` world positions of every sphere."""
    B, Nb = system.batch, system.n_bodies
    body = system.sphere_body_flat
    pos = bodies.position.reshape(B * Nb, 3)[body]
    if system.spheres_only:
        return pos
    q = bodies.orientation.reshape(B * Nb, 4)[body]
    return pos + quat_rotate(q, system.sphere_offset.reshape(-1, 3))


def sphere_active(system: System, bodies: Bodies) -> Tensor:
    """``[B * Ns]`` bool: sphere exists and its body is active."""
    return bodies.active.reshape(-1)[system.sphere_body_flat] & (system.sphere_radius.reshape(-1) > 0)


def rebuild(system: System, state: State, xs: Tensor, time: float, values: bool = True,
            moved: Tensor | None = None) -> tuple[State, Tensor]:
    """Rebuild both neighbour lists at the current positions and carry contact history.

    On periodic axes, body positions are wrapped back into the domain first; returns the new
    state and the (wrapped) sphere positions ``[B * Ns, 3]``. ``values=False``: the pairs' per-pair
    constants are left None (:class:`PairContacts`), for the C++ kernels, which look them up per sphere.

    ``moved`` (``[B * Ns]`` bool): a partial rebuild. The moved spheres take their current position
    as their reference and are searched anew; the others keep their reference and their pairs
    (nothing is wrapped). The lists are then those of a whole rebuild at the new references, so
    the skin criterion (:func:`neighbors.lists_expired`, which bounds how far two spheres closed
    in from their references, whenever each was last searched) holds as after a whole rebuild.
    The walls must be as at the last build (shift and presence).
    """
    Ns = system.n_spheres
    if moved is None and system.grid.is_periodic:
        x = state.bodies.position
        xw = neighbors.wrap(x, system.grid.lower, system.grid.period)
        xs = xs + (xw - x).reshape(-1, 3)[system.sphere_body_flat]
        state = state.set(bodies=state.bodies.set(position=xw))
    active = sphere_active(system, state.bodies)
    radius = system.sphere_radius.reshape(-1)

    found_at = xs if moved is None else torch.where(moved[:, None], xs, state.reference)
    keep = None if moved is None else (state.pairs.i, state.pairs.j)
    i, j = neighbors.find_pairs(found_at, radius, system.sphere_body_flat, active, Ns, system.grid, system.skin,
                                moved=moved, keep=keep)
    constants = system_pair_constants(system, i, j, values=values)
    tang, roll = neighbors.carry_history(state.pairs.key, [state.pairs.tangential, state.pairs.rolling],
                                         constants["key"])
    pairs = PairContacts(i=i, j=j, tangential=tang, rolling=roll, **constants)

    W = system.walls.n
    shift = system.walls.shift(time)
    wall_active = system.walls.active_at(time)
    keep = None if moved is None else (state.walls.sphere, state.walls.wall)
    s, w = neighbors.find_wall_pairs(found_at, radius, active, system.walls, shift, wall_active, system.skin,
                                     moved=moved, keep=keep)
    wkey = s * max(W, 1) + w
    wt, wr = neighbors.carry_history(state.walls.key, [state.walls.tangential, state.walls.rolling], wkey)
    state = state.set(pairs=pairs, walls=wall_contacts(system, s, w, wkey, wt, wr),
                      reference=xs.clone() if moved is None else found_at, wall_shift=shift,
                      wall_active=wall_active, rebuilds=state.rebuilds + 1)
    return state, xs


def wall_contacts(system: System, sphere: Tensor, wall: Tensor, key: Tensor, tangential: Tensor, rolling: Tensor
                  ) -> WallContacts:
    """The sphere-wall list of the pairs ``sphere, wall`` ``[Q]`` (sorted by ``key`` ``[Q]`` =
    sphere x max(W, 1) + wall) with their history ``tangential``, ``rolling`` ``[Q, 3]``: the
    per-contact constants gathered from the system's per-sphere arrays and material tables."""
    return WallContacts(
        sphere=sphere, body=system.sphere_body_flat[sphere], wall=wall, key=key, tangential=tangential,
        rolling=rolling, radius=system.sphere_radius.reshape(-1)[sphere], mass_eff=system.sphere_mass[sphere],
        rolling_inertia=system.sphere_rolling_inertia[sphere],
        **system.tables.gather(system.sphere_pair_row[sphere] + system.walls.material[wall]),
    )


PAIR_VALUES = ("radius_i", "radius_j", "radius_eff", "mass_eff", "rolling_inertia")
"""The per-pair values of :class:`PairContacts` besides the :attr:`MaterialTables.CONTACT_FIELDS`."""


def pair_constants(i: Tensor, j: Tensor, radius: Tensor, mass: Tensor, rolling_inertia: Tensor, body: Tensor,
                   pair_row: Tensor, material: Tensor, tables: MaterialTables, values: bool = True
                   ) -> dict[str, Tensor | None]:
    """The per-pair constants of a new sphere-sphere list ``i, j`` ``[P]``: ``key``, ``body_i``,
    ``body_j``, the radii, R*, m*, the EPSD I_r* and the :attr:`MaterialTables.CONTACT_FIELDS`
    (``[P]`` each), from per-sphere ``[S]`` radius, mass, rolling inertia, body, pair-table row
    and material. On CPU one pass of the C++ kernel (same values), else tensor operations.
    ``values=False``: the index fields only, every value None."""
    S = radius.shape[0]
    ext = _ext.kernels_for(radius.device)
    if ext is not None:
        index, value = ext.pair_constants(i, j, radius, mass, rolling_inertia, body, pair_row, material,
                                          tables.stacked, values)
        key, body_i, body_j = index.unbind(0)
        if not values:
            return dict(key=key, body_i=body_i, body_j=body_j, **dict.fromkeys(PAIR_VALUES + tables.CONTACT_FIELDS))
        ri, rj, r_eff, m_eff, i_eff, *fields = value.unbind(0)
        return dict(key=key, body_i=body_i, body_j=body_j, radius_i=ri, radius_j=rj, radius_eff=r_eff,
                    mass_eff=m_eff, rolling_inertia=i_eff, **dict(zip(tables.CONTACT_FIELDS, fields)))
    if not values:
        return dict(key=i * S + j, body_i=body[i], body_j=body[j], **dict.fromkeys(PAIR_VALUES + tables.CONTACT_FIELDS))
    ri, rj = radius[i], radius[j]
    mi, mj = mass[i], mass[j]
    ir_i, ir_j = rolling_inertia[i], rolling_inertia[j]
    return dict(key=i * S + j, body_i=body[i], body_j=body[j], radius_i=ri, radius_j=rj,
                radius_eff=ri * rj / (ri + rj), mass_eff=mi * mj / (mi + mj),
                rolling_inertia=ir_i * ir_j / (ir_i + ir_j), **tables.gather(pair_row[i] + material[j]))


def system_pair_constants(system: System, i: Tensor, j: Tensor, values: bool = True) -> dict[str, Tensor | None]:
    """:func:`pair_constants` of the list ``i, j`` ``[P]`` from the system's per-sphere arrays and tables."""
    return pair_constants(i, j, system.sphere_radius.reshape(-1), system.sphere_mass, system.sphere_rolling_inertia,
                          system.sphere_body_flat, system.sphere_pair_row, system.sphere_material.reshape(-1),
                          system.tables, values=values)


def with_pair_values(system: System, pairs: PairContacts) -> PairContacts:
    """``pairs`` with its per-pair constants, computed from the system's per-sphere arrays where a
    rebuild for the C++ kernels left them None (:func:`rebuild`'s ``values``); else ``pairs``."""
    if pairs.radius_i is not None:
        return pairs
    constants = system_pair_constants(system, pairs.i, pairs.j)
    return pairs.set(**{k: constants[k] for k in PAIR_VALUES + system.tables.CONTACT_FIELDS})


def _pair_geometry(xs: Tensor, X: Tensor, i: Tensor, j: Tensor, body_i: Tensor, body_j: Tensor,
                   radius_i: Tensor, radius_j: Tensor, period: Tensor, periodic: bool
                   ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Overlap, centre distance ``[P]``, unit normal from i to j and the lever arms from both
    bodies' centres to the contact point ``[P, 3]`` (mid-overlap on the line of centres)."""
    xi = torch.index_select(xs, 0, i)
    d = torch.index_select(xs, 0, j) - xi
    if periodic:
        d = neighbors.minimum_image(d, period)
    dist = d.norm(dim=-1)
    overlap = radius_i + radius_j - dist
    n = d / dist.clamp_min(1e-30)[:, None]
    cp = xi + (radius_i - 0.5 * overlap)[:, None] * n
    arm_i = cp - torch.index_select(X, 0, body_i)
    arm_j = cp - torch.index_select(X, 0, body_j)
    if periodic:
        arm_i = neighbors.minimum_image(arm_i, period)
        arm_j = neighbors.minimum_image(arm_j, period)
    return overlap, dist, n, arm_i, arm_j


def _wall_geometry(xs: Tensor, X: Tensor, sphere: Tensor, body: Tensor, wall: Tensor, wall_centre: Tensor,
                   wall_u: Tensor, wall_v: Tensor, half_u: Tensor, half_v: Tensor, wall_present: Tensor,
                   radius: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Overlap (-1 where the wall is absent), distance to the closest point of the wall ``[Q]``,
    unit normal towards the wall and lever arm from the body centre to the contact point ``[Q, 3]``."""
    xw = torch.index_select(xs, 0, sphere)
    c = torch.index_select(wall_centre, 0, wall)
    u = torch.index_select(wall_u, 0, wall)
    v = torch.index_select(wall_v, 0, wall)
    rel = xw - c
    hu = torch.index_select(half_u, 0, wall)
    hv = torch.index_select(half_v, 0, wall)
    su = torch.maximum(torch.minimum((rel * u).sum(-1), hu), -hu)
    sv = torch.maximum(torch.minimum((rel * v).sum(-1), hv), -hv)
    d = c + su[:, None] * u + sv[:, None] * v - xw
    dist = d.norm(dim=-1)
    present = torch.index_select(wall_present, 0, wall)
    overlap = torch.where(present, radius - dist, torch.full_like(dist, -1.0))
    n = d / dist.clamp_min(1e-30)[:, None]
    arm = xw + (radius - 0.5 * overlap)[:, None] * n - torch.index_select(X, 0, body)
    return overlap, dist, n, arm


def pair_kernel(xs: Tensor, X: Tensor, V: Tensor, omega: Tensor, force: Tensor, torque: Tensor,
                i: Tensor, j: Tensor, body_i: Tensor, body_j: Tensor, radius_i: Tensor, radius_j: Tensor,
                radius_eff: Tensor, mass_eff: Tensor, young_eff: Tensor, shear_eff: Tensor, beta: Tensor,
                mu_s: Tensor, mu_r: Tensor, rolling_damping: Tensor, rolling_inertia: Tensor,
                tangential: Tensor, rolling: Tensor, dt: Tensor, period: Tensor, stiffness_model: str,
                periodic: bool = False) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Sphere-sphere contacts: add forces and torques into ``force``/``torque`` ``[B*Nb, 3]``.

    ``period`` ``[3]``: periodic box lengths (0 on non-periodic axes); when ``periodic`` is True,
    separations and lever arms use the minimum image.

    Pure tensor wiring around :func:`contact.hertz_mindlin` and :func:`contact.rolling_epsd`
    (no host reads, no data-dependent Python control flow), so it can be compiled.
    Returns (force, torque, tangential, rolling).
    """
    overlap, dist, n, arm_i, arm_j = _pair_geometry(xs, X, i, j, body_i, body_j, radius_i, radius_j, period,
                                                    periodic)
    wi = torch.index_select(omega, 0, body_i)
    wj = torch.index_select(omega, 0, body_j)
    v_rel = (torch.index_select(V, 0, body_i) + torch.linalg.cross(wi, arm_i, dim=-1)
             - torch.index_select(V, 0, body_j) - torch.linalg.cross(wj, arm_j, dim=-1))
    f_n, f, tangential, k_t = contact.hertz_mindlin(
        overlap, n, v_rel, tangential, radius_eff, mass_eff, young_eff, shear_eff, beta, mu_s, dt)
    m_roll, rolling = contact.rolling_epsd(
        wi - wj, n, rolling, f_n, k_t, overlap, radius_eff, young_eff, mu_r, rolling_damping,
        rolling_inertia, dt, stiffness_model)
    tau_i = torch.linalg.cross(arm_i, f, dim=-1) + m_roll
    tau_j = torch.linalg.cross(f, arm_j, dim=-1) - m_roll
    force = force.index_add(0, body_i, f).index_add(0, body_j, -f)
    torque = torque.index_add(0, body_i, tau_i).index_add(0, body_j, tau_j)
    return force, torque, tangential, rolling


def wall_kernel(xs: Tensor, X: Tensor, V: Tensor, omega: Tensor, force: Tensor, torque: Tensor,
                sphere: Tensor, body: Tensor, wall: Tensor, wall_centre: Tensor, wall_u: Tensor,
                wall_v: Tensor, half_u: Tensor, half_v: Tensor, wall_velocity: Tensor, wall_present: Tensor,
                radius: Tensor, mass_eff: Tensor, young_eff: Tensor, shear_eff: Tensor, beta: Tensor,
                mu_s: Tensor, mu_r: Tensor, rolling_damping: Tensor, rolling_inertia: Tensor,
                tangential: Tensor, rolling: Tensor, dt: Tensor, stiffness_model: str
                ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Sphere-wall contacts (walls: current centre ``[W, 3]``, axes, half-extents, velocity,
    presence ``[W]``). Same conventions as :func:`pair_kernel`."""
    overlap, _, n, arm = _wall_geometry(xs, X, sphere, body, wall, wall_centre, wall_u, wall_v, half_u, half_v,
                                        wall_present, radius)
    w = torch.index_select(omega, 0, body)
    v_rel = (torch.index_select(V, 0, body) + torch.linalg.cross(w, arm, dim=-1)
             - torch.index_select(wall_velocity, 0, wall))
    f_n, f, tangential, k_t = contact.hertz_mindlin(
        overlap, n, v_rel, tangential, radius, mass_eff, young_eff, shear_eff, beta, mu_s, dt)
    m_roll, rolling = contact.rolling_epsd(
        w, n, rolling, f_n, k_t, overlap, radius, young_eff, mu_r, rolling_damping, rolling_inertia,
        dt, stiffness_model)
    force = force.index_add(0, body, f)
    torque = torque.index_add(0, body, torch.linalg.cross(arm, f, dim=-1) + m_roll)
    return force, torque, tangential, rolling


def _pair_operands(system: System, p: PairContacts) -> tuple[Tensor, ...]:
    """The ``contacts`` of :meth:`Kernels.pair` (i ... rolling, in :func:`pair_kernel`'s order)."""
    same = system.spheres_are_bodies  # body indices = sphere indices: stream one array, not two
    return (p.i, p.j, *((p.i, p.j) if same else (p.body_i, p.body_j)), p.radius_i, p.radius_j,
            p.radius_eff, p.mass_eff, p.young_eff, p.shear_eff, p.beta, p.mu_s, p.mu_r,
            p.rolling_damping, p.rolling_inertia, p.tangential, p.rolling)


def _wall_operands(system: System, wc: WallContacts, time: float) -> tuple[Tensor, ...]:
    """The ``contacts`` of :meth:`Kernels.wall` (sphere ... rolling, in :func:`wall_kernel`'s order)."""
    walls = system.walls
    return (wc.sphere, wc.sphere if system.spheres_are_bodies else wc.body, wc.wall,
            walls.centre + walls.shift(time) if walls.moves else walls.centre, walls.axis_u, walls.axis_v,
            walls.half_u, walls.half_v, walls.velocity_at(time), walls.active_at(time), wc.radius, wc.mass_eff,
            wc.young_eff, wc.shear_eff, wc.beta, wc.mu_s, wc.mu_r, wc.rolling_damping, wc.rolling_inertia,
            wc.tangential, wc.rolling)


def contact_forces(system: System, state: State, xs: Tensor, omega: Tensor, time: float,
                   kernels: "Kernels | None" = None) -> tuple[Tensor, Tensor, State]:
    """Total contact force and torque on every body, and the state with updated history.

    Args:
        xs: ``[B * Ns, 3]`` sphere positions. omega: ``[B * Nb, 3]`` angular velocities.
    Returns:
        force, torque: ``[B * Nb, 3]``.
    """
    kernels = kernels or EAGER
    B, Nb = system.batch, system.n_bodies
    X = state.bodies.position.reshape(B * Nb, 3)
    V = state.bodies.velocity.reshape(B * Nb, 3)
    force = torque = system.zero_body_vectors
    dt = system.dt_tensor
    p = state.pairs
    cohesive = system.has_cohesion
    if p.n and kernels.extension(xs) is None:  # the torch kernels read the per-pair constants
        p = with_pair_values(system, p)
    if p.n:
        force, torque, tang, roll = kernels.pair(
            xs, X, V, omega, force, torque, *_pair_operands(system, p), dt=dt, period=system.grid.period,
            stiffness_model=system.rolling_stiffness, periodic=system.grid.is_periodic, members=B,
            lookup=system.pair_lookup, centred=system.spheres_only, cohesion=p.cohesion if cohesive else None)
        p = p.set(tangential=tang, rolling=roll)
    wc = state.walls
    if wc.n:
        force, torque, tang, roll = kernels.wall(
            xs, X, V, omega, force, torque, *_wall_operands(system, wc, time), dt=dt,
            stiffness_model=system.rolling_stiffness, members=B, cohesion=wc.cohesion if cohesive else None)
        wc = wc.set(tangential=tang, rolling=roll)
    return force, torque, state.set(pairs=p, walls=wc)


def forces_and_kick(system: System, state: State, xs: Tensor, omega: Tensor, time: float,
                    kernels: "Kernels | None" = None) -> State:
    """:func:`contact_forces` followed by the second half kick (:func:`kick_kernel`): the state
    with the new force, torque (gravity added, inactive bodies masked), velocity, angular
    momentum and contact history. Where the kernels can (:meth:`Kernels.fuses`), one fused
    call (the same bits); else the two steps."""
    kernels = kernels or EAGER
    b = state.bodies
    dt_t = system.dt_tensor
    p, wc = state.pairs, state.walls
    if p.n and wc.n and kernels.fuses(xs):
        B, Nb = system.batch, system.n_bodies
        f, tau, v, L, tang, roll, wtang, wroll = kernels.forces_kick(
            xs, b.position.reshape(B * Nb, 3), b.velocity.reshape(B * Nb, 3), omega, system.zero_body_vectors,
            system.zero_body_vectors, _pair_operands(system, p), _wall_operands(system, wc, time),
            (b.velocity, b.angular_momentum, system.mass, system.gravity, b.active), dt=dt_t,
            period=system.grid.period, stiffness_model=system.rolling_stiffness, periodic=system.grid.is_periodic,
            members=B, lookup=system.pair_lookup, centred=system.spheres_only,
            wall_cohesion=wc.cohesion if system.has_cohesion else None)
        state = state.set(pairs=p.set(tangential=tang, rolling=roll), walls=wc.set(tangential=wtang, rolling=wroll))
    else:
        force, torque, state = contact_forces(system, state, xs, omega, time, kernels)
        f, tau, v, L = kernels.kick(force, torque, b.velocity, b.angular_momentum, system.mass, system.gravity,
                                    b.active, dt_t)
    return state.set(bodies=b.set(force=f, torque=tau, velocity=v, angular_momentum=L))


def pair_cohesion(xs: Tensor, X: Tensor, force: Tensor, torque: Tensor, i: Tensor, j: Tensor, body_i: Tensor,
                  body_j: Tensor, radius_i: Tensor, radius_j: Tensor, cohesion: Tensor, period: Tensor,
                  periodic: bool = False) -> tuple[Tensor, Tensor]:
    """Add the SJKR cohesion (:func:`contact.sjkr_cohesion`, ``cohesion`` ``[P]`` J/m^3) of every
    touching sphere pair to ``force``/``torque`` ``[B*Nb, 3]``: an attractive normal force at the
    contact point of :func:`pair_kernel` (its torque included). The torch kernels' cohesion (the
    C++ pair kernel adds it inside its contact law). Returns (force, torque)."""
    overlap, dist, n, arm_i, arm_j = _pair_geometry(xs, X, i, j, body_i, body_j, radius_i, radius_j, period,
                                                    periodic)
    f = contact.sjkr_cohesion(contact.sjkr_contact_area(overlap, dist, radius_i, radius_j), cohesion)[:, None] * n
    force = force.index_add(0, body_i, f).index_add(0, body_j, -f)
    torque = (torque.index_add(0, body_i, torch.linalg.cross(arm_i, f, dim=-1))
              .index_add(0, body_j, torch.linalg.cross(f, arm_j, dim=-1)))
    return force, torque


def wall_cohesion(xs: Tensor, X: Tensor, force: Tensor, torque: Tensor, sphere: Tensor, body: Tensor, wall: Tensor,
                  wall_centre: Tensor, wall_u: Tensor, wall_v: Tensor, half_u: Tensor, half_v: Tensor,
                  wall_present: Tensor, radius: Tensor, cohesion: Tensor) -> tuple[Tensor, Tensor]:
    """The sphere-wall twin of :func:`pair_cohesion` (walls as in :func:`wall_kernel`; ``cohesion``
    ``[Q]``). Returns (force, torque)."""
    overlap, dist, n, arm = _wall_geometry(xs, X, sphere, body, wall, wall_centre, wall_u, wall_v, half_u, half_v,
                                           wall_present, radius)
    f = contact.sjkr_cohesion(contact.sjkr_contact_area(overlap, dist, radius), cohesion)[:, None] * n
    force = force.index_add(0, body, f)
    torque = torque.index_add(0, body, torch.linalg.cross(arm, f, dim=-1))
    return force, torque


def body_angular_velocity(system: System, bodies: Bodies) -> Tensor:
    """``[B * Nb, 3]`` world angular velocity of every body."""
    B, Nb = system.batch, system.n_bodies
    L = bodies.angular_momentum.reshape(B * Nb, 3)
    I = system.inertia.reshape(B * Nb, 3)
    if system.spheres_only:
        return L / I
    return angular_velocity(bodies.orientation.reshape(B * Nb, 4), L, I)


def evaluate_forces(system: System, state: State, time: float, kernels: "Kernels | None" = None) -> State:
    """Rebuild the lists, compute forces and torques at the current state; store them.

    Used at t = 0 and after a member is frozen; :func:`step` does the same work fused with
    the kicks.
    """
    bodies = state.bodies
    state, xs = rebuild(system, state, sphere_positions(system, bodies), time)
    bodies = state.bodies
    omega = body_angular_velocity(system, bodies)
    force, torque, state = contact_forces(system, state, xs, omega, time, kernels)
    B, Nb = system.batch, system.n_bodies
    force = force.reshape(B, Nb, 3) + system.mass[..., None] * system.gravity
    act = bodies.active[..., None].to(force.dtype)
    return state.set(bodies=bodies.set(force=force * act, torque=torque.reshape(B, Nb, 3) * act))


def drift_kernel(position: Tensor, velocity: Tensor, angular_momentum: Tensor, orientation: Tensor,
                 force: Tensor, torque: Tensor, mass: Tensor, inertia: Tensor, active: Tensor,
                 sphere_body: Tensor, sphere_offset: Tensor, reference: Tensor, dt: Tensor,
                 spheres_only: bool) -> tuple[Tensor, ...]:
    """First half kick and drift; sphere positions, angular velocities and the box of the sphere
    displacements since the last list build (:func:`neighbors.displacement_box`).

    Shapes: bodies ``[B, Nb, ...]``; sphere_body ``[B*Ns]`` flat; sphere_offset ``[B*Ns, 3]``;
    reference ``[B*Ns, 3]``. Returns (x, v, L, q, xs ``[B*Ns, 3]``, omega ``[B*Nb, 3]``,
    displacement ``[B, 7]``).
    """
    act = active[..., None].to(position.dtype)
    v = velocity + (0.5 * dt) * force / mass[..., None]
    L = angular_momentum + (0.5 * dt) * torque
    x = position + dt * v * act
    L_flat = L.reshape(-1, 3)
    I_flat = inertia.reshape(-1, 3)
    xs = torch.index_select(x.reshape(-1, 3), 0, sphere_body)
    if spheres_only:
        q = orientation
        omega = L_flat / I_flat
    else:
        q = advance_orientation(orientation, L, inertia, dt)
        q = torch.where(active[..., None], q, orientation)
        q_flat = q.reshape(-1, 4)
        xs = xs + quat_rotate(torch.index_select(q_flat, 0, sphere_body), sphere_offset)
        omega = angular_velocity(q_flat, L_flat, I_flat)
    members = position.shape[0] if position.dim() == 3 else 1
    return x, v, L, q, xs, omega, neighbors.displacement_box(xs, reference, members)


def kick_kernel(force: Tensor, torque: Tensor, velocity: Tensor, angular_momentum: Tensor,
                mass: Tensor, gravity: Tensor, active: Tensor, dt: Tensor) -> tuple[Tensor, ...]:
    """Add gravity, mask inactive bodies, second half kick. force/torque: ``[B*Nb, 3]``."""
    shape = velocity.shape
    act = active[..., None].to(velocity.dtype)
    f = (force.reshape(shape) + mass[..., None] * gravity) * act
    tau = torque.reshape(shape) * act
    v = velocity + (0.5 * dt) * f / mass[..., None]
    L = angular_momentum + (0.5 * dt) * tau
    return f, tau, v, L


def step(system: System, state: State, kernels: "Kernels | None" = None) -> State:
    """Advance one time step (see the module docstring)."""
    kernels = kernels or EAGER
    dt = system.dt
    b = state.bodies
    dt_t = system.dt_tensor
    x, v, L, q, xs, omega, displacement = kernels.drift(
        b.position, b.velocity, b.angular_momentum, b.orientation, b.force, b.torque, system.mass,
        system.inertia, b.active, system.sphere_body_flat, system.sphere_offset.reshape(-1, 3),
        state.reference, dt_t, system.spheres_only)
    state = state.set(bodies=b.set(position=x, velocity=v, angular_momentum=L, orientation=q),
                      step=state.step + 1)
    time = system.time_of(state.step)
    displacement = displacement.tolist()
    rebuild_now = neighbors.lists_expired(displacement, system.skin, 0.0 if system.walls.n else None)
    if system.walls.n and not rebuild_now and system.wall_events:
        if any((time - dt) < e <= time for e in system.wall_events):
            rebuild_now = bool((system.walls.active_at(time) != state.wall_active).any())
        if not rebuild_now and system.walls_move:
            wall_move = float((system.walls.shift(time) - state.wall_shift).norm(dim=-1).max())
            rebuild_now = neighbors.lists_expired(displacement, system.skin, wall_move)
    if rebuild_now:  # the C++ kernels look the per-pair constants up per sphere
        state, xs = rebuild(system, state, xs, time, values=kernels.extension(xs) is None,
                            moved=moved_spheres(system, state, xs, time))
    return forces_and_kick(system, state, xs, omega, time, kernels)


def moved_spheres(system: System, state: State, xs: Tensor, time: float) -> Tensor | None:
    """``[B * Ns]`` bool: the spheres farther than ``system.moved_share`` of the skin from their
    reference (a non-finite position counts as moved), which a partial rebuild searches anew; None
    where a rebuild must be whole: ``moved_share`` 0, a periodic grid (a whole rebuild wraps the
    bodies back into the domain), or walls that moved or came or went since the last build."""
    if not system.moved_share > 0 or system.grid.is_periodic:
        return None
    if system.walls.n and not (torch.equal(system.walls.active_at(time), state.wall_active)
                               and torch.equal(system.walls.shift(time), state.wall_shift)):
        return None
    threshold = system.moved_share * system.skin
    return ~((xs - state.reference).square().sum(-1) <= threshold * threshold)


KERNEL_BACKENDS = ("auto", "cpp", "torch")


def _compiled_or_eager(kernel):
    """``torch.compile(kernel, dynamic=True)``, falling back to ``kernel`` itself for good when
    compiling it fails (``torch._dynamo.exc.BackendCompilerFailed``, raised before anything runs).
    ``.compile_error`` holds the reason (None while compiled)."""
    from torch._dynamo.exc import BackendCompilerFailed

    compiled = torch.compile(kernel, dynamic=True)

    def call(*args):
        if call.compile_error is None:
            try:
                return compiled(*args)
            except BackendCompilerFailed as err:
                lines = [line.strip() for line in str(err).splitlines() if line.strip()]
                call.compile_error = f"{type(err).__name__}: {' '.join(lines[:2])}"  # the backend and its error
                warnings.warn(f"torchdem: torch.compile failed on {kernel.__name__} ({call.compile_error}); "
                              f"it runs eager from now on", RuntimeWarning, stacklevel=2)
        return kernel(*args)

    call.compile_error = None
    call.__name__ = kernel.__name__
    return call


class Kernels:
    """The contact and integration kernels: the one place that picks an implementation.

    ``backend`` chooses the sphere-sphere and sphere-wall contact kernels for CPU tensors:

    - ``"cpp"``: the C++ kernels of :mod:`torchdem._ext` (built just in time on first use;
      raises if they cannot be built);
    - ``"torch"``: :func:`pair_kernel` and :func:`wall_kernel`, eager or compiled;
    - ``"auto"`` (default): ``"cpp"`` when the extension builds, else ``"torch"`` (the loader
      warns once per process).

    Tensors on other devices (CUDA) always use the torch kernels. ``compile=True`` compiles
    the torch kernels with ``torch.compile`` (dynamic shapes): fusing the element-wise contact
    law into a few loops (one pass over the contacts instead of ~100 tensor operations); the
    first call of each kernel compiles (tens of seconds on a CPU), later calls and other
    contact counts reuse it. The drift and the kick follow the contact kernels (C++ with them,
    else torch, compiled if asked). A kernel that torch cannot compile on this device and torch
    version (Inductor's ``CantSplit`` on a clump system's drift, torch 2.11 on CUDA, for one) runs eager from
    then on, with one warning naming it: the kernels are pure functions, so nothing is lost.
    """

    def __init__(self, compile: bool = False, backend: str = "auto"):
        if backend not in KERNEL_BACKENDS:
            raise ValueError(f"kernel backend = {backend!r}; expected one of {KERNEL_BACKENDS}")
        self.compiled = compile
        self.backend = backend
        wrap = _compiled_or_eager if compile else (lambda f: f)  # noqa: E731
        self.torch_pair = wrap(pair_kernel)
        self.torch_wall = wrap(wall_kernel)
        self.torch_drift = wrap(drift_kernel)
        self.torch_kick = wrap(kick_kernel)
        self.torch_pair_cohesion = wrap(pair_cohesion)
        self.torch_wall_cohesion = wrap(wall_cohesion)

    def extension(self, like: Tensor):
        """The C++ kernels for tensors like ``like``, or None when the torch kernels are used."""
        ext = _ext.kernels_for(like.device, self.backend != "torch")
        if ext is None and self.backend == "cpp" and like.device.type == "cpu":
            raise RuntimeError(f"kernel backend 'cpp': the C++ contact kernels could not be built "
                               f"({_ext.build_error()}); use backend 'auto' or 'torch'")
        return ext

    def drift(self, position: Tensor, *args) -> tuple[Tensor, ...]:
        """:func:`drift_kernel` (same arguments), by the C++ kernel when the contact kernels are."""
        ext = self.extension(position)
        if ext is None:
            return self.torch_drift(position, *args)
        (velocity, angular_momentum, orientation, force, torque, mass, inertia, active, sphere_body,
         sphere_offset, reference, dt, spheres_only) = args
        return tuple(ext.drift(position, velocity, angular_momentum, orientation, force, torque, mass, inertia,
                               active, sphere_body, sphere_offset, reference, float(dt), spheres_only))

    def kick(self, force: Tensor, *args) -> tuple[Tensor, ...]:
        """:func:`kick_kernel` (same arguments), by the C++ kernel when the contact kernels are."""
        ext = self.extension(force)
        if ext is None:
            return self.torch_kick(force, *args)
        torque, velocity, angular_momentum, mass, gravity, active, dt = args
        return tuple(ext.kick(force, torque, velocity, angular_momentum, mass, gravity, active, float(dt)))

    def pair(self, xs: Tensor, X: Tensor, V: Tensor, omega: Tensor, force: Tensor, torque: Tensor,
             *contacts: Tensor, dt: Tensor, period: Tensor, stiffness_model: str, periodic: bool,
             members: int = 1, lookup: tuple[Tensor, ...] | None = None,
             centred: bool = False, cohesion: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """:func:`pair_kernel` (same arguments; ``contacts`` are i ... rolling in its order).

        ``members``: ensemble size B of the flat ``[B*Nb]`` bodies; the C++ kernel then gives
        each thread whole members (same results, one pass less through memory).
        ``lookup``: :attr:`System.pair_lookup`; the C++ kernel reads the per-pair constants from
        it instead of from ``contacts`` (same values, less memory traffic).
        ``centred``: every body is one sphere at its centre (:attr:`System.spheres_only`); the C++
        kernel then takes the lever arms from the sphere centres and skips the body centres
        (same values up to rounding).
        ``cohesion``: ``[P]`` SJKR cohesion energy density of every pair (None: no cohesion), added
        by :func:`pair_cohesion` after the torch kernel. The C++ kernel adds cohesion inside its
        contact law when the lookup table has the 7th, cohesion row (:attr:`System.pair_lookup` of a
        system with cohesion), as :meth:`forces_kick` does; ``cohesion`` is not read there (a list
        built for it has no per-pair values) and given with a 6-row table it is an error."""
        ext = self.extension(xs)
        if ext is None:
            out = self.torch_pair(xs, X, V, omega, force, torque, *contacts, dt, period, stiffness_model, periodic)
            if cohesion is None:
                return out
            f, tau = self.torch_pair_cohesion(xs, X, out[0], out[1], *contacts[:6], cohesion, period, periodic)
            return f, tau, out[2], out[3]
        if lookup is None:
            raise ValueError("Kernels.pair: the C++ pair kernel needs lookup=system.pair_lookup")
        f, tau, tang, roll = ext.pair_forces(
            *_cpp_pair_tensors(xs, X, V, omega, force, torque, contacts, _law_lookup(lookup, cohesion)),
            float(dt), period.tolist(), _ai2011(stiffness_model), periodic, members, centred)
        return f, tau, tang, roll

    def wall(self, xs: Tensor, X: Tensor, V: Tensor, omega: Tensor, force: Tensor, torque: Tensor,
             *contacts: Tensor, dt: Tensor, stiffness_model: str, members: int = 1,
             cohesion: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """:func:`wall_kernel` (same arguments; ``contacts`` are sphere ... rolling in its order;
        ``members`` as in :meth:`pair`; ``cohesion`` ``[Q]`` per contact or None, added by
        :func:`wall_cohesion` after the torch kernel, inside the C++ kernel's law)."""
        ext = self.extension(xs)
        if ext is None:
            out = self.torch_wall(xs, X, V, omega, force, torque, *contacts, dt, stiffness_model)
            if cohesion is None:
                return out
            sphere, body, wall, centre, u, v, hu, hv, _, present, radius = contacts[:11]
            f, tau = self.torch_wall_cohesion(xs, X, out[0], out[1], sphere, body, wall, centre, u, v, hu, hv,
                                              present, radius, cohesion)
            return f, tau, out[2], out[3]
        f, tau, tang, roll = ext.wall_forces(xs, X, V, omega, force, torque, *contacts, float(dt),
                                             _ai2011(stiffness_model), members, cohesion)
        return f, tau, tang, roll

    def fuses(self, like: Tensor) -> bool:
        """True when :meth:`forces_kick` runs as one fused kernel for tensors like ``like``."""
        return self.extension(like) is not None

    def forces_kick(self, xs: Tensor, X: Tensor, V: Tensor, omega: Tensor, force: Tensor, torque: Tensor,
                    pair_contacts: tuple[Tensor, ...], wall_contacts: tuple[Tensor, ...],
                    kick: tuple[Tensor, ...], *, dt: Tensor, period: Tensor, stiffness_model: str,
                    periodic: bool, members: int, lookup: tuple[Tensor, ...], centred: bool,
                    wall_cohesion: Tensor | None = None) -> tuple[Tensor, ...]:
        """:meth:`pair`, then :meth:`wall` on its force and torque, then :meth:`kick` (``kick`` =
        velocity, angular_momentum, mass, gravity, active) in one C++ call: each thread runs the
        three on its own ensemble members while their bodies are in its cache. Returns (f, tau,
        v, L) as :meth:`kick`, then the pair springs and the wall springs; the same bits as the
        three calls. Only where :meth:`fuses` is True. Cohesion: the pairs' from a ``[7, R]``
        lookup table, the walls' from ``wall_cohesion`` ``[Q]`` (None: none)."""
        ext = self.extension(xs)
        if ext is None:
            raise RuntimeError("Kernels.forces_kick needs the C++ kernels (see Kernels.fuses)")
        pair = _cpp_pair_tensors(xs, X, V, omega, force, torque, pair_contacts, lookup)
        wall = list(wall_contacts) + ([] if wall_cohesion is None else [wall_cohesion])
        return tuple(ext.forces_kick(pair, wall, list(kick), float(dt), period.tolist(),
                                     _ai2011(stiffness_model), periodic, members, centred))


def _cpp_pair_tensors(xs: Tensor, X: Tensor, V: Tensor, omega: Tensor, force: Tensor, torque: Tensor,
                      contacts: tuple[Tensor, ...], lookup: tuple[Tensor, ...]) -> list[Tensor]:
    """The tensors of the C++ ``pair_forces`` in its order, from the arguments of :meth:`Kernels.pair`:
    the pairs' indices and springs from ``contacts``, the per-pair constants from ``lookup``."""
    i, j, body_i, body_j = contacts[:4]
    tangential, rolling = contacts[-2:]
    return [xs, X, V, omega, force, torque, i, j, body_i, body_j, *lookup, tangential, rolling]


def _law_lookup(lookup: tuple[Tensor, ...], cohesion: Tensor | None) -> tuple[Tensor, ...]:
    """``lookup``, checked: given ``cohesion``, its law table must carry the cohesion row (the C++
    pair kernel adds cohesion when its table has 7 rows)."""
    table = lookup[-1]
    if cohesion is not None and table.shape[0] != 7:
        raise ValueError(f"Kernels.pair: cohesion given but the lookup table has shape {tuple(table.shape)}; "
                         "expected [7, R] with the cohesion row (System.pair_lookup of a system with cohesion)")
    return lookup


def _ai2011(stiffness_model: str) -> bool:
    if stiffness_model not in ("tangential", "ai2011"):
        raise ValueError(f"stiffness_model = {stiffness_model!r}; expected 'tangential' or 'ai2011'")
    return stiffness_model == "ai2011"


EAGER = Kernels(False, backend="torch")
