"""A calibration read back: the ``calibration.json`` that ``torchdem-calibrate`` writes
(:mod:`bo.calibration.report`), for the tools that start from a calibrated set: ``torchdem-discover
calibration=...``, ``scripts/contrast_check.py --at`` and ``scripts/rerun_equivalence.py --calibration``.

Light on purpose (json and the error type only), so a script's ``--help`` and discovery's config checks do not
import the surrogate stack. Every error names the option that gave the file and the file.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from torchdem.errors import ConfigError, out_of_range


def _where(path: str | Path, option: str) -> str:
    return f"{option} = {str(path)!r}"


def read_calibration(path: str | Path, option: str) -> dict[str, Any]:
    """The JSON object of the calibration at ``path``, given by ``option`` (``calibration``, ``--at``...)."""
    where = _where(path, option)
    try:
        doc = json.loads(Path(path).read_text())
    except OSError as exc:
        raise ConfigError(f"{where}: cannot read it ({exc.strerror})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        detail = f"{exc.msg} at line {exc.lineno}" if isinstance(exc, json.JSONDecodeError) else exc.reason
        raise ConfigError(f"{where}: not JSON ({detail})") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"{where}: a JSON {type(doc).__name__}, expected the object of a calibration.json "
                          "of torchdem-calibrate")
    return doc


def _numbers(doc: dict[str, Any], key: str, where: str, *, required: bool) -> dict[str, float]:
    values = doc.get(key)
    if values is None and not required:
        return {}
    if not isinstance(values, dict) or (required and not values):
        raise ConfigError(f"{where}: no {key!r} object (expected a calibration.json of torchdem-calibrate)")
    for name, value in values.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise out_of_range(f"{key}.{name}", value, "a finite number", where)
    return {k: float(v) for k, v in values.items()}


def calibrated_parameters(path: str | Path, option: str, *, held: bool = False) -> dict[str, float]:
    """The calibration's ``calibrated_parameters`` (name -> value). With ``held``, over its
    ``held_parameters``: the whole set every run of the campaign had, where the file records them."""
    doc, where = read_calibration(path, option), _where(path, option)
    values = _numbers(doc, "calibrated_parameters", where, required=True)
    return {**_numbers(doc, "held_parameters", where, required=False), **values} if held else values
