"""Numerical studies before calibration: the time-step study (paper section 3.2.4, Fig. 9) and
the reduced-shear-modulus study, both run through the campaign store so they resume.

Contract
--------
``run_time_step_study(store, executor, *, condition, params, fractions, seeds, kpis)`` runs the
reference parameter set ``params`` at every time-step fraction of the Rayleigh time step, one
replicate per seed. Each fraction is the condition ``torchdem.model.variant(condition,
time_step_fraction=f)`` and one store batch (stage ``"timestep"``, key
``timestep/<variant condition>``), so a rerun with the same store evaluates only what never
finished, and adding a fraction or a seed adds only the new runs (a seed list change makes a new
batch key, ``.../seeds=<hash>``). It returns a ``StudyRuns`` (KPI values
``[n_values, replicates, n_kpi]``, NaN for failures, and the mean wall time per value).

``run_shear_modulus_study(store, executor, *, condition, params, shear_moduli_pa, seeds, kpis)``
does the same with ``variant(condition, shear_modulus=G)`` under stage ``"shear_modulus"``.

``time_step_report(runs, out_dir, ...)`` applies ``bo.studies.timestep.choose_time_step`` and writes
``timestep.json``, ``timestep.md`` and ``fig9_time_step.png``; ``shear_modulus_report`` applies
``bo.studies.timestep.summarise_shear_modulus_study`` (wall times give the measured speed-up) and
writes ``shear_modulus.json`` and ``shear_modulus.md``. The wall time of an evaluation is the
wall time of the ensemble it ran in, so compare values whose replicates ran in batches of one
size (``batch_size >= replicates``, the default).

``run_precision_study(store, executor, *, condition, params, dtypes, seeds, kpis)`` runs the
same in each floating-point precision (``variant(condition, dtype=...)``, stage ``"precision"``);
``precision_report`` applies ``bo.studies.precision.precision_verdict`` (TOST per KPI against the
lab's CI half-width) and writes ``precision.json`` and ``precision.md``.

``run_geometry_study(store, executor, *, condition, geometries, parameter_sets, seeds, kpis, ...)``
runs every named parameter set in every geometry (condition variants of ``slice_depth`` and
``mirror``, stage ``"geometry"``); ``geometry_report`` applies
``bo.studies.geometry.geometry_comparison`` and writes ``geometry.json`` and ``geometry.md``.

``STUDY_STAGES`` are the extra stage names to open the store with.
``smallest_sphere_rayleigh_time_step(mixture, settings)`` is Eq. 3 for the smallest sphere the
sieve allows (smallest sieve size after the fines cut x the smallest template sphere), the
report's conversion of fractions to seconds; a run's own step uses its smallest *sampled*
sphere, so it is this or slightly longer.

Reference: A. Hadi, Y. Pang, D. Schott, section 3.2.4, Eq. 3, Fig. 9.
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from torchdem.model import variant
from bo.campaign.executor import Executor, canonical_params, run_pending
from bo.screening.pipeline import _check_kpis, json_ready
from bo.campaign.store import CampaignStore
from bo.studies.precision import PrecisionVerdict, precision_verdict
from bo.studies.timestep import ShearModulusSummary, TimeStepChoice, choose_time_step, summarise_shear_modulus_study
from torchdem.errors import ConfigError, out_of_range

__all__ = [
    "STUDY_STAGES",
    "smallest_sphere_rayleigh_time_step",
    "StudyRuns",
    "run_time_step_study",
    "run_shear_modulus_study",
    "time_step_report",
    "shear_modulus_report",
    "run_precision_study",
    "precision_report",
    "GeometryRuns",
    "run_geometry_study",
    "geometry_report",
]

STUDY_STAGES = ("timestep", "shear_modulus", "precision", "geometry")
DTYPES = ("float64", "float32")


@dataclass(frozen=True, eq=False)
class StudyRuns:
    """KPIs of a study: one row per studied value (time-step fraction or shear modulus).

    Attributes:
        setting: ``"time_step_fraction"`` or ``"shear_modulus"``.
        values: the studied values, in the order given.
        conditions: the variant condition of each value.
        seeds: one per replicate.
        kpi_names: KPI columns.
        kpi_values: ``[n_values, replicates, n_kpi]``, NaN for failures / unmeasured KPIs.
        wall_time_s: ``[n_values]`` mean wall time of the evaluations of each value (NaN if none
            finished).
        n_failed: ``[n_values]`` failed evaluations.
    """

    setting: str
    values: tuple[float, ...]
    conditions: tuple[str, ...]
    seeds: tuple[int, ...]
    kpi_names: tuple[str, ...]
    kpi_values: np.ndarray
    wall_time_s: np.ndarray
    n_failed: np.ndarray

    def to_dict(self) -> dict:
        return json_ready({"setting": self.setting, "values": list(self.values),
                        "conditions": list(self.conditions), "seeds": list(self.seeds),
                        "kpi_names": list(self.kpi_names), "kpi_values": self.kpi_values,
                        "wall_time_s": self.wall_time_s, "n_failed": self.n_failed})


def smallest_sphere_rayleigh_time_step(mixture, settings) -> float:
    """Rayleigh time step (Eq. 3) of the smallest sphere ``mixture`` can hold under ``settings``
    (``torchdem.drawdown.RunSettings``: fines cut and shear-modulus override), s."""
    from torchdem.materials import rayleigh_time_step
    from torchdem.mixture import scalp_mixture

    mix = scalp_mixture(mixture, settings.fines_cut, "sim.fines_cut")
    steps = []
    for m in mix.materials:
        d_min = min(c.d_min for c in m.sieve if c.mass_fraction > 0)
        radius = d_min * float(np.min(m.template.radii))  # template radii are per unit sieve size
        g = settings.shear_modulus if settings.shear_modulus is not None else m.shear_modulus
        steps.append(rayleigh_time_step(radius, m.density, g, m.poisson_ratio))
    return min(steps)


def _check_values(values, name: str, allowed: str, low: float, high: float, source: str) -> tuple[float, ...]:
    if isinstance(values, (str, bytes)) or not isinstance(values, Sequence):
        raise out_of_range(name, values, allowed, source)
    try:
        out = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise out_of_range(name, list(values), allowed, source) from None
    if len(out) < 2 or len(set(out)) != len(out) or not all(math.isfinite(v) and low < v <= high for v in out):
        raise out_of_range(name, list(values), allowed, source)
    return out


def _check_seeds(seeds, source: str) -> tuple[int, ...]:
    allowed = "at least two distinct int seeds (one per replicate; the criteria need a spread)"
    if isinstance(seeds, (str, bytes)) or not isinstance(seeds, Sequence) \
            or any(isinstance(s, bool) or not isinstance(s, (int, np.integer)) for s in seeds) \
            or len(seeds) < 2 or len(set(int(s) for s in seeds)) != len(seeds):
        raise out_of_range("seeds", seeds, allowed, source)
    return tuple(int(s) for s in seeds)


def _run_study(store: CampaignStore, executor: Executor, stage: str, setting: str, condition: str,
               params: Mapping[str, float], values: Sequence[float], seeds: Sequence[int],
               kpis: Sequence[str]) -> StudyRuns:
    source = f"{stage} study"
    if not isinstance(condition, str) or not condition or "|" in condition:
        raise out_of_range("condition", condition, "a base condition name such as '50-50'", source)
    point = canonical_params(params, f"{source}: params")
    seed_tag = hashlib.sha256(json.dumps(list(seeds)).encode()).hexdigest()[:8]
    conditions = tuple(variant(condition, **{setting: v}) for v in values)
    keys = []
    for cond in conditions:
        key = f"{stage}/{cond}/seeds={seed_tag}"
        stored = store.batch(stage, key, lambda: [point], seeds=list(seeds), conditions=[cond])
        if stored != [point]:
            raise ConfigError(f"{store.path}: batch {stage}/{key} holds parameters {stored}, not {[point]}; "
                              f"use a new store for other reference parameters")
        keys.append(key)
    run_pending(store, executor, stage)
    out = np.full((len(values), len(seeds), len(kpis)), np.nan)
    walls = np.full(len(values), np.nan)
    failed = np.zeros(len(values), dtype=np.int64)
    for i, (cond, key) in enumerate(zip(conditions, keys)):
        out[i], times, failed[i] = _collect(store, stage, key, cond, seeds, kpis)
        if times:
            walls[i] = float(np.mean(times))
    return StudyRuns(setting=setting, values=tuple(values), conditions=conditions, seeds=tuple(seeds),
                     kpi_names=tuple(kpis), kpi_values=out, wall_time_s=walls, n_failed=failed)


def _collect(store: CampaignStore, stage: str, key: str, condition: str, seeds: Sequence[int],
             kpis: Sequence[str]) -> tuple[np.ndarray, list[float], int]:
    """KPIs ``[seeds, kpis]`` of one batch's runs (NaN: failed or unmeasured), the wall times of
    the runs that were computed, and the number of failures."""
    out = np.full((len(seeds), len(kpis)), np.nan)
    times, failed = [], 0
    for rec in store.records(stage, batch_key=key, condition=condition):
        if rec.status == "failed":
            failed += 1
        if rec.status != "done" or rec.kpis is None:
            continue
        out[list(seeds).index(rec.seed)] = [rec.kpis.get(k, math.nan) for k in kpis]
        if rec.wall_time is not None:
            times.append(rec.wall_time)
    out[~np.isfinite(out)] = np.nan
    return out, times, failed


def run_time_step_study(store: CampaignStore, executor: Executor, *, condition: str,
                        params: Mapping[str, float], fractions: Sequence[float], seeds: Sequence[int],
                        kpis: Sequence[str], stage: str = "timestep") -> StudyRuns:
    """Run (or resume) the reference parameters at every time-step fraction; see the module docstring."""
    source = "run_time_step_study"
    fractions = _check_values(fractions, "fractions", "at least two distinct fractions of the Rayleigh "
                              "time step in (0, 1], e.g. [0.05, 0.1, 0.15, 0.2, 0.3, 0.4]", 0.0, 1.0, source)
    seeds = _check_seeds(seeds, source)
    kpis = _check_kpis(kpis, source)
    store.check_stage(stage, source)
    return _run_study(store, executor, stage, "time_step_fraction", condition, params, fractions, list(seeds), kpis)


def run_shear_modulus_study(store: CampaignStore, executor: Executor, *, condition: str,
                            params: Mapping[str, float], shear_moduli_pa: Sequence[float],
                            seeds: Sequence[int], kpis: Sequence[str],
                            stage: str = "shear_modulus") -> StudyRuns:
    """Run (or resume) the reference parameters at every particle shear modulus."""
    source = "run_shear_modulus_study"
    moduli = _check_values(shear_moduli_pa, "shear_moduli_pa", "at least two distinct shear moduli "
                           "> 0 Pa, e.g. [1e8, 1e7, 1e6]", 0.0, math.inf, source)
    seeds = _check_seeds(seeds, source)
    kpis = _check_kpis(kpis, source)
    store.check_stage(stage, source)
    return _run_study(store, executor, stage, "shear_modulus", condition, params, moduli, list(seeds), kpis)


def run_precision_study(store: CampaignStore, executor: Executor, *, condition: str,
                        params: Mapping[str, float], dtypes: Sequence[str], seeds: Sequence[int],
                        kpis: Sequence[str], stage: str = "precision") -> StudyRuns:
    """Run (or resume) the reference parameters in every floating-point precision of ``dtypes``."""
    source = "run_precision_study"
    dtypes = tuple(dtypes)
    if len(dtypes) != 2 or len(set(dtypes)) != 2 or any(d not in DTYPES for d in dtypes):
        raise out_of_range("dtypes", list(dtypes), f"two distinct precisions of {list(DTYPES)}, the reference first",
                           source)
    seeds = _check_seeds(seeds, source)
    kpis = _check_kpis(kpis, source)
    store.check_stage(stage, source)
    return _run_study(store, executor, stage, "dtype", condition, params, dtypes, list(seeds), kpis)


def precision_report(runs: StudyRuns, out_dir, *, margins: Mapping[str, float], alpha: float = 0.05,
                     power: float = 0.8, minimum_seeds: int = 10) -> tuple[PrecisionVerdict, dict[str, Path]]:
    """TOST of the second precision against the first per KPI; writes precision.json and .md."""
    verdict = precision_verdict(runs.kpi_values[0], runs.kpi_values[1], runs.kpi_names, margins,
                                labels=(str(runs.values[0]), str(runs.values[1])), alpha=alpha, power=power,
                                minimum_seeds=minimum_seeds)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    walls = {str(v): (None if not np.isfinite(w) else float(w)) for v, w in zip(runs.values, runs.wall_time_s)}
    payload = {**verdict.to_dict(), "seeds": list(runs.seeds), "conditions": list(runs.conditions),
               "failed_runs": {str(v): int(n) for v, n in zip(runs.values, runs.n_failed)},
               "mean_wall_time_s": walls}
    files = {"json": out / "precision.json", "md": out / "precision.md"}
    files["json"].write_text(json.dumps(json_ready(payload), indent=2))
    files["md"].write_text(f"# Precision study: {runs.conditions[1]} against {runs.conditions[0]}\n\n"
                           f"Seeds: {list(runs.seeds)}; failed runs: {payload['failed_runs']}; mean wall time "
                           f"per run (s): {walls}\n\n{verdict.to_text()}\n")
    return verdict, files


def _measured_columns(runs: StudyRuns, deciding: Sequence[str] | None, source: str) -> list[str]:
    """KPIs with >= 2 finite replicates at every value (the others cannot be judged)."""
    ok = [k for j, k in enumerate(runs.kpi_names)
          if np.all(np.isfinite(runs.kpi_values[:, :, j]).sum(axis=1) >= 2)]
    if deciding is not None:
        unknown = [k for k in deciding if k not in runs.kpi_names]
        if unknown:
            raise ConfigError(f"{source}: deciding KPIs {unknown} are not among the study's KPIs "
                              f"{list(runs.kpi_names)}")
    if not ok:
        raise ConfigError(f"{source}: no KPI has at least 2 finite replicates at every value "
                          f"{list(runs.values)} (failed evaluations: {runs.n_failed.tolist()}); "
                          f"add replicates or check the runs")
    return ok



def _analysed_kpis(runs: StudyRuns, deciding_kpis: Sequence[str] | None, source: str, level: str
                   ) -> tuple[list[str], list[str], list[str], list[int]]:
    """KPIs measured twice at every study level (usable), those left out, the deciding ones
    and the usable columns of ``runs.kpi_values``."""
    usable = _measured_columns(runs, deciding_kpis, source)
    left_out = [k for k in runs.kpi_names if k not in usable]
    deciding = [k for k in (deciding_kpis or usable) if k in usable]
    if not deciding:
        raise ConfigError(f"{source}: none of the deciding KPIs {list(deciding_kpis)} was measured with "
                          f"2 finite replicates at every {level}; measured: {usable}")
    return usable, left_out, deciding, [runs.kpi_names.index(k) for k in usable]

def time_step_report(runs: StudyRuns, out_dir, *, rayleigh_time_step_s: float | None = None,
                     deciding_kpis: Sequence[str] | None = None, relative_tolerance: float = 0.02,
                     std_growth_factor: float = 2.0) -> tuple[TimeStepChoice, dict[str, Path]]:
    """``choose_time_step`` on the study and its files (JSON, Markdown, Fig. 9 PNG).

    KPIs without two finite replicates at every fraction are left out of the analysis (and
    named in the report); deciding KPIs default to every analysed KPI.
    """
    from bo.report.plots import write_time_step_plot

    usable, left_out, deciding, cols = _analysed_kpis(runs, deciding_kpis, "time_step_report", "fraction")
    choice = choose_time_step(runs.values, runs.kpi_values[:, :, cols], usable, kpis=deciding,
                              relative_tolerance=relative_tolerance, std_growth_factor=std_growth_factor,
                              rayleigh_time_step_s=rayleigh_time_step_s)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = {"fig9": write_time_step_plot(choice, out / "fig9_time_step.png")}
    order = np.argsort(runs.values)
    walls = ", ".join(f"{runs.values[i]:g}: {runs.wall_time_s[i]:.1f} s" for i in order)
    text = "\n".join(["# Time-step study (Fig. 9)", "", "```", choice.to_text(), "```", "",
                      f"KPIs left out (not measured twice at every fraction): {left_out or 'none'}",
                      f"Wall time per ensemble by fraction: {walls}",
                      f"Failed evaluations by fraction: {dict(zip(runs.values, runs.n_failed.tolist()))}",
                      "", "- fig9_time_step.png", ""])
    files["timestep_md"] = out / "timestep.md"
    files["timestep_md"].write_text(text)
    files["timestep_json"] = out / "timestep.json"
    files["timestep_json"].write_text(json.dumps(json_ready({"runs": runs.to_dict(), "choice": choice.to_dict(),
                                                          "left_out_kpis": left_out}),
                                                 indent=2, allow_nan=False) + "\n")
    return choice, files


def shear_modulus_report(runs: StudyRuns, out_dir, *, deciding_kpis: Sequence[str] | None = None,
                         relative_tolerance: float = 0.02
                         ) -> tuple[ShearModulusSummary, dict[str, Path]]:
    """``summarise_shear_modulus_study`` on the study (wall times included) and its files."""
    usable, left_out, deciding, cols = _analysed_kpis(runs, deciding_kpis, "shear_modulus_report", "modulus")
    walls = runs.wall_time_s if np.all(np.isfinite(runs.wall_time_s)) else None
    summary = summarise_shear_modulus_study(runs.values, runs.kpi_values[:, :, cols], usable, walls,
                                            relative_tolerance=relative_tolerance, kpis=deciding)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    text = "\n".join(["# Reduced shear modulus study", "", "```", summary.to_text(), "```", "",
                      f"KPIs left out (not measured twice at every modulus): {left_out or 'none'}", ""])
    files = {"shear_modulus_md": out / "shear_modulus.md", "shear_modulus_json": out / "shear_modulus.json"}
    files["shear_modulus_md"].write_text(text)
    payload = {"runs": runs.to_dict(), "left_out_kpis": left_out,
               "summary": {"shear_moduli_pa": list(summary.shear_moduli_pa),
                           "reference_modulus_pa": summary.reference_modulus_pa,
                           "kpi_names": list(summary.kpi_names), "mean": summary.mean, "std": summary.std,
                           "change": summary.change, "relative_change": summary.relative_change,
                           "within_tolerance": summary.within_tolerance,
                           "expected_speedup": list(summary.expected_speedup),
                           "measured_speedup": None if summary.measured_speedup is None
                           else list(summary.measured_speedup),
                           "recommended_modulus_pa": summary.recommended_modulus_pa,
                           "reasoning": list(summary.reasoning)}}
    files["shear_modulus_json"].write_text(json.dumps(json_ready(payload), indent=2, allow_nan=False) + "\n")
    return summary, files


@dataclass(frozen=True, eq=False)
class GeometryRuns:
    """KPIs of a geometry study.

    Attributes:
        geometries: name -> geometry variant (``{"slice_depth": 0.1, "mirror": True}``), reference first.
        parameter_sets: name -> parameters. seeds: one per replicate. kpi_names: KPI columns.
        kpi_values: parameter set -> geometry -> ``[replicates, n_kpi]`` (NaN for failures).
        cost_per_run_s: geometry -> mean wall time of its ensembles / members per ensemble (the executor's
            batch size, at most the runs of one geometry), s.
        n_failed: parameter set -> geometry -> failed evaluations.
    """

    geometries: Mapping[str, Mapping[str, object]]
    parameter_sets: Mapping[str, Mapping[str, float]]
    seeds: tuple[int, ...]
    kpi_names: tuple[str, ...]
    kpi_values: Mapping[str, Mapping[str, np.ndarray]]
    cost_per_run_s: Mapping[str, float]
    n_failed: Mapping[str, Mapping[str, int]]

    def to_dict(self) -> dict:
        return json_ready({"geometries": {k: dict(v) for k, v in self.geometries.items()},
                           "parameter_sets": {k: dict(v) for k, v in self.parameter_sets.items()},
                           "seeds": list(self.seeds), "kpi_names": list(self.kpi_names),
                           "kpi_values": {p: {g: v for g, v in by.items()} for p, by in self.kpi_values.items()},
                           "cost_per_run_s": dict(self.cost_per_run_s),
                           "n_failed": {p: dict(by) for p, by in self.n_failed.items()}})


def run_geometry_study(store: CampaignStore, executor: Executor, *, condition: str,
                       geometries: Mapping[str, Mapping[str, object]],
                       parameter_sets: Mapping[str, Mapping[str, float]], seeds: Sequence[int],
                       kpis: Sequence[str], members_per_ensemble: int, stage: str = "geometry") -> GeometryRuns:
    """Run (or resume) every parameter set in every geometry (condition variants, the reference
    geometry first; see :mod:`bo.studies.geometry`). Each (parameter set, geometry) is one store
    batch; the batches are queued parameter set by parameter set, so an interrupted study has
    its first parameter set complete first."""
    source = "run_geometry_study"
    if not isinstance(condition, str) or not condition or "|" in condition:
        raise out_of_range("condition", condition, "a base condition name such as '50-50'", source)
    if len(geometries) < 2:
        raise out_of_range("geometries", list(geometries), "at least two geometries, the reference first", source)
    if not parameter_sets:
        raise out_of_range("parameter_sets", parameter_sets, "at least one named parameter set", source)
    seeds = list(_check_seeds(seeds, source))
    kpis = _check_kpis(kpis, source)
    store.check_stage(stage, source)
    seed_tag = hashlib.sha256(json.dumps(seeds).encode()).hexdigest()[:8]
    keys = {}
    for pset, params in parameter_sets.items():
        point = canonical_params(params, f"{source}: parameter_sets.{pset}")
        for g, changes in geometries.items():
            cond = variant(condition, **dict(changes))
            key = f"{stage}/{pset}/{cond}/seeds={seed_tag}"
            stored = store.batch(stage, key, lambda: [point], seeds=seeds, conditions=[cond])
            if stored != [point]:
                raise ConfigError(f"{store.path}: batch {key} holds parameters {stored}, not {[point]}; "
                                  f"give the changed parameter set a new name")
            keys[pset, g] = (key, cond)
    run_pending(store, executor, stage)
    values: dict[str, dict[str, np.ndarray]] = {}
    failed: dict[str, dict[str, int]] = {}
    walls: dict[str, list[float]] = {g: [] for g in geometries}
    for (pset, g), (key, cond) in keys.items():
        out, times, n_failed = _collect(store, stage, key, cond, seeds, kpis)
        walls[g] += times
        values.setdefault(pset, {})[g] = out
        failed.setdefault(pset, {})[g] = n_failed
    # the executor fills an ensemble with runs of one condition, across parameter sets
    per_run = max(1, min(int(members_per_ensemble), len(seeds) * len(parameter_sets)))
    cost = {g: float(np.mean(w)) / per_run if w else math.nan for g, w in walls.items()}
    return GeometryRuns(geometries=dict(geometries), parameter_sets=dict(parameter_sets), seeds=tuple(seeds),
                        kpi_names=tuple(kpis), kpi_values=values, cost_per_run_s=cost, n_failed=failed)


def geometry_report(runs: GeometryRuns, out_dir, *, lab_margins: Mapping[str, float] | None = None):
    """:func:`bo.studies.geometry.geometry_comparison` on the study; writes geometry.json and .md."""
    from bo.studies.geometry import geometry_comparison

    comparison = geometry_comparison(runs.kpi_values, runs.kpi_names, runs.cost_per_run_s, lab_margins=lab_margins)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = {"json": out / "geometry.json", "md": out / "geometry.md"}
    files["json"].write_text(json.dumps(json_ready({"runs": runs.to_dict(), "comparison": comparison.to_dict()}),
                                        indent=2) + "\n")
    geoms = "; ".join(f"{g}: {dict(v)}" for g, v in runs.geometries.items())
    files["md"].write_text(f"# Geometry study\n\nGeometries (condition variants): {geoms}\n\nSeeds: "
                           f"{list(runs.seeds)}; failed runs: {runs.n_failed}\n\n{comparison.to_text()}\n")
    return comparison, files
