"""Typed objects from plain config mappings (what the Hydra apps hand over after
``OmegaConf.to_container``). The only place that knows the YAML layout of ``conf/``; library
code takes the typed objects. Every missing or bad key raises :class:`ConfigError` naming the
key path (``mixture.materials.sinter.sieve[2].d_max_mm``) and the allowed range.
"""
from __future__ import annotations

import math
from typing import Any, Mapping

from torchdem.drawdown import RunSettings
from torchdem.errors import ConfigError, out_of_range
from torchdem.geometry import DrawDownGeometry
from torchdem.mixture import TEMPLATES, Mixture, ParticleMaterial, SieveClass
from torchdem.simulation import GuardSettings

_MISSING = object()


def _get(cfg: Mapping[str, Any], key: str, where: str, default: Any = _MISSING) -> Any:
    if not isinstance(cfg, Mapping):
        raise ConfigError(f"{where}: expected a mapping of keys, got {cfg!r}")
    if key not in cfg:
        if default is _MISSING:
            raise ConfigError(f"{where}.{key} is missing; known keys: {sorted(cfg)}")
        return default
    return cfg[key]


def _number(cfg: Mapping[str, Any], key: str, where: str, low: float = -math.inf, high: float = math.inf,
            default: Any = _MISSING, allowed: str | None = None, open_low: bool = False) -> float | None:
    value = _get(cfg, key, where, default)
    if value is None and default is None:
        return None
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"config: {where}.{key} = {value!r} is not a number") from None
    ok = math.isfinite(x) and (x > low if open_low else x >= low) and x <= high
    if not ok:
        rng = allowed or f"{'(' if open_low else '['}{low}, {high}]"
        raise out_of_range(f"{where}.{key}", value, rng, "config")
    return x


def material_from(cfg: Mapping[str, Any], where: str) -> ParticleMaterial:
    """A :class:`ParticleMaterial` from ``{name, shape, label, density_kg_m3, shear_modulus_pa,
    poisson_ratio, sieve: [{d_min_mm, d_max_mm, mass_fraction}, ...]}``."""
    shape = str(_get(cfg, "shape", where))
    if shape not in TEMPLATES:
        raise ConfigError(f"{where}.shape = {shape!r}; expected one of {sorted(TEMPLATES)}")
    rows = _get(cfg, "sieve", where)
    if not isinstance(rows, (list, tuple)) or not rows:
        raise ConfigError(f"{where}.sieve must be a non-empty list of {{d_min_mm, d_max_mm, mass_fraction}}")
    sieve = []
    for k, row in enumerate(rows):
        w = f"{where}.sieve[{k}]"
        d_min = _number(row, "d_min_mm", w, 0.0, open_low=True, allowed="> 0 mm")
        d_max = _number(row, "d_max_mm", w, d_min, open_low=True, allowed=f"> d_min_mm = {d_min} mm")
        sieve.append(SieveClass(d_min / 1000.0, d_max / 1000.0, _number(row, "mass_fraction", w, 0.0, 1.0)))
    material = ParticleMaterial(
        name=str(_get(cfg, "name", where)), shape=shape, sieve=tuple(sieve),
        density=_number(cfg, "density_kg_m3", where, 0.0, open_low=True, allowed="> 0 kg/m^3"),
        shear_modulus=_number(cfg, "shear_modulus_pa", where, 0.0, open_low=True, allowed="> 0 Pa"),
        poisson_ratio=_number(cfg, "poisson_ratio", where, -1.0, 0.5, open_low=True, allowed="(-1, 0.5)"),
        label=str(_get(cfg, "label", where, "")))
    return material.validate(where)


def mixture_from(cfg: Mapping[str, Any], where: str = "mixture") -> Mixture:
    """A :class:`Mixture` from ``{name, total_mass_kg, mass_fractions: {material: f},
    layering: [material, ...], materials: {key: material config}}`` (materials may be listed
    that the mixture does not use; every material in ``mass_fractions`` must be defined)."""
    materials_cfg = _get(cfg, "materials", where)
    fractions_cfg = _get(cfg, "mass_fractions", where)
    if not isinstance(fractions_cfg, Mapping) or not fractions_cfg:
        raise ConfigError(f"{where}.mass_fractions must map material names to mass fractions, got {fractions_cfg!r}")
    by_name = {}
    for key, mcfg in materials_cfg.items():
        m = material_from(mcfg, f"{where}.materials.{key}")
        by_name[m.name] = m
    names = list(fractions_cfg)
    unknown = [n for n in names if n not in by_name]
    if unknown:
        raise ConfigError(f"{where}.mass_fractions names {unknown}, which {where}.materials does not define; "
                          f"defined: {sorted(by_name)}")
    fractions = tuple(_number(fractions_cfg, n, f"{where}.mass_fractions", 0.0, 1.0) for n in names)
    layering = _get(cfg, "layering", where)
    if isinstance(layering, str) or not isinstance(layering, (list, tuple)) or not layering:
        raise ConfigError(f"{where}.layering must be a non-empty list of material names, bottom to top")
    mixture = Mixture(str(_get(cfg, "name", where)), tuple(by_name[n] for n in names), fractions,
                      tuple(str(x) for x in layering),
                      _number(cfg, "total_mass_kg", where, 0.0, open_low=True, allowed="> 0 kg"))
    return mixture.validate(where)


