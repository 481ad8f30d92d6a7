"""The rained fill's random sequential addition (torchdem/fill.py) and the clump template cache.

- Rounds of placement are tested several at a time, the random stream rewound to just after
  the round that placed a body: the fill is the same, bit for bit, as one round at a time
  (``_BATCH_SPHERES = 1``), on a periodic slice and between walls, by bounding spheres and by
  lobes, at a loose fraction crowded enough that slabs are retried (the rounds that place
  nothing are where the batches act).
- No two placed bodies overlap: every pair of spheres of different bodies is at least the gap
  apart (minimum images on the periodic slice).
- ``principal_template`` hands out copies of its cached result: mutating one changes no later one.
"""
import numpy as np
import pytest
from scipy.spatial import cKDTree

import torchdem.fill as fill
from torchdem.clumps import ClumpTemplate, principal_template
from torchdem.fill import rain_positions, rotate
from torchdem.geometry import DrawDownGeometry

GAP = 0.0002


def _particles(n: int, seed: int):
    """``n`` bodies in two layers: spheres of 10-14 mm and flat trilobes of 12 mm sieve size."""
    rng = np.random.default_rng(seed)
    radius = rng.uniform(0.005, 0.007, n)
    layer = (np.arange(n) >= n // 2).astype(int)
    offsets = np.zeros((n, 3, 3))
    lobe_r = np.repeat(radius[:, None], 3, 1)
    t = 2 * np.pi * np.arange(3) / 3
    tri = layer == 1
    offsets[tri] = 0.3 * 0.012 * np.stack([np.cos(t), np.sin(t), np.zeros(3)], 1)
    lobe_r[tri] = 0.2 * 0.012
    radius[tri] = 0.5 * 0.012
    return radius, layer, 4 / 3 * np.pi * radius ** 3, (offsets, lobe_r)


def _min_gap(fill_, lobes, period):
    offsets, lobe_r = lobes
    x = (fill_.position[:, None, :] + rotate(fill_.orientation, offsets)).reshape(-1, 3)
    r, body = lobe_r.reshape(-1), np.repeat(np.arange(offsets.shape[0]), offsets.shape[1])
    a, b = cKDTree(x).query_pairs(2 * r.max() + 2 * GAP + (period or 0), output_type="ndarray").T
    d = x[a] - x[b]
    if period:
        d[:, 1] -= period * np.round(d[:, 1] / period)
    other = body[a] != body[b]
    return float((np.linalg.norm(d, axis=1) - r[a] - r[b])[other].min())


@pytest.mark.parametrize("slice_walls", [False, True], ids=["periodic", "walled"])
@pytest.mark.parametrize("packing", ["bounding", "lobes"])
def test_batched_rounds_place_the_same_fill_as_one_round_at_a_time(monkeypatch, slice_walls, packing):
    geometry = DrawDownGeometry(slice_depth=0.03, slice_walls=slice_walls)
    radius, layer, volume, lobes = _particles(300, seed=1)
    kw = dict(loose_fraction=0.33, lobes=lobes if packing == "lobes" else None, max_top=10.0)
    calls = []
    place = fill._place_slab
    monkeypatch.setattr(fill, "_place_slab", lambda *a, **k: calls.append(1) or place(*a, **k))
    batched = rain_positions(radius, layer, volume, geometry, seed=7, **kw)
    slabs = len(calls)
    monkeypatch.setattr(fill, "_BATCH_SPHERES", 1)
    single = rain_positions(radius, layer, volume, geometry, seed=7, **kw)
    assert slabs > 2, "no slab was retried: the case does not reach the rounds that place nothing"
    np.testing.assert_array_equal(batched.position, single.position)
    np.testing.assert_array_equal(batched.orientation, single.orientation)
    assert batched.layer_tops == single.layer_tops
    if packing == "lobes":
        assert _min_gap(batched, lobes, None if slice_walls else geometry.simulated_depth) >= GAP * (1 - 1e-9)


def test_principal_template_hands_out_copies_of_its_cached_result():
    t = ClumpTemplate("tri", np.array([[0.3, 0.0, 0.0], [-0.15, 0.26, 0.0], [-0.15, -0.26, 0.0]]), np.full(3, 0.2))
    first = principal_template(t)
    volume, offsets = first.volume, first.template.offsets.copy()
    first.template.offsets[:] = 0.0
    first.principal_inertia[:] = -1.0
    again = principal_template(t)
    assert again.volume == volume
    np.testing.assert_array_equal(again.template.offsets, offsets)
    assert (again.principal_inertia > 0).all()
    # three disjoint lobes of radius 0.2: the exact volume of three spheres within the quadrature's 0.1 %
    assert again.volume == pytest.approx(3 * 4 / 3 * np.pi * 0.2 ** 3, rel=1e-3)
