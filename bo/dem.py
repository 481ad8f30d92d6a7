"""DEM evaluations of draw down tests for calibration: the ``evaluate_batch`` of the executors.

Contract:
- :class:`DrawDownModel` is everything a DEM evaluation needs besides the varied contact
  parameters and the seed: the mixture of every condition, the geometry, the run settings,
  the contact parameters that stay fixed, the device. It is a frozen, picklable dataclass, so
  ``functools.partial(evaluate_batch, model)`` ships to dask workers.
- :func:`evaluate_batch` runs a batch of :class:`~bo.executor.EvalTask` of one condition as
  one batched ensemble (:meth:`torchdem.drawdown.DrawDownTest.run_members`): every distinct
  parameter set is a parameter set of the test, every task a member with its own seed. It
  returns one :class:`~bo.executor.EvalOutcome` per task with every KPI of
  :data:`torchdem.drawdown.KPI_UNITS` (NaN where the lab method could not measure it, e.g. no
  heap edge) and the wall time of the batch. The blow-up guard runs in isolate mode: a member
  that blows up is frozen and fails alone, with the guard's message. A member whose ensemble
  cannot be built (its fill overflows the column, its clump is too large for a periodic slice)
  fails alone too: when the ensemble's build fails, every member is built by itself, those
  that fail get their own error, and the others run as one ensemble. Bad input common to the
  batch fails the whole batch with the message.
- A condition name may carry run-setting variants after ``|``:
  ``"50-50|time_step_fraction=0.2|shear_modulus=1e7"`` runs the 50-50 mixture with those
  :class:`~torchdem.drawdown.RunSettings` fields replaced (the time-step and stiffness
  studies store their runs this way, so they resume like any other campaign stage).
- A task parameter ``density_<material>`` (kg/m^3) is not a contact parameter: it replaces that
  material's solid density in the mixture of the task's parameter set (bulk-density
  recalibration, section 3.6 of the paper, and density as a calibration parameter, which the
  paper recommends); ``lobe_spacing_<material>`` makes that material a trilobe clump of that
  lobe spacing (:func:`torchdem.mixture.trilobe_template`). Such parameter sets run in one
  ensemble with per-member mixtures.
- :func:`mixtures_from_measured` builds the mixture of every condition of a measured-data file
  (:mod:`torchdem.measured`) from the materials the model uses.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from bo.executor import EvalOutcome, EvalTask
from torchdem.drawdown import KPI_UNITS, DrawDownTest, RunSettings
from torchdem.errors import BlowUpError, ConfigError
from torchdem.geometry import DrawDownGeometry
from torchdem.measured import MeasuredData
from torchdem.mixture import Mixture, ParticleMaterial, trilobe_shape

#: Prefix of task parameters that set a material's solid density (kg/m^3), not a contact law.
DENSITY_PREFIX = "density_"
#: Per-material task parameters: prefix -> (exclusive low, inclusive high, allowed range text).
MATERIAL_PREFIXES = {DENSITY_PREFIX: (0.0, math.inf, "a solid density > 0 kg/m^3"),
                     "lobe_spacing_": (0.0, 0.3, "a trilobe lobe spacing in (0, 0.3] of the sieve size")}

_VARIANT_FIELDS = {"time_step_fraction": float, "shear_modulus": float, "fines_cut": float,
                   "rolling_damping": float, "loose_fraction": float}


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

    def test_for(self, condition: str, parameter_sets: Sequence[Mapping[str, float]]) -> DrawDownTest:
        """The :class:`DrawDownTest` of a (possibly variant) condition with these parameter sets."""
        base, settings = split_condition(condition, self.settings)
        # a blow-up fails that member only (its outcome says why), not the whole ensemble
        settings = dataclasses.replace(settings, guards=dataclasses.replace(settings.guards, on_blowup="isolate"))
        if base not in self.conditions:
            raise ConfigError(f"condition {base!r} is not part of the model; known: {sorted(self.conditions)}")
        mixture = self.conditions[base]
        sets, properties = [], []
        for p in parameter_sets:
            contact, props = split_material_parameters({**self.fixed, **p}, mixture, f"condition {condition!r}")
            sets.append(contact)
            properties.append(props)
        mixtures = None
        if any(properties):
            mixtures = [with_material_properties(mixture, props) for props in properties]
        return DrawDownTest(mixture, self.geometry, sets, settings, mixtures=mixtures)


def split_material_parameters(params: Mapping[str, float], mixture: Mixture, source: str
                              ) -> tuple[dict[str, float], dict[str, dict[str, float]]]:
    """``(contact parameters, {material: {property: value}})`` of a parameter set: the per-material
    parameters ``density_<material>`` (solid density, kg/m^3) and ``lobe_spacing_<material>``
    (trilobe clump shape, :func:`torchdem.mixture.trilobe_template`, in (0, 0.3] of the sieve size)
    are taken out; everything else is a contact parameter."""
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
        low, high, allowed = MATERIAL_PREFIXES[prefix]
        if not (math.isfinite(value) and low < value <= high):
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


def with_material_properties(mixture: Mixture, properties: Mapping[str, Mapping[str, float]]) -> Mixture:
    """The mixture with the given materials' densities and trilobe lobe spacings replaced."""
    materials = []
    for m in mixture.materials:
        props = properties.get(m.name, {})
        changes = {}
        if "density" in props:
            changes["density"] = props["density"]
        if "lobe_spacing" in props:
            changes["shape"] = trilobe_shape(props["lobe_spacing"])
        materials.append(dataclasses.replace(m, **changes) if changes else m)
    return dataclasses.replace(mixture, materials=tuple(materials))


