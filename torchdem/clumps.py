"""Rigid clumps of overlapping spheres: templates and exact-enough mass properties.

Contract:
- A :class:`ClumpTemplate` lists K spheres (offsets ``[K, 3]`` and radii ``[K]``, metres, for
  a template of unit scale). A body of scale ``s`` made from it has offsets ``s * offsets``
  and radii ``s * radii``; its volume scales as s^3 and its inertia as s^5.
- :func:`mass_properties` integrates the union of the spheres (overlaps counted once) for a
  unit density: volume, centre of mass and inertia tensor. It integrates exactly along x
  (union of 1-D chords, with closed-form moments) and by Gauss-Legendre quadrature over
  (y, z) cells, so the relative error is below 1e-5 for the default resolution (tested
  against the closed-form volume of two overlapping spheres).
- :func:`principal_template` re-expresses a template in its principal frame (centre of mass
  at the origin, inertia diagonal), which is the frame the integrator uses.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from torchdem.errors import ConfigError


@dataclass(frozen=True)
class ClumpTemplate:
    """Spheres of a rigid clump, unit scale.

    Attributes:
        name: template name (``"sphere"``, ``"sinter3"``).
        offsets: ``[K, 3]`` sphere centres in the template frame, metres at scale 1.
        radii: ``[K]`` sphere radii, metres at scale 1.
    """

    name: str
    offsets: np.ndarray
    radii: np.ndarray

    def __post_init__(self):
        off = np.asarray(self.offsets, dtype=np.float64).reshape(-1, 3)
        rad = np.asarray(self.radii, dtype=np.float64).reshape(-1)
        if off.shape[0] != rad.shape[0] or rad.shape[0] == 0:
            raise ConfigError(f"ClumpTemplate[{self.name}]: offsets {off.shape} and radii {rad.shape} "
                              "must describe the same K >= 1 spheres")
        if not (rad > 0).all() or not np.isfinite(off).all():
            raise ConfigError(f"ClumpTemplate[{self.name}]: radii must be > 0 and offsets finite; got radii {rad}")
        object.__setattr__(self, "offsets", off)
        object.__setattr__(self, "radii", rad)

    @property
    def n_spheres(self) -> int:
        return self.radii.shape[0]

    def bounding_radius(self) -> float:
        """Radius of the smallest origin-centred sphere enclosing the clump (scale 1)."""
        return float((np.linalg.norm(self.offsets, axis=1) + self.radii).max())


@dataclass(frozen=True)
class MassProperties:
    """Unit-density mass properties of a clump at scale 1.

    Attributes:
        volume: m^3. centre: ``[3]`` m. inertia: ``[3, 3]`` m^5 (times density gives kg m^2),
        about the centre of mass, in the template frame.
    """

    volume: float
    centre: np.ndarray
    inertia: np.ndarray


def _union_chords(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge K intervals per line into disjoint pieces. lo, hi: [L, K] (empty: lo > hi).

    Returns merged (lo, hi) [L, K] where overlapping pieces are collapsed so that each point
    is covered once; collapsed pieces become empty (lo == hi).
    """
    order = np.argsort(lo, axis=1)
    lo = np.take_along_axis(lo, order, axis=1)
    hi = np.take_along_axis(hi, order, axis=1)
    reach = np.maximum.accumulate(hi, axis=1)
    prev_reach = np.concatenate([np.full((lo.shape[0], 1), -np.inf), reach[:, :-1]], axis=1)
    start = np.maximum(lo, prev_reach)
    end = np.maximum(hi, start)
    return start, end


