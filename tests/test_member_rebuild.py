"""Each ensemble member rebuilds its own neighbour lists (torchdem/integrate.py, step 3).

- Rebuilding only the members whose skin criterion fired gives the same trajectories, bit for
  bit, as rebuilding every member whenever one needs it: 1,000 steps, float64, two members that
  move differently, single spheres and three-sphere clumps, a piston that moves for the first
  200 steps and then stands. A pair list holds pairs within contact distance plus the skin and
  springs reset when a pair does not touch, so when a member's list was built cannot change a
  force; the assertion is exact equality, and the run must have made partial rebuilds.
- Partial rebuilds build fewer member lists: the member rebuilds counted are below
  members x rebuild events of the all-member rule.
- While the piston moves, every rebuild rebuilds every member (the walls' shift at the last
  build is one record for the ensemble).
- A partial rebuild keeps the other member's lists, history and reference positions as they
  were (bit for bit), and its own lists equal a full rebuild's.
"""
import torch

from conftest import F64, glass, steel
from torchdem import integrate
from torchdem.clumps import SPHERE
from torchdem.materials import interaction_table
from torchdem.mixture import trilobe_template
from torchdem.simulation import GuardSettings, Simulation
from torchdem.system import build_system
from torchdem.walls import WallSpec, box_walls

N = 64
DT = 2e-5
PISTON_STEPS = 200


def _system():
    """Two members of 64 bodies (every third a trilobe) in a box; a piston moves down for
    PISTON_STEPS steps, then stands. The members start from different packings and velocities."""
    B = 2
    mats = [glass(), steel()]
    pp = dict(mu_s=[0.3, 0.6], mu_r=[0.02, 0.1], restitution=[0.4, 0.8], rolling_damping=0.3)
    table = interaction_table(mats, {("glass", "glass"): pp, ("glass", "steel"): pp}, batch=B)
    pos, vel, scale = [], [], []
    for m in range(B):
        g = torch.Generator().manual_seed(11 + m)
        k = torch.randperm(N, generator=g)
        p = torch.stack([k % 4, (k // 4) % 4, k // 16], -1).to(F64) * 0.012 + 0.008
        pos.append(p + 0.002 * (torch.rand(N, 3, generator=g, dtype=F64) - 0.5))
        vel.append((0.2 + 0.4 * m) * torch.randn(N, 3, generator=g, dtype=F64))
        u = torch.rand(N, generator=g, dtype=F64)
        scale.append(torch.where(torch.arange(N) % 3 == 0, 0.009 + 0.001 * u, 0.004 + 0.001 * u))
    template_index = (torch.arange(N) % 3 == 0).long().expand(B, N)
    piston = WallSpec("piston", (0.025, 0.025, 0.07), (0, 0, 1), (1, 0, 0), 0.03, 0.03, "steel",
                      velocity=(0.0, 0.0, -0.5), move_from=0.0, move_until=PISTON_STEPS * DT)
    return build_system(torch.stack(pos), torch.zeros(B, N, dtype=torch.long), mats, table,
                        templates=[SPHERE, trilobe_template(0.15)], template_index=template_index,
                        scale=torch.stack(scale), velocity=torch.stack(vel),
                        walls=[*box_walls("box", (0, 0, 0), (0.05, 0.05, 0.3), "steel"), piston],
                        dt=DT, domain=((-0.01, -0.01, -0.01), (0.06, 0.06, 0.31)))


def _counting(monkeypatch, everyone: bool):
    """Patch integrate.rebuild to log the members each call rebuilds (every member if ``everyone``)."""
    original = integrate.rebuild
    calls = []

    def logged(system, state, xs, time, members=None):
        chosen = [True] * system.batch if everyone or members is None else list(members)
        calls.append((int(state.step), chosen))
        return original(system, state, xs, time, None if everyone else members)

    monkeypatch.setattr(integrate, "rebuild", logged)
    return calls


def test_partial_rebuilds_follow_the_all_member_trajectories_bit_for_bit(monkeypatch):
    runs = {}
    for everyone in (True, False):
        calls = _counting(monkeypatch, everyone)
        sim = Simulation(*_system(), GuardSettings(check_every=100))
        sim.advance(1000)
        runs[everyone] = (sim.state, calls)
        monkeypatch.undo()
    full, full_calls = runs[True]
    part, part_calls = runs[False]
    partial = [c for c in part_calls if not all(c[1])]
    assert partial, "no partial rebuild happened: the test would not test them"
    assert torch.equal(part.bodies.position, full.bodies.position)
    assert torch.equal(part.bodies.velocity, full.bodies.velocity)
    assert torch.equal(part.bodies.angular_momentum, full.bodies.angular_momentum)
    assert torch.equal(part.bodies.orientation, full.bodies.orientation)
    # fewer member lists built, and none partial while the piston moved
    assert sum(sum(m) for _, m in part_calls) < sum(sum(m) for _, m in full_calls)
    assert all(step > PISTON_STEPS for step, _ in partial)


def test_partial_rebuild_keeps_the_other_members_lists_and_matches_a_full_one_for_its_own():
    system, state = _system()
    sim = Simulation(system, state)
    sim.advance(PISTON_STEPS + 100)
    st = sim.state
    xs = integrate.sphere_positions(system, st.bodies)
    part, _ = integrate.rebuild(system, st, xs, st.step * DT, [True, False])
    full, _ = integrate.rebuild(system, st, xs, st.step * DT)
    S = system.batch * system.n_spheres
    Ns = system.n_spheres
    second_old = st.pairs.i >= Ns
    second_new = part.pairs.i >= Ns
    assert torch.equal(part.pairs.key[second_new], st.pairs.key[second_old])
    assert torch.equal(part.pairs.tangential[second_new], st.pairs.tangential[second_old])
    assert torch.equal(part.pairs.rolling[second_new], st.pairs.rolling[second_old])
    assert torch.equal(part.reference[Ns:], st.reference[Ns:]) and torch.equal(part.reference[:Ns], xs[:Ns])
    first = full.pairs.i < Ns
    for name in ("key", "i", "j", "tangential", "rolling", "mu_s", "radius_eff", "mass_eff"):
        assert torch.equal(getattr(part.pairs, name)[~second_new], getattr(full.pairs, name)[first]), name
    assert bool(torch.all(part.pairs.key[1:] > part.pairs.key[:-1]))          # sorted, unique
    assert torch.equal(part.pairs.key, part.pairs.i * S + part.pairs.j)
    wfirst_part = part.walls.sphere < Ns
    wfirst_full = full.walls.sphere < Ns
    assert torch.equal(part.walls.key[wfirst_part], full.walls.key[wfirst_full])
    assert torch.equal(part.walls.key[~wfirst_part], st.walls.key[st.walls.sphere >= Ns])
    assert bool(torch.all(part.walls.key[1:] > part.walls.key[:-1]))
