"""Angle of repose and shear angle from a front-view photo or render of the draw-down test.

Contract (paper section 2.3.1, done with OpenCV instead of MATLAB):

1. **Crop** the image to the region of interest (:class:`kpi.io.CropBox`): the inside of the
   lower box for the angle of repose, the inside of the upper box for the shear angle. The box
   should lie inside the walls: every pixel that is not background is taken as material.
2. **Remove the background**: the CIE76 colour difference (Delta E) of every pixel from the
   background colour (``SurfaceConfig.background_bgr``, the render convention
   :data:`kpi.colors.BACKGROUND_BGR` by default; set it to the backdrop of a lab photo).
   Pixels close to it are background and are replaced by the artificial background
   :data:`kpi.colors.BACKGROUND_BGR` in the preprocessed image (for reports).
3. **Binarise**: material = Delta E above a threshold, Otsu's threshold on the Delta E image by
   default (never below ``min_background_delta_e``) or a fixed ``background_delta_e``. Specks
   are removed with a morphological opening, gaps between particles at the surface closed with
   a closing, and connected components much smaller than the largest are dropped.
4. **Extract the edge**: for each image column, the highest material pixel (the free surface
   profile). Columns without material (the outlet gap, the ground beyond a heap) have no edge.
5. **Split and fit**: the profile is split at its extremum -- the heap's apex for the angle of
   repose (the paper's "divided at the center"), the bottom of the V/funnel for the shear
   angle -- and each half is fitted with a least-squares straight line over the *whole* half,
   flattened parts included, as the paper does. Each line's inclination to the horizontal is
   that side's angle; the KPI is the mean of the left and right angles.

Units and geometry: pixels are assumed square unless ``pixel_aspect`` (height of a pixel over
its width, both in metres) says otherwise; only angles are measured, so no metric scale is
needed. Angles are reported in degrees (this is the KPI edge). Lines and profiles are in
full-image pixel coordinates (x = column, row = y down) so a report can draw them on the
original image.

Errors: a crop outside the image, an image with no material, or a side that does not slope
the way a heap (or funnel) must raise :class:`kpi.errors.KPIInputError` naming the source.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from scipy.ndimage import median_filter

from kpi.colors import BACKGROUND_BGR, bgr_colour_to_lab, bgr_to_lab, delta_e
from kpi.errors import bad_input, out_of_range
from kpi.io import CropBox, crop

SurfaceKind = Literal["repose", "shear"]

#: Fewest profile columns a side needs for its line fit (two define a line; a third gives
#: a residual), independent of ``min_side_fraction``.
MIN_SIDE_COLUMNS = 3


@dataclass(frozen=True)
class SurfaceConfig:
    """Background removal, binarisation and profile-splitting settings.

    Attributes:
        background_bgr: colour of the background (8-bit BGR) to remove.
        background_delta_e: fixed Delta E (CIE76) threshold between background and material;
            ``None`` uses Otsu's threshold on the Delta E image.
        min_background_delta_e: lower bound on Otsu's threshold, so an image that is almost
            all background does not turn its noise into material.
        speck_size_px: diameter in pixels of the opening/closing kernel (1 disables cleaning).
        min_component_fraction: connected material regions smaller than this fraction of the
            largest one are dropped as debris.
        min_side_fraction: each side of the split profile must hold at least this fraction of
            the profile's columns, else the image shows no two-sided heap (or funnel).
        background_match_delta_e: the pixels classed as background must differ from
            ``background_bgr`` by at most this median Delta E, else the configured background
            colour is not the image's (e.g. the render green applied to a lab photo).
    """

    background_bgr: tuple[int, int, int] = BACKGROUND_BGR
    background_delta_e: float | None = None
    min_background_delta_e: float = 10.0
    speck_size_px: int = 5
    min_component_fraction: float = 0.05
    min_side_fraction: float = 0.1
    background_match_delta_e: float = 30.0

    def __post_init__(self) -> None:
        source = "SurfaceConfig"
        try:
            colour = tuple(float(c) for c in self.background_bgr)
        except (TypeError, ValueError):
            colour = ()
        if len(colour) != 3 or not all(c.is_integer() and 0 <= c <= 255 for c in colour):
            raise out_of_range(source, "background_bgr", self.background_bgr, "three integers in 0..255 (B, G, R)")
        object.__setattr__(self, "background_bgr", tuple(int(c) for c in colour))
        if self.background_delta_e is not None and not (
            np.isfinite(self.background_delta_e) and self.background_delta_e > 0
        ):
            raise out_of_range(source, "background_delta_e", self.background_delta_e, "None or a finite Delta E > 0")
        if not (np.isfinite(self.min_background_delta_e) and self.min_background_delta_e >= 0):
            raise out_of_range(source, "min_background_delta_e", self.min_background_delta_e, "a finite Delta E >= 0")
        if isinstance(self.speck_size_px, bool) or not isinstance(self.speck_size_px, (int, np.integer)) or self.speck_size_px < 1:
            raise out_of_range(source, "speck_size_px", self.speck_size_px, "an integer >= 1 pixel")
        if not 0 <= self.min_component_fraction <= 1:
            raise out_of_range(source, "min_component_fraction", self.min_component_fraction, "a fraction in [0, 1]")
        if not 0 <= self.min_side_fraction < 0.5:
            raise out_of_range(source, "min_side_fraction", self.min_side_fraction, "a fraction in [0, 0.5)")
        if not (np.isfinite(self.background_match_delta_e) and self.background_match_delta_e > 0):
            raise out_of_range(source, "background_match_delta_e", self.background_match_delta_e, "a finite Delta E > 0")


@dataclass(frozen=True)
class SurfaceProfile:
    """Free-surface profile of the material in full-image pixel coordinates.

    Attributes:
        columns_px: ``[W]`` image column (x) of every column of the crop.
        top_rows_px: ``[W]`` image row of the highest material pixel in that column; NaN where
            the column holds no material.
    """

    columns_px: np.ndarray
    top_rows_px: np.ndarray


@dataclass(frozen=True)
class FittedLine:
    """Least-squares line through one side of the profile, in full-image pixel coordinates.

    The line is ``row = row_slope * x + row_intercept_px`` for ``x_start_px <= x <= x_end_px``;
    ``angle_deg`` is its inclination to the horizontal with the pixel aspect applied (positive
    when the side slopes the way a heap, or a funnel, must).
    """

    x_start_px: float
    x_end_px: float
    row_slope: float
    row_intercept_px: float
    angle_deg: float

    def row_at(self, x_px: float | np.ndarray) -> float | np.ndarray:
        """Image row of the line at column(s) ``x_px``."""
        return self.row_slope * np.asarray(x_px, dtype=float) + self.row_intercept_px

    def endpoints_px(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """((x, row) at the start, (x, row) at the end), e.g. for ``cv2.line``."""
        return (
            (self.x_start_px, float(self.row_at(self.x_start_px))),
            (self.x_end_px, float(self.row_at(self.x_end_px))),
        )


@dataclass(frozen=True)
class SurfaceAngle:
    """Angle of repose or shear angle of one image.

    Attributes:
        kind: ``"repose"`` (lower-box heap) or ``"shear"`` (upper-box funnel).
        angle_deg: the KPI, mean of the left and right angles, degrees.
        left_angle_deg, right_angle_deg: per-side angles, degrees.
        left_line, right_line: the fitted lines.
        split_x_px: image column at which the profile was split (apex or funnel bottom).
        profile: the extracted free-surface profile.
        crop_box: the region of interest that was measured.
        pixel_aspect: pixel height over pixel width used for the angles.
        source: where the image came from.
    """

    kind: SurfaceKind
    angle_deg: float
    left_angle_deg: float
    right_angle_deg: float
    left_line: FittedLine
    right_line: FittedLine
    split_x_px: float
    profile: SurfaceProfile
    crop_box: CropBox
    pixel_aspect: float
    source: str


def large_regions(mask: np.ndarray, min_fraction: float) -> np.ndarray:
    """``bool [H, W]``: the 8-connected regions of ``mask`` whose area is at least ``min_fraction`` of
    the largest region's (debris and grains lying apart are dropped; all False if the mask is empty)."""
    count, labels, stats, _ = cv2.connectedComponentsWithStats(np.asarray(mask, dtype=np.uint8), connectivity=8)
    keep = np.zeros(count, dtype=bool)
    if count > 1:
        areas = stats[1:, cv2.CC_STAT_AREA]
        keep[1:] = areas >= min_fraction * areas.max()
    return keep[labels]