def with_densities(mixture: Mixture, density: Mapping[str, float]) -> Mixture:
    """The mixture with the given materials' solid densities replaced."""
    return with_material_properties(mixture, {m: {"density": rho} for m, rho in density.items()})


def variant(condition: str, **changes: float) -> str:
    """Condition name with run-setting variants, e.g. ``variant("50-50", time_step_fraction=0.2)``."""
    for k in changes:
        if k not in _VARIANT_FIELDS:
            raise ConfigError(f"variant: {k!r} is not a run setting a study may vary; allowed: {sorted(_VARIANT_FIELDS)}")
    return "|".join([condition] + [f"{k}={changes[k]!r}" for k in sorted(changes)])


def split_condition(condition: str, settings: RunSettings) -> tuple[str, RunSettings]:
    """Base condition name and the run settings with the variant's fields replaced."""
    base, *parts = condition.split("|")
    changes = {}
    for part in parts:
        key, sep, value = part.partition("=")
        if not sep or key not in _VARIANT_FIELDS:
            raise ConfigError(f"condition {condition!r}: variant {part!r} is not <field>=<value> with a field of "
                              f"{sorted(_VARIANT_FIELDS)}")
        try:
            changes[key] = _VARIANT_FIELDS[key](value)
        except ValueError:
            raise ConfigError(f"condition {condition!r}: {key} = {value!r} is not a number") from None
    return base, dataclasses.replace(settings, **changes).validate(f"condition {condition!r}")


def evaluate_batch(model: DrawDownModel, tasks: list[EvalTask]) -> list[EvalOutcome]:
    """Run the tasks (one condition) as one ensemble; one outcome per task, in order."""
    started = time.perf_counter()
    if not tasks:
        return []
    conditions = {t.condition for t in tasks}
    if len(conditions) != 1:
        raise ConfigError(f"evaluate_batch: a batch must hold one condition, got {sorted(conditions)}")
    keys: dict[tuple, int] = {}
    sets: list[dict[str, float]] = []
    members = []
    for r, t in enumerate(tasks):
        key = tuple(sorted(t.params.items()))
        if key not in keys:
            keys[key] = len(sets)
            sets.append(dict(t.params))
        members.append((keys[key], r, t.seed))
    try:
        test = model.test_for(tasks[0].condition, sets)
        result = test.run_members(members, device=model.device)
    except (BlowUpError, ConfigError) as exc:
        own = _members_that_fail_alone(model, tasks) if isinstance(exc, ConfigError) and len(sets) > 1 else {}
        if own:  # each failed member keeps its own error; the others run without them
            rest = iter(evaluate_batch(model, [t for r, t in enumerate(tasks) if r not in own]))
            wall = time.perf_counter() - started
            return [EvalOutcome.failure(own[r], wall) if r in own else next(rest) for r in range(len(tasks))]
        wall = time.perf_counter() - started
        return [EvalOutcome.failure(f"{type(exc).__name__}: {exc}", wall) for _ in tasks]
    wall = time.perf_counter() - started
    out = []
    for m, k in enumerate(result.kpis):
        if m in result.failed:
            out.append(EvalOutcome.failure(f"BlowUpError: member {m} (seed {tasks[m].seed}): {result.failed[m]}", wall))
            continue
        kpis = {name: float(k.get(name, math.nan)) for name in KPI_UNITS}
        out.append(EvalOutcome.success(kpis, wall))
    return out


def _members_that_fail_alone(model: DrawDownModel, tasks: list[EvalTask]) -> dict[int, str]:
    """Task index -> error, for the tasks whose one-member ensemble cannot be built (fill and
    system, no stepping)."""
    failed = {}
    for r, t in enumerate(tasks):
        try:
            model.test_for(t.condition, [dict(t.params)]).build([t.seed], [0], device=model.device)
        except ConfigError as exc:
            failed[r] = f"ConfigError: {exc}"
    return failed


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


def kpi_matrix(outcomes: Sequence[EvalOutcome], kpis: Sequence[str]) -> np.ndarray:
    """``[n, len(kpis)]`` KPI values (NaN for failures and unmeasured KPIs)."""
    arr = np.full((len(outcomes), len(kpis)), np.nan)
    for i, o in enumerate(outcomes):
        if o.ok:
            arr[i] = [o.kpis.get(k, np.nan) for k in kpis]
    return arr
