"""Tests for kpi.segregation: painted two-colour images with known per-slice fractions."""
from __future__ import annotations

import math

import numpy as np
import pytest

from kpi.colors import BACKGROUND_BGR, PELLET_BGR, SINTER_BGR, WALL_BGR
from kpi.errors import KPIInputError
from kpi.io import CropBox
from kpi.segregation import SegmentationConfig, measure_segregation, segment_pellet_sinter

CELL_PX = 100
#: Pellet fraction painted in each 100 x 100 px cell of a 3 x 6 grid (rows top to bottom).
PELLET_SHARE = np.array(
    [
        [0.80, 0.70, 0.65, 0.55, 0.60, 0.90],
        [0.50, 0.45, 0.40, 0.35, 0.30, 0.55],
        [0.20, 0.25, 0.10, 0.15, 0.30, 0.05],
    ]
)
TOP, LEFT = 40, 50  # heap region offset in the image


def sample_rsd(values, ddof: int = 1) -> float:
    """sigma / mu written out, independent of numpy's std."""
    values = [float(v) for v in values]
    mean = sum(values) / len(values)
    variance = sum((v - mean) ** 2 for v in values) / (len(values) - ddof)
    return math.sqrt(variance) / mean


def paint_grid(
    pellet_bgr=PELLET_BGR, sinter_bgr=SINTER_BGR, background_bgr=BACKGROUND_BGR, noise: float = 0.0, seed: int = 0
) -> np.ndarray:
    """A 3 x 6 grid of cells; in each cell the left PELLET_SHARE part is pellet, the rest sinter.

    Walls frame the image and sinter-coloured dust specks lie outside the heap region.
    """
    rng = np.random.default_rng(seed)
    image = np.full((3 * CELL_PX + 120, 6 * CELL_PX + 120, 3), background_bgr, np.uint8)
    image[:, :8] = WALL_BGR
    image[:, -8:] = WALL_BGR
    image[-8:, :] = WALL_BGR
    for r in range(3):
        for c in range(6):
            y, x = TOP + r * CELL_PX, LEFT + c * CELL_PX
            split = int(round(PELLET_SHARE[r, c] * CELL_PX))
            image[y : y + CELL_PX, x : x + split] = pellet_bgr
            image[y : y + CELL_PX, x + split : x + CELL_PX] = sinter_bgr
    for x in range(20, image.shape[1] - 20, 37):  # dust above and below the heap region
        image[10:12, x : x + 2] = sinter_bgr
        image[TOP + 3 * CELL_PX + 20 : TOP + 3 * CELL_PX + 22, x : x + 2] = pellet_bgr
    if noise:
        image = np.clip(np.rint(image + rng.normal(0.0, noise, image.shape)), 0, 255).astype(np.uint8)
    return image


def test_painted_fractions_give_exact_rsd():
    result = measure_segregation(paint_grid(), source="grid.png")
    assert result.heap_box == CropBox(LEFT, TOP, LEFT + 6 * CELL_PX, TOP + 3 * CELL_PX)

    vertical_pellet = PELLET_SHARE.mean(axis=1)  # bands stacked top to bottom
    horizontal_pellet = PELLET_SHARE.mean(axis=0)  # strips side by side
    np.testing.assert_allclose(result.vertical.pellet_fraction, vertical_pellet, atol=1e-12)
    np.testing.assert_allclose(result.horizontal.pellet_fraction, horizontal_pellet, atol=1e-12)
    np.testing.assert_allclose(result.vertical.sinter_fraction, 1 - vertical_pellet, atol=1e-12)

    assert result.vertical.pellet_rsd == pytest.approx(sample_rsd(vertical_pellet), abs=1e-9)
    assert result.vertical.sinter_rsd == pytest.approx(sample_rsd(1 - vertical_pellet), abs=1e-9)
    assert result.horizontal.pellet_rsd == pytest.approx(sample_rsd(horizontal_pellet), abs=1e-9)
    assert result.horizontal.sinter_rsd == pytest.approx(sample_rsd(1 - horizontal_pellet), abs=1e-9)
    # the painted layering is stronger along the height than across the width
    assert result.vertical.pellet_rsd > 3 * result.horizontal.pellet_rsd

    assert result.vertical.slice_bounds_px == ((TOP, TOP + 100), (TOP + 100, TOP + 200), (TOP + 200, TOP + 300))
    assert result.horizontal.slice_bounds_px == tuple((LEFT + 100 * k, LEFT + 100 * (k + 1)) for k in range(6))
    assert result.ddof == 1


