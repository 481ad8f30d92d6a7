"""Tests for torchdem.render: synthetic sphere packings with known surfaces, measured by kpi.

The scenes are packings of equal spheres whose centres fill a region of the x-z plane with a
known boundary (a 30 deg heap, a 40 deg funnel, a rectangle split into pellets and sinter),
several layers deep in y, built in a few milliseconds; no simulation runs here.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from kpi.angles import angle_of_repose, shear_angle
from kpi.colors import BACKGROUND_BGR, PELLET_BGR, SHADOW_BGR, SINTER_BGR, WALL_BGR
from kpi.io import CropBox
from kpi.segregation import measure_segregation, segment_pellet_sinter
from torchdem.errors import ConfigError
from torchdem.materials import Material, interaction_table
from torchdem.render import (
    DEFAULT_WIDTH_PX, PELLET_LABEL, SINTER_LABEL, View, crop_box_for, render_front, render_state,
)
from torchdem.system import build_system
from torchdem.walls import WallSpec, box_walls

# Draw-down scene (metres): lower box x in [0, 0.4], z in [0, 0.15]; upper box x in [0, 0.4],
# z in [0.25, 0.45] with a floor of two plates leaving a 60 mm outlet in the middle; both
# boxes 50 mm deep (y in [0, 0.05]) behind a glass front pane at y = 0.
BOX_X = (0.0, 0.4)
DEPTH_Y = 0.05
LOWER_Z = (0.0, 0.15)
UPPER_Z = (0.25, 0.45)
OUTLET_HALF_WIDTH = 0.03
RADIUS = 0.005
HEAP_ANGLE_DEG = 30.0
HEAP_HALF_BASE = 0.18
FUNNEL_ANGLE_DEG = 40.0
VIEW = View(-0.02, 0.42, -0.02, 0.47, metres_per_pixel=0.0005)  # 880 x 980 px, r = 10 px

#: Angle tolerance against the nominal slope. The surface is a row of touching spheres whose
#: centres lie on the nominal line (over a jittered hexagonal bulk), so its profile is the
#: line raised by up to one radius with scallops one diameter long: parallel to the line,
#: except that it rounds off over about one diameter where a side ends (apex, foot, wall,
#: outlet), which flattens a least-squares fit over the whole side a little. Measured over six
#: seeds: |error| <= 0.02 deg for the heap, -0.10 to -0.20 deg for the funnel (whose sides end
#: at a wall and at the outlet). 1 deg leaves room for other packings and sphere sizes.
ANGLE_TOLERANCE_DEG = 1.0
#: Renderer fidelity: the measured angle against the least-squares angle of the exact upper
#: envelope of the sphere discs over the same profile columns. Pixel rows quantise each column
#: top by at most half a pixel (random along the side, so it averages out) and kpi's closing
#: fills notches narrower than 5 px; measured differences <= 0.02 deg over six seeds.
RENDER_FIDELITY_DEG = 0.1


def layered_packing(inside, x_range, z_range, radius, y_range, seed=0, jitter=0.15):
    """Centres ``[N, 3]`` of hexagonal sphere layers in x-z stacked along y (ABC offsets plus
    a seeded random jitter), keeping those whose (x, z) satisfies ``inside(x, z)``."""
    rng = np.random.default_rng(seed)
    spacing_z = math.sqrt(3.0) * radius
    layer_step = 2.0 * radius * math.sqrt(2.0 / 3.0)
    n_layers = int((y_range[1] - y_range[0] - 2 * radius) // layer_step) + 1
    centres = []
    for layer in range(n_layers):
        shift_x = (layer % 3) * radius
        shift_z = (layer % 3) * spacing_z / 3.0
        xs = np.arange(x_range[0] - 2 * radius, x_range[1] + 2 * radius, 2 * radius) + shift_x
        zs = np.arange(z_range[0] - spacing_z, z_range[1] + spacing_z, spacing_z) + shift_z
        x, z = np.meshgrid(xs, zs)
        x = x + (np.round((z - zs[0]) / spacing_z) % 2) * radius   # alternate rows offset by r
        x = x + rng.uniform(-jitter, jitter, x.shape) * radius
        z = z + rng.uniform(-jitter, jitter, z.shape) * radius
        keep = inside(x, z)
        y = np.full(int(keep.sum()), y_range[0] + radius + layer * layer_step)
        centres.append(np.stack([x[keep], y, z[keep]], axis=1))
    return np.concatenate(centres)


def surface_chain(start, end, radius, y):
    """Centres ``[M, 3]`` of touching spheres (about one diameter apart) along the segment
    ``start -> end`` (x, z) at depth y: the grains resting on a surface line."""
    start, end = np.asarray(start, float), np.asarray(end, float)
    count = int(np.ceil(np.linalg.norm(end - start) / (2 * radius))) + 1
    xz = start + np.linspace(0.0, 1.0, count)[:, None] * (end - start)
    return np.stack([xz[:, 0], np.full(count, y), xz[:, 1]], axis=1)


def heap_centres(seed=0):
    """Heap in the lower box: apex over the middle, both sides at HEAP_ANGLE_DEG."""
    apex_x = 0.5 * (BOX_X[0] + BOX_X[1])
    slope = math.tan(math.radians(HEAP_ANGLE_DEG))
    height = HEAP_HALF_BASE * slope

    def inside(x, z):
        return (z >= LOWER_Z[0] + RADIUS) & (z <= LOWER_Z[0] + height - np.abs(x - apex_x) * slope)

    bulk = layered_packing(inside, (apex_x - HEAP_HALF_BASE, apex_x + HEAP_HALF_BASE), (0.0, height),
                           RADIUS, (0.0, DEPTH_Y), seed)
    foot_z = LOWER_Z[0] + RADIUS
    apex = (apex_x, LOWER_Z[0] + height)
    foot_run = (height - RADIUS) / slope
    sides = [surface_chain((apex_x + sign * foot_run, foot_z), apex, RADIUS, RADIUS) for sign in (-1, 1)]
    return np.concatenate([bulk] + sides)


def funnel_centres(seed=1):
    """Material left in the upper box: on the floor plates, below a V at FUNNEL_ANGLE_DEG whose
    sides meet the floor at the outlet's edges."""
    middle = 0.5 * (BOX_X[0] + BOX_X[1])
    slope = math.tan(math.radians(FUNNEL_ANGLE_DEG))

    def inside(x, z):
        surface = UPPER_Z[0] + (np.abs(x - middle) - OUTLET_HALF_WIDTH) * slope
        return ((x >= BOX_X[0] + RADIUS) & (x <= BOX_X[1] - RADIUS)
                & (z >= UPPER_Z[0] + RADIUS) & (z <= surface))

    bulk = layered_packing(inside, BOX_X, UPPER_Z, RADIUS, (0.0, DEPTH_Y), seed)
    bottom_run = OUTLET_HALF_WIDTH + RADIUS / slope  # where the V is one radius above the floor
    sides = []
    for sign in (-1, 1):
        wall_x = BOX_X[0] + RADIUS if sign < 0 else BOX_X[1] - RADIUS
        wall_z = UPPER_Z[0] + (abs(wall_x - middle) - OUTLET_HALF_WIDTH) * slope
        sides.append(surface_chain((middle + sign * bottom_run, UPPER_Z[0] + RADIUS), (wall_x, wall_z), RADIUS, RADIUS))
    return np.concatenate([bulk] + sides)


