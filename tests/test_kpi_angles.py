"""Tests for kpi.angles: synthetic heaps and funnels with known slopes, drawn with cv2."""
from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from kpi.angles import SurfaceConfig, angle_of_repose, measure_surface_angle, remove_background, shear_angle
from kpi.colors import BACKGROUND_BGR, PELLET_BGR, SINTER_BGR, WALL_BGR
from kpi.errors import KPIInputError
from kpi.io import CropBox

ANGLE_TOLERANCE_DEG = 0.5
WALL_PX = 12


#: Particles (circles of radius 3-5 px) per pixel of heap area. Their random protrusion above
#: the true surface makes the measured angle scatter with a standard deviation of about 0.11 deg
#: (measured over 30 seeds, no bias beyond 0.04 deg), so the 0.5 deg tolerance is ~4.5 sigma.
PARTICLE_DENSITY = 0.07


def _texture(image: np.ndarray, polygon: np.ndarray, rng: np.random.Generator) -> None:
    """Fill ``polygon`` with sinter grey and scatter pellet/sinter 'particles' over it.

    Particle centres lie inside the polygon, so particles on the surface protrude above it
    like real ones do.
    """
    mask = np.zeros(image.shape[:2], np.uint8)
    cv2.fillPoly(mask, [polygon], 1)
    cv2.fillPoly(image, [polygon], SINTER_BGR)
    rows, cols = np.nonzero(mask)
    picks = rng.integers(0, rows.size, size=int(PARTICLE_DENSITY * rows.size))
    for row, col in zip(rows[picks], cols[picks]):
        base = PELLET_BGR if rng.random() < 0.5 else SINTER_BGR
        shade = rng.uniform(0.7, 1.1)
        colour = tuple(int(min(255, c * shade)) for c in base)
        cv2.circle(image, (int(col), int(row)), int(rng.integers(3, 6)), colour, -1, lineType=cv2.LINE_AA)


def _finish(image: np.ndarray, rng: np.random.Generator, specks: int = 40) -> np.ndarray:
    """Draw box walls, add dark specks (dust) in the background and Gaussian pixel noise."""
    height, width = image.shape[:2]
    image[:, :WALL_PX] = WALL_BGR
    image[:, width - WALL_PX :] = WALL_BGR
    image[height - WALL_PX :, :] = WALL_BGR
    for _ in range(specks):
        x, y = int(rng.integers(WALL_PX, width - WALL_PX - 2)), int(rng.integers(0, height // 4))
        image[y : y + 2, x : x + 2] = SINTER_BGR
    noisy = image.astype(np.float32) + rng.normal(0.0, 6.0, image.shape)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def draw_heap(
    left_deg: float = 29.5,
    right_deg: float = 31.0,
    width: int = 640,
    height: int = 360,
    apex_x: int = 300,
    apex_height_px: float = 240.0,
    seed: int = 0,
) -> tuple[np.ndarray, CropBox]:
    """A lower-box heap between two walls with the given slopes; returns (image, inner crop box)."""
    rng = np.random.default_rng(seed)
    image = np.full((height, width, 3), BACKGROUND_BGR, np.uint8)
    floor = height - WALL_PX
    x_left, x_right = WALL_PX, width - WALL_PX
    h_left = apex_height_px - math.tan(math.radians(left_deg)) * (apex_x - x_left)
    h_right = apex_height_px - math.tan(math.radians(right_deg)) * (x_right - apex_x)
    assert h_left > 0 and h_right > 0, "heap must span the box"
    scale = 16  # sub-pixel vertices (cv2 shift) so the drawn slopes are exact
    polygon = np.array(
        [
            (x_left, floor),
            (x_left, floor - h_left),
            (apex_x, floor - apex_height_px),
            (x_right, floor - h_right),
            (x_right, floor),
        ]
    )
    polygon = np.rint(polygon * scale).astype(np.int32)
    mask = np.zeros((height, width), np.uint8)
    cv2.fillPoly(mask, [polygon], 1, shift=4)
    outline = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)[0][0]
    _texture(image, outline, rng)
    return _finish(image, rng), CropBox(WALL_PX, 0, width - WALL_PX, floor)


def draw_funnel(
    left_deg: float = 41.0,
    right_deg: float = 44.0,
    width: int = 640,
    height: int = 400,
    outlet_px: int = 70,
    seed: int = 1,
) -> tuple[np.ndarray, CropBox]:
    """Material left in the upper box: two wedges falling towards a central outlet."""
    rng = np.random.default_rng(seed)
    image = np.full((height, width, 3), BACKGROUND_BGR, np.uint8)
    floor = height - WALL_PX
    x_left, x_right = WALL_PX, width - WALL_PX
    centre = width / 2
    gap_left, gap_right = centre - outlet_px / 2, centre + outlet_px / 2
    h_left = math.tan(math.radians(left_deg)) * (gap_left - x_left)
    h_right = math.tan(math.radians(right_deg)) * (x_right - gap_right)
    for wedge in (
        [(x_left, floor), (x_left, floor - h_left), (gap_left, floor)],
        [(gap_right, floor), (x_right, floor - h_right), (x_right, floor)],
    ):
        mask = np.zeros((height, width), np.uint8)
        cv2.fillPoly(mask, [np.rint(np.array(wedge) * 16).astype(np.int32)], 1, shift=4)
        outline = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)[0][0]
        _texture(image, outline, rng)
    image = _finish(image, rng)
    image[floor:, int(gap_left) : int(gap_right)] = BACKGROUND_BGR  # the open outlet
    return image, CropBox(WALL_PX, 0, width - WALL_PX, floor)


