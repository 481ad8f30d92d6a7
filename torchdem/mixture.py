"""Granular materials and mixtures: shapes, sieve size distributions, layered fills.

Contract:
- :class:`ParticleMaterial` is one bulk material as a DEM model sees it: intrinsic
  properties (G, nu, solid density), a shape (a :class:`~torchdem.clumps.ClumpTemplate` of
  unit size, scaled by the sieve diameter d of each particle), a sieve size distribution
  (mass fractions per sieve class, metres) and a render label (``"pellet"`` / ``"sinter"`` or
  any name the renderer knows).
- :class:`Mixture` is a set of materials with mass fractions and a layering order (bottom to
  top, each entry a material name). Every layer of a material gets an equal share of that
  material's mass: four alternating layers of a 50-50 mixture of 40 kg are 10 kg each.
  Three or more materials and any layer sequence work the same way.
- :func:`sample_layers` draws particles (material index, sieve diameter) per layer from the
  size distributions until each layer reaches its mass, reproducibly from a seed: within a
  sieve class the diameter is uniform between the sieve sizes, and classes are chosen with
  probability proportional to mass fraction / mean particle mass of the class, so the drawn
  mass distribution matches the sieve analysis.

The sinter template (three equal overlapping spheres, :data:`SINTER_TRILOBE`): sphere radius
0.35 d, centres on an equilateral triangle of circumradius 0.15 d, so the clump just fits a
sphere of the sieve diameter d (it passes the sieve) and is 0.7 d thick (a flat, irregular
grain). The smallest sphere of the smallest sinter (d = 5.6 mm) then has r = 1.96 mm, which
with rho = 3449 kg/m^3 and G = 1e8 Pa gives 15% of the Rayleigh time step = 5.9e-6 s — the time
step Hadi et al. report (Section 3.2.4), i.e. the same smallest-sphere size as their clumps.
The trilobe family (:func:`trilobe_template`) varies the lobe spacing and scale; the tetralobe
family (:func:`tetralobe_template`, four lobes on a tetrahedron) is the same sphere budget per lobe
out of the plane, a grain that stands out of every plane it rests on.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from torchdem.clumps import ClumpTemplate, principal_template
from torchdem.errors import ConfigError, out_of_range

PELLET_SPHERE = ClumpTemplate("sphere", np.zeros((1, 3)), np.array([0.5]))
_R = 0.15
SINTER_TRILOBE = ClumpTemplate(
    "sinter_trilobe",
    np.array([[_R * math.cos(a), _R * math.sin(a), 0.0] for a in (0.0, 2 * math.pi / 3, 4 * math.pi / 3)]),
    np.full(3, 0.35),
)


def _check_lobed(lobe_spacing: float, scale: float, source: str) -> None:
    """A lobed clump's lobe spacing in (0, 0.3] and scale in (0.5, 2], or a ConfigError naming ``source``."""
    if not 0 < lobe_spacing <= 0.3:
        raise out_of_range("lobe_spacing", lobe_spacing, "(0, 0.3] of the sieve diameter", source)
    if not (math.isfinite(scale) and 0.5 < scale <= 2.0):
        raise out_of_range("clump scale", scale, "(0.5, 2] of the clump that fits the sieve diameter", source)


