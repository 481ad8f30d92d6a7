"""One time step of the batched DEM: velocity Verlet for translation, midpoint quaternion
rotation at fixed angular momentum for orientation.

Contract: ``step(system, state) -> state``. Per step:

1. half kick  v += dt/2 F/m,  L += dt/2 tau    (forces of the previous evaluation)
2. drift      x += dt v,  q <- exp(dt omega_mid) q
3. sphere positions from body pose; neighbour lists rebuilt if the skin criterion fires
   (contact history carried over by key)
4. forces: Hertz-Mindlin + EPSD rolling for sphere pairs and sphere-wall pairs, gravity
5. half kick with the new forces

Forces are evaluated with the half-step velocities, as in LIGGGHTS. The wiring here
(gathering per-contact quantities, scattering forces to bodies) is separate from the
contact laws in :mod:`torchdem.contact`, which are pure functions.
"""
from __future__ import annotations

import torch

from torchdem import contact, neighbors
from torchdem.rigid import advance_orientation, angular_velocity, quat_rotate
from torchdem.state import Bodies, PairContacts, State, WallContacts
from torchdem.system import System
from torchdem.walls import closest_points

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


def _pair_table_index(system: System, member: Tensor, mat_a: Tensor, mat_b: Tensor) -> Tensor:
    M = system.tables.n_materials
    return (member * M + mat_a) * M + mat_b


def _rolling_inertia(system: System, body: Tensor, radius: Tensor) -> Tensor:
    """I + m r^2 about the contact point of a sphere of radius r on its body (mean moment)."""
    m = system.mass.reshape(-1)[body]
    inertia = system.inertia.reshape(-1, 3)[body].mean(-1)
    return inertia + m * radius * radius