@pytest.mark.parametrize("left_deg,right_deg,seed", [(29.5, 31.0, 0), (25.0, 35.0, 3), (33.0, 28.0, 4)])
def test_angle_of_repose_of_synthetic_heap(left_deg, right_deg, seed):
    image, box = draw_heap(left_deg, right_deg, seed=seed)
    result = angle_of_repose(image, crop_box=box, source="heap.png")
    assert result.kind == "repose"
    assert result.left_angle_deg == pytest.approx(left_deg, abs=ANGLE_TOLERANCE_DEG)
    assert result.right_angle_deg == pytest.approx(right_deg, abs=ANGLE_TOLERANCE_DEG)
    assert result.angle_deg == pytest.approx((left_deg + right_deg) / 2, abs=ANGLE_TOLERANCE_DEG)
    assert result.split_x_px == pytest.approx(300, abs=15)  # at the apex


def test_shear_angle_of_synthetic_funnel():
    image, box = draw_funnel(41.0, 44.0)
    result = shear_angle(image, crop_box=box, source="upper.png")
    assert result.kind == "shear"
    assert result.left_angle_deg == pytest.approx(41.0, abs=ANGLE_TOLERANCE_DEG)
    assert result.right_angle_deg == pytest.approx(44.0, abs=ANGLE_TOLERANCE_DEG)
    assert result.angle_deg == pytest.approx(42.5, abs=ANGLE_TOLERANCE_DEG)
    assert result.split_x_px == pytest.approx(320, abs=5)  # middle of the outlet gap
    # no profile inside the outlet gap
    in_gap = (result.profile.columns_px > 300) & (result.profile.columns_px < 340)
    assert np.all(np.isnan(result.profile.top_rows_px[in_gap]))


def test_lines_and_profile_are_in_full_image_coordinates():
    image, box = draw_heap(seed=5)
    padded = cv2.copyMakeBorder(image, 30, 10, 50, 20, cv2.BORDER_CONSTANT, value=BACKGROUND_BGR)
    moved = CropBox(box.x0 + 50, box.y0 + 30, box.x1 + 50, box.y1 + 30)
    base = angle_of_repose(image, crop_box=box)
    shifted = angle_of_repose(padded, crop_box=moved)
    assert shifted.angle_deg == pytest.approx(base.angle_deg, abs=1e-9)
    np.testing.assert_allclose(shifted.profile.columns_px, base.profile.columns_px + 50)
    np.testing.assert_allclose(shifted.profile.top_rows_px, base.profile.top_rows_px + 30)
    assert shifted.left_line.row_at(400.0) == pytest.approx(base.left_line.row_at(350.0) + 30)
    # the fitted line runs along the extracted profile
    (x0, r0), (x1, r1) = base.right_line.endpoints_px()
    on_side = (base.profile.columns_px >= x0) & (base.profile.columns_px <= x1)
    residual = base.profile.top_rows_px[on_side] - base.right_line.row_at(base.profile.columns_px[on_side])
    assert np.nanmean(residual) == pytest.approx(0.0, abs=1e-6)
    assert np.nanstd(residual) < 4.0


def test_pixel_aspect_corrects_non_square_pixels():
    image, box = draw_heap(seed=6)
    stretched = cv2.resize(image, (image.shape[1], image.shape[0] * 2), interpolation=cv2.INTER_NEAREST)
    stretched_box = CropBox(box.x0, box.y0 * 2, box.x1, box.y1 * 2)
    naive = angle_of_repose(stretched, crop_box=stretched_box)
    corrected = angle_of_repose(stretched, crop_box=stretched_box, pixel_aspect=0.5)
    assert naive.left_angle_deg == pytest.approx(math.degrees(math.atan(2 * math.tan(math.radians(29.5)))), abs=1.0)
    assert corrected.left_angle_deg == pytest.approx(29.5, abs=ANGLE_TOLERANCE_DEG)
    assert corrected.right_angle_deg == pytest.approx(31.0, abs=ANGLE_TOLERANCE_DEG)