def trilobe_template(lobe_spacing: float, scale: float = 1.0) -> ClumpTemplate:
    """The trilobe family of :data:`SINTER_TRILOBE`: three equal spheres on an equilateral
    triangle of circumradius ``lobe_spacing`` (units of the sieve diameter d), each of radius
    ``0.5 - lobe_spacing`` so the clump just fits a sphere of diameter d. 0 is a sphere, 0.15
    the default sinter, larger values are flatter and more angular; allowed (0, 0.3]. The lobes
    (centres ``sqrt(3) lobe_spacing`` apart) touch at ``1 / (2 + sqrt 3)`` = 0.2679 and part
    beyond it: at 0.3 the clump is three separate spheres 0.12 d apart.

    ``scale`` multiplies every length of the clump (allowed (0.5, 2]): 1 fits the sphere of the sieve
    diameter, which passes a square aperture of only :func:`trilobe_aperture` d; ``1 /
    trilobe_aperture(s)`` passes the aperture d itself, as a grain sieved into a class of size d does."""
    _check_lobed(lobe_spacing, scale, "trilobe_template")
    a = (0.0, 2 * math.pi / 3, 4 * math.pi / 3)
    return ClumpTemplate(trilobe_shape(lobe_spacing, scale),
                         scale * np.array([[lobe_spacing * math.cos(t), lobe_spacing * math.sin(t), 0.0] for t in a]),
                         np.full(3, scale * (0.5 - lobe_spacing)))


def tetralobe_template(lobe_spacing: float, scale: float = 1.0) -> ClumpTemplate:
    """Four equal spheres on the corners of a regular tetrahedron of circumradius ``lobe_spacing``
    (units of the sieve diameter d), each of radius ``0.5 - lobe_spacing``, so the clump just fits a
    sphere of diameter d as the trilobe of the same spacing does; allowed (0, 0.3], ``scale`` as for
    :func:`trilobe_template`. The trilobe is flat: its lobes lie in a plane, and clumps can slide on
    one another plane to plane. The tetralobe stands out of every plane it rests on. The lobes
    (centres ``sqrt(8/3) lobe_spacing`` apart) touch at ``1 / (2 + sqrt(8/3))`` = 0.2753 and part
    beyond it."""
    _check_lobed(lobe_spacing, scale, "tetralobe_template")
    corners = np.array([[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]]) / math.sqrt(3.0)
    return ClumpTemplate(lobe_shape(4, lobe_spacing, scale), scale * lobe_spacing * corners,
                         np.full(4, scale * (0.5 - lobe_spacing)))


def trilobe_aperture(lobe_spacing: float) -> float:
    """Side of the smallest square sieve aperture the trilobe of unit scale passes, in units of its
    sieve diameter d: ``1 - (2 - 3 / (2 sqrt 2)) lobe_spacing`` (0.859 at 0.15, 0.758 at 0.2574). The
    clump passes standing, its plane along the travel and along the aperture's diagonal, with the lobes
    in a row across the triangle's height (1.5 s): each side of the square holds two lobe radii,
    1 - 2 s, and that height's share on it, 1.5 s / sqrt 2 (tests/test_clump_size.py finds no
    orientation that passes a smaller square)."""
    if not 0 < lobe_spacing <= 0.3:
        raise out_of_range("lobe_spacing", lobe_spacing, "(0, 0.3] of the sieve diameter", "trilobe_aperture")
    return 1.0 - (2.0 - 1.5 / math.sqrt(2.0)) * lobe_spacing


_TRILOBE_PREFIX = "trilobe_s"
_TETRALOBE_PREFIX = "tetralobe_s"
_SCALE_TAG = "_k"
#: Lobe count -> (shape key prefix, template builder) of the lobed clump families.
_LOBED = {3: (_TRILOBE_PREFIX, trilobe_template), 4: (_TETRALOBE_PREFIX, tetralobe_template)}


def trilobe_shape(lobe_spacing: float, scale: float = 1.0) -> str:
    """Shape key of a trilobe of this lobe spacing and scale (``"trilobe_s0.2000"``,
    ``"trilobe_s0.2000_k1.1500"``); :data:`TEMPLATES` builds it on first use, in any process (the key
    is the recipe)."""
    return lobe_shape(3, lobe_spacing, scale)


def lobe_shape(lobes: int, lobe_spacing: float, scale: float = 1.0) -> str:
    """Shape key of a lobed clump: ``"trilobe_s0.2574[_k...]"`` for 3 lobes, ``"tetralobe_s0.2574[_k...]"``
    for 4 (:func:`tetralobe_template`)."""
    if lobes not in _LOBED:
        raise out_of_range("lobe count", lobes, f"one of {sorted(_LOBED)}", "lobe_shape")
    key = f"{_LOBED[lobes][0]}{lobe_spacing:.4f}"
    return key if scale == 1.0 else f"{key}{_SCALE_TAG}{scale:.4f}"


