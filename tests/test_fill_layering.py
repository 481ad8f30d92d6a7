"""The fill's layering as the gate opens (``fill_pellet_share_q1`` .. ``q4``,
``DrawDownTest._fill_layering``), on hand-built fills whose shares are known exactly."""
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from torchdem.drawdown import FILL_LAYERING_KPIS, KPI_UNITS, DrawDownTest
from torchdem.geometry import DrawDownGeometry

GEOMETRY = DrawDownGeometry(upper_width=0.4, depth=0.2, upper_height=0.5, outlet_width=0.06,
                            upper_bottom_z=0.3, lower_width=0.6, lower_height=0.2, slice_depth=0.04)
MIXTURE = SimpleNamespace(materials=(SimpleNamespace(label="pellet"), SimpleNamespace(label="sinter")))


def fill(layers: list[int], columns: int = 8, per_layer: int = 10, swap: int = 0) -> tuple:
    """Bodies of equal mass stacked in ``columns`` columns across the box, ``per_layer`` deep per layer
    and column, layer k of material ``layers[k]`` from the floor up; ``swap`` bodies of each column's
    bottom layer traded with as many of the layer above (mixing of known size). One inactive body and
    one in the lower box, which count for nothing."""
    x = (np.arange(columns) + 0.5) / columns * GEOMETRY.upper_width - GEOMETRY.upper_width / 2
    pos, mat = [], []
    for c in range(columns):
        column = [m for m in layers for _ in range(per_layer)]
        for i in range(swap):  # the top of layer 0 and the bottom of layer 1 change places
            a, b = per_layer - 1 - i, per_layer + i
            column[a], column[b] = column[b], column[a]
        for level, m in enumerate(column):
            pos.append([x[c], 0.02, GEOMETRY.upper_bottom_z + 0.01 + 0.02 * level])
            mat.append(m)
    pos += [[0.0, 0.02, GEOMETRY.upper_bottom_z + 0.2], [0.0, 0.02, 0.1]]
    mat += [0, 0]
    n = len(mat)
    active = torch.ones(1, n, dtype=torch.bool)
    active[0, -2] = False
    bodies = SimpleNamespace(position=torch.tensor([pos], dtype=torch.float64), active=active)
    system = SimpleNamespace(batch=1, body_material=torch.tensor([mat]), mass=torch.full((1, n), 0.01, dtype=torch.float64),
                             sphere_radius=torch.full((1, n), 0.005, dtype=torch.float64))
    return SimpleNamespace(geometry=GEOMETRY, mixture=MIXTURE), SimpleNamespace(system=system, state=SimpleNamespace(bodies=bodies))


@pytest.mark.parametrize("layers, shares", [([0, 1, 0, 1], [1, 0, 1, 0]), ([1, 0, 1, 0], [0, 1, 0, 1])])
def test_unmixed_layers_read_one_and_zero(layers, shares):
    test, sim = fill(layers)
    assert set(FILL_LAYERING_KPIS) <= set(KPI_UNITS)
    np.testing.assert_allclose(DrawDownTest._fill_layering(test, sim), [shares], atol=1e-12)


def test_pellets_sunk_into_the_sinter_below_move_the_bottom_share_by_their_mass():
    # reverse layering, 3 of each column's 10 bottom sinter bodies traded with pellets from above:
    # the bottom quarter holds 3 pellets in 10, the second 3 sinter in 10
    test, sim = fill([1, 0, 1, 0], swap=3)
    np.testing.assert_allclose(DrawDownTest._fill_layering(test, sim), [[0.3, 0.7, 0.0, 1.0]], atol=1e-12)
