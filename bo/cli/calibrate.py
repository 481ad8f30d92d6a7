"""``torchdem-calibrate``: screening -> surrogate -> GA -> verification -> bulk density ->
validation as one resumable campaign (Hadi et al. sections 3.3-3.7).

Usage::

    torchdem-calibrate                                    # profile=cpu (what `make run` runs)
    torchdem-calibrate profile=smoke                      # the whole pipeline in under 3 minutes
    torchdem-calibrate store=/tmp/cal.sqlite              # rerun with the same store: resumes
    torchdem-calibrate profile=paper sim=gpu store=paper.sqlite
    torchdem-calibrate surrogate.strategy=per_kpi surrogate.budget=80 measured=my_lab.json

Writes to the Hydra run directory: ``report.md``, ``calibration.json``, the figures, and the
screening's own report in ``screening/`` (``bo.calibration.report``). Every DEM evaluation goes
through the SQLite store (``store``, default ``campaign.sqlite`` in the run directory), so a
killed campaign started again with the same ``store=`` loses nothing and repeats no DEM run.

``main()`` only turns the config into typed objects (``calibration_settings_from``, and the
helpers shared with ``torchdem-screen``) and calls ``bo.calibration.pipeline.run_calibration``; config
errors are raised before the store is opened or any DEM run starts, naming the key and the
allowed range.
"""
from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

import hydra
from omegaconf import DictConfig

from bo.cli.common import (MODEL_KEYS, _int, check_kpis, check_ranges, check_screening_levels, checkpoint_dir_for,
                           executor_from, executor_settings_from, flag, open_store, plain_config, replicate_seeds,
                           requeue_failed, screen_settings_from, store_path_from)
from torchdem.config import parameter_range
from torchdem.cli import CONF_DIR, one_line_errors
from torchdem.errors import ConfigError, out_of_range


def _seeds(block: Mapping[str, Any], where: str, base: int) -> tuple[int, ...]:
    n = _int(block.get("replicates"), "replicates", where, 1, "an int >= 1")
    return tuple(base + k for k in range(n))


def _floats(value, key: str, where: str, allowed: str) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise out_of_range(key, value, allowed, where) from None
    if not all(math.isfinite(v) for v in out):
        raise out_of_range(key, value, allowed, where)
    return out


def _intervals(mapping: Mapping, key: str, where: str) -> dict[str, tuple[float, ...]]:
    """``{name: (low, high)}`` from a config mapping of ``[low, high]`` pairs with low < high."""
    checked = {}
    for n, b in mapping.items():
        lo_hi = _floats(b, f"{key}.{n}", where, "[low, high] with low < high")
        if len(lo_hi) != 2 or not lo_hi[0] < lo_hi[1]:
            raise out_of_range(f"{key}.{n}", list(b), "[low, high] with low < high", where)
        checked[str(n)] = lo_hi
    return checked


def seed_store(plain: Mapping[str, Any], path: Path) -> Path | None:
    """Copy ``store_from`` (a shipped campaign store) to the run's store ``path`` if that does
    not exist yet, so the campaign resumes from it and the shipped file stays as it is; returns
    the source, or None without ``store_from``. A run whose store exists already resumes its own."""
    source = plain.get("store_from")
    if source is None:
        return None
    if not isinstance(source, str) or not source:
        raise out_of_range("store_from", source, "the path of a campaign store (.sqlite) or null", "config")
    src = Path(source).expanduser().resolve()
    if not src.is_file():
        raise out_of_range("store_from", source, "an existing campaign store file", "config")
    if src == path.resolve():
        raise ConfigError(f"config: store_from = {source} is the run's own store; give a new store= (or none)")
    if not path.exists():
        from bo.campaign.store import copy_store

        try:
            copy_store(src, path)
        except ConfigError as exc:  # not a store: say which option named it
            raise out_of_range("store_from", source, f"a campaign store a torchdem campaign wrote (SQLite: "
                               f"{exc.__cause__})", "config") from exc
    return src


def _wrap(where: str, build):
    """Build a typed settings object; its ConfigError names the config block."""
    try:
        return build()
    except ConfigError as exc:
        raise ConfigError(f"config {where}: {exc}") from None
    except TypeError as exc:
        raise ConfigError(f"config {where}: {exc}") from None


def _names(cfg: Mapping[str, Any], key: str, where: str, allowed: str) -> list[str]:
    """``cfg[key]``: a list of distinct non-empty strings (null: none)."""
    names = cfg.get(key) or []
    if isinstance(names, str) or not isinstance(names, Sequence) \
            or any(not isinstance(k, str) or not k for k in names) or len(set(names)) != len(names):
        raise out_of_range(key, names, allowed, where)
    return list(names)