def lobed_parameters(shape: str) -> tuple[int, float, float] | None:
    """``(lobes, lobe spacing, scale)`` of a lobed clump's shape key (3 for a trilobe, 4 for a
    tetralobe); None for any other shape."""
    if shape == "sinter_trilobe":
        return 3, _R, 1.0
    for lobes, (prefix, _) in _LOBED.items():
        if shape.startswith(prefix):
            spacing, _, scale = shape[len(prefix):].partition(_SCALE_TAG)
            try:
                return lobes, float(spacing), float(scale) if scale else 1.0
            except ValueError:
                return None
    return None


def trilobe_parameters(shape: str) -> tuple[float, float] | None:
    """``(lobe spacing, scale)`` of a trilobe shape key (``"sinter_trilobe"`` is ``(0.15, 1.0)``);
    None for a shape that is no trilobe."""
    parsed = lobed_parameters(shape)
    return parsed[1:] if parsed is not None and parsed[0] == 3 else None


class _TemplateTable(dict):
    """Named templates plus the parametric lobed families (keys ``trilobe_s<spacing>[_k<scale>]``,
    ``tetralobe_s<spacing>[_k<scale>]``)."""

    def _parametric(self, key) -> ClumpTemplate | None:
        if isinstance(key, str) and key != "sinter_trilobe":
            parsed = lobed_parameters(key)
            if parsed is None:
                return None
            lobes, spacing, scale = parsed
            if 0 < spacing <= 0.3 and 0.5 < scale <= 2.0 and lobe_shape(lobes, spacing, scale) == key:
                return _LOBED[lobes][1](spacing, scale)
        return None

    def __contains__(self, key) -> bool:
        return dict.__contains__(self, key) or self._parametric(key) is not None

    def __missing__(self, key):
        template = self._parametric(key)
        if template is None:
            raise KeyError(key)
        self[key] = template
        return template


TEMPLATES: dict[str, ClumpTemplate] = _TemplateTable({"sphere": PELLET_SPHERE, "sinter_trilobe": SINTER_TRILOBE})

#: A material's render label -> how the front views draw it: ``"pellet"`` white/blue, ``"sinter"`` dark
#: grey, as the lab's photos show them; unlabelled (``""``) draws as sinter. The segregation KPI counts
#: the pellet-coloured pixels, so a label the renderer does not know is refused, not drawn as sinter.
RENDER_LABELS = {"pellet": "white/blue", "sinter": "dark grey", "": "unlabelled: dark grey"}


@dataclass(frozen=True)
class SieveClass:
    """Mass fraction of particles between two sieve sizes (metres)."""

    d_min: float
    d_max: float
    mass_fraction: float


