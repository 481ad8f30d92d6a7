"""Measured KPI data: the paper's draw down tests, shipped with the package, and user files.

Contract:
    * ``load_measured(path=None)`` reads a measured-data JSON file (default: the shipped
      ``torchdem/data/hadi2025_pellet_sinter.json``, Table 2 of Hadi, Pang & Schott) and returns
      a frozen ``MeasuredData``. Every malformed entry raises ``MeasuredDataError`` (a
      ``ConfigError``) naming the file and the key path, e.g.
      ``data.json: conditions["50-50"].kpis.shear_angle_deg.ci95 = -1.0 is not allowed; ...``.
    * ``path`` may also be the bare name of a file shipped in ``torchdem/data/`` (e.g.
      ``"mini_box_twin.json"``, the synthetic measurement of the CPU calibration profile).
    * ``MeasuredData.save(path)`` writes the same format, so ``load_measured(save(d)) == d``.
      This format is the input of the calibration/discovery commands: users add their own test
      conditions with any subset of KPIs.
    * ``load_materials()`` and ``load_paper_tables()`` return the shipped file's ``materials``
      (Tables 1, 3) and ``dem_reported`` (Tables 4, 6-9, A.3-A.6) sections as plain dicts.
      They are reference values from the paper, never inputs a user must supply.

File format (``"format": "torchdem-measured-data/1"``)::

    {
      "format": "torchdem-measured-data/1",          # optional
      "source": "citation and table numbers",        # required, free text
      "units": {"my_new_kpi": "s"},                  # optional for known KPIs, required for new ones
      "notes": ["free text", ...],                   # optional
      "conditions": {                                # required, at least one
        "50-50": {
          "description": "free text",                # optional
          "pellet_mass_fraction": 0.5,               # two-component pellet-sinter form ...
          "layering": ["pellet", "sinter", "pellet", "sinter"],   # bottom to top
          "fill_mass_kg": 40.0,                      # optional
          "replicates": 5,                           # optional: lab repeats behind the CIs
          "kpis": {"angle_of_repose_deg": {"mean": 29.47, "ci95": 0.48}, ...}
        },
        "three-component": {
          "mixture": {                               # ... or the general form, any materials
            "materials": [{"name": "pellet", "mass_fraction": 0.4}, ...],
            "layering": ["coke", "pellet", "sinter"],
            ...                                      # further keys are kept as given
          },
          "kpis": {...}
        }
      },
      "materials": {...}, "dem_reported": {...}      # optional, paper data; save() omits them
    }

``ci95`` is the half-width of the 95 % confidence interval of the mean, in the KPI's unit
(write 0 when only one measurement exists). ``replicates`` (an integer >= 2, optional) is how many
lab repeats the means and CIs come from: the standard uncertainty of a mean is then
``ci95 / t(0.975, replicates - 1)`` (a Student-t half-width, as a lab computes it from few
repeats) with ``replicates - 1`` degrees of freedom; without it ``ci95 / 1.96`` (a large-sample
half-width), which overstates the uncertainty of a mean of few repeats (2x in variance at 5).
KPI names carry their unit; the known names are in
``KPI_UNITS``. A condition may carry any non-empty subset of KPIs; pass ``required_kpis`` to
``load_measured`` to insist on some.
"""
from __future__ import annotations

import copy
import dataclasses
import difflib
import importlib.resources
import json
import math
import os
import pathlib
import re
from collections.abc import Iterable, Mapping
from types import MappingProxyType
from typing import Any

from torchdem.errors import ConfigError, out_of_range

FORMAT = "torchdem-measured-data/1"
SHIPPED_FILE = "hadi2025_pellet_sinter.json"

