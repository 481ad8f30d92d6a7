"""Front-view images of a DEM state, painted like the lab's photos of the draw-down test.

Contract:

* **Camera.** Orthographic, looking along +y (the depth axis) through the glass front wall at
  the x-z plane: image columns run along +x (left to right), image rows along -z (the top row
  is the highest z). A :class:`View` is the window ``[x_min, x_max] x [z_min, z_max]`` (m)
  and the pixel size ``metres_per_pixel`` (default: the window width over 800 pixels). The
  image has ``width_px = ceil((x_max - x_min) / metres_per_pixel)`` columns and ``height_px``
  rows likewise, and pixel (row ``r``, column ``c``) shows the point at its centre,
  ``x = x_min + (c + 1/2) m``, ``z = z_max - (r + 1/2) m``.
* **Spheres.** A pixel shows the sphere whose surface is nearest the camera along the pixel's
  line of sight: a z-buffer on the exact depth ``y_c - sqrt(r^2 - d^2)`` of every sphere, which
  is the painter's algorithm (back to front) made exact where spheres of different sizes
  overlap. A pixel belongs to a sphere's disc when its centre lies in the disc; there is no
  antialiasing, so every pixel carries exactly one palette colour (or the background) and the
  :mod:`kpi` colour thresholds never see a mixed pixel. The front layer, seen through the
  glass, is what the camera records; spheres behind it show only through its gaps.
* **Colours** follow :mod:`kpi.colors`, so :func:`kpi.angles.angle_of_repose`,
  :func:`kpi.angles.shear_angle` and :func:`kpi.segregation.measure_segregation` measure a
  render with their default settings: background ``BACKGROUND_BGR``, walls ``WALL_BGR``, and
  each sphere the ``palette`` colour of its component label (default ``0 -> PELLET_BGR``,
  ``1 -> SINTER_BGR``). ``rim_darkening`` > 0 shades each disc towards its rim (a Lambert term
  with ambient light); the default 0 keeps colours flat.
* **Shadows.** A lab photo is lit through the glass, so what it shows through the gaps of the front
  layer lies in shadow. With ``shadow_depth`` (m) set, a pixel whose visible surface lies more
  than ``shadow_depth`` behind the nearest sphere surface of the image (the bed against the glass)
  is painted ``SHADOW_BGR``, near black, which kpi's default thresholds class as sinter; None (the
  default) paints every surface in its own colour.
* **Walls** (:class:`torchdem.walls.Walls` or a sequence of :class:`torchdem.walls.WallSpec`)
  are drawn after the spheres as the front view of a plate ``wall_thickness`` thick, lying on
  the side of the wall plane *opposite* its normal. Box walls' normals point into the box
  (:func:`torchdem.walls.box_walls`), so the bands lie outside the region the walls enclose
  and a crop box of that region (:func:`crop_box_for`) holds no wall pixels, as kpi's angle
  measurement requires. Walls facing the camera (``|normal_y| >= GLASS_NORMAL_Y``: the front
  and back panes) are glass and are not drawn. Infinite extents are clipped to the view. With
  ``time`` given, only walls that exist at that time are drawn, moved by their displacement.
* :func:`crop_box_for` turns a region in metres into the :class:`kpi.io.CropBox` of the pixels
  whose centres lie in it (edges included), so the draw-down code can say where to measure in
  metres (the lower box's interior for the angle of repose, the upper box's for the shear
  angle).
* :func:`render_state` renders one ensemble member of a torchdem ``(System, State)``: active
  spheres only, labels from material ids, the system's walls at the state's time.
  :func:`member_spheres` gives the spheres it draws (centres, radii, labels on the host), so a
  photo can be drawn again later, with other settings, without the state.

Inputs may be torch tensors (any device; they are detached and copied to the host) or numpy
arrays. Bad input raises :class:`torchdem.errors.ConfigError` naming the value, the allowed
range and the function or class it came from.
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from types import MappingProxyType
from typing import Mapping, Sequence

import numpy as np
import torch

from kpi.colors import BACKGROUND_BGR, PELLET_BGR, SHADOW_BGR, SINTER_BGR, WALL_BGR
from kpi.io import CropBox
from torchdem.errors import ConfigError, out_of_range
from torchdem.integrate import sphere_active, sphere_positions
from torchdem.walls import Walls, WallSpec, make_walls

#: Image width of a :class:`View` whose ``metres_per_pixel`` is not given.
DEFAULT_WIDTH_PX = 800
#: Largest image side; a bigger image is almost surely a pixel size given in mm, not m.
MAX_IMAGE_SIDE_PX = 16384
#: Component labels of the default palette.
PELLET_LABEL = 0
SINTER_LABEL = 1
DEFAULT_PALETTE: Mapping[int, tuple[int, int, int]] = MappingProxyType(
    {PELLET_LABEL: PELLET_BGR, SINTER_LABEL: SINTER_BGR}
)
#: Walls whose unit normal has ``|n_y|`` at least this (within ~2.6 deg of the camera axis)
#: face the camera: the glass front and back panes, not drawn.
GLASS_NORMAL_Y = 0.999
#: Wall band thickness in pixels when ``wall_thickness`` is not given (visible at any scale).
DEFAULT_WALL_THICKNESS_PX = 6
#: Tolerance, in pixels, for a region edge or wall face that falls exactly on a pixel centre.
PIXEL_TOLERANCE = 1e-6
#: Sphere-pixel candidates rasterised per vectorised chunk (bounds the temporary memory to
#: a few tens of MB).
_CHUNK_ENTRIES = 1 << 20


def _finite_number(value, name: str, source: str) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(float(value)):
        raise out_of_range(name, value, "a finite number", source)
    return float(value)


@dataclass(frozen=True)
class View:
    """Orthographic front-view window and pixel size.

    Attributes:
        x_min, x_max: horizontal extent of the window, m (x_max > x_min).
        z_min, z_max: vertical extent of the window, m (z_max > z_min).
        metres_per_pixel: pixel size, m (> 0; default ``(x_max - x_min) / 800``).
    """

    x_min: float
    x_max: float
    z_min: float
    z_max: float
    metres_per_pixel: float | None = None

    def __post_init__(self) -> None:
        source = "View"
        for name in ("x_min", "x_max", "z_min", "z_max"):
            object.__setattr__(self, name, _finite_number(getattr(self, name), name, source))
        if not self.x_max > self.x_min:
            raise out_of_range("x_max", self.x_max, f"a value > x_min = {self.x_min!r} m", source)
        if not self.z_max > self.z_min:
            raise out_of_range("z_max", self.z_max, f"a value > z_min = {self.z_min!r} m", source)
        if self.metres_per_pixel is None:
            object.__setattr__(self, "metres_per_pixel", (self.x_max - self.x_min) / DEFAULT_WIDTH_PX)
        mpp = self.metres_per_pixel
        if isinstance(mpp, bool) or not isinstance(mpp, numbers.Real) or not (math.isfinite(mpp) and mpp > 0):
            raise out_of_range("metres_per_pixel", mpp, "a finite pixel size > 0 m", source)
        object.__setattr__(self, "metres_per_pixel", float(mpp))
        largest_span = max(self.x_max - self.x_min, self.z_max - self.z_min)
        if max(self.width_px, self.height_px) > MAX_IMAGE_SIDE_PX:
            raise out_of_range(
                "metres_per_pixel", mpp,
                f"a pixel size >= {largest_span / MAX_IMAGE_SIDE_PX:.4g} m, so that the "
                f"{self.x_max - self.x_min:g} m x {self.z_max - self.z_min:g} m window is at most "
                f"{MAX_IMAGE_SIDE_PX} pixels a side",
                source,
            )

    @property
    def width_px(self) -> int:
        """Number of image columns."""
        return max(1, math.ceil((self.x_max - self.x_min) / self.metres_per_pixel - PIXEL_TOLERANCE))

    @property
    def height_px(self) -> int:
        """Number of image rows."""
        return max(1, math.ceil((self.z_max - self.z_min) / self.metres_per_pixel - PIXEL_TOLERANCE))

    @property
    def shape(self) -> tuple[int, int]:
        """``(height_px, width_px)``."""
        return self.height_px, self.width_px

    def column(self, x):
        """Pixel column coordinate of ``x`` (m); column ``c``'s centre is at ``c``."""
        return (np.asarray(x, dtype=float) - self.x_min) / self.metres_per_pixel - 0.5

    def row(self, z):
        """Pixel row coordinate of ``z`` (m); row ``r``'s centre is at ``r``."""
        return (self.z_max - np.asarray(z, dtype=float)) / self.metres_per_pixel - 0.5

    def x_at(self, column):
        """x (m) of a pixel column coordinate (inverse of :meth:`column`)."""
        return self.x_min + (np.asarray(column, dtype=float) + 0.5) * self.metres_per_pixel

    def z_at(self, row):
        """z (m) of a pixel row coordinate (inverse of :meth:`row`)."""
        return self.z_max - (np.asarray(row, dtype=float) + 0.5) * self.metres_per_pixel


