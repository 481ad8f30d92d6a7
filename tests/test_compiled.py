"""torch.compile'd kernels give the same trajectories as the eager ones.

A small mixed system (spheres and three-sphere clumps, walls, periodic y) runs 300 steps
eagerly and compiled; positions agree to 1e-9 m (float64; fusion reorders floating-point
operations, so agreement is to round-off accumulation, not bit-for-bit).
"""
import numpy as np
import pytest
import torch

from conftest import F64, glass, steel
from torchdem.clumps import ClumpTemplate
from torchdem.materials import interaction_table
from torchdem.simulation import Simulation
from torchdem.system import build_system
from torchdem.walls import WallSpec

TRI = ClumpTemplate("tri", np.array([[0, 0, 0], [0.006, 0, 0], [0.003, 0.005, 0]]), np.array([0.004, 0.004, 0.0035]))


def _sim(compile):
    B, N = 2, 24
    g = torch.Generator().manual_seed(2)
    k = torch.arange(N)
    pos = (torch.stack([k % 4, (k // 4) % 2, k // 8], -1).to(F64) * 0.018 + 0.01).expand(B, N, 3).clone()
    pos += 0.001 * torch.rand(pos.shape, generator=g, dtype=F64)
    mats = [glass(), steel()]
    pp = dict(mu_s=0.5, mu_r=0.05, restitution=0.5, rolling_damping=0.3)
    table = interaction_table(mats, {("glass", "glass"): pp, ("glass", "steel"): pp}, batch=B)
    template_index = (k % 2).expand(B, N).clone()
    walls = [WallSpec("floor", (0.04, 0.02, 0.0), (0, 0, 1), (1, 0, 0), 0.05, 1.0, "steel"),
             WallSpec("left", (0.0, 0.02, 0.05), (1, 0, 0), (0, 0, 1), 0.05, 1.0, "steel"),
             WallSpec("right", (0.08, 0.02, 0.05), (-1, 0, 0), (0, 0, 1), 0.05, 1.0, "steel")]
    system, state = build_system(
        pos, torch.zeros(B, N, dtype=torch.long), mats, table,
        templates=[ClumpTemplate("sphere", np.zeros((1, 3)), np.ones(1)), TRI], template_index=template_index,
        scale=torch.where(template_index == 0, 0.005, 1.0).to(F64),
        velocity=torch.randn(B, N, 3, generator=g, dtype=F64), walls=walls, time_step_fraction=0.2,
        domain=((-0.01, 0.0, -0.01), (0.09, 0.04, 0.2)), periodic=(False, True, False))
    return Simulation(system, state, compile=compile)


@pytest.mark.slow
def test_compiled_kernels_match_eager():
    eager = _sim(False).advance(300)
    compiled = _sim(True).advance(300)
    assert eager.state.pairs.n > 0 and eager.state.walls.n > 0
    assert torch.allclose(compiled.state.bodies.position, eager.state.bodies.position, rtol=0, atol=1e-9)
    assert torch.allclose(compiled.state.bodies.orientation, eager.state.bodies.orientation, rtol=0, atol=1e-7)


def test_a_kernel_torch_cannot_compile_runs_eager(monkeypatch):
    """A compiler failure (torch 2.11's Inductor could not compile the drift on CUDA) warns once
    per kernel and the run goes on eager, bit for bit as an eager run."""
    def failing_backend(graph, example_inputs):
        raise RuntimeError("this backend compiles nothing")

    plain_compile = torch.compile
    monkeypatch.setattr(torch, "compile", lambda f, **kw: plain_compile(f, backend=failing_backend, **kw))
    eager = _sim(False)
    eager.kernels.backend = "torch"
    eager.advance(150)
    fallback = _sim(True)
    fallback.kernels.backend = "torch"
    with pytest.warns(RuntimeWarning, match="runs eager from now on") as record:
        fallback.advance(150)
    failed = {str(w.message).split(" on ")[1].split(" ")[0] for w in record if "runs eager" in str(w.message)}
    assert {"drift_kernel", "pair_kernel", "kick_kernel"} <= failed
    assert "this backend compiles nothing" in fallback.kernels.torch_drift.compile_error
    assert eager.state.pairs.n > 0
    assert torch.equal(fallback.state.bodies.position, eager.state.bodies.position)