def drawdown_walls():
    """Lower box (open top) and upper box whose floor is two plates around the outlet."""
    middle = 0.5 * (BOX_X[0] + BOX_X[1])
    lower = box_walls("lower", (BOX_X[0], 0.0, LOWER_Z[0]), (BOX_X[1], DEPTH_Y, LOWER_Z[1]), "steel")
    upper = [w for w in box_walls("upper", (BOX_X[0], 0.0, UPPER_Z[0]), (BOX_X[1], DEPTH_Y, UPPER_Z[1]), "steel")
             if not w.name.endswith("bottom")]
    plate_half = 0.5 * (middle - OUTLET_HALF_WIDTH - BOX_X[0])
    plates = [
        WallSpec(f"upper_floor_{side}", (middle + sign * (OUTLET_HALF_WIDTH + plate_half), DEPTH_Y / 2, UPPER_Z[0]),
                 (0, 0, 1), (1, 0, 0), plate_half, DEPTH_Y / 2, "steel")
        for side, sign in (("left", -1), ("right", 1))
    ]
    return lower + upper + plates


def envelope_angles_deg(centres, radius, result, view):
    """(left, right) angle of lines fitted to the exact top of the union of sphere discs at the
    centre x of every profile column kpi used, split where kpi split (the geometric truth that
    the rendered image approximates)."""
    columns = result.profile.columns_px
    x = view.x_at(columns)
    dx = x[:, None] - centres[None, :, 0]
    heights = centres[None, :, 2] + np.sqrt(np.clip(radius * radius - dx * dx, 0.0, None))
    top = np.where(np.abs(dx) <= radius, heights, -np.inf).max(axis=1)
    valid = ~np.isnan(result.profile.top_rows_px)
    angles = []
    for side in (columns < result.split_x_px, columns > result.split_x_px):
        slope = np.polyfit(x[valid & side], top[valid & side], 1)[0]
        angles.append(math.degrees(math.atan(abs(slope))))
    return tuple(angles)