def test_fixed_threshold_and_custom_background_for_photos():
    image, box = draw_heap(seed=7)
    backdrop = (235, 235, 240)  # a light grey lab backdrop instead of the render green
    green = np.all(np.abs(image.astype(int) - BACKGROUND_BGR) < 40, axis=-1)
    photo = image.copy()
    photo[green] = backdrop
    config = SurfaceConfig(background_bgr=backdrop, background_delta_e=25.0)
    result = angle_of_repose(photo, crop_box=box, config=config)
    assert result.left_angle_deg == pytest.approx(29.5, abs=ANGLE_TOLERANCE_DEG)
    assert result.right_angle_deg == pytest.approx(31.0, abs=ANGLE_TOLERANCE_DEG)
    with pytest.raises(KPIInputError, match=r"^photo\.jpg: background colour \(0, 255, 0\) \(BGR\) not found"):
        angle_of_repose(photo, crop_box=box, source="photo.jpg")  # default: the render green


def test_remove_background_cleans_specks_and_inserts_artificial_background():
    image, box = draw_heap(seed=8)
    cropped = image[box.y0 : box.y1, box.x0 : box.x1]
    preprocessed, material = remove_background(cropped)
    assert material.dtype == bool and material.shape == cropped.shape[:2]
    assert not material[: cropped.shape[0] // 4 - 40].any()  # dust specks above the heap removed
    assert material[-5:].all()  # heap base is solid
    np.testing.assert_array_equal(preprocessed[~material], np.broadcast_to(BACKGROUND_BGR, preprocessed[~material].shape))
    np.testing.assert_array_equal(preprocessed[material], cropped[material])


def test_blank_image_has_no_heap():
    blank = np.full((200, 300, 3), BACKGROUND_BGR, np.uint8)
    blank = np.clip(blank + np.random.default_rng(0).normal(0, 6, blank.shape), 0, 255).astype(np.uint8)
    with pytest.raises(KPIInputError, match=r"^blank\.png: no heap found"):
        angle_of_repose(blank, source="blank.png")
    with pytest.raises(KPIInputError, match=r"^blank\.png: no remaining material \(funnel\) found"):
        shear_angle(blank, source="blank.png")


def test_one_sided_ramp_is_not_a_heap():
    image = np.full((300, 400, 3), BACKGROUND_BGR, np.uint8)
    cv2.fillPoly(image, [np.array([(0, 299), (399, 60), (399, 299)], np.int32)], SINTER_BGR)
    with pytest.raises(KPIInputError, match=r"^ramp\.png: no right side of the heap"):
        angle_of_repose(image, source="ramp.png")


def test_heap_measured_as_funnel_is_rejected():
    image, box = draw_heap(seed=9)
    with pytest.raises(KPIInputError, match=r"^heap\.png: no right side of the remaining material \(funnel\)"):
        shear_angle(image, crop_box=box, source="heap.png")


def test_split_heap_measured_as_funnel_slopes_the_wrong_way():
    # two wedges rising towards a central gap: the lowest point is the gap, but neither side
    # falls towards it
    image = np.full((300, 600, 3), BACKGROUND_BGR, np.uint8)
    cv2.fillPoly(image, [np.array([(0, 299), (270, 60), (270, 299)], np.int32)], SINTER_BGR)
    cv2.fillPoly(image, [np.array([(330, 299), (330, 60), (599, 299)], np.int32)], PELLET_BGR)
    with pytest.raises(
        KPIInputError, match=r"^notch\.png: the left side of the surface does not fall towards the funnel's bottom \(fitted angle -4\d\.\d\d deg"
    ):
        shear_angle(image, source="notch.png")


def test_crop_box_outside_image_names_file():
    image, _ = draw_heap(seed=10)
    with pytest.raises(KPIInputError, match=r"^heap\.png: crop box .* does not fit the 640 x 360"):
        angle_of_repose(image, crop_box=CropBox(0, 0, 700, 300), source="heap.png")


def test_bad_arguments_and_config_values_are_named():
    image, box = draw_heap(seed=11)
    with pytest.raises(KPIInputError, match=r"heap\.png: pixel_aspect = 0\.0 is not allowed"):
        angle_of_repose(image, crop_box=box, pixel_aspect=0.0, source="heap.png")
    with pytest.raises(KPIInputError, match=r"heap\.png: kind = 'slope' is not allowed"):
        measure_surface_angle(image, "slope", source="heap.png")
    with pytest.raises(KPIInputError, match=r"SurfaceConfig: speck_size_px = 0 is not allowed"):
        SurfaceConfig(speck_size_px=0)
    with pytest.raises(KPIInputError, match=r"SurfaceConfig: background_bgr = \(0, 300, 0\)"):
        SurfaceConfig(background_bgr=(0, 300, 0))


def test_result_is_frozen():
    image, box = draw_heap(seed=12)
    result = angle_of_repose(image, crop_box=box)
    with pytest.raises(dataclasses.FrozenInstanceError):
        result.angle_deg = 0.0  # type: ignore[misc]
