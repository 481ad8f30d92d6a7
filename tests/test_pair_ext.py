"""The C++ contact kernels (torchdem/_ext) equal the torch kernels of torchdem.integrate.

Oracle: :func:`torchdem.integrate.pair_kernel` and :func:`wall_kernel` run eagerly (the laws
of :mod:`torchdem.contact`). The packings are random, dense (many overlapping contacts,
some only within the skin), polydisperse, with three-sphere clumps, random orientations
and spins, walls with edges, periodic x and y axes, three ensemble members with different
friction, restitution and rolling coefficients, and random contact history whose sizes
span five decades, so that sticking and sliding springs, rolling springs below and at
their limit, and open contacts all occur.

Tolerances: float64 forces, torques and springs agree to 1e-12 of each tensor's largest
entry (the two codes round differently, nothing else); float32 to 1e-4 (the overlap is a
difference of near-equal numbers). A 300-step run with the C++ kernels follows the torch
run to 1e-9 m. The C++ results do not depend on the number of threads (bitwise).
A process whose compiler is missing warns once and runs on the torch kernels.
"""
import os
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import F64, glass, steel
from torchdem import _ext
from torchdem.clumps import ClumpTemplate
from torchdem.integrate import Kernels, body_angular_velocity, contact_forces, rebuild, sphere_positions
from torchdem.materials import interaction_table
from torchdem.simulation import GuardSettings, Simulation
from torchdem.system import build_system
from torchdem.walls import WallSpec

REPO = Path(__file__).resolve().parents[1]
TRI = ClumpTemplate("tri", np.array([[0, 0, 0], [0.006, 0, 0], [0.003, 0.005, 0]]), np.array([0.004, 0.004, 0.0035]))
SPHERE = ClumpTemplate("sphere", np.zeros((1, 3)), np.ones(1))
BOX = ((0.0, 0.0, -0.005), (0.06, 0.05, 0.08))


@pytest.fixture(scope="module")
def extension():
    ext = _ext.cpu_kernels()
    assert ext is not None, f"the C++ contact kernels did not build: {_ext.build_error()}"
    return ext


