"""A draw down DEM model: everything a run needs besides the varied parameters and the seed.

Contract:
- :class:`DrawDownModel` holds the mixture of every condition, the geometry, the run settings,
  the contact parameters that stay fixed and the device. It is a frozen, picklable dataclass
  (campaign executors ship it to worker processes). :meth:`DrawDownModel.test_for` turns a
  condition and parameter sets into a :class:`~torchdem.drawdown.DrawDownTest`.
- A condition name may carry run-setting variants after ``|``:
  ``"50-50|time_step_fraction=0.2|shear_modulus=1e7"`` runs the 50-50 mixture with those
  :class:`~torchdem.drawdown.RunSettings` fields replaced (the time-step and stiffness
  studies store their runs this way, so they resume like any other campaign stage).
- A parameter ``density_<material>`` (kg/m^3) is not a contact parameter: it replaces that
  material's solid density in the mixture of the parameter set (bulk-density recalibration,
  section 3.6 of the paper, and density as a calibration parameter, which the paper
  recommends); ``lobe_spacing_<material>`` makes that material a trilobe clump of that lobe
  spacing (:func:`torchdem.mixture.trilobe_template`) and ``clump_scale_<material>`` scales that
  material's trilobes (1: the clump fits the sphere of its sieve size); ``lobe_count_<material>``
  3 or 4 makes its clumps trilobes or tetralobes (:func:`torchdem.mixture.tetralobe_template`) of
  the same spacing and scale. Such parameter sets run in one ensemble with per-member mixtures.
- A parameter ``geometry_<field>`` (m) replaces that length of the boxes
  (:data:`GEOMETRY_PARAMETERS`, fields of :class:`~torchdem.geometry.DrawDownGeometry`): the
  outlet width, which the paper's text does not give, as a discovery candidate
  (:mod:`torchdem.mechanisms.outlet_width`); ``geometry_gate_opening`` (s, :data:`GEOMETRY_TIMES`)
  makes the gate slide out in that time instead of vanishing. An ensemble has one set of walls, so the parameter
  sets of one test agree on them (``bo.campaign.dem.evaluate_batch`` splits a batch that does not).
- Model extensions (:mod:`torchdem.mechanisms`) change a model through
  :func:`torchdem.mechanisms.apply_extension`; every entry point applies the ``extension``
  config group that way.
- :func:`mixtures_from_measured` builds the mixture of every condition of a measured-data file
  (:mod:`torchdem.measured`) from the materials the model uses.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence

from torchdem.drawdown import DrawDownTest, RunSettings
from torchdem.errors import ConfigError, out_of_range
from torchdem.geometry import DrawDownGeometry
from torchdem.measured import MeasuredData
from torchdem.mixture import Mixture, ParticleMaterial, lobe_shape, lobed_parameters

#: Prefix of task parameters that set a material's solid density (kg/m^3), not a contact law.
DENSITY_PREFIX = "density_"
#: Per-material task parameters: prefix -> (low, inclusive high, low open, allowed text, the only values
#: allowed inside the range or None for any).
MATERIAL_PREFIXES = {DENSITY_PREFIX: (0.0, math.inf, True, "a solid density > 0 kg/m^3", None),
                     "lobe_spacing_": (0.0, 0.3, True, "a trilobe lobe spacing in (0, 0.3] of the sieve size", None),
                     "clump_scale_": (0.5, 2.0, True, "a trilobe's size in (0.5, 2] of the one that fits the sieve "
                                      "size", None),
                     "lobe_count_": (2.0, 4.0, True, "3 (a flat trilobe) or 4 (a tetralobe) lobes", (3.0, 4.0)),
                     "fines_kept_": (0.0, 1.0, False, "a share in [0, 1] of the fines below sim.fines_cut_mm kept "
                                     "as sieved (0: all scalped)", None)}
#: Prefix of task parameters that set a length of the boxes, m (``geometry_outlet_width``), or how
#: the gate opens (``geometry_gate_opening``, s).
GEOMETRY_PREFIX = "geometry_"
#: The ``DrawDownGeometry`` lengths a task parameter may set (the depth stays: the lab geometry's
#: mirror plane sits at half of it).
GEOMETRY_PARAMETERS = ("upper_width", "upper_height", "outlet_width", "upper_bottom_z", "lower_width", "lower_height")
#: The ``DrawDownGeometry`` times a task parameter may set, s (``gate_opening``: 0 the gate vanishes).
GEOMETRY_TIMES = ("gate_opening",)


def geometry_parameter_range(name: str) -> tuple[float, bool, str]:
    """``(low, open low, allowed text)`` of a ``geometry_<field>`` task parameter: a length > 0 m or,
    for :data:`GEOMETRY_TIMES`, a time >= 0 s."""
    if name[len(GEOMETRY_PREFIX):] in GEOMETRY_TIMES:
        return 0.0, False, "a time >= 0 s (geometry_gate_opening 0: the gate vanishes at once)"
    return 0.0, True, "a length > 0 m"


def mixture_parameters(params: Mapping[str, float]) -> tuple[tuple[str, float], ...]:
    """The task parameters that change a member's mixture (``density_*``, ``lobe_spacing_*``,
    ``clump_scale_*``) or the ensemble's boxes (``geometry_*``), sorted by name. Members of one
    ensemble share its time step (the smallest member's), its body count (the largest member's) and
    its walls, so a campaign batches tasks with equal or near values of these together
    (``CampaignStore.claim(affinity=...)``): a flat-sinter run (lobe spacing 0.3) batched with a
    default one made the latter take 1.75x its steps."""
    return tuple(sorted((k, float(v)) for k, v in params.items()
                        if k.startswith((*MATERIAL_PREFIXES, GEOMETRY_PREFIX))))


def geometry_parameters(params: Mapping[str, float]) -> tuple[tuple[str, float], ...]:
    """The ``geometry_*`` task parameters of a parameter set, sorted by name."""
    return tuple(sorted((k, float(v)) for k, v in params.items() if k.startswith(GEOMETRY_PREFIX)))


def with_geometry_parameters(geometry: DrawDownGeometry, params: Mapping[str, float], source: str
                             ) -> DrawDownGeometry:
    """``geometry`` with the lengths its ``geometry_<field>`` parameters set (other keys ignored),
    validated; an unknown field or a length the boxes cannot have is a ConfigError naming it."""
    changes = {}
    for key, value in geometry_parameters(params):
        field_name = key[len(GEOMETRY_PREFIX):]
        if field_name not in GEOMETRY_PARAMETERS + GEOMETRY_TIMES:
            raise ConfigError(f"{source}: parameter {key!r} names no length or time a task may set; expected "
                              f"{GEOMETRY_PREFIX}<field> with a field of {list(GEOMETRY_PARAMETERS + GEOMETRY_TIMES)}")
        low, open_low, allowed = geometry_parameter_range(key)
        if not (math.isfinite(value) and (value > low if open_low else value >= low)):
            raise out_of_range(key, value, allowed, source)
        changes[field_name] = value
    return dataclasses.replace(geometry, **changes).validate(source) if changes else geometry

def _optional_length(value: str) -> float | None:
    return None if value == "None" else float(value)


def _flag(value: str) -> bool:
    if value not in ("True", "False"):
        raise ValueError(value)
    return value == "True"


_VARIANT_FIELDS = {"time_step_fraction": float, "shear_modulus": float, "fines_cut": float,
                   "rolling_damping": float, "loose_fraction": float, "dtype": str}
#: Geometry fields a condition may vary (``DrawDownGeometry``): a study of geometries runs each
#: as a variant of the same condition, so one store holds them all.
_GEOMETRY_FIELDS = {"slice_depth": _optional_length, "mirror": _flag}


#: Settings that decide where and how fast a run goes, not what it gives: the device, compiled
#: kernels and the bodies' spatial order (fields of ``DrawDownModel`` and of its ``RunSettings``,
#: named as in the ``sim`` config block). Runs that differ in them differ at round-off, as the C++
#: kernels' runs do between CPUs, so a campaign store and a batch's checkpoint do not tell them apart
#: (``bo.cli.common.config_hash``, ``bo.campaign.dem.checkpoint_path``). ``retry_time_steps`` is
#: one too: it decides only whether a run that blew up is run again at a shorter step (the outcome
#: of such a run records the step it ran at, ``time_step_s``). ``skin_fraction`` is one too: the
#: Verlet skin decides how often the neighbour lists are rebuilt, never which pairs touch nor their
#: order (without the reorder and on a grid without periods, runs at any skin end with the same bits:
#: ``tests/test_neighbors.py::test_the_skin_changes_no_bit_of_a_run``; on a periodic one a whole
#: rebuild wraps the bodies back into the domain, at round-off), and a checkpoint resumed at another
#: skin rebuilds its lists (:meth:`torchdem.simulation.Simulation.load`).
EXECUTION_ONLY = ("device", "compile", "reorder_every", "retry_time_steps", "skin_fraction")


@dataclass(frozen=True)
class DrawDownModel:
    """A draw down DEM model ready to evaluate (see the module docstring).

    Attributes:
        conditions: condition name -> mixture (e.g. ``"50-50"`` -> the 50-50 layered fill).
        geometry: the boxes. settings: how runs are simulated.
        fixed: contact parameters not varied by the campaign (``mu_s_pp`` ... ), overridden by
            a task's parameters of the same name.
        device: torch device name of the ensembles.
    """

    conditions: Mapping[str, Mixture]
    geometry: DrawDownGeometry
    settings: RunSettings
    fixed: Mapping[str, float] = field(default_factory=dict)
    device: str = "cpu"

    def without_execution(self) -> "DrawDownModel":
        """This model with its :data:`EXECUTION_ONLY` settings at their defaults: what its runs
        give, whatever device, compilation, Verlet skin or body order they run with."""
        def defaults(obj):
            return {f.name: f.default for f in dataclasses.fields(obj) if f.name in EXECUTION_ONLY}
        return dataclasses.replace(self, settings=dataclasses.replace(self.settings, **defaults(self.settings)),
                                   **defaults(self))

    def test_for(self, condition: str, parameter_sets: Sequence[Mapping[str, float]],
                 isolate: bool = True, time_step_scale: float = 1.0) -> DrawDownTest:
        """The :class:`DrawDownTest` of a (possibly variant) condition with these parameter sets.

        ``isolate`` (campaigns): a blow-up fails that member only (its outcome says why), not the
        whole ensemble; False keeps the run settings' own ``guards.on_blowup``.
        ``time_step_scale``: a factor in (0, 1] on the condition's time step (the retry of a run
        that blew up)."""
        if not 0 < time_step_scale <= 1:
            raise out_of_range("time_step_scale", time_step_scale, "(0, 1]", "DrawDownModel.test_for")
        base, settings = split_condition(condition, self.settings)
        if time_step_scale != 1:
            discharge = settings.discharge_time_step_fraction
            settings = dataclasses.replace(settings, time_step_fraction=settings.time_step_fraction * time_step_scale,
                                           discharge_time_step_fraction=None if discharge is None
                                           else discharge * time_step_scale)
        geometry = condition_geometry(condition, self.geometry)
        if isolate:
            settings = dataclasses.replace(settings, guards=dataclasses.replace(settings.guards, on_blowup="isolate"))
        if base not in self.conditions:
            raise ConfigError(f"condition {base!r} is not part of the model; known: {sorted(self.conditions)}")
        mixture = self.conditions[base]
        source = f"condition {condition!r}"
        merged = [{**self.fixed, **p} for p in parameter_sets]
        boxes = {geometry_parameters(m) for m in merged}
        if len(boxes) > 1:
            raise ConfigError(f"{source}: the parameter sets of one ensemble set different box lengths "
                              f"{sorted(boxes)}; an ensemble has one set of walls (run them apart)")
        geometry = with_geometry_parameters(geometry, dict(next(iter(boxes), ())), source)
        sets, properties = [], []
        for m in merged:
            full = {k: v for k, v in m.items() if not k.startswith(GEOMETRY_PREFIX)}
            contact, props = split_material_parameters(full, mixture, source)
            sets.append(contact)
            properties.append(props)
        kept = sorted({f"fines_kept_{name}" for props in properties for name, p in props.items() if "fines_kept" in p})
        if kept and settings.fines_cut is None:
            raise ConfigError(f"{source}: {', '.join(kept)} set a share of the scalped fines, but the runs scalp none "
                              "(sim.fines_cut_mm is null: every sieve class is kept already)")
        mixtures = None
        if any(properties):
            mixtures = [with_material_properties(mixture, props, source) for props in properties]
        return DrawDownTest(mixture, geometry, sets, settings, mixtures=mixtures)


def split_material_parameters(params: Mapping[str, float], mixture: Mixture, source: str
                              ) -> tuple[dict[str, float], dict[str, dict[str, float]]]:
    """``(contact parameters, {material: {property: value}})`` of a parameter set: the per-material
    parameters ``density_<material>`` (solid density, kg/m^3), ``lobe_spacing_<material>``
    (trilobe clump shape, :func:`torchdem.mixture.trilobe_template`, in (0, 0.3] of the sieve size)
    ``clump_scale_<material>`` (the trilobe's size, (0.5, 2] of the clump that fits the sieve
    size), ``lobe_count_<material>`` (3 or 4) and ``fines_kept_<material>`` (the share of the fines below
    ``sim.fines_cut_mm`` kept as sieved, [0, 1]) are taken out; everything else is a contact parameter."""
    names = {m.name for m in mixture.materials}
    contact: dict[str, float] = {}
    material: dict[str, dict[str, float]] = {}
    for key, value in params.items():
        prefix = next((p for p in MATERIAL_PREFIXES if key.startswith(p)), None)
        if prefix is None:
            contact[key] = value
            continue
        name = key[len(prefix):]
        if name not in names:
            raise ConfigError(f"{source}: parameter {key!r} names no material of mixture {mixture.name!r}; "
                              f"expected {prefix}<material> with a material of {sorted(names)}")
        low, high, open_low, allowed, values = MATERIAL_PREFIXES[prefix]
        above = low < value if open_low else low <= value
        if not (math.isfinite(value) and above and value <= high) or (values is not None and value not in values):
            raise ConfigError(f"{source}: {key} = {value!r} is not allowed; expected {allowed}")
        material.setdefault(name, {})[prefix[:-1]] = float(value)
    return contact, material


def split_density(params: Mapping[str, float], mixture: Mixture, source: str
                  ) -> tuple[dict[str, float], dict[str, float]]:
    """``(contact parameters, {material: density kg/m^3})`` (other material parameters are refused)."""
    contact, material = split_material_parameters(params, mixture, source)
    other = sorted(k for props in material.values() for k in props if k != "density")
    if other:
        raise ConfigError(f"{source}: split_density got material parameters {other}; use split_material_parameters")
    return contact, {m: props["density"] for m, props in material.items()}


def with_material_properties(mixture: Mixture, properties: Mapping[str, Mapping[str, float]],
                             source: str = "with_material_properties") -> Mixture:
    """The mixture with the given materials' densities, trilobe lobe spacings, clump scales and kept
    fines replaced (a scale alone keeps the material's lobe spacing, a spacing alone its scale). A scale
    for a material that is no trilobe and gets no lobe spacing is a ConfigError naming ``source``."""
    materials = []
    for m in mixture.materials:
        props = properties.get(m.name, {})
        changes = {}
        for field_name in ("density", "fines_kept"):
            if field_name in props:
                changes[field_name] = props[field_name]
        if "lobe_spacing" in props or "clump_scale" in props or "lobe_count" in props:
            lobes, spacing, scale = lobed_parameters(m.shape) or (3, None, 1.0)
            if "lobe_spacing" not in props and spacing is None:
                given = next(f"{k}_{m.name} = {props[k]!r}" for k in ("clump_scale", "lobe_count") if k in props)
                raise ConfigError(f"{source}: {given} changes a lobed clump, but material {m.name!r} is a "
                                  f"{m.shape!r}; give lobe_spacing_{m.name} too, or leave it out")
            changes["shape"] = lobe_shape(int(props.get("lobe_count", lobes)), props.get("lobe_spacing", spacing),
                                          props.get("clump_scale", scale))
        materials.append(dataclasses.replace(m, **changes) if changes else m)
    return dataclasses.replace(mixture, materials=tuple(materials))


def variant(condition: str, **changes: float | str | bool | None) -> str:
    """Condition name with run-setting or geometry variants, e.g. ``variant("50-50",
    time_step_fraction=0.2)``, ``variant("50-50", dtype="float32")`` or ``variant("50-50",
    slice_depth=0.1, mirror=True)`` (numbers, flags and None by ``repr``, names as they are)."""
    allowed = sorted({**_VARIANT_FIELDS, **_GEOMETRY_FIELDS})
    for k, v in changes.items():
        if k not in _VARIANT_FIELDS and k not in _GEOMETRY_FIELDS:
            raise ConfigError(f"variant: {k!r} is not a setting a study may vary; allowed: {allowed}")
        if _VARIANT_FIELDS.get(k) is str and (not isinstance(v, str) or any(c in v for c in "|=")):
            raise ConfigError(f"variant: {k} = {v!r} is not allowed; expected a name without '|' or '='")
        if k == "mirror" and not isinstance(v, bool):
            raise ConfigError(f"variant: mirror = {v!r} is not allowed; expected True or False")
    return "|".join([condition] + [f"{k}={v if _VARIANT_FIELDS.get(k) is str else repr(v)}"
                                   for k, v in sorted(changes.items())])


def _variant_parts(condition: str) -> tuple[str, dict[str, object], dict[str, object]]:
    """Base name, run-setting changes and geometry changes of a condition name."""
    base, *parts = condition.split("|")
    settings, geometry = {}, {}
    for part in parts:
        key, sep, value = part.partition("=")
        kind = _VARIANT_FIELDS if key in _VARIANT_FIELDS else _GEOMETRY_FIELDS
        if not sep or key not in kind:
            raise ConfigError(f"condition {condition!r}: variant {part!r} is not <field>=<value> with a field of "
                              f"{sorted({**_VARIANT_FIELDS, **_GEOMETRY_FIELDS})}")
        try:
            (settings if kind is _VARIANT_FIELDS else geometry)[key] = kind[key](value)
        except ValueError:
            raise ConfigError(f"condition {condition!r}: {key} = {value!r} is not a number (or None, True, False "
                              "where the field allows)") from None
    return base, settings, geometry


def split_condition(condition: str, settings: RunSettings) -> tuple[str, RunSettings]:
    """Base condition name and the run settings with the variant's fields replaced."""
    base, changes, _ = _variant_parts(condition)
    return base, dataclasses.replace(settings, **changes).validate(f"condition {condition!r}")


def condition_geometry(condition: str, geometry: DrawDownGeometry) -> DrawDownGeometry:
    """The geometry with the condition's geometry variants (``slice_depth``, ``mirror``) replaced;
    a full box (``slice_depth=None``) or a mirror drops ``slice_walls``."""
    _, _, changes = _variant_parts(condition)
    if not changes:
        return geometry
    if changes.get("slice_depth", geometry.slice_depth) is None or changes.get("mirror"):
        changes["slice_walls"] = False
    return dataclasses.replace(geometry, **changes).validate(f"condition {condition!r}")


def mixtures_from_measured(data: MeasuredData, materials: Mapping[str, ParticleMaterial],
                           total_mass: float | None = None, layers_source: str = "measured data"
                           ) -> dict[str, Mixture]:
    """Mixture of every condition (fractions and layering from the data, materials given)."""
    out = {}
    for name in data.names:
        c = data.condition(name)
        fractions = c.mass_fractions()
        missing = [m for m in fractions if m not in materials]
        if missing:
            raise ConfigError(f"{layers_source}: condition {name!r} uses materials {missing} that the model does not "
                              f"define; defined: {sorted(materials)}")
        used = [m for m, f in fractions.items() if f > 0]
        mass = total_mass if total_mass is not None else (c.fill_mass_kg or 40.0)
        out[name] = Mixture(f"{name}", tuple(materials[m] for m in used), tuple(fractions[m] for m in used),
                            tuple(c.layering), mass).validate(f"{layers_source}: condition {name!r}")
    return out


