"""Pure helpers of scripts/bench_engine.py (--scaling packings, --stream byte counts); no timing."""
import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

_PATH = Path(__file__).resolve().parents[1] / "scripts" / "bench_engine.py"
_spec = importlib.util.spec_from_file_location("bench_engine", _PATH)
bench = importlib.util.module_from_spec(_spec)
sys.modules.setdefault("bench_engine", bench)
_spec.loader.exec_module(bench)


def _packing(position, radius):
    position = np.asarray(position, dtype=float)
    zero = np.zeros_like(position)
    return bench.Packing(position, np.asarray(radius, dtype=float), zero, zero, 0.0, 0.0)


def test_pair_bytes_float64_single_spheres():
    d = bench.pair_bytes_per_step(8, True)
    # indices 16 + history write 48; history read 48 per touching pair; per sphere x 24, radius 8,
    # mass and rolling inertia 16, pair_row and material 16; per body V 24, W 24, force/torque 96.
    assert d["lower"] == {"listed_pair": 64, "touching_pair": 48, "sphere": 64, "body": 144}
    # per listed pair: indices 16, history 96, x and radius 2 lines each; per touching pair:
    # V, W, mass, inertia 2 lines each, pair_row/material 2, force/torque 4 lines read + written.
    assert d["upper"] == {"listed_pair": 368, "touching_pair": 1152, "sphere": 0, "body": 0}
    for bound in ("lower", "upper"):
        for unit, total in d[bound].items():
            assert total == sum(s[bound].get(unit, 0) for s in d["streams"])


def test_pair_bytes_clumps_and_float32():
    d64, c64 = bench.pair_bytes_per_step(8, True), bench.pair_bytes_per_step(8, False)
    assert c64["lower"]["listed_pair"] - d64["lower"]["listed_pair"] == 16      # body_i, body_j streamed
    assert c64["lower"]["body"] - d64["lower"]["body"] == 24                    # body centres gathered
    assert c64["upper"]["touching_pair"] - d64["upper"]["touching_pair"] == 128
    d32 = bench.pair_bytes_per_step(4, True)
    assert d32["lower"] == {"listed_pair": 40, "touching_pair": 24, "sphere": 40, "body": 72}
    assert d32["upper"]["listed_pair"] == 320 and d32["upper"]["touching_pair"] == 1152


def test_pair_traffic_is_linear_in_the_counts():
    lower = bench.pair_bytes_per_step(8, True)["lower"]
    assert bench.pair_traffic(lower, 10, 3, 2, 2) == 64 * 10 + 48 * 3 + 64 * 2 + 144 * 2


def test_tile_packing_leaves_a_gap_at_every_seam():
    # Two spheres pressing 10 um into the x walls of a 0.05 x 0.02 m box, level with each other.
    r = 0.005
    p = _packing([[r - 1e-5, 0.01, r], [0.05 - r + 1e-5, 0.01, r]], [r, r])
    tiled, box, tile = bench.tile_packing(p, 0.05, 0.02, 3, 2)
    assert len(tiled.radius) == 12 and list(tile) == [k for k in range(6) for _ in range(2)]
    assert box[0] == pytest.approx(3 * 0.05 + 2 * 2e-5) and box[1] == pytest.approx(2 * 0.02)
    assert np.array_equal(tiled.position[:2], p.position)                 # tile 0 is the source
    overlap, seam = bench.max_overlaps(tiled.position, tiled.radius, tile)
    assert overlap == pytest.approx(0.0, abs=1e-12)                        # seam pairs touch, no more
    assert seam == pytest.approx(0.0, abs=1e-12)
    # Without the gap the two spheres facing each other across the seam would overlap by 20 um.
    naive = np.concatenate([p.position, p.position + [0.05, 0.0, 0.0]])
    assert bench.max_overlaps(naive, np.r_[p.radius, p.radius], np.repeat([0, 1], 2))[1] == pytest.approx(2e-5)


def test_trim_packing_moves_the_wall_to_the_last_sphere():
    p = _packing([[0.01, 0.01, 0.01], [0.02, 0.01, 0.01], [0.09, 0.01, 0.01]], [0.005, 0.007, 0.005])
    cut, box_x = bench.trim_packing(p, 0.1, 0.3)
    assert len(cut.radius) == 2 and box_x == pytest.approx(0.027)


def test_a_device_torch_does_not_know_is_named():
    with pytest.raises(bench.ConfigError, match="--device: device = 'gpu0' is not a torch device"):
        bench.main(["--device", "gpu0", "--no-liggghts", "--quick"])


def _script_refuses(monkeypatch, capsys, script: str, argv: list[str], message: str) -> None:
    """scripts/<script>.py exits on ``argv`` before building anything, naming ``message``."""
    path = Path(__file__).resolve().parents[1] / "scripts" / f"{script}.py"
    spec = importlib.util.spec_from_file_location(script, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    monkeypatch.setattr(sys, "argv", [f"{script}.py", *argv])
    with pytest.raises(SystemExit):
        module.main()
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["--every", "3", "10"], "--every must include 0"),
    (["--every", "0", "-2"], "distinct ints >= 0"),
    (["--chunk", "0"], "--chunk and --rounds must be >= 1"),
])
def test_bench_reorder_refuses_cases_without_a_baseline_or_steps(monkeypatch, capsys, argv, message):
    """scripts/bench_reorder.py compares every case with build order: it needs the baseline and steps."""
    _script_refuses(monkeypatch, capsys, "bench_reorder", argv, message)


@pytest.mark.parametrize("argv, message", [
    (["--fractions", "0.25", "0.25"], "distinct values in (0, 2]"),
    (["--fractions", "0.25", "0"], "distinct values in (0, 2]"),
    (["--rounds", "0"], "--chunk and --rounds must be >= 1"),
    (["--same-bits", "-5"], "--same-bits -5: expected a number of steps >= 1"),
])
def test_bench_skin_refuses_bad_skins_or_steps(monkeypatch, capsys, argv, message):
    """scripts/bench_skin.py names a bad --fractions or step count before it builds anything."""
    _script_refuses(monkeypatch, capsys, "bench_skin", argv, message)


@pytest.mark.parametrize("script, argv, message", [
    ("bench_drawdown", ["--workers", "2", "--ensemble", "0"], "--ensemble 0: expected an int >= 1"),
    ("bench_core_share", ["--runs", "0"], "each must be >= 1"),
    ("bench_core_share", ["--pairs", "0"], "each must be >= 1"),
])
def test_the_batch_benches_refuse_empty_splits(monkeypatch, capsys, script, argv, message):
    """scripts/bench_drawdown.py and bench_core_share.py name a split that runs nothing."""
    _script_refuses(monkeypatch, capsys, script, argv, message)
