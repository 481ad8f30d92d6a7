"""Spatial reordering of bodies (torchdem/reorder.py) changes no physics.

- Morton codes interleave the cell coordinates' bits (x lowest).
- A run that reorders after every neighbour rebuild and one that never does give the same
  trajectories to round-off over 1,000 steps: float64, two members, single spheres and
  three-sphere clumps mixed, a moving wall (a piston). Tolerance: 1e-12 m on positions after
  1,000 steps of a dense settling packing (measured: 1.9e-16 m, 32 rebuilds; the gap is stated
  in the assertion message), bodies matched by ``State.body_id``.
- The reorder keeps every listed contact and its history bit for bit (tangential spring and
  rolling torque negated exactly where the two spheres swap order).
- The rebuild schedule is unchanged (same rebuild count).
- A checkpoint of a reordered run loads onto the system as built and continues bit for bit;
  VTK output names spheres and bodies by their ids as built.
"""
import numpy as np
import torch

from conftest import F64, glass, steel
from torchdem.clumps import SPHERE
from torchdem.io import read_vtk_points, write_vtk_frame
from torchdem.materials import interaction_table
from torchdem.mixture import trilobe_template
from torchdem.reorder import morton_code, reorder, spatial_permutation
from torchdem.simulation import GuardSettings, Simulation
from torchdem.system import build_system
from torchdem.walls import WallSpec, box_walls

N = 64