def remove_background(
    image_bgr: np.ndarray, config: SurfaceConfig = SurfaceConfig(), source: str = "image"
) -> tuple[np.ndarray, np.ndarray]:
    """Background removal and binarisation of an (already cropped) BGR image.

    Returns:
        (preprocessed, material): the image with background pixels replaced by the artificial
        background :data:`kpi.colors.BACKGROUND_BGR` (``uint8 [H, W, 3]``), and the cleaned
        binary material mask (``bool [H, W]``).
    """
    image_bgr = np.asarray(image_bgr)
    if image_bgr.dtype != np.uint8 or image_bgr.ndim != 3 or image_bgr.shape[2] != 3:
        raise bad_input(source, f"expected an 8-bit BGR image [H, W, 3]; got dtype {image_bgr.dtype}, shape {image_bgr.shape}")
    distance = delta_e(bgr_to_lab(image_bgr), bgr_colour_to_lab(config.background_bgr))
    if config.background_delta_e is None:
        distance_u8 = np.clip(np.rint(distance), 0, 255).astype(np.uint8)
        otsu, _ = cv2.threshold(distance_u8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
        threshold = max(float(otsu), config.min_background_delta_e)
    else:
        threshold = float(config.background_delta_e)
    material = (distance > threshold).astype(np.uint8)
    if not material.all():
        background_distance = float(np.median(distance[material == 0]))
        if background_distance > config.background_match_delta_e:
            raise bad_input(
                source,
                f"background colour {config.background_bgr} (BGR) not found: the pixels classed as "
                f"background differ from it by a median Delta E of {background_distance:.1f}, expected "
                f"<= {config.background_match_delta_e:g} (SurfaceConfig.background_match_delta_e); set "
                "SurfaceConfig.background_bgr to the colour behind the material",
            )

    if config.speck_size_px > 1:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (config.speck_size_px, config.speck_size_px))
        material = cv2.morphologyEx(material, cv2.MORPH_OPEN, kernel)
        material = cv2.morphologyEx(material, cv2.MORPH_CLOSE, kernel)
    material_mask = large_regions(material, config.min_component_fraction)

    preprocessed = image_bgr.copy()
    preprocessed[~material_mask] = BACKGROUND_BGR
    return preprocessed, material_mask


