"""What the core share saves: a stage of N runs on a local dask cluster, with and without it.

Prints figures; it is not a test and asserts nothing about speed.

Contract: composes ``conf/calibrate.yaml`` with the Hydra overrides after ``--`` (default: the lab
profile at its default parameters), builds the campaign's model (``bo.cli.common.model_from``) and
runs ``--runs`` replicates of one parameter set (seeds 0 .. N-1, condition 50-50, what a
verification stage runs) through ``run_pending`` on ``executor=dask executor.n_workers=W
executor.batch_size=1``, once with ``executor.share_cores`` on and once off, in alternating order
over ``--pairs`` pairs, each case in a fresh temporary store (so nothing is reused). It times from
the first claim to the last result (the cluster is started before the clock and kept for all
cases) and prints, per case, the wall time, the runs' own wall times and the CPU other processes
used meanwhile (figures taken with ``other cores`` above ~0.1 are low). With N a multiple of W there
is no tail and the two cases should tie; with N = W k + 1 the last run takes every core.

Usage::

    python scripts/bench_core_share.py [--runs 3] [--workers 2] [--pairs 1] [--json] [-- profile=lab ...]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

from hydra import compose, initialize_config_dir

from bo.campaign.executor import run_pending
from bo.campaign.store import CampaignStore
from bo.cli.common import ExecutorSettings, executor_factory, model_from, plain_config
from torchdem.cli import CONF_DIR
from torchdem.cpu_monitor import CpuMonitor


def time_stage(executor_for, model, runs: int, directory: Path) -> dict:
    """One stage of ``runs`` replicates through a fresh store."""
    store = CampaignStore(directory / "stage.sqlite", "bench-core-share", code_version="bench")
    store.batch("verification", "bench", lambda: [{"mu_s_pp": float(model.fixed.get("mu_s_pp", 0.5))}],
                seeds=list(range(runs)), conditions=["50-50"])
    with executor_for(model) as executor, CpuMonitor() as cpu:
        started = time.perf_counter()
        run_pending(store, executor, "verification")
        wall = time.perf_counter() - started
    records = store.records("verification")
    failed = [r.error for r in records if r.status != "done"]
    return {"wall_s": wall, "run_wall_s": sorted(r.wall_time for r in records), "failed": failed,
            "other_cores": cpu.other_cores}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--pairs", type=int, default=1, help="pairs of cases, alternating which runs first")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides (default: profile=lab)")
    args = parser.parse_args(argv)
    if args.runs < 1 or args.workers < 1 or args.pairs < 1:
        parser.error(f"--runs {args.runs}, --workers {args.workers}, --pairs {args.pairs}: each must be >= 1")
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        plain = plain_config(compose("calibrate", overrides=args.overrides or ["profile=lab"]))
    model = model_from(plain)
    log = (lambda *a: print(*a, file=sys.stderr)) if args.json else print
    settings = ExecutorSettings("dask", batch_size=1, n_workers=args.workers)
    cases: dict[str, list[dict]] = {"share": [], "no share": []}
    with executor_factory(settings) as shared_for, executor_factory(
            dataclasses.replace(settings, share_cores=False)) as plain_for:
        executors = {"share": shared_for, "no share": plain_for}
        for pair in range(args.pairs):
            order = ["share", "no share"] if pair % 2 == 0 else ["no share", "share"]
            for name in order:
                with tempfile.TemporaryDirectory() as tmp:
                    figures = time_stage(executors[name], model, args.runs, Path(tmp))
                cases[name].append(figures)
                log(f"{name:>8}: {args.runs} runs on {args.workers} workers in {figures['wall_s']:.1f} s "
                    f"(runs {', '.join(f'{w:.1f}' for w in figures['run_wall_s'])} s; "
                    f"other cores {figures['other_cores']:.2f}){'; FAILED ' + str(figures['failed']) if figures['failed'] else ''}")
    best = {name: min(c["wall_s"] for c in runs) for name, runs in cases.items()}
    summary = {"runs": args.runs, "workers": args.workers, "overrides": args.overrides or ["profile=lab"],
               "cases": cases, "best_wall_s": best, "speedup": best["no share"] / best["share"]}
    log(f"best of {args.pairs}: share {best['share']:.1f} s, no share {best['no share']:.1f} s, "
        f"{summary['speedup']:.2f}x")
    if args.json:
        print(json.dumps(summary))


if __name__ == "__main__":
    main()