@dataclass(frozen=True)
class ParticleMaterial:
    """A bulk material as modelled (see the module docstring).

    Attributes:
        name: unique name. shape: key of :data:`TEMPLATES` (unit sieve diameter).
        sieve: the size distribution. density: solid density, kg/m^3.
        shear_modulus: Pa. poisson_ratio. label: render/segmentation label.
        fines_kept: share of the mass of every sieve class below a run's fines cut
            (``RunSettings.fines_cut``) kept in its class; the rest is scalped into the class at the
            cut (:func:`scalp_sieve`). 0, the default: all scalped; 1: the sieve as measured.
    """

    name: str
    shape: str
    sieve: tuple[SieveClass, ...]
    density: float
    shear_modulus: float = 1e8
    poisson_ratio: float = 0.25
    label: str = ""
    fines_kept: float = 0.0

    def validate(self, source: str) -> "ParticleMaterial":
        src = f"{source}[{self.name}]"
        if self.shape not in TEMPLATES:
            raise ConfigError(f"{src}: shape = {self.shape!r}; expected one of {sorted(TEMPLATES)}")
        if not self.sieve:
            raise ConfigError(f"{src}: the sieve size distribution is empty")
        total = sum(c.mass_fraction for c in self.sieve)
        if abs(total - 1.0) > 1e-3:
            raise out_of_range("sum of sieve mass fractions", round(total, 6), "1 (within 1e-3)", src)
        for k, c in enumerate(self.sieve):
            if not (0 < c.d_min < c.d_max):
                raise out_of_range(f"sieve[{k}] (d_min, d_max)", (c.d_min, c.d_max), "0 < d_min < d_max (m)", src)
            if not (0 <= c.mass_fraction <= 1):
                raise out_of_range(f"sieve[{k}].mass_fraction", c.mass_fraction, "[0, 1]", src)
        if not self.density > 0:
            raise out_of_range("density", self.density, "> 0 kg/m^3", src)
        if not 0 <= self.fines_kept <= 1:
            raise out_of_range("fines_kept", self.fines_kept, "[0, 1]", src)
        if self.label not in RENDER_LABELS:
            raise out_of_range("label", self.label, "a render label of " + ", ".join(
                f"{k!r} ({v})" for k, v in RENDER_LABELS.items()), src)
        return self

    @property
    def template(self) -> ClumpTemplate:
        return TEMPLATES[self.shape]

    def unit_volume(self) -> float:
        """Volume of a particle of unit sieve diameter, m^3."""
        return principal_template(self.template).volume

    @property
    def smallest_sphere_radius(self) -> float:
        """Radius of the smallest sphere in the smallest particle, m."""
        return float(self.template.radii.min()) * min(c.d_min for c in self.sieve)

    @property
    def largest_extent(self) -> float:
        """Diameter of the sphere enclosing the largest particle, m."""
        return 2 * self.template.bounding_radius() * max(c.d_max for c in self.sieve)


@dataclass(frozen=True)
class Mixture:
    """Materials, mass fractions and layering (bottom to top).

    Attributes:
        name: e.g. ``"pellet_sinter_50_50"``.
        materials: the materials. mass_fractions: one per material, summing to 1.
        layering: material names bottom to top (each must be a material; every material with
            a positive fraction must appear).
        total_mass: kg in the full box.
    """

    name: str
    materials: tuple[ParticleMaterial, ...]
    mass_fractions: tuple[float, ...]
    layering: tuple[str, ...]
    total_mass: float

    def validate(self, source: str = "mixture") -> "Mixture":
        names = [m.name for m in self.materials]
        if len(set(names)) != len(names):
            raise ConfigError(f"{source}: material names must be unique, got {names}")
        for m in self.materials:
            m.validate(f"{source}.materials")
        if len(self.mass_fractions) != len(self.materials):
            raise ConfigError(f"{source}: {len(self.mass_fractions)} mass fractions for {len(names)} materials")
        if any(f < 0 for f in self.mass_fractions) or abs(sum(self.mass_fractions) - 1) > 1e-6:
            raise out_of_range("mass_fractions", tuple(self.mass_fractions), "non-negative values summing to 1", source)
        for k, layer in enumerate(self.layering):
            if layer not in names:
                raise ConfigError(f"{source}: layering[{k}] = {layer!r} is not a material; known: {names}")
        for n, f in zip(names, self.mass_fractions):
            if f > 0 and n not in self.layering:
                raise ConfigError(f"{source}: material {n!r} has mass fraction {f} but no layer in {list(self.layering)}")
        if not self.total_mass > 0:
            raise out_of_range("total_mass", self.total_mass, "> 0 kg", source)
        return self

    def layer_masses(self, scale: float = 1.0) -> list[tuple[int, float]]:
        """(material index, mass in kg) per layer, bottom to top, for ``scale`` of the total."""
        index = {m.name: k for k, m in enumerate(self.materials)}
        counts = {n: self.layering.count(n) for n in set(self.layering)}
        out = []
        for layer in self.layering:
            k = index[layer]
            out.append((k, scale * self.total_mass * self.mass_fractions[k] / counts[layer]))
        return out


