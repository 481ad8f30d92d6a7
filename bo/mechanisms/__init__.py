"""Candidate model extensions for model discovery: a registry of named physical mechanisms.

Contract
--------
Every module in this package defines ``MECHANISM``, a :class:`Mechanism`; :func:`registry`
imports them all (``pkgutil``), so adding a candidate is one small file here. A mechanism is

* ``name``: its registry name (the module's name), ``description``: the physics in words;
* ``parameters(context) -> {name: (low, high)}``: its extra task parameters with their prior
  ranges, given the :class:`ModelContext` (materials, nominal densities, calibrated contact
  parameters, effective stiffness); the names are those ``bo.dem`` evaluates (contact
  parameters such as ``mu_s_ps`` or ``coh_pp``, ``density_<material>``,
  ``lobe_spacing_<material>``, ``eta_r``);
* ``apply(model) -> model``: what else the mechanism changes in a ``bo.dem.DrawDownModel``
  (run settings, geometry); the identity for pure-parameter mechanisms;
* ``available(context) -> str | None``: why it cannot apply to this model (None: it can).

Mechanisms never see a DictConfig; ``bo.cli_discover`` and the ``extension`` config group apply
a chosen mechanism with its fitted values to any command's model (:func:`apply_extension`).
"""
from __future__ import annotations

import dataclasses
import importlib
import pkgutil
from dataclasses import dataclass, field
from typing import Callable, Mapping

from torchdem.errors import ConfigError

__all__ = ["Mechanism", "ModelContext", "registry", "get", "apply_extension"]


@dataclass(frozen=True)
class ModelContext:
    """What a mechanism may look at to set its prior ranges.

    Attributes:
        materials: particle material names, in mixture order.
        letters: one-letter abbreviation of each material (``{"pellet": "p", ...}``).
        densities: nominal solid density per material, kg/m^3.
        shapes: shape key per material (``"sphere"``, ``"sinter_trilobe"``, ``"trilobe_s0.2000"``).
        calibrated: the calibrated contact parameters (``mu_s_pp``, ...).
        young_eff: effective Young's modulus E* of a particle-particle contact, Pa.
        periodic_slice: the model is a periodic slice (no front and back walls).
        period: the slice's period (its depth) when ``periodic_slice``, else None, m.
        largest_size: largest sieve size per material, m.
    """

    materials: tuple[str, ...]
    letters: Mapping[str, str]
    densities: Mapping[str, float]
    shapes: Mapping[str, str]
    calibrated: Mapping[str, float]
    young_eff: float
    periodic_slice: bool
    period: float | None = None
    largest_size: Mapping[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Mechanism:
    """A candidate model extension (see the module docstring)."""

    name: str
    description: str
    parameters: Callable[[ModelContext], Mapping[str, tuple[float, float]]]
    apply: Callable = field(default=lambda model: model)
    available: Callable[[ModelContext], str | None] = field(default=lambda context: None)


def registry() -> dict[str, Mechanism]:
    """Every mechanism of this package, by name (sorted)."""
    found = {}
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{__name__}.{info.name}")
        mechanism = getattr(module, "MECHANISM", None)
        if not isinstance(mechanism, Mechanism):
            raise ConfigError(f"bo/mechanisms/{info.name}.py defines no MECHANISM = Mechanism(...)")
        if mechanism.name != info.name:
            raise ConfigError(f"bo/mechanisms/{info.name}.py: MECHANISM.name = {mechanism.name!r}; expected the "
                              f"module's name {info.name!r}")
        found[mechanism.name] = mechanism
    return found


def get(name: str, source: str = "extension") -> Mechanism:
    """The mechanism ``name``; an unknown name is a ConfigError listing the known ones."""
    mechanisms = registry()
    if name not in mechanisms:
        raise ConfigError(f"{source}: mechanism {name!r} is not in the registry (bo/mechanisms/); known: "
                          f"{sorted(mechanisms)}")
    return mechanisms[name]


def apply_extension(model, name: str | None, values: Mapping[str, float], context: ModelContext,
                    source: str = "extension"):
    """``model`` with mechanism ``name`` switched on at ``values`` (its parameters join the fixed
    ones); ``name`` None returns the model unchanged. Values must be inside the prior ranges'
    names (a value for a parameter the mechanism does not have is an error)."""
    if name is None:
        if values:
            raise ConfigError(f"{source}: values {dict(values)} given without a mechanism name")
        return model
    mechanism = get(name, source)
    why = mechanism.available(context)
    if why is not None:
        raise ConfigError(f"{source}: mechanism {name!r} cannot apply to this model: {why}")
    known = mechanism.parameters(context)
    unknown = sorted(set(values) - set(known))
    missing = sorted(set(known) - set(values))
    if unknown or missing:
        raise ConfigError(f"{source}: mechanism {name!r} has parameters {sorted(known)}; unknown {unknown}, "
                          f"missing {missing}")
    model = mechanism.apply(model)
    return dataclasses.replace(model, fixed={**model.fixed, **{k: float(v) for k, v in values.items()}})
