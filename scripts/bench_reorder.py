"""Time the steps of one lab-geometry member (profile=lab, 50-50) with its bodies in build order and
renumbered along the Morton curve every k neighbour rebuilds (``sim.reorder_every``), on one thread.

The member is filled and settled once per lobe spacing and seed and cached in ``.bench_cache/`` (as
``scripts/bench_search.py`` does); every case starts from that state at the gate's opening, a
reordered case with one reorder first. After ``--warm`` steps each, the cases take ``--chunk`` steps
in turn, ``--rounds`` times, the order reversed every round so that the machine's drift hits them
alike. It prints the time per step of each case, its speed-up over build order, and how much CPU
other processes used meanwhile (above ~0.1 cores the figures are low and noisy).

Usage::

    python scripts/bench_reorder.py [--lobe-spacing 0.3] [--every 0 3 10 30] [--chunk 150] [--rounds 8]
                                    [--warm 0] [--json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_search import settled_member  # noqa: E402

from torchdem.cpu_monitor import CpuMonitor  # noqa: E402
from torchdem.reorder import reorder  # noqa: E402
from torchdem.simulation import Simulation  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--lobe-spacing", type=float, default=0.3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--every", type=int, nargs="+", default=[0, 3, 10, 30],
                        help="neighbour rebuilds between reorders per case (0: build order, the baseline)")
    parser.add_argument("--chunk", type=int, default=150, help="steps per case per round")
    parser.add_argument("--rounds", type=int, default=8)
    parser.add_argument("--warm", type=int, default=0, help="steps of every case before timing (into the discharge)")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON too")
    args = parser.parse_args()
    if 0 not in args.every:
        parser.error("--every must include 0, the build-order baseline")
    if any(k < 0 for k in args.every) or len(set(args.every)) != len(args.every):
        parser.error(f"--every {args.every}: distinct ints >= 0 expected")
    if args.chunk < 1 or args.rounds < 1 or args.warm < 0:
        parser.error("--chunk and --rounds must be >= 1 and --warm >= 0")
    torch.set_num_threads(1)
    sims: dict[int, Simulation] = {}
    for k in args.every:
        member = settled_member(args.lobe_spacing, args.seed, 0.8)
        if k:
            system, state = reorder(member.system, member.state)
            member = Simulation(system, state, reorder_every=k)
        member.advance(args.warm)
        sims[k] = member
    spent = {k: 0.0 for k in args.every}
    with CpuMonitor() as monitor:
        for r in range(args.rounds):
            for k in (args.every if r % 2 == 0 else args.every[::-1]):
                started = time.perf_counter()
                sims[k].advance(args.chunk)
                spent[k] += time.perf_counter() - started
    steps = args.chunk * args.rounds
    spheres = int(sims[0].system.sphere_radius.numel())
    other = monitor.other_cores
    print(f"lobe spacing {args.lobe_spacing}, seed {args.seed}: {spheres} spheres, t = {sims[0].time:.3f} s at the "
          f"end, {steps} steps per case after {args.warm}, one thread; other processes used "
          + (f"{other:.2f} cores" if other is not None else "? cores")
          + (" (figures low and noisy)" if other is not None and other > 0.1 else ""))
    out = {}
    for k in args.every:
        ms = 1e3 * spent[k] / steps
        label = "build order" if k == 0 else f"reorder every {k} rebuilds"
        print(f"  {label:26s} {ms:7.2f} ms/step  {spent[0] / spent[k]:.3f}x")
        out[str(k)] = {"ms_per_step": ms, "speedup": spent[0] / spent[k]}
    if args.json:
        print(json.dumps({"lobe_spacing": args.lobe_spacing, "spheres": spheres, "steps": steps, "warm": args.warm,
                          "other_cpu_cores": other, "cases": out}))


if __name__ == "__main__":
    main()
