"""Walls: finite rectangles (infinite planes are rectangles with infinite extent).

Contract:
- A wall is a rectangle with centre c, unit normal n, in-plane unit axes u and v = n x u,
  half-extents (a, b) along u and v, and a material id. It is two-sided: a sphere touches it
  at the closest point of the rectangle, so spheres also feel its edges and corners.
- A wall exists from ``active_from`` until ``active_until`` (seconds; a gate that is released
  at t = 0 has ``active_until = 0``) and translates with ``velocity`` between ``move_from``
  and ``move_until`` (a gate that slides away).
- Geometry is shared by all ensemble members; per-member differences in wall behaviour go
  through the material pair table (each wall has its own material).
- :class:`Walls` holds W walls as tensors ``[W, ...]``; :func:`make_walls` validates a list of
  :class:`WallSpec` (unit normal, perpendicular axes, positive extents, no two walls lying
  on top of each other) and raises ConfigError naming the wall.
"""
from __future__ import annotations

import bisect
import functools
import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import torch

from torchdem.errors import ConfigError, out_of_range

Tensor = torch.Tensor
INF = math.inf


@dataclass(frozen=True)
class WallSpec:
    """One rectangle, in plain numbers (metres, seconds).

    Attributes:
        name: unique name (``"upper_left"``, ``"gate"``).
        centre, normal, axis_u: 3-vectors; axis_u must be perpendicular to normal.
        half_u, half_v: half-extents along u and v = normal x u (``inf`` for a plane).
        material: material name (resolved to an id by the system builder).
        active_from, active_until: existence window, s.
        velocity: translation velocity, m/s, applied between move_from and move_until.
    """

    name: str
    centre: tuple[float, float, float]
    normal: tuple[float, float, float]
    axis_u: tuple[float, float, float]
    half_u: float
    half_v: float
    material: str
    active_from: float = -INF
    active_until: float = INF
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    move_from: float = 0.0
    move_until: float = 0.0


def plane(name: str, point, normal, material: str, **kw) -> WallSpec:
    """An infinite plane through ``point`` with ``normal``."""
    n = torch.tensor(normal, dtype=torch.float64)
    n = n / n.norm()
    helper = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    if abs(float(n @ helper)) > 0.9:
        helper = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    u = helper - (helper @ n) * n
    u = u / u.norm()
    return WallSpec(name, tuple(point), tuple(n.tolist()), tuple(u.tolist()), INF, INF, material, **kw)


