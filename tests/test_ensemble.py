"""The ensemble axis: B members in one tensor program give the same trajectories as B solo
runs (float64, agreement to 1e-12 relative), with per-member friction, rolling friction,
restitution and density. A blow-up in one member is reported by member and step, and in
"isolate" mode the other members carry on unchanged.
"""
import gc

import pytest
import torch

from conftest import F64, glass, steel
from torchdem.errors import BlowUpError
from torchdem.materials import interaction_table
from torchdem.simulation import GuardSettings, Simulation
from torchdem.system import build_system
from torchdem.walls import box_walls

N = 60


def _initial(seed):
    g = torch.Generator().manual_seed(seed)
    k = torch.arange(N)
    pos = torch.stack([k % 4, (k // 4) % 4, k // 16], -1).to(F64) * 0.012 + 0.008
    pos = pos + 0.002 * (torch.rand(N, 3, generator=g, dtype=F64) - 0.5)
    radius = 0.004 + 0.001 * torch.rand(N, generator=g, dtype=F64)
    vel = 0.3 * torch.randn(N, 3, generator=g, dtype=F64)
    return pos, radius, vel


PARAMS = [dict(mu_s=0.3, mu_r=0.02, restitution=0.4, density=2500.0),
          dict(mu_s=0.6, mu_r=0.10, restitution=0.8, density=3600.0),
          dict(mu_s=0.45, mu_r=0.06, restitution=0.6, density=3000.0)]


def _build(members, seeds, guards=GuardSettings(check_every=100), velocity_scale=None):
    B = len(members)
    mats = [glass(), steel()]
    pick = lambda k: [m[k] for m in members]  # noqa: E731
    pp = dict(mu_s=pick("mu_s"), mu_r=pick("mu_r"), restitution=pick("restitution"), rolling_damping=0.3)
    table = interaction_table(mats, {("glass", "glass"): pp, ("glass", "steel"): pp}, batch=B,
                              density={"glass": pick("density")})
    init = [_initial(s) for s in seeds]
    pos = torch.stack([i[0] for i in init])
    radius = torch.stack([i[1] for i in init])
    vel = torch.stack([i[2] for i in init])
    if velocity_scale is not None:
        vel = vel * torch.tensor(velocity_scale, dtype=F64)[:, None, None]
    system, state = build_system(pos, torch.zeros(B, N, dtype=torch.long), mats, table, radius=radius,
                                 velocity=vel, walls=box_walls("box", (0, 0, 0), (0.05, 0.05, 0.3), "steel"),
                                 dt=2e-5, domain=((-0.01, -0.01, -0.01), (0.06, 0.06, 0.31)))
    return Simulation(system, state, guards)


def test_batched_ensemble_equals_members_run_alone():
    seeds = [1, 2, 3]
    batched = _build(PARAMS, seeds).advance(600)
    assert batched.state.pairs.n > 0
    for b, (p, s) in enumerate(zip(PARAMS, seeds)):
        solo = _build([p], [s]).advance(600)
        assert torch.allclose(batched.state.bodies.position[b], solo.state.bodies.position[0], rtol=1e-12, atol=1e-14)
        assert torch.allclose(batched.state.bodies.velocity[b], solo.state.bodies.velocity[0], rtol=1e-10, atol=1e-12)
    # Members really differ (different parameters and seeds give different trajectories).
    assert not torch.allclose(batched.state.bodies.position[0], batched.state.bodies.position[1])


def test_blowup_names_member_and_step():
    sim = _build(PARAMS, [1, 2, 3], velocity_scale=[1.0, 400.0, 1.0])
    with pytest.raises(BlowUpError) as err:
        sim.advance(300)
    assert err.value.member == 1
    assert err.value.step == 100
    assert "member 1" in str(err.value) and "step 100" in str(err.value)
    fastest = int(sim.state.bodies.velocity[1].norm(dim=-1).argmax())
    assert f"at t = {sim.time:.4g} s the fastest body is {fastest} at (" in str(err.value)


def test_isolated_blowup_leaves_other_members_untouched():
    sim = _build(PARAMS, [1, 2, 3], GuardSettings(check_every=100, on_blowup="isolate"),
                 velocity_scale=[1.0, 400.0, 1.0])
    sim.advance(600)
    assert set(sim.failed) == {1}
    assert not bool(sim.state.bodies.active[1].any())
    solo = _build([PARAMS[0]], [1]).advance(600)
    assert torch.allclose(sim.state.bodies.position[0], solo.state.bodies.position[0], rtol=1e-12, atol=1e-14)


def test_stepping_creates_no_reference_cycles_and_restores_the_collector():
    """advance() pauses Python's cyclic collector; that is only sound if a step leaves no cycles
    behind (they would pile up until advance returns). Stepping with rebuilds and wall contacts
    leaves none, and the collector's state is restored either way."""
    sim = _build(PARAMS[:2], [1, 2]).advance(5)
    rebuilds = sim.state.rebuilds
    assert gc.isenabled()
    gc.collect()
    gc.disable()
    try:
        sim.advance(300)
        assert not gc.isenabled()
        assert sim.state.rebuilds > rebuilds and sim.state.walls.n > 0
        assert gc.collect() == 0
    finally:
        gc.enable()
    sim.advance(1)
    assert gc.isenabled()