def crop_box_for(view: View, x_min: float, x_max: float, z_min: float, z_max: float,
                 *, source: str = "crop_box_for") -> CropBox:
    """Crop box of the pixels whose centres lie in ``[x_min, x_max] x [z_min, z_max]`` (m).

    The region must lie inside the view; it is, e.g., the interior of the lower box (between
    its side walls, above its floor) for :func:`kpi.angles.angle_of_repose`.
    """
    if not isinstance(view, View):
        raise ConfigError(f"{source}: view is a {type(view).__name__}; expected a torchdem.render.View")
    x_min, x_max = (_finite_number(v, n, source) for v, n in ((x_min, "x_min"), (x_max, "x_max")))
    z_min, z_max = (_finite_number(v, n, source) for v, n in ((z_min, "z_min"), (z_max, "z_max")))
    if not x_max > x_min:
        raise out_of_range("x_max", x_max, f"a value > x_min = {x_min!r} m", source)
    if not z_max > z_min:
        raise out_of_range("z_max", z_max, f"a value > z_min = {z_min!r} m", source)
    mpp, width, height = view.metres_per_pixel, view.width_px, view.height_px
    image_x_max = view.x_min + width * mpp
    image_z_min = view.z_max - height * mpp
    tolerance_m = PIXEL_TOLERANCE * mpp
    bounds = (("x_min", x_min, view.x_min, image_x_max), ("x_max", x_max, view.x_min, image_x_max),
              ("z_min", z_min, image_z_min, view.z_max), ("z_max", z_max, image_z_min, view.z_max))
    for name, value, low, high in bounds:
        if not low - tolerance_m <= value <= high + tolerance_m:
            raise out_of_range(name, value, f"a value inside the view, [{low:g}, {high:g}] m", source)
    x0 = max(0, math.ceil(float(view.column(x_min)) - PIXEL_TOLERANCE))
    x1 = min(width, math.floor(float(view.column(x_max)) + PIXEL_TOLERANCE) + 1)
    y0 = max(0, math.ceil(float(view.row(z_max)) - PIXEL_TOLERANCE))
    y1 = min(height, math.floor(float(view.row(z_min)) + PIXEL_TOLERANCE) + 1)
    if x1 <= x0 or y1 <= y0:
        raise ConfigError(
            f"{source}: region x in [{x_min:g}, {x_max:g}] m, z in [{z_min:g}, {z_max:g}] m holds no pixel "
            f"centre at {mpp:g} m per pixel; expected a region at least one pixel wide and high"
        )
    return CropBox(x0, y0, x1, y1)


