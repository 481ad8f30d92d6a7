"""Wall schedules (torchdem/walls.py): ``Walls.active_at`` hands out the active set of the
interval between the walls' own times, computed once; it must equal the direct comparison
``active_from <= t < active_until`` at every time, including the walls' times themselves and the
times one float step beside them, in float64 and float32 (where the tensors compare in float32)."""
import math

import numpy as np
import pytest
import torch

from torchdem.walls import WallSpec, make_walls


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_active_set_equals_the_direct_comparison_at_every_time(dtype):
    specs = [WallSpec("floor", (0, 0, 0), (0, 0, 1), (1, 0, 0), math.inf, math.inf, "steel"),
             WallSpec("gate", (0, 0, 0.35), (0, 0, 1), (1, 0, 0), 0.05, 0.1, "steel", active_until=0.8),
             WallSpec("lid", (0, 0, 1), (0, 0, -1), (1, 0, 0), 0.2, 0.1, "steel", active_from=0.1, active_until=0.8),
             WallSpec("late", (0, 0, 2), (0, 0, -1), (1, 0, 0), 0.2, 0.1, "steel", active_from=1.0 / 3.0)]
    walls = make_walls(specs, {"steel": 0}, dtype=dtype)
    edges = [0.1, 0.8, 1.0 / 3.0, float(np.float32(1.0 / 3.0))]
    times = [-1.0, 0.0, 0.05, 0.5, 0.9, 5.0] + [e + d for e in edges for d in (0.0, -1e-9, 1e-9)]
    times += [float(np.nextafter(e, s)) for e in edges for s in (-np.inf, np.inf)]
    rng = np.random.default_rng(0)
    times += list(rng.uniform(-0.1, 1.2, 200))
    for t in rng.permutation(np.array(times)):
        direct = (walls.active_from <= float(t)) & (float(t) < walls.active_until)
        assert torch.equal(walls.active_at(float(t)), direct), (float(t), dtype)
    assert walls.active_at(0.5).tolist() == [True, True, True, True]
    assert walls.active_at(0.9).tolist() == [True, False, False, True]