def test_two_components_share_sigma_and_fractions_sum_to_one():
    result = measure_segregation(paint_grid())
    for direction in (result.vertical, result.horizontal):
        np.testing.assert_allclose(direction.pellet_fraction + direction.sinter_fraction, 1.0, atol=1e-12)
        sigma_pellet = direction.pellet_rsd * direction.pellet_fraction.mean()
        sigma_sinter = direction.sinter_rsd * direction.sinter_fraction.mean()
        assert sigma_pellet == pytest.approx(sigma_sinter, rel=1e-12)


def test_population_ddof_scales_by_sqrt_k_minus_one_over_k():
    sample = measure_segregation(paint_grid())
    population = measure_segregation(paint_grid(), config=SegmentationConfig(ddof=0))
    assert population.vertical.pellet_rsd == pytest.approx(sample.vertical.pellet_rsd * math.sqrt(2 / 3), rel=1e-12)
    assert population.horizontal.sinter_rsd == pytest.approx(sample.horizontal.sinter_rsd * math.sqrt(5 / 6), rel=1e-12)


def test_white_painted_pellets_segment_like_blue_ones():
    blue = measure_segregation(paint_grid())
    white = measure_segregation(paint_grid(pellet_bgr=(255, 255, 255)))
    assert white.vertical.pellet_rsd == pytest.approx(blue.vertical.pellet_rsd, abs=1e-12)
    assert white.horizontal.pellet_rsd == pytest.approx(blue.horizontal.pellet_rsd, abs=1e-12)


def test_noisy_render_within_a_few_pixels_of_the_painted_fractions():
    # Gaussian pixel noise (sigma 6 grey levels) pushes about 1 in 50 000 dark-grey pixels past
    # the sinter chroma limit; allow 3 pixels' worth per slice.
    result = measure_segregation(paint_grid(noise=6.0, seed=3))
    band_px, strip_px = CELL_PX * 6 * CELL_PX, 3 * CELL_PX * CELL_PX  # pixels per band, per strip
    np.testing.assert_allclose(result.vertical.pellet_fraction, PELLET_SHARE.mean(axis=1), atol=3 / band_px)
    np.testing.assert_allclose(result.horizontal.pellet_fraction, PELLET_SHARE.mean(axis=0), atol=3 / strip_px)
    assert result.vertical.pellet_rsd == pytest.approx(sample_rsd(PELLET_SHARE.mean(axis=1)), rel=1e-3)
    assert result.horizontal.pellet_rsd == pytest.approx(sample_rsd(PELLET_SHARE.mean(axis=0)), rel=1e-3)


def test_tuned_thresholds_for_a_photo():
    # pale blue pellets (b* ~ -8.6), brownish sinter (chroma ~ 16), white backdrop (L* ~ 96)
    photo = paint_grid(pellet_bgr=(215, 200, 190), sinter_bgr=(55, 70, 95), background_bgr=(245, 245, 245))
    expected = sample_rsd(PELLET_SHARE.mean(axis=1))
    # defaults: the white backdrop passes as white-painted pellets, the pale pellets as nothing
    default = measure_segregation(photo, source="photo.jpg")
    assert abs(default.vertical.pellet_rsd - expected) > 0.1
    tuned = SegmentationConfig(pellet_b_max=-5.0, pellet_white_l_min=None, sinter_chroma_max=25.0)
    result = measure_segregation(photo, config=tuned, source="photo.jpg")
    assert result.vertical.pellet_rsd == pytest.approx(expected, abs=1e-9)


