"""The sorted cell list equals an all-pairs oracle, before and after rebuilds.

Oracle: every pair of spheres of the same member, different bodies, with centre distance
below r_i + r_j + skin, found by brute force over all pairs. The cell list must return
exactly that set (no missed pair, no extra pair), for random polydisperse packings,
including spheres outside the domain box (clamped into border cells) and padding spheres.
"""
import dataclasses

import pytest
import torch

from torchdem import _ext
from torchdem.neighbors import carry_history, cell_grid, find_pairs, needs_rebuild, pair_order

F64 = torch.float64


def _oracle(pos, radius, body, active, Ns, skin):
    S = pos.shape[0]
    i, j = torch.triu_indices(S, S, offset=1)
    same_member = (i // Ns) == (j // Ns)
    close = (pos[i] - pos[j]).norm(dim=-1) < radius[i] + radius[j] + skin
    keep = same_member & close & (body[i] != body[j]) & active[i] & active[j]
    return set(zip(i[keep].tolist(), j[keep].tolist()))


def _random_packing(seed, B=3, Ns=300, box=0.08):
    g = torch.Generator().manual_seed(seed)
    pos = torch.rand(B * Ns, 3, generator=g, dtype=F64) * box
    pos[:5] -= 0.02  # a few spheres outside the domain
    radius = 0.002 + 0.004 * torch.rand(B * Ns, generator=g, dtype=F64)
    body = torch.arange(B * Ns)
    body[1::7] = body[0::7][: body[1::7].shape[0]]  # some spheres share a body (clumps)
    active = torch.rand(B * Ns, generator=g) > 0.05
    return pos, radius, body, active, Ns


def test_cell_list_equals_all_pairs_oracle_on_random_polydisperse_packings():
    for seed in range(4):
        pos, radius, body, active, Ns = _random_packing(seed)
        skin = 0.001
        grid = cell_grid((0, 0, 0), (0.08, 0.08, 0.08), 2 * float(radius.max()) + skin, dtype=F64)
        i, j = find_pairs(pos, radius, body, active, Ns, grid, skin)
        found = set(zip(i.tolist(), j.tolist()))
        assert len(found) == i.shape[0]  # no duplicates
        assert found == _oracle(pos, radius, body, active, Ns, skin)
        keys = i * pos.shape[0] + j
        assert bool((keys[1:] > keys[:-1]).all())  # sorted keys for history carry-over


def test_cell_list_matches_oracle_after_particles_move_and_list_is_rebuilt():
    pos, radius, body, active, Ns = _random_packing(7)
    skin = 0.0015
    grid = cell_grid((0, 0, 0), (0.08, 0.08, 0.08), 2 * float(radius.max()) + skin, dtype=F64)
    g = torch.Generator().manual_seed(1)
    reference = pos.clone()
    for _ in range(5):
        pos = pos + 0.0004 * torch.randn(pos.shape, generator=g, dtype=F64)
        if needs_rebuild(pos, reference, skin):
            reference = pos.clone()
        i, j = find_pairs(reference, radius, body, active, Ns, grid, skin)
        listed = set(zip(i.tolist(), j.tolist()))
        # Skin guarantee: every pair touching *now* is in the list built at `reference`.
        touching = _oracle(pos, radius, body, active, Ns, 0.0)
        assert touching <= listed


def test_skin_criterion_waits_for_spheres_moving_alike_and_never_misses_a_contact():
    """The lists hold while the displacement box's diagonal stays within the skin: a rigid
    shift of three skins keeps them, so does a block of spheres falling 0.9 skin past resting
    ones (the rule of half the skin would have rebuilt at 0.5); 1.1 skin expires them. Every
    pair touching when they hold was listed at the build. A wall's movement adds to the
    largest displacement."""
    from torchdem.neighbors import displacement_box, lists_expired

    pos, radius, body, active, Ns = _random_packing(7)
    skin = 0.0015
    grid = cell_grid((0, 0, 0), (0.08, 0.08, 0.08), 2 * float(radius.max()) + skin, dtype=F64)
    i, j = find_pairs(pos, radius, body, active, Ns, grid, skin)
    listed = set(zip(i.tolist(), j.tolist()))
    g = torch.Generator().manual_seed(2)
    shift = torch.tensor([0.5, -1.0, 2.7], dtype=F64) * skin  # |shift| = 2.9 skin
    jitter = 0.1 * skin * (2 * torch.rand(pos.shape, generator=g, dtype=F64) - 1)
    falling = (pos[:, 0] > 0.04)[:, None] * torch.tensor([0.0, 0.0, -1.0], dtype=F64)
    cases = [(pos + shift + jitter, False), (pos + 0.9 * skin * falling, False), (pos + 1.1 * skin * falling, True)]
    for moved, expired in cases:
        assert needs_rebuild(moved, pos, skin) == expired
        if not expired:
            assert _oracle(moved, radius, body, active, Ns, 0.0) <= listed
    touching = _oracle(pos + 0.9 * skin * falling, radius, body, active, Ns, 0.0)
    assert touching - _oracle(pos, radius, body, active, Ns, 0.0)  # the fall made new contacts
    assert needs_rebuild(pos + shift, pos, skin, wall_move=0.0)  # with walls, a shift may reach one
    box = displacement_box(pos + 0.6 * skin * falling, pos).tolist()
    assert box[0][2] == pytest.approx(-0.6 * skin) and box[0][5] == 0.0
    assert box[0][6] == pytest.approx((0.6 * skin) ** 2)
    assert not lists_expired(box, skin, 0.3 * skin) and lists_expired(box, skin, 0.5 * skin)
    nan = pos.clone()
    nan[3] = float("nan")
    assert displacement_box(nan, pos).tolist() == [[0.0] * 7]  # non-finite left out
    assert displacement_box(nan + shift, pos)[0, :6].tolist() == pytest.approx(2 * shift.tolist())
    # spheres spread in six directions by 0.4 skin: a box diagonal of 1.39 skin, but no two of them
    # approached by more than 0.8 skin (twice the largest), so the lists hold, as by the half-skin rule
    spread = torch.zeros_like(pos)
    for k, direction in enumerate(torch.eye(3, dtype=F64).repeat_interleave(2, 0) * torch.tensor([1.0, -1.0] * 3,
                                                                                                   dtype=F64)[:, None]):
        spread[k::6] = 0.4 * skin * direction
    assert not needs_rebuild(pos + spread, pos, skin)
    assert _oracle(pos + spread, radius, body, active, Ns, 0.0) <= listed
    # members apart: one member's shift and another's fall do not add up (pairs never cross members)
    S = pos.shape[0] - pos.shape[0] % 2
    apart = torch.cat([shift.expand(S // 2, 3), 0.9 * skin * falling[S // 2:S]])
    assert needs_rebuild(pos[:S] + apart, pos[:S], skin, members=1)
    assert not needs_rebuild(pos[:S] + apart, pos[:S], skin, members=2)


def test_simulation_lists_hold_every_touching_pair_while_spheres_fall_onto_resting_ones():
    """End to end with the step's criterion: two members, each a block of spheres falling at
    2.5 m/s onto a bed of resting ones (bouncing back up), a floor below. At every step every
    pair touching now is listed and every sphere touching the floor has its wall contact."""
    from conftest import simulation, two_material_table
    from torchdem.integrate import sphere_positions
    from torchdem.walls import WallSpec

    R = 0.004
    mats, table = two_material_table(2, dict(mu_s=0.5, mu_r=0.05, restitution=0.6))
    bed = [(0.01 + 0.0088 * a, 0.01 + 0.0088 * b, 0.0045) for a in range(9) for b in range(3)]
    block = [(0.014 + 0.0092 * a, 0.012 + 0.0092 * b, 0.02 + 0.0092 * c) for a in range(8) for b in range(2)
             for c in range(3)]
    pos = torch.tensor([bed + block, [(x + 0.002, y, z) for x, y, z in bed + block]], dtype=F64)
    vel = torch.zeros_like(pos)
    vel[:, len(bed):, 2] = -2.5
    floor = WallSpec("floor", (0.05, 0.02, 0.0), (0, 0, 1), (1, 0, 0), float("inf"), float("inf"), "steel")
    sim = simulation(pos, torch.full(pos.shape[:2], R, dtype=F64), mats, table, velocity=vel, gravity=(0, 0, -9.81),
                     walls=[floor], time_step_fraction=0.1, domain=((0, 0, -0.01), (0.1, 0.04, 0.06)))
    system = sim.system
    Ns = system.n_spheres
    radius = system.sphere_radius.reshape(-1)
    body = system.sphere_body_flat
    active = torch.ones(2 * Ns, dtype=torch.bool)
    steps = int(0.02 / system.dt)
    for _ in range(steps):
        sim.advance(1)
        xs = sphere_positions(system, sim.state.bodies)
        listed = set(zip(sim.state.pairs.i.tolist(), sim.state.pairs.j.tolist()))
        assert _oracle(xs, radius, body, active, Ns, 0.0) <= listed
        on_floor = set(torch.nonzero(xs[:, 2] < radius).squeeze(1).tolist())
        assert on_floor <= set(sim.state.walls.sphere.tolist())
    v = sim.state.bodies.velocity
    assert float(v[:, len(bed):, 2].max()) > 0.1  # some bounced back up
    assert sim.state.rebuilds < steps / 3


@pytest.mark.parametrize("use_extension", [True, False])
def test_history_is_carried_for_persisting_pairs_and_zero_for_new_ones(use_extension):
    old_key = torch.tensor([3, 8, 15, 40])
    old = torch.arange(12, dtype=F64).reshape(4, 3)
    new_key = torch.tensor([1, 8, 40, 41])
    (new,) = carry_history(old_key, [old], new_key, use_extension=use_extension)
    assert torch.equal(new[0], torch.zeros(3, dtype=F64))
    assert torch.equal(new[1], old[1])
    assert torch.equal(new[2], old[3])
    assert torch.equal(new[3], torch.zeros(3, dtype=F64))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_history_kernel_equals_the_torch_path_on_sorted_unsorted_and_empty_lists(dtype):
    g = torch.Generator().manual_seed(3)
    old_key = torch.unique(torch.randint(0, 200_000, (30_000,), generator=g))
    values = [torch.randn(old_key.shape[0], 3, generator=g, dtype=dtype),
              torch.randn(old_key.shape[0], 3, generator=g, dtype=dtype)]
    persisting = old_key[torch.randperm(old_key.shape[0], generator=g)[:20_000]]
    sorted_new = torch.unique(torch.cat([persisting, torch.randint(0, 200_000, (15_000,), generator=g)]))
    for new_key in (sorted_new, sorted_new[torch.randperm(sorted_new.shape[0], generator=g)],
                    sorted_new[:0], sorted_new[-1:] + 10**9):
        fast = carry_history(old_key, values, new_key)
        slow = carry_history(old_key, values, new_key, use_extension=False)
        assert all(torch.equal(a, b) and a.dtype == dtype for a, b in zip(fast, slow))
    empty = carry_history(old_key[:0], [v[:0] for v in values], sorted_new)
    assert all(e.shape == (sorted_new.shape[0], 3) and not e.any() for e in empty)


def test_pair_order_kernel_sorts_as_argsort_of_the_keys():
    """The counting sort of reorder's renumbered lists gives the order of torch.argsort(lo n + hi)
    for unique pairs in any order, with empty groups, a single pair and none; an index outside
    [0, n) is refused, naming it."""
    g = torch.Generator().manual_seed(5)
    n = 5_000
    key = torch.unique(torch.randint(0, n * n, (40_000,), generator=g))
    key = key[torch.randperm(key.shape[0], generator=g)]
    lo, hi = key // n, key % n
    for a, b in ((lo, hi), (lo[:1], hi[:1]), (lo[:0], hi[:0])):
        fast = pair_order(a, b, n)
        assert fast.dtype == torch.int64
        assert torch.equal(fast, pair_order(a, b, n, use_extension=False))
        assert torch.equal(fast, torch.argsort(a * n + b))
    if _ext.cpu_kernels() is not None:
        with pytest.raises(RuntimeError, match=r"pair \(3, 5000\) is outside \[0, 5000\)"):
            pair_order(torch.tensor([3]), torch.tensor([n]), n)


def test_simulation_never_misses_a_touching_pair():
    """During a dense settling run, every overlapping pair is in the current neighbour list."""
    from conftest import simulation, two_material_table
    from torchdem.integrate import sphere_positions
    from torchdem.walls import box_walls

    g = torch.Generator().manual_seed(3)
    B, N = 2, 120
    k = torch.arange(N)
    lattice = torch.stack([k % 5, (k // 5) % 5, k // 25], -1).to(F64) * 0.011 + 0.006
    pos = lattice + 0.002 * (torch.rand(B, N, 3, generator=g, dtype=F64) - 0.5)
    radius = 0.003 + 0.0015 * torch.rand(B, N, generator=g, dtype=F64)
    mats, table = two_material_table(B, dict(mu_s=0.5, mu_r=0.05, restitution=0.5))
    velocity = 0.5 * torch.randn(B, N, 3, generator=g, dtype=F64)
    sim = simulation(pos, radius, mats, table, walls=box_walls("box", (0, 0, 0), (0.062, 0.062, 0.3), "steel"),
                     time_step_fraction=0.3, velocity=velocity)
    S = B * N
    for _ in range(30):
        sim.advance(20)
        xs = sphere_positions(sim.system, sim.state.bodies)
        r = sim.system.sphere_radius.reshape(-1)
        body = sim.system.sphere_body_flat
        touching = _oracle(xs, r, body, torch.ones(S, dtype=torch.bool), N, 0.0)
        listed = set(zip(sim.state.pairs.i.tolist(), sim.state.pairs.j.tolist()))
        assert touching <= listed
    assert sim.state.rebuilds > 2


def _oracle_periodic(pos, radius, body, active, Ns, skin, period):
    from torchdem.neighbors import minimum_image
    S = pos.shape[0]
    i, j = torch.triu_indices(S, S, offset=1)
    same_member = (i // Ns) == (j // Ns)
    close = minimum_image(pos[i] - pos[j], period).norm(dim=-1) < radius[i] + radius[j] + skin
    keep = same_member & close & (body[i] != body[j]) & active[i] & active[j]
    return set(zip(i[keep].tolist(), j[keep].tolist()))


def test_periodic_cell_list_equals_minimum_image_oracle():
    """Periodic along y with many cells, and with only 1 or 2 cells across the period."""
    for depth in (0.08, 0.03, 0.016):
        pos, radius, body, active, Ns = _random_packing(21)
        pos[:, 1] = pos[:, 1] * depth / 0.08 - 0.01 * (pos[:, 0] > 0.05)  # some outside: wrapped
        skin = 0.001
        grid = cell_grid((0, 0, 0), (0.08, depth, 0.08), 2 * float(radius.max()) + skin,
                         periodic=(False, True, False), dtype=F64)
        i, j = find_pairs(pos, radius, body, active, Ns, grid, skin)
        found = set(zip(i.tolist(), j.tolist()))
        assert len(found) == i.shape[0]
        assert found == _oracle_periodic(pos, radius, body, active, Ns, skin, grid.period), depth


def test_collision_across_periodic_boundary_matches_direct_collision():
    """Two spheres meeting across the periodic y boundary rebound as if the boundary were not there."""
    from conftest import simulation, two_material_table

    R = 0.005
    mats, table = two_material_table(1, dict(mu_s=0.5, mu_r=0.05, restitution=0.6))
    pos = torch.tensor([[[0.05, 0.0055, 0.05], [0.05, 0.0345, 0.05]]], dtype=F64)  # 11 mm apart across y = 0
    vel = torch.tensor([[[0.0, -0.4, 0.0], [0.0, 0.4, 0.0]]], dtype=F64)
    sim = simulation(pos, torch.full((1, 2), R, dtype=F64), mats, table, velocity=vel, gravity=(0, 0, 0),
                     time_step_fraction=0.05, domain=((0, 0, 0), (0.1, 0.04, 0.1)), periodic=(False, True, False))
    sim.advance(3000)
    v = sim.state.bodies.velocity[0]
    assert torch.allclose(v.sum(0), torch.zeros(3, dtype=F64), atol=1e-12)  # momentum conserved
    rebound = (v[0, 1] - v[1, 1]).item() / 0.8  # sphere 0 now moves +y, sphere 1 -y
    assert abs(rebound - 0.6) < 0.006, rebound
    assert sim.state.rebuilds > 1


def test_periodic_period_needs_twice_the_contact_distance_not_the_skin():
    """A period between 2 x (2 r_max) and 2 x (2 r_max + skin) builds (the pair search keeps pairs
    by minimum-image distance) and collides right; below 2 x (2 r_max) it is refused."""
    from conftest import simulation, two_material_table
    from torchdem.errors import ConfigError

    R = 0.005
    mats, table = two_material_table(1, dict(mu_s=0.5, mu_r=0.05, restitution=0.6))
    # period 0.0265 m, skin 0.8 R: 2 (2 R + skin) = 0.028 m > period > 4 R = 0.02 m
    pos = torch.tensor([[[0.05, 0.0053, 0.05], [0.05, 0.0213, 0.05]]], dtype=F64)  # 10.5 mm apart across y = 0
    vel = torch.tensor([[[0.0, -0.4, 0.0], [0.0, 0.4, 0.0]]], dtype=F64)
    kw = dict(velocity=vel, gravity=(0, 0, 0), time_step_fraction=0.05, periodic=(False, True, False), skin=0.8 * R)
    sim = simulation(pos, torch.full((1, 2), R, dtype=F64), mats, table, domain=((0, 0, 0), (0.1, 0.0265, 0.1)), **kw)
    sim.advance(int(0.004 / sim.system.dt))  # the contact across y = 0 and 3 ms of separation, not the next one
    v = sim.state.bodies.velocity[0]
    assert abs((v[0, 1] - v[1, 1]).item() / 0.8 - 0.6) < 0.006
    with pytest.raises(ConfigError, match=r"domain extent along periodic axis y = 0\.019 is not allowed; expected > 0\.02 m"):
        simulation(pos, torch.full((1, 2), R, dtype=F64), mats, table, domain=((0, 0, 0), (0.1, 0.019, 0.1)), **kw)


SCATTER_BOX = (0.12, 0.04, 0.2)


def _scattered(seed, N, dtype, radius):
    """3 members of N spheres uniformly in SCATTER_BOX, bodies of 3 spheres, 90 % active; radii
    drawn by ``radius(generator, count)`` after the positions."""
    gen = torch.Generator().manual_seed(seed)
    pos = torch.rand(3 * N, 3, generator=gen, dtype=dtype) * torch.tensor(SCATTER_BOX, dtype=dtype)
    rad = radius(gen, 3 * N)
    return pos, rad, torch.arange(3 * N) // 3, torch.rand(3 * N, generator=gen) > 0.1


@pytest.mark.parametrize("periodic", [(False, False, False), (False, True, False), (True, True, False),
                                      (False, False, True), (True, True, True)])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cpp_cell_search_equals_torch_path(periodic, dtype):
    """The C++ candidate scan (torchdem/_ext/cells_cpu.cpp) returns exactly the torch path's list,
    including periodic axes with 2 cells (wrapped neighbour cells visited once), a periodic
    sort axis of 11 cells (windows that wrap), a sort axis other than z (x when z is periodic),
    padding and spheres with non-finite positions (no pairs)."""
    from torchdem import _ext

    if _ext.cpu_kernels() is None:
        pytest.skip("C++ extension unavailable on this machine (the torch path is tested above)")
    N, hi = 1500, SCATTER_BOX
    pos, rad, body, active = _scattered(3, N, dtype, lambda g, n: 0.002 + 0.006 * torch.rand(n, generator=g, dtype=dtype))
    pos[7] = float("nan")
    pos[N + 11, 2] = float("inf")
    grid = cell_grid((0, 0, 0), hi, float(2 * rad.max() + 0.002), periodic=periodic, dtype=dtype)
    b = find_pairs(pos, rad, body, active, N, grid, 0.002, use_extension=False)
    assert b[0].numel() > 1000
    threads = torch.get_num_threads()
    try:
        for n in (1, 3):  # the columns are split over threads; the list must not depend on how
            torch.set_num_threads(n)
            a = find_pairs(pos, rad, body, active, N, grid, 0.002)
            assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    finally:
        torch.set_num_threads(threads)
    ext = _ext.cpu_kernels()
    args = (grid.lower.tolist(), grid.cell_size.tolist(), list(grid.dims), grid.period.tolist(), N, 0.002)
    with pytest.raises(RuntimeError, match=r"radius, body and active need 4500 entries"):
        ext.cell_pairs(pos, rad[:-1], body, active, *args)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cpp_wall_search_equals_torch_path(dtype):
    """The C++ sphere-wall scan returns exactly the broadcast torch path's (sphere, wall) list:
    finite rectangles (edges and corners), an infinite plane, a shifted wall, a removed wall,
    inactive spheres."""
    from torchdem import _ext
    from torchdem.neighbors import find_wall_pairs
    from torchdem.walls import WallSpec, box_walls, make_walls

    if _ext.cpu_kernels() is None:
        pytest.skip("C++ extension unavailable on this machine")
    gen = torch.Generator().manual_seed(5)
    S = 4000
    pos = (torch.rand(S, 3, generator=gen, dtype=torch.float64) * torch.tensor([0.2, 0.1, 0.15])
           - torch.tensor([0.0, 0.0, 0.01])).to(dtype)
    rad = (0.002 + 0.006 * torch.rand(S, generator=gen, dtype=torch.float64)).to(dtype)
    active = torch.rand(S, generator=gen) > 0.1
    specs = box_walls("box", (0.0, 0.0, 0.0), (0.2, 0.1, 0.12), "steel") + [
        WallSpec("plate", (0.1, 0.05, 0.06), (0, 0, 1), (1, 0, 0), 0.03, 0.02, "steel"),
        WallSpec("plane", (0.0, 0.0, 0.14), (0, 0, -1), (1, 0, 0), float("inf"), float("inf"), "steel")]
    walls = make_walls(specs, {"steel": 0}, dtype=dtype)
    shift = torch.zeros(walls.n, 3, dtype=dtype)
    shift[-2] = torch.tensor([0.01, 0.0, -0.005], dtype=dtype)
    live = torch.ones(walls.n, dtype=torch.bool)
    live[1] = False
    a = find_wall_pairs(pos, rad, active, walls, shift, live, 0.003)
    b = find_wall_pairs(pos, rad, active, walls, shift, live, 0.003, use_extension=False)
    assert a[0].numel() > 500 and bool((b[1] == walls.n - 1).any()) and bool((b[1] == walls.n - 2).any())
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


@pytest.mark.parametrize("periodic", [(False, False, False), (False, True, False), (True, True, True)])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cpp_two_grid_search_equals_torch_path(periodic, dtype):
    """With the small spheres on a finer grid of their own (a bimodal packing: 80 % lobes of 1.5-2.5
    mm, 20 % pellets of 4-8 mm), the C++ search returns exactly the torch path's list at several
    split radii, on 1 and 3 threads, with a periodic axis of 2 coarse cells, spheres with
    non-finite positions and inactive spheres; and with every sphere small or none."""
    from torchdem import _ext
    from torchdem.neighbors import with_split, wrap

    if _ext.cpu_kernels() is None:
        pytest.skip("C++ extension unavailable on this machine")
    def bimodal(g, n):
        lobe = torch.rand(n, generator=g) < 0.8
        return torch.where(lobe, 0.0015 + 0.001 * torch.rand(n, generator=g),
                           0.004 + 0.004 * torch.rand(n, generator=g)).to(dtype)

    N, hi = 2500, SCATTER_BOX
    pos, rad, body, active = _scattered(4, N, dtype, bimodal)
    pos[5] = float("nan")
    pos[N + 9, 1] = float("inf")
    skin = 0.002
    grid = cell_grid((0, 0, 0), hi, float(2 * rad.max() + skin), periodic=periodic, dtype=dtype)
    ref = find_pairs(pos, rad, body, active, N, grid, skin, use_extension=False)
    assert ref[0].numel() > 5000
    threads = torch.get_num_threads()
    try:
        for split in (0.3, 0.5, 0.7):
            g2 = with_split(grid, split * float(rad.max()), skin)
            assert g2.split > 0
            for n in (1, 3):
                torch.set_num_threads(n)
                a = find_pairs(pos, rad, body, active, N, g2, skin)
                assert torch.equal(a[0], ref[0]) and torch.equal(a[1], ref[1]), (split, n)
    finally:
        torch.set_num_threads(threads)
    ext = _ext.cpu_kernels()
    wrapped = wrap(pos, grid.lower, grid.period) if grid.is_periodic else pos
    args = (grid.lower.tolist(), grid.cell_size.tolist(), list(grid.dims), grid.period.tolist(), N, skin)
    fine = (grid.cell_size.tolist(), list(grid.dims))
    for split in (0.5 * float(rad.min()), float(rad.max())):  # no sphere small; every sphere small
        a = ext.cell_pairs(wrapped, rad, body, active, *args, split, *fine)
        assert torch.equal(a[0], ref[0]) and torch.equal(a[1], ref[1]), split


def test_search_grid_splits_only_where_small_spheres_dominate():
    """search_grid splits at the fraction of the largest radius when at least half of the spheres
    are that small, keeps one grid otherwise (or for fraction 0), and build_system names a bad
    fraction."""
    from conftest import two_material_table
    from torchdem.errors import ConfigError
    from torchdem.neighbors import search_grid
    from torchdem.system import build_system

    grid = cell_grid((0, 0, 0), (0.2, 0.2, 0.2), 0.018)
    bimodal = torch.tensor([0.002] * 6 + [0.008] * 4, dtype=torch.float64)
    split = search_grid(grid, bimodal, 0.002, 0.6)
    assert split.split == pytest.approx(0.0048) and split.fine_dims == (17, 17, 17)
    assert search_grid(grid, torch.tensor([0.002] * 4 + [0.008] * 6, dtype=torch.float64), 0.002).split == 0
    assert search_grid(grid, bimodal, 0.002, 0.0).split == 0
    assert search_grid(grid, torch.full((5,), 0.008, dtype=torch.float64), 0.002).split == 0
    mats, table = two_material_table(1, dict(mu_s=0.5, mu_r=0.1, restitution=0.5))
    with pytest.raises(ConfigError, match=r"search_split = 1.5.*\[0, 1\)"):
        build_system(torch.zeros(1, 1, 3, dtype=F64), torch.zeros(1, 1, dtype=torch.long), mats, table,
                     radius=torch.full((1, 1), 0.01, dtype=F64), search_split=1.5)


def _bimodal(dtype):
    def radius(g, n):
        lobe = torch.rand(n, generator=g) < 0.8
        return torch.where(lobe, 0.0015 + 0.001 * torch.rand(n, generator=g),
                           0.004 + 0.004 * torch.rand(n, generator=g)).to(dtype)
    return radius


@pytest.mark.parametrize("periodic", [(False, False, False), (False, True, False)])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_partial_search_equals_the_whole_search_at_the_new_references(periodic, dtype):
    """A partial search (the moved spheres searched anew, the last list's other pairs kept) returns
    exactly the whole search's list at the positions where the moved spheres are now and the others
    were at the last build: torch path and C++ kernel, one grid and two, 1 and 3 threads. A third
    of the spheres moved (some by several cells), some went inactive since the build, one moved
    sphere's position is not finite; no sphere moved keeps the list as it was."""
    from torchdem import _ext
    from torchdem.neighbors import with_split

    N = 2500
    pos, rad, body, active = _scattered(6, N, dtype, _bimodal(dtype))
    skin = 0.002
    grid = cell_grid((0, 0, 0), SCATTER_BOX, float(2 * rad.max() + skin), periodic=periodic, dtype=dtype)
    built = find_pairs(pos, rad, body, active, N, grid, skin, use_extension=False)
    gen = torch.Generator().manual_seed(9)
    moved = torch.rand(3 * N, generator=gen) < 0.3
    jump = torch.where(torch.rand(3 * N, 1, generator=gen) < 0.2, 0.03, 0.003)
    now = torch.where(moved[:, None], pos + (jump * torch.randn(3 * N, 3, generator=gen)).to(dtype), pos)
    now[torch.nonzero(moved)[0, 0]] = float("nan")
    active = active & (torch.rand(3 * N, generator=gen) > 0.03)
    whole = find_pairs(now, rad, body, active, N, grid, skin, use_extension=False)
    assert whole[0].numel() > 5000
    kept = (~moved[built[0]] & ~moved[built[1]]).sum()
    assert 0 < int(kept) < whole[0].numel()  # both kept and new pairs
    grids = [grid, with_split(grid, 0.5 * float(rad.max()), skin)]
    assert grids[1].split > 0
    paths = [False] + ([True] if _ext.cpu_kernels() is not None else [])
    threads = torch.get_num_threads()
    try:
        for g in grids:
            for use_extension in paths:
                for n in (1, 3):
                    torch.set_num_threads(n)
                    a = find_pairs(now, rad, body, active, N, g, skin, use_extension, moved=moved, keep=built)
                    assert torch.equal(a[0], whole[0]) and torch.equal(a[1], whole[1]), (g.split, use_extension, n)
                    still = torch.zeros(3 * N, dtype=torch.bool)
                    b = find_pairs(pos, rad, body, active, N, g, skin, use_extension, moved=still, keep=built)
                    ref = find_pairs(pos, rad, body, active, N, g, skin, use_extension=False)
                    assert torch.equal(b[0], ref[0]) and torch.equal(b[1], ref[1])
    finally:
        torch.set_num_threads(threads)


def test_partial_wall_search_equals_the_whole_search_at_the_new_references():
    """The sphere-wall list of a partial search equals the whole search's at the new references
    (torch path and C++ kernel): moved spheres tested anew, the others keep their walls, a sphere
    gone inactive loses them."""
    from torchdem import _ext
    from torchdem.neighbors import find_wall_pairs
    from torchdem.walls import WallSpec, box_walls, make_walls

    gen = torch.Generator().manual_seed(11)
    S = 3000
    pos = torch.rand(S, 3, generator=gen, dtype=F64) * torch.tensor([0.2, 0.1, 0.12], dtype=F64)
    rad = 0.002 + 0.006 * torch.rand(S, generator=gen, dtype=F64)
    active = torch.rand(S, generator=gen) > 0.1
    specs = box_walls("box", (0.0, 0.0, 0.0), (0.2, 0.1, 0.12), "steel") + [
        WallSpec("plate", (0.1, 0.05, 0.06), (0, 0, 1), (1, 0, 0), 0.03, 0.02, "steel")]
    walls = make_walls(specs, {"steel": 0}, dtype=F64)
    shift = torch.zeros(walls.n, 3, dtype=F64)
    live = torch.ones(walls.n, dtype=torch.bool)
    skin = 0.004
    built = find_wall_pairs(pos, rad, active, walls, shift, live, skin, use_extension=False)
    moved = torch.rand(S, generator=gen) < 0.3
    now = torch.where(moved[:, None], pos + 0.01 * torch.randn(S, 3, generator=gen, dtype=F64), pos)
    active = active & (torch.rand(S, generator=gen) > 0.05)
    whole = find_wall_pairs(now, rad, active, walls, shift, live, skin, use_extension=False)
    assert whole[0].numel() > 300
    for use_extension in [False] + ([True] if _ext.cpu_kernels() is not None else []):
        a = find_wall_pairs(now, rad, active, walls, shift, live, skin, use_extension, moved=moved, keep=built)
        assert torch.equal(a[0], whole[0]) and torch.equal(a[1], whole[1]), use_extension


def _clumps_falling_on_a_bed(moved_share):
    """Two members: a bed of 48 bodies at rest on the floor of a box and 48 above it falling at
    2 m/s, every third a trilobe clump, float64."""
    from conftest import glass, steel
    from torchdem.clumps import SPHERE
    from torchdem.materials import interaction_table
    from torchdem.mixture import trilobe_template
    from torchdem.system import build_system
    from torchdem.walls import box_walls

    B, N = 2, 96
    mats = [glass(), steel()]
    pp = dict(mu_s=[0.3, 0.6], mu_r=[0.02, 0.1], restitution=[0.4, 0.8], rolling_damping=0.3)
    table = interaction_table(mats, {("glass", "glass"): pp, ("glass", "steel"): pp}, batch=B)
    k = torch.arange(N)
    lattice = torch.stack([k % 4, (k // 4) % 4, k // 16], -1).to(F64) * 0.0125 + 0.007
    lattice[48:, 2] += 0.02
    gen = torch.Generator().manual_seed(2)
    pos = lattice + 0.002 * (torch.rand(B, N, 3, generator=gen, dtype=F64) - 0.5)
    vel = torch.zeros(B, N, 3, dtype=F64)
    vel[:, 48:, 2] = -2.0
    u = torch.rand(B, N, generator=gen, dtype=F64)
    clump = (torch.arange(N) % 3 == 0).expand(B, N)
    system, state = build_system(pos, torch.zeros(B, N, dtype=torch.long), mats, table,
                                 templates=[SPHERE, trilobe_template(0.15)], template_index=clump.long(),
                                 scale=torch.where(clump, 0.009 + 0.001 * u, 0.004 + 0.001 * u), velocity=vel,
                                 walls=box_walls("box", (0, 0, 0), (0.05, 0.05, 0.3), "steel"),
                                 dt=2e-5, domain=((-0.01, -0.01, -0.01), (0.06, 0.06, 0.31)))
    return dataclasses.replace(system, moved_share=moved_share), state


@pytest.mark.parametrize("path", ["cpp", "torch"])
def test_partial_rebuilds_list_every_touching_pair_and_change_no_trajectory(monkeypatch, path):
    """With partial rebuilds (moved_share 0.25) every pair and wall contact touching now is listed
    at every step while clumps and spheres fall onto a resting bed, some rebuilds search only a
    part of the spheres, and the run is the one with whole rebuilds bit for bit (one thread): the
    lists differ only in pairs that do not touch, which add nothing. ``torch``: no C++ kernel at
    all (searches, per-pair constants, contact laws), as on a GPU."""
    import torchdem.integrate as integrate
    from torchdem import _ext
    from torchdem.integrate import sphere_positions
    from torchdem.simulation import Simulation

    if path == "torch":
        monkeypatch.setattr(_ext, "kernels_for", lambda device, enabled=True: None)
    elif _ext.cpu_kernels() is None:
        pytest.skip("C++ extension unavailable on this machine")

    searched = []  # per rebuild, the share of the spheres searched anew
    whole_rebuild = integrate.rebuild

    def rebuild(system, state, xs, time, values=True, moved=None):
        searched.append(1.0 if moved is None else float(moved.float().mean()))
        return whole_rebuild(system, state, xs, time, values, moved)

    monkeypatch.setattr(integrate, "rebuild", rebuild)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        runs = {}
        for share in (0.0, 0.25):
            system, state = _clumps_falling_on_a_bed(share)
            sim = Simulation(system, state)
            radius, body = system.sphere_radius.reshape(-1), system.sphere_body_flat
            active = radius > 0
            searched.clear()
            touching = set()
            for step in range(1200):
                sim.advance(1)
                xs = sphere_positions(system, sim.state.bodies)
                if share and step % 4 == 0:
                    listed = set(zip(sim.state.pairs.i.tolist(), sim.state.pairs.j.tolist()))
                    now = _oracle(xs, radius, body, active, system.n_spheres, 0.0)
                    assert now <= listed, step
                    touching |= now
                    walls = system.walls
                    gap = ((xs[:, None, :] - walls.centre[None]) * torch.cross(walls.axis_u, walls.axis_v, dim=-1)[None]
                           ).sum(-1).abs() - radius[:, None]
                    s, w = torch.nonzero((gap < 0) & active[:, None], as_tuple=True)
                    assert set(zip(s.tolist(), w.tolist())) <= set(zip(sim.state.walls.sphere.tolist(),
                                                                       sim.state.walls.wall.tolist())), step
            runs[share] = (sim, list(searched))
        (whole, whole_searched), (part, part_searched) = runs[0.0], runs[0.25]
        member_body = part.system.sphere_body.reshape(-1)  # as built: partial runs do not reorder
        assert any((int(member_body[i]) < 48) != (int(member_body[j]) < 48) for i, j in touching)  # it landed
        assert whole.state.rebuilds > 10 and set(whole_searched) == {1.0}
        assert sum(0 < f < 0.7 for f in part_searched) >= 5, part_searched  # the bed is not searched again
        assert torch.equal(part.state.bodies.position, whole.state.bodies.position)
        assert torch.equal(part.state.bodies.angular_momentum, whole.state.bodies.angular_momentum)
    finally:
        torch.set_num_threads(threads)


def test_the_skin_changes_no_bit_of_a_run():
    """The Verlet skin decides which pairs that do not touch are listed and how often the lists are
    rebuilt, never which pairs touch nor their order: 60 spheres of 2 and 6 mm (the small ones on
    the fine grid) thrown at one another collide inelastically over 1,500 steps, and the runs at a
    skin of 0.25, 0.1 and 0.5 of the largest radius end with the same bits, with 2.5x more rebuilds
    at the thinnest (without the periodic spatial reorder, whose schedule follows the rebuilds)."""
    from torchdem.materials import Material, interaction_table
    from torchdem.simulation import Simulation
    from torchdem.system import build_system

    g = torch.Generator().manual_seed(3)
    glass = Material("glass", shear_modulus=1e7, poisson_ratio=0.25, density=2500.0)
    table = interaction_table([glass], {("glass", "glass"): dict(mu_s=0.5, mu_r=0.1, restitution=0.5)}, batch=1)
    radius = torch.where(torch.rand(1, 60, generator=g) < 0.6, 0.002, 0.006).to(F64)
    sites = torch.cartesian_prod(*[torch.arange(4, dtype=F64) * 0.0135] * 3)  # no two spheres touch
    position = (sites[torch.randperm(64, generator=g)[:60]] + 0.005).unsqueeze(0)
    velocity = -(position - 0.025) * 20.0  # everything towards the centre, up to ~0.5 m/s
    runs = {}
    for fraction in (0.25, 0.1, 0.5):
        system, state = build_system(position, torch.zeros(1, 60, dtype=torch.long), [glass], table, radius=radius,
                                     velocity=velocity, gravity=(0, 0, 0), skin=fraction * 0.006,
                                     domain=((-0.05, -0.05, -0.05), (0.1, 0.1, 0.1)))
        assert system.grid.split > 0
        runs[fraction] = Simulation(system, state)
        runs[fraction].advance(1500)
    start = float((velocity ** 2).sum())
    assert float((runs[0.25].state.bodies.velocity ** 2).sum()) < 0.8 * start  # they collided
    assert runs[0.1].state.rebuilds > 2 * runs[0.25].state.rebuilds > 0
    for fraction in (0.1, 0.5):
        assert torch.equal(runs[fraction].state.bodies.position, runs[0.25].state.bodies.position)
        assert torch.equal(runs[fraction].state.bodies.angular_momentum, runs[0.25].state.bodies.angular_momentum)


def test_a_run_resumed_at_another_skin_ends_with_the_same_bits(tmp_path):
    """The skin is an execution setting (``torchdem.model.EXECUTION_ONLY``), so a checkpoint may resume
    at another one: the spheres of the test above, saved after 700 of 1,500 steps at a skin of 0.1 of the
    largest radius and resumed at 0.5 (whose criterion waits for pairs the thin lists never held), or
    the other way, end with the bits of the run not interrupted; a resume at the same skin keeps the
    saved lists (no rebuild at load)."""
    from torchdem.materials import Material, interaction_table
    from torchdem.simulation import Simulation
    from torchdem.system import build_system

    g = torch.Generator().manual_seed(3)
    glass = Material("glass", shear_modulus=1e7, poisson_ratio=0.25, density=2500.0)
    table = interaction_table([glass], {("glass", "glass"): dict(mu_s=0.5, mu_r=0.1, restitution=0.5)}, batch=1)
    radius = torch.where(torch.rand(1, 60, generator=g) < 0.6, 0.002, 0.006).to(F64)
    sites = torch.cartesian_prod(*[torch.arange(4, dtype=F64) * 0.0135] * 3)
    position = (sites[torch.randperm(64, generator=g)[:60]] + 0.005).unsqueeze(0)
    velocity = -(position - 0.025) * 20.0

    def system(fraction):
        return build_system(position, torch.zeros(1, 60, dtype=torch.long), [glass], table, radius=radius,
                            velocity=velocity, gravity=(0, 0, 0), skin=fraction * 0.006,
                            domain=((-0.05, -0.05, -0.05), (0.1, 0.1, 0.1)))

    whole = Simulation(*system(0.25))
    whole.advance(1500)
    for saved, resumed in ((0.1, 0.5), (0.5, 0.1), (0.1, 0.1)):
        first = Simulation(*system(saved))
        first.advance(700)
        first.save(tmp_path / "run.pt")
        again = Simulation.load(tmp_path / "run.pt", system(resumed)[0])
        assert again.state.rebuilds == first.state.rebuilds + (saved != resumed)
        again.advance(800)
        assert torch.equal(again.state.bodies.position, whole.state.bodies.position), (saved, resumed)
        assert torch.equal(again.state.bodies.angular_momentum, whole.state.bodies.angular_momentum)