@pytest.fixture(scope="module")
def drawdown_render():
    heap, funnel = heap_centres(), funnel_centres()
    centres = np.concatenate([heap, funnel])
    rng = np.random.default_rng(2)
    labels = rng.integers(0, 2, len(centres))  # a random pellet/sinter mixture
    image = render_front(centres, np.full(len(centres), RADIUS), labels, VIEW, walls=drawdown_walls())
    return dict(image=image, centres=centres, labels=labels, heap=heap, funnel=funnel)


def test_angle_of_repose_of_a_rendered_30_degree_heap(drawdown_render):
    image = drawdown_render["image"]
    box = crop_box_for(VIEW, BOX_X[0], BOX_X[1], LOWER_Z[0], LOWER_Z[1])
    result = angle_of_repose(image, crop_box=box, source="render")
    report = f"left {result.left_angle_deg:.3f}, right {result.right_angle_deg:.3f}, mean {result.angle_deg:.3f} deg"
    assert result.left_angle_deg == pytest.approx(HEAP_ANGLE_DEG, abs=ANGLE_TOLERANCE_DEG), report
    assert result.right_angle_deg == pytest.approx(HEAP_ANGLE_DEG, abs=ANGLE_TOLERANCE_DEG), report
    assert result.angle_deg == pytest.approx(HEAP_ANGLE_DEG, abs=ANGLE_TOLERANCE_DEG), report
    # The apex is found over the middle of the box (within one sphere diameter).
    assert VIEW.x_at(result.split_x_px) == pytest.approx(0.5 * sum(BOX_X), abs=2 * RADIUS)
    left, right = envelope_angles_deg(drawdown_render["heap"], RADIUS, result, VIEW)
    assert result.left_angle_deg == pytest.approx(left, abs=RENDER_FIDELITY_DEG), (report, left)
    assert result.right_angle_deg == pytest.approx(right, abs=RENDER_FIDELITY_DEG), (report, right)


def test_shear_angle_of_a_rendered_40_degree_funnel(drawdown_render):
    image = drawdown_render["image"]
    box = crop_box_for(VIEW, BOX_X[0], BOX_X[1], UPPER_Z[0], UPPER_Z[1])
    result = shear_angle(image, crop_box=box, source="render")
    report = f"left {result.left_angle_deg:.3f}, right {result.right_angle_deg:.3f}, mean {result.angle_deg:.3f} deg"
    assert result.left_angle_deg == pytest.approx(FUNNEL_ANGLE_DEG, abs=ANGLE_TOLERANCE_DEG), report
    assert result.right_angle_deg == pytest.approx(FUNNEL_ANGLE_DEG, abs=ANGLE_TOLERANCE_DEG), report
    assert result.angle_deg == pytest.approx(FUNNEL_ANGLE_DEG, abs=ANGLE_TOLERANCE_DEG), report
    left, right = envelope_angles_deg(drawdown_render["funnel"], RADIUS, result, VIEW)
    assert result.left_angle_deg == pytest.approx(left, abs=RENDER_FIDELITY_DEG), (report, left)
    assert result.right_angle_deg == pytest.approx(right, abs=RENDER_FIDELITY_DEG), (report, right)


