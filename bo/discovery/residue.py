"""The upper box's residue per unit slope: a check of a draw down's KPIs against the box itself.

After the discharge the upper box holds two wedges of material beside the slot, rising at the
shear angle theta from the slot's edges towards the side walls. Their mass is what the lower box
did not receive, so

    R = (M_fill - M_lower) / tan(theta)      (kg)

is the residue's mass per unit slope. For straight wedges that reach the side walls,
``R = rho_b a^2 L``: ``a = (W_upper - b_outlet) / 2`` is the floor's ledge beside the slot, ``L``
the box's depth and ``rho_b`` the residue's bulk density. R is then a property of the box and of
the bulk density, not of the angle. A model whose R differs from the lab's can match the shear
angle or the lower box's mass but not both: whatever steepens its face then leaves more in the upper
box. Reading R off every run of a campaign says whether any calibration parameter moves it.

Contract:

* :func:`residue_per_slope` ``(fill kg, lower box kg, shear angle deg) -> R`` (kg), floats or
  arrays; a value outside its range raises :class:`~torchdem.errors.ConfigError` naming it.
* :func:`wedge_residue_per_slope` ``(upper width, outlet width, depth m, bulk density kg/m^3)``:
  ``rho_b a^2 L``, the straight-wedge R of a box.
* :func:`residue_check` ``(store paths, measured data) -> ResidueCheck``: per condition, the lab's
  R with its 95 % half-width (from Table 2's CIs, first order) and the model's R over every
  finished run in the stores that has a shear angle (jammed runs left out); per condition with at
  least a dozen runs, a least-squares fit of R on the run parameters that vary (those set in at
  least half the runs, over the runs that set them all), per standard deviation of each parameter,
  with its standard error and the fit's R^2.
  ``ResidueCheck.ledge_factor(condition)``: ``sqrt(R_lab / R_model)``, the factor on the ledge
  ``a`` that would give the model the lab's R if its wedges kept their shape; ``ResidueCheck.to_dict()``
  the same as plain data (the discovery report's ``residue``).
* :func:`format_residue` turns it into markdown (``scripts/residue_check.py``); with ``by_stage``
  also R per stage and condition (``ResidueCheck.by_stage()``), so a discovery store shows which
  candidate's runs moved it.

Stores are opened read-only, so a running campaign is not disturbed.
"""
from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from bo.campaign.progress import finished_runs
from bo.screening.effects import least_squares
from kpi.loadcell import discharge_jammed
from torchdem.errors import ConfigError
from torchdem.measured import MeasuredData

#: Conditions with fewer runs than this get no fit of R on the parameters.
MIN_RUNS_FOR_FIT = 12


def residue_per_slope(fill_kg, lower_kg, shear_angle_deg, source: str = "residue_per_slope"):
    """``(fill_kg - lower_kg) / tan(shear_angle_deg)``, kg (module docstring). Floats or arrays."""
    fill, lower, theta = (np.asarray(v, dtype=float) for v in (fill_kg, lower_kg, shear_angle_deg))
    if not (np.isfinite(theta).all() and ((theta > 0) & (theta < 90)).all()):
        raise ConfigError(f"{source}: shear angle = {shear_angle_deg!r} deg; expected in (0, 90)")
    if not (np.isfinite(fill).all() and (fill > 0).all()):
        raise ConfigError(f"{source}: fill mass = {fill_kg!r} kg; expected a finite number > 0")
    if not (np.isfinite(lower).all() and ((lower >= 0) & (lower <= fill)).all()):
        raise ConfigError(f"{source}: lower box mass = {lower_kg!r} kg; expected in [0, fill mass {fill_kg!r}]")
    r = (fill - lower) / np.tan(np.radians(theta))
    return float(r) if r.ndim == 0 else r


def wedge_residue_per_slope(upper_width: float, outlet_width: float, depth: float, bulk_density: float) -> float:
    """``rho_b a^2 L`` with ``a = (upper_width - outlet_width) / 2`` (m, m, m, kg/m^3 -> kg)."""
    if not 0 < outlet_width < upper_width:
        raise ConfigError(f"wedge_residue_per_slope: outlet width = {outlet_width!r} m; expected in "
                          f"(0, upper width {upper_width!r} m)")
    if not (depth > 0 and bulk_density > 0):
        raise ConfigError(f"wedge_residue_per_slope: depth = {depth!r} m and bulk density = {bulk_density!r} kg/m^3; "
                          "expected both > 0")
    a = 0.5 * (upper_width - outlet_width)
    return bulk_density * a * a * depth