def surface_profile(material_mask: np.ndarray, crop_box: CropBox) -> SurfaceProfile:
    """Highest material pixel of every column of a cropped mask, in full-image coordinates."""
    has_material = material_mask.any(axis=0)
    top_rows = np.argmax(material_mask, axis=0).astype(float)
    top_rows[~has_material] = np.nan
    columns = np.arange(material_mask.shape[1], dtype=float) + crop_box.x0
    return SurfaceProfile(columns_px=columns, top_rows_px=top_rows + crop_box.y0)


def _split_column(columns: np.ndarray, heights: np.ndarray, kind: SurfaceKind) -> float:
    """Middle column of the longest run at the profile's maximum (heap) or minimum (funnel).

    Columns without material count as height 0 (bottom of the crop); a median filter over
    ~2 % of the width keeps single protruding particles from moving the split.
    """
    filled = np.where(np.isnan(heights), 0.0, heights)
    window = max(3, (len(filled) // 50) | 1)
    smoothed = median_filter(filled, size=window, mode="nearest")
    extreme = smoothed.max() if kind == "repose" else smoothed.min()
    at_extreme = np.concatenate(([0], (smoothed == extreme).astype(np.int8), [0]))
    starts = np.flatnonzero(np.diff(at_extreme) == 1)
    ends = np.flatnonzero(np.diff(at_extreme) == -1)
    longest = int(np.argmax(ends - starts))
    return float(np.mean(columns[starts[longest] : ends[longest]]))


def _fit_side(
    x: np.ndarray, rows: np.ndarray, rising_to_right: bool, pixel_aspect: float, side: str, source: str, kind: SurfaceKind
) -> FittedLine:
    row_slope, row_intercept = np.polyfit(x, rows, deg=1)
    surface_slope = -row_slope * pixel_aspect  # rise over run, both in metres
    angle = float(np.degrees(np.arctan(surface_slope if rising_to_right else -surface_slope)))
    if angle <= 0:
        shape = "rise towards the heap's apex" if kind == "repose" else "fall towards the funnel's bottom"
        raise bad_input(
            source,
            f"the {side} side of the surface does not {shape} (fitted angle {angle:.2f} deg, "
            "expected > 0); check the crop box and background colour",
        )
    return FittedLine(
        x_start_px=float(x.min()),
        x_end_px=float(x.max()),
        row_slope=float(row_slope),
        row_intercept_px=float(row_intercept),
        angle_deg=angle,
    )


def measure_surface_angle(
    image_bgr: np.ndarray,
    kind: SurfaceKind,
    *,
    crop_box: CropBox | None = None,
    config: SurfaceConfig = SurfaceConfig(),
    pixel_aspect: float = 1.0,
    source: str = "image",
) -> SurfaceAngle:
    """Angle of repose (``kind="repose"``) or shear angle (``kind="shear"``) of one image.

    Args:
        image_bgr: 8-bit BGR image ``[H, W, 3]`` (see :func:`kpi.io.read_image`).
        kind: which surface the crop shows: the lower-box heap or the upper-box funnel.
        crop_box: region of interest; the whole image if None.
        config: background removal and binarisation settings.
        pixel_aspect: pixel height / pixel width (1 for square pixels).
        source: name of the image for error messages (its file path).
    """
    if kind not in ("repose", "shear"):
        raise out_of_range(source, "kind", kind, "'repose' (angle of repose) or 'shear' (shear angle)")
    if not (np.isfinite(pixel_aspect) and pixel_aspect > 0):
        raise out_of_range(source, "pixel_aspect", pixel_aspect, "a finite ratio > 0 (pixel height / pixel width)")
    image_bgr = np.asarray(image_bgr)
    if image_bgr.ndim < 2 or image_bgr.shape[0] == 0 or image_bgr.shape[1] == 0:
        raise bad_input(source, f"image has zero size (shape {image_bgr.shape})")
    crop_box = CropBox.whole(image_bgr) if crop_box is None else crop_box
    _, material = remove_background(crop(image_bgr, crop_box, source), config, source)

    profile = surface_profile(material, crop_box)
    columns, rows = profile.columns_px, profile.top_rows_px
    valid = ~np.isnan(rows)
    what = "heap" if kind == "repose" else "remaining material (funnel)"
    if np.count_nonzero(valid) < 2 * MIN_SIDE_COLUMNS:
        raise bad_input(
            source,
            f"no {what} found in crop box (x0={crop_box.x0}, y0={crop_box.y0}, x1={crop_box.x1}, "
            f"y1={crop_box.y1}): {np.count_nonzero(valid)} columns hold material, expected at least "
            f"{2 * MIN_SIDE_COLUMNS}; check the crop box and background colour {config.background_bgr} (BGR)",
        )
    heights = crop_box.y1 - rows  # pixels above the crop's bottom edge
    split = _split_column(columns, heights, kind)

    min_columns = max(MIN_SIDE_COLUMNS, int(np.ceil(config.min_side_fraction * np.count_nonzero(valid))))
    lines = {}
    for side, in_side in (("left", valid & (columns < split)), ("right", valid & (columns > split))):
        if np.count_nonzero(in_side) < min_columns:
            raise bad_input(
                source,
                f"no {side} side of the {what}: {np.count_nonzero(in_side)} profile columns lie "
                f"{side} of the split at x={split:g} px, expected at least {min_columns}; "
                "check that the crop box holds the whole surface and lies inside the box walls",
            )
        rising_to_right = (side == "left") == (kind == "repose")
        lines[side] = _fit_side(columns[in_side], rows[in_side], rising_to_right, pixel_aspect, side, source, kind)

    left, right = lines["left"], lines["right"]
    return SurfaceAngle(
        kind=kind,
        angle_deg=0.5 * (left.angle_deg + right.angle_deg),
        left_angle_deg=left.angle_deg,
        right_angle_deg=right.angle_deg,
        left_line=left,
        right_line=right,
        split_x_px=split,
        profile=profile,
        crop_box=crop_box,
        pixel_aspect=float(pixel_aspect),
        source=source,
    )


def angle_of_repose(
    image_bgr: np.ndarray,
    *,
    crop_box: CropBox | None = None,
    config: SurfaceConfig = SurfaceConfig(),
    pixel_aspect: float = 1.0,
    source: str = "image",
) -> SurfaceAngle:
    """Angle of repose of the lower-box heap: mean of the two half-profile angles, degrees."""
    return measure_surface_angle(
        image_bgr, "repose", crop_box=crop_box, config=config, pixel_aspect=pixel_aspect, source=source
    )


def shear_angle(
    image_bgr: np.ndarray,
    *,
    crop_box: CropBox | None = None,
    config: SurfaceConfig = SurfaceConfig(),
    pixel_aspect: float = 1.0,
    source: str = "image",
) -> SurfaceAngle:
    """Shear angle of the material left in the upper box: mean of the funnel's two slopes, degrees."""
    return measure_surface_angle(
        image_bgr, "shear", crop_box=crop_box, config=config, pixel_aspect=pixel_aspect, source=source
    )