def _host_array(value, name: str, source: str) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu()
        return (value.double() if value.is_floating_point() else value).numpy()
    try:
        return np.asarray(value)
    except (TypeError, ValueError) as error:
        raise ConfigError(f"{source}: {name} cannot be read as an array ({error})") from None


def _check_palette(palette: Mapping[int, Sequence[int]] | None, source: str) -> dict[int, tuple[int, int, int]]:
    if palette is None:
        return dict(DEFAULT_PALETTE)
    if not isinstance(palette, Mapping) or len(palette) == 0:
        raise out_of_range("palette", palette, "a non-empty mapping from component label to BGR colour", source)
    checked = {}
    for label, colour in palette.items():
        if isinstance(label, bool) or not isinstance(label, numbers.Integral):
            raise out_of_range("palette label", label, "an integer component label", source)
        try:
            values = tuple(float(c) for c in colour)
        except (TypeError, ValueError):
            values = ()
        if len(values) != 3 or not all(v.is_integer() and 0 <= v <= 255 for v in values):
            raise out_of_range(f"palette[{label}]", colour, "three integers in 0..255 (B, G, R)", source)
        checked[int(label)] = tuple(int(v) for v in values)
    return checked


def _check_spheres(centres, radii, labels, palette: dict, source: str):
    centres = _host_array(centres, "centres", source)
    radii = _host_array(radii, "radii", source)
    labels = _host_array(labels, "labels", source)
    if centres.ndim != 2 or centres.shape[1] != 3:
        raise ConfigError(f"{source}: centres has shape {tuple(centres.shape)}; expected [N, 3] (metres)")
    n = centres.shape[0]
    if n == 0:
        raise ConfigError(f"{source}: centres is empty (N = 0); expected at least one sphere")
    if radii.shape != (n,):
        raise ConfigError(f"{source}: radii has shape {tuple(radii.shape)}; expected [{n}] (one per centre)")
    if labels.shape != (n,):
        raise ConfigError(f"{source}: labels has shape {tuple(labels.shape)}; expected [{n}] (one per centre)")
    if not (np.issubdtype(centres.dtype, np.number) and np.issubdtype(radii.dtype, np.number)):
        raise ConfigError(f"{source}: centres and radii have dtypes {centres.dtype}, {radii.dtype}; expected numbers")
    centres = centres.astype(np.float64)
    radii = radii.astype(np.float64)
    bad = np.flatnonzero(~np.isfinite(centres).all(axis=1))
    if bad.size:
        raise out_of_range("centres", centres[bad[0]].tolist(), f"finite coordinates (sphere {bad[0]})", source)
    bad = np.flatnonzero(~(np.isfinite(radii) & (radii > 0)))
    if bad.size:
        raise out_of_range("radii", float(radii[bad[0]]), f"finite radii > 0 m (sphere {bad[0]})", source)
    if not np.issubdtype(labels.dtype, np.integer):
        raise ConfigError(f"{source}: labels have dtype {labels.dtype}; expected integer component labels "
                          f"(palette keys {sorted(palette)})")
    unknown = np.setdiff1d(np.unique(labels), np.array(sorted(palette)))
    if unknown.size:
        sphere = int(np.flatnonzero(labels == unknown[0])[0])
        raise out_of_range("labels", int(unknown[0]), f"a palette key in {sorted(palette)} (sphere {sphere})", source)
    return centres, radii, labels.astype(np.int64)


