"""``torchdem-discover``: what the calibrated model gets wrong, the likely cause, the gain of the
extension (bo/discovery/pipeline.py), as a Hydra app.

Usage::

    torchdem-discover                                   # profile=cpu: the mini box against its twin data
    torchdem-discover data=lab.json calibration=outputs/2026-11-23/12-00-00/calibration.json
    torchdem-discover store=/tmp/discover.sqlite        # rerun with the same store: resumes

Writes ``discovery.json``, ``discovery.md``, ``discrepancy.png`` and ``gain.png`` to the Hydra run
directory (``bo.discovery.report``), and prints the override that makes the found mechanism part
of any command's model (``extension=<name> extension.values.<p>=<v>``, conf/extension/).
``main()`` only turns the config into typed objects and calls ``bo.discovery.pipeline.run_discovery``;
config errors are raised before the store is opened or any DEM run starts.
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Mapping

import hydra
from omegaconf import DictConfig

from bo.calibration.document import calibrated_parameters, read_calibration
from bo.cli.common import (MODEL_KEYS, _int, check_kpis, checkpoint_dir_for, executor_settings_from, open_store,
                           plain_config, replicate_seeds, requeue_failed, store_hashes, store_path_from)
from torchdem.cli import CONF_DIR, one_line_errors
from torchdem.errors import ConfigError, out_of_range


def discovery_settings_from(plain: Mapping[str, Any]):
    from bo.discovery.pipeline import DiscoverySettings
    from bo.surrogate.ga import GASettings
    from torchdem.mechanisms import registry

    where = "discovery"
    cfg = plain.get(where)
    if not isinstance(cfg, Mapping):
        raise ConfigError("config: 'discovery' block is missing")
    base = replicate_seeds({**plain, "replicates": 1})[0]
    seeds = tuple(base + k for k in range(_int(cfg.get("replicates"), "replicates", where, 2, "an int >= 2")))
    fit = tuple(base + k for k in range(_int(cfg.get("fit_replicates"), "fit_replicates", where, 1, "an int >= 1")))
    candidates = cfg.get("candidates")
    if candidates is not None:
        known = registry()
        if isinstance(candidates, str) or not isinstance(candidates, (list, tuple)) \
                or [c for c in candidates if c not in known]:
            raise out_of_range("candidates", candidates, f"a list of mechanisms of torchdem/mechanisms/ {sorted(known)}, "
                               "[] (the discrepancy only) or null (all)", where)
        candidates = tuple(candidates)
    refit = cfg.get("refit") or []
    if isinstance(refit, str) or not isinstance(refit, (list, tuple)):
        raise out_of_range("refit", refit, "a list of calibrated parameter names", where)
    try:
        ga = GASettings(**(cfg.get("ga") or {}))
        settings = DiscoverySettings(
            kpis=check_kpis(cfg.get("kpis"), where), seeds=seeds, fit_seeds=fit, candidates=candidates,
            refit=tuple(refit), refit_fraction=float(cfg.get("refit_fraction")),
            points_per_parameter=cfg.get("points_per_parameter"), min_points=cfg.get("min_points"),
            escalations=cfg.get("escalations", 1),
            alpha=float(cfg.get("alpha")), penalty=float(cfg.get("penalty")), margin=float(cfg.get("margin")),
            always_score=bool(cfg.get("always_score")), ga=ga, kernel=str(cfg.get("kernel")), seed=base,
            fit_starts=cfg.get("fit_starts", 3), fit_search=str(cfg.get("fit_search", "multistart")),
            search_samples=cfg.get("search_samples", 1024), proposed_kpis=_proposed(cfg.get("proposed_kpis"), where),
            proposed_conditions=_names(cfg.get("proposed_conditions"), "proposed_conditions", where),
            prune_probability=float(cfg.get("prune_probability", 0.0)))
        return settings.validate(where)
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"config {where}: {exc}") from None


def _proposed(kpis, where: str) -> tuple[str, ...]:
    """``discovery.proposed_kpis``: an empty list or distinct KPI names the draw down test reports."""
    if kpis is None or (isinstance(kpis, (list, tuple)) and not kpis):
        return ()
    return check_kpis(kpis, where, "proposed_kpis")


def _names(value, key: str, where: str) -> tuple[str, ...]:
    """A list of distinct non-empty names (null or [] for none)."""
    if value is None:
        return ()
    if isinstance(value, str) or not isinstance(value, (list, tuple)) \
            or not all(isinstance(v, str) and v for v in value) or len(set(value)) != len(value):
        raise out_of_range(key, value, "a list of distinct condition names, or [] for none", f"config {where}")
    return tuple(value)


PAPER_DATA = "hadi2025_pellet_sinter.json"


def attainable_from(plain: Mapping[str, Any]):
    """The calibration's "what the bounds allow" (``attainable`` of its calibration.json, as
    :class:`bo.surrogate.attainable.AttainableRange`); empty without one."""
    from bo.surrogate.attainable import AttainableRange

    path = plain.get("calibration")
    if path is None or path == "paper":
        return ()
    rows = read_calibration(path, "calibration").get("attainable") or []
    try:
        return tuple(AttainableRange.from_dict(r) for r in rows)
    except TypeError as exc:
        raise ConfigError(f"calibration = {path!r}: 'attainable' is not a list of ranges of torchdem-calibrate "
                          f"({exc})") from None


def calibrated_from(plain: Mapping[str, Any], fixed: Mapping[str, float]) -> tuple[dict[str, float], str]:
    """The calibrated parameters: ``calibration.json``'s ``calibrated_parameters`` over the
    config's contact parameters, the paper's own calibrated set (``calibration=paper``: Table 8,
    the mode it selected, from the shipped data file), or the contact parameters alone."""
    path = plain.get("calibration")
    if path is None:
        return dict(fixed), "the config's contact parameters (no calibration= given)"
    if path == "paper":
        from torchdem.measured import shipped_file
        table = json.loads(shipped_file(PAPER_DATA).read_text())["dem_reported"]["ga_calibration"]
        values = table[table["selected"]]
        return ({**fixed, **{k: float(v) for k, v in values.items()}},
                f"the paper's calibrated set ({table['table']}, {table['selected']} GA, in {PAPER_DATA})")
    return {**fixed, **calibrated_parameters(path, "calibration")}, f"{path}"


def baseline_runs(plain: Mapping[str, Any], data, calibrated: Mapping[str, float], conditions: list[str]):
    """``discovery.baseline_store``: a store of the same model (its config hash is this config's model
    and data) that holds runs of the calibrated set: the torchdem-calibrate campaign that found it
    (its verification and validation), or a probe of the set (``scripts/probe_sets.py``, stage
    ``probe``). Its runs of that set, whatever stage made them, are the discrepancy's runs
    (``run_discovery``'s ``baseline``). Returns (path, condition -> runs), or None without it."""
    from bo.campaign.progress import check_same_model, done_records
    from bo.discovery.pipeline import runs_of_set

    path = (plain.get("discovery") or {}).get("baseline_store")
    if path is None:
        return None
    where = "config discovery"
    if not isinstance(path, str) or not Path(path).is_file():
        raise out_of_range("baseline_store", path, "an existing torchdem-calibrate campaign store (.sqlite) or null",
                           where)
    # read only (a shipped store, or one a campaign is writing, is not touched); the calibrate app's hash of
    # this model and data (bo/cli/calibrate.py): a store of another model is refused
    source = f"discovery.baseline_store ({where})"
    check_same_model(Path(path), store_hashes({**plain, "measured": data}, MODEL_KEYS + ("measured",)), source)
    # every stage: a run at the set's values is a run of the set, whichever stage asked for it
    return str(path), runs_of_set(done_records(Path(path), None, source), calibrated, conditions)


def residue_from(plain: Mapping[str, Any], store_path, measured):
    """The upper box's residue per unit slope (``bo.discovery.residue``) of the lab and of the runs in
    the baseline store and the discovery's own; None when the data or the runs give none."""
    from bo.discovery.residue import residue_check

    stores = [p for p in ((plain.get("discovery") or {}).get("baseline_store"), store_path) if p]
    check = residue_check(stores, measured)
    return check if check.lab and check.runs else None


def gap_from(plain: Mapping[str, Any], store_path, measured):
    """How far the face stands above the heap (``bo.discovery.gap``), the lab's against the runs in the
    baseline store and the discovery's own; None when the data or the runs give none."""
    from bo.discovery.gap import gap_check

    stores = [p for p in ((plain.get("discovery") or {}).get("baseline_store"), store_path) if p and Path(p).is_file()]
    check = gap_check(stores, measured) if stores else None
    return check if check is not None and check.lab and check.runs else None


def extension_command(name: str | None, values: Mapping[str, float]) -> str | None:
    """The Hydra overrides that switch mechanism ``name`` on at ``values`` in any command."""
    if name is None:
        return None
    shipped = (Path(CONF_DIR) / "extension" / f"{name}.yaml").is_file()
    head = f"extension={name}" if shipped else f"extension.name={name}"
    plus = "" if shipped else "+"
    return " ".join([head, *(f"{plus}extension.values.{k}={v:.6g}" for k, v in values.items())])


def discover(plain: Mapping[str, Any], out: Path, echo=print) -> dict:
    """The whole app on a plain config: check, run (resume), report. Returns a summary."""
    from bo.cli.calibrate import calibration_model_from
    from bo.cli.common import check_builds, executor_factory
    from bo.discovery.pipeline import discovery_stages, refit_bounds, run_discovery
    from bo.discovery.report import write_discovery_report
    from torchdem.measured import load_measured

    settings = discovery_settings_from(plain)
    executor_settings = executor_settings_from(plain.get("executor") or {})
    data = plain.get("data") if plain.get("data") is not None else plain.get("measured")
    every = load_measured(data)
    subset = (plain.get("discovery") or {}).get("conditions")
    measured = every
    if subset is not None:
        if isinstance(subset, str) or not isinstance(subset, (list, tuple)):
            raise out_of_range("conditions", subset, f"a list of conditions of the data {list(every.names)}, "
                               "or null (all)", "config discovery")
        measured = every.subset(subset, "config discovery")
    unmeasured = [c for c in settings.proposed_conditions if c not in every.names or c in measured.names]
    if unmeasured:
        raise out_of_range("proposed_conditions", list(settings.proposed_conditions),
                           f"conditions of the data {list(every.names)} left out of discovery.conditions "
                           f"({list(measured.names)}); not so: {unmeasured}", "config discovery")
    # the model knows the proposed conditions' mixtures (fractions and layering from the data file)
    model_data = every.subset(list(measured.names) + list(settings.proposed_conditions), "config discovery") \
        if settings.proposed_conditions else measured
    model, _ = calibration_model_from({**plain, "measured": data}, model_data)
    calibrated, source = calibrated_from(plain, model.fixed)
    refit_bounds(calibrated, settings.refit, settings.refit_fraction)  # a refit name the set lacks: stop here
    check_builds(model, measured.names[0], calibrated, f"the calibrated set from {source} does not build the model")
    path = store_path_from(plain, out)
    # the store is for this data file and, when given, this choice of its conditions
    hashed = {**plain, "measured": data if subset is None else [data, list(measured.names)]}
    store = open_store(path, hashed, MODEL_KEYS + ("measured", "calibration"),
                       allow_config_mismatch=bool(plain.get("allow_config_mismatch")), extra_stages=discovery_stages())
    requeue_failed(plain, store, echo)
    baseline = baseline_runs(plain, data, calibrated, list(measured.names))
    echo(f"torchdem-discover: {len(measured.names)} conditions of {measured.origin}; calibrated set from {source}; "
         f"store {path}")
    started = time.perf_counter()
    with executor_factory(executor_settings, checkpoints=checkpoint_dir_for(path)) as executor_for:
        result = run_discovery(store, executor_for, model, calibrated, measured, settings, echo=echo,
                               baseline=baseline)
    command = extension_command(result.cause, result.extension)
    files = write_discovery_report(result, out, command, attainable_from(plain), residue_from(plain, path, measured),
                                   gap_from(plain, path, measured))
    wall = time.perf_counter() - started
    if command:
        echo(f"use it: torchdem-calibrate {command}")
    echo(f"DEM evaluations {result.evaluations.get('total', 0)}; wall {wall:.1f} s; wrote "
         f"{', '.join(sorted(p.name for p in files.values()))} to {out}")
    return {"cause": result.cause, "store": str(path), "out_dir": str(out), "wall_time_s": round(wall, 2),
            "files": {k: str(v) for k, v in files.items()}}


@hydra.main(config_path=CONF_DIR, config_name="discover", version_base="1.3")
@one_line_errors("torchdem-discover")
def main(cfg: DictConfig) -> None:
    """Discrepancy -> candidate causes -> extension -> gain."""
    from hydra.core.hydra_config import HydraConfig

    discover(plain_config(cfg), Path(HydraConfig.get().runtime.output_dir))


if __name__ == "__main__":  # pragma: no cover
    main()