def geometry_from(cfg: Mapping[str, Any], where: str = "geometry") -> DrawDownGeometry:
    """A :class:`DrawDownGeometry` from the ``*_m`` keys of ``conf/geometry`` (and ``gate_opening_s``)."""
    fields = ("upper_width", "depth", "upper_height", "outlet_width", "upper_bottom_z", "lower_width", "lower_height")
    values = {f: _number(cfg, f + "_m", where, 0.0, open_low=True, allowed="a length > 0 m") for f in fields}
    values["slice_depth"] = _number(cfg, "slice_depth_m", where, 0.0, open_low=True, default=None,
                                    allowed="a length > 0 m or null")
    mirror = cfg.get("mirror", False)
    if not isinstance(mirror, bool):
        raise ConfigError(f"{where}: mirror = {mirror!r} is not allowed; expected true or false (a frictionless "
                          "elastic symmetry plane at the slice's back face)")
    values["mirror"] = mirror
    opening = _number(cfg, "gate_opening_s", where, 0.0, default=None,
                      allowed="a time >= 0 s or null (null or 0: the gate vanishes at once)")
    values["gate_opening"] = 0.0 if opening is None else opening
    return DrawDownGeometry(**values).validate(where)


#: Allowed range of a contact parameter by the prefix of its name: (low, high, open low, text).
CONTACT_RANGES = {"mu_s_": (0.0, math.inf, False, "a sliding friction coefficient >= 0"),
                  "mu_r_": (0.0, math.inf, False, "a rolling friction coefficient >= 0"),
                  "e_": (0.0, 1.0, True, "a restitution coefficient in (0, 1]"),
                  "coh_": (0.0, math.inf, False, "a cohesion energy density >= 0 J/m^3"),
                  "eta_r": (0.0, 1.0, False, "a rolling damping ratio in [0, 1]")}


def parameter_range(name: str) -> tuple[float, float, bool, str]:
    """``(low, high, open low, allowed text)`` of a named model parameter by its prefix: the
    contact parameters of :data:`CONTACT_RANGES` and the material parameters of
    :data:`torchdem.model.MATERIAL_PREFIXES` (``density_<m>``, ``lobe_spacing_<m>``), the box lengths
    ``geometry_<field>`` (> 0 m) and the gate's opening time ``geometry_gate_opening`` (>= 0 s); any
    number for other names."""
    from torchdem.model import GEOMETRY_PREFIX, MATERIAL_PREFIXES, geometry_parameter_range

    contact = next((p for p in CONTACT_RANGES if name.startswith(p)), None)
    if contact is not None:
        return CONTACT_RANGES[contact]
    material = next((p for p in MATERIAL_PREFIXES if name.startswith(p)), None)
    if material is not None:
        low, high, open_low, allowed, _ = MATERIAL_PREFIXES[material]
        return low, high, open_low, allowed
    if name.startswith(GEOMETRY_PREFIX):
        low, open_low, allowed = geometry_parameter_range(name)
        return low, math.inf, open_low, allowed
    return -math.inf, math.inf, False, "a number"


def _ranged(cfg: Mapping[str, Any], key: str, where: str, name: str | None = None) -> float:
    """``cfg[key]`` checked against :func:`parameter_range` of ``name`` (default ``key``)."""
    low, high, open_low, allowed = parameter_range(name or key)
    return _number(cfg, key, where, low, high, open_low=open_low, allowed=allowed)


def contact_from(cfg: Mapping[str, Any], where: str = "contact") -> dict[str, float]:
    """Named contact parameters (``mu_s_pp: 0.49`` ...), each checked against the range its
    prefix allows (:data:`CONTACT_RANGES`); the error names the key, e.g. ``contact.mu_s_pp``."""
    out = {str(k): _ranged(cfg, k, where, str(k)) for k in cfg}
    if not out:
        raise ConfigError(f"{where}: no contact parameters given")
    return out


def single_contact_from(cfg: Mapping[str, Any], where: str = "contact") -> dict[str, float]:
    """The one contact law of a single-material config (``torchdem-demo``): ``mu_s``, ``mu_r``,
    ``restitution``, ``rolling_damping``, each range-checked with its config key in the error."""
    return {key: _ranged(cfg, key, where, name) for key, name in
            (("mu_s", "mu_s_"), ("mu_r", "mu_r_"), ("restitution", "e_"), ("rolling_damping", "eta_r"))}