def test_walls_are_bands_outside_the_boxes_and_glass_is_not_drawn(drawdown_render):
    image = drawdown_render["image"]
    is_wall = (image == WALL_BGR).all(axis=-1)
    band = 6  # DEFAULT_WALL_THICKNESS_PX
    left_wall_column = int(np.floor(VIEW.column(BOX_X[0])))  # last column left of x = 0
    floor_row = int(np.ceil(VIEW.row(LOWER_Z[0])))           # first row below z = 0
    mid_lower_row = int(VIEW.row(0.5 * sum(LOWER_Z)))
    assert is_wall[mid_lower_row, left_wall_column - band + 1: left_wall_column + 1].all()
    assert not is_wall[mid_lower_row, left_wall_column + 1]
    assert is_wall[floor_row: floor_row + band, int(VIEW.column(0.1))].all()
    # The outlet between the upper box's floor plates is open.
    outlet_row = int(np.ceil(VIEW.row(UPPER_Z[0])))
    assert not is_wall[outlet_row, int(VIEW.column(0.5 * sum(BOX_X)))]
    assert is_wall[outlet_row, int(VIEW.column(0.1))]
    # No wall pixel inside either box's interior (the glass front and back are not drawn).
    for z_range in (LOWER_Z, UPPER_Z):
        box = crop_box_for(VIEW, BOX_X[0], BOX_X[1], *z_range)
        assert not is_wall[box.y0:box.y1, box.x0:box.x1].any()


def test_walls_follow_their_existence_window_and_motion():
    view = View(-0.1, 0.1, -0.1, 0.1, metres_per_pixel=0.001)  # 200 x 200 px
    gate = WallSpec("gate", (0.0, 0.0, 0.0), (0, 0, 1), (1, 0, 0), 0.02, 0.02, "steel", active_until=0.0)
    slider = WallSpec("slider", (-0.05, 0.0, 0.0), (1, 0, 0), (0, 1, 0), 0.02, 0.02, "steel",
                      velocity=(0.1, 0.0, 0.0), move_from=0.0, move_until=1.0)
    glass = WallSpec("front", (0.0, 0.0, 0.0), (0, 1, 0), (1, 0, 0), 0.05, 0.05, "glass")
    sphere = (torch.tensor([[0.0, 0.01, 0.05]], requires_grad=True), torch.tensor([0.005]), torch.tensor([1]))

    def wall_columns(image):  # wall pixels in the row at z = 10 mm (above the gate's band)
        return np.flatnonzero((image[int(view.row(0.01))] == WALL_BGR).all(-1))

    before = render_front(*sphere, view, walls=[gate, slider, glass], wall_thickness=0.004)
    assert (before == WALL_BGR).all(-1)[int(view.row(-0.002)), int(view.column(0.01))]   # gate drawn
    # The slider's band (normal +x) lies on its -x side: x in (-0.054, -0.05).
    assert wall_columns(before).tolist() == list(range(46, 50))
    later = render_front(*sphere, view, walls=[gate, slider, glass], wall_thickness=0.004, time=0.5)
    assert not (later == WALL_BGR).all(-1)[int(view.row(-0.002)), int(view.column(0.01))]  # gate gone
    assert wall_columns(later).tolist() == list(range(96, 100))  # slider moved 50 mm
    assert tuple(later[int(view.row(0.05)), int(view.column(0.0))]) == SINTER_BGR  # glass not drawn