def box_walls(prefix: str, lo, hi, material: str, open_top: bool = True, **kw) -> list[WallSpec]:
    """Axis-aligned box [lo, hi] made of five (or six) rectangles, z up."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    cx, cy, cz = (x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2
    hx, hy, hz = (x1 - x0) / 2, (y1 - y0) / 2, (z1 - z0) / 2
    walls = [
        WallSpec(f"{prefix}_bottom", (cx, cy, z0), (0, 0, 1), (1, 0, 0), hx, hy, material, **kw),
        WallSpec(f"{prefix}_left", (x0, cy, cz), (1, 0, 0), (0, 1, 0), hy, hz, material, **kw),
        WallSpec(f"{prefix}_right", (x1, cy, cz), (-1, 0, 0), (0, 0, 1), hz, hy, material, **kw),
        WallSpec(f"{prefix}_front", (cx, y0, cz), (0, 1, 0), (0, 0, 1), hz, hx, material, **kw),
        WallSpec(f"{prefix}_back", (cx, y1, cz), (0, -1, 0), (1, 0, 0), hx, hz, material, **kw),
    ]
    if not open_top:
        walls.append(WallSpec(f"{prefix}_top", (cx, cy, z1), (0, 0, -1), (1, 0, 0), hx, hy, material, **kw))
    return walls


@dataclass(frozen=True)
class Walls:
    """W rectangles shared by every ensemble member.

    Attributes:
        centre: ``[W, 3]`` at t = 0, m. normal, axis_u, axis_v: ``[W, 3]`` unit vectors.
        half_u, half_v: ``[W]`` half-extents, m (may be inf).
        material: ``[W]`` int64 material ids.
        active_from, active_until: ``[W]`` s. velocity: ``[W, 3]`` m/s.
        move_from, move_until: ``[W]`` s.
        names: wall names, in order.
    """

    centre: Tensor
    normal: Tensor
    axis_u: Tensor
    axis_v: Tensor
    half_u: Tensor
    half_v: Tensor
    material: Tensor
    active_from: Tensor
    active_until: Tensor
    velocity: Tensor
    move_from: Tensor
    move_until: Tensor
    names: tuple[str, ...] = field(default=())

    @property
    def n(self) -> int:
        return self.centre.shape[0]

    @functools.cached_property
    def moves(self) -> bool:
        """True if some wall has a velocity and a move window (else shift and velocity are zero
        at all times: one cached zero tensor instead of half a dozen operations per step)."""
        return bool(((self.velocity != 0).any(-1) & (self.move_until > self.move_from)).any())

    @functools.cached_property
    def _still(self) -> Tensor:
        return torch.zeros_like(self.centre)

    def shift(self, time: float) -> Tensor:
        """``[W, 3]`` displacement of every wall at ``time`` (s) from its t = 0 position, m."""
        if not self.moves:
            return self._still
        span = (self.move_until - self.move_from).clamp_min(0.0)
        moved = (torch.as_tensor(time, dtype=self.centre.dtype) - self.move_from).clamp(min=0.0)
        moved = torch.minimum(moved, span)
        return self.velocity * moved[:, None]

    def velocity_at(self, time: float) -> Tensor:
        """``[W, 3]`` wall velocity at ``time``, m/s."""
        if not self.moves:
            return self._still
        moving = (self.move_from <= time) & (time < self.move_until)
        return self.velocity * moving[:, None].to(self.velocity.dtype)

    @functools.cached_property
    def events(self) -> tuple[float, ...]:
        """Finite times at which some wall appears or goes, sorted (s; the exact values of the
        tensors' dtype)."""
        times = torch.cat([self.active_from, self.active_until]).tolist()
        return tuple(sorted({float(t) for t in times if math.isfinite(t)}))

    @functools.cached_property
    def _active_sets(self) -> dict[int, Tensor]:
        return {}

    def active_at(self, time: float) -> Tensor:
        """``[W]`` bool: which walls exist at ``time``. The set only changes at :attr:`events`,
        so it is computed once per interval between them and then handed out (asked for at every
        step); do not modify it in place."""
        if self.active_from.dtype == torch.float32:  # compared as the tensors compare: in float32
            time = float(np.float32(time))
        k = bisect.bisect_right(self.events, time)  # events[k - 1] <= time < events[k]
        sets = self._active_sets
        if k not in sets:
            sets[k] = (self.active_from <= time) & (time < self.active_until)
        return sets[k]


def _vec(v, name: str, source: str) -> Tensor:
    t = torch.as_tensor(v, dtype=torch.float64).reshape(-1)
    if t.shape[0] != 3 or not bool(torch.isfinite(t).all()):
        raise out_of_range(name, tuple(v), "a finite 3-vector", source)
    return t


def make_walls(specs: Sequence[WallSpec], material_ids: dict[str, int], *,
               dtype=torch.float64, device="cpu", source: str = "walls") -> Walls:
    """Validate wall specs and pack them into a :class:`Walls` on ``device``."""
    names = [s.name for s in specs]
    if len(set(names)) != len(names):
        raise ConfigError(f"{source}: wall names must be unique, got {names}")
    rows = []
    for s in specs:
        src = f"{source}[{s.name}]"
        c = _vec(s.centre, "centre", src)
        n = _vec(s.normal, "normal", src)
        u = _vec(s.axis_u, "axis_u", src)
        if abs(float(n.norm()) - 1.0) > 1e-6:
            raise out_of_range("normal", tuple(s.normal), "a unit vector (|n| = 1)", src)
        if abs(float(u.norm()) - 1.0) > 1e-6 or abs(float(n @ u)) > 1e-6:
            raise out_of_range("axis_u", tuple(s.axis_u), "a unit vector perpendicular to the normal", src)
        for key in ("half_u", "half_v"):
            val = getattr(s, key)
            if not val > 0:
                raise out_of_range(key, val, "a half-extent > 0 m (inf for a plane)", src)
        if s.material not in material_ids:
            raise ConfigError(f"{src}: material {s.material!r} is unknown; known: {sorted(material_ids)}")
        if not s.active_from < s.active_until:
            raise ConfigError(f"{src}: active_from = {s.active_from} must be before active_until = {s.active_until}")
        _vec(s.velocity, "velocity", src)  # checked here; the rows keep the spec
        rows.append((c, n, u, torch.linalg.cross(n, u), s))
    _check_no_coincident_walls(rows, source)
    if not rows:
        z3 = torch.zeros((0, 3), dtype=dtype, device=device)
        z1 = torch.zeros((0,), dtype=dtype, device=device)
        return Walls(z3, z3, z3, z3, z1, z1, torch.zeros(0, dtype=torch.long, device=device),
                     z1, z1, z3, z1, z1, ())
    st = lambda xs: torch.stack(xs).to(dtype=dtype, device=device)  # noqa: E731
    sc = lambda xs: torch.tensor(xs, dtype=dtype, device=device)  # noqa: E731
    return Walls(
        centre=st([r[0] for r in rows]),
        normal=st([r[1] for r in rows]),
        axis_u=st([r[2] for r in rows]),
        axis_v=st([r[3] for r in rows]),
        half_u=sc([r[4].half_u for r in rows]),
        half_v=sc([r[4].half_v for r in rows]),
        material=torch.tensor([material_ids[r[4].material] for r in rows], dtype=torch.long, device=device),
        active_from=sc([r[4].active_from for r in rows]),
        active_until=sc([r[4].active_until for r in rows]),
        velocity=st([torch.as_tensor(r[4].velocity, dtype=torch.float64) for r in rows]),
        move_from=sc([r[4].move_from for r in rows]),
        move_until=sc([r[4].move_until for r in rows]),
        names=tuple(names),
    )


def _check_no_coincident_walls(rows, source: str) -> None:
    """Two walls in the same plane whose rectangles overlap in area, existing at the same time."""
    for a in range(len(rows)):
        for b in range(a + 1, len(rows)):
            ca, na, ua, va, sa = rows[a]
            cb, nb, ub, vb, sb = rows[b]
            if abs(abs(float(na @ nb)) - 1.0) > 1e-9 or abs(float((cb - ca) @ na)) > 1e-9:
                continue
            if sa.active_until <= sb.active_from or sb.active_until <= sa.active_from:
                continue
            # Separating-axis test of the two rectangles inside their common plane.
            overlap = True
            for axis in (ua, va, ub, vb):
                def extent(c, u, v, hu, hv):
                    r = (abs(float(u @ axis)) * hu if hu != INF else (INF if abs(float(u @ axis)) > 1e-12 else 0.0))
                    r += (abs(float(v @ axis)) * hv if hv != INF else (INF if abs(float(v @ axis)) > 1e-12 else 0.0))
                    return float(c @ axis), r
                pa, ra = extent(ca, ua, va, sa.half_u, sa.half_v)
                pb, rb = extent(cb, ub, vb, sb.half_u, sb.half_v)
                if abs(pa - pb) >= ra + rb - 1e-12:
                    overlap = False
                    break
            if overlap:
                raise ConfigError(f"{source}: walls {sa.name!r} and {sb.name!r} lie on top of each other "
                                  "(same plane, overlapping area, present at the same time); remove one "
                                  "or give them disjoint existence windows")


def closest_points(walls: Walls, shift: Tensor, x: Tensor, wall_index: Tensor) -> Tensor:
    """Closest point on wall ``wall_index[k]`` to point ``x[k]``.

    Args:
        shift: ``[W, 3]`` current wall displacement. x: ``[Q, 3]``. wall_index: ``[Q]``.
    Returns:
        ``[Q, 3]`` closest points, m.
    """
    c = walls.centre[wall_index] + shift[wall_index]
    u = walls.axis_u[wall_index]
    v = walls.axis_v[wall_index]
    d = x - c
    su = (d * u).sum(-1).clamp(-walls.half_u[wall_index], walls.half_u[wall_index])
    sv = (d * v).sum(-1).clamp(-walls.half_v[wall_index], walls.half_v[wall_index])
    return c + su[:, None] * u + sv[:, None] * v