def rebuild(system: System, state: State, xs: Tensor, time: float) -> State:
    """Rebuild both neighbour lists at the current positions and carry contact history."""
    B, Ns = system.batch, system.n_spheres
    S = B * Ns
    active = sphere_active(system, state.bodies)
    radius = system.sphere_radius.reshape(-1)
    body = system.sphere_body_flat
    mat = system.sphere_material.reshape(-1)
    mass = system.mass.reshape(-1)
    t = system.tables
    flat = lambda x: x.reshape(-1)  # noqa: E731

    i, j = neighbors.find_pairs(xs, radius, body, active, Ns, system.grid, system.skin)
    key = i * S + j
    tang, roll = neighbors.carry_history(state.pairs.key, [state.pairs.tangential, state.pairs.rolling], key)
    bi, bj = body[i], body[j]
    idx = _pair_table_index(system, i // Ns, mat[i], mat[j])
    ri, rj = radius[i], radius[j]
    ir_i, ir_j = _rolling_inertia(system, bi, ri), _rolling_inertia(system, bj, rj)
    pairs = PairContacts(
        i=i, j=j, body_i=bi, body_j=bj, key=key, tangential=tang, rolling=roll,
        radius_i=ri, radius_j=rj, radius_eff=ri * rj / (ri + rj),
        mass_eff=mass[bi] * mass[bj] / (mass[bi] + mass[bj]),
        young_eff=flat(t.young_eff)[idx], shear_eff=flat(t.shear_eff)[idx], beta=flat(t.beta)[idx],
        mu_s=flat(t.mu_s)[idx], mu_r=flat(t.mu_r)[idx], rolling_damping=flat(t.rolling_damping)[idx],
        rolling_inertia=ir_i * ir_j / (ir_i + ir_j),
    )

    W = system.walls.n
    shift = system.walls.shift(time)
    wall_active = system.walls.active_at(time)
    s, w = neighbors.find_wall_pairs(xs, radius, active, system.walls, shift, wall_active, system.skin)
    wkey = s * max(W, 1) + w
    wt, wr = neighbors.carry_history(state.walls.key, [state.walls.tangential, state.walls.rolling], wkey)
    bs = body[s]
    widx = _pair_table_index(system, s // Ns, mat[s], system.walls.material[w])
    rs = radius[s]
    wall_contacts = WallContacts(
        sphere=s, body=bs, wall=w, key=wkey, tangential=wt, rolling=wr, radius=rs, mass_eff=mass[bs],
        young_eff=flat(t.young_eff)[widx], shear_eff=flat(t.shear_eff)[widx], beta=flat(t.beta)[widx],
        mu_s=flat(t.mu_s)[widx], mu_r=flat(t.mu_r)[widx], rolling_damping=flat(t.rolling_damping)[widx],
        rolling_inertia=_rolling_inertia(system, bs, rs),
    )
    return state.set(pairs=pairs, walls=wall_contacts, reference=xs.clone(), wall_shift=shift,
                     wall_active=wall_active, rebuilds=state.rebuilds + 1)


def contact_forces(system: System, state: State, xs: Tensor, omega: Tensor, time: float
                   ) -> tuple[Tensor, Tensor, State]:
    """Total contact force and torque on every body, and the state with updated history.

    Args:
        xs: ``[B * Ns, 3]`` sphere positions. omega: ``[B * Nb, 3]`` angular velocities.
    Returns:
        force, torque: ``[B * Nb, 3]``.
    """
    dt = system.dt
    B, Nb = system.batch, system.n_bodies
    X = state.bodies.position.reshape(B * Nb, 3)
    V = state.bodies.velocity.reshape(B * Nb, 3)
    force = torch.zeros_like(X)
    torque = torch.zeros_like(X)

    p = state.pairs
    if p.n:
        d = xs[p.j] - xs[p.i]
        dist = d.norm(dim=-1)
        overlap = p.radius_i + p.radius_j - dist
        n = d / dist.clamp_min(1e-30)[:, None]
        cp = xs[p.i] + (p.radius_i - 0.5 * overlap)[:, None] * n
        arm_i = cp - X[p.body_i]
        arm_j = cp - X[p.body_j]
        wi, wj = omega[p.body_i], omega[p.body_j]
        v_rel = (V[p.body_i] + torch.linalg.cross(wi, arm_i, dim=-1)
                 - V[p.body_j] - torch.linalg.cross(wj, arm_j, dim=-1))
        f_n, f, tang, k_t = contact.hertz_mindlin(
            overlap, n, v_rel, p.tangential, p.radius_eff, p.mass_eff, p.young_eff, p.shear_eff,
            p.beta, p.mu_s, dt)
        m_roll, roll = contact.rolling_epsd(
            wi - wj, n, p.rolling, f_n, k_t, overlap, p.radius_eff, p.young_eff, p.mu_r,
            p.rolling_damping, p.rolling_inertia, dt, system.rolling_stiffness)
        tau_i = torch.linalg.cross(arm_i, f, dim=-1) + m_roll
        tau_j = -torch.linalg.cross(arm_j, f, dim=-1) - m_roll
        force.index_add_(0, torch.cat((p.body_i, p.body_j)), torch.cat((f, -f)))
        torque.index_add_(0, torch.cat((p.body_i, p.body_j)), torch.cat((tau_i, tau_j)))
        p = p.set(tangential=tang, rolling=roll)

    wc = state.walls
    if wc.n:
        walls = system.walls
        shift = walls.shift(time)
        present = walls.active_at(time)[wc.wall]
        xw = xs[wc.sphere]
        q = closest_points(walls, shift, xw, wc.wall)
        d = q - xw
        dist = d.norm(dim=-1)
        overlap = torch.where(present, wc.radius - dist, torch.full_like(dist, -1.0))
        n = d / dist.clamp_min(1e-30)[:, None]
        cp = xw + (wc.radius - 0.5 * overlap)[:, None] * n
        arm = cp - X[wc.body]
        w = omega[wc.body]
        v_rel = V[wc.body] + torch.linalg.cross(w, arm, dim=-1) - walls.velocity_at(time)[wc.wall]
        f_n, f, tang, k_t = contact.hertz_mindlin(
            overlap, n, v_rel, wc.tangential, wc.radius, wc.mass_eff, wc.young_eff, wc.shear_eff,
            wc.beta, wc.mu_s, dt)
        m_roll, roll = contact.rolling_epsd(
            w, n, wc.rolling, f_n, k_t, overlap, wc.radius, wc.young_eff, wc.mu_r,
            wc.rolling_damping, wc.rolling_inertia, dt, system.rolling_stiffness)
        force.index_add_(0, wc.body, f)
        torque.index_add_(0, wc.body, torch.linalg.cross(arm, f, dim=-1) + m_roll)
        wc = wc.set(tangential=tang, rolling=roll)

    return force, torque, state.set(pairs=p, walls=wc)


def body_angular_velocity(system: System, bodies: Bodies) -> Tensor:
    """``[B * Nb, 3]`` world angular velocity of every body."""
    B, Nb = system.batch, system.n_bodies
    L = bodies.angular_momentum.reshape(B * Nb, 3)
    I = system.inertia.reshape(B * Nb, 3)
    if system.spheres_only:
        return L / I
    return angular_velocity(bodies.orientation.reshape(B * Nb, 4), L, I)


def evaluate_forces(system: System, state: State, time: float) -> State:
    """Rebuild lists if needed, compute forces and torques; return state with them stored."""
    bodies = state.bodies
    xs = sphere_positions(system, bodies)
    wall_move = float((system.walls.shift(time) - state.wall_shift).norm(dim=-1).max()) if system.walls.n else 0.0
    walls_changed = bool((system.walls.active_at(time) != state.wall_active).any()) if system.walls.n else False
    if (state.rebuilds == 0 or walls_changed
            or neighbors.needs_rebuild(xs, state.reference, wall_move, system.skin)):
        state = rebuild(system, state, xs, time)
    omega = body_angular_velocity(system, bodies)
    force, torque, state = contact_forces(system, state, xs, omega, time)
    B, Nb = system.batch, system.n_bodies
    force = force.reshape(B, Nb, 3) + system.mass[..., None] * system.gravity
    act = bodies.active[..., None].to(force.dtype)
    return state.set(bodies=bodies.set(force=force * act, torque=torque.reshape(B, Nb, 3) * act))


def step(system: System, state: State) -> State:
    """Advance one time step (see the module docstring)."""
    dt = system.dt
    b = state.bodies
    act = b.active[..., None].to(b.position.dtype)
    v = b.velocity + (0.5 * dt) * b.force / system.mass[..., None]
    L = b.angular_momentum + (0.5 * dt) * b.torque
    x = b.position + dt * v * act
    if system.spheres_only:
        q = b.orientation
    else:
        q = advance_orientation(b.orientation, L, system.inertia, dt)
        q = torch.where(b.active[..., None], q, b.orientation)
    state = state.set(bodies=b.set(position=x, velocity=v, angular_momentum=L, orientation=q),
                      step=state.step + 1)
    state = evaluate_forces(system, state, state.step * dt)
    b = state.bodies
    v = b.velocity + (0.5 * dt) * b.force / system.mass[..., None]
    L = b.angular_momentum + (0.5 * dt) * b.torque
    return state.set(bodies=b.set(velocity=v, angular_momentum=L))