def test_segregation_of_a_render_half_pellets_half_sinter():
    radius, x_range, z_range, split_x = 0.003, (0.02, 0.38), (0.0, 0.12), 0.2
    def inside(x, z):
        return (x >= x_range[0]) & (x <= x_range[1]) & (z >= z_range[0]) & (z <= z_range[1])

    centres = layered_packing(inside, x_range, z_range, radius, (0.0, 0.03), seed=3)
    labels = np.where(centres[:, 0] < split_x, PELLET_LABEL, SINTER_LABEL)
    view = View(0.0, 0.4, -0.01, 0.14)  # default pixel size: 0.4 m / 800 px
    assert view.metres_per_pixel == pytest.approx(0.4 / DEFAULT_WIDTH_PX)
    image = render_front(torch.as_tensor(centres), torch.full((len(centres),), radius), torch.as_tensor(labels), view)
    result = measure_segregation(image, source="render")

    # Every rendered pixel is classified as what it was painted, and nothing else is counted.
    assert np.array_equal(result.pellet_mask, (image == PELLET_BGR).all(axis=-1))
    assert np.array_equal(result.sinter_mask, (image == SINTER_BGR).all(axis=-1))
    assert ((image == PELLET_BGR).all(-1) | (image == SINTER_BGR).all(-1) | (image == BACKGROUND_BGR).all(-1)).all()

    # Expected fraction of a slice: the share of its columns left of split_x (five ABC-stacked
    # layers cover the region in projection, so every column inside the heap box holds about
    # the same number of material pixels). Only pixels within one radius of split_x can have
    # the other colour (a sphere is labelled by its centre), so a slice w pixel columns wide
    # may differ by at most r_px / w; one more pixel allows for the rounding of slice bounds.
    # Measured: |error| <= 0.018 (horizontal strips) and <= 0.004 (vertical bands) over three
    # seeds, against tolerances 0.117 and 0.018.
    split_column = view.column(split_x) + 0.5  # columns < this have their centre left of split_x
    radius_px = radius / view.metres_per_pixel
    fractions = []
    for (c0, c1), pellet in zip(result.horizontal.slice_bounds_px, result.horizontal.pellet_fraction):
        expected = np.clip((split_column - c0) / (c1 - c0), 0.0, 1.0)
        tolerance = (radius_px + 1) / (c1 - c0)
        fractions.append((pellet, expected))
        assert pellet == pytest.approx(expected, abs=tolerance), fractions
    heap = result.heap_box
    expected = (split_column - heap.x0) / heap.width
    for pellet in result.vertical.pellet_fraction:
        assert pellet == pytest.approx(expected, abs=(radius_px + 1) / heap.width), result.vertical.pellet_fraction
    np.testing.assert_allclose(result.horizontal.pellet_fraction + result.horizontal.sinter_fraction, 1.0)


def test_rim_darkening_keeps_the_kpi_classification(drawdown_render):
    centres, labels = drawdown_render["centres"], drawdown_render["labels"]
    radii = np.full(len(centres), RADIUS)
    flat = render_front(centres, radii, labels, VIEW, walls=drawdown_walls())
    shaded = render_front(centres, radii, labels, VIEW, walls=drawdown_walls(), rim_darkening=0.3)
    assert not np.array_equal(flat, shaded)
    pellet_flat = measure_segregation(flat).pellet_mask
    shaded_result = measure_segregation(shaded)
    assert np.array_equal(shaded_result.pellet_mask, pellet_flat)
    assert np.array_equal(shaded_result.pellet_mask | shaded_result.sinter_mask,
                          (flat == PELLET_BGR).all(-1) | (flat == SINTER_BGR).all(-1))
    box = crop_box_for(VIEW, BOX_X[0], BOX_X[1], LOWER_Z[0], LOWER_Z[1])
    assert angle_of_repose(shaded, crop_box=box).angle_deg == pytest.approx(
        angle_of_repose(flat, crop_box=box).angle_deg, abs=1e-9)


def test_front_sphere_hides_the_one_behind_it():
    view = View(-0.02, 0.02, -0.02, 0.02, metres_per_pixel=0.0005)  # 80 x 80 px
    middle = (40, 40)  # (row, column) of the pixel centred at x = +0.25 mm, z = -0.25 mm
    centres = np.array([[0.0, 0.03, 0.0], [0.0, 0.01, 0.0]])  # pellet behind, sinter in front
    radii = np.array([0.008, 0.004])
    labels = np.array([PELLET_LABEL, SINTER_LABEL])
    for order in ([0, 1], [1, 0]):  # the input order does not matter
        image = render_front(centres[order], radii[order], labels[order], view)
        assert tuple(image[middle]) == SINTER_BGR
        assert tuple(image[40, 52]) == PELLET_BGR  # x = 6.25 mm: outside the sinter disc
        assert tuple(image[0, 0]) == BACKGROUND_BGR
    # Overlapping spheres (the members of a clump overlap): a small sphere inside a big one is
    # hidden by the big one's surface although its centre is nearer the camera, where a
    # painter's algorithm sorted by centre depth would paint it on top.
    centres = np.array([[0.0, 0.010, 0.0], [0.0, 0.009, 0.0]])
    radii = np.array([0.008, 0.001])
    image = render_front(centres, radii, np.array([PELLET_LABEL, SINTER_LABEL]), view)
    assert (image == PELLET_BGR).all(-1).sum() == (image != BACKGROUND_BGR).any(-1).sum()


