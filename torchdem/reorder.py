"""Spatial order: renumber bodies (and their spheres) along a space-filling curve.

Contract
--------
The contact kernels read both partners' rows of every listed pair. When the body indices carry
no spatial order, the partner j of sphere i lies anywhere in memory and most of those reads miss
the cache. LIGGGHTS sorts its atoms by spatial bin for the same reason (``atom_modify sort``).

- :func:`spatial_permutation` gives, per member, the body order along the Morton (Z-order) curve
  of the cell grid's cells: ``perm[m, k]`` is the current slot of the body that goes to slot
  ``k``. Active bodies come first (by cell, ties by current slot), inactive ones (padding, lost,
  frozen) after them in their current order.
- :func:`permute_system` and :func:`reorder` apply a permutation: every per-body and per-sphere
  tensor of the :class:`~torchdem.system.System` and of the :class:`~torchdem.state.State` is
  gathered (a body's spheres follow it, kept in their order), ``sphere_body`` is renumbered,
  and ``State.body_id`` / ``State.sphere_id`` record each slot's body and sphere as built, so
  outputs keep naming a body (a sphere) by the same id. The neighbour lists are renumbered, not
  searched again: they hold the same pairs with the same history and the same reference
  positions. A listed pair whose two spheres swap order (i < j in the new numbering) has its
  tangential spring and rolling torque negated, since both are defined from i towards j. Only
  the order of the force sums changes, by round-off.
- :func:`permute_system` alone maps a system as built onto a saved state's order
  (``Simulation.load``).
"""
from __future__ import annotations

import dataclasses

import torch

from torchdem.neighbors import pair_order
from torchdem.state import State
from torchdem.system import System

Tensor = torch.Tensor

__all__ = ["morton_code", "spatial_permutation", "permute_system", "reorder"]


def _spread_bits(v: Tensor) -> Tensor:
    """Insert two zero bits between the low 21 bits of ``v`` (int64)."""
    v = v & 0x1FFFFF
    v = (v | (v << 32)) & 0x1F00000000FFFF
    v = (v | (v << 16)) & 0x1F0000FF0000FF
    v = (v | (v << 8)) & 0x100F00F00F00F00F
    v = (v | (v << 4)) & 0x10C30C30C30C30C3
    v = (v | (v << 2)) & 0x1249249249249249
    return v


def morton_code(cell: Tensor) -> Tensor:
    """Morton (Z-order) code of integer cell coordinates ``[..., 3]`` (each < 2^21) -> ``[...]``."""
    c = cell.to(torch.int64)
    return _spread_bits(c[..., 0]) | (_spread_bits(c[..., 1]) << 1) | (_spread_bits(c[..., 2]) << 2)


def spatial_permutation(system: System, state: State) -> Tensor:
    """``[B, Nb]`` int64: the bodies of each member along the Morton curve of the grid's cells
    (see the module docstring)."""
    grid = system.grid
    x = state.bodies.position
    dims = torch.tensor(grid.dims, device=x.device)
    cell = torch.floor((x - grid.lower) / grid.cell_size).to(torch.int64)
    cell = torch.minimum(torch.clamp_min(cell, 0), dims - 1)
    code = morton_code(cell)
    Nb = system.n_bodies
    slot = torch.arange(Nb, device=x.device)
    inactive = ~state.bodies.active
    big = int(code.max()) + 1 if code.numel() else 1
    # active by code then slot; inactive after every active one, by slot
    key = torch.where(inactive, big + slot, code) * Nb + slot
    return torch.argsort(key, dim=1)


def _inverse(perm: Tensor) -> Tensor:
    """Inverse of a per-member permutation ``[B, n]`` (new slot of every old slot)."""
    inverse = torch.empty_like(perm)
    return inverse.scatter_(1, perm, torch.arange(perm.shape[1], device=perm.device).expand_as(perm))


def _sphere_permutation(system: System, body_perm: Tensor) -> tuple[Tensor, Tensor]:
    """Per-member sphere permutation following ``body_perm`` and the new body index of every
    sphere slot ``[B, Ns]`` each."""
    Ns = system.n_spheres
    new_body = torch.gather(_inverse(body_perm), 1, system.sphere_body)
    order = torch.argsort(new_body * Ns + torch.arange(Ns, device=body_perm.device), dim=1)
    return order, torch.gather(new_body, 1, order)