@dataclass(frozen=True)
class ResidueRun:
    """One finished run: its stage, condition, parameters and R (kg)."""

    stage: str
    condition: str
    params: Mapping[str, float]
    r: float


@dataclass(frozen=True)
class ResidueFit:
    """R on the run parameters at one condition: per parameter ``(change of R per standard
    deviation of the parameter, its standard error, the parameter's sd)``, kg; ``r2`` the fit's."""

    condition: str
    runs: int
    slopes: Mapping[str, tuple[float, float, float]]
    r2: float


@dataclass(frozen=True)
class ResidueCheck:
    """``lab``: condition -> (R, 95 % half-width); ``runs``: the model's; ``fits``: per condition."""

    stores: tuple[str, ...]
    lab: Mapping[str, tuple[float, float]]
    runs: tuple[ResidueRun, ...]
    fits: tuple[ResidueFit, ...]

    def model(self, condition: str) -> np.ndarray:
        """``[n]`` R of the model's runs at ``condition``."""
        return np.array([r.r for r in self.runs if r.condition == condition])

    def conditions(self) -> list[str]:
        """The lab's conditions, then any other the runs have, in order."""
        return list(dict.fromkeys([*self.lab, *(r.condition for r in self.runs)]))

    def to_dict(self) -> dict:
        """Plain data: per condition the lab's R and half-width, the model's runs, mean, sd and ledge
        factor; per fitted condition its slopes (per sd, se, the parameter's sd) and R^2."""
        per = {}
        for c in self.conditions():
            r = self.model(c)
            per[c] = {"lab": list(self.lab[c]) if c in self.lab else None, "runs": int(len(r)),
                      "mean": float(r.mean()) if len(r) else math.nan,
                      "sd": float(r.std(ddof=1)) if len(r) > 1 else math.nan,
                      "ledge_factor": self.ledge_factor(c)}
        return {"stores": list(self.stores), "conditions": per,
                "fits": {f.condition: {"runs": f.runs, "r2": f.r2,
                                       "slopes": {n: {"per_sd": v[0], "se": v[1], "sd": v[2]}
                                                  for n, v in f.slopes.items()}} for f in self.fits}}

    def by_stage(self) -> dict[tuple[str, str], np.ndarray]:
        """``(stage, condition) -> [n]`` R of the model's runs, stages in the order the stores list them
        (in a discovery store a stage is a candidate's design or held-out runs)."""
        out: dict[tuple[str, str], list[float]] = {}
        for r in self.runs:
            out.setdefault((r.stage, r.condition), []).append(r.r)
        return {k: np.array(v) for k, v in out.items()}

    def ledge_factor(self, condition: str) -> float:
        """``sqrt(R_lab / mean R_model)`` at ``condition`` (NaN without runs or lab value)."""
        r = self.model(condition)
        if condition not in self.lab or not len(r):
            return math.nan
        return math.sqrt(self.lab[condition][0] / float(r.mean()))


def lab_residue(measured: MeasuredData) -> dict[str, tuple[float, float]]:
    """Condition -> (R, 95 % half-width) from the measured means and CIs of the shear angle and
    the lower box's mass (first-order propagation), conditions with both and a fill mass only."""
    out = {}
    for name in measured.names:
        c = measured.condition(name)
        theta, lower = c.kpis.get("shear_angle_deg"), c.kpis.get("mass_lower_box_kg")
        if theta is None or lower is None or c.fill_mass_kg is None:
            continue
        source = f"{measured.origin or 'measured data'}: condition {name!r}"
        r = residue_per_slope(c.fill_mass_kg, lower.mean, theta.mean, source)
        t = math.tan(math.radians(theta.mean))
        d_lower = (lower.ci95 or 0.0) / t
        d_theta = r / (t * math.cos(math.radians(theta.mean)) ** 2) * math.radians(theta.ci95 or 0.0)
        out[name] = (r, math.hypot(d_lower, d_theta))
    return out


def _store_runs(path: Path) -> list[ResidueRun]:
    out = []
    for stage, condition, _, p, k in finished_runs(path, "residue_check"):
        theta, fill, lower = (k.get(n, math.nan) for n in ("shear_angle_deg", "fill_mass_full_kg",
                                                          "mass_lower_box_full_kg"))
        if discharge_jammed(k) or not (0 < theta < 90 and 0 <= lower <= fill):
            continue
        out.append(ResidueRun(stage, condition, p, residue_per_slope(fill, lower, theta, str(path))))
    return out