def test_pixel_grid_and_crop_boxes():
    view = View(0.0, 0.4, 0.0, 0.3, metres_per_pixel=0.0005)
    assert (view.width_px, view.height_px) == (800, 600)
    assert crop_box_for(view, 0.05, 0.35, 0.0, 0.1) == CropBox(100, 400, 700, 600)
    assert crop_box_for(view, 0.0, 0.4, 0.0, 0.3) == CropBox(0, 0, 800, 600)
    assert crop_box_for(view, 0.1, 0.2, 0.2, 0.25) == CropBox(200, 100, 400, 200)
    # Region edges on pixel centres include those pixels.
    assert crop_box_for(view, 0.00025, 0.00075, 0.29925, 0.29975) == CropBox(0, 0, 2, 2)
    # The crop holds exactly the pixels of a sphere drawn inside the region.
    image = render_front(np.array([[0.15, 0.0, 0.225]]), np.array([0.02]), np.array([0]), view)
    box = crop_box_for(view, 0.13, 0.17, 0.205, 0.245)
    painted = (image != BACKGROUND_BGR).any(-1)
    assert painted[box.y0:box.y1, box.x0:box.x1].sum() == painted.sum()
    assert (box.width, box.height) == (80, 80)
    assert view.x_at(view.column(0.123)) == pytest.approx(0.123)
    assert view.z_at(view.row(0.277)) == pytest.approx(0.277)
    with pytest.raises(ConfigError, match=r"x_max = 0.5 is not allowed; expected a value inside the view"):
        crop_box_for(view, 0.1, 0.5, 0.0, 0.1)
    with pytest.raises(ConfigError, match=r"z_max = 0.1 is not allowed; expected a value > z_min = 0.2"):
        crop_box_for(view, 0.1, 0.2, 0.2, 0.1)


@pytest.mark.parametrize("kwargs,message", [
    (dict(x_max=0.0), r"View: x_max = 0.0 is not allowed; expected a value > x_min = 0.0 m"),
    (dict(z_max=-1.0), r"View: z_max = -1.0 is not allowed; expected a value > z_min = 0.0 m"),
    (dict(metres_per_pixel=0.0), r"View: metres_per_pixel = 0.0 is not allowed; expected a finite pixel size > 0 m"),
    (dict(metres_per_pixel=-0.001), r"metres_per_pixel = -0.001 is not allowed"),
    (dict(metres_per_pixel=1e-6), r"metres_per_pixel = 1e-06 is not allowed; expected a pixel size >= "),
    (dict(x_min=float("nan")), r"View: x_min = nan is not allowed; expected a finite number"),
])
def test_bad_view_is_rejected(kwargs, message):
    values = dict(x_min=0.0, x_max=0.4, z_min=0.0, z_max=0.3, metres_per_pixel=0.0005)
    values.update(kwargs)
    with pytest.raises(ConfigError, match=message):
        View(**values)


@pytest.mark.parametrize("centres,radii,labels,message", [
    (np.zeros((0, 3)), np.zeros(0), np.zeros(0, int), r"render_front: centres is empty \(N = 0\)"),
    (np.zeros((2, 2)), np.ones(2), np.zeros(2, int), r"centres has shape \(2, 2\); expected \[N, 3\]"),
    (np.zeros((2, 3)), np.ones(3), np.zeros(2, int), r"radii has shape \(3,\); expected \[2\]"),
    (np.zeros((2, 3)), np.ones(2), np.zeros(3, int), r"labels has shape \(3,\); expected \[2\]"),
    (np.zeros((2, 3)), np.array([0.01, -0.01]), np.zeros(2, int),
     r"radii = -0.01 is not allowed; expected finite radii > 0 m \(sphere 1\)"),
    (np.array([[0, 0, 0], [0, np.nan, 0]]), np.ones(2), np.zeros(2, int),
     r"centres = .* expected finite coordinates \(sphere 1\)"),
    (np.zeros((2, 3)), np.ones(2), np.array([0, 7]),
     r"labels = 7 is not allowed; expected a palette key in \[0, 1\] \(sphere 1\)"),
    (np.zeros((2, 3)), np.ones(2), np.array([0.0, 1.0]), r"labels have dtype float64; expected integer"),
])
def test_bad_spheres_are_rejected(centres, radii, labels, message):
    with pytest.raises(ConfigError, match=message):
        render_front(centres, radii, labels, View(0.0, 0.4, 0.0, 0.3))