# Known KPIs with their unit and allowed range of the mean. Units live in the name so a
# number is never read in the wrong unit; degrees are allowed here because KPIs are the
# report edge (STYLE.md habit 4).
KPI_UNITS: Mapping[str, str] = MappingProxyType({
    "angle_of_repose_deg": "deg",
    "shear_angle_deg": "deg",
    "mass_flow_rate_kg_s": "kg/s",
    "mass_lower_box_kg": "kg",
    "segregation_rsd_vertical": "1",
    "segregation_rsd_horizontal": "1",
    "max_heap_height_m": "m",
})
_KPI_RANGES: Mapping[str, tuple[float, float]] = MappingProxyType({
    "angle_of_repose_deg": (0.0, 90.0),
    "shear_angle_deg": (0.0, 90.0),
    "mass_flow_rate_kg_s": (0.0, math.inf),
    "mass_lower_box_kg": (0.0, math.inf),
    "segregation_rsd_vertical": (0.0, math.inf),
    "segregation_rsd_horizontal": (0.0, math.inf),
    "max_heap_height_m": (0.0, math.inf),
})
# The six KPIs of Table 2, and the four the paper calibrates on (segregation is excluded in
# Section 3.3 because DEM stochasticity dominates its variance).
PAPER_KPIS: tuple[str, ...] = (
    "angle_of_repose_deg", "shear_angle_deg", "mass_flow_rate_kg_s", "mass_lower_box_kg",
    "segregation_rsd_vertical", "segregation_rsd_horizontal",
)
CALIBRATION_KPIS: tuple[str, ...] = PAPER_KPIS[:4]
TWO_COMPONENT_MATERIALS: tuple[str, ...] = ("pellet", "sinter")

_TOP_LEVEL_KEYS = ("format", "source", "units", "notes", "conditions", "materials", "dem_reported")
_CONDITION_KEYS = ("description", "pellet_mass_fraction", "layering", "fill_mass_kg", "replicates", "mixture",
                   "kpis")
_KPI_KEYS = ("mean", "ci95")
_NEW_KPI_NAME = re.compile(r"^[a-z][a-z0-9_]*$")
_MIXTURE_SUM_TOLERANCE = 1e-3


class MeasuredDataError(ConfigError):
    """Malformed measured data. ``source`` is the file (or class), ``key`` the path inside it."""

    def __init__(self, source: str, key: str, problem: str):
        self.source = source
        self.key = key
        self.problem = problem
        super().__init__(f"{source}: {key} {problem}")


class UnknownConditionError(KeyError):
    """``MeasuredData.condition(name)`` was asked for a name the data do not contain."""

    def __init__(self, message: str):
        super().__init__(message)
        self.message = message

    def __str__(self) -> str:  # KeyError would print the message in quotes
        return self.message


def _not_allowed(key: str, value: Any, expected: str) -> MeasuredDataError:
    # Raised by the dataclasses with a field name; the file loader re-raises it with the file
    # name and the full key path in front (see _located).
    return MeasuredDataError("", key, f"= {value!r} is not allowed; expected {expected}")


def _number(key: str, value: Any, low: float = -math.inf, high: float = math.inf,
            what: str = "a finite number") -> float:
    """Return ``value`` as a float, or raise if it is not a finite number in [low, high]."""
    if low > -math.inf and high < math.inf:
        expected = f"{what} in [{low:g}, {high:g}]"
    elif low > -math.inf:
        expected = f"{what} >= {low:g}"
    elif high < math.inf:
        expected = f"{what} <= {high:g}"
    else:
        expected = what
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise _not_allowed(key, value, expected)
    if not low <= value <= high:
        raise _not_allowed(key, value, expected)
    return float(value)


def _text(key: str, value: Any) -> str:
    if not isinstance(value, str) or not value.strip():
        raise _not_allowed(key, value, "a non-empty string")
    return value


def _layering(key: str, value: Any, materials: Iterable[str]) -> tuple[str, ...]:
    allowed = tuple(materials)
    if isinstance(value, str) or not isinstance(value, (list, tuple)) or not value:
        raise _not_allowed(key, value, f"a non-empty list of layers, bottom to top, from {list(allowed)}")
    for i, layer in enumerate(value):
        if layer not in allowed:
            raise _not_allowed(f"{key}[{i}]", layer, f"one of {list(allowed)}")
    return tuple(value)