def _rasterise_spheres(view: View, centres: np.ndarray, radii: np.ndarray):
    """Z-buffer the sphere discs: ``(owner [H*W] int64, -1 = none; rim [H*W] d/r in [0, 1];
    depth [H*W] y of the visible surface, m, inf where none)``.

    Spheres are grouped by their radius in whole pixels; each group is rasterised in chunks
    of candidate pixels (a square patch around every centre) with array operations. A disc
    larger than the image is rasterised over the image alone.
    """
    height, width = view.shape
    mpp = view.metres_per_pixel
    col, row = view.column(centres[:, 0]), view.row(centres[:, 2])
    radius_px = radii / mpp
    visible = ((col + radius_px >= -0.5) & (col - radius_px <= width - 0.5)
               & (row + radius_px >= -0.5) & (row - radius_px <= height - 0.5))
    depth_buffer = np.full(height * width, np.inf)
    owner = np.full(height * width, -1, dtype=np.int64)
    rim = np.zeros(height * width)

    def draw(sphere: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> None:
        """Z-test candidate pixels (``rows``, ``cols``) of ``sphere`` (all ``[M]``)."""
        dist2_m = ((cols - col[sphere]) ** 2 + (rows - row[sphere]) ** 2) * mpp * mpp
        inside = ((dist2_m <= radii[sphere] ** 2)
                  & (cols >= 0) & (cols < width) & (rows >= 0) & (rows < height))
        sphere, dist2_m = sphere[inside], dist2_m[inside]
        pixel = rows[inside] * width + cols[inside]
        depth = centres[sphere, 1] - np.sqrt(np.maximum(radii[sphere] ** 2 - dist2_m, 0.0))
        np.minimum.at(depth_buffer, pixel, depth)
        nearest = depth <= depth_buffer[pixel]
        owner[pixel[nearest]] = sphere[nearest]
        rim[pixel[nearest]] = np.sqrt(dist2_m[nearest]) / radii[sphere[nearest]]

    spheres = np.flatnonzero(visible)
    half = np.ceil(radius_px[spheres]).astype(np.int64)
    for h in np.unique(half):
        group = spheres[half == h]
        if 2 * h + 2 > max(height, width):  # bigger than the image: the image is the patch
            image_rows, image_cols = np.divmod(np.arange(height * width), width)
            for k in group:
                draw(np.full(image_rows.size, k), image_rows, image_cols)
            continue
        offsets = np.arange(-h, h + 2)  # columns floor(c) - h .. floor(c) + h + 1 hold the disc
        d_col = np.repeat(offsets, offsets.size)
        d_row = np.tile(offsets, offsets.size)
        per_chunk = max(1, _CHUNK_ENTRIES // d_col.size)
        for start in range(0, group.size, per_chunk):
            k = group[start:start + per_chunk]
            cols = np.floor(col[k]).astype(np.int64)[:, None] + d_col[None, :]
            rows = np.floor(row[k]).astype(np.int64)[:, None] + d_row[None, :]
            draw(np.broadcast_to(k[:, None], cols.shape).ravel(), rows.ravel(), cols.ravel())
    return owner, rim, depth_buffer


def _wall_arrays(walls, time: float | None, source: str):
    """``(centre, normal, axis_u, axis_v, half_u, half_v)`` numpy arrays of the walls to draw."""
    if isinstance(walls, Walls):
        packed = walls
    else:
        specs = list(walls)
        if not all(isinstance(s, WallSpec) for s in specs):
            raise ConfigError(f"{source}: walls must be a torchdem.walls.Walls or a sequence of WallSpec; "
                              f"got {[type(s).__name__ for s in specs]}")
        material_ids = {name: k for k, name in enumerate(sorted({s.material for s in specs}))}
        packed = make_walls(specs, material_ids, source=f"{source}.walls")
    if packed.n == 0:
        return None
    host = lambda t: t.detach().cpu().double().numpy()  # noqa: E731
    centre = host(packed.centre)
    present = np.ones(packed.n, dtype=bool)
    if time is not None:
        time = _finite_number(time, "time", source)
        present = packed.active_at(time).detach().cpu().numpy()
        centre = centre + host(packed.shift(time))
    return (centre[present], host(packed.normal)[present], host(packed.axis_u)[present],
            host(packed.axis_v)[present], host(packed.half_u)[present], host(packed.half_v)[present])


def _convex_hull(points: np.ndarray) -> np.ndarray:
    """Counter-clockwise convex hull ``[K, 2]`` of a few 2-D points (Andrew's monotone chain)."""
    pts = sorted(set(map(tuple, np.round(points, 9).tolist())))
    if len(pts) < 3:
        return np.array(pts, dtype=float)

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower, upper = [], []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return np.array(lower[:-1] + upper[:-1], dtype=float)


def _draw_walls(image: np.ndarray, view: View, walls, time: float | None, thickness: float, source: str) -> None:
    arrays = _wall_arrays(walls, time, source)
    if arrays is None:
        return
    height, width = view.shape
    view_centre = np.array([(view.x_min + view.x_max) / 2, (view.z_min + view.z_max) / 2])
    diagonal = math.hypot(view.x_max - view.x_min, view.z_max - view.z_min)
    for centre, normal, axis_u, axis_v, half_u, half_v in zip(*arrays):
        if abs(normal[1]) >= GLASS_NORMAL_Y:
            continue  # glass pane facing the camera
        # Clip infinite (or huge) extents: every part of the wall that projects into the view
        # lies within this distance of the wall centre.
        reach = float(np.linalg.norm(centre[[0, 2]] - view_centre)) + diagonal + thickness
        a, b = min(half_u, reach), min(half_v, reach)
        corners = np.array([centre + su * a * axis_u + sv * b * axis_v for su in (-1, 1) for sv in (-1, 1)])
        corners = np.concatenate([corners, corners - thickness * normal])
        hull = _convex_hull(np.stack([view.column(corners[:, 0]), view.row(corners[:, 2])], axis=1))
        if len(hull) < 3:
            continue
        c0 = max(0, math.floor(hull[:, 0].min()))
        c1 = min(width, math.ceil(hull[:, 0].max()) + 1)
        r0 = max(0, math.floor(hull[:, 1].min()))
        r1 = min(height, math.ceil(hull[:, 1].max()) + 1)
        if c1 <= c0 or r1 <= r0:
            continue
        cols, rows = np.meshgrid(np.arange(c0, c1, dtype=float), np.arange(r0, r1, dtype=float))
        inside = np.ones(cols.shape, dtype=bool)
        for p, q in zip(hull, np.roll(hull, -1, axis=0)):
            edge = q - p
            # Strictly inside: a pixel centre on the wall's face belongs to the region the wall
            # bounds, not to the wall.
            inside &= edge[0] * (rows - p[1]) - edge[1] * (cols - p[0]) > PIXEL_TOLERANCE * np.hypot(*edge)
        image[r0:r1, c0:c1][inside] = WALL_BGR


def render_front(
    centres,
    radii,
    labels,
    view: View,
    walls: Walls | Sequence[WallSpec] | None = None,
    palette: Mapping[int, Sequence[int]] | None = None,
    *,
    time: float | None = None,
    wall_thickness: float | None = None,
    rim_darkening: float = 0.0,
    shadow_depth: float | None = None,
    source: str = "render_front",
) -> np.ndarray:
    """Front view (camera along +y) of spheres and walls as an 8-bit BGR image ``[H, W, 3]``.

    Args:
        centres: ``[N, 3]`` sphere centres, m (torch tensor on any device, or numpy).
        radii: ``[N]`` sphere radii, m (> 0).
        labels: ``[N]`` integer component label of each sphere (a ``palette`` key).
        view: window and pixel size.
        walls: walls to draw (see the module docstring); None draws none.
        palette: component label -> BGR colour; default ``{0: PELLET_BGR, 1: SINTER_BGR}``.
        time: if given (s), draw only walls that exist then, at their position then; if None,
            every wall at its t = 0 position.
        wall_thickness: thickness of the wall bands, m (default 6 pixels).
        rim_darkening: fraction in [0, 1) by which a disc darkens at its rim (0: flat colours).
        shadow_depth: surfaces more than this behind the nearest one are painted ``SHADOW_BGR``, m
            (> 0); None: none (see the module docstring).
        source: name used in error messages.
    """
    if not isinstance(view, View):
        raise ConfigError(f"{source}: view is a {type(view).__name__}; expected a torchdem.render.View")
    palette = _check_palette(palette, source)
    centres, radii, labels = _check_spheres(centres, radii, labels, palette, source)
    rim_darkening = _finite_number(rim_darkening, "rim_darkening", source)
    if not 0 <= rim_darkening < 1:
        raise out_of_range("rim_darkening", rim_darkening, "a fraction in [0, 1) (0: flat colours)", source)
    if shadow_depth is not None:
        shadow_depth = _finite_number(shadow_depth, "shadow_depth", source)
        if not shadow_depth > 0:
            raise out_of_range("shadow_depth", shadow_depth, "a depth > 0 m behind the front layer, or None", source)
    if wall_thickness is None:
        wall_thickness = DEFAULT_WALL_THICKNESS_PX * view.metres_per_pixel
    wall_thickness = _finite_number(wall_thickness, "wall_thickness", source)
    if not wall_thickness > 0:
        raise out_of_range("wall_thickness", wall_thickness, "a finite thickness > 0 m", source)

    height, width = view.shape
    owner, rim, depth = _rasterise_spheres(view, centres, radii)
    image = np.empty((height * width, 3), dtype=np.uint8)
    image[:] = BACKGROUND_BGR
    covered = owner >= 0
    keys = np.array(sorted(palette))
    table = np.array([palette[int(k)] for k in keys], dtype=np.float64)  # [K, 3] BGR
    colours = table[np.searchsorted(keys, labels)][owner[covered]]
    if rim_darkening > 0:
        lambert = np.sqrt(np.clip(1.0 - rim[covered] ** 2, 0.0, 1.0))  # cos of the surface tilt
        colours *= (1.0 - rim_darkening * (1.0 - lambert))[:, None]
    image[covered] = np.clip(np.rint(colours), 0, 255).astype(np.uint8)
    if shadow_depth is not None and covered.any():
        image[covered & (depth > depth[covered].min() + shadow_depth)] = SHADOW_BGR
    image = image.reshape(height, width, 3)
    if walls is not None:
        _draw_walls(image, view, walls, time, wall_thickness, source)
    return image


def member_spheres(system, state, member: int, labels_by_material: Mapping[int, int], shown=None,
                   source: str = "member_spheres") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(centres [N, 3] m, radii [N] m, labels [N])`` on the host: the active spheres of ensemble member
    ``member`` (of its ``shown`` bodies, when a ``[n_bodies]`` bool mask is given), labelled by
    ``labels_by_material``: what :func:`render_state` draws, kept so a photo can be drawn again."""
    batch = system.batch
    if isinstance(member, bool) or not isinstance(member, numbers.Integral) or not 0 <= member < batch:
        raise out_of_range("member", member, f"an ensemble member index in [0, {batch - 1}]", source)
    member = int(member)
    with torch.no_grad():
        positions = sphere_positions(system, state.bodies).reshape(batch, system.n_spheres, 3)[member]
        active = sphere_active(system, state.bodies).reshape(batch, system.n_spheres)[member]
        if shown is not None:
            shown = torch.as_tensor(shown, device=active.device)
            if shown.dtype != torch.bool or tuple(shown.shape) != (system.n_bodies,):
                raise ConfigError(f"{source}: shown must be a bool mask of shape ({system.n_bodies},), got "
                                  f"{shown.dtype} {tuple(shown.shape)}")
            active = active & shown[system.sphere_body[member]]
        centres = positions[active].detach().cpu()
        radii = system.sphere_radius[member][active].detach().cpu()
        materials = system.sphere_material[member][active].detach().cpu().numpy()
    if materials.size == 0:
        raise ConfigError(f"{source}: ensemble member {member} has no active spheres to render")
    labels = np.empty(materials.shape, dtype=np.int64)
    for material in np.unique(materials):
        if int(material) not in labels_by_material:
            name = system.material_names[int(material)]
            raise ConfigError(
                f"{source}: labels_by_material has no label for material {int(material)} ({name!r}) of "
                f"member {member}; expected a component label for every particle material present, "
                f"got keys {sorted(labels_by_material)}"
            )
        labels[materials == material] = labels_by_material[int(material)]
    return centres.numpy(), radii.numpy(), labels


def render_state(
    system,
    state,
    member: int,
    labels_by_material: Mapping[int, int],
    view: View,
    walls: bool = True,
    *,
    palette: Mapping[int, Sequence[int]] | None = None,
    wall_thickness: float | None = None,
    rim_darkening: float = 0.0,
    shadow_depth: float | None = None,
    shown=None,
    source: str = "render_state",
) -> np.ndarray:
    """Front view of ensemble member ``member`` of a torchdem ``(System, State)``.

    Args:
        system, state: a :class:`torchdem.system.System` and its :class:`torchdem.state.State`.
        member: ensemble member index in ``[0, B)``.
        labels_by_material: material id -> component label (palette key), for every material
            of an active sphere, e.g. ``{0: PELLET_LABEL, 1: SINTER_LABEL}``.
        view: window and pixel size.
        walls: draw the system's walls that exist at the state's time (``system.time_of(step)``).
        palette, wall_thickness, rim_darkening, shadow_depth: as in :func:`render_front`.
        shown: optional ``[n_bodies]`` bool mask of the member's bodies to draw (e.g. the bodies at
            rest); None draws every active body.
    """
    centres, radii, labels = member_spheres(system, state, member, labels_by_material, shown, source)
    return render_front(
        centres, radii, labels, view,
        walls=system.walls if walls else None,
        palette=palette,
        time=system.time_of(state.step),
        wall_thickness=wall_thickness,
        rim_darkening=rim_darkening,
        shadow_depth=shadow_depth,
        source=source,
    )
