"""Draw down benchmark: wall time of one default ``drawdown_slice`` run and of a batch of 10.

Prints figures; it is not a test and asserts nothing about speed.

Contract: composes the same config as ``torchdem-simulate`` (``conf/simulate.yaml`` with the
CPU profile: ``geometry=drawdown_slice``, ``mixture=pellet_sinter_50_50``, ``sim=cpu``) plus
any Hydra overrides given after ``--``, then times ``DrawDownTest.run`` for B = 1 and for a
batch of B = ``--batch`` replicates (one ensemble). With ``--workers W`` (> 1) the batch is
split into W worker processes (spawned, ``torch.set_num_threads(cores // W)`` each), each running
its share of the replicates (its own seeds) one run after the other (``--ensemble 1``, the default:
what ``executor=dask executor.n_workers=W executor.batch_size=1`` does, the lab campaign's split),
or in ensembles of at most ``--ensemble K`` members (``--ensemble 5`` with ``--batch 10 --workers
2``: the split the figures before 2026-11-27 used). On 2 cores a slice run alone in its process
is faster than a member of a five-member ensemble: 274 s against 311 s for the batch of 10
(docs/performance.md). Its wall time runs from the first submission to the
last result, process start-up and extension loading included. For each it prints the bodies and spheres
per member, steps, time step, wall time split into fill (particle placement) and simulation,
particle-steps per second, and the CPU other processes used meanwhile (figures taken with
``other cores`` above ~0.1 are low). ``--json`` prints one JSON object.

Issue target on the 2-core reference machine: one run within 2 minutes, a batch of 10 within
10 minutes.

On a GPU: ``sim.device=cuda`` (or ``sim=gpu``, the paper's unreduced model) runs each case as
one ensemble on the GPU (use ``--workers 1``); the fill is placed on the CPU.

Usage: ``python scripts/bench_drawdown.py [--batch 10] [--workers 2] [--ensemble 1] [--json] [--skip-single | --skip-batch]
[-- sim.compile=true ...]``
"""
from __future__ import annotations

import argparse
import concurrent.futures
import json
import multiprocessing
import os
import sys
import time

import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from torchdem import config
from torchdem.cli import CONF_DIR, device_from
from torchdem.cpu_monitor import CpuMonitor
from torchdem.drawdown import DrawDownTest