def permute_system(system: System, body_perm: Tensor, sphere_perm: Tensor | None = None) -> System:
    """The system with its bodies in the order ``body_perm`` ``[B, Nb]`` (slot k takes the body of
    slot ``body_perm[:, k]``) and their spheres following them (in the order ``sphere_perm``
    ``[B, Ns]`` when given, e.g. a saved state's ``sphere_id``)."""
    if sphere_perm is None:
        sphere_perm, sphere_body = _sphere_permutation(system, body_perm)
    else:
        sphere_body = torch.gather(torch.gather(_inverse(body_perm), 1, system.sphere_body), 1, sphere_perm)

    def bodies(t: Tensor) -> Tensor:
        index = body_perm.reshape(body_perm.shape + (1,) * (t.dim() - 2)).expand_as(t)
        return torch.gather(t, 1, index)

    def spheres(t: Tensor) -> Tensor:
        index = sphere_perm.reshape(sphere_perm.shape + (1,) * (t.dim() - 2)).expand_as(t)
        return torch.gather(t, 1, index)

    return dataclasses.replace(
        system, sphere_body=sphere_body, sphere_offset=spheres(system.sphere_offset),
        sphere_radius=spheres(system.sphere_radius), sphere_material=spheres(system.sphere_material),
        mass=bodies(system.mass), inertia=bodies(system.inertia), body_material=bodies(system.body_material))


def _flat(perm: Tensor, n: int) -> Tensor:
    """Flat old index of every flat new slot for a per-member permutation ``[B, n]``."""
    B = perm.shape[0]
    return (perm + torch.arange(B, device=perm.device)[:, None] * n).reshape(-1)


def reorder(system: System, state: State, body_perm: Tensor | None = None) -> tuple[System, State]:
    """Renumber bodies and spheres (default order: :func:`spatial_permutation`) and carry the
    neighbour lists into the new numbering with their history (see the module docstring). The
    rebuild counter is left as it was."""
    from torchdem.integrate import sphere_active, system_pair_constants, wall_contacts

    if body_perm is None:
        body_perm = spatial_permutation(system, state)
    B, Nb, Ns = system.batch, system.n_bodies, system.n_spheres
    sphere_perm, _ = _sphere_permutation(system, body_perm)
    new_system = permute_system(system, body_perm)
    old_body, old_sphere = _flat(body_perm, Nb), _flat(sphere_perm, Ns)
    S = B * Ns
    sphere_new = _flat(_inverse(sphere_perm), Ns)  # new flat slot of every old flat sphere

    b = state.bodies
    take = torch.index_select  # along dim 0; about twice as fast as indexing with a tensor on CPU
    bodies = b.set(**{f.name: take(getattr(b, f.name).reshape((B * Nb,) + getattr(b, f.name).shape[2:]), 0, old_body)
                      .reshape(getattr(b, f.name).shape) for f in dataclasses.fields(b)})
    body_id = torch.gather(state.body_id, 1, body_perm)
    sphere_id = torch.gather(state.sphere_id, 1, sphere_perm)
    reference = take(state.reference, 0, old_sphere)
    # The lists keep every pair under the new numbering (no search: a rebuild in which no sphere
    # moved), so the skin criterion keeps measuring from the same references and the rebuild
    # schedule does not change. As a rebuild would, they drop the pairs of spheres that are
    # inactive or whose reference is not finite, and the wall pairs of walls that are gone.
    live = sphere_active(new_system, bodies) & torch.isfinite(reference).all(-1)

    # sphere pairs: i < j, sorted by key; a pair whose spheres swap order negates its history
    p = state.pairs
    i, j = take(sphere_new, 0, p.i), take(sphere_new, 0, p.j)
    swap = i > j
    sign = torch.where(swap, -1.0, 1.0).to(p.tangential.dtype)[:, None]
    lo, hi = torch.minimum(i, j), torch.maximum(i, j)
    order = pair_order(lo, hi, S)
    lo, hi = take(lo, 0, order), take(hi, 0, order)
    tangential, rolling = take(p.tangential * sign, 0, order), take(p.rolling * sign, 0, order)
    kept = take(live, 0, lo) & take(live, 0, hi)
    if not bool(kept.all()):
        lo, hi, tangential, rolling = lo[kept], hi[kept], tangential[kept], rolling[kept]
    constants = system_pair_constants(new_system, lo, hi,
                                      values=p.radius_i is not None)  # per-pair constants as the state had them
    pairs = p.set(i=lo, j=hi, tangential=tangential, rolling=rolling, **constants)

    # sphere-wall pairs, sorted by key
    w = state.walls
    W = max(system.walls.n, 1)
    wsphere = take(sphere_new, 0, w.sphere)
    worder = torch.argsort(wsphere * W + w.wall)
    wsphere, wall = take(wsphere, 0, worder), take(w.wall, 0, worder)
    wtangential, wrolling = take(w.tangential, 0, worder), take(w.rolling, 0, worder)
    wkept = take(live, 0, wsphere) & take(system.walls.active_at(system.time_of(state.step)), 0, wall)
    if not bool(wkept.all()):
        wsphere, wall, wtangential, wrolling = wsphere[wkept], wall[wkept], wtangential[wkept], wrolling[wkept]
    walls = wall_contacts(new_system, wsphere, wall, wsphere * W + wall, wtangential, wrolling)

    return new_system, state.set(bodies=bodies, pairs=pairs, walls=walls, body_id=body_id, sphere_id=sphere_id,
                                 reference=reference)
