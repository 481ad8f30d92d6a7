"""Calibration benchmark: one whole ``torchdem-calibrate`` campaign on a profile, and its figures.

Prints (and with ``--json`` as one JSON object): the DEM evaluations per stage and in total, the
cross-validated R^2 after every surrogate round for both strategies with the DEM runs each took
to reach R^2 >= target (or that it did not), the final relative error per KPI of verification,
bulk-density verification and validation, the wall time per stage, and the CPU other processes
used meanwhile. A figure is comparable only with the same profile on an otherwise idle machine.
The paper needed 110 design points x 5 replicates (550 DEM runs) to reach R^2 0.95.

Usage: ``python scripts/bench_calibration.py [--profile cpu] [--json] [--out DIR] [-- hydra overrides]``
(a fresh store in ``--out``, default a temporary directory, so nothing is resumed).
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from hydra import compose, initialize_config_dir

from bo.cli.calibrate import calibrate
from bo.cli.common import plain_config
from torchdem.cli import CONF_DIR
from torchdem.cpu_monitor import CpuMonitor


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--profile", default="cpu")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--out", default=None)
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_args(argv)
    out = Path(args.out or tempfile.mkdtemp(prefix="bench_calibration_"))
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        plain = plain_config(compose(config_name="calibrate", overrides=[f"profile={args.profile}",
                                                                          f"store={out / 'campaign.sqlite'}",
                                                                          *args.overrides]))
    started = time.perf_counter()
    with CpuMonitor() as cpu:
        calibrate(plain, out, echo=(lambda s: None) if args.json else print)
    wall = time.perf_counter() - started
    doc = json.loads((out / "calibration.json").read_text())
    sur = doc["surrogate"]
    figures = {
        "profile": args.profile, "wall_time_s": round(wall, 1), "other_cores": cpu.other_cores,
        "wall_time_per_stage_s": doc["wall_time_s"], "dem_evaluations": doc["dem_evaluations"],
        "replicates_per_point": sur["replicates_per_point"], "target_r2": sur["target_r2"],
        "r2_per_round": {"points": [r["n_points"] for r in sur["rounds"]], **sur["strategy_r2"]},
        "to_target": {k: v["dem_runs_to_target"] for k, v in sur["strategy_comparison"].items()},
        "calibrated_parameters": doc["calibrated_parameters"],
        "relative_error_pct": {
            "verification": {a["kpi"]: round(a["relative_error_pct"], 2) for a in doc["verification"]},
            "density": {a["kpi"]: round(a["relative_error_pct"], 2) for a in doc["density"]["verification"]},
            "validation": {c: {a["kpi"]: round(a["relative_error_pct"], 2) for a in rows}
                           for c, rows in doc["validation"].items()}},
        "out_dir": str(out),
    }
    if args.json:
        print(json.dumps(figures, indent=2))
        return
    other = "unknown" if cpu.other_cores is None else f"{cpu.other_cores:.2f}"
    print(f"\nprofile {args.profile}: wall {wall:.0f} s (other processes used {other} cores)")
    print("DEM evaluations: " + ", ".join(f"{k} {v}" for k, v in doc["dem_evaluations"].items()))
    print(f"CV R^2 per round (points {figures['r2_per_round']['points']}, {sur['replicates_per_point']} replicates each):")
    for k, v in sur["strategy_r2"].items():
        reached = figures["to_target"][k]
        print(f"  {k:8s} " + " ".join(f"{x:6.3f}" for x in v) + "   R^2 >= "
              f"{sur['target_r2']}: " + (f"after {reached} DEM runs" if reached else "not reached"))
    for stage, rows in figures["relative_error_pct"].items():
        if stage == "validation":
            for c, r in rows.items():
                print(f"validation {c}: " + ", ".join(f"{k} {v:+.2f} %" for k, v in r.items()))
        elif rows:
            print(f"{stage}: " + ", ".join(f"{k} {v:+.2f} %" for k, v in rows.items()))
    print("wall time per stage: " + ", ".join(f"{k} {v:.0f} s" for k, v in doc["wall_time_s"].items()))


if __name__ == "__main__":
    main()
