"""``torchdem-study``: the time-step study (Hadi et al. section 3.2.4, Fig. 9) and the
reduced-shear-modulus study as a Hydra app.

Usage::

    torchdem-study study=timestep                       # study_profile=mini: a few minutes
    torchdem-study study=shear_modulus store=/tmp/study.sqlite
    torchdem-study study=timestep study_profile=paper store=ts.sqlite   # 5 % .. 40 %, 5 replicates

Config: ``conf/study.yaml``; the model is that of ``conf/simulate.yaml``, sized by
``conf/study_profile/``. Every studied value is one store batch of a variant condition
(``torchdem.model.variant``), so a rerun with the same ``store=PATH`` evaluates nothing that finished
and adding a value runs only that value. Writes ``timestep.md``, ``timestep.json`` and
``fig9_time_step.png`` or ``shear_modulus.md`` and ``shear_modulus.json`` to the Hydra run
directory. ``main()`` only builds typed objects and calls ``bo.studies.pipeline``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import hydra
from omegaconf import DictConfig

from bo.cli.common import (_int, check_kpis, checkpoint_dir_for, executor_from, executor_settings_from,
                           measured_kpis_from, model_from, open_store, plain_config, replicate_seeds, requeue_failed,
                           store_path_from)
from torchdem.cli import CONF_DIR, one_line_errors
from torchdem.errors import ConfigError, out_of_range

STUDIES = ("timestep", "shear_modulus", "precision", "geometry")


@dataclass(frozen=True)
class StudySettings:
    """Checked settings of one study run."""

    study: str
    values: tuple[float, ...]
    seeds: tuple[int, ...]
    condition: str
    kpis: tuple[str, ...]
    deciding_kpis: tuple[str, ...] | None
    relative_tolerance: float
    std_growth_factor: float
    alpha: float = 0.05
    power: float = 0.8
    minimum_seeds: int = 10
    geometries: Mapping[str, Mapping[str, Any]] | None = None
    parameter_sets: Mapping[str, Mapping[str, float]] | None = None


def _numbers(values, key: str, where: str, allowed: str) -> tuple[float, ...]:
    if isinstance(values, (str, bytes)) or not isinstance(values, (list, tuple)):
        raise out_of_range(key, values, allowed, where)
    try:
        return tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise out_of_range(key, values, allowed, where) from None


def _geometry_study_from(plain: Mapping[str, Any]) -> tuple[dict, dict]:
    """``geometries`` (name -> {slice_depth, mirror}, the reference first) and ``parameter_sets``
    (name -> contact parameters replacing the config's ``contact``) of the geometry study."""
    from torchdem.config import contact_from

    geometries = plain.get("geometries")
    if not isinstance(geometries, Mapping) or len(geometries) < 2:
        raise out_of_range("geometries", geometries, "a mapping of >= 2 named geometries, the reference first, e.g. "
                           "{full: {slice_depth: null, mirror: false}, lab: {slice_depth: 0.1, mirror: true}}", "config")
    out_g = {}
    for name, g in geometries.items():
        where = f"config: geometries.{name}"
        if not isinstance(g, Mapping) or set(g) - {"slice_depth", "mirror"}:
            raise out_of_range(f"geometries.{name}", g, "a mapping with keys slice_depth (m or null) and mirror "
                               "(true/false)", "config")
        depth, mirror = g.get("slice_depth"), bool(g.get("mirror", False))
        if depth is not None and (isinstance(depth, bool) or not isinstance(depth, (int, float)) or not depth > 0):
            raise out_of_range(f"geometries.{name}.slice_depth", depth, "a length > 0 m or null (whole box)", where)
        out_g[str(name)] = {"slice_depth": None if depth is None else float(depth), "mirror": mirror}
    sets = plain.get("parameter_sets")
    if not isinstance(sets, Mapping) or not sets:
        raise out_of_range("parameter_sets", sets, "a mapping of >= 1 named parameter sets (contact parameters that "
                           "replace the config's contact values)", "config")
    out_p = {}
    for name, params in sets.items():
        if not isinstance(params, Mapping):
            raise out_of_range(f"parameter_sets.{name}", params, "a mapping of parameter -> value", "config")
        checked = contact_from(params, f"parameter_sets.{name}") if params else {}
        out_p[str(name)] = {**dict(plain.get("contact") or {}), **checked}
    return out_g, out_p


def study_settings_from(plain: Mapping[str, Any]) -> StudySettings:
    """Checked study settings; errors name the key and the allowed range."""
    study = plain.get("study")
    if study not in STUDIES:
        raise out_of_range("study", study, f"one of {list(STUDIES)} (study=timestep|shear_modulus)", "config")
    seeds = replicate_seeds(plain)
    if len(seeds) < 2:
        raise out_of_range("replicates", len(seeds), "an int >= 2 (the criteria compare standard deviations)",
                           "config")
    equivalence = plain.get("equivalence") or {}
    if study == "timestep":
        values = _numbers(plain.get("fractions"), "fractions", "config",
                          "a list of >= 2 distinct fractions of the Rayleigh time step in (0, 1]")
        ok = len(values) >= 2 and len(set(values)) == len(values) and all(0 < v <= 1 for v in values)
        if not ok:
            raise out_of_range("fractions", list(values), "a list of >= 2 distinct fractions in (0, 1]", "config")
    elif study == "shear_modulus":
        values = _numbers(plain.get("shear_moduli_pa"), "shear_moduli_pa", "config",
                          "a list of >= 2 distinct shear moduli > 0 Pa")
        if len(values) < 2 or len(set(values)) != len(values) or not all(v > 0 for v in values):
            raise out_of_range("shear_moduli_pa", list(values), "a list of >= 2 distinct shear moduli > 0 Pa",
                               "config")
    elif study == "geometry":
        values = ()
    else:
        values = tuple(plain.get("dtypes") or ())
        if len(values) != 2 or len(set(values)) != 2 or any(v not in ("float32", "float64") for v in values):
            raise out_of_range("dtypes", list(values), "two distinct precisions, the reference first, e.g. "
                               "[float64, float32]", "config")
        alpha, power = equivalence.get("alpha", 0.05), equivalence.get("power", 0.8)
        if not isinstance(alpha, (int, float)) or not 0 < alpha < 0.5:
            raise out_of_range("equivalence.alpha", alpha, "a number in (0, 0.5)", "config")
        if not isinstance(power, (int, float)) or not 0 < power < 1:
            raise out_of_range("equivalence.power", power, "a number in (0, 1)", "config")
        _int(equivalence.get("minimum_seeds", 10), "equivalence.minimum_seeds", "config", 2, "an int >= 2")
    kpis = check_kpis(plain.get("kpis"), "config")
    deciding = plain.get("deciding_kpis")
    if deciding is not None:
        deciding = tuple(deciding)
        unknown = [k for k in deciding if k not in kpis]
        if unknown or not deciding:
            raise out_of_range("deciding_kpis", list(deciding), f"a non-empty subset of kpis {list(kpis)} or null",
                               "config")
    try:
        rel, growth = float(plain.get("relative_tolerance")), float(plain.get("std_growth_factor"))
    except (TypeError, ValueError):
        raise ConfigError("config: relative_tolerance and std_growth_factor must be numbers") from None
    if not rel > 0:
        raise out_of_range("relative_tolerance", rel, "a number > 0, e.g. 0.02", "config")
    if not growth >= 1:
        raise out_of_range("std_growth_factor", growth, "a number >= 1, e.g. 2.0", "config")
    geometries = parameter_sets = None
    if study == "geometry":
        geometries, parameter_sets = _geometry_study_from(plain)
    return StudySettings(study=study, values=values, seeds=tuple(seeds), condition=str(plain.get("condition")),
                         geometries=geometries, parameter_sets=parameter_sets,
                         kpis=kpis, deciding_kpis=deciding, relative_tolerance=rel, std_growth_factor=growth,
                         alpha=float(equivalence.get("alpha", 0.05)), power=float(equivalence.get("power", 0.8)),
                         minimum_seeds=int(equivalence.get("minimum_seeds", 10)))


def run_study(plain: Mapping[str, Any], out: Path, echo=print) -> dict:
    """The whole app on a plain config: check, run (resume), analyse, write. Returns a summary."""
    from bo.screening.pipeline import measured_for
    from bo.studies.pipeline import (STUDY_STAGES, precision_report, run_precision_study, run_shear_modulus_study,
                                     run_time_step_study, shear_modulus_report, smallest_sphere_rayleigh_time_step,
                                     time_step_report, geometry_report, run_geometry_study)

    s = study_settings_from(plain)
    executor_settings = executor_settings_from(plain.get("executor") or {})
    model = model_from(plain)
    params = dict(model.fixed)
    path = store_path_from(plain, out)
    store = open_store(path, plain, extra_stages=STUDY_STAGES,
                       allow_config_mismatch=bool(plain.get("allow_config_mismatch")))
    requeue_failed(plain, store, echo)
    stage = s.study
    counts = store.counts(stage)
    before = counts["done"] + counts["failed"]
    started = time.perf_counter()
    with executor_from(executor_settings, model, checkpoints=checkpoint_dir_for(path)) as executor:
        if s.study == "timestep":
            runs = run_time_step_study(store, executor, condition=s.condition, params=params, fractions=s.values,
                                       seeds=list(s.seeds), kpis=list(s.kpis), stage=stage)
        elif s.study == "shear_modulus":
            runs = run_shear_modulus_study(store, executor, condition=s.condition, params=params,
                                           shear_moduli_pa=s.values, seeds=list(s.seeds), kpis=list(s.kpis),
                                           stage=stage)
        elif s.study == "geometry":
            runs = run_geometry_study(store, executor, condition=s.condition, geometries=s.geometries,
                                      parameter_sets=s.parameter_sets, seeds=list(s.seeds), kpis=list(s.kpis),
                                      members_per_ensemble=executor_settings.batch_size, stage=stage)
        else:
            runs = run_precision_study(store, executor, condition=s.condition, params=params, dtypes=s.values,
                                       seeds=list(s.seeds), kpis=list(s.kpis), stage=stage)
    wall = time.perf_counter() - started
    counts = store.counts(stage)
    evaluated = counts["done"] + counts["failed"] - before
    if s.study == "timestep":
        rayleigh = smallest_sphere_rayleigh_time_step(model.conditions[s.condition], model.settings)
        result, files = time_step_report(runs, out, rayleigh_time_step_s=rayleigh, deciding_kpis=s.deciding_kpis,
                                         relative_tolerance=s.relative_tolerance,
                                         std_growth_factor=s.std_growth_factor)
    elif s.study == "shear_modulus":
        result, files = shear_modulus_report(runs, out, deciding_kpis=s.deciding_kpis,
                                             relative_tolerance=s.relative_tolerance)
    elif s.study == "geometry":
        measured = measured_for(s.kpis, measured_kpis_from(plain))
        result, files = geometry_report(runs, out, lab_margins={k: v.ci95 for k, v in measured.items()})
    else:
        measured = measured_for(s.kpis, measured_kpis_from(plain))
        result, files = precision_report(runs, out, margins={k: v.ci95 for k, v in measured.items()},
                                         alpha=s.alpha, power=s.power, minimum_seeds=s.minimum_seeds)
    echo(result.to_text())
    echo(f"store {path}: {counts['done']} done, {counts['failed']} failed; DEM evaluations run now: "
         f"{evaluated} in {wall:.1f} s")
    echo(f"wrote {', '.join(sorted(p.name for p in files.values()))} to {out}")
    return {"store": str(path), "evaluations_run_now": evaluated, "dem_wall_time_s": round(wall, 2),
            "files": {k: str(v) for k, v in files.items()}}


@hydra.main(config_path=CONF_DIR, config_name="study", version_base="1.3")
@one_line_errors("torchdem-study")
def main(cfg: DictConfig) -> None:
    """Time-step or shear-modulus study through the store -> report and figure."""
    from hydra.core.hydra_config import HydraConfig

    run_study(plain_config(cfg), Path(HydraConfig.get().runtime.output_dir))


if __name__ == "__main__":  # pragma: no cover
    main()
