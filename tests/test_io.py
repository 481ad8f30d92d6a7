"""Trajectory output and save/restore.

- A VTK frame holds every active sphere with id, material, radius and velocity, and reads
  back to the simulated values.
- Saving mid-run and restoring continues the run bit-for-bit (contact history included),
  so an interrupted run loses nothing.
"""
import numpy as np
import torch

from conftest import F64, glass, steel
from torchdem.clumps import ClumpTemplate
from torchdem.integrate import sphere_positions
from torchdem.io import VTKWriter, read_vtk_points
from torchdem.materials import interaction_table
from torchdem.simulation import Simulation
from torchdem.system import build_system
from torchdem.walls import box_walls

TRI = ClumpTemplate("tri", np.array([[0, 0, 0], [0.006, 0, 0], [0.003, 0.005, 0]]), np.array([0.004, 0.004, 0.0035]))


def _sim():
    B, N = 2, 18
    g = torch.Generator().manual_seed(5)
    k = torch.arange(N)
    pos = (torch.stack([k % 3, (k // 3) % 3, k // 9], -1).to(F64) * 0.02 + 0.0105).expand(B, N, 3).clone()
    pos += 0.001 * torch.rand(pos.shape, generator=g, dtype=F64)
    mats = [glass(), steel()]
    pp = dict(mu_s=0.5, mu_r=0.05, restitution=0.5, rolling_damping=0.3)
    table = interaction_table(mats, {("glass", "glass"): pp, ("glass", "steel"): pp}, batch=B)
    template_index = (torch.arange(N) % 2).expand(B, N).clone()  # spheres and clumps mixed
    scale = torch.where(template_index == 0, 0.005, 1.0).to(F64)
    system, state = build_system(pos, torch.zeros(B, N, dtype=torch.long), mats, table,
                                 templates=[ClumpTemplate("sphere", np.zeros((1, 3)), np.ones(1)), TRI],
                                 template_index=template_index, scale=scale,
                                 velocity=torch.randn(B, N, 3, generator=g, dtype=F64),
                                 walls=box_walls("box", (0, 0, 0), (0.07, 0.07, 0.2), "steel"),
                                 time_step_fraction=0.2)
    return Simulation(system, state)


def test_vtk_frames_round_trip(tmp_path):
    sim = _sim()
    writer = VTKWriter(tmp_path, interval=100, members=[1])
    sim.advance(300, callback=writer, callback_every=100)
    assert [p.name for p in writer.paths] == [f"particles_m001_{s:09d}.vtk" for s in (100, 200, 300)]
    data = read_vtk_points(writer.paths[-1])
    Ns = sim.system.n_spheres
    xs = sphere_positions(sim.system, sim.state.bodies).reshape(2, Ns, 3)[1].numpy()
    assert np.allclose(data["points"], xs[data["id"]])
    assert np.allclose(data["radius"], sim.system.sphere_radius[1].numpy()[data["id"]])
    assert set(data["material"].tolist()) == {0}
    assert data["velocity"].shape == (Ns, 3) and np.isfinite(data["velocity"]).all()
    assert data["points"].shape[0] == 18 + 9 * 2  # 9 spheres + 9 three-sphere clumps


def test_save_and_restore_continue_bit_for_bit(tmp_path):
    first = _sim()
    # advance until live contact history exists, so the checkpoint must carry it
    while not (bool((first.state.pairs.tangential != 0).any()) or bool((first.state.walls.tangential != 0).any())):
        first.advance(20)
        assert first.state.step < 4000
    k = first.state.step
    first.save(tmp_path / "checkpoint.pt")
    resumed = Simulation.load(tmp_path / "checkpoint.pt", first.system)
    resumed.advance(300)
    straight = _sim().advance(k + 300)
    assert resumed.state.step == straight.state.step
    assert torch.equal(resumed.state.bodies.position, straight.state.bodies.position)
    assert torch.equal(resumed.state.bodies.orientation, straight.state.bodies.orientation)
    assert torch.equal(resumed.state.pairs.tangential, straight.state.pairs.tangential)
    assert torch.equal(resumed.state.walls.rolling, straight.state.walls.rolling)
