"""A KPI's change between two conditions at one parameter set: the contrast of a mixture's make-up.

Two conditions of one test differ in the mixture alone (75-25 and 25-75: the pellets' and the
sinter's shares swapped), so at a fixed parameter set the change of a KPI from one to the other,

    C = KPI(condition a) - KPI(condition b),

is what the make-up does to it. A calibration on one condition cannot see C: it can trade one
material's contribution against the other's and still match its own condition, and the other
conditions then show C. Discovery's design points run on every condition, so a discovery store
holds C at every point it tried. Reading C off every parameter set that a set of stores ran on both
conditions says whether any parameter or candidate they varied reaches the lab's C; when none
does, the cause lies in what they all held.

Contract:

* :func:`lab_contrast` ``(measured, a, b) -> {KPI: (C, 95 % half-width)}``: Table 2's means and the
  two CIs combined in quadrature (independent tests), for the KPIs both conditions report, under the
  DEM's names (``mass_flow_rate_full_kg_s`` for the lab's ``mass_flow_rate_kg_s``).
* :func:`contrast_check` ``(stores, measured, a, b, kpis) -> ContrastCheck``: every parameter set
  with finished runs on both conditions (jammed runs and runs without all of ``kpis`` left out;
  a run that two stores hold, as a discovery's copy of its baseline, counted once: same condition,
  seed and KPI values), its runs and
  KPI means on each; the DEM's replicate sd per condition and KPI pooled over the sets with two or
  more runs there. A condition the data lack is a :class:`~torchdem.errors.ConfigError` naming it.
* ``ContrastCheck.contrast(kpi)``: ``[n_sets]`` C; ``standard_error(kpi)``: ``[n_sets]`` its DEM
  standard error from the pooled sds and the set's runs; ``consistent(kpi)``: ``[n_sets]`` bool,
  ``|C - C_lab|`` within 1.96 x the combined standard error of the set's and the lab's.
* :func:`regress_contrast` ``(check, kpi) -> ContrastFit``: C on the parameters that every set names
  and that vary between the sets, by least squares weighted with each set's DEM standard error
  (:func:`bo.screening.effects.least_squares`; equal weights where the stores hold no replicates to
  give one): the change of C per
  standard deviation of each parameter over the sets, its standard error and p-value. It says which
  parameter of one campaign's space moves C, and by how much, from runs the campaign has already
  made (a campaign whose design points also ran on a second condition, as ``surrogate.jam_conditions``
  does). Sets of different models name different parameters, so it is meant for one campaign's store;
  fewer sets than the parameters plus two is a :class:`~torchdem.errors.ConfigError`.
* :func:`format_contrast` turns it into markdown (``scripts/contrast_check.py``); with ``by_stage``
  also C per stage (a discovery's candidates), with ``regress`` the fit of C on the parameters.

Stores are opened read-only, so a running campaign is not disturbed.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from scipy import stats

from bo.campaign.progress import finished_runs
from bo.screening.effects import least_squares
from bo.screening.pipeline import measured_name
from kpi.loadcell import discharge_jammed
from torchdem.drawdown import CALIBRATION_KPIS_DEM
from torchdem.errors import ConfigError
from torchdem.measured import MeasuredData

#: Normal quantile of a two-sided 95 % interval.
Z95 = 1.959964


@dataclass(frozen=True)
class ContrastSet:
    """One parameter set run on both conditions: where it came from, its parameters, and per
    condition (``a``, ``b``) its runs' KPI values ``{kpi: [n_runs]}``."""

    store: str
    stage: str
    params: Mapping[str, float]
    a: Mapping[str, np.ndarray]
    b: Mapping[str, np.ndarray]

    def runs(self, side: str) -> int:
        """Runs on condition ``side`` ("a" or "b")."""
        values = self.a if side == "a" else self.b
        return len(next(iter(values.values())))

    def contrast(self, kpi: str) -> float:
        """Mean on a less mean on b."""
        return float(np.mean(self.a[kpi]) - np.mean(self.b[kpi]))


