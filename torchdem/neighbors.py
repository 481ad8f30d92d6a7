"""Neighbour search: a cell list built by sorting, with a Verlet skin and history carry-over.

Contract:
- :func:`cell_grid` fixes a uniform grid over the domain with cells at least as wide as the
  largest possible contact distance (largest sphere diameter plus the skin). Points outside
  the domain are clamped into the border cells; clamping keeps adjacency, so no pair is
  missed, only the border cells get more crowded.
- Periodic axes (a thin slice of a wider box) wrap cells around; separations use the
  minimum image (:func:`minimum_image`), and positions are wrapped at every rebuild.
- :func:`find_pairs` hashes every active sphere to ``member * n_cells + cell``, sorts by hash
  (so members never meet), and for each sphere scans the 27 neighbouring cells through
  ``searchsorted`` ranges. It returns every pair (i < j, different bodies) whose centre
  distance is below ``r_i + r_j + skin``. Work and memory are linear in the number of
  spheres at fixed density.
- :func:`find_wall_pairs` returns every (sphere, wall) closer than ``r + skin``.
- :func:`carry_history` copies spring history from an old list to a new one by matching
  sorted int64 keys (pairs that persist keep their springs; new pairs start at zero).
- :func:`lists_expired` is the skin criterion: rebuild when the box of a member's sphere
  displacements from their reference positions (where each was last searched) has a diagonal
  above the skin (two of its spheres may then have closed the skin between them), or, with
  walls, when the largest displacement plus how far any wall moved is above it.
- With ``moved`` and ``keep``, :func:`find_pairs` and :func:`find_wall_pairs` search only the
  moved spheres and keep the last build's other pairs (a partial rebuild,
  :func:`torchdem.integrate.rebuild`).
"""
from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from torchdem import _ext
from torchdem.walls import Walls

Tensor = torch.Tensor


@dataclass(frozen=True)
class CellGrid:
    """Uniform cell grid, optionally periodic along some axes.

    Attributes:
        lower: ``[3]`` domain lower corner, m. cell_size: ``[3]`` cell edge per axis, m (each
            at least the requested size; on a periodic axis it divides the period exactly).
        dims: number of cells along x, y, z.
        period: ``[3]`` period length on periodic axes, 0 elsewhere, m.
        split: radius, m, up to which spheres are searched among themselves on a finer grid
            of their own (0: one grid for all); see :func:`with_split`.
        fine_cell_size: ``[3]`` cell edge of that finer grid per axis, m (None without a split).
        fine_dims: its cells along x, y, z (None without a split).
    """

    lower: Tensor
    cell_size: Tensor
    dims: tuple[int, int, int]
    period: Tensor
    split: float = 0.0
    fine_cell_size: Tensor | None = None
    fine_dims: tuple[int, int, int] | None = None

    @property
    def n_cells(self) -> int:
        return self.dims[0] * self.dims[1] * self.dims[2]

    @functools.cached_property
    def is_periodic(self) -> bool:
        return bool((self.period > 0).any())