def surrogate_settings_from(cfg: Mapping[str, Any], base_seed: int):
    from bo.surrogate.acquisition import AcquisitionSettings, AdaptiveSettings
    from bo.calibration.pipeline import NOISE_MODELS, SurrogateStageSettings
    from bo.surrogate.gp import KERNELS, STRATEGIES, SurrogateConfig

    where = "surrogate"
    if not isinstance(cfg, Mapping):
        raise ConfigError("config: 'surrogate' block is missing")
    names = cfg.get("parameters")
    if names is not None:
        if isinstance(names, (str, bytes)) or not isinstance(names, (list, tuple)) or not names \
                or len(set(names)) != len(names):
            raise out_of_range("parameters", names, "a list of distinct parameter names or null (Table 5's)", where)
        names = tuple(str(n) for n in names)
    bounds = cfg.get("bounds")
    if bounds is not None:
        if not isinstance(bounds, Mapping) or not bounds:
            raise out_of_range("bounds", bounds, "a mapping name -> [low, high] or null (Table 6 proposal)", where)
        bounds = _intervals(bounds, "bounds", where)
        if names is not None and [n for n in names if n not in bounds]:
            raise out_of_range("bounds", dict(bounds), f"bounds for every parameter {list(names)}", where)
    added = cfg.get("added") or {}
    if not isinstance(added, Mapping):
        raise out_of_range("added", added, "a mapping name -> [low, high] of parameters calibrated besides the "
                           "selection, or null", where)
    checked_added = {}
    for n, b in added.items():
        lo_hi = _floats(b, f"added.{n}", where, "[low, high] with low < high")
        low, high, open_low, allowed = parameter_range(str(n))
        ok = len(lo_hi) == 2 and lo_hi[0] < lo_hi[1] and (lo_hi[0] > low if open_low else lo_hi[0] >= low) \
            and lo_hi[1] <= high
        if not ok:
            raise out_of_range(f"added.{n}", list(b), f"[low, high] with low < high, each {allowed}", where)
        checked_added[str(n)] = lo_hi
    strategy = cfg.get("strategy")
    if strategy not in STRATEGIES:
        raise out_of_range("strategy", strategy, f"one of {list(STRATEGIES)}", where)
    kernels = cfg.get("kernels")
    if isinstance(kernels, str):
        kernels = [kernels]
    if not isinstance(kernels, (list, tuple)) or not kernels or [k for k in kernels if k not in KERNELS]:
        raise out_of_range("kernels", kernels, f"a non-empty list from {list(KERNELS)}", where)
    acq = cfg.get("acquisition") or {}
    acquisition = _wrap(f"{where}.acquisition", lambda: AcquisitionSettings(**acq))
    adaptive = _wrap(where, lambda: AdaptiveSettings(
        budget=cfg.get("budget"), points_per_parameter=cfg.get("points_per_parameter"), q=cfg.get("q"),
        target_r2=cfg.get("target_r2"), target_basis=cfg.get("target_basis", "total"), n_folds=cfg.get("n_folds"), cv_seeds=tuple(cfg.get("cv_seeds") or ()),
        kernels=tuple(kernels), seed=base_seed, acquisition=acquisition))
    if names is not None:  # budget vs initial design, up front (with reuse, the least the design can run)
        d = len(names) + len(checked_added)
        _wrap(where, lambda: adaptive.initial_size(d, reused=d * adaptive.points_per_parameter
                                                   if cfg.get("reuse_screening", False) is True else 0))
    config = _wrap(where, lambda: SurrogateConfig(kernel=kernels[0], strategy=strategy))
    noise = cfg.get("noise", "learned")
    if noise not in NOISE_MODELS:
        raise out_of_range("noise", noise, f"one of {list(NOISE_MODELS)}", where)
    seeds = _seeds(cfg, where, base_seed)
    if adaptive.target_basis == "explainable" and noise == "learned" and len(seeds) < 2:
        raise out_of_range("target_basis", adaptive.target_basis, "'total' when points run once with learned noise "
                           "('explainable' needs each point's noise: replicates >= 2 or noise: pooled)", where)
    limits = cfg.get("limits") or {}
    if not isinstance(limits, Mapping):
        raise out_of_range("limits", limits, "a mapping name -> [low, high] or null", where)
    checked_limits = _intervals(limits, "limits", where)
    reuse = cfg.get("reuse_screening", False)
    if not isinstance(reuse, bool):
        raise out_of_range("reuse_screening", reuse, "true or false (the screening's points as surrogate data)", where)
    designs = _names(cfg, "reuse_designs", where, "a list of distinct batch keys of earlier initial designs in the "
                     "store (python scripts/campaign_status.py lists them), or null")
    jam_conditions = _names(cfg, "jam_conditions", where, "a list of distinct measured conditions (e.g. [75-25]) "
                            "whose runs feed the jam classifier only, or null")
    return SurrogateStageSettings(parameters=names, bounds=bounds, seeds=seeds,
                                  adaptive=adaptive, config=config,
                                  compare_strategies=bool(cfg.get("compare_strategies")), added=checked_added,
                                  noise=noise, reuse_screening=reuse, limits=checked_limits,
                                  reuse_designs=tuple(designs), jam_conditions=tuple(jam_conditions))