@dataclass(frozen=True)
class ContrastCheck:
    """``between``: the two conditions (C = a - b); ``kpis``; ``lab``: KPI -> (C, 95 % half-width);
    ``sets``: the parameter sets; ``noise``: (condition, KPI) -> (pooled replicate sd, degrees of
    freedom), NaN sd without replicates."""

    stores: tuple[str, ...]
    between: tuple[str, str]
    kpis: tuple[str, ...]
    lab: Mapping[str, tuple[float, float]]
    sets: tuple[ContrastSet, ...]
    noise: Mapping[tuple[str, str], tuple[float, int]]

    def contrast(self, kpi: str) -> np.ndarray:
        """``[n_sets]`` C of each set."""
        return np.array([s.contrast(kpi) for s in self.sets])

    def standard_error(self, kpi: str) -> np.ndarray:
        """``[n_sets]`` DEM standard error of each set's C: sqrt(sd_a^2 / n_a + sd_b^2 / n_b)."""
        sd_a, sd_b = (self.noise[(c, kpi)][0] for c in self.between)
        return np.array([math.sqrt(sd_a ** 2 / s.runs("a") + sd_b ** 2 / s.runs("b")) for s in self.sets])

    def consistent(self, kpi: str) -> np.ndarray:
        """``[n_sets]`` whether the set's C agrees with the lab's at 95 %: ``|C - C_lab| <= 1.96
        sqrt(se^2 + (half-width / 1.96)^2)``; all False without the lab's C or the DEM's noise."""
        if kpi not in self.lab:
            return np.zeros(len(self.sets), dtype=bool)
        value, half = self.lab[kpi]
        se = self.standard_error(kpi)
        return np.abs(self.contrast(kpi) - value) <= Z95 * np.sqrt(se ** 2 + (half / Z95) ** 2)

    def by_stage(self) -> dict[str, list[ContrastSet]]:
        """Stage -> its sets, stages in the order the stores list them."""
        out: dict[str, list[ContrastSet]] = {}
        for s in self.sets:
            out.setdefault(s.stage, []).append(s)
        return out


@dataclass(frozen=True)
class ContrastFit:
    """C of one KPI on the sets' parameters (:func:`regress_contrast`). ``parameters``: their names;
    ``mean_params``, ``parameter_sd``: ``[n_parameters]`` their mean and sd (ddof 1) over the sets;
    ``effect``, ``effect_se``, ``p_value``: ``[n_parameters]`` the change of C per ``parameter_sd``,
    its standard error and two-sided p-value; ``mean_c``: C at the sets' mean parameters; ``r2``;
    ``residual_sd``: the sd of C about the fit, against ``noise_se``, the sets' mean DEM standard
    error of C (NaN without replicates); ``weighted``: whether the sets were weighted by their DEM
    standard errors."""

    kpi: str
    parameters: tuple[str, ...]
    mean_params: np.ndarray
    parameter_sd: np.ndarray
    effect: np.ndarray
    effect_se: np.ndarray
    p_value: np.ndarray
    mean_c: float
    r2: float
    residual_sd: float
    noise_se: float
    n_sets: int
    weighted: bool

    def at(self, params: Mapping[str, float]) -> float:
        """C the fit gives at ``params`` (every one of :attr:`parameters` named)."""
        missing = [n for n in self.parameters if n not in params]
        if missing:
            raise ConfigError(f"ContrastFit.at: {missing} are not given; the fit needs every one of "
                              f"{list(self.parameters)}")
        z = (np.array([params[n] for n in self.parameters]) - self.mean_params) / self.parameter_sd
        return float(self.mean_c + z @ self.effect)