@dataclasses.dataclass(frozen=True)
class KPIValue:
    """One measured KPI: mean and 95 % confidence half-width, both in ``unit``.

    Attributes:
        mean: mean over the repetitions of the test.
        ci95: half-width of the 95 % confidence interval of the mean (>= 0).
        unit: unit of ``mean`` and ``ci95`` ("deg", "kg/s", "kg", "m", "1" for dimensionless).
    """

    mean: float
    ci95: float
    unit: str

    def __post_init__(self):
        try:
            object.__setattr__(self, "mean", _number("mean", self.mean))
            object.__setattr__(self, "ci95", _number(
                "ci95", self.ci95, 0.0, what="the half-width of the 95 % CI, a finite number"))
            _text("unit", self.unit)
        except MeasuredDataError as error:
            raise _located(error, "KPIValue", "") from None

    def to_dict(self) -> dict[str, float]:
        """The file form ``{"mean": ..., "ci95": ...}`` (the unit is stored once per file)."""
        return {"mean": self.mean, "ci95": self.ci95}


@dataclasses.dataclass(frozen=True)
class Condition:
    """One tested condition (mixture, fill) and the KPIs measured for it.

    A pellet-sinter condition sets ``pellet_mass_fraction`` (sinter is the rest) and
    ``layering`` over "pellet"/"sinter". A condition with other or more materials sets
    ``mixture`` instead: ``{"materials": [{"name": str, "mass_fraction": float}, ...],
    "layering": [...], ...}``, fractions summing to 1; ``layering`` must then equal
    ``mixture["layering"]`` and ``pellet_mass_fraction`` is None. Further mixture keys are
    kept as given.

    Attributes:
        name: label of the condition, unique within a ``MeasuredData``.
        pellet_mass_fraction: pellet share of the fill mass in [0, 1], or None with ``mixture``.
        layering: material of each layer in the filled box, bottom to top.
        fill_mass_kg: total mass filled into the upper box, or None if not recorded.
        kpis: KPI name -> ``KPIValue``; any non-empty subset of KPIs.
        mixture: general mixture description for any materials, or None.
        description: free text (where the numbers come from, test notes).
        replicates: lab repeats behind the means and CIs (>= 2), or None if not stated.
    """

    name: str
    pellet_mass_fraction: float | None
    layering: tuple[str, ...]
    fill_mass_kg: float | None
    kpis: Mapping[str, KPIValue]
    mixture: Mapping[str, Any] | None = None
    description: str = ""
    replicates: int | None = None

    def __post_init__(self):
        try:
            self._validate()
        except MeasuredDataError as error:
            raise _located(error, f"Condition {self.name!r}", "") from None

    def _validate(self):
        _text("name", self.name)
        if (self.pellet_mass_fraction is None) == (self.mixture is None):
            raise _not_allowed("pellet_mass_fraction", self.pellet_mass_fraction,
                               "exactly one of 'pellet_mass_fraction' (pellet-sinter) or 'mixture'"
                               " (any materials) to be given")
        if self.mixture is None:
            object.__setattr__(self, "pellet_mass_fraction", _number(
                "pellet_mass_fraction", self.pellet_mass_fraction, 0.0, 1.0, "a mass fraction"))
            object.__setattr__(self, "layering", _layering(
                "layering", self.layering, TWO_COMPONENT_MATERIALS))
        else:
            mixture = _check_mixture(self.mixture)
            if tuple(self.layering) != tuple(mixture["layering"]):
                raise _not_allowed("layering", self.layering,
                                   f"the mixture's layering {mixture['layering']}")
            object.__setattr__(self, "layering", tuple(self.layering))
            object.__setattr__(self, "mixture", MappingProxyType(mixture))
        if self.fill_mass_kg is not None:
            fill = _number("fill_mass_kg", self.fill_mass_kg, what="a mass in kg")
            if fill <= 0.0:
                raise _not_allowed("fill_mass_kg", fill, "a mass in kg > 0")
            object.__setattr__(self, "fill_mass_kg", fill)
        if self.replicates is not None and (isinstance(self.replicates, bool) or not isinstance(self.replicates, int)
                                            or self.replicates < 2):
            raise _not_allowed("replicates", self.replicates, "an integer >= 2 (lab repeats behind the CIs) or null")
        if not isinstance(self.description, str):
            raise _not_allowed("description", self.description, "a string")
        if not isinstance(self.kpis, Mapping) or not self.kpis:
            raise _not_allowed("kpis", self.kpis, "a non-empty mapping KPI name -> KPIValue")
        for kpi, value in self.kpis.items():
            if not isinstance(kpi, str) or not _NEW_KPI_NAME.match(kpi):
                raise _not_allowed("kpis", kpi, "KPI names in snake_case with the unit in the name")
            if not isinstance(value, KPIValue):
                raise _not_allowed(f"kpis.{kpi}", value, "a KPIValue")
            if kpi in KPI_UNITS:
                if value.unit != KPI_UNITS[kpi]:
                    raise _not_allowed(f"kpis.{kpi}.unit", value.unit, f"{KPI_UNITS[kpi]!r}")
                low, high = _KPI_RANGES[kpi]
                _number(f"kpis.{kpi}.mean", value.mean, low, high)
        lower = self.kpis.get("mass_lower_box_kg")
        if lower is not None and self.fill_mass_kg is not None and lower.mean > self.fill_mass_kg:
            raise _not_allowed("kpis.mass_lower_box_kg.mean", lower.mean,
                               f"at most the mass filled, fill_mass_kg = {self.fill_mass_kg:g} kg")
        object.__setattr__(self, "kpis", MappingProxyType(dict(self.kpis)))

    def standard_uncertainty(self, kpi: str) -> tuple[float, float]:
        """``(u, dof)`` of the measured mean of ``kpi``: ``ci95 / t(0.975, replicates - 1)`` with
        ``replicates - 1`` degrees of freedom, or ``ci95 / 1.96`` with infinite ones when the
        number of repeats is not stated."""
        ci95 = self.kpis[kpi].ci95
        if self.replicates is None:
            return ci95 / 1.959963984540054, math.inf
        dof = self.replicates - 1
        return ci95 / float(_student_t_975(dof)), float(dof)

    def mass_fractions(self) -> dict[str, float]:
        """Material name -> mass fraction of the fill, for either form of the condition."""
        if self.mixture is None:
            return {"pellet": self.pellet_mass_fraction, "sinter": 1.0 - self.pellet_mass_fraction}
        return {m["name"]: float(m["mass_fraction"]) for m in self.mixture["materials"]}

    def to_dict(self) -> dict[str, Any]:
        """The file form of this condition (without its name, which is the key in the file)."""
        out: dict[str, Any] = {}
        if self.description:
            out["description"] = self.description
        if self.mixture is None:
            out["pellet_mass_fraction"] = self.pellet_mass_fraction
            out["layering"] = list(self.layering)
        else:
            out["mixture"] = copy.deepcopy(dict(self.mixture))
        if self.fill_mass_kg is not None:
            out["fill_mass_kg"] = self.fill_mass_kg
        if self.replicates is not None:
            out["replicates"] = self.replicates
        out["kpis"] = {kpi: value.to_dict() for kpi, value in self.kpis.items()}
        return out