def _system(seed_base=0, device="cpu", dtype=F64):
    """Two members of 64 bodies (every third a trilobe clump) in a box with a piston moving down
    (built on ``device`` in ``dtype``; tests/test_cuda.py runs it on a GPU)."""
    B = 2
    mats = [glass(), steel()]
    pp = dict(mu_s=[0.3, 0.6], mu_r=[0.02, 0.1], restitution=[0.4, 0.8], rolling_damping=0.3)
    table = interaction_table(mats, {("glass", "glass"): pp, ("glass", "steel"): pp}, batch=B)
    pos, vel, scale = [], [], []
    for m in range(B):
        g = torch.Generator().manual_seed(seed_base + m)
        k = torch.randperm(N, generator=g)  # indices with no spatial order, as a rained fill has
        p = torch.stack([k % 4, (k // 4) % 4, k // 16], -1).to(F64) * 0.012 + 0.008
        pos.append(p + 0.002 * (torch.rand(N, 3, generator=g, dtype=F64) - 0.5))
        vel.append(0.3 * torch.randn(N, 3, generator=g, dtype=F64))
        u = torch.rand(N, generator=g, dtype=F64)
        # a trilobe's scale is its sieve diameter, a sphere's its radius
        scale.append(torch.where(torch.arange(N) % 3 == 0, 0.009 + 0.001 * u, 0.004 + 0.001 * u))
    template_index = (torch.arange(N) % 3 == 0).long().expand(B, N)
    piston = WallSpec("piston", (0.025, 0.025, 0.07), (0, 0, 1), (1, 0, 0), 0.03, 0.03, "steel",
                      velocity=(0.0, 0.0, -0.5), move_from=0.0, move_until=1.0)
    system, state = build_system(torch.stack(pos).to(device=device, dtype=dtype), torch.zeros(B, N, dtype=torch.long),
                                 mats, table,
                                 templates=[SPHERE, trilobe_template(0.15)], template_index=template_index,
                                 scale=torch.stack(scale), velocity=torch.stack(vel),
                                 walls=[*box_walls("box", (0, 0, 0), (0.05, 0.05, 0.3), "steel"), piston],
                                 dt=2e-5, domain=((-0.01, -0.01, -0.01), (0.06, 0.06, 0.31)))
    return system, state


def _in_build_order(body_id, tensor):
    """``[B, Nb, ...]`` per-body tensor with slot k holding body k as built (``body_id`` ``[B, Nb]``)."""
    out = torch.empty_like(tensor)
    index = body_id.reshape(body_id.shape + (1,) * (tensor.dim() - 2)).expand_as(tensor)
    return out.scatter_(1, index, tensor)


def test_morton_code_interleaves_bits():
    cells = torch.tensor([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [2, 0, 0], [3, 3, 3], [0, 0, 2]])
    assert morton_code(cells).tolist() == [1, 2, 4, 7, 8, 63, 32]


def test_permutation_orders_active_bodies_along_the_curve_and_inactive_last():
    system, state = _system()
    active = state.bodies.active.clone()
    active[0, :5] = False
    state = state.set(bodies=state.bodies.set(active=active))
    perm = spatial_permutation(system, state)
    assert sorted(perm[0].tolist()) == list(range(N))
    assert perm[0, -5:].tolist() == [0, 1, 2, 3, 4]
    grid = system.grid
    cell = torch.floor((state.bodies.position[0] - grid.lower) / grid.cell_size).long()
    codes = morton_code(cell)[perm[0, :-5]]
    assert bool((codes[1:] >= codes[:-1]).all())


def test_reordered_run_follows_the_same_trajectories():
    runs = []
    for every in (0, 1):
        system, state = _system()
        sim = Simulation(system, state, GuardSettings(check_every=100), reorder_every=every)
        sim.advance(1000)
        runs.append(sim)
    plain, sorted_run = runs
    assert plain.state.rebuilds > 5  # the piston and the settling make the lists rebuild
    assert sorted_run.state.rebuilds == plain.state.rebuilds
    assert not torch.equal(sorted_run.state.body_id, plain.state.body_id)  # it did reorder
    gap = (_in_build_order(sorted_run.state.body_id, sorted_run.state.bodies.position) - plain.state.bodies.position).abs().max()
    assert float(gap) < 1e-12, f"positions differ by {float(gap):.3g} m after 1000 steps"
    vgap = (_in_build_order(sorted_run.state.body_id, sorted_run.state.bodies.velocity) - plain.state.bodies.velocity).abs().max()
    assert float(vgap) < 1e-6, f"velocities differ by {float(vgap):.3g} m/s"


def test_reorder_keeps_every_contact_and_its_history_bit_for_bit():
    system, state = _system()
    sim = Simulation(system, state)
    sim.advance(300)
    rebuilds = sim.state.rebuilds
    while sim.state.rebuilds == rebuilds:  # stop at a step that rebuilt the lists, as Simulation reorders
        sim.advance(1)
    st = sim.state
    new_system, new = reorder(sim.system, st)
    S = system.batch * system.n_spheres
    sphere_id = new.sphere_id + torch.arange(system.batch)[:, None] * system.n_spheres  # flat ids as built
    flat = sphere_id.reshape(-1)
    i, j = flat[new.pairs.i], flat[new.pairs.j]
    swap = i > j
    key = torch.minimum(i, j) * S + torch.maximum(i, j)
    order = torch.argsort(key)
    assert torch.equal(key[order], st.pairs.key)  # the same contacts
    sign = torch.where(swap, -1.0, 1.0).to(F64)[:, None]
    assert torch.equal((new.pairs.tangential * sign)[order], st.pairs.tangential)
    assert torch.equal((new.pairs.rolling * sign)[order], st.pairs.rolling)
    assert bool((st.pairs.tangential.abs().sum(-1) > 0).any())  # there was history to carry
    W = system.walls.n
    wkey = flat[new.walls.sphere] * W + new.walls.wall
    worder = torch.argsort(wkey)
    assert torch.equal(wkey[worder], st.walls.key)
    assert torch.equal(new.walls.tangential[worder], st.walls.tangential)
    # the per-body constants travel with their bodies
    assert torch.equal(_in_build_order(new.body_id, new_system.mass), system.mass)


def test_reorder_lists_are_a_rebuild_without_moved_spheres_even_after_a_body_went_inactive():
    """The reorder carries the lists without a search: they must be what a partial rebuild in which no
    sphere moved gives in the new numbering, every field bit for bit (per-pair constants included),
    also when a body went inactive since the last build (its pairs dropped, as a rebuild drops them)."""
    import dataclasses

    from torchdem.integrate import rebuild

    system, state = _system()
    sim = Simulation(system, state)
    sim.advance(300)
    rebuilds = sim.state.rebuilds
    while sim.state.rebuilds == rebuilds:
        sim.advance(1)
    st = sim.state
    touching = int(st.pairs.body_i[0]) % system.n_bodies  # a body with listed pairs, member 0
    active = st.bodies.active.clone()
    active[0, touching] = False
    for before in (st, st.set(bodies=st.bodies.set(active=active))):
        new_system, new = reorder(sim.system, before)
        S = system.batch * system.n_spheres
        expected, _ = rebuild(new_system, new, new.reference, system.time_of(before.step),
                              values=before.pairs.radius_i is not None, moved=torch.zeros(S, dtype=torch.bool))
        for lists in ("pairs", "walls"):
            for f in dataclasses.fields(getattr(new, lists)):
                a, b = getattr(getattr(new, lists), f.name), getattr(getattr(expected, lists), f.name)
                assert (a is None and b is None) or torch.equal(a, b), f"{lists}.{f.name} differs from a rebuild's"
    assert new.pairs.i.numel() < st.pairs.i.numel()  # the inactive body's pairs went


def test_checkpoint_of_a_reordered_run_resumes_bit_for_bit(tmp_path):
    system, state = _system()
    sim = Simulation(system, state, reorder_every=1)
    sim.advance(200)
    sim.save(tmp_path / "ckpt.pt")
    built, _ = _system()  # the system as built, in the original order
    resumed = Simulation.load(tmp_path / "ckpt.pt", built, reorder_every=1)
    sim.advance(200)
    resumed.advance(200)
    assert torch.equal(resumed.state.bodies.position, sim.state.bodies.position)
    assert torch.equal(resumed.state.body_id, sim.state.body_id)
    assert torch.equal(resumed.system.sphere_radius, sim.system.sphere_radius)


def test_vtk_names_spheres_and_bodies_as_built(tmp_path):
    system, state = _system()
    plain = Simulation(system, state)
    sim = Simulation(*_system())
    sim.system, sim.state = reorder(sim.system, sim.state)
    assert not torch.equal(sim.state.sphere_id, plain.state.sphere_id)
    a = read_vtk_points(write_vtk_frame(tmp_path / "a", sim.system, sim.state, members=[1])[0])
    b = read_vtk_points(write_vtk_frame(tmp_path / "b", plain.system, plain.state, members=[1])[0])
    ia, ib = np.argsort(a["id"]), np.argsort(b["id"])
    assert np.array_equal(a["id"][ia], b["id"][ib]) and np.array_equal(a["body"][ia], b["body"][ib])
    assert np.allclose(a["points"][ia], b["points"][ib], atol=1e-12)