def fit_residue(runs: Sequence[ResidueRun], condition: str) -> ResidueFit | None:
    """Least squares of R on the parameters set in at least half the runs at ``condition`` that vary,
    each standardised, over the runs that set them all (a stage that held a parameter at a value of
    its config leaves it out of its runs' parameters); None below :data:`MIN_RUNS_FOR_FIT` runs or
    without a fit."""
    at = [r for r in runs if r.condition == condition]
    counts: dict[str, int] = defaultdict(int)
    for r in at:
        for n in r.params:
            counts[n] += 1
    common = sorted(n for n, k in counts.items() if 2 * k >= len(at))
    at = [r for r in at if all(n in r.params for n in common)]
    if len(at) < MIN_RUNS_FOR_FIT:
        return None
    x = {n: np.array([r.params[n] for r in at]) for n in common}
    names = [n for n, v in x.items() if v.std() > 1e-12 * max(1.0, abs(v).max())]
    y = np.array([r.r for r in at])
    sd = {n: float(x[n].std()) for n in names}
    design = np.column_stack([np.ones(len(at))] + [(x[n] - x[n].mean()) / sd[n] for n in names])
    fit = least_squares(design, y)
    if fit is None:
        return None
    beta, se, _, _ = fit
    resid = y - design @ beta
    r2 = 1.0 - float(resid @ resid) / float(((y - y.mean()) ** 2).sum())
    return ResidueFit(condition, len(at), {n: (float(beta[i + 1]), float(se[i + 1]), sd[n])
                                           for i, n in enumerate(names)}, r2)


def residue_check(stores: Sequence[str | Path], measured: MeasuredData) -> ResidueCheck:
    """The lab's R and the model's over every run of ``stores`` (module docstring)."""
    runs = [run for s in stores for run in _store_runs(Path(s))]
    conditions = list(dict.fromkeys([*measured.names, *(r.condition for r in runs)]))
    fits = tuple(f for f in (fit_residue(runs, c) for c in conditions) if f is not None)
    return ResidueCheck(tuple(str(s) for s in stores), lab_residue(measured), tuple(runs), fits)


def _sd(r: np.ndarray) -> float:
    return float(r.std(ddof=1)) if len(r) > 1 else 0.0


def format_residue(check: ResidueCheck, by_stage: bool = False, heading: bool = True) -> str:
    """Markdown: R of the lab and of the model per condition, then the fits of R on the parameters;
    ``by_stage``: between them, R per stage and condition (mean, sd, runs); ``heading``: the section's
    own title first (a report that titles it itself leaves it out)."""
    lines = (["## Residue per unit slope, R = (fill - lower box) / tan(shear angle), kg", ""] if heading else []) + [
             "Stores: " + ", ".join(check.stores), "",
             "| condition | lab (95 % CI) | model runs | model mean (sd) | model range | ledge factor |",
             "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for c in check.conditions():
        lab = f"{check.lab[c][0]:.2f} +- {check.lab[c][1]:.2f}" if c in check.lab else "-"
        r = check.model(c)
        model = (f"| {len(r)} | {r.mean():.2f} ({_sd(r):.2f}) | "
                 f"{r.min():.2f}-{r.max():.2f} |" if len(r) else "| 0 | - | - |")
        lines.append(f"| {c} | {lab} {model} {check.ledge_factor(c):.3f} |")
    if by_stage:
        groups = check.by_stage()
        conditions = list(dict.fromkeys(c for _, c in groups))
        lines += ["", "R per stage, kg: mean (sd, runs)", "",
                  "| stage | " + " | ".join(conditions) + " |", "| --- |" + " ---: |" * len(conditions)]
        for stage in dict.fromkeys(st for st, _ in groups):
            cells = []
            for c in conditions:
                r = groups.get((stage, c))
                cells.append("-" if r is None else f"{r.mean():.2f} ({_sd(r):.2f}, {len(r)})")
            lines.append(f"| {stage} | " + " | ".join(cells) + " |")
    for f in check.fits:
        lines += ["", f"R at {f.condition} on the run parameters ({f.runs} runs, one fit, R^2 {f.r2:.2f}): "
                  "change of R per standard deviation of each parameter, kg", "",
                  "| parameter | per sd (se) | the parameter's sd |", "| --- | ---: | ---: |"]
        for n, (slope, se, sd) in sorted(f.slopes.items(), key=lambda kv: -abs(kv[1][0])):
            lines.append(f"| {n} | {slope:+.3f} ({se:.3f}) | {sd:.3g} |")
    return "\n".join(lines) + "\n"
