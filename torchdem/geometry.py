"""Geometry of the draw down test: an upper box with a bottom slot closed by a gate, above a
lower box that receives the material.

Contract: :class:`DrawDownGeometry` holds the dimensions (metres; x across the boxes with the
outlet centred at x = 0, y the depth, z up with the lower box floor at z = 0) and produces
the walls (:meth:`walls`), the simulation domain and the regions used by the KPIs. With
``slice_depth`` set, it describes a thin slice of the same boxes, periodic along y (no front
and back walls: the slice stands for the interior of the full box); quantities that scale
with depth are multiplied by ``depth / slice_depth`` to report them for the full box. With
``mirror`` set, the slice is bounded by the box's front wall at y = 0 and, at y = slice_depth, by
a symmetry plane: a frictionless, elastic wall (material :data:`MIRROR_MATERIAL`, see
:class:`torchdem.drawdown.RunSettings`). The lab box has the same wall on both faces, so half its
depth with a mirror at mid-depth keeps the wall friction the full box has at half the cost.

Default dimensions. The paper's figure with the dimensions is not in our text, so the
defaults are derived from its numbers (40 kg fill; steady flow 10.3 kg/s; 81 % discharged,
i.e. 32.3 kg in the lower box; shear angle 42.5 deg; angle of repose 29.5 deg), assuming a
bulk density of the 50-50 mixture of about 2050 kg/m^3 (pellets ~0.60 x 3602, sinter ~0.55 x
3449) and a box depth of 0.20 m:

* flow rate, Beverloo's law for a slot of width b and length L (the depth):
  W = C rho_b sqrt(g) L (b - k d)^1.5 with C = 1.0, k = 2, d = 12 mm:
  b = 0.065 m gives 10.6 kg/s.
* discharged mass: after discharge the material left on each side of the slot is a
  triangle rising at the shear angle from the slot edge to the side wall. With the side
  distance a = (W_u - b) / 2, the residue is a^2 tan(42.5 deg) L rho_b; W_u = 0.35 m gives
  a = 0.1425 m and 7.6 kg left (19 %), 32.4 kg discharged.
* fill height: 40 kg / (rho_b W_u L) = 0.28 m; the upper box walls are 0.5 m high so a
  loose rained fill fits before it settles.
* lower box: a ridge heap of 32.3 kg at 29.5 deg is 0.75 m wide and 0.21 m high; the lower box
  is 0.80 m wide and 0.30 m high, and the outlet is at 0.35 m, above the heap's apex.

All of these are overridable (``conf/geometry/*.yaml``).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from torchdem.errors import out_of_range
from torchdem.walls import WallSpec

#: Material name of the symmetry plane of a mirrored slice (``DrawDownGeometry.mirror``).
MIRROR_MATERIAL = "mirror"
#: How far under the upper box's floor a sliding gate runs, m (``DrawDownGeometry.gate_opening``):
#: a plate drawn out under the floor's right half, not through it (two coplanar rectangles would
#: both push a sphere lying on them).
GATE_CLEARANCE = 0.002


@dataclass(frozen=True, repr=False)
class DrawDownGeometry:
    """Dimensions of the draw down test, metres (see the module docstring).

    Attributes:
        upper_width: inner width of the upper box (x). depth: inner depth of both boxes (y).
        upper_height: height of the upper box walls above its bottom.
        outlet_width: width of the bottom slot (x), centred; it spans the whole depth.
        upper_bottom_z: height of the upper box bottom (and gate) above the lower box floor.
        lower_width: inner width of the lower box. lower_height: height of its walls.
        slice_depth: None for the full box, else the depth of a y-periodic slice.
        slice_walls: a slice bounded by front and back walls instead of periodic along y
            (the walls of the lab box, brought to ``slice_depth`` apart); ignored for the full box.
        mirror: the slice's back face (y = slice_depth) is a symmetry plane, a frictionless
            elastic wall, and its front face the box's front wall; needs ``slice_depth``
            (``depth / 2`` for the lab box's mid-depth plane).
        gate_opening: how long the gate takes to uncover the slot, s. 0: it vanishes the moment the
            fill has settled. Else it is a plate :data:`GATE_CLEARANCE` under the floor that slides
            at constant speed (``outlet_width / gate_opening``) towards +x, under the floor's right
            half, dragging the grains on it by the wall friction; the slot opens from its left edge.
    """

    upper_width: float = 0.35
    depth: float = 0.20
    upper_height: float = 0.50
    outlet_width: float = 0.065
    upper_bottom_z: float = 0.35
    lower_width: float = 0.80
    lower_height: float = 0.30
    slice_depth: float | None = None
    slice_walls: bool = False
    mirror: bool = False
    gate_opening: float = 0.0

    def __repr__(self) -> str:
        """The fields, ``gate_opening`` only when the gate slides: campaign checkpoints are named by
        the model's repr, and those of a gate that vanishes were named before the gate could slide."""
        shown = [f for f in dataclasses.fields(self) if not (f.name == "gate_opening" and self.gate_opening == 0)]
        return f"{type(self).__name__}({', '.join(f'{f.name}={getattr(self, f.name)!r}' for f in shown)})"

    def validate(self, source: str = "geometry") -> "DrawDownGeometry":
        for name in ("upper_width", "depth", "upper_height", "outlet_width", "upper_bottom_z",
                     "lower_width", "lower_height"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise out_of_range(name, value, "a length > 0 m", source)
        if not self.outlet_width < self.upper_width:
            raise out_of_range("outlet_width", self.outlet_width, f"< upper_width = {self.upper_width} m", source)
        if not self.lower_width >= self.upper_width:
            raise out_of_range("lower_width", self.lower_width, f">= upper_width = {self.upper_width} m", source)
        if not self.upper_bottom_z > 0:
            raise out_of_range("upper_bottom_z", self.upper_bottom_z, "> 0 m", source)
        if self.slice_depth is not None and not (0 < self.slice_depth <= self.depth):
            raise out_of_range("slice_depth", self.slice_depth, f"(0, depth = {self.depth}] m or null", source)
        if not (isinstance(self.gate_opening, (int, float)) and math.isfinite(self.gate_opening)
                and self.gate_opening >= 0):
            raise out_of_range("gate_opening", self.gate_opening, "a time >= 0 s (0: the gate vanishes at once)",
                               source)
        if self.mirror and self.slice_depth is None:
            raise out_of_range("mirror", self.mirror, "false for the full box (a mirror plane bounds a slice: set "
                               "slice_depth, e.g. depth / 2)", source)
        return self

    @property
    def is_slice(self) -> bool:
        return self.slice_depth is not None

    @property
    def simulated_depth(self) -> float:
        """Depth of the simulated domain along y, m."""
        return self.slice_depth if self.slice_depth is not None else self.depth

    @property
    def depth_scale(self) -> float:
        """Simulated share of the full box: slice_depth / depth (1 for the full box)."""
        return self.simulated_depth / self.depth

    @property
    def has_front_back_walls(self) -> bool:
        """Whether front and back walls bound the simulated depth (full box or walled slice)."""
        return not self.is_slice or self.slice_walls or self.mirror

    @property
    def periodic(self) -> tuple[bool, bool, bool]:
        return (False, not self.has_front_back_walls, False)

    def domain(self, margin: float = 0.05, fill_top: float | None = None
               ) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """Simulation box (lower, upper corners); y spans exactly the slice when periodic; it
        reaches above a loose fill stacked up to ``fill_top`` (m) when that is higher than the walls."""
        D = self.simulated_depth
        y0, y1 = (-margin, D + margin) if self.has_front_back_walls else (0.0, D)
        top = max(self.upper_bottom_z + self.upper_height, fill_top or 0.0) + margin
        return ((-self.lower_width / 2 - margin, y0, -margin), (self.lower_width / 2 + margin, y1, top))

    def walls(self, material: str, gate_open_time: float, fill_top: float | None = None,
              front_back_material: str | None = None, mirror_material: str = "mirror") -> list[WallSpec]:
        """Walls of both boxes; the gate opens at ``gate_open_time`` (s): it vanishes then, or with
        ``gate_opening`` it slides away under the floor's right half within ``gate_opening`` s. The front and back
        walls (full box or walled slice) are of ``front_back_material`` (default ``material``);
        with ``mirror`` the back walls are replaced by the symmetry plane, one rectangle of
        ``mirror_material`` over the whole width and height of the domain (nothing crosses a plane
        of symmetry, also not in the gap between the boxes).

        A loose rained fill stacked up to ``fill_top`` above the upper box walls is held by
        fill extension walls (a filling hopper continuing the box walls upwards) that exist
        only until the gate opens; by then the fill has settled into the box.
        """
        D = self.simulated_depth
        yc = D / 2
        # Periodic slices: walls reach one full period beyond the slice so spheres near the cut
        # faces (whose centres are wrapped into [0, D)) always see them.
        walled = self.has_front_back_walls
        fb = front_back_material or material
        hy = D / 2 if walled else 1.5 * D
        Wu, Wl, b = self.upper_width, self.lower_width, self.outlet_width
        zb, Hu, Hl = self.upper_bottom_z, self.upper_height, self.lower_height
        side = (Wu - b) / 2
        walls = [
            WallSpec("upper_left", (-Wu / 2, yc, zb + Hu / 2), (1, 0, 0), (0, 0, 1), Hu / 2, hy, material),
            WallSpec("upper_right", (Wu / 2, yc, zb + Hu / 2), (-1, 0, 0), (0, 0, 1), Hu / 2, hy, material),
            WallSpec("upper_bottom_left", (-(b / 2 + side / 2), yc, zb), (0, 0, 1), (1, 0, 0), side / 2, hy, material),
            WallSpec("upper_bottom_right", (b / 2 + side / 2, yc, zb), (0, 0, 1), (1, 0, 0), side / 2, hy, material),
            self._gate(material, gate_open_time, yc, hy),
            WallSpec("lower_bottom", (0.0, yc, 0.0), (0, 0, 1), (1, 0, 0), Wl / 2, hy, material),
            WallSpec("lower_left", (-Wl / 2, yc, Hl / 2), (1, 0, 0), (0, 0, 1), Hl / 2, hy, material),
            WallSpec("lower_right", (Wl / 2, yc, Hl / 2), (-1, 0, 0), (0, 0, 1), Hl / 2, hy, material),
        ]
        top = zb + Hu
        if fill_top is not None and fill_top > top:
            He = fill_top - top + 0.01
            zc = top + He / 2
            walls += [
                WallSpec("fill_left", (-Wu / 2, yc, zc), (1, 0, 0), (0, 0, 1), He / 2, hy, material,
                         active_until=gate_open_time),
                WallSpec("fill_right", (Wu / 2, yc, zc), (-1, 0, 0), (0, 0, 1), He / 2, hy, material,
                         active_until=gate_open_time),
            ]
            if walled:
                walls += [
                    WallSpec("fill_front", (0.0, 0.0, zc), (0, 1, 0), (0, 0, 1), He / 2, Wu / 2, fb,
                             active_until=gate_open_time),
                ]
                if not self.mirror:
                    walls.append(WallSpec("fill_back", (0.0, D, zc), (0, -1, 0), (0, 0, 1), He / 2, Wu / 2, fb,
                                          active_until=gate_open_time))
        if walled:
            walls += [
                WallSpec("upper_front", (0.0, 0.0, zb + Hu / 2), (0, 1, 0), (0, 0, 1), Hu / 2, Wu / 2, fb),
                WallSpec("lower_front", (0.0, 0.0, Hl / 2), (0, 1, 0), (0, 0, 1), Hl / 2, Wl / 2, fb),
            ]
            if self.mirror:  # a symmetry plane is everywhere, gaps between the boxes included
                zt = max(top, fill_top or 0.0) + 0.01
                walls.append(WallSpec("mirror", (0.0, D, zt / 2), (0, -1, 0), (0, 0, 1), zt / 2, Wl / 2,
                                      mirror_material))
            else:
                walls += [WallSpec("upper_back", (0.0, D, zb + Hu / 2), (0, -1, 0), (0, 0, 1), Hu / 2, Wu / 2, fb),
                          WallSpec("lower_back", (0.0, D, Hl / 2), (0, -1, 0), (0, 0, 1), Hl / 2, Wl / 2, fb)]
        return walls

    def _gate(self, material: str, gate_open_time: float, yc: float, hy: float) -> WallSpec:
        """The gate under the slot: gone at ``gate_open_time``, or a plate sliding towards +x from
        then on at ``outlet_width / gate_opening`` until the slot is open (see :attr:`gate_opening`)."""
        b, zb = self.outlet_width, self.upper_bottom_z
        if self.gate_opening == 0:
            return WallSpec("gate", (0.0, yc, zb), (0, 0, 1), (1, 0, 0), b / 2, hy, material,
                            active_until=gate_open_time)
        open_at = gate_open_time + self.gate_opening
        return WallSpec("gate", (0.0, yc, zb - GATE_CLEARANCE), (0, 0, 1), (1, 0, 0), b / 2, hy, material,
                        active_until=open_at, velocity=(b / self.gate_opening, 0.0, 0.0),
                        move_from=gate_open_time, move_until=open_at)

    def in_upper_box(self, x, z):
        """Bool mask of centres inside the upper box (above its bottom, between its walls)."""
        return (z >= self.upper_bottom_z) & (x.abs() <= self.upper_width / 2)

    def in_lower_box(self, x, z):
        """Bool mask of centres inside the lower box."""
        return (z < self.upper_bottom_z) & (z >= -0.01) & (x.abs() <= self.lower_width / 2) & (z <= self.lower_height + 0.05)
