"""Named contact parameters of a mixture, as calibration sees them.

Contract: parameters are named ``<coefficient>_<a><b>`` with coefficient ``mu_s`` (sliding
friction), ``mu_r`` (rolling friction), ``e`` (restitution) or ``coh`` (SJKR cohesion energy
density, J/m^3; optional, 0 when not given) and ``a``, ``b`` one-letter
abbreviations of two materials (``p`` pellet, ``s`` sinter, ``g`` geometry by default):
``mu_s_pp``, ``e_sg``, ... — the paper's 12 parameters. A value is a scalar or a sequence of B
values (one per ensemble member). Pairs of two different particle materials that are not
given (``mu_s_ps``) are the average of the two pure pairs, as in the paper (Section 3.2.3);
giving them explicitly frees them (a model extension). :func:`interaction_pairs` turns the
names into the per-pair dictionaries of :func:`torchdem.materials.interaction_table`.
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from torchdem.errors import ConfigError

COEFFICIENTS = {"mu_s": "mu_s", "mu_r": "mu_r", "e": "restitution", "coh": "cohesion"}

# Reference case of Hadi et al. (Table 4, middle level; from their ref. [40]).
PAPER_REFERENCE: dict[str, float] = {
    "mu_s_pp": 0.49, "mu_r_pp": 0.06, "e_pp": 0.7,
    "mu_s_ss": 0.7, "mu_r_ss": 0.08, "e_ss": 0.35,
    "mu_s_pg": 0.38, "mu_r_pg": 0.06, "e_pg": 0.7,
    "mu_s_sg": 0.38, "mu_r_sg": 0.08, "e_sg": 0.4,
}

DEFAULT_ABBREVIATIONS = {"p": "pellet", "s": "sinter", "g": "geometry"}


def _split(name: str) -> tuple[str, str]:
    for coeff in ("mu_s", "mu_r", "e", "coh"):
        prefix = coeff + "_"
        if name.startswith(prefix) and len(name) == len(prefix) + 2:
            return coeff, name[len(prefix):]
    raise ConfigError(f"contact parameter {name!r}: expected <mu_s|mu_r|e|coh>_<a><b> with one-letter material "
                      "abbreviations, e.g. mu_s_pp or e_sg")


def interaction_pairs(params: Mapping[str, object], particle_materials: Sequence[str], geometry_material: str,
                      abbreviations: Mapping[str, str] = DEFAULT_ABBREVIATIONS, rolling_damping: float = 0.3,
                      source: str = "contact") -> dict[tuple[str, str], dict[str, object]]:
    """Per-pair coefficient dictionaries for every pair that can touch (see module docstring)."""
    letter = {}
    for k, v in abbreviations.items():
        letter[v] = k
    names = list(particle_materials) + [geometry_material]
    for n in names:
        if n not in letter and n != geometry_material:
            raise ConfigError(f"{source}: material {n!r} has no abbreviation; known: {dict(abbreviations)}")
    letter.setdefault(geometry_material, "g")
    given: dict[tuple[str, str], dict[str, object]] = {}
    inverse = {v: k for k, v in letter.items()}
    for name, value in params.items():
        coeff, ab = _split(name)
        a, b = inverse.get(ab[0]), inverse.get(ab[1])
        if a is None or b is None:
            raise ConfigError(f"{source}: {name} names unknown material letter(s) in {ab!r}; "
                              f"known: {sorted(inverse)}")
        key = tuple(sorted((a, b)))
        given.setdefault(key, {})[COEFFICIENTS[coeff]] = value
    pairs: dict[tuple[str, str], dict[str, object]] = {}
    for i, a in enumerate(particle_materials):
        for b in list(particle_materials[i:]) + [geometry_material]:
            key = tuple(sorted((a, b)))
            coeffs = dict(given.get(key, {}))
            for coeff in ("mu_s", "mu_r", "restitution"):
                if coeff in coeffs:
                    continue
                if b != geometry_material and a != b:
                    pa, pb = given.get((a, a), {}), given.get((b, b), {})
                    if coeff in pa and coeff in pb:
                        coeffs[coeff] = _average(pa[coeff], pb[coeff])
                        continue
                short = {"restitution": "e"}.get(coeff, coeff)
                raise ConfigError(f"{source}: missing {short}_{letter[a]}{letter[b]} (pair {a}-{b})")
            if "cohesion" not in coeffs and b != geometry_material and a != b:  # optional: 0 unless given
                pa, pb = given.get((a, a), {}), given.get((b, b), {})
                if "cohesion" in pa and "cohesion" in pb:
                    coeffs["cohesion"] = _average(pa["cohesion"], pb["cohesion"])
            coeffs.setdefault("rolling_damping", rolling_damping)
            pairs[(a, b)] = coeffs
    return pairs


def _average(x, y):
    ax, ay = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    out = 0.5 * (ax + ay)
    return out.tolist() if out.ndim else float(out)
