"""The engine on a CUDA GPU gives the CPU's physics. Skipped where torch sees no GPU (CI has none):
run ``pytest tests/test_cuda.py`` on a CUDA machine.

- Hertz on the GPU: two spheres meeting head on at 2 x 0.5 m/s, float64 and float32. Restitution
  within 1 % of the input (0.3, 0.5, 0.9) and the elastic contact duration within 2 % of
  theory, the tolerances of tests/test_contact.py.
- The same run on both devices: tests/test_reorder.py's two members of 64 bodies (spheres and
  trilobe clumps), a piston moving down, 1,000 steps in float64, reordering at every rebuild.
  The GPU's atomic scatter-adds sum forces in another order, so the runs part at round-off.
  Tolerance: 1e-9 m on positions (the gap is stated in the message). Over the same 1,000 steps a
  reordered CPU run stays within 1e-12 m of a plain one (tests/test_reorder.py).
- A checkpoint saved on the GPU resumes on the CPU (and one saved on the CPU resumes on the
  GPU). After 200 more steps on each device the two runs agree within 1e-9 m.
- ``compile=True`` on the GPU (Triton kernels) follows the eager GPU run within 1e-9 m over
  300 steps. A kernel torch cannot compile runs eager (with a warning); whether every kernel
  compiled is its own test, an expected failure on torch 2.11 (Inductor's ``CantSplit`` on this
  system's drift kernel, measured on an H100; a default slice member compiled every kernel).
- tests/test_drawdown.py's small draw down on the GPU in float32, in one ensemble of two
  replicates: mass conserved (upper + lower + in flight = fill within 1e-3; float32 sums),
  no body lost, every KPI measured.
"""
import pytest
import torch

from conftest import glass, hertz_contact_duration
from test_contact import R, V, _e_star, _run_pair
from test_drawdown import small_drawdown
from test_reorder import _in_build_order, _system
from torchdem.simulation import GuardSettings, Simulation

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")

CUDA = "cuda"


def _gap(a: Simulation, b: Simulation) -> float:
    """Largest position difference, m, between two runs of the same system (bodies matched by id)."""
    pa = _in_build_order(a.state.body_id, a.state.bodies.position).cpu().double()
    pb = _in_build_order(b.state.body_id, b.state.bodies.position).cpu().double()
    return float((pa - pb).abs().max())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_hertz_impacts_on_the_gpu(dtype):
    restitution = [0.3, 0.5, 0.9, 1.0]
    sim, e_measured, duration = _run_pair(restitution, device=CUDA, dtype=dtype)
    assert sim.state.bodies.position.device.type == CUDA
    for e_in, e_out in zip(restitution, e_measured.tolist()):
        assert abs(e_out - e_in) / e_in < 0.01, (dtype, e_in, e_out)
    m = float(sim.system.mass[0, 0])
    expected = hertz_contact_duration(m / 2, R / 2, _e_star(glass(), glass()), 2 * V)
    assert abs(float(duration[-1]) - expected) / expected < 0.02, (dtype, float(duration[-1]), expected)


def test_gpu_run_follows_the_cpu_run():
    runs = []
    for device in ("cpu", CUDA):
        sim = Simulation(*_system(device=device), GuardSettings(check_every=100), reorder_every=1)
        sim.advance(1000)
        runs.append(sim)
    cpu, gpu = runs
    assert gpu.state.bodies.position.device.type == CUDA
    assert cpu.state.rebuilds > 5 and not gpu.failed and not cpu.failed
    gap = _gap(cpu, gpu)
    assert gap < 1e-9, f"GPU and CPU positions differ by {gap:.3g} m after 1000 steps"


@pytest.mark.parametrize("saved_on, resumed_on", [(CUDA, "cpu"), ("cpu", CUDA)])
def test_checkpoint_moves_between_devices(tmp_path, saved_on, resumed_on):
    sim = Simulation(*_system(device=saved_on), reorder_every=1)
    sim.advance(300)
    sim.save(tmp_path / "ckpt.pt")
    built, _ = _system(device=resumed_on)
    resumed = Simulation.load(tmp_path / "ckpt.pt", built, reorder_every=1)
    assert resumed.state.bodies.position.device.type == resumed_on
    assert resumed.state.pairs.tangential.device.type == resumed_on
    sim.advance(200)
    resumed.advance(200)
    gap = _gap(sim, resumed)
    assert gap < 1e-9, f"resumed on {resumed_on}: positions differ by {gap:.3g} m after 200 steps"


def _compiled_and_eager():
    runs = []
    for compile in (False, True):
        sim = Simulation(*_system(device=CUDA), compile=compile)
        sim.advance(300)
        runs.append(sim)
    return runs


def test_compiled_kernels_on_the_gpu_follow_eager():
    gap = _gap(*_compiled_and_eager())
    assert gap < 1e-9, f"compiled and eager GPU runs differ by {gap:.3g} m after 300 steps"


@pytest.mark.xfail(strict=False, reason="torch 2.11.0+cu130 (H100): Inductor could not compile this system's drift_kernel with "
                                        "dynamic shapes (CantSplit); that kernel runs eager")
def test_every_kernel_compiles_on_the_gpu():
    _, compiled = _compiled_and_eager()
    k = compiled.kernels
    failed = {f.__name__: f.compile_error for f in (k.torch_drift, k.torch_kick, k.torch_pair, k.torch_wall)
              if f.compile_error is not None}
    assert not failed, failed


@pytest.mark.slow
def test_small_drawdown_on_the_gpu_in_float32():
    res = small_drawdown(dtype="float32").run(replicates=2, seeds=[3, 4], device=CUDA)
    for k, err, c in zip(res.kpis, res.errors, res.conservation):
        assert err == {}, err
        assert c["lost_bodies"] == 0
        assert abs(c["upper_kg"] + c["lower_kg"] + c["in_flight_kg"] - c["fill_kg"]) < 1e-3 * c["fill_kg"]
        assert k["mass_flow_rate_kg_s"] > 0
        assert 0.3 * k["fill_mass_kg"] < k["mass_lower_box_kg"] <= k["fill_mass_kg"]
        assert 5 < k["angle_of_repose_deg"] < 45 and 10 < k["shear_angle_deg"] < 70