def calibration_settings_from(plain: Mapping[str, Any]):
    """Checked ``bo.calibration.pipeline.CalibrationSettings``; every error names the key and the allowed range."""
    from bo.calibration.pipeline import CalibrationSettings
    from bo.surrogate.ga import GASettings

    screening = screen_settings_from(plain)
    base = replicate_seeds(plain)[0]
    obj = plain.get("objective") or {}
    kpis = obj.get("kpis")
    kpis = None if kpis is None else check_kpis(kpis, "objective")
    weights = obj.get("weights")
    if weights is not None:
        if not isinstance(weights, Mapping) or not weights:
            raise out_of_range("weights", weights, "a mapping KPI -> weight summing to 1, or null (equal)",
                               "objective")
        if kpis is None or set(weights) != set(kpis):
            raise out_of_range("weights", dict(weights), f"one weight for each KPI of objective.kpis ({kpis})",
                               "objective")
        w = _floats(weights.values(), "weights", "objective", "weights >= 0 summing to 1")
        if any(x < 0 for x in w) or abs(math.fsum(w) - 1.0) > 1e-9:
            raise out_of_range("weights", dict(weights), f"weights >= 0 summing to 1 (they sum to {math.fsum(w)!r})",
                               "objective")
        weights = dict(zip(weights, w))
    fitted = _names(obj, "conditions", "objective", "a list of distinct measured conditions besides the calibrated "
                    "one whose KPIs join Eq. 7 (e.g. [75-25]), or null")
    ga_cfg = dict(plain.get("ga") or {})
    reps = _int(ga_cfg.pop("repetitions", None), "repetitions", "ga", 1, "an int >= 1 (surrogate trainings)")
    mode = ga_cfg.pop("mode", None)
    if mode not in ("restricted", "unrestricted"):
        raise out_of_range("mode", mode, "'restricted' or 'unrestricted'", "ga")
    ga_strategy = ga_cfg.pop("strategy", None)
    ga = _wrap("ga", lambda: GASettings(**ga_cfg))
    from bo.surrogate.attainable import AttainableSettings
    attainable = _wrap("attainable", lambda: AttainableSettings(**dict(plain.get("attainable") or {})).validate("attainable"))
    ver = plain.get("verification") or {}
    val = plain.get("validation") or {}
    conditions = val.get("conditions")
    if conditions is not None:
        if isinstance(conditions, (str, bytes)) or not isinstance(conditions, (list, tuple)):
            raise out_of_range("conditions", conditions, "a list of measured condition names or null (all others)",
                               "validation")
        conditions = tuple(str(c) for c in conditions)
    settings = CalibrationSettings(
        condition=str(plain.get("condition")), screening=screening, objective_kpis=kpis, weights=weights,
        surrogate=surrogate_settings_from(plain.get("surrogate"), base), ga=ga, ga_repetitions=reps, ga_mode=mode,
        verification_seeds=_seeds(ver, "verification", base),
        density_recalibration=bool((plain.get("density") or {}).get("recalibrate", True)),
        validation_conditions=conditions, validation_seeds=_seeds(val, "validation", base),
        validate_with_density=bool(val.get("with_density", True)), seed=base,
        fresh_verification=flag(ver.get("fresh", False), "fresh", "verification"), ga_strategy=ga_strategy,
        attainable=attainable, objective_conditions=tuple(fitted))
    return _wrap("", settings.validate)


def calibration_model_from(plain: Mapping[str, Any], measured):
    """``torchdem.model.DrawDownModel`` with every measured condition's mixture built from the config's
    materials and fill mass (fractions and layering from the measured data)."""
    from torchdem import config
    from torchdem.cli import device_from
    from torchdem.mechanisms import with_extension
    from torchdem.model import DrawDownModel, mixtures_from_measured

    mixture = config.mixture_from(plain["mixture"])
    conditions = mixtures_from_measured(measured, {m.name: m for m in mixture.materials},
                                        total_mass=mixture.total_mass,
                                        layers_source=f"measured data ({plain.get('measured') or 'shipped Table 2'})")
    device = device_from(str(plain["sim"]["device"]), "sim.device")
    model = with_extension(DrawDownModel(conditions=conditions, geometry=config.geometry_from(plain["geometry"]),
                                         settings=config.run_settings_from(plain["sim"], plain["run"]),
                                         fixed=config.contact_from(plain["contact"]), device=str(device)),
                           *config.extension_from(plain.get("extension")))
    return model, {m.name: m.density for m in mixture.materials}


