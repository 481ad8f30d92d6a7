"""``torchdem-screen``: the sensitivity analysis of Hadi et al. section 3.3 as a Hydra app.

Usage::

    torchdem-screen                                   # screen=cpu: 4 parameters, ~4 min on 2 CPU cores
    torchdem-screen store=/tmp/screen.sqlite          # fixed store: rerun resumes, repeats nothing
    torchdem-screen screen=paper store=paper.sqlite   # 12 parameters + 2 fake, 29 runs, 5 replicates
    torchdem-screen replicates=5 executor=dask executor.n_workers=2

Config: ``conf/screen.yaml`` (the draw down model of ``conf/simulate.yaml`` plus the screening
settings), profiles in ``conf/screen/``, executors in ``conf/executor/``. The store defaults to
``campaign.sqlite`` in the Hydra run directory (a new one per run); pass ``store=PATH`` to resume
a killed or finished screening: stored batches are reused and only pending evaluations run.

``main()`` only turns the config into typed objects (``screen_settings_from``,
``model_from``, ``executor_from``) and calls ``bo.screening.pipeline.run_screening`` and
``bo.screening.pipeline.analyse_and_report``. Every config error is a ``ConfigError`` raised before the store
is opened or any DEM run starts. The helpers shared with the other campaign commands are in ``bo.cli.common``.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Mapping

import hydra
from omegaconf import DictConfig

from bo.cli.common import (check_screening_levels, checkpoint_dir_for, executor_from, executor_settings_from,
                           measured_kpis_from, model_from, open_store, plain_config, requeue_failed,
                           screen_settings_from, store_path_from)
from torchdem.cli import CONF_DIR, one_line_errors


def screen(plain: Mapping[str, Any], out: Path, echo=print) -> dict:
    """The whole app on a plain config: check, run (resume), analyse, write. Returns a summary."""
    from bo.screening.pipeline import analyse_and_report, run_screening

    settings = screen_settings_from(plain)
    executor_settings = executor_settings_from(plain.get("executor") or {})
    measured = measured_kpis_from(plain)
    model = model_from(plain)
    check_screening_levels(model, settings)
    path = store_path_from(plain, out)
    store = open_store(path, plain, allow_config_mismatch=bool(plain.get("allow_config_mismatch")))
    requeue_failed(plain, store, echo)
    stage = "screening"
    before = store.counts(stage)["done"] + store.counts(stage)["failed"]
    started = time.perf_counter()
    with executor_from(executor_settings, model, checkpoints=checkpoint_dir_for(path)) as executor:
        results = run_screening(store, executor, settings.table, n_fake=settings.n_fake,
                                seeds=list(settings.seeds), condition=settings.condition,
                                kpis=list(settings.kpis), stage=stage)
    counts = store.counts(stage)
    evaluated = counts["done"] + counts["failed"] - before
    run_wall = time.perf_counter() - started
    report = analyse_and_report(results, measured, out, p_threshold=settings.p_threshold,
                                selection_fraction=settings.selection_fraction,
                                stochastic_threshold=settings.stochastic_threshold,
                                extension_factor=settings.extension_factor,
                                extension_mode=settings.extension_mode, limits=settings.physical_limits(),
                                second_order=settings.second_order,
                                title=f"Screening of {settings.table.k} parameters, condition {settings.condition}")
    echo(report.text)
    summary = {"store": str(path), "design_runs": results.n_runs, "replicates": results.n_replicates,
               "evaluations_run_now": evaluated, "failed_in_store": counts["failed"],
               "dem_wall_time_s": round(run_wall, 2), "out_dir": str(out),
               "files": {k: str(v) for k, v in report.files.items()}}
    echo(f"store {path}: {counts['done']} done, {counts['failed']} failed; DEM evaluations run now: "
         f"{evaluated} in {run_wall:.1f} s")
    echo(f"wrote {', '.join(sorted(p.name for p in report.files.values()))} to {out}")
    return summary


@hydra.main(config_path=CONF_DIR, config_name="screen", version_base="1.3")
@one_line_errors("torchdem-screen")
def main(cfg: DictConfig) -> None:
    """Definitive screening design through the store -> Table 5, Fig. 10/11, extension."""
    from hydra.core.hydra_config import HydraConfig

    out = Path(HydraConfig.get().runtime.output_dir)
    screen(plain_config(cfg), out)


if __name__ == "__main__":  # pragma: no cover
    main()
