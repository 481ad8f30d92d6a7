"""The fill's bulk density as the gate opens (``fill_bulk_density_kg_m3``, ``DrawDownTest._fill_bulk_density``) on
hand-built fills whose density is known exactly: the upper-box mass over the box's width x depth x the mean
height of the fill's top, read column by column at the highest sphere that rests on the fill. A grain in the
air (a pellet still bouncing on the reverse layering's top as the gate opens) is no part of that top; read as
one, a single pellet 0.37 m above a 0.28 m bed had put the density 30 % low."""
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from torchdem.drawdown import RESTING_GAP, DrawDownTest
from torchdem.geometry import DrawDownGeometry

GEOMETRY = DrawDownGeometry(upper_width=0.4, depth=0.2, upper_height=0.8, outlet_width=0.06,
                            upper_bottom_z=0.3, lower_width=0.6, lower_height=0.2, slice_depth=0.04)
R = 0.005            # every sphere's radius, m: the columns (_fill_columns) are 0.4 / (8 R) = 10, 0.04 m wide
MASS = 0.01          # every body's mass, kg
COLUMNS, LEVELS = 10, 20


def fill(extra: list[list[tuple[float, float, float]]] = ()) -> tuple:
    """A bed of one stack of touching spheres per column, ``LEVELS`` high (top 2 R LEVELS above the floor),
    and ``extra`` bodies, each a list of sphere centres (a clump when more than one)."""
    x = (np.arange(COLUMNS) + 0.5) / COLUMNS * GEOMETRY.upper_width - GEOMETRY.upper_width / 2
    bodies = [[(xc, 0.02, GEOMETRY.upper_bottom_z + R + 2 * R * k)] for xc in x for k in range(LEVELS)]
    bodies += [list(b) for b in extra]
    centre = [np.mean(b, axis=0) for b in bodies]
    spheres = [(n, tuple(np.subtract(s, centre[n]))) for n, b in enumerate(bodies) for s in b]
    nb, ns = len(bodies), len(spheres)
    body = torch.tensor([[n for n, _ in spheres]])
    system = SimpleNamespace(batch=1, n_bodies=nb, n_spheres=ns, spheres_only=False, sphere_body=body,
                             sphere_body_flat=body.reshape(-1),
                             sphere_offset=torch.tensor([[o for _, o in spheres]], dtype=torch.float64),
                             sphere_radius=torch.full((1, ns), R, dtype=torch.float64),
                             mass=torch.full((1, nb), MASS, dtype=torch.float64))
    state = SimpleNamespace(bodies=SimpleNamespace(
        position=torch.tensor(np.array([centre]), dtype=torch.float64), active=torch.ones(1, nb, dtype=torch.bool),
        orientation=torch.tensor([[[1.0, 0.0, 0.0, 0.0]] * nb], dtype=torch.float64)))
    test = SimpleNamespace(geometry=GEOMETRY)
    test._upper_mass = lambda sim: DrawDownTest._upper_mass(test, sim)
    return test, SimpleNamespace(system=system, state=state)


def density(extra=()) -> float:
    test, sim = fill(extra)
    return float(DrawDownTest._fill_bulk_density(test, sim)[0])


def expected(n_extra_bodies: int, height: float) -> float:
    mass = (COLUMNS * LEVELS + n_extra_bodies) * MASS
    return mass / (GEOMETRY.upper_width * GEOMETRY.simulated_depth * height)


BED = 2 * R * LEVELS                                  # the bed's top above the floor, m
X3 = (3.5 / COLUMNS - 0.5) * GEOMETRY.upper_width     # column 3's centre


def test_a_bed_of_stacks_reads_its_mass_over_its_volume():
    assert density() == pytest.approx(expected(0, BED), rel=1e-12)


def test_a_grain_resting_on_the_top_raises_its_column_by_its_diameter():
    on_top = [[(X3, 0.02, GEOMETRY.upper_bottom_z + BED + R)]]           # touching the stack's top sphere
    assert density(on_top) == pytest.approx(expected(1, BED + 2 * R / COLUMNS), rel=1e-12)


def test_a_grain_just_off_the_top_within_the_resting_gap_still_rests():
    gap = 0.5 * RESTING_GAP * 2 * R
    near = [[(X3, 0.02, GEOMETRY.upper_bottom_z + BED + R + gap)]]
    assert density(near) == pytest.approx(expected(1, BED + (2 * R + gap) / COLUMNS), rel=1e-12)


@pytest.mark.parametrize("in_the_air", [
    [[(X3, 0.02, 0.3 + 0.37)]],                                            # one pellet bouncing high
    [[(X3, 0.02, 0.3 + 0.37)], [(X3, 0.02, 0.3 + 0.30)]],                 # two in one column, one under the other
    [[(X3, 0.02, 0.3 + 0.40), (X3 + 2 * R, 0.02, 0.3 + 0.40)]],            # a clump: its own lobes hold nothing up
], ids=["one grain", "two grains in one column", "a two-lobe clump"])
def test_grains_in_the_air_count_as_mass_not_as_the_fill_top(in_the_air):
    got = density(in_the_air)
    assert got == pytest.approx(expected(len(in_the_air), BED), rel=1e-12)
    highest = max(z for b in in_the_air for _, _, z in b) + R - GEOMETRY.upper_bottom_z
    as_top = expected(len(in_the_air), BED + (highest - BED) / COLUMNS)   # what reading them as the top gives
    assert got > 1.05 * as_top