def _system(dtype=F64, rolling_stiffness="tangential", B=3, N=60, seed=0, spacing=0.0095, size=1.0,
            clumps=0.3, cohesion=None):
    """Mixed packing: spheres (r 3-5.5 mm x size) and, a fraction ``clumps`` of the bodies, clumps
    (8-11 mm long x size) on a jittered lattice (6 x 5 per layer, so spacing 0.01 m fills the
    periodic x period), random spins. ``cohesion``: SJKR k_c of the sphere pairs and of the
    sphere-wall pairs per member (two lists), or None."""
    g = torch.Generator().manual_seed(seed)
    k = torch.arange(N)
    lattice = torch.stack([k % 6, (k // 6) % 5, k // 30], -1).to(F64) * spacing + torch.tensor([0.004, 0.004, 0.006])
    pos = lattice.expand(B, N, 3) + 0.002 * torch.rand(B, N, 3, generator=g, dtype=F64)
    template_index = (torch.rand(B, N, generator=g) < clumps).long()
    scale = size * torch.where(template_index == 0, 0.003 + 0.0025 * torch.rand(B, N, generator=g, dtype=F64),
                               0.8 + 0.3 * torch.rand(B, N, generator=g, dtype=F64))
    q = torch.randn(B, N, 4, generator=g, dtype=F64)
    mats = [glass(), steel()]
    pp = dict(mu_s=[0.2, 0.5, 0.9, 0.4], mu_r=[0.02, 0.1, 0.3, 0.05], restitution=[0.3, 0.6, 0.9, 0.5],
              rolling_damping=[0.0, 0.3, 0.7, 0.1])
    pw = dict(mu_s=[0.3, 0.4, 0.6, 0.5], mu_r=[0.05, 0.01, 0.2, 0.1], restitution=[0.5, 0.7, 0.4, 0.8],
              rolling_damping=[0.2, 0.0, 0.5, 0.3])
    if cohesion is not None:
        pp["cohesion"], pw["cohesion"] = cohesion
    members = lambda coefficients: {k: [v[m % len(v)] for m in range(B)] for k, v in coefficients.items()}  # noqa: E731
    table = interaction_table(mats, {("glass", "glass"): members(pp), ("glass", "steel"): members(pw)}, batch=B)
    walls = [WallSpec("floor", (0.03, 0.025, 0.0), (0, 0, 1), (1, 0, 0), 0.02, 0.015, "steel"),
             WallSpec("post", (0.02, 0.02, 0.01), (1, 0, 0), (0, 0, 1), 0.008, 0.006, "steel")]
    system, state = build_system(
        pos.to(dtype), torch.zeros(B, N, dtype=torch.long), mats, table, templates=[SPHERE, TRI] if clumps > 0 else [SPHERE],
        template_index=template_index, scale=scale.to(dtype), orientation=q.to(dtype),
        velocity=(0.3 * torch.randn(B, N, 3, generator=g, dtype=F64)).to(dtype),
        angular_velocity=(30 * torch.randn(B, N, 3, generator=g, dtype=F64)).to(dtype), walls=walls,
        time_step_fraction=0.2, domain=BOX, periodic=(True, True, False), rolling_stiffness=rolling_stiffness)
    return system, state


def _with_history(system, state, seed=1):
    """Neighbour lists at t = 0 and random springs, log-uniform in size over five decades."""
    state, xs = rebuild(system, state, sphere_positions(system, state.bodies), 0.0)
    g = torch.Generator().manual_seed(seed)
    dtype = xs.dtype

    def springs(n, scale):
        direction = torch.randn(n, 3, generator=g, dtype=F64)
        size = scale * 10.0 ** (-5 * torch.rand(n, 1, generator=g, dtype=F64))
        return (direction / direction.norm(dim=-1, keepdim=True) * size).to(dtype)

    p, w = state.pairs, state.walls
    state = state.set(pairs=p.set(tangential=springs(p.n, 1e-3), rolling=springs(p.n, 1e-1)),
                      walls=w.set(tangential=springs(w.n, 1e-3), rolling=springs(w.n, 1e-1)))
    omega = body_angular_velocity(system, state.bodies)
    return state, xs, omega


def _both(system, state, xs, omega):
    torch_out = contact_forces(system, state, xs, omega, 0.0, Kernels(backend="torch"))
    cpp_out = contact_forces(system, state, xs, omega, 0.0, Kernels(backend="cpp"))
    return torch_out, cpp_out


def _outputs(out):
    force, torque, state = out
    return {"force": force, "torque": torque, "pair tangential": state.pairs.tangential,
            "pair rolling": state.pairs.rolling, "wall tangential": state.walls.tangential,
            "wall rolling": state.walls.rolling}


def _assert_close(actual: dict, expected: dict, rel: float):
    for name, ref in expected.items():
        scale = float(ref.abs().max())
        err = float((actual[name] - ref).abs().max())
        assert scale > 0, f"{name}: reference is all zero, the test would prove nothing"
        assert err <= rel * scale, f"{name}: max difference {err:.3g} > {rel:g} x largest entry {scale:.3g}"


def _touching(system, state, xs):
    p = state.pairs
    sep = xs[p.j] - xs[p.i]
    period = system.grid.period
    sep = sep - period * torch.round(sep / torch.where(period > 0, period, torch.ones_like(period)))
    return p.radius_i + p.radius_j - sep.norm(dim=-1) > 0


@pytest.mark.parametrize("rolling_stiffness", ["tangential", "ai2011"])
def test_cpp_contact_kernels_equal_torch_eager_float64(extension, rolling_stiffness):
    system, state = _system(rolling_stiffness=rolling_stiffness)
    state, xs, omega = _with_history(system, state)
    torch_out, cpp_out = _both(system, state, xs, omega)
    _assert_close(_outputs(cpp_out), _outputs(torch_out), 1e-12)

    # The cases the test must cover.
    touching = _touching(system, state, xs)
    assert int(touching.sum()) > 200 and int((~touching).sum()) > 20
    assert bool(((state.pairs.body_i // system.n_bodies) == 2).any())       # every member has contacts
    old = state.pairs.tangential.norm(dim=-1)
    new = torch_out[2].pairs.tangential.norm(dim=-1)
    assert int((touching & (new < 0.5 * old)).sum()) > 10                  # sliding springs, clipped
    assert int((touching & (new > 0.9 * old) & (new < 1.1 * old)).sum()) > 10   # sticking springs
    old_r = state.pairs.rolling.norm(dim=-1)
    new_r = torch_out[2].pairs.rolling.norm(dim=-1)
    assert int((touching & (new_r < 0.5 * old_r)).sum()) > 10              # rolling spring at its limit
    assert int((touching & (new_r > 0.9 * old_r)).sum()) > 10              # rolling spring below it
    assert bool((torch_out[2].walls.tangential.norm(dim=-1) > 0).any())    # touching walls
    member = state.pairs.i // system.n_spheres
    assert bool((member != 0).any()) and system.grid.is_periodic
    assert not system.spheres_are_bodies


@pytest.mark.parametrize("rolling_stiffness", ["tangential", "ai2011"])
def test_cpp_contact_kernels_equal_torch_eager_for_single_spheres(extension, rolling_stiffness):
    """Single spheres take the C++ kernel's centred path (lever arms from the sphere centres,
    the partner at the touching periodic image): same forces, torques and springs."""
    system, state = _system(rolling_stiffness=rolling_stiffness, clumps=0.0, size=1.3)
    assert system.spheres_only
    state, xs, omega = _with_history(system, state)
    torch_out, cpp_out = _both(system, state, xs, omega)
    _assert_close(_outputs(cpp_out), _outputs(torch_out), 1e-12)
    touching = _touching(system, state, xs)
    p = state.pairs
    across = (xs[p.j] - xs[p.i]).abs().max(dim=-1).values > 0.5 * float(system.grid.period.max())
    assert int(touching.sum()) > 100 and int((touching & across).sum()) > 5   # contacts through the period
    assert float(torch_out[1].abs().max()) > 0                                 # torques, i.e. lever arms
    # sphere k is body k here, so the kernels read the sphere indices as body indices; through the
    # pairs' own body arrays they give the same bits
    assert system.spheres_are_bodies and torch.equal(state.pairs.body_i, state.pairs.i)
    system.__dict__["spheres_are_bodies"] = False          # the cached property, overridden
    own = contact_forces(system, state, xs, omega, 0.0, Kernels(backend="cpp"))
    for name, value in _outputs(own).items():
        assert torch.equal(value, _outputs(cpp_out)[name]), name


# SJKR k_c (J/m^3) of the sphere pairs and the sphere-wall pairs per member (E* of glass-glass is
# 1.3e8 Pa): up to the mechanism's prior of 1 % E* and beyond; member 3 of the sphere-wall pairs none.
COHESION = ([2e6, 5e6, 1e7, 1e6], [1e7, 0.0, 3e6, 1e6])


@pytest.mark.parametrize("dtype, rel", [(F64, 1e-12), (torch.float32, 1e-4)])
@pytest.mark.parametrize("clumps", [0.0, 0.3])
def test_cpp_cohesion_equals_torch_cohesion(extension, dtype, rel, clumps):
    """The C++ kernels add the SJKR cohesion inside their contact law (pairs: the 7th row of the
    lookup table; walls: per contact); the torch kernels in a pass of their own. Same forces and
    torques to rounding, and the cohesion moves them by far more than that."""
    system, state = _system(dtype=dtype, clumps=clumps, cohesion=COHESION)
    assert system.has_cohesion and system.pair_lookup[-1].shape[0] == 7
    state, xs, omega = _with_history(system, state)
    torch_out, cpp_out = _both(system, state, xs, omega)
    _assert_close(_outputs(cpp_out), _outputs(torch_out), rel)
    plain_system, plain_state = _system(dtype=dtype, clumps=clumps)
    assert not plain_system.has_cohesion and plain_system.pair_lookup[-1].shape[0] == 6
    plain_state, plain_xs, _ = _with_history(plain_system, plain_state)
    assert torch.equal(plain_xs, xs)
    plain = contact_forces(plain_system, plain_state, xs, omega, 0.0, Kernels(backend="cpp"))
    def moved(k):  # 0: force, 1: torque
        return float((plain[k] - cpp_out[k]).abs().max()) / float(plain[k].abs().max())

    assert moved(0) > 0.05
    if clumps:
        assert moved(1) > 0.05  # the pull acts at the contact point, off the clump's centre
    else:
        assert moved(1) <= 10 * rel  # a sphere's pull points at its centre: no torque
    # the springs do not feel cohesion (its force is not in the Coulomb or rolling limits)
    for name in ("pair tangential", "pair rolling", "wall tangential", "wall rolling"):
        assert torch.equal(_outputs(plain)[name], _outputs(cpp_out)[name]), name
    # a cohesive call needs the cohesion row
    p = state.pairs
    with pytest.raises(ValueError, match=r"lookup table has shape \(6, "):
        Kernels(backend="cpp").pair(xs, state.bodies.position.reshape(-1, 3), state.bodies.velocity.reshape(-1, 3),
                                    omega, system.zero_body_vectors, system.zero_body_vectors,
                                    p.i, p.j, p.body_i, p.body_j, p.tangential, p.rolling, dt=system.dt_tensor,
                                    period=system.grid.period, stiffness_model="tangential", periodic=True,
                                    lookup=plain_system.pair_lookup, cohesion=p.cohesion)


def test_cpp_contact_kernels_equal_torch_eager_float32(extension):
    system, state = _system(dtype=torch.float32)
    state, xs, omega = _with_history(system, state)
    torch_out, cpp_out = _both(system, state, xs, omega)
    for name, value in _outputs(cpp_out).items():
        assert value.dtype == torch.float32, name
    _assert_close(_outputs(cpp_out), _outputs(torch_out), 1e-4)


def test_cpp_contact_kernels_do_not_depend_on_thread_count(extension):
    system, state = _system(N=120, seed=3)
    state, xs, omega = _with_history(system, state, seed=4)
    threads = torch.get_num_threads()
    results = []
    try:
        for n in (1, 2, 3):
            torch.set_num_threads(n)
            results.append(_outputs(contact_forces(system, state, xs, omega, 0.0, Kernels(backend="cpp"))))
    finally:
        torch.set_num_threads(threads)
    for other in results[1:]:
        for name, value in results[0].items():
            assert torch.equal(value, other[name]), name


def _raw_call(extension, system, state, xs, omega, members, order=None):
    """The C++ pair and wall operators on the state's contacts (optionally reordered), with the
    bodies split into ``members`` for the scatter."""
    p, w, walls = state.pairs, state.walls, system.walls
    if order is not None:
        p = p.set(**{k: getattr(p, k)[order] for k in ("i", "j", "body_i", "body_j", "radius_i", "radius_j",
                                                        "radius_eff", "mass_eff", "young_eff", "shear_eff", "beta",
                                                        "mu_s", "mu_r", "rolling_damping", "rolling_inertia",
                                                        "tangential", "rolling")})
    X = state.bodies.position.reshape(-1, 3)
    V = state.bodies.velocity.reshape(-1, 3)
    zero = torch.zeros_like(X)
    pair = extension.pair_forces(xs, X, V, omega, zero, zero, p.i, p.j, p.body_i, p.body_j, *system.pair_lookup,
                                 p.tangential, p.rolling, system.dt, system.grid.period.tolist(), False,
                                 system.grid.is_periodic, members)
    wall = extension.wall_forces(xs, X, V, omega, zero, zero, w.sphere, w.body, w.wall, walls.centre, walls.axis_u,
                                 walls.axis_v, walls.half_u, walls.half_v, walls.velocity_at(0.0),
                                 walls.active_at(0.0), w.radius, w.mass_eff, w.young_eff, w.shear_eff, w.beta,
                                 w.mu_s, w.mu_r, w.rolling_damping, w.rolling_inertia, w.tangential, w.rolling,
                                 system.dt, False, members)
    return [*pair, *wall]


def test_two_pass_scatter_over_body_ranges_does_not_depend_on_thread_count(extension):
    """The two-pass scatter gives each thread a range of at least 1024 bodies and skips the blocks of
    rows that act on none of them. On 2,400 bodies in lattice order (most blocks meet one range, some
    straddle two), one member on 1, 2 and 3 threads gives the same bits, in spatial and in shuffled
    contact order, and the forces are the torch kernels' to rounding."""
    system, state = _system(B=12, N=200, seed=31, clumps=0.3)
    state, xs, omega = _with_history(system, state, seed=32)
    assert system.batch * system.n_bodies >= 2400 and state.pairs.n > 4000
    threads = torch.get_num_threads()
    shuffled = torch.randperm(state.pairs.n, generator=torch.Generator().manual_seed(33))
    results = {}
    try:
        for n in (1, 2, 3):
            torch.set_num_threads(n)
            for order in ("lattice", "shuffled"):
                results[n, order] = _raw_call(extension, system, state, xs, omega, members=1,
                                              order=None if order == "lattice" else shuffled)
    finally:
        torch.set_num_threads(threads)
    for (n, order), outputs in results.items():
        for k, (a, b) in enumerate(zip(outputs, results[1, order])):
            assert torch.equal(a, b), (n, order, k)
    torch_force = contact_forces(system, state, xs, omega, 0.0, Kernels(backend="torch"))[0]
    lattice = results[1, "lattice"]
    assert float((lattice[0] + lattice[4] - torch_force).abs().max()) <= 1e-12 * float(torch_force.abs().max())


def test_cpp_member_partition_equals_two_passes_bitwise(extension):
    """Threads owning whole members (one pass) give bitwise the two-pass result, for 1 and 2
    threads; contacts not grouped by member fall back to two passes (same result again). The
    reference is one member on two threads, which always takes two passes; one member on one
    thread (a campaign worker) takes the one-pass path and must equal it too."""
    system, state = _system(B=4, N=120, seed=6)
    state, xs, omega = _with_history(system, state, seed=7)
    assert state.pairs.n > 500 and state.walls.n > 30
    threads = torch.get_num_threads()
    shuffled = torch.randperm(state.pairs.n, generator=torch.Generator().manual_seed(8))
    try:
        torch.set_num_threads(2)
        two_pass = _raw_call(extension, system, state, xs, omega, members=1)
        mixed_ref = _raw_call(extension, system, state, xs, omega, members=1, order=shuffled)
        for n in (1, 2):
            torch.set_num_threads(n)
            for members in (1, 2, 4):
                one_pass = _raw_call(extension, system, state, xs, omega, members=members)
                for a, b in zip(one_pass, two_pass):
                    assert torch.equal(a, b), (n, members)
            for members in (1, 4):
                mixed = _raw_call(extension, system, state, xs, omega, members=members, order=shuffled)
                for a, b in zip(mixed, mixed_ref):
                    assert torch.equal(a, b), (n, members)
    finally:
        torch.set_num_threads(threads)
    # The per-member scatter changes nothing but the schedule: the forces are the torch ones.
    torch_force = contact_forces(system, state, xs, omega, 0.0, Kernels(backend="torch"))[0]
    scale = float(torch_force.abs().max())
    assert float((two_pass[0] + two_pass[4] - torch_force).abs().max()) <= 1e-12 * scale


def _unfused(system, state, xs, omega, kernels):
    """contact_forces then the kick: the two calls that forces_and_kick fuses."""
    from torchdem.integrate import contact_forces

    force, torque, after = contact_forces(system, state, xs, omega, 0.0, kernels)
    b = state.bodies
    f, tau, v, L = kernels.kick(force, torque, b.velocity, b.angular_momentum, system.mass, system.gravity,
                                b.active, system.dt_tensor)
    return after.set(bodies=b.set(force=f, torque=tau, velocity=v, angular_momentum=L))


def _step_outputs(state):
    b, p, w = state.bodies, state.pairs, state.walls
    return {"force": b.force, "torque": b.torque, "velocity": b.velocity, "momentum": b.angular_momentum,
            "pair tangential": p.tangential, "pair rolling": p.rolling, "wall tangential": w.tangential,
            "wall rolling": w.rolling}


@pytest.mark.parametrize("dtype", [F64, torch.float32])
@pytest.mark.parametrize("clumps, cohesion", [(0.0, None), (0.3, None), (0.3, COHESION)])
def test_fused_forces_and_kick_equal_the_three_calls_bitwise(extension, dtype, clumps, cohesion):
    """forces_and_kick (pairs, walls and kick of each member in one pass) gives the same bits as
    pair_forces, wall_forces and kick one after the other: spheres (sphere k is body k) and
    clumps, with and without cohesion, with inactive bodies, for 1, 2 and 3 threads, and for
    contacts that do not split into members (fallback to the three calls). It also equals the
    torch kernels to rounding."""
    from torchdem.integrate import forces_and_kick

    system, state = _system(dtype=dtype, B=4, N=90, seed=21, clumps=clumps, cohesion=cohesion)
    state, xs, omega = _with_history(system, state, seed=22)
    state = state.set(bodies=state.bodies.set(active=state.bodies.active.clone().index_fill_(1, torch.tensor([5]), False)))
    assert state.pairs.n > 300 and state.walls.n > 20 and system.has_cohesion == (cohesion is not None)
    cpp = Kernels(backend="cpp")
    assert cpp.fuses(xs) and not Kernels(backend="torch").fuses(xs)
    reference = _step_outputs(_unfused(system, state, xs, omega, cpp))
    threads = torch.get_num_threads()
    try:
        for n in (1, 2, 3):
            torch.set_num_threads(n)
            fused = _step_outputs(forces_and_kick(system, state, xs, omega, 0.0, cpp))
            for name, value in reference.items():
                assert torch.equal(fused[name], value), (n, name)
    finally:
        torch.set_num_threads(threads)
    # pairs shuffled across members: the fused kernel cannot give members to threads
    order = torch.randperm(state.pairs.n, generator=torch.Generator().manual_seed(23))
    p = state.pairs
    shuffled = state.set(pairs=p.set(**{k: getattr(p, k)[order] for k in (
        "i", "j", "body_i", "body_j", "radius_i", "radius_j", "radius_eff", "mass_eff", "young_eff", "shear_eff",
        "beta", "mu_s", "mu_r", "rolling_damping", "rolling_inertia", "tangential", "rolling")}))
    fused = _step_outputs(forces_and_kick(system, shuffled, xs, omega, 0.0, cpp))
    for name, value in _step_outputs(_unfused(system, shuffled, xs, omega, cpp)).items():
        assert torch.equal(fused[name], value), name
    eager = _step_outputs(forces_and_kick(system, state, xs, omega, 0.0, Kernels(backend="torch")))
    rel = 1e-12 if dtype == F64 else 1e-4
    for name, value in reference.items():
        assert float((value - eager[name]).abs().max()) <= rel * float(eager[name].abs().max()), name


def test_fused_forces_and_kick_reject_bad_indices(extension):
    """A bad index in either list fails the fused call with the error of its own kernel."""
    from torchdem.integrate import forces_and_kick

    system, state = _system(B=2, N=60)
    state, xs, omega = _with_history(system, state)
    cpp = Kernels(backend="cpp")
    p, w = state.pairs, state.walls
    bad_pairs = state.set(pairs=p.set(j=p.j.clone().fill_(xs.shape[0])))
    with pytest.raises(RuntimeError, match="pair_forces: .* outside"):
        forces_and_kick(system, bad_pairs, xs, omega, 0.0, cpp)
    bad_walls = state.set(walls=w.set(wall=w.wall.clone().fill_(system.walls.n)))
    with pytest.raises(RuntimeError, match="wall_forces: .* out of range"):
        forces_and_kick(system, bad_walls, xs, omega, 0.0, cpp)


def test_cpp_kernels_reject_bad_indices(extension):
    system, state = _system(N=30)
    state, xs, omega = _with_history(system, state)
    p = state.pairs
    bad = state.set(pairs=p.set(body_j=p.body_j.clone().fill_(system.batch * system.n_bodies)))
    with pytest.raises(RuntimeError, match="outside"):
        contact_forces(system, bad, xs, omega, 0.0, Kernels(backend="cpp"))
    # a pair-table row beyond the table (the constants are looked up per touching pair)
    radius, mass, inertia, pair_row, material, table = system.pair_lookup
    X = state.bodies.position.reshape(-1, 3)
    zero = torch.zeros_like(X)
    with pytest.raises(RuntimeError, match="columns of the material-pair table"):
        extension.pair_forces(xs, X, state.bodies.velocity.reshape(-1, 3), omega, zero, zero, p.i, p.j, p.body_i,
                              p.body_j, radius, mass, inertia, pair_row + table.shape[1], material, table,
                              p.tangential, p.rolling, system.dt, system.grid.period.tolist(), False,
                              system.grid.is_periodic, 1)


def test_run_with_cpp_kernels_equals_run_with_torch_kernels(extension):
    def run(backend):
        # Overlapping start: the released elastic energy (which the energy guard does not count)
        # throws particles apart through many collisions and list rebuilds; guards relaxed.
        system, state = _system(B=2, N=40, seed=5, spacing=0.01, size=0.9)
        guards = GuardSettings(energy_tolerance=1e3, max_speed=1e3)
        return Simulation(system, state, guards, backend=backend).advance(300)

    ref, cpp = run("torch"), run("cpp")
    assert ref.state.pairs.n > 0 and ref.state.walls.n > 0 and ref.state.rebuilds > 20
    assert torch.allclose(cpp.state.bodies.position, ref.state.bodies.position, rtol=0, atol=1e-9)
    assert torch.allclose(cpp.state.bodies.orientation, ref.state.bodies.orientation, rtol=0, atol=1e-7)
    assert cpp.state.rebuilds == ref.state.rebuilds


def test_lists_built_for_the_cpp_kernels_leave_the_per_pair_constants_to_the_torch_path(extension, tmp_path):
    """A rebuild inside a C++ step writes the list's index only (the kernel looks the constants up
    per sphere): the per-pair constants are None. Whatever needs them gets them from the system:
    the torch kernels continuing the run (the same trajectory as the C++ kernels, to rounding), the
    energy, a checkpoint reloaded (None saved as None)."""
    from torchdem.integrate import PAIR_VALUES, with_pair_values
    from torchdem.simulation import elastic_energy

    system, state = _system(B=2, N=40, seed=5, spacing=0.01, size=0.9)
    guards = GuardSettings(energy_tolerance=1e3, max_speed=1e3)
    sim = Simulation(system, state, guards, backend="cpp").advance(150)
    p = sim.state.pairs
    assert sim.state.rebuilds > 3 and p.n > 0
    assert all(getattr(p, k) is None for k in PAIR_VALUES + system.tables.CONTACT_FIELDS)
    filled = with_pair_values(system, p)
    radius = system.sphere_radius.reshape(-1)
    ri, rj = radius[p.i], radius[p.j]
    assert torch.equal(filled.radius_i, ri) and torch.equal(filled.radius_eff, ri * rj / (ri + rj))
    law = system.tables.gather(system.sphere_pair_row[p.i] + system.sphere_material.reshape(-1)[p.j])
    for k in system.tables.CONTACT_FIELDS:
        assert torch.equal(getattr(filled, k), law[k]), k
    assert torch.equal(elastic_energy(system, sim.state), elastic_energy(system, sim.state.set(pairs=filled)))
    cpp = Simulation(system, sim.state, guards, backend="cpp").advance(100)
    torch_run = Simulation(system, sim.state, guards, backend="torch").advance(100)
    assert torch.allclose(torch_run.state.bodies.position, cpp.state.bodies.position, rtol=0, atol=1e-9)
    sim.save(tmp_path / "s.pt")
    loaded = Simulation.load(tmp_path / "s.pt", system, guards)
    assert loaded.state.pairs.radius_i is None and torch.equal(loaded.state.pairs.key, p.key)
    again = Simulation(system, loaded.state, guards, backend="cpp").advance(100)
    assert torch.equal(again.state.bodies.position, cpp.state.bodies.position)


def test_recycled_outputs_keep_to_memory_of_their_element_size_and_checkpoints_load(extension, tmp_path):
    """A kernel's outputs reuse the memory of its earlier outputs (recycle.h), never memory whose size
    their element size does not divide (123 float32 values are 492 bytes: a float64 tensor over them
    made torch.save write more bytes than its header stated, and the checkpoint did not load). A
    state over memory larger than it uses is saved compact and loads back equal."""
    kernels = Kernels(backend="cpp")

    def kick(dtype, n):
        z = torch.zeros(n, 3, dtype=dtype)
        return kernels.kick(z, z, z, z, torch.ones(n, dtype=dtype), torch.tensor([0.0, 0.0, -9.81], dtype=dtype),
                            torch.ones(n, dtype=torch.bool), torch.tensor(1e-5, dtype=dtype))

    def fresh_thread():  # its pools are empty (they are per thread)
        for _ in range(4):  # every slot then holds 41 x 3 float32 (492 bytes) and nothing else
            kick(torch.float32, 41)
        sizes.extend(t.untyped_storage().nbytes() for t in kick(F64, 20))  # 480 bytes would fit in 492

    sizes = []
    thread = threading.Thread(target=fresh_thread)
    thread.start()
    thread.join()
    assert len(sizes) == 4 and all(n % 8 == 0 for n in sizes), sizes

    system, state = _system(B=2, N=40, seed=5, spacing=0.01, size=0.9)
    guards = GuardSettings(energy_tolerance=1e3, max_speed=1e3)
    sim = Simulation(system, state, guards, backend="cpp").advance(20)
    w = sim.state.walls
    loose = torch.empty(0, dtype=w.tangential.dtype).set_(torch.UntypedStorage(w.tangential.numel() * 8 + 100), 0,
                                                            w.tangential.shape)
    loose.copy_(w.tangential)
    sim.state = sim.state.set(walls=w.set(tangential=loose))
    sim.save(tmp_path / "s.pt")
    loaded = Simulation.load(tmp_path / "s.pt", system, guards)
    assert torch.equal(loaded.state.walls.tangential, w.tangential)


def test_missing_compiler_falls_back_to_torch_kernels_with_one_warning(tmp_path):
    script = textwrap.dedent("""
        import warnings
        import torch
        from test_pair_ext import _system
        from torchdem import _ext
        from torchdem.simulation import GuardSettings, Simulation
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            system, state = _system(B=1, N=12)
            sim = Simulation(system, state).advance(3)
            Simulation(system, state).advance(3)
        messages = [str(w.message) for w in caught if "C++ contact kernels" in str(w.message)]
        assert len(messages) == 1, messages
        assert _ext.cpu_kernels() is None and _ext.build_error()
        assert sim.state.pairs.n > 0
        print("fallback ok")
    """)
    env = dict(os.environ, CXX=str(tmp_path / "no-such-compiler"), TORCH_EXTENSIONS_DIR=str(tmp_path / "ext"),
               PYTHONPATH=os.pathsep.join([str(REPO / "tests"), str(REPO)]))
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "fallback ok" in proc.stdout, proc.stdout + proc.stderr


@pytest.mark.parametrize("dtype, rel", [(F64, 1e-12), (torch.float32, 1e-5)])
def test_cpp_drift_equals_torch_drift(extension, dtype, rel):
    """The C++ drift (half kick, drift, midpoint rotation, sphere positions, angular velocity,
    largest displacement) equals :func:`drift_kernel` for clumps, spheres and inactive bodies."""
    from torchdem.integrate import drift_kernel

    system, state = _system(dtype=dtype, B=3, N=60, seed=9)
    state, xs, omega = _with_history(system, state)
    b = state.bodies
    g = torch.Generator().manual_seed(10)
    force = (torch.randn(b.force.shape, generator=g, dtype=F64) * 1e-2).to(dtype)
    torque = (torch.randn(b.torque.shape, generator=g, dtype=F64) * 1e-5).to(dtype)
    active = b.active.clone()
    active[1, :5] = False
    reference = (xs + 1e-4 * torch.randn(xs.shape, generator=g, dtype=F64).to(dtype))
    dt = torch.tensor(system.dt, dtype=dtype)
    args = (b.position, b.velocity, b.angular_momentum, b.orientation, force, torque, system.mass, system.inertia,
            active, system.sphere_body_flat, system.sphere_offset.reshape(-1, 3), reference, dt)
    assert not system.spheres_only
    ref = drift_kernel(*args, False)
    out = Kernels(backend="cpp").drift(*args, False)
    names = ("x", "v", "L", "q", "xs", "omega", "displacement")
    for name, a, e in zip(names, out, ref):
        assert a.shape == e.shape and a.dtype == e.dtype, name
        scale = float(e.abs().max())
        assert scale > 0 and float((a - e).abs().max()) <= rel * scale, name
    assert torch.equal(out[3][1, :5], b.orientation[1, :5])   # inactive bodies keep their orientation
    # spheres only: no rotation, omega = L / I, sphere = body position
    ref_s = drift_kernel(*args, True)
    out_s = Kernels(backend="cpp").drift(*args, True)
    for name, a, e in zip(names, out_s, ref_s):
        assert float((a - e).abs().max()) <= rel * float(e.abs().max()), name
    # a sphere of a body that does not exist is an error naming it, not a read out of bounds
    sphere_body = system.sphere_body_flat.clone()
    sphere_body[7] = system.batch * system.n_bodies
    with pytest.raises(RuntimeError, match="drift: sphere 7 belongs to body"):
        Kernels(backend="cpp").drift(*args[:9], sphere_body, *args[10:], False)


def _cpp_drift_on_one_and_two_threads(args, spheres_only):
    """The C++ drift of ``args`` on one thread and on two."""
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = Kernels(backend="cpp").drift(*args, spheres_only)
        torch.set_num_threads(2)
        two = Kernels(backend="cpp").drift(*args, spheres_only)
    finally:
        torch.set_num_threads(threads)
    return one, two


@pytest.mark.parametrize("dtype, rel", [(F64, 1e-12), (torch.float32, 1e-5)])
def test_cpp_drift_of_single_spheres_in_one_sweep(extension, dtype, rel):
    """A system of single spheres, each its own body, drifts in one sweep (drift_spheres): every
    output equals :func:`drift_kernel` (inactive spheres stay put), the orientation is the one passed
    in, unchanged, and the result is bitwise the same on 1 and 2 threads; with the sphere-to-body map
    not the identity (spheres of one member swapped) it takes the two-pass path and still equals it."""
    from torchdem.integrate import drift_kernel

    system, state = _system(dtype=dtype, B=3, N=150, seed=5, clumps=0.0)
    assert system.spheres_are_bodies
    b = state.bodies
    g = torch.Generator().manual_seed(6)
    force = (torch.randn(b.force.shape, generator=g, dtype=F64) * 1e-2).to(dtype)
    torque = (torch.randn(b.torque.shape, generator=g, dtype=F64) * 1e-5).to(dtype)
    active = b.active.clone()
    active[2, 10:20] = False
    xs = sphere_positions(system, b)
    reference = xs + (1e-4 * torch.randn(xs.shape, generator=g, dtype=F64)).to(dtype)
    dt = torch.tensor(system.dt, dtype=dtype)
    orientation = b.orientation.clone()
    args = [b.position, b.velocity, b.angular_momentum, orientation, force, torque, system.mass, system.inertia,
            active, system.sphere_body_flat, system.sphere_offset.reshape(-1, 3), reference, dt]
    names = ("x", "v", "L", "q", "xs", "omega", "displacement")
    ref = drift_kernel(*args, True)
    one, two = _cpp_drift_on_one_and_two_threads(args, True)
    for name, a, c, e in zip(names, one, two, ref):
        assert a.shape == e.shape and torch.equal(a, c), name
        assert float((a - e).abs().max()) <= rel * float(e.abs().max()), name
    assert one[3] is orientation and torch.equal(orientation, b.orientation)
    assert torch.equal(one[0][2, 10:20], b.position[2, 10:20])
    # spheres 0 and 1 of member 1 swapped between bodies: not its own body, so the two passes
    sphere_body = system.sphere_body_flat.clone()
    first = system.n_bodies
    sphere_body[first], sphere_body[first + 1] = first + 1, first
    swapped = [*args[:9], sphere_body, args[10], reference, dt]
    ref_w = drift_kernel(*swapped, True)
    out_w = Kernels(backend="cpp").drift(*swapped, True)
    for name, a, e in zip(names, out_w, ref_w):
        assert float((a - e).abs().max()) <= rel * float(e.abs().max()), name
    assert torch.equal(out_w[4][first], out_w[0].reshape(-1, 3)[first + 1])  # sphere 0 sits on body 1
    assert out_w[3] is not orientation and torch.equal(out_w[3], orientation)


@pytest.mark.parametrize("dtype, rel", [(F64, 1e-12), (torch.float32, 1e-5)])
def test_cpp_drift_lanes_fast_spin_and_threads(extension, dtype, rel):
    """The C++ drift runs bodies in blocks of 16 lanes and hands a body turning by 0.2 rad or more
    in one step (beyond its rotation series) to the scalar path: spheres and clumps spinning that
    fast, beside slow ones in the same blocks, still equal :func:`drift_kernel`; and every output
    is bitwise the same on 1 and 2 threads (the blocks are fixed by body index)."""
    from torchdem.integrate import drift_kernel

    system, state = _system(dtype=dtype, B=3, N=61, seed=21)  # 183 bodies: a last block of 7
    b = state.bodies
    dt = torch.tensor(system.dt, dtype=dtype)
    L = b.angular_momentum.clone()
    fast = torch.zeros(L.shape[:2], dtype=torch.bool)
    fast[0, 3:40:4] = fast[2, -5:] = True  # in blocks of slow bodies, and in the last block
    inertia = system.inertia.reshape(L.shape)
    # |omega| dt of 0.3-1.2 rad: omega ~ L / I
    turn = (0.3 + 0.9 * torch.rand(L.shape[:2], generator=torch.Generator().manual_seed(3), dtype=F64)).to(dtype)
    direction = L / L.norm(dim=-1, keepdim=True)
    L = torch.where(fast[..., None], direction * inertia.min(dim=-1, keepdim=True).values * (turn / dt)[..., None], L)
    force = torch.zeros_like(b.force)
    torque = torch.zeros_like(b.torque)
    xs = sphere_positions(system, b)
    args = (b.position, b.velocity, L, b.orientation, force, torque, system.mass, system.inertia, b.active,
            system.sphere_body_flat, system.sphere_offset.reshape(-1, 3), xs, dt)
    ref = drift_kernel(*args, False)
    one, two = _cpp_drift_on_one_and_two_threads(args, False)
    names = ("x", "v", "L", "q", "xs", "omega", "displacement")
    for name, a, c, e in zip(names, one, two, ref):
        assert torch.equal(a, c), name
        scale = float(e.abs().max())
        assert float((a - e).abs().max()) <= rel * scale, name
    q_new = one[3]
    angle = 2 * torch.acos((q_new * b.orientation).sum(-1).abs().clamp(max=1))
    assert float(angle[fast].min()) > 0.2 and float(angle[~fast].max()) < 0.05  # the fast bodies did turn fast


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_cpp_kick_equals_torch_kick(extension, dtype):
    """The C++ kick (gravity, inactive bodies masked, second half kick) equals :func:`kick_kernel`
    to rounding, with inactive bodies getting zero force and torque and keeping their velocity."""
    from torchdem.integrate import kick_kernel

    system, state = _system(dtype=dtype, B=3, N=60, seed=11)
    b = state.bodies
    g = torch.Generator().manual_seed(12)
    B, Nb = system.batch, system.n_bodies
    force = (torch.randn(B * Nb, 3, generator=g, dtype=F64) * 1e-2).to(dtype)
    torque = (torch.randn(B * Nb, 3, generator=g, dtype=F64) * 1e-5).to(dtype)
    velocity = torch.randn(b.velocity.shape, generator=g, dtype=F64).to(dtype)
    active = b.active.clone()
    active[2, 3:9] = False
    args = (force, torque, velocity, b.angular_momentum, system.mass, system.gravity, active,
            torch.tensor(system.dt, dtype=dtype))
    ref = kick_kernel(*args)
    out = Kernels(backend="cpp").kick(*args)
    rel = 1e-12 if dtype == F64 else 1e-5
    for name, a, e in zip(("f", "tau", "v", "L"), out, ref):
        assert a.shape == e.shape and a.dtype == e.dtype, name
        assert float((a - e).abs().max()) <= rel * float(e.abs().max()), name
    assert torch.equal(out[0][2, 3:9], torch.zeros_like(out[0][2, 3:9]))
    assert torch.equal(out[2][2, 3:9], velocity[2, 3:9])


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_cpp_pair_constants_equal_torch(extension, dtype, monkeypatch):
    """The per-pair constants of a rebuilt list (key, bodies, radii, R*, m*, I_r*, the material
    tables of three members with different coefficients) from the C++ pass equal those of the
    tensor operations bit for bit (same IEEE operations, same order); bad indices raise."""
    from torchdem import integrate
    from torchdem.neighbors import find_pairs

    system, state = _system(dtype=dtype, B=3, N=60, seed=13)
    xs = sphere_positions(system, state.bodies)
    radius, body = system.sphere_radius.reshape(-1), system.sphere_body_flat
    i, j = find_pairs(xs, radius, body, torch.ones_like(radius, dtype=torch.bool), system.n_spheres, system.grid,
                      system.skin)
    assert i.numel() > 100 and len({int(m) for m in i // system.n_spheres}) == 3
    args = [i, j, radius, system.sphere_mass, system.sphere_rolling_inertia, body, system.sphere_pair_row,
            system.sphere_material.reshape(-1), system.tables]
    cpp = integrate.pair_constants(*args)
    monkeypatch.setattr(integrate._ext, "kernels_for", lambda device, enabled=True: None)
    ref = integrate.pair_constants(*args)
    assert set(cpp) == set(ref) and len(ref) == 8 + len(system.tables.CONTACT_FIELDS)
    for name in ref:
        assert cpp[name].dtype == ref[name].dtype and torch.equal(cpp[name], ref[name]), name
    assert float(ref["mu_s"].std()) > 0   # the members' coefficients differ, so the table lookup is exercised
    bad = i.clone()
    bad[7] = radius.numel()
    with pytest.raises(RuntimeError, match="outside"):
        extension.pair_constants(bad, *args[1:-1], system.tables.stacked)


def test_kernel_outputs_recycle_only_memory_nobody_references(extension):
    """The step kernels recycle the memory of outputs the caller has dropped (no fresh pages, so
    no page faults, per step) and never that of outputs still referenced: a kept result, or a
    view of one, keeps its values through later calls. The pools are per thread, so the check runs
    in a thread of its own: in the test process's main thread, storages freed by earlier tests can
    be handed out first (the order of tests decided it)."""
    import threading

    failures = []

    def body():
        try:
            _recycle_checks(extension)
        except BaseException as exc:  # re-raised in the test's thread
            failures.append(exc)

    worker = threading.Thread(target=body)
    worker.start()
    worker.join()
    if failures:
        raise failures[0]


def _recycle_checks(extension):
    g = torch.Generator().manual_seed(31)
    N = 5000
    mass = 1 + torch.rand(N, generator=g, dtype=F64)
    gravity = torch.tensor([0.0, 0.0, -9.81], dtype=F64)
    active = torch.ones(N, dtype=torch.bool)

    def kick(scale):
        force = scale * torch.randn(N, 3, generator=g, dtype=F64)
        return extension.kick(force, force, force, force, mass, gravity, active, 1e-3)

    kept = kick(1.0)
    kept_copy = [t.clone() for t in kept]
    view = kick(2.0)[2][10:20]                   # only a view survives of this call's velocity
    view_copy = view.clone()
    dropped = kick(3.0)
    dropped_ptr = dropped[0].data_ptr()
    del dropped
    again = kick(4.0)
    assert again[0].data_ptr() == dropped_ptr    # the dropped force's memory is handed out again
    for _ in range(5):
        kick(5.0)
    for a, b in zip(kept, kept_copy):
        assert torch.equal(a, b)
    assert torch.equal(view, view_copy)
    assert again[0].shape == (N, 3) and again[0].is_contiguous()


def test_every_checkout_has_a_build_of_its_own(tmp_path, monkeypatch):
    """The extension's name hashes the sources' directory too: torch's build file names the
    sources by path, so two checkouts of the same sources under one name rebuilt each other's
    objects (and a build killed in one left a lock the other waited on)."""
    import importlib.util
    import shutil

    from torchdem import _ext

    copy = tmp_path / "other_checkout" / "_ext"
    shutil.copytree(Path(_ext.__file__).parent, copy, ignore=shutil.ignore_patterns("__pycache__"))
    spec = importlib.util.spec_from_file_location("torchdem_ext_copy", copy / "__init__.py")
    other = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(other)
    assert other._module_name() != _ext._module_name()
    assert other._module_name().startswith("torchdem_cpu_") and _ext._module_name() == _ext._module_name()