def mass_properties(template: ClumpTemplate, resolution: int = 96) -> MassProperties:
    """Volume, centre of mass and inertia tensor of the union of the template's spheres.

    Chords along x are merged exactly; the (y, z) plane is covered by ``resolution`` x
    ``resolution`` cells, each with a 4 x 4 Gauss-Legendre rule.
    """
    c, r = template.offsets, template.radii
    y0, y1 = (c[:, 1] - r).min(), (c[:, 1] + r).max()
    z0, z1 = (c[:, 2] - r).min(), (c[:, 2] + r).max()
    g, w = np.polynomial.legendre.leggauss(4)

    def nodes(a, b):
        edges = np.linspace(a, b, resolution + 1)
        h = np.diff(edges)[:, None]
        mid = 0.5 * (edges[1:] + edges[:-1])[:, None]
        return (mid + 0.5 * h * g[None, :]).ravel(), (0.5 * h * w[None, :]).ravel()

    ys, wy = nodes(y0, y1)
    zs, wz = nodes(z0, z1)
    Y, Z = np.meshgrid(ys, zs, indexing="ij")
    W = np.outer(wy, wz).ravel()
    Y, Z = Y.ravel(), Z.ravel()
    h2 = r[None, :] ** 2 - (Y[:, None] - c[None, :, 1]) ** 2 - (Z[:, None] - c[None, :, 2]) ** 2
    inside = h2 > 0
    h = np.sqrt(np.where(inside, h2, 0.0))
    lo = np.where(inside, c[None, :, 0] - h, np.inf)
    hi = np.where(inside, c[None, :, 0] + h, -np.inf)
    lo, hi = _union_chords(lo, hi)
    valid = np.isfinite(lo) & np.isfinite(hi) & (hi > lo)
    lo = np.where(valid, lo, 0.0)
    hi = np.where(valid, hi, 0.0)
    m0 = (hi - lo).sum(1)                      # integral of 1 dx
    m1 = 0.5 * (hi ** 2 - lo ** 2).sum(1)      # integral of x dx
    m2 = (hi ** 3 - lo ** 3).sum(1) / 3.0      # integral of x^2 dx
    V = (W * m0).sum()
    Sx, Sy, Sz = (W * m1).sum(), (W * Y * m0).sum(), (W * Z * m0).sum()
    Sxx, Syy, Szz = (W * m2).sum(), (W * Y ** 2 * m0).sum(), (W * Z ** 2 * m0).sum()
    Sxy, Sxz, Syz = (W * Y * m1).sum(), (W * Z * m1).sum(), (W * Y * Z * m0).sum()
    com = np.array([Sx, Sy, Sz]) / V
    second = np.array([[Sxx, Sxy, Sxz], [Sxy, Syy, Syz], [Sxz, Syz, Szz]]) - V * np.outer(com, com)
    inertia = np.trace(second) * np.eye(3) - second
    return MassProperties(volume=float(V), centre=com, inertia=inertia)


@dataclass(frozen=True)
class PrincipalTemplate:
    """A template in its principal frame, with its unit-density mass properties.

    Attributes:
        template: spheres relative to the centre of mass, principal axes along x, y, z.
        volume: m^3 at scale 1. principal_inertia: ``[3]`` m^5 at scale 1 (unit density).
    """

    template: ClumpTemplate
    volume: float
    principal_inertia: np.ndarray


def principal_template(template: ClumpTemplate, resolution: int = 96) -> PrincipalTemplate:
    """Move a template to its centre of mass and rotate it onto its principal axes.

    The quadrature of a clump takes a tenth of a second, and every member of every run asks for
    the same few templates: results are kept per template (name, spheres, resolution) in a
    process-wide cache and handed out as copies."""
    key = (template.name, template.offsets.tobytes(), template.radii.tobytes(), int(resolution))
    kept = _PRINCIPAL.get(key)
    if kept is None:
        kept = _PRINCIPAL[key] = _principal(template, resolution)
    return PrincipalTemplate(ClumpTemplate(kept.template.name, kept.template.offsets.copy(),
                                           kept.template.radii.copy()), kept.volume, kept.principal_inertia.copy())


#: principal_template's results by (name, offsets, radii, resolution): a few hundred bytes each.
_PRINCIPAL: dict[tuple, PrincipalTemplate] = {}


def _principal(template: ClumpTemplate, resolution: int) -> PrincipalTemplate:
    if template.n_spheres == 1:
        r = float(template.radii[0])
        V = 4.0 / 3.0 * np.pi * r ** 3
        I = 0.4 * V * r ** 2
        return PrincipalTemplate(ClumpTemplate(template.name, np.zeros((1, 3)), template.radii.copy()),
                                 V, np.full(3, I))
    props = mass_properties(template, resolution)
    evals, evecs = np.linalg.eigh(props.inertia)
    if np.linalg.det(evecs) < 0:
        evecs[:, 0] *= -1.0
    offsets = (template.offsets - props.centre) @ evecs
    return PrincipalTemplate(ClumpTemplate(template.name, offsets, template.radii.copy()),
                             props.volume, evals)


SPHERE = ClumpTemplate("sphere", np.zeros((1, 3)), np.ones(1))
