"""Where the wall time of a flowing lab-geometry member's step goes, on one or more threads.

The member of ``scripts/bench_member.py`` (profile=lab, 50-50, cached in ``.bench_cache/``) is
advanced ``--warm`` steps, then ``--steps`` more with wall-clock timers around the parts of a step
that Python calls: the neighbour rebuild (and, inside it, the pair search, the per-pair constants,
the history carried, the wall list), the moved-sphere test, the fused forces and kick, and the
spatial reorder. The drift and the rest are the remainder. It printed the figures of
docs/performance.md ("The reorder without a search"); compare thread counts or versions of the code
by running it in turn, alternating, on an idle machine.

Usage::

    python scripts/bench_step_parts.py [--threads 1] [--steps 400] [--lobe-spacing 0.2574] [--json]
"""
from __future__ import annotations

import argparse
import collections
import json
import time

import torch

import torchdem.integrate as integrate
import torchdem.neighbors as neighbors
import torchdem.simulation as simulation
from bench_member import flowing_member

#: (module, function) pairs timed; the rebuild's parts are inside the rebuild's time.
PARTS = ((integrate, "rebuild"), (neighbors, "find_pairs"), (integrate, "pair_constants"),
         (neighbors, "carry_history"), (neighbors, "find_wall_pairs"), (integrate, "moved_spheres"),
         (integrate, "forces_and_kick"), (simulation, "reorder"))


def timed(total: collections.Counter, calls: collections.Counter) -> None:
    """Wrap every function of :data:`PARTS` in its module so that its wall time and calls add up."""
    for module, name in PARTS:
        function = getattr(module, name)

        def wrapper(*args, _f=function, _name=name, **kwargs):
            started = time.perf_counter()
            try:
                return _f(*args, **kwargs)
            finally:
                total[_name] += time.perf_counter() - started
                calls[_name] += 1

        setattr(module, name, wrapper)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--warm", type=int, default=20)
    parser.add_argument("--lobe-spacing", type=float, default=0.2574)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--start", type=float, default=1.3, help="simulated time before timing, s")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON too")
    args = parser.parse_args()
    if args.threads < 1 or args.steps < 1:
        parser.error(f"--threads {args.threads} and --steps {args.steps} must be at least 1")
    torch.set_num_threads(args.threads)
    total, calls = collections.Counter(), collections.Counter()
    timed(total, calls)
    sim = flowing_member(args.lobe_spacing, args.seed, args.start)
    sim.advance(args.warm)
    total.clear(), calls.clear()
    started = time.perf_counter()
    sim.advance(args.steps)
    step_ms = 1e3 * (time.perf_counter() - started) / args.steps
    print(f"lab member, lobe spacing {args.lobe_spacing:g}, {sim.system.n_spheres} spheres, {args.threads} thread(s): "
          f"{step_ms:.3f} ms a step (wall clock), {calls['rebuild']} rebuilds and {calls['reorder']} reorders "
          f"in {args.steps} steps")
    figures = {"threads": args.threads, "step_ms": step_ms, "parts": {}}
    for name, seconds in total.most_common():
        per_step, per_call = 1e3 * seconds / args.steps, 1e3 * seconds / calls[name]
        figures["parts"][name] = {"ms_per_step": per_step, "ms_per_call": per_call, "calls": calls[name]}
        print(f"  {name:16s} {per_step:7.3f} ms a step  {per_call:7.3f} ms a call  ({calls[name]} calls)")
    if args.json:
        print(json.dumps(figures))


if __name__ == "__main__":
    main()
