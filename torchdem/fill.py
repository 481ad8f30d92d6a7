"""Filling the upper box layer by layer: a loose, non-overlapping rain of particles.

Contract: :func:`rain_positions` places every particle of a sampled fill (bottom layer first)
above the closed gate. Each layer occupies its own horizontal slab of the box, stacked in
layer order; inside a slab, particles are placed by random sequential addition of their
bounding spheres (largest first, each at a uniformly random position, retried until it
overlaps nothing already placed) at a target solid fraction of the bounding spheres
(``loose_fraction``, default 0.3, below the 0.38 jamming limit of random sequential addition so
placement always succeeds). Positions are uniform inside the slab, so the largest-first order
creates no size stratification. Bounding spheres never overlap, so the DEM starts without
overlaps; gravity then settles the loose stack (the "rain and settle" stage). Orientations of
clumps are uniformly random. Everything follows from the seed.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from torchdem.errors import ConfigError
from torchdem.geometry import DrawDownGeometry


@dataclass(frozen=True)
class RainedFill:
    """Initial pose of every particle.

    Attributes:
        position: ``[N, 3]`` centres, m. orientation: ``[N, 4]`` unit quaternions (w, x, y, z).
        top: height of the loose stack's highest point, m.
        layer_tops: top of each layer's slab, m.
    """

    position: np.ndarray
    orientation: np.ndarray
    top: float
    layer_tops: tuple[float, ...]


def random_quaternions(n: int, rng: np.random.Generator) -> np.ndarray:
    """Uniformly distributed unit quaternions ``[n, 4]`` (Shoemake 1992)."""
    u1, u2, u3 = rng.random((3, n))
    a, b = np.sqrt(1 - u1), np.sqrt(u1)
    return np.stack([a * np.sin(2 * np.pi * u2), a * np.cos(2 * np.pi * u2),
                     b * np.sin(2 * np.pi * u3), b * np.cos(2 * np.pi * u3)], 1)


def _with_images(points: np.ndarray, depth: float, periodic: bool) -> tuple[np.ndarray, np.ndarray]:
    """Points plus their images at y +/- depth (periodic slices); returns (points, source index)."""
    idx = np.arange(points.shape[0])
    if not periodic:
        return points, idx
    up, down = points.copy(), points.copy()
    up[:, 1] += depth
    down[:, 1] -= depth
    return np.concatenate([points, up, down]), np.concatenate([idx, idx, idx])


def _place_slab(radius: np.ndarray, lo: np.ndarray, hi: np.ndarray, placed: np.ndarray, placed_r: np.ndarray,
                depth: float, periodic: bool, rng: np.random.Generator, rounds: int = 200) -> np.ndarray | None:
    """Vectorised random sequential addition of spheres (radii sorted descending) in the box
    [lo, hi] of allowed centres (per particle rows ``lo``/``hi`` ``[n, 3]``), avoiding the placed
    spheres. Returns positions ``[n, 3]`` or None if some particles found no room."""
    n = radius.shape[0]
    pos = np.full((n, 3), np.nan)
    P, PR = placed.copy(), placed_r.copy()
    # Largest first, in chunks: large spheres need empty space, small ones fill the gaps.
    for chunk in np.array_split(np.arange(n), max(1, n // 64)):
        P, PR, left = _place_chunk(chunk, radius, lo, hi, P, PR, pos, depth, periodic, rng, rounds)
        if left:
            return None
    return pos


def _place_chunk(todo, radius, lo, hi, P, PR, pos, depth, periodic, rng, rounds):
    for _ in range(rounds):
        if todo.size == 0:
            return P, PR, 0
        cand = lo[todo] + (hi[todo] - lo[todo]) * rng.random((todo.size, 3))
        r = radius[todo]
        ok = np.ones(todo.size, dtype=bool)
        if P.shape[0]:
            imgs, src = _with_images(P, depth, periodic)
            tree = cKDTree(imgs)
            hits = tree.query_ball_point(cand, r + PR.max())
            for a, h in enumerate(hits):
                if h:
                    h = np.asarray(h)
                    d = np.linalg.norm(imgs[h] - cand[a], axis=1)
                    if (d < r[a] + PR[src[h]]).any():
                        ok[a] = False
        # conflicts among this round's candidates: the earlier (larger) one wins
        good = np.flatnonzero(ok)
        if good.size > 1:
            imgs, src = _with_images(cand[good], depth, periodic)
            tree = cKDTree(imgs)
            for a, b in tree.query_pairs(2 * r[good].max(), output_type="ndarray"):
                ia, ib = src[a], src[b]
                if ia == ib:
                    continue
                if np.linalg.norm(imgs[a] - imgs[b]) < r[good][ia] + r[good][ib]:
                    ok[good[max(ia, ib)]] = False
        acc = np.flatnonzero(ok)
        pos[todo[acc]] = cand[acc]
        P = np.concatenate([P, cand[acc]])
        PR = np.concatenate([PR, r[acc]])
        todo = todo[~ok]
    return P, PR, todo.size


def rain_positions(bounding_radius: np.ndarray, layer: np.ndarray, volume: np.ndarray,
                   geometry: DrawDownGeometry, seed: int, loose_fraction: float = 0.3,
                   gap: float = 0.0002, max_top: float | None = None) -> RainedFill:
    """Place particles layer by layer into the upper box (see the module docstring).

    Args:
        bounding_radius: ``[N]`` radius of each particle's enclosing sphere, m.
        layer: ``[N]`` layer index (0 = bottom). volume: ``[N]`` solid volume, m^3.
        geometry: the boxes. seed: random seed. loose_fraction: bounding-sphere volume
            fraction of the loose slabs. gap: clearance between bounding spheres, m.
        max_top: highest z the loose stack may reach (default: the top of the upper box
            walls); a stack above the walls needs the fill extension walls of
            :meth:`DrawDownGeometry.walls` (``fill_top``).
    """
    if not 0.05 <= loose_fraction <= 0.35:
        raise ConfigError(f"fill: loose_fraction = {loose_fraction}; expected [0.05, 0.35] "
                          "(random sequential addition jams near 0.38)")
    rng = np.random.default_rng(seed)
    W, D = geometry.upper_width, geometry.simulated_depth
    periodic = geometry.is_slice
    N = bounding_radius.shape[0]
    if N and 2 * float(bounding_radius.max()) >= W:
        raise ConfigError(f"fill: a particle of diameter {2 * float(bounding_radius.max()):.4g} m does not fit "
                          f"the upper box ({W} m wide)")
    if N and not periodic and 2 * float(bounding_radius.max()) >= D:
        raise ConfigError(f"fill: a particle of diameter {2 * float(bounding_radius.max()):.4g} m does not fit "
                          f"the box depth ({D} m)")
    pos = np.zeros((N, 3))
    z0 = geometry.upper_bottom_z
    tops = []
    placed = np.zeros((0, 3))
    placed_r = np.zeros(0)
    for k in np.unique(layer):
        members = np.flatnonzero(layer == k)
        members = members[np.argsort(-bounding_radius[members], kind="stable")]
        R = bounding_radius[members] + gap / 2
        height = float((4 / 3 * np.pi * R ** 3).sum()) / (loose_fraction * W * D)
        # Only spheres reaching above the slab's floor z0 can touch its candidates (centres at
        # z >= z0 + R): the layers below end at z0, so they are left out of the overlap search
        # (same positions, bit for bit; the search had grown with every layer placed).
        reach = placed[:, 2] + placed_r > z0
        while True:
            lo = np.stack([-W / 2 + R, np.zeros_like(R) if periodic else R, z0 + R], 1)
            hi = np.stack([W / 2 - R, np.full_like(R, D) if periodic else D - R, np.maximum(z0 + height - R, z0 + R)], 1)
            got = _place_slab(R, lo, hi, placed[reach], placed_r[reach], D, periodic, rng)
            if got is not None:
                break
            height *= 1.1  # too crowded: give the slab more room and place the layer again
        pos[members] = got
        placed = np.concatenate([placed, got])
        placed_r = np.concatenate([placed_r, R])
        z0 = float((got[:, 2] + R).max())
        tops.append(z0)
    top = z0 if N else geometry.upper_bottom_z
    limit = geometry.upper_bottom_z + geometry.upper_height if max_top is None else max_top
    if top > limit:
        raise ConfigError(f"fill: the loose stack reaches z = {top:.3f} m, above the allowed z = {limit:.3f} m; "
                          "raise geometry.upper_height, raise run.loose_fraction or reduce the fill mass")
    return RainedFill(pos, random_quaternions(N, rng), top, tuple(tops))