def guards_from(cfg: Mapping[str, Any], where: str = "sim.guards") -> GuardSettings:
    return GuardSettings(check_every=int(_get(cfg, "check_every", where)),
                         max_speed=_number(cfg, "max_speed", where, 0.0, open_low=True),
                         energy_tolerance=_number(cfg, "energy_tolerance", where, 0.0, open_low=True),
                         on_blowup=str(_get(cfg, "on_blowup", where))).validate(where)


def run_settings_from(sim: Mapping[str, Any], run: Mapping[str, Any]) -> RunSettings:
    """:class:`RunSettings` from the ``sim`` group (engine and model reductions) and the
    ``run`` block (procedure: fill and discharge times, load cell, rendering)."""
    fines = _number(sim, "fines_cut_mm", "sim", 0.0, open_low=True, default=None, allowed="> 0 mm or null")
    return RunSettings(
        fill_time=_number(run, "fill_time_s", "run", 0.0, open_low=True, allowed="> 0 s"),
        discharge_time=_number(run, "discharge_time_s", "run", 0.0, open_low=True, allowed="> 0 s"),
        max_discharge_time=_number(run, "max_discharge_time_s", "run", 0.0, open_low=True, default=None,
                                   allowed="> 0 s or null"),
        flow_window=tuple(_number({"v": v}, "v", "run.flow_window_s", 0.0) for v in _get(run, "flow_window_s", "run",
                                                                                          [0.5, 2.0])),
        final_window=_number(run, "final_window_s", "run", 0.0, open_low=True, default=0.5, allowed="> 0 s"),
        loadcell_rate=_number(run, "loadcell_rate_hz", "run", 0.0, open_low=True, allowed="> 0 Hz"),
        time_step_fraction=_number(sim, "time_step_fraction", "sim", 0.0, 1.0, open_low=True,
                                   allowed="(0, 1] of the Rayleigh time step"),
        discharge_time_step_fraction=_number(sim, "discharge_time_step_fraction", "sim", 0.0, 1.0, open_low=True,
                                             default=None, allowed="(0, 1] of the Rayleigh time step or null"),
        shear_modulus=_number(sim, "shear_modulus_pa", "sim", 0.0, open_low=True, default=None,
                              allowed="> 0 Pa or null"),
        rolling_damping=_number(run, "rolling_damping", "run", 0.0, 1.0),
        dtype=str(_get(sim, "dtype", "sim")),
        compile=bool(_get(sim, "compile", "sim")),
        guards=guards_from(_get(sim, "guards", "sim")),
        metres_per_pixel=_number(run, "metres_per_pixel", "run", 0.0, open_low=True, allowed="> 0 m"),
        rsd_component=str(_get(run, "rsd_component", "run")),
        photo_shadow_depth=_number(run, "photo_shadow_depth_m", "run", 0.0, open_low=True, default=None,
                                   allowed="> 0 m behind the front layer, or null (no shadows)"),
        loose_fraction=_number(run, "loose_fraction", "run", 0.0, 0.6, open_low=True),
        fines_cut=None if fines is None else fines / 1000.0,
        skin_fraction=_number(sim, "skin_fraction", "sim", 0.0, 2.0, open_low=True, default=0.2,
                              allowed="(0, 2] of the largest sphere radius"),
        reorder_every=int(_number(sim, "reorder_every", "sim", 0.0, default=0,
                                  allowed="an int >= 0 (neighbour rebuilds between spatial reorders; 0: never)")),
        fill_packing=str(run.get("fill_packing", "bounding")),
        retry_time_steps=_tuple(sim.get("retry_time_steps", [])),
    ).validate("sim/run")


def _tuple(value: Any) -> Any:
    """A config list as a tuple (anything else as given, for the settings' check to name)."""
    return tuple(value) if isinstance(value, (list, tuple)) else value


def extension_from(cfg: Mapping[str, Any] | None, where: str = "extension") -> tuple[str | None, dict[str, float]]:
    """``(mechanism name or None, values)`` of the ``extension`` block (conf/extension/); apply it
    with :func:`torchdem.mechanisms.with_extension`."""
    ext = cfg or {}
    if not isinstance(ext, Mapping):
        raise out_of_range(where, ext, "a mapping {name, values} (conf/extension/)", "config")
    name, values = ext.get("name"), ext.get("values") or {}
    if name is not None and not isinstance(name, str):
        raise out_of_range(f"{where}.name", name, "a mechanism name of torchdem/mechanisms/ or null", "config")
    if not isinstance(values, Mapping):
        raise out_of_range(f"{where}.values", values, "a mapping parameter -> number", "config")
    return name, {str(k): _ranged(values, k, f"{where}.values", str(k)) for k in values}