def make_test(overrides: list[str]) -> tuple[DrawDownTest, torch.device]:
    """The configured draw down test and the device it runs on (``sim.device``)."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        c = OmegaConf.to_container(compose(config_name="simulate", overrides=overrides), resolve=True)
    test = DrawDownTest(config.mixture_from(c["mixture"]), config.geometry_from(c["geometry"]),
                        config.contact_from(c["contact"]), config.run_settings_from(c["sim"], c["run"]))
    return test, device_from(c["sim"]["device"], "sim.device")


def _figures(result, members: int) -> dict:
    """What one ensemble run reports (both modes)."""
    spheres, steps, fill_s = result.spheres, int(result.steps), result.build_time_s
    sim_s = result.wall_time_s - fill_s
    return {"members": members, "bodies_per_member": result.particles, "spheres_per_member": spheres, "steps": steps,
            "dt_s": result.dt, "wall_s": result.wall_time_s, "fill_s": fill_s, "simulation_s": sim_s,
            "particle_steps_per_s": members * spheres * steps / max(sim_s, 1e-9),
            "kpis_member0": result.kpis[0], "not_measured_member0": result.errors[0],
            "mass_balance_member0": result.conservation[0]}


def time_run(test: DrawDownTest, members: int, device: torch.device) -> dict:
    with CpuMonitor() as cpu:
        result = test.run(replicates=members, device=device)
    return {**_figures(result, members), "other_cores": cpu.other_cores}


def _worker_run(overrides: list[str], seeds: list[int], threads: int, ensemble: int | None = None) -> dict:
    """One worker of ``--workers``: its replicates (``seeds``) on ``threads`` threads, as one ensemble,
    or one after the other in ensembles of at most ``ensemble`` members."""
    torch.set_num_threads(threads)
    test, device = make_test(overrides)
    size = ensemble or len(seeds)
    parts = [_figures(test.run(replicates=len(chunk), seeds=chunk, device=device), len(chunk))
             for chunk in (seeds[i:i + size] for i in range(0, len(seeds), size))]
    first = parts[0]
    return {**first, "members": len(seeds), "wall_s": sum(p["wall_s"] for p in parts),
            "fill_s": sum(p["fill_s"] for p in parts), "simulation_s": sum(p["simulation_s"] for p in parts),
            "particle_steps_per_s": sum(p["members"] * p["spheres_per_member"] * p["steps"] for p in parts)
            / max(sum(p["simulation_s"] for p in parts), 1e-9)}


def time_workers(overrides: list[str], members: int, workers: int, ensemble: int | None = None) -> dict:
    """The batch split over ``workers`` processes (see the module docstring); ``ensemble``: members
    per ensemble inside a worker (None: all of its share at once)."""
    cores = os.cpu_count() or 1
    threads = max(1, cores // workers)
    seeds = list(range(members))
    shares = [seeds[w::workers] for w in range(workers) if seeds[w::workers]]
    context = multiprocessing.get_context("spawn")
    with CpuMonitor() as cpu:
        started = time.perf_counter()
        with concurrent.futures.ProcessPoolExecutor(len(shares), mp_context=context) as pool:
            parts = list(pool.map(_worker_run, [overrides] * len(shares), shares, [threads] * len(shares),
                                  [ensemble] * len(shares)))
        wall = time.perf_counter() - started
    first = parts[0]
    work = sum(p["members"] * p["spheres_per_member"] * p["steps"] for p in parts)
    return {"members": members, "workers": len(shares), "threads_per_worker": threads,
            "ensemble": ensemble or max(len(share) for share in shares),
            "bodies_per_member": first["bodies_per_member"], "spheres_per_member": first["spheres_per_member"],
            "steps": first["steps"], "dt_s": first["dt_s"], "wall_s": wall,
            "fill_s": max(p["fill_s"] for p in parts), "simulation_s": max(p["wall_s"] - p["fill_s"] for p in parts),
            "particle_steps_per_s": work / max(wall - max(p["fill_s"] for p in parts), 1e-9),
            "other_cores": cpu.other_cores,
            "worker_wall_s": [p["wall_s"] for p in parts], "kpis_member0": first["kpis_member0"],
            "not_measured_member0": first["not_measured_member0"],
            "mass_balance_member0": first["mass_balance_member0"]}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--batch", type=int, default=10)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--skip-single", action="store_true")
    parser.add_argument("--skip-batch", action="store_true")
    parser.add_argument("--workers", type=int, default=1,
                        help="split the batch over this many processes (threads: cores // workers each)")
    parser.add_argument("--ensemble", type=int, default=1,
                        help="members per ensemble inside a worker (default 1: one run after the other, as a "
                             "campaign with executor.batch_size=1; 5 with --batch 10 --workers 2: the older split)")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. sim.compile=true")
    args = parser.parse_args(argv)
    if args.workers < 1 or args.workers > args.batch:
        parser.error(f"--workers {args.workers}: expected 1 .. --batch ({args.batch})")
    if args.ensemble < 1:
        parser.error(f"--ensemble {args.ensemble}: expected an int >= 1")
    test, device = make_test(args.overrides)
    log = (lambda *a: print(*a, file=sys.stderr)) if args.json else print
    gpu = f", {torch.cuda.get_device_name(device)}" if device.type == "cuda" else ""
    log(f"torch {torch.__version__}, device {device}{gpu}, threads {torch.get_num_threads()}, mixture {test.mixture.name}, "
        f"slice {test.geometry.slice_depth} m, G {test.settings.shear_modulus}, fines cut {test.settings.fines_cut}")
    figures = {}
    for name, members in (("single", 1), ("batch", args.batch)):
        if (name == "single" and args.skip_single) or (name == "batch" and args.skip_batch):
            continue
        split = name == "batch" and args.workers > 1
        r = (time_workers(args.overrides, members, args.workers, args.ensemble) if split
             else time_run(test, members, device))
        figures[name] = r = {**r, "device": str(device)}  # both modes run on sim.device
        how = (f" in {r['workers']} processes x {r['threads_per_worker']} threads, ensembles of {r['ensemble']}"
               if split else "")
        log(f"{name:6s} B={members:3d}{how}: {r['spheres_per_member']} spheres/member, {r['steps']} steps of "
            f"{r['dt_s']:.3g} s; wall {r['wall_s']:.1f} s (fill {r['fill_s']:.1f} s, simulation "
            f"{r['simulation_s']:.1f} s); {r['particle_steps_per_s']:.3g} particle-steps/s; other cores "
            f"{r['other_cores'] if r['other_cores'] is None else round(r['other_cores'], 2)}")
    if args.json:
        print(json.dumps(figures, indent=2, default=float))


if __name__ == "__main__":
    main()