def test_shadow_paints_what_lies_behind_the_front_layer():
    """A lab photo is lit through the glass: with ``shadow_depth`` the spheres seen through the gaps of the
    front layer are near black (kpi counts them as sinter), the front layer keeps its colours, and None
    changes nothing."""
    view = View(-0.02, 0.02, -0.02, 0.02, metres_per_pixel=0.0005)  # 80 x 80 px
    # a pellet against the glass (surface at y = 0) and a pellet 30 mm behind, beside it
    centres = np.array([[-0.008, 0.004, 0.0], [0.008, 0.034, 0.0]])
    radii = np.array([0.004, 0.004])
    labels = np.array([PELLET_LABEL, PELLET_LABEL])
    flat = render_front(centres, radii, labels, view)
    assert np.array_equal(render_front(centres, radii, labels, view, shadow_depth=None), flat)
    lit = render_front(centres, radii, labels, view, shadow_depth=0.01)
    front, back = (40, 24), (40, 56)  # the discs' centre pixels (x = -7.75 mm and +8.25 mm)
    assert tuple(lit[front]) == PELLET_BGR and tuple(lit[back]) == SHADOW_BGR
    assert (lit == PELLET_BGR).all(-1).sum() == (flat == PELLET_BGR).all(-1).sum() // 2
    assert segment_pellet_sinter(lit)[1].sum() == (lit == SHADOW_BGR).all(-1).sum() > 0  # shadow counts as sinter
    # the front disc's own rim lies up to a radius (4 mm) behind its centre: a depth of 2 mm shades it
    rim = render_front(centres, radii, labels, view, shadow_depth=0.002)
    assert tuple(rim[front]) == PELLET_BGR and tuple(rim[40, 16]) == SHADOW_BGR  # x = -11.75 mm: 3.75 mm out, 2.6 mm deep


def test_bad_palette_and_options_are_rejected():
    args = (np.zeros((1, 3)), np.array([0.01]), np.array([0]), View(-0.1, 0.1, -0.1, 0.1))
    with pytest.raises(ConfigError, match=r"palette\[0\] = \(0, 0, 300\) is not allowed; expected three integers"):
        render_front(*args, palette={0: (0, 0, 300)})
    with pytest.raises(ConfigError, match=r"rim_darkening = 1.0 is not allowed; expected a fraction in \[0, 1\)"):
        render_front(*args, rim_darkening=1.0)
    with pytest.raises(ConfigError, match=r"wall_thickness = 0.0 is not allowed; expected a finite thickness > 0 m"):
        render_front(*args, wall_thickness=0.0)
    with pytest.raises(ConfigError, match=r"shadow_depth = -0.01 is not allowed; expected a depth > 0 m behind the front"):
        render_front(*args, shadow_depth=-0.01)
    with pytest.raises(ConfigError, match=r"view is a tuple; expected a torchdem.render.View"):
        render_front(*args[:3], (0, 1, 0, 1))


def _tiny_system():
    """Two members of three spheres (two pellets, one sinter) in a box; member 1 moved up 2 cm
    and its sinter sphere deactivated."""
    materials = [Material("pellet", 1e7, 0.25, 3500.0), Material("sinter", 1e7, 0.25, 3000.0),
                 Material("steel", 2e11, 0.3, 7800.0)]
    pp = dict(mu_s=0.5, mu_r=0.05, restitution=0.5)
    pairs = {(a, b): pp for a, b in (("pellet", "pellet"), ("pellet", "sinter"), ("sinter", "sinter"),
                                      ("pellet", "steel"), ("sinter", "steel"))}
    table = interaction_table(materials, pairs, batch=2)
    position = torch.tensor([[[0.03, 0.02, 0.02], [0.07, 0.02, 0.02], [0.05, 0.02, 0.05]]], dtype=torch.float64)
    position = torch.cat([position, position + torch.tensor([0.0, 0.0, 0.02], dtype=torch.float64)])
    material = torch.tensor([[0, 0, 1], [0, 0, 1]])
    active = torch.tensor([[True, True, True], [True, True, False]])
    return build_system(position, material, materials, table, radius=torch.full((2, 3), 0.01, dtype=torch.float64),
                        active=active, walls=box_walls("box", (0, 0, 0), (0.1, 0.04, 0.1), "steel"))