def sieve_from_table(rows: Sequence[Mapping[str, float]]) -> tuple[SieveClass, ...]:
    """Sieve classes from rows ``{d_min_mm, d_max_mm, mass_fraction}`` (as in the data file)."""
    return tuple(SieveClass(r["d_min_mm"] / 1000.0, r["d_max_mm"] / 1000.0, float(r["mass_fraction"])) for r in rows)


@dataclass(frozen=True)
class SampledLayers:
    """Particles drawn for a fill, bottom layer first.

    Attributes:
        material: ``[N]`` int material index. diameter: ``[N]`` sieve diameter d, m.
        layer: ``[N]`` layer index (0 = bottom). mass: ``[N]`` kg.
    """

    material: np.ndarray
    diameter: np.ndarray
    layer: np.ndarray
    mass: np.ndarray


def sample_layers(mixture: Mixture, scale: float, seed: int) -> SampledLayers:
    """Draw the particles of every layer (see the module docstring); ``scale`` is the share of
    the full box simulated (a slice of depth D_s of a box of depth D has scale D_s / D)."""
    rng = np.random.default_rng(seed)
    mats, diams, layers, masses = [], [], [], []
    unit = [m.unit_volume() * m.density for m in mixture.materials]  # kg per d^3
    for li, (k, target) in enumerate(mixture.layer_masses(scale)):
        m = mixture.materials[k]
        lo = np.array([c.d_min for c in m.sieve])
        hi = np.array([c.d_max for c in m.sieve])
        frac = np.array([c.mass_fraction for c in m.sieve])
        mean_mass = unit[k] * (hi ** 4 - lo ** 4) / (4 * (hi - lo))  # E[d^3] for d ~ U(lo, hi)
        p = frac / mean_mass
        p = p / p.sum()
        got = 0.0
        while got < target:
            n = max(16, int(1.2 * (target - got) / float((p * mean_mass).sum())))
            cls = rng.choice(len(p), size=n, p=p)
            d = lo[cls] + (hi[cls] - lo[cls]) * rng.random(n)
            mass = unit[k] * d ** 3
            cum = got + np.cumsum(mass)
            take = int(np.searchsorted(cum, target, side="left")) + 1  # the particle that crosses the target
            take = min(take, n)
            mats.append(np.full(take, k))
            diams.append(d[:take])
            layers.append(np.full(take, li))
            masses.append(mass[:take])
            got = float(cum[take - 1])
    return SampledLayers(np.concatenate(mats), np.concatenate(diams), np.concatenate(layers), np.concatenate(masses))


def scalp_sieve(sieve: Sequence[SieveClass], d_cut: float, source: str = "sieve",
                fines_kept: float = 0.0) -> tuple[SieveClass, ...]:
    """Merge the sieve classes below ``d_cut`` (m) into the first class at or above it, keeping mass.

    This is the "scalping" of fines that industrial DEM uses to afford a run: the mass of the
    fines is kept but carried by coarser particles, so the particle count and the smallest
    sphere (which sets the time step) shrink. It changes what fines do (percolation, packing),
    so a study that asks about fines must not use it; ``d_cut`` must be a sieve boundary.
    ``fines_kept`` in [0, 1]: that share of each fine class's mass stays in its class and only the
    rest is merged (1 returns the sieve as it is); a fine class left with no mass is dropped.
    """
    bounds = sorted({c.d_min for c in sieve})
    if not any(abs(d_cut - b) < 1e-9 for b in bounds):
        raise out_of_range("fines_cut", d_cut, f"one of the sieve boundaries {[round(b, 6) for b in bounds]} m", source)
    if not 0 <= fines_kept <= 1:
        raise out_of_range("fines_kept", fines_kept, "[0, 1]", source)
    kept = [c for c in sieve if c.d_min >= d_cut - 1e-9]
    fines = [c for c in sieve if c.d_min < d_cut - 1e-9]
    lost = (1.0 - fines_kept) * sum(c.mass_fraction for c in fines)
    first = kept[0]
    stay = tuple(SieveClass(c.d_min, c.d_max, fines_kept * c.mass_fraction) for c in fines) if fines_kept > 0 else ()
    return stay + (SieveClass(first.d_min, first.d_max, first.mass_fraction + lost),) + tuple(kept[1:])