def _student_t_975(dof: int) -> float:
    """The 97.5 % quantile of Student's t with ``dof`` degrees of freedom."""
    from scipy import stats

    return float(stats.t.ppf(0.975, dof))


def _check_mixture(mixture: Any) -> dict[str, Any]:
    """Validate the general mixture form and return a deep copy of it."""
    if not isinstance(mixture, Mapping):
        raise _not_allowed("mixture", mixture, "an object with 'materials' and 'layering'")
    mixture = copy.deepcopy(dict(mixture))
    materials = mixture.get("materials")
    if not isinstance(materials, list) or not materials:
        raise _not_allowed("mixture.materials", materials,
                           'a non-empty list of {"name": str, "mass_fraction": float}')
    names: list[str] = []
    total = 0.0
    for i, material in enumerate(materials):
        key = f"mixture.materials[{i}]"
        if not isinstance(material, Mapping):
            raise _not_allowed(key, material, '{"name": str, "mass_fraction": float}')
        if "name" not in material or "mass_fraction" not in material:
            missing = "name" if "name" not in material else "mass_fraction"
            raise MeasuredDataError("", f"{key}.{missing}", "is missing")
        name = _text(f"{key}.name", material["name"])
        if name in names:
            raise _not_allowed(f"{key}.name", name, "each material listed once")
        names.append(name)
        total += _number(f"{key}.mass_fraction", material["mass_fraction"], 0.0, 1.0, "a mass fraction")
    if abs(total - 1.0) > _MIXTURE_SUM_TOLERANCE:
        raise _not_allowed("mixture.materials[*].mass_fraction (sum)", round(total, 6),
                           f"a sum of 1 within {_MIXTURE_SUM_TOLERANCE}")
    if "layering" not in mixture:
        raise MeasuredDataError("", "mixture.layering", "is missing")
    mixture["layering"] = list(_layering("mixture.layering", mixture["layering"], names))
    return mixture


