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


class FillOverflowError(ConfigError):
    """The loose stack of a fill would rise above the height it may reach."""


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
                depth: float, periodic: bool, rng: np.random.Generator, rounds: int = 200,
                lobe_offset: np.ndarray | None = None, lobe_radius: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Vectorised random sequential addition of bodies (sorted largest first) in the box [lo, hi]
    of allowed centres (per body rows ``lo``/``hi`` ``[n, 3]``), avoiding the placed spheres.

    A body is its bounding sphere of ``radius`` unless ``lobe_offset`` ``[n, K, 3]`` (world-frame
    offsets of its spheres from its centre) and ``lobe_radius`` ``[n, K]`` are given; then its
    spheres must overlap nothing. Returns (body positions ``[n, 3]``, sphere centres ``[n K, 3]``,
    sphere radii ``[n K]``), or None if some bodies found no room."""
    n = radius.shape[0]
    if lobe_offset is None:
        lobe_offset, lobe_radius = np.zeros((n, 1, 3)), radius[:, None]
    pos = np.full((n, 3), np.nan)
    P, PR = placed.copy(), placed_r.copy()
    # Largest first, in chunks: large bodies need empty space, small ones fill the gaps.
    for chunk in np.array_split(np.arange(n), max(1, n // 64)):
        P, PR, left = _place_chunk(chunk, lobe_offset, lobe_radius, lo, hi, P, PR, pos, depth, periodic, rng, rounds)
        if left:
            return None
    return pos, (pos[:, None, :] + lobe_offset).reshape(-1, 3), lobe_radius.reshape(-1)


def _overlaps_placed(tree: cKDTree, points: np.ndarray, radii: np.ndarray, spheres: np.ndarray, r: np.ndarray,
                     r_max: float, k: int = 16) -> np.ndarray:
    """Indices of ``spheres`` (radii ``r``) that overlap a sphere of ``points`` (``radii``, in
    ``tree``): the ``k`` nearest within reach are tested at once; a sphere with ``k`` of them
    in reach is tested against everything in reach."""
    reach = r + r_max
    _, idx = tree.query(spheres, k=min(k, points.shape[0]), distance_upper_bound=float(reach.max()))
    idx = idx.reshape(spheres.shape[0], -1)
    found = idx < points.shape[0]
    safe = np.where(found, idx, 0)
    d = np.linalg.norm(points[safe] - spheres[:, None, :], axis=2)
    hit = (found & (d < r[:, None] + radii[safe])).any(1)
    for a in np.flatnonzero(found[:, -1] & ~hit):  # k neighbours in reach: maybe more beyond them
        h = np.asarray(tree.query_ball_point(spheres[a], reach[a]), dtype=int)
        if h.size and (np.linalg.norm(points[h] - spheres[a], axis=1) < r[a] + radii[h]).any():
            hit[a] = True
    return np.flatnonzero(hit)


#: Spheres tested per batch of rounds in :func:`_place_chunk` (bounds its temporaries).
_BATCH_SPHERES = 1024


def _place_chunk(todo, lobe_offset, lobe_radius, lo, hi, P, PR, pos, depth, periodic, rng, rounds):
    """Rounds of random sequential addition of the bodies ``todo`` (at most ``rounds``): each
    round draws a candidate centre for every body left, keeps those that overlap nothing placed
    and no earlier candidate, and records them in ``pos``. Returns (placed spheres, their radii,
    bodies left).

    Several rounds are drawn and tested at once: until a round places a body the placed spheres
    do not change, so the rounds before the first that places one are only tested, and the random
    stream is then rewound to just after that round. The result is the same, bit for bit, as one
    round at a time; a crowded chunk whose last bodies need a hundred rounds costs a few batches."""
    K = lobe_offset.shape[1]
    # spheres placed before this chunk: one search tree for all rounds; those the chunk places
    # (at most 64 bodies): a tree remade whenever a round places more
    if P.shape[0]:
        old_imgs, old_src = _with_images(P, depth, periodic)
        old_tree, old_r, old_max = cKDTree(old_imgs), PR[old_src], PR.max()
    new_P, new_R = [np.zeros((0, 3))], [np.zeros(0)]
    fresh_imgs = fresh_r = None  # images of the spheres this chunk placed, remade when it places more
    left, span = rounds, 1  # span: rounds to try at once, from how long the last placement took
    while left > 0 and todo.size:
        m = todo.size
        batch = max(1, min(left, span, _BATCH_SPHERES // (m * K)))
        state = rng.bit_generator.state if batch > 1 else None
        cand = lo[todo] + (hi[todo] - lo[todo]) * rng.random((batch, m, 3))  # [batch, m, 3]
        spheres = (cand[:, :, None, :] + lobe_offset[todo]).reshape(-1, 3)  # round t body a: rows (t m + a) K ..
        r = np.tile(lobe_radius[todo].reshape(-1), batch)
        owner = np.repeat(np.arange(batch * m), K)
        ok = np.ones(batch * m, dtype=bool)
        if P.shape[0]:
            hit = _overlaps_placed(old_tree, old_imgs, old_r, spheres, r, old_max)
            ok &= ~np.bincount(owner[hit], minlength=batch * m).astype(bool)
        if fresh_imgs is None and len(new_P) > 1:
            fresh_imgs, src = _with_images(np.concatenate(new_P), depth, periodic)
            fresh_r = np.concatenate(new_R)[src]
            fresh_tree = cKDTree(fresh_imgs)
        if fresh_imgs is not None:
            test = np.flatnonzero(ok[owner])
            if test.size:
                hit = test[_overlaps_placed(fresh_tree, fresh_imgs, fresh_r, spheres[test], r[test],
                                            float(fresh_r.max()))]
                ok &= ~np.bincount(owner[hit], minlength=batch * m).astype(bool)
        ok = ok.reshape(batch, m)
        placing = np.flatnonzero(ok.any(1))
        t = int(placing[0]) if placing.size else batch - 1  # the round this batch ends with
        if state is not None and t < batch - 1:  # rewind the stream to just after round t
            rng.bit_generator.state = state
            rng.random((t + 1, m, 3))
        left -= t + 1
        span = t + 1 if placing.size else 4 * batch
        if not placing.size:
            continue
        ok, cand = ok[t], cand[t]
        spheres, r, owner = spheres[t * m * K:(t + 1) * m * K], r[:m * K], owner[:m * K]
        # conflicts among this round's candidates: the earlier (larger) one wins
        good = np.flatnonzero(ok[owner])
        if np.unique(owner[good]).size > 1:
            imgs, src = _with_images(spheres[good], depth, periodic)
            rg, og = r[good], owner[good]
            a, b = cKDTree(imgs).query_pairs(2 * rg.max(), output_type="ndarray").T
            ia, ib = src[a], src[b]
            clash = (og[ia] != og[ib]) & (np.linalg.norm(imgs[a] - imgs[b], axis=1) < rg[ia] + rg[ib])
            ok[np.maximum(og[ia], og[ib])[clash]] = False
        acc = np.flatnonzero(ok)
        pos[todo[acc]] = cand[acc]
        taken = ok[owner]
        new_P.append(spheres[taken])
        new_R.append(r[taken])
        fresh_imgs = None
        todo = todo[~ok]
    return np.concatenate([P, *new_P]), np.concatenate([PR, *new_R]), todo.size


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors ``v`` ``[N, K, 3]`` by unit quaternions ``q`` ``[N, 4]`` (w, x, y, z)."""
    w, u = q[:, None, :1], q[:, None, 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def rain_positions(bounding_radius: np.ndarray, layer: np.ndarray, volume: np.ndarray,
                   geometry: DrawDownGeometry, seed: int, loose_fraction: float = 0.3,
                   gap: float = 0.0002, max_top: float | None = None,
                   lobes: tuple[np.ndarray, np.ndarray] | None = None) -> RainedFill:
    """Place particles layer by layer into the upper box (see the module docstring).

    Args:
        bounding_radius: ``[N]`` radius of each particle's enclosing sphere, m.
        layer: ``[N]`` layer index (0 = bottom). volume: ``[N]`` solid volume, m^3.
        geometry: the boxes. seed: random seed. loose_fraction: volume fraction of the loose
            slabs (of the bounding spheres, or of the lobes with ``lobes``). gap: clearance
            between bounding spheres (lobes), m.
        max_top: highest z the loose stack may reach (default: the top of the upper box
            walls); a stack above the walls needs the fill extension walls of
            :meth:`DrawDownGeometry.walls` (``fill_top``).
        lobes: pack by the particles' own spheres instead of their bounding spheres:
            (offsets ``[N, K, 3]`` of each particle's spheres from its centre in its own frame,
            m; radii ``[N, K]``, m; pad a particle with fewer spheres by repeating one). The
            orientations are drawn first, so each particle is placed as it will lie. A flat clump
            takes the room of its lobes, not of its bounding sphere (a trilobe of lobe spacing
            0.3 holds a fifth of its bounding sphere's volume).
    """
    if not 0.05 <= loose_fraction <= 0.375:
        raise ConfigError(f"fill: loose_fraction = {loose_fraction}; expected [0.05, 0.375] "
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
    orientation = None
    if lobes is not None:
        offset, lobe_r = (np.asarray(a, dtype=float) for a in lobes)
        if offset.ndim != 3 or offset.shape[0] != N or offset.shape[2] != 3 or lobe_r.shape != offset.shape[:2]:
            raise ConfigError(f"fill: lobes must be offsets [N = {N}, K, 3] and radii [N, K]; got {offset.shape} "
                              f"and {lobe_r.shape}")
        orientation = random_quaternions(N, rng)
        offset = rotate(orientation, offset)
        lobe_r = lobe_r + gap / 2
        ext_lo, ext_hi = (offset - lobe_r[..., None]).min(1), (offset + lobe_r[..., None]).max(1)  # [N, 3]
    pos = np.zeros((N, 3))
    z0 = geometry.upper_bottom_z
    tops = []
    placed = np.zeros((0, 3))
    placed_r = np.zeros(0)
    for k in np.unique(layer):
        members = np.flatnonzero(layer == k)
        members = members[np.argsort(-bounding_radius[members], kind="stable")]
        R = bounding_radius[members] + gap / 2
        if lobes is None:
            lo_ext, hi_ext, shape = -np.repeat(R[:, None], 3, 1), np.repeat(R[:, None], 3, 1), {}
            height = float((4 / 3 * np.pi * R ** 3).sum()) / (loose_fraction * W * D)
        else:
            lo_ext, hi_ext = ext_lo[members], ext_hi[members]
            shape = {"lobe_offset": offset[members], "lobe_radius": lobe_r[members]}
            height = float((4 / 3 * np.pi * lobe_r[members] ** 3).sum()) / (loose_fraction * W * D)
        # Only spheres reaching above the slab's floor z0 can touch its candidates (every sphere
        # of a candidate lies above z0): the layers below end at z0, so they are left out of the
        # overlap search (same positions, bit for bit; the search had grown with every layer placed).
        reach = placed[:, 2] + placed_r > z0
        while True:
            lo = np.stack([-W / 2 - lo_ext[:, 0], np.zeros_like(R) if periodic else -lo_ext[:, 1], z0 - lo_ext[:, 2]], 1)
            hi = np.stack([W / 2 - hi_ext[:, 0], np.full_like(R, D) if periodic else D - hi_ext[:, 1],
                           np.maximum(z0 + height - hi_ext[:, 2], z0 - lo_ext[:, 2])], 1)
            got = _place_slab(R, lo, hi, placed[reach], placed_r[reach], D, periodic, rng, **shape)
            if got is not None:
                break
            height *= 1.1  # too crowded: give the slab more room and place the layer again
        body, centres, radii = got
        pos[members] = body
        placed = np.concatenate([placed, centres])
        placed_r = np.concatenate([placed_r, radii])
        z0 = float((centres[:, 2] + radii).max())
        tops.append(z0)
    top = z0 if N else geometry.upper_bottom_z
    limit = geometry.upper_bottom_z + geometry.upper_height if max_top is None else max_top
    if top > limit:
        raise FillOverflowError(f"fill: the loose stack reaches z = {top:.3f} m, above the allowed z = {limit:.3f} m; "
                          "raise geometry.upper_height, raise run.loose_fraction, pack by lobes "
                          "(run.fill_packing: lobes) or reduce the fill mass")
    return RainedFill(pos, orientation if orientation is not None else random_quaternions(N, rng), top, tuple(tops))


def rain_to_fit(bounding_radius: np.ndarray, layer: np.ndarray, volume: np.ndarray, geometry: DrawDownGeometry,
                seed: int, loose_fraction: float = 0.3, *, max_top: float | None = None,
                lobes: tuple[np.ndarray, np.ndarray] | None = None, densest: float = 0.375,
                step: float = 0.025) -> tuple[RainedFill, float]:
    """:func:`rain_positions` at ``loose_fraction``, and where its loose stack would rise above
    ``max_top``, again at loose fractions ``step`` denser, up to ``densest``; returns the fill and
    the fraction it used.

    Why: a draw down test fills a fixed mass, so lighter particles (a calibrated density at the low
    end of its range) and flat clumps take more room; the lab campaign's corner of lobe spacing 0.3
    and densities at 90 % stacked to z = 2.02 m against the 1.85 m the lab geometry allows, and its
    75-25 condition still to 1.89 m at 0.35 (1.82 m at 0.375). A fill
    that fits at ``loose_fraction`` is the same, bit for bit, as before; only a fill that would
    have failed is placed denser (and settles from a lower stack). Raises
    :class:`FillOverflowError` when even ``densest`` overflows.
    """
    if not step > 0:
        raise ConfigError(f"fill: step = {step}; expected a loose-fraction step > 0")
    fraction = loose_fraction
    while True:
        try:
            return rain_positions(bounding_radius, layer, volume, geometry, seed, fraction, max_top=max_top,
                                  lobes=lobes), fraction
        except FillOverflowError as err:
            if fraction >= densest:
                raise FillOverflowError(f"{err} (loose fractions {loose_fraction:g} to {fraction:g} tried)") from None
            fraction = min(densest, round(fraction + step, 10))