def test_crop_box_restricts_the_region():
    image = paint_grid()
    left_half = CropBox(0, 0, LEFT + 3 * CELL_PX, image.shape[0])
    result = measure_segregation(image, crop_box=left_half)
    assert result.heap_box == CropBox(LEFT, TOP, LEFT + 3 * CELL_PX, TOP + 3 * CELL_PX)
    assert result.pellet_mask.shape == (image.shape[0], LEFT + 3 * CELL_PX)
    # 6 strips of 50 px over the left three cell columns; two neighbouring strips of equal
    # material area make up one cell column
    fractions = result.horizontal.pellet_fraction
    np.testing.assert_allclose((fractions[0::2] + fractions[1::2]) / 2, PELLET_SHARE[:, :3].mean(axis=0), atol=1e-12)


def test_canonical_render_colours_are_classified():
    colours = np.array([[PELLET_BGR, SINTER_BGR, BACKGROUND_BGR, WALL_BGR]], np.uint8)
    pellet, sinter = segment_pellet_sinter(colours)
    assert pellet.tolist() == [[True, False, False, False]]
    assert sinter.tolist() == [[False, True, False, False]]


def test_image_without_material_names_file():
    image = np.full((200, 300, 3), BACKGROUND_BGR, np.uint8)
    with pytest.raises(KPIInputError, match=r"^empty\.png: no heap found"):
        measure_segregation(image, source="empty.png")


def test_missing_component_makes_rsd_undefined():
    image = paint_grid(sinter_bgr=PELLET_BGR)
    with pytest.raises(KPIInputError, match=r"^pellets\.png: no sinter pixels in the heap region"):
        measure_segregation(image, source="pellets.png")


def test_empty_slice_is_reported():
    image = paint_grid()
    image[:, LEFT + 200 : LEFT + 300] = BACKGROUND_BGR  # the third strip holds no material
    with pytest.raises(KPIInputError, match=r"^gap\.png: horizontal-segregation slice 3 of 6 \(image columns 250\.\.350\)"):
        measure_segregation(image, source="gap.png")


def test_config_values_are_validated():
    with pytest.raises(KPIInputError, match=r"SegmentationConfig: ddof = 2 is not allowed"):
        SegmentationConfig(ddof=2)
    with pytest.raises(KPIInputError, match=r"SegmentationConfig: vertical_segregation_slices = 1 is not allowed; expected an integer >= 2"):
        SegmentationConfig(vertical_segregation_slices=1)
    with pytest.raises(KPIInputError, match=r"SegmentationConfig: pellet_b_max = 5\.0 is not allowed"):
        SegmentationConfig(pellet_b_max=5.0)


def test_a_grain_resting_apart_from_the_heap_does_not_stretch_the_region():
    """A sinter grain at rest above the heap (in a draw-down photo: wedged under the slot) is a region of
    its own, far smaller than the heap: the heap region and the RSDs stay those of the grid, unless
    ``min_component_fraction`` = 0 keeps it, when the top band takes the empty rows above the grid."""
    image = paint_grid()
    image[14:26, 300:312] = SINTER_BGR  # 12 x 12 px, 0.08 % of the heap's area, above the grid (TOP = 40)
    clean = measure_segregation(paint_grid())
    result = measure_segregation(image)
    assert result.heap_box == clean.heap_box == CropBox(LEFT, TOP, LEFT + 6 * CELL_PX, TOP + 3 * CELL_PX)
    assert result.vertical.pellet_rsd == pytest.approx(clean.vertical.pellet_rsd, rel=1e-12)
    kept = measure_segregation(image, config=SegmentationConfig(min_component_fraction=0.0))
    assert kept.heap_box.y0 == 14 and kept.vertical.pellet_rsd != pytest.approx(clean.vertical.pellet_rsd, rel=1e-3)
    with pytest.raises(KPIInputError, match=r"min_component_fraction = 1\.5 is not allowed; expected a fraction in \[0, 1\]"):
        SegmentationConfig(min_component_fraction=1.5)