def regress_contrast(check: ContrastCheck, kpi: str) -> ContrastFit:
    """C of ``kpi`` on the parameters every set names and that vary between them (module docstring)."""
    if kpi not in check.kpis:
        raise ConfigError(f"regress_contrast: KPI {kpi!r} is not one of the check's ({', '.join(check.kpis)})")
    sets = check.sets
    if not sets:
        raise ConfigError(f"regress_contrast: no parameter set ran on both {check.between[0]!r} and "
                          f"{check.between[1]!r} in {', '.join(check.stores)}; the fit needs runs of each set on both")
    common = sorted(set.intersection(*(set(s.params) for s in sets)))
    x = np.array([[float(s.params[n]) for n in common] for s in sets]).reshape(len(sets), len(common))
    keep = [i for i, n in enumerate(common) if np.all(np.isfinite(x[:, i])) and np.ptp(x[:, i]) > 0]
    names = tuple(common[i] for i in keep)
    if len(sets) < len(names) + 2 or not names:
        raise ConfigError(f"regress_contrast: {len(sets)} parameter sets ran on both {check.between[0]!r} and "
                          f"{check.between[1]!r}, and they vary {len(names)} parameters that all of them name "
                          f"({', '.join(names) or 'none'}); the fit needs at least the parameters plus two sets")
    x = x[:, keep]
    mean, sd = x.mean(axis=0), x.std(axis=0, ddof=1)
    z = np.column_stack([np.ones(len(sets)), (x - mean) / sd])
    y = check.contrast(kpi)
    se = check.standard_error(kpi)
    weighted = bool(np.all(np.isfinite(se)) and np.all(se > 0))
    w = 1.0 / se ** 2 if weighted else np.ones(len(y))
    fit = least_squares(z, y, w)
    if fit is None:
        raise ConfigError(f"regress_contrast: the {len(sets)} sets' parameters ({', '.join(names)}) are collinear; "
                          "the fit needs sets that vary them independently")
    beta, beta_se, _, dof = fit
    resid = y - z @ beta
    centred = y - np.average(y, weights=w)
    return ContrastFit(kpi=kpi, parameters=names, mean_params=mean, parameter_sd=sd, effect=beta[1:],
                       effect_se=beta_se[1:], p_value=2.0 * stats.t.sf(np.abs(beta[1:] / beta_se[1:]), dof),
                       mean_c=float(beta[0]), r2=1.0 - float(w @ resid ** 2) / float(w @ centred ** 2),
                       residual_sd=float(np.sqrt(resid @ resid / dof)),
                       noise_se=float(se.mean()) if weighted else math.nan, n_sets=len(sets), weighted=weighted)


def lab_contrast(measured: MeasuredData, a: str, b: str,
                 kpis: Sequence[str] = CALIBRATION_KPIS_DEM) -> dict[str, tuple[float, float]]:
    """KPI (DEM name) -> (mean on ``a`` less mean on ``b``, hypot of the two 95 % half-widths), for
    the KPIs both conditions report."""
    ca, cb = measured.condition(a), measured.condition(b)
    out = {}
    for kpi in kpis:
        name = measured_name(kpi)
        if name in ca.kpis and name in cb.kpis:
            va, vb = ca.kpis[name], cb.kpis[name]
            out[kpi] = (va.mean - vb.mean, math.hypot(va.ci95, vb.ci95))
    return out


def _store_runs(path: Path, conditions: Sequence[str], kpis: Sequence[str]):
    """``(stage, params key, params, condition, seed, values)`` of every finished run on
    ``conditions`` that flowed and has every KPI finite."""
    out = []
    for stage, condition, seed, p, k in finished_runs(path, "contrast_check"):
        if condition not in conditions or discharge_jammed(k) or not all(
                math.isfinite(k.get(n, math.nan)) for n in kpis):
            continue
        out.append((stage, json.dumps(p, sort_keys=True), p, condition, seed, tuple(k[n] for n in kpis)))
    return out


def _pooled_sd(groups: Sequence[np.ndarray]) -> tuple[float, int]:
    """Replicate sd pooled over the groups of two or more values, and its degrees of freedom."""
    ss = sum(float(((g - g.mean()) ** 2).sum()) for g in groups if len(g) > 1)
    dof = sum(len(g) - 1 for g in groups if len(g) > 1)
    return (math.sqrt(ss / dof) if dof else math.nan), dof


