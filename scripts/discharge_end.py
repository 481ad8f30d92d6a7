"""What stopping a draw down at a fixed time does to its KPIs: runs of one parameter set of a
campaign store, each measured at ``run.discharge_time_s`` and again, on the same trajectory, once
its discharge has ended (``run.max_discharge_time_s``), side by side.

The parameter set is the first run of ``--stage`` in ``--store`` (default: the verification of the
first lab campaign, its calibrated set); the model is the config's (Hydra overrides after ``--``,
default ``profile=lab``). Each ``CONDITION:SEED`` runs alone on one thread; the table gives each
KPI at the fixed end, at the discharge's end, and the difference, then the means per condition.

Usage::

    python scripts/discharge_end.py 50-50:0 50-50:1 25-75:0 --json out.json -- profile=lab
"""
from __future__ import annotations

import argparse
import json
import sqlite3
import sys
import time

import numpy as np
import torch

from bo.cli.calibrate import calibration_model_for
from torchdem.drawdown import CALIBRATION_KPIS_DEM
from torchdem.errors import ConfigError, exit_on_bad_input

KPIS = CALIBRATION_KPIS_DEM


def parameter_set(store: str, stage: str) -> dict[str, float]:
    """The parameters of the first run of ``stage`` in the store (opened read-only)."""
    with sqlite3.connect(f"file:{store}?mode=ro", uri=True) as con:
        row = con.execute("SELECT params FROM evaluations WHERE stage = ? ORDER BY task_id LIMIT 1", (stage,)).fetchone()
    if row is None:
        raise ConfigError(f"--stage {stage!r}: no run of that stage in {store}")
    return json.loads(row[0])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="CONDITION:SEED, e.g. 50-50:0")
    parser.add_argument("--store", default="campaigns/table2/lab_4s.sqlite")
    parser.add_argument("--stage", default="verification")
    parser.add_argument("--json", help="write the rows as JSON here too")
    argv = sys.argv[1:]
    cut = argv.index("--") if "--" in argv else len(argv)
    args = parser.parse_args(argv[:cut])
    args.overrides = argv[cut + 1:]  # Hydra overrides of the calibrate config, after --
    torch.set_num_threads(1)
    _, model, _ = calibration_model_for(args.overrides or ["profile=lab"])
    s = model.settings
    if s.max_discharge_time is None:
        raise ConfigError("run.max_discharge_time_s is null in this config: the runs would stop at "
                          f"run.discharge_time_s = {s.discharge_time:g} s; set it (profile=lab does)")
    params = parameter_set(args.store, args.stage)
    print(f"parameters ({args.stage} of {args.store}): {params}")
    rows = []
    for spec in args.runs:
        condition, _, seed = spec.partition(":")
        started = time.perf_counter()
        res = model.test_for(condition, [params]).run_members([(0, 0, int(seed or 0))], kpis_at_discharge_time=True)
        fixed, end = res.kpis_at_discharge_time[0], res.kpis[0]
        row = {"condition": condition, "seed": int(seed or 0), "wall_s": round(time.perf_counter() - started, 1),
               "ended": bool(end.get("discharge_ended")), "discharge_duration_s": end.get("discharge_duration_s"),
               "fixed": {k: fixed.get(k) for k in KPIS}, "end": {k: end.get(k) for k in KPIS}}
        rows.append(row)
        print(f"{condition} seed {row['seed']}: discharge ended {row['discharge_duration_s']:.2f} s after the gate "
              f"opened ({row['wall_s']:.0f} s wall); " + ", ".join(
                  f"{k} {row['fixed'][k]:.2f} -> {row['end'][k]:.2f}" for k in KPIS), flush=True)
    print("\n| condition | runs | ended after, s | " + " | ".join(f"{k}: at {s.discharge_time:g} s -> ended (diff)"
                                                                  for k in KPIS) + " |")
    print("| --- | ---: | ---: |" + " ---: |" * len(KPIS))
    for condition in dict.fromkeys(r["condition"] for r in rows):
        mine = [r for r in rows if r["condition"] == condition]
        cells = []
        for k in KPIS:
            a = np.array([r["fixed"][k] for r in mine])
            b = np.array([r["end"][k] for r in mine])
            cells.append(f"{a.mean():.2f} -> {b.mean():.2f} ({(b - a).mean():+.2f})")
        duration = ", ".join(f"{r['discharge_duration_s']:.2f}" for r in mine)
        print(f"| {condition} | {len(mine)} | {duration} | " + " | ".join(cells) + " |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"parameters": params, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    exit_on_bad_input("discharge_end.py", main)