def calibration_model_for(overrides: Sequence[str]):
    """``(plain config, model, measured data)`` of the calibrate config composed with Hydra
    ``overrides`` (as on the command line): the model whose runs a campaign of that config makes,
    for scripts that run or inspect such runs outside a campaign. Overrides Hydra cannot compose (a
    profile that does not exist, a key the config lacks) raise ``ConfigError`` naming them."""
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from bo.cli.common import plain_config
    from torchdem.measured import load_measured

    try:
        with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
            plain = plain_config(compose("calibrate", overrides=list(overrides)))
    except (HydraException, OmegaConfBaseException) as exc:
        raise ConfigError(f"overrides {list(overrides)}: {' '.join(str(exc).split())}") from exc
    measured = load_measured(plain.get("measured"))
    model, _ = calibration_model_from(plain, measured)
    return plain, model, measured


def calibrate(plain: Mapping[str, Any], out: Path, echo=print) -> dict:
    """The whole app on a plain config: check, run (resume), report. Returns a summary."""
    from bo.calibration.pipeline import EXTRA_STAGES, run_calibration, validation_conditions
    from bo.calibration.report import validation_summary, write_calibration_report
    from torchdem.measured import load_measured, load_paper_tables

    settings = calibration_settings_from(plain)
    executor_settings = executor_settings_from(plain.get("executor") or {})
    measured = load_measured(plain.get("measured"))
    validation_conditions(settings, measured)
    model, densities = calibration_model_from(plain, measured)
    # ranges the config gives (the screening's levels, the surrogate's bounds): the model builds at their ends
    check_screening_levels(model, settings.screening)
    check_ranges(model, settings.condition, {**(settings.surrogate.bounds or {}), **settings.surrogate.added},
                 "surrogate (bounds and added)")
    path = store_path_from(plain, out)
    source = seed_store(plain, path)
    # the measured data decide the conditions' mixtures, so they are part of the model
    store = open_store(path, plain, MODEL_KEYS + ("measured",),
                       allow_config_mismatch=bool(plain.get("allow_config_mismatch")), extra_stages=EXTRA_STAGES)
    requeue_failed(plain, store, echo)
    started = time.perf_counter()
    echo(f"torchdem-calibrate: store {path}" + (f" (from {source})" if source else "") + f", output {out}")
    with executor_from(executor_settings, model, checkpoints=checkpoint_dir_for(path)) as executor:
        result = run_calibration(store, executor, settings, measured, out, densities, echo=echo, held=model.fixed)
    paper = load_paper_tables() if plain.get("measured") is None else None  # the paper's own Table 2
    files = write_calibration_report(result, out, paper=paper)
    wall = time.perf_counter() - started
    echo("calibrated: " + ", ".join(f"{k} = {v:.4g}" for k, v in result.final_parameters.items()))
    for label, rows in (("verification", result.verification), ("fresh       ", result.fresh_verification or ())):
        for a in rows:
            echo(f"  {label} {a.kpi:28s} DEM {a.dem_mean:.4g} vs lab {a.measured_mean:.4g} +- {a.measured_ci95:.3g}: "
                 f"{a.relative_error_pct:+.2f} %" + ("" if a.within_ci else " (outside the lab's 95 % CI)")
                 + (f"; {a.jammed} jammed runs left out" if a.jammed else ""))
    for line in validation_summary(result, paper):
        echo(line)
    echo(f"DEM evaluations {result.evaluations['total']}; wall {wall:.1f} s; wrote "
         f"{', '.join(sorted(p.name for p in files.values()))} to {out}")
    return {"store": str(path), "out_dir": str(out), "wall_time_s": round(wall, 2),
            "dem_evaluations": dict(result.evaluations), "files": {k: str(v) for k, v in files.items()},
            "calibrated_parameters": dict(result.final_parameters)}


@hydra.main(config_path=CONF_DIR, config_name="calibrate", version_base="1.3")
@one_line_errors("torchdem-calibrate")
def main(cfg: DictConfig) -> None:
    """Screening -> surrogate -> GA -> verification -> density -> validation."""
    from hydra.core.hydra_config import HydraConfig

    calibrate(plain_config(cfg), Path(HydraConfig.get().runtime.output_dir))


if __name__ == "__main__":  # pragma: no cover
    main()