def contrast_check(stores: Sequence[str | Path], measured: MeasuredData, a: str = "25-75", b: str = "75-25",
                   kpis: Sequence[str] = CALIBRATION_KPIS_DEM, across_stages: bool = False) -> ContrastCheck:
    """The lab's contrast between ``a`` and ``b`` and the model's at every parameter set the stores
    ran on both (module docstring). A set is a store's runs of one stage and one parameter set;
    ``across_stages``: of one parameter set in any stage of its store, so that a calibrated set's
    verification on one condition and its validation on another pair up (its stage is then named
    ``verification+validation``)."""
    for name in (a, b):
        if name not in measured.names:
            raise ConfigError(f"contrast_check: condition {name!r} is not in {measured.origin or 'the measured data'}; "
                              f"known conditions: {', '.join(measured.names)}")
    if a == b:
        raise ConfigError(f"contrast_check: the two conditions are both {a!r}; expected two different conditions")
    kpis = tuple(kpis)
    seen: set = set()
    groups: dict[tuple[str, str, str], dict] = {}
    for s in stores:
        for stage, key, params, condition, seed, values in _store_runs(Path(s), (a, b), kpis):
            if (condition, seed, values) in seen:  # the same run in two stores (a discovery's copy of its baseline)
                continue
            seen.add((condition, seed, values))
            group = groups.setdefault((str(s), "" if across_stages else stage, key),
                                      {"params": params, "stages": [], a: [], b: []})
            if stage not in group["stages"]:
                group["stages"].append(stage)
            group[condition].append(values)
    sets = tuple(ContrastSet(store, "+".join(g["stages"]), g["params"],
                             {k: np.array([v[i] for v in g[a]]) for i, k in enumerate(kpis)},
                             {k: np.array([v[i] for v in g[b]]) for i, k in enumerate(kpis)})
                 for (store, _, _), g in groups.items() if g[a] and g[b])
    noise = {}
    for condition in (a, b):
        for i, k in enumerate(kpis):
            noise[(condition, k)] = _pooled_sd([np.array([v[i] for v in g[condition]]) for g in groups.values()])
    return ContrastCheck(tuple(str(s) for s in stores), (a, b), kpis, lab_contrast(measured, a, b, kpis), sets, noise)


def _short(kpi: str) -> str:
    return {"angle_of_repose_deg": "angle of repose, deg", "shear_angle_deg": "shear angle, deg",
            "mass_flow_rate_full_kg_s": "flow, kg/s", "mass_lower_box_full_kg": "lower box, kg"}.get(kpi, kpi)


def set_labels(sets: Sequence[ContrastSet]) -> list[str]:
    """A short name of each set: the parameters whose values differ between the sets of its store and
    stage, as ``name=value``: where it leaves the value most of them share, or, for a parameter without
    such a value, its own (``"(only set)"`` when its store and stage hold one set, ``"(common)"`` for
    the set of the shared values)."""
    labels = []
    for s in sets:
        peers = [t for t in sets if t.store == s.store and t.stage == s.stage]
        if len(peers) == 1:
            labels.append("(only set)")
            continue
        names = sorted(set().union(*(t.params for t in peers)))
        varying = [n for n in names if len({t.params.get(n) for t in peers}) > 1]
        values = {n: [t.params.get(n) for t in peers] for n in varying}
        # a value that more peers share than any other is the common one, and a set is labelled by where
        # it leaves it; without one (two sets, say), by the value it has
        def common(n):
            counts = {v: values[n].count(v) for v in values[n]}
            top = max(counts.values())
            modes = [v for v, c in counts.items() if c == top]
            return modes[0] if len(modes) == 1 else None
        own = [n for n in varying if s.params.get(n) is not None and s.params[n] != common(n)]
        labels.append(", ".join(f"{n}={s.params[n]:.4g}" for n in own) or "(common)")
    return labels