def cell_grid(lower, upper, cell_size: float, *, periodic=(False, False, False), dtype=torch.float64,
              device="cpu", max_cells: int = 8_000_000) -> CellGrid:
    """Grid over the box [lower, upper] with cells of at least ``cell_size`` per axis."""
    lo = torch.as_tensor(lower, dtype=dtype, device=device)
    hi = torch.as_tensor(upper, dtype=dtype, device=device)
    extent = (hi - lo).tolist()
    dims = [max(1, int(math.floor(e / cell_size))) for e in extent]
    while dims[0] * dims[1] * dims[2] > max_cells:
        dims = [max(1, d // 2) for d in dims]
    size = torch.tensor([e / d for e, d in zip(extent, dims)], dtype=dtype, device=device)
    period = torch.tensor([e if p else 0.0 for e, p in zip(extent, periodic)], dtype=dtype, device=device)
    return CellGrid(lo, size, (dims[0], dims[1], dims[2]), period)


def with_split(grid: CellGrid, split: float, skin: float, max_cells: int = 8_000_000) -> CellGrid:
    """``grid`` with the spheres of radius up to ``split`` searched on a finer grid of their own
    (cells of at least ``2 split + skin``, same domain and periods); ``split`` 0 or a fine grid
    no finer than ``grid``: one grid. The list of pairs is the same either way."""
    if not split > 0:
        return dataclasses.replace(grid, split=0.0, fine_cell_size=None, fine_dims=None)
    upper = grid.lower + grid.cell_size * torch.tensor(grid.dims, dtype=grid.cell_size.dtype,
                                                       device=grid.cell_size.device)
    fine = cell_grid(grid.lower, upper, 2 * split + skin, periodic=[bool(p) for p in (grid.period > 0).tolist()],
                     dtype=grid.lower.dtype, device=grid.lower.device, max_cells=max_cells)
    if all(f <= d for f, d in zip(fine.dims, grid.dims)):
        return dataclasses.replace(grid, split=0.0, fine_cell_size=None, fine_dims=None)
    return dataclasses.replace(grid, split=float(split), fine_cell_size=fine.cell_size, fine_dims=fine.dims)


def search_grid(grid: CellGrid, radius: Tensor, skin: float, fraction: float = 0.6) -> CellGrid:
    """``grid`` split at ``fraction`` of the largest of ``radius`` (the active spheres' radii, m)
    when at least half of the spheres are that small (:func:`with_split`), else one grid.

    Why: a cell is one contact distance of the largest sphere wide, so a small sphere's cell
    holds many candidates far from contact. On a lab-geometry member with flat sinter (lobe
    spacing 0.3: 53,780 spheres of 2.0-8.0 mm) a rebuild took 34 ms split at 0.6 against 45 ms
    with one grid; at lobe spacing 0.15 (3.5-8.7 mm), 11.1 ms against 12.1 ms (medians of
    interleaved calls, one thread, ``scripts/bench_search.py``).
    """
    split = fraction * float(radius.max()) if fraction > 0 and radius.numel() else 0.0
    if 2 * int((radius <= split).sum()) < radius.numel():
        split = 0.0
    return with_split(grid, split, skin)


def minimum_image(d: Tensor, period: Tensor) -> Tensor:
    """Shortest periodic image of separation vectors ``d`` ``[..., 3]`` (period 0: not periodic)."""
    safe = torch.where(period > 0, period, torch.ones_like(period))
    return d - period * torch.round(d / safe)


def wrap(position: Tensor, lower: Tensor, period: Tensor) -> Tensor:
    """Map positions ``[..., 3]`` into [lower, lower + period) on periodic axes."""
    safe = torch.where(period > 0, period, torch.ones_like(period))
    wrapped = lower + torch.remainder(position - lower, safe)
    return torch.where(period > 0, wrapped, position)


_OFFSETS_CACHE: dict[tuple, Tensor] = {}


def _stencil(device) -> Tensor:
    key = (str(device),)
    if key not in _OFFSETS_CACHE:
        r = torch.arange(-1, 2, device=device)
        _OFFSETS_CACHE[key] = torch.cartesian_prod(r, r, r)  # [27, 3]
    return _OFFSETS_CACHE[key]


def find_pairs(position: Tensor, radius: Tensor, body: Tensor, active: Tensor, n_per_member: int,
               grid: CellGrid, skin: float, use_extension: bool = True, moved: Tensor | None = None,
               keep: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """All sphere pairs within contact distance plus skin.

    On CPU the candidate scan runs in the C++ kernel of :mod:`torchdem._ext` (same list,
    about two orders of magnitude faster on polydisperse packings) unless ``use_extension``
    is False or it cannot be built.

    Partial search (``moved`` given): only the pairs with at least one moved sphere are searched;
    the pairs of ``keep`` (the last build's list) whose two spheres did not move and are active
    are kept. When the spheres that did not move are where they were at that build, the list is
    the whole search's at ``position``, pair for pair.

    Args:
        position: ``[S, 3]`` flat sphere positions (S = B * Ns), m.
        radius: ``[S]`` m. body: ``[S]`` flat body index (spheres of one body never pair).
        active: ``[S]`` bool. n_per_member: Ns (flat index // Ns is the member).
        grid: the cell grid. skin: m.
        moved: ``[S]`` bool, the spheres to search for (None: all). keep: ``i, j`` ``[K]`` int64,
            the last build's list (with ``moved`` only; None: keep none).
    Returns:
        i, j: ``[P]`` int64 flat sphere indices with i < j, sorted by ``i * S + j``.
    """
    device = position.device
    S = position.shape[0]
    dims = torch.tensor(grid.dims, device=device)
    periodic_axis = grid.period > 0
    if grid.is_periodic:
        position = wrap(position, grid.lower, grid.period)
    ext = _ext.kernels_for(device, use_extension)
    if ext is not None:
        fine = (grid.fine_cell_size.tolist(), list(grid.fine_dims)) if grid.split > 0 else ([], [])
        return ext.cell_pairs(position, radius, body, active, grid.lower.tolist(), grid.cell_size.tolist(),
                              list(grid.dims), [float(p) for p in grid.period.tolist()], int(n_per_member),
                              float(skin), float(grid.split), *fine, moved, *(keep or (None, None)))
    cell = torch.floor((position - grid.lower) / grid.cell_size).long()
    cell = torch.minimum(cell.clamp_min(0), dims - 1)
    cell = torch.where(torch.isfinite(position).all(-1, keepdim=True), cell, torch.zeros_like(cell))
    member = torch.arange(S, device=device) // n_per_member
    n_cells = grid.n_cells
    linear = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    sentinel = (member.max() + 1 if S else 1) * n_cells
    hashes = torch.where(active, member * n_cells + linear, torch.full_like(linear, int(sentinel)))
    sorted_hash, order = torch.sort(hashes)

    act = torch.nonzero(active if moved is None else active & moved).squeeze(1)  # the query spheres
    nb = cell[act][:, None, :] + _stencil(device)[None, :, :]              # [A, 27, 3]
    nb = torch.where(periodic_axis, torch.remainder(nb, dims), nb)
    inside = ((nb >= 0) & (nb < dims)).all(-1)
    nb_linear = (nb[..., 0] * dims[1] + nb[..., 1]) * dims[2] + nb[..., 2]
    nb_hash = member[act][:, None] * n_cells + nb_linear
    start = torch.searchsorted(sorted_hash, nb_hash, right=False)
    end = torch.searchsorted(sorted_hash, nb_hash, right=True)
    count = torch.where(inside, end - start, torch.zeros_like(start))
    flat_count = count.reshape(-1)
    total = int(flat_count.sum())
    query = torch.repeat_interleave(act.repeat_interleave(27), flat_count)
    first = torch.repeat_interleave(start.reshape(-1), flat_count)
    offset = torch.arange(total, device=device) - torch.repeat_interleave(
        torch.cumsum(flat_count, 0) - flat_count, flat_count)
    other = order[first + offset]
    if moved is None:
        take = query < other
    else:  # a pair of two moved spheres is found from both: kept from the lower index (never itself)
        take = ~moved[other] | (query < other)
    i, j = torch.minimum(query, other)[take], torch.maximum(query, other)[take]
    take = body[i] != body[j]
    i, j = i[take], j[take]
    d = position[i] - position[j]
    if grid.is_periodic:
        d = minimum_image(d, grid.period)
    cutoff = radius[i] + radius[j] + skin
    take = d.square().sum(-1) < cutoff * cutoff
    i, j = i[take], j[take]
    if moved is not None and keep is not None:
        ki, kj = keep
        still = ~moved[ki] & ~moved[kj] & active[ki] & active[kj]
        i, j = torch.cat([i, ki[still]]), torch.cat([j, kj[still]])
    key = i * S + j
    if grid.is_periodic and min(g for g, p in zip(grid.dims, periodic_axis.tolist()) if p) < 3:
        key = torch.unique(key)  # fewer than 3 cells on a periodic axis: a cell is seen twice
        return key // S, key % S
    key, perm = torch.sort(key)
    return i[perm], j[perm]


def find_wall_pairs(position: Tensor, radius: Tensor, active: Tensor, walls: Walls, shift: Tensor,
                    wall_active: Tensor, skin: float, use_extension: bool = True, moved: Tensor | None = None,
                    keep: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """All (sphere, wall) pairs with gap below the skin.

    On CPU the scan runs in the C++ kernel of :mod:`torchdem._ext` (same list) unless
    ``use_extension`` is False or it cannot be built. Partial (``moved`` ``[S]`` bool and ``keep``,
    the last build's ``sphere, wall`` list, sorted, built with the same walls): only the moved
    spheres are tested; an active sphere that did not move keeps its pairs with live walls.

    Returns:
        sphere, wall: ``[Q]`` int64, sorted by ``sphere * W + wall``.
    """
    device = position.device
    W = walls.n
    if W == 0 or position.shape[0] == 0:
        empty = torch.zeros(0, dtype=torch.long, device=device)
        return empty, empty
    if moved is not None and keep is None:
        raise ValueError("find_wall_pairs: a partial search (moved) needs the last build's list (keep)")
    ext = _ext.kernels_for(device, use_extension)
    if ext is not None:
        return ext.wall_pairs(position, radius, active, walls.centre + shift, walls.axis_u, walls.axis_v,
                              walls.half_u, walls.half_v, wall_active, float(skin), moved, *(keep or (None, None)))
    if moved is not None:
        s, w = find_wall_pairs(position, radius, active & moved, walls, shift, wall_active, skin, False)
        ks, kw = keep
        still = ~moved[ks] & active[ks] & wall_active[kw]
        key, order = torch.sort(torch.cat([s * W + w, ks[still] * W + kw[still]]))
        return key // W, key % W
    act = torch.nonzero(active).squeeze(1)
    live = torch.nonzero(wall_active).squeeze(1)
    # every active sphere against every live wall, broadcast [A, L] (the closest-point rule of
    # walls.closest_points without gathering A x L copies of the inputs)
    x = position[act][:, None, :]
    c = (walls.centre[live] + shift[live])[None]
    u, v = walls.axis_u[live][None], walls.axis_v[live][None]
    hu, hv = walls.half_u[live][None], walls.half_v[live][None]
    d = x - c
    su = torch.minimum(torch.maximum((d * u).sum(-1), -hu), hu)
    sv = torch.minimum(torch.maximum((d * v).sum(-1), -hv), hv)
    gap = (d - su[..., None] * u - sv[..., None] * v).norm(dim=-1) - radius[act][:, None]
    a, k = torch.nonzero(gap < skin, as_tuple=True)
    return act[a], live[k]


def carry_history(old_key: Tensor, old_values: list[Tensor], new_key: Tensor,
                  use_extension: bool = True) -> list[Tensor]:
    """History of the new list: old values where the key persists, zeros elsewhere.

    On CPU the match runs in the C++ kernel of :mod:`torchdem._ext` (same result; a forward
    walk for sorted new keys instead of a searchsorted and masked copies) unless
    ``use_extension`` is False or it cannot be built.

    Args:
        old_key: ``[P_old]`` sorted unique int64. old_values: tensors ``[P_old, ...]``.
        new_key: ``[P_new]`` int64.
    Returns:
        tensors ``[P_new, ...]``.
    """
    ext = _ext.kernels_for(new_key.device, use_extension and all(v.is_floating_point() for v in old_values))
    if ext is not None:
        return list(ext.carry_history(old_key, list(old_values), new_key))
    out = [torch.zeros((new_key.shape[0],) + v.shape[1:], dtype=v.dtype, device=v.device) for v in old_values]
    if old_key.numel() == 0 or new_key.numel() == 0:
        return out
    pos = torch.searchsorted(old_key, new_key).clamp_max(old_key.shape[0] - 1)
    match = old_key[pos] == new_key
    src = pos[match]
    for o, v in zip(out, old_values):
        o[match] = v[src]
    return out


def pair_order(lo: Tensor, hi: Tensor, n: int, use_extension: bool = True) -> Tensor:
    """``[P]`` int64: the order that sorts the unique pairs ``lo, hi`` ``[P]`` (indices in ``[0, n)``)
    by ``lo``, then ``hi``, as ``torch.argsort(lo * n + hi)`` does. On CPU a counting sort in the C++
    kernel of :mod:`torchdem._ext` (same order) unless ``use_extension`` is False or it cannot be built."""
    ext = _ext.kernels_for(lo.device, use_extension)
    if ext is not None:
        return ext.pair_order(lo, hi, int(n))
    return torch.argsort(lo * n + hi)


def displacement_box(position: Tensor, reference: Tensor, members: int = 1) -> Tensor:
    """``[members, 7]``: per ensemble member, the lowest x, y, z and the highest x, y, z of its
    sphere displacements ``position - reference`` (``[members * Ns, 3]`` each), then the largest
    squared length. Non-finite displacements are left out (the blow-up guard reports them); all
    0 for a member with none finite."""
    d = (position - reference).reshape(members, -1, 3)
    d2 = d.square().sum(-1)
    bad = ~torch.isfinite(d2)
    box = torch.cat([d.masked_fill(bad[..., None], math.inf).amin(1), d.masked_fill(bad[..., None], -math.inf).amax(1),
                     d2.masked_fill(bad, 0.0).amax(1, keepdim=True)], dim=1)
    return box.masked_fill(~torch.isfinite(box), 0.0)  # a member with none finite: all 0 (no host read)


def lists_expired(displacement: Sequence[Sequence[float]], skin: float, wall_move: float | None = None) -> bool:
    """Skin criterion from a :func:`displacement_box` (one row per member): whether a contact
    may now be missing.

    Two spheres of a member not listed were at least r_i + r_j + skin apart at the build; since
    then they approached by at most |d_i - d_j|, which is at most both the diagonal of the
    member's displacement box and twice its largest displacement. A sphere not listed for a
    wall had a gap of at least the skin; it closed by at most |d_i| plus the wall's own movement
    ``wall_move`` (None: no walls). So the lists hold while, in every member, the smaller of the
    two pair bounds, and the largest displacement plus ``wall_move``, stay within the skin. This
    is never earlier than the usual rule (largest displacement above half the skin), and later
    when spheres move alike: a discharge stream falls together past resting spheres, so the
    diagonal is about the largest displacement, not twice it.
    """
    for row in displacement:
        diagonal = math.sqrt(sum((row[a + 3] - row[a]) ** 2 for a in range(3)))
        largest = math.sqrt(row[6])
        if min(diagonal, 2 * largest) > skin or (wall_move is not None and largest + wall_move > skin):
            return True
    return False


def needs_rebuild(position: Tensor, reference: Tensor, skin: float, wall_move: float | None = None,
                  members: int = 1) -> bool:
    """:func:`lists_expired` for sphere positions ``[members * Ns, 3]`` and those at the last build."""
    return lists_expired(displacement_box(position, reference, members).tolist(), skin, wall_move)
