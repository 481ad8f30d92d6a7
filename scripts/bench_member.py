"""Time the steps of one flowing lab-geometry member (profile=lab, 50-50) on one thread: the figure
the rebuild and kernel changes of docs/performance.md ("What limits a run now") were compared by.

The member is filled and settled (``bench_search.settled_member``, cached), then run to ``--start``
s of simulated time (the gate opens at the end of the 0.8 s fill, so the default 1.3 s is half a
second into the discharge) and cached again in ``.bench_cache/``. The script then advances
``--warm`` steps and times ``--steps`` more by the process's CPU time (``time.thread_time``), which
other processes on the machine disturb less than the wall clock (on a GPU, ``--device cuda``, by the
wall clock, the GPU synchronised at both ends; ``--compile`` compiles the kernels in the warm-up).
Sorting along the Morton curve every 10 rebuilds, as the lab profile does. Compare two versions of the code by running it with
each in turn (two git worktrees, ``PYTHONPATH`` set to each), several times, alternating.

Usage::

    python scripts/bench_member.py [--lobe-spacing 0.3] [--start 1.3] [--steps 1000] [--moved-share 0.25] [--json]
                                   [--device cuda [--compile]] [--fines-kept [--skin-fraction 0.1]]

``--moved-share 0`` makes every neighbour rebuild search every sphere (``System.moved_share``).
``--time-step-factor 1.5`` times the member at 1.5x its step from ``--start`` on (what
``sim.discharge_time_step_fraction`` 0.225 over 0.15 does); compare the cases by the CPU seconds per
simulated second it prints, since a longer step also rebuilds the lists after fewer steps.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time

import torch

from bench_search import CACHE, member_system, settled_member
from torchdem.simulation import Simulation


def flowing_member(lobe_spacing: float, seed: int, start: float, device: str = "cpu",
                   compile: bool = False, fines_kept: bool = False, skin_fraction: float | None = None) -> Simulation:
    """The member run to ``start`` s, cached on disk (only that file is read once it is there);
    reordered every 10 rebuilds; ``skin_fraction``: its lists at that skin from ``start`` on (the cache
    is run at the profile's; the skin changes no contact, docs/performance.md "Settings")."""
    path = CACHE / f"member_lab_s{lobe_spacing:g}_seed{seed}_t{start:g}{'_fines' if fines_kept else ''}.pt"
    if path.exists():
        system, _ = member_system(lobe_spacing, seed, device, fines_kept, skin_fraction)
        return Simulation.load(path, system, reorder_every=10, compile=compile)
    settled = settled_member(lobe_spacing, seed, 0.8, device, fines_kept)
    sim = Simulation(settled.system, settled.state, reorder_every=10)
    started = time.perf_counter()
    sim.run_until(start)
    print(f"ran to {start} s in {time.perf_counter() - started:.0f} s; cached in {path}")
    sim.save(path)
    system = settled.system if skin_fraction is None else member_system(lobe_spacing, seed, device, fines_kept,
                                                                         skin_fraction)[0]
    return Simulation.load(path, system, reorder_every=10, compile=compile)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--lobe-spacing", type=float, default=0.3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--start", type=float, default=1.3, help="simulated time before timing, s")
    parser.add_argument("--warm", type=int, default=20, help="untimed steps first")
    parser.add_argument("--steps", type=int, default=1000, help="timed steps")
    parser.add_argument("--moved-share", type=float, default=None,
                        help="System.moved_share (default: the system's; 0: whole rebuilds)")
    parser.add_argument("--time-step-factor", type=float, default=1.0,
                        help="the member's time step times this from --start on (> 0)")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON too")
    parser.add_argument("--device", default="cpu", help="torch device (cpu, cuda); a GPU is timed by the wall clock")
    parser.add_argument("--compile", action="store_true", help="Simulation(compile=True), compiled in the warm-up")
    parser.add_argument("--fines-kept", action="store_true",
                        help="the sinter's whole sieve (sim.fines_cut_mm=null, as profile=lab_fines runs it)")
    parser.add_argument("--skin-fraction", type=float, default=None,
                        help="sim.skin_fraction from --start on (default: profile=lab's 0.25; profile=lab_round runs "
                             "the fines kept at 0.1)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.skin_fraction is not None and not 0 < args.skin_fraction <= 1:
        parser.error(f"--skin-fraction {args.skin_fraction}: expected a fraction of the largest radius in (0, 1]")
    sim = flowing_member(args.lobe_spacing, args.seed, args.start, args.device, args.compile, args.fines_kept,
                         args.skin_fraction)
    gpu = sim.system.mass.device.type == "cuda"
    clock = time.perf_counter if gpu else time.thread_time
    sync = torch.cuda.synchronize if gpu else (lambda: None)
    if args.moved_share is not None:
        sim.system = dataclasses.replace(sim.system, moved_share=args.moved_share)
    if not args.time_step_factor > 0:
        parser.error(f"--time-step-factor {args.time_step_factor}: expected > 0")
    if args.time_step_factor != 1:
        sim.system = sim.system.with_time_step(sim.system.dt * args.time_step_factor, sim.state.step)
    sim.advance(args.warm)
    rebuilds = sim.state.rebuilds
    sync()
    started = clock()
    sim.advance(args.steps)
    sync()
    elapsed = clock() - started
    out = {"lobe_spacing": args.lobe_spacing, "moved_share": sim.system.moved_share, "device": args.device,
           "compile": args.compile, "fines_kept": args.fines_kept,
           "spheres": sim.system.n_spheres, "skin_m": float(sim.system.skin), "steps": args.steps,
           "ms_per_step": 1e3 * elapsed / args.steps, "steps_per_rebuild": args.steps / max(sim.state.rebuilds - rebuilds, 1),
           "dt_s": sim.system.dt, "cpu_s_per_simulated_s": elapsed / (args.steps * sim.system.dt)}
    timed_by = f"wall clock on {args.device}" if gpu else "CPU time, one thread"
    print(f"lab member{' (fines kept)' if args.fines_kept else ''}, lobe spacing {args.lobe_spacing:g}, {out['spheres']} spheres, from t = {args.start:g} s: "
          f"{out['ms_per_step']:.2f} ms a step ({timed_by}), {out['steps_per_rebuild']:.1f} steps a rebuild, "
          f"moved share {out['moved_share']:g}; step {out['dt_s']:.4g} s: {out['cpu_s_per_simulated_s']:.1f} s per "
          "simulated second")
    if args.json:
        print(json.dumps(out))


if __name__ == "__main__":
    main()
