"""Candidate model extensions for model discovery: a registry of named physical mechanisms.

Contract
--------
Every module in this package defines ``MECHANISM``, a :class:`Mechanism`; :func:`registry`
imports them all (``pkgutil``), so adding a candidate is one small file here. A mechanism is

* ``name``: its registry name (the module's name), ``description``: the physics in words;
* ``parameters(context) -> {name: (low, high)}``: its extra task parameters with their prior
  ranges, given the :class:`ModelContext` (materials, nominal densities, calibrated contact
  parameters, effective stiffness); the names are those ``torchdem.model`` evaluates (contact
  parameters such as ``mu_s_ps`` or ``coh_pp``, ``density_<material>``,
  ``lobe_spacing_<material>``, ``eta_r``, the box lengths ``geometry_<field>``);
* ``apply(model) -> model``: what else the mechanism changes in a ``torchdem.model.DrawDownModel``
  (run settings, geometry); the identity for pure-parameter mechanisms;
* ``available(context) -> str | None``: why it cannot apply to this model (None: it can).

Mechanisms never see a DictConfig. A mechanism changes the model, so it lives on the model's side:
every command applies the ``extension`` config group through :func:`with_extension`
(``torchdem.config.extension_from`` reads the block), and ``torchdem-discover`` scores them.
"""
from __future__ import annotations

import dataclasses
import importlib
import pkgutil
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Mapping, Sequence

from torchdem.errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover
    from torchdem.model import DrawDownModel

__all__ = ["Mechanism", "ModelContext", "registry", "get", "model_context", "apply_extension", "with_extension"]


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
        geometry: the boxes' lengths a task may set (``torchdem.model.GEOMETRY_PARAMETERS``:
            ``outlet_width`` ...), m.
        smallest_size: smallest sieve size per material, as measured (before any scalping), m.
        fines_cut: the sieve size below which the runs scalp the fines (``sim.fines_cut_mm``), m;
            None: the sieve as measured.
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
    geometry: Mapping[str, float] = field(default_factory=dict)
    smallest_size: Mapping[str, float] = field(default_factory=dict)
    fines_cut: float | None = None


@dataclass(frozen=True)
class Mechanism:
    """A candidate model extension (see the module docstring)."""

    name: str
    description: str
    parameters: Callable[[ModelContext], Mapping[str, tuple[float, float]]]
    apply: Callable = field(default=lambda model: model)
    available: Callable[[ModelContext], str | None] = field(default=lambda context: None)
    #: The parameter values at which the mechanism changes nothing (None: it has none, e.g. a model
    #: switch); discovery measures from there how large an effect the data could have detected.
    null: Callable[[ModelContext], Mapping[str, float] | None] = field(default=lambda context: None)


def registry() -> dict[str, Mechanism]:
    """Every mechanism of this package, by name (sorted)."""
    found = {}
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{__name__}.{info.name}")
        mechanism = getattr(module, "MECHANISM", None)
        if not isinstance(mechanism, Mechanism):
            raise ConfigError(f"torchdem/mechanisms/{info.name}.py defines no MECHANISM = Mechanism(...)")
        if mechanism.name != info.name:
            raise ConfigError(f"torchdem/mechanisms/{info.name}.py: MECHANISM.name = {mechanism.name!r}; expected the "
                              f"module's name {info.name!r}")
        found[mechanism.name] = mechanism
    return found


def get(name: str, source: str = "extension") -> Mechanism:
    """The mechanism ``name``; an unknown name is a ConfigError listing the known ones."""
    mechanisms = registry()
    if name not in mechanisms:
        raise ConfigError(f"{source}: mechanism {name!r} is not in the registry (torchdem/mechanisms/); known: "
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


def model_context(model: "DrawDownModel", calibrated: Mapping[str, float]) -> ModelContext:
    """What the mechanisms see of ``model`` (first condition's materials)."""
    import torch

    from torchdem.materials import effective_young_modulus
    from torchdem.model import GEOMETRY_PARAMETERS

    mixture = next(iter(model.conditions.values()))
    names = tuple(m.name for m in mixture.materials)
    letters = ({"pellet": "p", "sinter": "s"} if set(names) <= {"pellet", "sinter"} else
               {n: a for a, n in _letters_of(names).items()})
    m0 = mixture.materials[0]
    G = model.settings.shear_modulus if model.settings.shear_modulus is not None else m0.shear_modulus
    E = 2 * G * (1 + m0.poisson_ratio)
    e_eff = float(effective_young_modulus(torch.tensor(E), torch.tensor(m0.poisson_ratio), torch.tensor(E),
                                          torch.tensor(m0.poisson_ratio)))
    periodic = model.geometry.periodic[1]
    return ModelContext(materials=names, letters=letters, densities={m.name: m.density for m in mixture.materials},
                        shapes={m.name: m.shape for m in mixture.materials}, calibrated=dict(calibrated),
                        young_eff=e_eff, periodic_slice=periodic, period=model.geometry.slice_depth if periodic else None,
                        largest_size={m.name: max(c.d_max for c in m.sieve) for m in mixture.materials},
                        geometry={n: float(getattr(model.geometry, n)) for n in GEOMETRY_PARAMETERS},
                        smallest_size={m.name: min(c.d_min for c in m.sieve) for m in mixture.materials},
                        fines_cut=model.settings.fines_cut)


def _letters_of(names: Sequence[str]) -> dict[str, str]:
    from torchdem.drawdown import _letters

    return {k: v for k, v in _letters(names, "geometry").items() if k != "g"}


def with_extension(model: "DrawDownModel", name: str | None, values: Mapping[str, float],
                   source: str = "extension") -> "DrawDownModel":
    """``model`` with mechanism ``name`` switched on at ``values``, its prior ranges set by the
    model's own fixed parameters (the ``extension`` config group of every command)."""
    if name is None and not values:
        return model
    return apply_extension(model, name, values, model_context(model, model.fixed), source=source)
