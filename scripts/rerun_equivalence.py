"""Does a change of the model's settings move its KPIs by more than the lab can resolve? Reruns a
campaign store's finished runs under config overrides (same parameters, seed and condition: the
same seeded fill) and tests each KPI's paired difference by TOST, the margin being the lab's 95 %
CI half-width (the smallest over the runs' conditions, or that of ``--margin-condition``), as the
float32 study did
(``bo.studies.precision.precision_verdict(..., paired=True)``).

The model is the calibrate config's (Hydra overrides after ``--``), so a rerun is the run a
campaign of that config would make. The store is only read (it may be run beside a campaign).
Each finished rerun is appended to ``--out`` (JSON lines) at once: an interrupted check loses at
most the runs in flight and, run again with the same arguments, reruns only what is missing.

    python scripts/rerun_equivalence.py campaigns/table2/lab.sqlite --stages verification validation \\
        --calibration campaigns/table2/calibration_lab.json --out campaigns/table2/discharge_step.jsonl \\
        --workers 2 -- profile=lab sim.discharge_time_step_fraction=0.225
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from bo.calibration.document import calibrated_parameters
from torchdem.errors import ConfigError, exit_on_bad_input

_MODEL = {}  # the worker process's model, built once per process


def _rerun(overrides: tuple[str, ...], row: dict) -> dict:
    """One stored run again under ``overrides``, on one thread (a worker process)."""
    import torch

    from bo.cli.calibrate import calibration_model_for

    torch.set_num_threads(1)
    if overrides not in _MODEL:
        _MODEL[overrides] = calibration_model_for(list(overrides))[1]
    model = _MODEL[overrides]
    started = time.perf_counter()
    res = model.test_for(row["condition"], [row["params"]]).run_members([(0, 0, row["seed"])])
    kpis = {k: (float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None) for k, v in res.kpis[0].items()}
    return {**row, "kpis": kpis, "failed": res.failed.get(0), "wall_s": round(time.perf_counter() - started, 1),
            "dt_s": res.dt, "discharge_dt_s": res.discharge_dt}


def stored_runs(store: Path, stages: list[str], parameters: dict[str, float] | None,
                task_ids: list[int] | None = None) -> list[dict]:
    """The store's finished runs of ``stages`` (of ``parameters`` only, and of ``task_ids`` only, when
    given), task id order."""
    from bo.campaign.progress import open_read_only

    conn = open_read_only(store, "rerun_equivalence")
    try:
        rows = conn.execute("SELECT task_id, stage, condition, seed, params, kpis, wall_time FROM evaluations "
                            f"WHERE status = 'done' AND stage IN ({','.join('?' * len(stages))}) ORDER BY task_id",
                            stages).fetchall()
    finally:
        conn.close()
    out = []
    for task_id, stage, condition, seed, params, kpis, wall in rows:
        if task_ids is not None and task_id not in task_ids:
            continue
        params = json.loads(params)
        if parameters is not None and (set(params) != set(parameters) or any(
                not math.isclose(params[k], v, rel_tol=1e-9, abs_tol=1e-12) for k, v in parameters.items())):
            continue
        out.append({"task_id": task_id, "stage": stage, "condition": condition, "seed": seed, "params": params,
                    "stored_kpis": json.loads(kpis), "stored_wall_s": wall})
    return out


def _read_out(path: Path, header: dict) -> dict[int, dict]:
    """Reruns already in ``path`` by task id (the file starts with its header, which must match)."""
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(header) + "\n")
        return {}
    lines = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    if not lines or lines[0] != header:
        raise ConfigError(f"{path}: holds the reruns of {lines[0] if lines else 'nothing'}, not of {header}; "
                          "use another --out for another check")
    return {r["task_id"]: r for r in lines[1:]}


def verdict_text(done: list[dict], kpis: list[str], measured, margin_condition: str | None = None) -> str:
    """The paired TOST of every KPI over the reruns ``done`` against their stored runs; the margins are
    the lab's CI half-widths of ``margin_condition``, or the smallest over the runs' conditions."""
    from bo.screening.pipeline import measured_name
    from bo.studies.precision import precision_verdict

    margins = {}
    conditions = [margin_condition] if margin_condition else sorted({r["condition"] for r in done})
    for k in kpis:
        widths = [measured.condition(c).kpis[measured_name(k)].ci95 for c in conditions
                  if measured_name(k) in measured.condition(c).kpis]
        if widths:
            margins[k] = min(widths)
    value = lambda d, k: math.nan if d.get(k) is None else float(d[k])  # noqa: E731
    ok = [r for r in done if r["failed"] is None]
    a = np.array([[value(r["stored_kpis"], k) for k in kpis] for r in ok]).reshape(len(ok), len(kpis))
    b = np.array([[value(r["kpis"], k) for k in kpis] for r in ok]).reshape(len(ok), len(kpis))
    verdict = precision_verdict(a, b, kpis, margins, labels=("stored", "rerun"), paired=True, minimum_seeds=2)
    lines = [f"{len(done)} reruns, {len(done) - len(ok)} blew up" + "".join(
        f"\n- blew up: {r['condition']} seed {r['seed']}: {r['failed']}" for r in done if r["failed"] is not None)]
    where = (f"margins: the lab's 95 % CI half-widths at {margin_condition}" if margin_condition
             else f"margins: the smallest of the lab's 95 % CI half-widths over {', '.join(conditions)}")
    return "\n".join(lines + ["", where, verdict.to_text()])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("store", type=Path, help="campaign store (SQLite) whose runs are rerun")
    parser.add_argument("--stages", nargs="+", default=["verification", "validation"])
    parser.add_argument("--calibration", type=Path, default=None,
                        help="calibration JSON: rerun only the runs of its calibrated_parameters")
    parser.add_argument("--task-ids", type=int, nargs="+", default=None,
                        help="rerun only these store rows (e.g. a sample of the screening design's corners)")
    parser.add_argument("--margin-condition", default=None,
                        help="the condition whose lab CI half-widths are the margins (default: the smallest "
                             "over the runs' conditions)")
    parser.add_argument("--out", type=Path, required=True, help="JSON lines of the reruns (resumed when it exists)")
    parser.add_argument("--workers", type=int, default=1, help="worker processes of one thread each")
    argv = sys.argv[1:]
    cut = argv.index("--") if "--" in argv else len(argv)
    args = parser.parse_args(argv[:cut])
    overrides = tuple(argv[cut + 1:])
    if not overrides:
        raise ConfigError("rerun_equivalence: give the changed model's config overrides after --, e.g. "
                          "-- profile=lab sim.discharge_time_step_fraction=0.225")
    if args.workers < 1:
        raise ConfigError(f"rerun_equivalence: --workers = {args.workers}; expected an integer >= 1")
    parameters = None
    if args.calibration is not None:
        parameters = calibrated_parameters(args.calibration, "--calibration")
    runs = stored_runs(args.store, args.stages, parameters, args.task_ids)
    if not runs:
        raise ConfigError(f"{args.store}: no finished run of stages {args.stages}"
                          + (f" at the parameters of {args.calibration}" if parameters else "")
                          + (f" among task ids {args.task_ids}" if args.task_ids else ""))
    header = {"store": str(args.store), "stages": args.stages, "parameters": parameters, "overrides": list(overrides)}
    if args.task_ids is not None:
        header["task_ids"] = sorted(set(args.task_ids))
    done = _read_out(args.out, header)
    todo = [r for r in runs if r["task_id"] not in done]
    print(f"{len(runs)} stored runs, {len(done)} rerun before, {len(todo)} to run; overrides: {' '.join(overrides)}",
          flush=True)
    with ProcessPoolExecutor(max_workers=args.workers, mp_context=get_context("spawn")) as pool:
        pending = {pool.submit(_rerun, overrides, r) for r in todo}
        while pending:
            finished, pending = wait(pending, return_when=FIRST_COMPLETED)
            for f in finished:
                r = f.result()
                with args.out.open("a") as fh:
                    fh.write(json.dumps(r) + "\n")
                done[r["task_id"]] = r
                k, s = r["kpis"], r["stored_kpis"]
                print(f"{r['condition']} seed {r['seed']} ({r['wall_s']:.0f} s, stored {r['stored_wall_s']:.0f} s): "
                      + ", ".join(f"{n} {k.get(n)} ({s.get(n)})" for n in ("shear_angle_deg", "angle_of_repose_deg",
                                                                           "fill_bulk_density_kg_m3"))
                      + (f"; blew up: {r['failed']}" if r["failed"] else ""), flush=True)
    from bo.cli.calibrate import calibration_model_for
    from torchdem.drawdown import CALIBRATION_KPIS_DEM

    measured = calibration_model_for(list(overrides))[2]
    if args.margin_condition is not None and args.margin_condition not in measured.names:
        raise ConfigError(f"rerun_equivalence: --margin-condition {args.margin_condition!r} is not a measured "
                          f"condition; known: {list(measured.names)}")
    print("\n" + verdict_text([done[r["task_id"]] for r in runs], list(CALIBRATION_KPIS_DEM), measured,
                              args.margin_condition))


if __name__ == "__main__":
    exit_on_bad_input("rerun_equivalence.py", main)