def test_render_state_of_a_tiny_system():
    system, state = _tiny_system()
    view = View(-0.01, 0.11, -0.01, 0.11, metres_per_pixel=0.0005)
    labels = {0: PELLET_LABEL, 1: SINTER_LABEL}
    image0 = render_state(system, state, 0, labels, view)
    image1 = render_state(system, state, 1, labels, view)

    def at(image, x, z):
        return tuple(image[int(round(float(view.row(z)))), int(round(float(view.column(x))))])

    assert at(image0, 0.03, 0.02) == PELLET_BGR and at(image0, 0.05, 0.05) == SINTER_BGR
    assert at(image1, 0.03, 0.04) == PELLET_BGR and at(image1, 0.03, 0.02) == BACKGROUND_BGR
    assert at(image1, 0.05, 0.05) == BACKGROUND_BGR  # the inactive sinter sphere is not drawn
    assert at(image0, -0.002, 0.05) == WALL_BGR and at(image0, 0.05, -0.002) == WALL_BGR
    no_walls = render_state(system, state, 0, labels, view, walls=False)
    assert not (no_walls == WALL_BGR).all(-1).any()
    with pytest.raises(ConfigError, match=r"member = 2 is not allowed; expected an ensemble member index in \[0, 1\]"):
        render_state(system, state, 2, labels, view)
    with pytest.raises(ConfigError, match=r"no label for material 1 \('sinter'\)"):
        render_state(system, state, 0, {0: PELLET_LABEL}, view)


def test_a_stream_falling_on_the_apex_tilts_the_heap_and_render_state_leaves_it_out():
    """Why the draw down photographs only bodies at rest (torchdem.drawdown.AT_REST_SPEED_M_S):
    a trickle still falling from the slot joins the heap's apex in the photo, the profile's
    apex moves up into the stream and both fitted flanks steepen. The lab photographs after the
    discharge has ended; ``render_state(shown=...)`` draws only the bodies asked for."""
    heap = heap_centres()
    apex_x, apex_z = 0.5 * sum(BOX_X), HEAP_HALF_BASE * math.tan(math.radians(HEAP_ANGLE_DEG))
    zs = np.arange(apex_z + 1.9 * RADIUS, LOWER_Z[1] - RADIUS, 1.9 * RADIUS)  # a falling column
    stream = np.stack([apex_x + 0.6 * RADIUS * np.sin(7.0 * zs / RADIUS), np.full(zs.size, RADIUS), zs], 1)
    box = crop_box_for(VIEW, BOX_X[0], BOX_X[1], LOWER_Z[0], LOWER_Z[1])
    centres = np.concatenate([heap, stream])
    radius = np.full(len(centres), RADIUS)
    labels = np.zeros(len(centres), dtype=np.int64)
    with_stream = angle_of_repose(render_front(centres, radius, labels, VIEW), crop_box=box).angle_deg
    at_rest = angle_of_repose(render_front(heap, radius[:len(heap)], labels[:len(heap)], VIEW), crop_box=box).angle_deg
    assert at_rest == pytest.approx(HEAP_ANGLE_DEG, abs=ANGLE_TOLERANCE_DEG)
    assert with_stream > at_rest + 1.0, (with_stream, at_rest)

    system, state = _tiny_system()
    view = View(-0.01, 0.11, -0.01, 0.11, metres_per_pixel=0.0005)
    labels = {0: PELLET_LABEL, 1: SINTER_LABEL}
    image = render_state(system, state, 0, labels, view, shown=torch.tensor([True, False, True]))

    def at(x, z):
        return tuple(image[int(round(float(view.row(z)))), int(round(float(view.column(x))))])

    assert at(0.03, 0.02) == PELLET_BGR and at(0.05, 0.05) == SINTER_BGR
    assert at(0.07, 0.02) == BACKGROUND_BGR  # the body left out
    with pytest.raises(ConfigError, match=r"shown must be a bool mask of shape \(3,\)"):
        render_state(system, state, 0, labels, view, shown=torch.tensor([1, 0, 1]))