@dataclasses.dataclass(frozen=True)
class MeasuredData:
    """Measured KPIs for a set of test conditions, with their source.

    Attributes:
        source: citation or lab record the numbers come from (free text).
        conditions: the conditions, in file order, names unique.
        notes: free-text remarks (transcription choices, test procedure).
        origin: file the data were loaded from, for error messages; not part of equality.
    """

    source: str
    conditions: tuple[Condition, ...]
    notes: tuple[str, ...] = ()
    origin: str | None = dataclasses.field(default=None, compare=False)

    def __post_init__(self):
        where = self.origin or "MeasuredData"
        try:
            _text("source", self.source)
            conditions = tuple(self.conditions)
            if not conditions or not all(isinstance(c, Condition) for c in conditions):
                raise _not_allowed("conditions", self.conditions, "a non-empty sequence of Condition")
            names = [c.name for c in conditions]
            duplicates = sorted({n for n in names if names.count(n) > 1})
            if duplicates:
                raise _not_allowed("conditions", duplicates, "unique condition names")
            units: dict[str, str] = {}
            for c in conditions:
                for kpi, value in c.kpis.items():
                    if units.setdefault(kpi, value.unit) != value.unit:
                        raise _not_allowed(f'conditions["{c.name}"].kpis.{kpi}.unit', value.unit,
                                           f"the unit used elsewhere in the data, {units[kpi]!r}")
            notes = tuple(self.notes)
            for i, note in enumerate(notes):
                _text(f"notes[{i}]", note)
        except MeasuredDataError as error:
            raise _located(error, where, "") from None
        object.__setattr__(self, "conditions", conditions)
        object.__setattr__(self, "notes", notes)

    @property
    def names(self) -> tuple[str, ...]:
        """Condition names, in file order."""
        return tuple(c.name for c in self.conditions)

    @property
    def kpi_names(self) -> tuple[str, ...]:
        """Every KPI measured in at least one condition, in order of first appearance."""
        return tuple(dict.fromkeys(kpi for c in self.conditions for kpi in c.kpis))

    def condition(self, name: str) -> Condition:
        """The condition called ``name``; the error lists the known names."""
        for c in self.conditions:
            if c.name == name:
                return c
        close = difflib.get_close_matches(str(name), self.names, n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise UnknownConditionError(
            f"{self.origin or 'MeasuredData'}: unknown condition {name!r}; "
            f"known conditions: {', '.join(self.names)}{hint}")

    def subset(self, names: Iterable[str], source: str = "MeasuredData.subset") -> "MeasuredData":
        """A copy with only the conditions ``names``, in that order. An empty list, a repeated or an
        unknown name is a :class:`ConfigError` from ``source`` (the setting that asked) listing the
        known names."""
        names = [str(n) for n in names]
        known = list(self.names)
        if not names or len(set(names)) < len(names) or not set(names) <= set(known):
            raise out_of_range("conditions", names, f"a non-empty list of distinct conditions of "
                               f"{self.origin or 'the measured data'}: {known}", source)
        return dataclasses.replace(self, conditions=tuple(self.condition(n) for n in names))

    def with_condition(self, condition: Condition) -> "MeasuredData":
        """A copy with ``condition`` added, replacing any condition of the same name."""
        kept = tuple(c for c in self.conditions if c.name != condition.name)
        return dataclasses.replace(self, conditions=kept + (condition,))

    def to_dict(self) -> dict[str, Any]:
        """The file form of the data (see the module docstring); ``origin`` is not written."""
        units = {kpi: self._unit(kpi) for kpi in self.kpi_names}
        out: dict[str, Any] = {"format": FORMAT, "source": self.source, "units": units}
        if self.notes:
            out["notes"] = list(self.notes)
        out["conditions"] = {c.name: c.to_dict() for c in self.conditions}
        return out

    def save(self, path: str | os.PathLike) -> None:
        """Write ``to_dict()`` as JSON to ``path``; ``load_measured(path)`` reads it back equal."""
        with open(path, "w", encoding="utf-8") as f:
            json.dump(self.to_dict(), f, indent=2, ensure_ascii=False, allow_nan=False)
            f.write("\n")

    def _unit(self, kpi: str) -> str:
        return next(c.kpis[kpi].unit for c in self.conditions if kpi in c.kpis)


# ---------------------------------------------------------------------------------- loading


def _shipped_path():
    return importlib.resources.files("torchdem").joinpath("data", SHIPPED_FILE)


def shipped_file(name: str):
    """The shipped data file ``torchdem/data/<name>`` (a resource), or None if there is none."""
    if not isinstance(name, str) or not name or os.sep in name or "/" in name:
        return None
    resource = importlib.resources.files("torchdem").joinpath("data", name)
    return resource if resource.is_file() else None


def _read_json(path: str | os.PathLike | None) -> tuple[dict[str, Any], str]:
    """Parse the file (default: the shipped one; a bare name that is no file here but a shipped
    file, e.g. ``"mini_box_twin.json"``, is that shipped file); return its top-level object and
    its name."""
    if path is None:
        resource = _shipped_path()
    elif not os.path.exists(path) and shipped_file(os.fspath(path)) is not None:
        resource = shipped_file(os.fspath(path))
    else:
        resource = pathlib.Path(path)
    where = str(resource)

    def no_duplicate_keys(pairs):
        seen: dict[str, Any] = {}
        for key, value in pairs:
            if key in seen:
                raise MeasuredDataError(where, f"{key!r}", "appears twice in the same JSON object")
            seen[key] = value
        return seen

    try:
        text = resource.read_text(encoding="utf-8")
    except OSError as error:
        raise ConfigError(f"{where}: cannot read measured-data file ({error.strerror})") from None
    try:
        data = json.loads(text, object_pairs_hook=no_duplicate_keys)
    except json.JSONDecodeError as error:
        raise MeasuredDataError(where, f"line {error.lineno} column {error.colno}",
                                f"is not valid JSON: {error.msg}") from None
    if not isinstance(data, dict):
        raise MeasuredDataError(where, "(top level)", "must be a JSON object")
    return data, where


def _located(error: MeasuredDataError, where: str, prefix: str) -> MeasuredDataError:
    """Re-raise a dataclass field error with the file name and full key path."""
    key = f"{prefix}.{error.key}" if prefix and error.key else (prefix or error.key)
    return MeasuredDataError(where, key, error.problem)


def _require(obj: Mapping[str, Any], key: str, where: str, path: str, expected: str) -> Any:
    if key not in obj:
        full = f"{path}.{key}" if path else key
        raise MeasuredDataError(where, full, f"is missing; expected {expected}")
    return obj[key]


def _reject_unknown_keys(obj: Mapping[str, Any], allowed: Iterable[str], where: str, path: str):
    allowed = tuple(allowed)
    for key in obj:
        if key not in allowed:
            close = difflib.get_close_matches(key, allowed, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            full = f"{path}.{key}" if path else key
            raise MeasuredDataError(where, full, f"is not a known key; allowed: {', '.join(allowed)}{hint}")


def _file_units(data: Mapping[str, Any], where: str) -> dict[str, str]:
    """Known KPI units merged with the file's ``units``, which must agree with the known ones."""
    declared = data.get("units", {})
    if not isinstance(declared, dict):
        raise MeasuredDataError(where, "units",
                                f"= {declared!r} is not allowed; expected an object KPI -> unit")
    units = dict(KPI_UNITS)
    for kpi, unit in declared.items():
        key = f"units.{kpi}"
        if kpi in KPI_UNITS:
            if unit != KPI_UNITS[kpi]:
                raise MeasuredDataError(where, key, f"= {unit!r} is not allowed; expected {KPI_UNITS[kpi]!r}")
            continue
        if not _NEW_KPI_NAME.match(kpi):
            raise MeasuredDataError(where, key, "is not allowed; new KPI names are snake_case with the "
                                                "unit in the name")
        if not isinstance(unit, str) or not unit.strip():
            raise MeasuredDataError(where, key,
                                    f"= {unit!r} is not allowed; expected a non-empty unit string")
        units[kpi] = unit
    return units


def _parse_condition(name: str, raw: Any, units: Mapping[str, str], where: str) -> Condition:
    path = f"conditions[{json.dumps(name)}]"
    if not isinstance(raw, dict):
        raise MeasuredDataError(where, path, f"= {raw!r} is not allowed; expected an object")
    _reject_unknown_keys(raw, _CONDITION_KEYS, where, path)
    raw_kpis = _require(raw, "kpis", where, path, "an object KPI name -> {mean, ci95}")
    if not isinstance(raw_kpis, dict) or not raw_kpis:
        raise MeasuredDataError(where, f"{path}.kpis",
                                f"= {raw_kpis!r} is not allowed; expected a non-empty object")
    kpis: dict[str, KPIValue] = {}
    for kpi, entry in raw_kpis.items():
        key = f"{path}.kpis.{kpi}"
        if kpi not in units:
            close = difflib.get_close_matches(kpi, list(units), n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise MeasuredDataError(
                where, key, f"is not a known KPI; {hint}known KPIs: {', '.join(units)}. "
                "A new KPI must have its unit declared in the top-level 'units'.")
        if not isinstance(entry, dict):
            raise MeasuredDataError(where, key,
                                    f"= {entry!r} is not allowed; expected {{\"mean\": ..., \"ci95\": ...}}")
        _reject_unknown_keys(entry, _KPI_KEYS, where, key)
        mean = _require(entry, "mean", where, key, "the mean of the KPI")
        ci95 = _require(entry, "ci95", where, key, "the half-width of the 95 % CI (>= 0)")
        try:
            kpis[kpi] = KPIValue(mean, ci95, units[kpi])
        except MeasuredDataError as error:
            raise _located(error, where, key) from None
    if "mixture" in raw:
        for key in ("pellet_mass_fraction", "layering"):
            if key in raw:
                raise MeasuredDataError(where, f"{path}.{key}",
                                        "is not allowed with 'mixture'; put the layering inside 'mixture'")
        mixture = raw["mixture"]
        pellet_mass_fraction = None
        layering = mixture.get("layering") if isinstance(mixture, dict) else None
        layering = tuple(layering) if isinstance(layering, list) else layering
    else:
        mixture = None
        pellet_mass_fraction = _require(raw, "pellet_mass_fraction", where, path,
                                        "the pellet mass fraction (or a 'mixture' object)")
        layering = _require(raw, "layering", where, path,
                            "the layers bottom to top, e.g. [\"pellet\", \"sinter\", \"pellet\", \"sinter\"]")
    try:
        return Condition(name=name, pellet_mass_fraction=pellet_mass_fraction, layering=layering,
                         fill_mass_kg=raw.get("fill_mass_kg"), kpis=kpis, mixture=mixture,
                         description=raw.get("description", ""), replicates=raw.get("replicates"))
    except MeasuredDataError as error:
        raise _located(error, where, path) from None


def load_measured(path: str | os.PathLike | None = None, *,
                  required_kpis: Iterable[str] = ()) -> MeasuredData:
    """Read and validate a measured-data file (default: the shipped paper data, Table 2).

    Args:
        path: JSON file in the format of the module docstring; None for the shipped file.
        required_kpis: KPI names every condition must carry (e.g. ``CALIBRATION_KPIS``).

    Raises:
        MeasuredDataError: naming the file and key of the first malformed entry.
    """
    data, where = _read_json(path)
    _reject_unknown_keys(data, _TOP_LEVEL_KEYS, where, "")
    fmt = data.get("format", FORMAT)
    if fmt != FORMAT:
        raise MeasuredDataError(where, "format", f"= {fmt!r} is not allowed; expected {FORMAT!r}")
    source = _require(data, "source", where, "", "a citation or lab record (string)")
    units = _file_units(data, where)
    raw_conditions = _require(data, "conditions", where, "", "an object condition name -> condition")
    if not isinstance(raw_conditions, dict) or not raw_conditions:
        raise MeasuredDataError(where, "conditions",
                                f"= {raw_conditions!r} is not allowed; expected a non-empty object")
    conditions = tuple(_parse_condition(name, raw, units, where) for name, raw in raw_conditions.items())
    notes = data.get("notes", [])
    if not isinstance(notes, list):
        raise MeasuredDataError(where, "notes", f"= {notes!r} is not allowed; expected a list of strings")
    measured = MeasuredData(source=source, conditions=conditions, notes=tuple(notes), origin=where)
    required_kpis = tuple(required_kpis)
    for kpi in required_kpis:
        if kpi not in units:
            raise ConfigError(f"required_kpis: {kpi!r} is not a known KPI; known KPIs: {', '.join(units)}")
        for c in measured.conditions:
            if kpi not in c.kpis:
                raise MeasuredDataError(where, f"conditions[{json.dumps(c.name)}].kpis.{kpi}",
                                        f"is missing; this use requires the KPIs {list(required_kpis)}")
    return measured


def _section(path: str | os.PathLike | None, section: str) -> tuple[dict[str, Any], str]:
    data, where = _read_json(path)
    value = _require(data, section, where, "", f"the '{section}' section of the paper data")
    if not isinstance(value, dict):
        raise MeasuredDataError(where, section, "must be a JSON object")
    return value, where


def load_materials(path: str | os.PathLike | None = None) -> dict[str, Any]:
    """The ``materials`` section (Tables 1 and 3) as plain dicts; sieve fractions checked.

    Per material: ``sieve_size_distribution`` (list of ``{d_min_mm, d_max_mm, mass_fraction}``),
    ``solid_density_kg_m3`` (``{mean, plus_minus}``), ``shear_modulus_pa``, ``poisson_ratio``.
    """
    materials, where = _section(path, "materials")
    for name, material in materials.items():
        if not isinstance(material, dict) or "sieve_size_distribution" not in material:
            continue
        classes = material["sieve_size_distribution"]
        key = f"materials.{name}.sieve_size_distribution"
        if not isinstance(classes, list) or not classes:
            raise MeasuredDataError(where, key,
                                    "must be a non-empty list of {d_min_mm, d_max_mm, mass_fraction}")
        total = 0.0
        for i, sieve_class in enumerate(classes):
            if not isinstance(sieve_class, dict):
                raise MeasuredDataError(where, f"{key}[{i}]", "must be {d_min_mm, d_max_mm, mass_fraction}")
            for field in ("d_min_mm", "d_max_mm", "mass_fraction"):
                _require(sieve_class, field, where, f"{key}[{i}]", "a number")
            try:
                d_min = _number("d_min_mm", sieve_class["d_min_mm"], 0.0, what="a sieve size in mm")
                _number("d_max_mm", sieve_class["d_max_mm"], d_min, what="a sieve size in mm")
                total += _number("mass_fraction", sieve_class["mass_fraction"], 0.0, 1.0, "a mass fraction")
            except MeasuredDataError as error:
                raise _located(error, where, f"{key}[{i}]") from None
        if abs(total - 1.0) > _MIXTURE_SUM_TOLERANCE:
            raise MeasuredDataError(where, key, f"mass fractions sum to {total:.6f}; expected 1 within "
                                                f"{_MIXTURE_SUM_TOLERANCE}")
    return materials


def load_paper_tables(path: str | os.PathLike | None = None) -> dict[str, Any]:
    """The ``dem_reported`` section as plain dicts: what the paper reports about its DEM model.

    Keys: ``dsd_levels`` (Table 4), ``extended_bounds`` (Table 6), ``surrogate_r2`` (Table 7),
    ``ga_calibration`` (Table 8), ``ga_repetitions`` (Table 9), ``ga_settings`` (Table A.3),
    ``time_step`` (Section 3.2.4), ``bulk_density_recalibration`` (Section 3.6),
    ``dem_vs_experiment`` (Tables A.4-A.6), ``notes``. A fresh copy on every call.
    """
    tables, _ = _section(path, "dem_reported")
    return tables
