"""Segregation of pellets and sinter in the lower-box heap: colour masks, slices, RSD.

Contract (paper section 2.3.2):

1. **Segment** the (cropped) image by colour in CIE L*a*b* (:func:`kpi.colors.bgr_to_lab`):
   a pixel is *pellet* if it is painted blue (b* <= ``pellet_b_max``) or painted white
   (L* >= ``pellet_white_l_min`` and chroma sqrt(a*^2 + b*^2) <= ``pellet_white_chroma_max``);
   it is *sinter* if it is dark and neutral (L* <= ``sinter_l_max`` and chroma <=
   ``sinter_chroma_max``) and not pellet. Anything else -- background, walls, glare -- is
   neither and is not counted. The defaults separate the render colours of
   :mod:`kpi.colors`; tune :class:`SegmentationConfig` for lab photos.
2. **Heap region**: the bounding box of all pellet and sinter pixels after a morphological
   opening removes specks and connected regions smaller than ``min_component_fraction`` of the
   largest are dropped (a grain left resting apart from the heap, e.g. wedged under the slot), so
   the slicing does not depend on how much empty space the crop leaves around the heap.
3. **Slice** the heap region into equal slices (boundaries rounded to whole pixels) and count
   pellet and sinter pixels N_i,k in each slice k. The pixel fraction of component i is the
   paper's Eq. (1), C_i,k = N_i,k / sum_i N_i,k (only pellet and sinter pixels count).
4. **RSD** per component, Eq. (2): RSD_i = sigma_i / mu_i over the slices, with sigma_i the
   *sample* standard deviation (``ddof=1``, dividing by K - 1). The paper does not print the
   divisor; it used MATLAB, whose ``std`` divides by K - 1 by default, so ddof = 1 is the
   faithful reading. ``SegmentationConfig.ddof`` = 0 gives the population form.

Directions -- our reading of the paper: "we divided the image into slices, either vertically
(Fig. 5(c)) or horizontally (Fig. 5(d)), to measure segregation in the respective direction
... 6 and 3 slices for horizontal and vertical directions". **Vertical segregation** is
variation *along the vertical (height) axis*: the heap region is cut by horizontal lines into
3 bands stacked top to bottom. **Horizontal segregation** is variation *along the horizontal
axis*: the region is cut by vertical lines into 6 strips side by side. The figure itself is
not in our copy of the paper, so this rests on the text. "Divided vertically" could also be
read as "cut by vertical lines"; we take the reading in which the direction names the axis
along which composition varies, which is how "vertical segregation" is used in the granular
literature (composition changing with height, as percolation and stratification produce),
and the slice counts fit it: a heap at ~30 deg is several times wider than it is high, so
more slices go across (6) than up (3). With two components
sigma_pellet = sigma_sinter, so the two RSDs differ only through the means (Table 2 prints
one value per direction without naming the component); both are reported.

Errors: no pellet/sinter pixels, an empty slice or a component absent from the heap raise
:class:`kpi.errors.KPIInputError` naming the image.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from kpi.angles import large_regions
from kpi.colors import bgr_to_lab
from kpi.errors import bad_input, out_of_range
from kpi.io import CropBox, crop

SegregationDirection = Literal["vertical", "horizontal"]


@dataclass(frozen=True)
class SegmentationConfig:
    """Colour thresholds (CIE L*a*b*, L* in [0, 100]) and slicing settings.

    Attributes:
        pellet_b_max: blue-painted pellet if b* <= this.
        pellet_white_l_min: white-painted pellet if L* >= this (and chroma small); None
            disables the white rule (e.g. for photos against a white backdrop).
        pellet_white_chroma_max: largest chroma of a white-painted pellet pixel.
        sinter_l_max: sinter if L* <= this (and chroma small).
        sinter_chroma_max: largest chroma of a sinter pixel (dark grey is near-neutral).
        vertical_segregation_slices: number of horizontal bands stacked top to bottom (3).
        horizontal_segregation_slices: number of vertical strips side by side (6).
        ddof: delta degrees of freedom of sigma_i in Eq. (2): 1 (sample std, MATLAB's
            default) or 0 (population std).
        speck_size_px: opening kernel in pixels used to find the heap region (1: none).
        min_component_fraction: connected regions smaller than this fraction of the largest are not
            part of the heap region (0 keeps them all).
    """

    pellet_b_max: float = -20.0
    pellet_white_l_min: float | None = 85.0
    pellet_white_chroma_max: float = 12.0
    sinter_l_max: float = 60.0
    sinter_chroma_max: float = 25.0
    vertical_segregation_slices: int = 3
    horizontal_segregation_slices: int = 6
    ddof: int = 1
    speck_size_px: int = 5
    min_component_fraction: float = 0.05

    def __post_init__(self) -> None:
        source = "SegmentationConfig"
        if not (np.isfinite(self.pellet_b_max) and -128 <= self.pellet_b_max < 0):
            raise out_of_range(source, "pellet_b_max", self.pellet_b_max, "a b* value in [-128, 0) (blue is b* < 0)")
        if self.pellet_white_l_min is not None and not 0 < self.pellet_white_l_min <= 100:
            raise out_of_range(source, "pellet_white_l_min", self.pellet_white_l_min, "None or an L* value in (0, 100]")
        if not (np.isfinite(self.pellet_white_chroma_max) and self.pellet_white_chroma_max >= 0):
            raise out_of_range(source, "pellet_white_chroma_max", self.pellet_white_chroma_max, "a chroma >= 0")
        if not 0 < self.sinter_l_max <= 100:
            raise out_of_range(source, "sinter_l_max", self.sinter_l_max, "an L* value in (0, 100]")
        if not (np.isfinite(self.sinter_chroma_max) and self.sinter_chroma_max >= 0):
            raise out_of_range(source, "sinter_chroma_max", self.sinter_chroma_max, "a chroma >= 0")
        for name in ("vertical_segregation_slices", "horizontal_segregation_slices", "speck_size_px"):
            value = getattr(self, name)
            smallest = 1 if name == "speck_size_px" else 2
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < smallest:
                raise out_of_range(source, name, value, f"an integer >= {smallest}")
        if self.ddof not in (0, 1):
            raise out_of_range(source, "ddof", self.ddof, "0 (population std) or 1 (sample std)")
        if not 0 <= self.min_component_fraction <= 1:
            raise out_of_range(source, "min_component_fraction", self.min_component_fraction, "a fraction in [0, 1]")


@dataclass(frozen=True)
class SliceSegregation:
    """Pixel fractions per slice and the resulting RSD for one direction.

    Attributes:
        direction: ``"vertical"`` (bands stacked top to bottom) or ``"horizontal"``
            (strips side by side).
        slice_bounds_px: half-open ``(start, end)`` image rows (vertical) or image columns
            (horizontal) of every slice, top/left first.
        pellet_fraction, sinter_fraction: ``[K]`` Eq. (1) pixel fractions; they sum to 1.
        pellet_rsd, sinter_rsd: Eq. (2) RSD of each component over the K slices.
    """

    direction: SegregationDirection
    slice_bounds_px: tuple[tuple[int, int], ...]
    pellet_fraction: np.ndarray
    sinter_fraction: np.ndarray
    pellet_rsd: float
    sinter_rsd: float


@dataclass(frozen=True)
class Segregation:
    """Vertical and horizontal segregation of one lower-box image.

    Attributes:
        vertical, horizontal: per-direction slice fractions and RSDs.
        heap_box: the heap region that was sliced, in full-image pixels.
        crop_box: the region of interest that was segmented, in full-image pixels.
        pellet_mask, sinter_mask: ``bool [h, w]`` masks over the crop (paper Fig. 5(b)).
        ddof: divisor offset used for sigma (1: sample std).
        source: where the image came from.
    """

    vertical: SliceSegregation
    horizontal: SliceSegregation
    heap_box: CropBox
    crop_box: CropBox
    pellet_mask: np.ndarray
    sinter_mask: np.ndarray
    ddof: int
    source: str


def segment_pellet_sinter(
    image_bgr: np.ndarray, config: SegmentationConfig = SegmentationConfig()
) -> tuple[np.ndarray, np.ndarray]:
    """Pellet and sinter masks (``bool [H, W]`` each, disjoint) of an 8-bit BGR image."""
    lab = bgr_to_lab(image_bgr)
    lightness, a_star, b_star = lab[..., 0], lab[..., 1], lab[..., 2]
    chroma = np.hypot(a_star, b_star)
    pellet = b_star <= config.pellet_b_max
    if config.pellet_white_l_min is not None:
        pellet |= (lightness >= config.pellet_white_l_min) & (chroma <= config.pellet_white_chroma_max)
    sinter = (lightness <= config.sinter_l_max) & (chroma <= config.sinter_chroma_max) & ~pellet
    return pellet, sinter


def relative_standard_deviation(fractions: np.ndarray, ddof: int = 1) -> float:
    """Eq. (2): sigma / mu of the per-slice fractions ``[K]``; NaN if mu is 0."""
    fractions = np.asarray(fractions, dtype=float)
    mean = float(fractions.mean())
    return float(fractions.std(ddof=ddof) / mean) if mean > 0 else float("nan")


def _slice_bounds(length: int, count: int) -> np.ndarray:
    return np.rint(np.linspace(0, length, count + 1)).astype(int)


def _slice_segregation(
    pellet: np.ndarray,
    sinter: np.ndarray,
    direction: SegregationDirection,
    count: int,
    offset: int,
    ddof: int,
    source: str,
) -> SliceSegregation:
    """Fractions and RSD over ``count`` slices of masks already cut to the heap region."""
    axis_name = "rows" if direction == "vertical" else "columns"
    keep_axis = 0 if direction == "vertical" else 1  # rows for bands, columns for strips
    length = pellet.shape[keep_axis]
    if length < count:
        raise bad_input(
            source,
            f"heap region is {length} pixel {axis_name} long, too small for {count} {direction}-segregation "
            f"slices; expected at least one pixel per slice",
        )
    bounds = _slice_bounds(length, count)
    per_line_pellet = pellet.sum(axis=1 - keep_axis)
    per_line_sinter = sinter.sum(axis=1 - keep_axis)
    pellet_count = np.add.reduceat(per_line_pellet, bounds[:-1]).astype(float)
    sinter_count = np.add.reduceat(per_line_sinter, bounds[:-1]).astype(float)
    total = pellet_count + sinter_count
    empty = np.flatnonzero(total == 0)
    if empty.size:
        k = int(empty[0])
        raise bad_input(
            source,
            f"{direction}-segregation slice {k + 1} of {count} (image {axis_name} "
            f"{bounds[k] + offset}..{bounds[k + 1] + offset}) holds no pellet or sinter pixels",
        )
    pellet_fraction = pellet_count / total
    sinter_fraction = sinter_count / total
    for name, fraction in (("pellet", pellet_fraction), ("sinter", sinter_fraction)):
        if fraction.max() == 0:
            raise bad_input(
                source,
                f"no {name} pixels in the heap region, so its RSD (sigma/mu) is undefined; check "
                f"the SegmentationConfig {name} thresholds",
            )
    for fraction in (pellet_fraction, sinter_fraction):
        fraction.setflags(write=False)
    return SliceSegregation(
        direction=direction,
        slice_bounds_px=tuple((int(bounds[k] + offset), int(bounds[k + 1] + offset)) for k in range(count)),
        pellet_fraction=pellet_fraction,
        sinter_fraction=sinter_fraction,
        pellet_rsd=relative_standard_deviation(pellet_fraction, ddof),
        sinter_rsd=relative_standard_deviation(sinter_fraction, ddof),
    )


def measure_segregation(
    image_bgr: np.ndarray,
    *,
    crop_box: CropBox | None = None,
    config: SegmentationConfig = SegmentationConfig(),
    source: str = "image",
) -> Segregation:
    """Vertical and horizontal segregation (RSD per component) of the lower-box heap.

    Args:
        image_bgr: 8-bit BGR image ``[H, W, 3]`` (see :func:`kpi.io.read_image`).
        crop_box: region of interest holding the heap; the whole image if None.
        config: colour thresholds, slice counts, ddof.
        source: name of the image for error messages (its file path).
    """
    image_bgr = np.asarray(image_bgr)
    if image_bgr.dtype != np.uint8 or image_bgr.ndim != 3 or image_bgr.shape[2] != 3 or image_bgr.size == 0:
        raise bad_input(source, f"expected a non-empty 8-bit BGR image [H, W, 3]; got dtype {image_bgr.dtype}, shape {image_bgr.shape}")
    crop_box = CropBox.whole(image_bgr) if crop_box is None else crop_box
    pellet, sinter = segment_pellet_sinter(crop(image_bgr, crop_box, source), config)

    material = (pellet | sinter).astype(np.uint8)
    if config.speck_size_px > 1:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (config.speck_size_px, config.speck_size_px))
        material = cv2.morphologyEx(material, cv2.MORPH_OPEN, kernel)
    material = large_regions(material, config.min_component_fraction)
    rows = np.flatnonzero(material.any(axis=1))
    columns = np.flatnonzero(material.any(axis=0))
    if rows.size == 0:
        raise bad_input(
            source,
            f"no heap found: no pellet or sinter pixels in crop box (x0={crop_box.x0}, y0={crop_box.y0}, "
            f"x1={crop_box.x1}, y1={crop_box.y1}); check the crop box and SegmentationConfig thresholds",
        )
    top, bottom, left, right = int(rows[0]), int(rows[-1]) + 1, int(columns[0]), int(columns[-1]) + 1
    heap_pellet, heap_sinter = pellet[top:bottom, left:right], sinter[top:bottom, left:right]
    heap_box = CropBox(crop_box.x0 + left, crop_box.y0 + top, crop_box.x0 + right, crop_box.y0 + bottom)

    vertical = _slice_segregation(
        heap_pellet, heap_sinter, "vertical", config.vertical_segregation_slices, heap_box.y0, config.ddof, source
    )
    horizontal = _slice_segregation(
        heap_pellet, heap_sinter, "horizontal", config.horizontal_segregation_slices, heap_box.x0, config.ddof, source
    )
    return Segregation(
        vertical=vertical,
        horizontal=horizontal,
        heap_box=heap_box,
        crop_box=crop_box,
        pellet_mask=pellet,
        sinter_mask=sinter,
        ddof=config.ddof,
        source=source,
    )