def format_contrast(check: ContrastCheck, by_stage: bool = False, by_set: bool = False,
                    regress: bool = False, at: Mapping[str, float] | None = None) -> str:
    """Markdown: per KPI the lab's contrast and the model's over the sets, how many agree with the
    lab's; ``by_stage``: then the mean contrast per stage; ``by_set``: then every set's C, its DEM
    standard error, and ``*`` where it agrees with the lab's; ``regress``: then, per KPI, C's fit on
    the sets' parameters (:func:`regress_contrast`), and with ``at`` (a parameter set, e.g. a
    calibration's) the C the fit gives there."""
    a, b = check.between
    lines = [f"## Contrast between conditions, C = KPI({a}) - KPI({b}), at each parameter set", "",
             "Stores: " + ", ".join(check.stores), "",
             f"{len(check.sets)} parameter sets ran on both conditions. DEM replicate sd pooled over the sets "
             "(degrees of freedom): " + "; ".join(
                 f"{_short(k)} {check.noise[(a, k)][0]:.3g} ({check.noise[(a, k)][1]}) at {a}, "
                 f"{check.noise[(b, k)][0]:.3g} ({check.noise[(b, k)][1]}) at {b}" for k in check.kpis), "",
             "| KPI | lab C (95 % CI) | model C: mean (sd over sets) | model range | sets agreeing with the lab |",
             "| --- | ---: | ---: | ---: | ---: |"]
    for k in check.kpis:
        c = check.contrast(k)
        lab = f"{check.lab[k][0]:+.2f} +- {check.lab[k][1]:.2f}" if k in check.lab else "-"
        model = (f"{c.mean():+.2f} ({c.std(ddof=1) if len(c) > 1 else 0.0:.2f}) | {c.min():+.2f} to {c.max():+.2f}"
                 if len(c) else "- | -")
        lines.append(f"| {_short(k)} | {lab} | {model} | {int(check.consistent(k).sum())} of {len(c)} |")
    if by_stage:
        lines += ["", "Mean C per stage (sets)", "",
                  "| store | stage | sets | " + " | ".join(_short(k) for k in check.kpis) + " |",
                  "| --- | --- | ---: |" + " ---: |" * len(check.kpis)]
        for stage, sets in check.by_stage().items():
            for store in dict.fromkeys(s.store for s in sets):
                mine = [s for s in sets if s.store == store]
                lines.append(f"| {Path(store).name} | {stage} | {len(mine)} | "
                             + " | ".join(f"{np.mean([s.contrast(k) for s in mine]):+.2f}" for k in check.kpis) + " |")
    if by_set:
        se = {k: check.standard_error(k) for k in check.kpis}
        agree = {k: check.consistent(k) for k in check.kpis}
        lines += ["", "C per set (DEM standard error; * agrees with the lab's)", "",
                  f"| store | stage | set | runs {a} / {b} | " + " | ".join(_short(k) for k in check.kpis) + " |",
                  "| --- | --- | --- | ---: |" + " ---: |" * len(check.kpis)]
        for i, (s, label) in enumerate(zip(check.sets, set_labels(check.sets))):
            lines.append(f"| {Path(s.store).name} | {s.stage} | {label} | {s.runs('a')} / {s.runs('b')} | " + " | ".join(
                f"{s.contrast(k):+.2f} ({se[k][i]:.2f}){'*' if agree[k][i] else ''}" for k in check.kpis) + " |")
    if regress:
        lines += ["", "C on the parameters the sets vary (weighted least squares): change of C per standard deviation "
                  "of each parameter over the sets, largest |t| first"]
        for k in check.kpis:
            try:
                fit = regress_contrast(check, k)
            except ConfigError as exc:  # the tables above stand without it
                lines += ["", f"No fit: {exc}"]
                break
            noise = f"{fit.noise_se:.2f}" if fit.weighted else "not known (no replicates; equal weights)"
            lab = f"; the lab's {check.lab[k][0]:+.2f}" if k in check.lab else ""
            lines += ["", f"{_short(k)}: {fit.n_sets} sets, R^2 {fit.r2:.2f}, C at the sets' mean parameters "
                      f"{fit.mean_c:+.2f}{lab}; residual sd {fit.residual_sd:.2f} against the DEM's standard error "
                      f"of a set's C {noise}" + (f"; at the given set {fit.at(at):+.2f}" if at is not None else ""), "",
                      "| parameter | per sd (se) | p | the parameter's sd |", "| --- | ---: | ---: | ---: |"]
            for j in np.argsort(-np.abs(fit.effect / fit.effect_se)):
                lines.append(f"| {fit.parameters[j]} | {fit.effect[j]:+.3f} ({fit.effect_se[j]:.3f}) | "
                             f"{fit.p_value[j]:.2g} | {fit.parameter_sd[j]:.3g} |")
    return "\n".join(lines) + "\n"