def scalp_mixture(mixture: Mixture, d_cut: float | None, source: str = "fines_cut") -> Mixture:
    """The mixture with every material's fines below ``d_cut`` scalped (see :func:`scalp_sieve`),
    but for the share ``ParticleMaterial.fines_kept`` of each; materials whose smallest sieve size is
    at or above ``d_cut`` are unchanged."""
    if d_cut is None:
        return mixture
    if not d_cut > 0:
        raise out_of_range("fines_cut", d_cut, "> 0 m or null", source)
    mats = []
    for m in mixture.materials:
        if min(c.d_min for c in m.sieve) < d_cut - 1e-9:
            boundaries = sorted({c.d_min for c in m.sieve})
            if d_cut >= max(boundaries) + 1e-9:
                raise out_of_range("fines_cut", d_cut, f"<= {max(boundaries)} m (the last sieve class of "
                                   f"{m.name!r} starts there)", source)
            snapped = min(b for b in boundaries if b >= d_cut - 1e-9)
            m = dataclasses.replace(m, sieve=scalp_sieve(m.sieve, snapped, f"{source}[{m.name}]", m.fines_kept))
        mats.append(m)
    return Mixture(mixture.name, tuple(mats), mixture.mass_fractions, mixture.layering, mixture.total_mass)


# -- the paper's materials (Tables 1 and 3), shipped in torchdem/data ---------------------------
PAPER_SHAPES = {"pellet": "sphere", "sinter": "sinter_trilobe"}


def paper_material(name: str) -> ParticleMaterial:
    """Pellet or sinter as the paper measured it: sieve analysis and solid density (Table 1),
    G and nu (Table 3); pellets are spheres, sinter the 3-sphere trilobe clump."""
    from torchdem.measured import load_materials

    if name not in PAPER_SHAPES:
        raise ConfigError(f"paper_material: {name!r} is not a material of the paper; expected one of "
                          f"{sorted(PAPER_SHAPES)}")
    row = load_materials()[name]
    return ParticleMaterial(name, PAPER_SHAPES[name], sieve_from_table(row["sieve_size_distribution"]),
                            float(row["solid_density_kg_m3"]["mean"]), float(row["shear_modulus_pa"]),
                            float(row["poisson_ratio"]), label=name)


def pellet_sinter_mixture(pellet_fraction: float = 0.5, reverse: bool = False, total_mass: float = 40.0,
                          layers: int = 4) -> Mixture:
    """The paper's layered fill: ``layers`` alternating layers, pellets at the bottom (sinter if
    ``reverse``), ``total_mass`` kg; e.g. ``pellet_sinter_mixture(0.75)`` is the 75-25 test."""
    if not 0 < pellet_fraction < 1:
        raise out_of_range("pellet_fraction", pellet_fraction, "(0, 1)", "pellet_sinter_mixture")
    if layers < 2:
        raise out_of_range("layers", layers, "an integer >= 2", "pellet_sinter_mixture")
    order = ("sinter", "pellet") if reverse else ("pellet", "sinter")
    pct = round(100 * pellet_fraction)
    name = f"pellet_sinter_{pct}_{100 - pct}" + ("_reverse" if reverse else "")
    return Mixture(name, (paper_material("pellet"), paper_material("sinter")),
                   (pellet_fraction, 1 - pellet_fraction), tuple(order[k % 2] for k in range(layers)),
                   total_mass).validate(name)
