"""Time the steps of one lab-geometry member (profile=lab, 50-50) at several Verlet skins
(``sim.skin_fraction``, a fraction of the largest sphere radius), on one thread.

A thinner skin lists fewer pairs that do not touch, so each step tests and gathers less, but the
list is rebuilt more often; on flat sinter (lobe spacing 0.3: 2 mm lobes beside 8 mm pellets, a skin
of 0.25 x 8 mm equals a lobe's radius) the balance may not be where it is on the slice. The member is
filled and settled once (cached in ``.bench_cache/`` as ``scripts/bench_search.py`` does); every case
starts from that state at the gate's opening, renumbered along the Morton curve and reordered every
10 rebuilds as a campaign run is. After ``--warm`` steps each (into the discharge), the cases take
``--chunk`` steps in turn, ``--rounds`` times, the order reversed every round so that the machine's
drift hits them alike. It prints the time per step, the steps per rebuild and the speed-up over the
first skin, and how much CPU other processes used meanwhile. ``--time-step-factor 1.5`` runs every
case at 1.5x the member's step from the gate's opening on (``sim.discharge_time_step_fraction`` 0.225
over 0.15): a longer step moves the spheres further between steps, so the balance may move.
``--fines-kept`` times the member with the sinter's whole sieve (``sim.fines_cut_mm=null``, as
``profile=lab_fines`` and ``profile=lab_round`` run it): at lobe spacing 0.15, spheres of 1.96-8.70 mm
radius, half of them under 2.61 mm, so a skin of 0.25 x the largest radius (2.18 mm) is about a median
sphere's radius. ``--same-bits STEPS`` times nothing: it
steps every skin's member without reordering and prints how far its positions end from the first's (the
lists hold the same touching pairs in the same order, so a skin should change no bit).

Usage::

    python scripts/bench_skin.py [--lobe-spacing 0.3] [--fractions 0.25 0.15 0.1 0.35 0.5] [--warm 1500]
                                 [--chunk 200] [--rounds 6] [--fines-kept] [--same-bits 3000] [--json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_search import CACHE, settled_member  # noqa: E402

from bo.cli.common import model_from, plain_config  # noqa: E402
from torchdem.cli import CONF_DIR  # noqa: E402
from torchdem.cpu_monitor import CpuMonitor  # noqa: E402
from torchdem.reorder import reorder  # noqa: E402
from torchdem.simulation import Simulation  # noqa: E402


def member_with_skin(lobe_spacing: float, seed: int, fraction: float, time_step_factor: float = 1.0,
                     fines_kept: bool = False, reordered: bool = True) -> Simulation:
    """The cached settled member, its system built with ``sim.skin_fraction = fraction`` (its step times
    ``time_step_factor`` from here on); ``reordered``: renumbered along the Morton curve now and every 10
    rebuilds, as a campaign run is (the order, and so the bits of the force sums, then follows the
    rebuilds, which the skin times)."""
    fines = ["sim.fines_cut_mm=null"] if fines_kept else []
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        plain = plain_config(compose("calibrate", overrides=["profile=lab", f"sim.skin_fraction={fraction}", *fines]))
    test = model_from(plain).test_for("50-50", [{"lobe_spacing_sinter": lobe_spacing}])
    system, _, _ = test.build([seed], [0])
    cached = CACHE / f"search_lab_s{lobe_spacing:g}_seed{seed}_t0.8{'_fines' if fines_kept else ''}.pt"
    settled = Simulation.load(cached, system)
    system, state = reorder(settled.system, settled.state) if reordered else (settled.system, settled.state)
    if time_step_factor != 1:
        system = system.with_time_step(system.dt * time_step_factor, state.step)
    return Simulation(system, state, reorder_every=10 if reordered else 0)


def same_bits(lobe_spacing: float, seed: int, fractions, steps: int, fines_kept: bool) -> dict[float, float]:
    """Largest position difference, m, of each skin's member from the first's after ``steps`` steps from
    the gate's opening, none of them reordered: 0.0 where the skin changed no bit of the run."""
    sims = {f: member_with_skin(lobe_spacing, seed, f, fines_kept=fines_kept, reordered=False) for f in fractions}
    for sim in sims.values():
        sim.advance(steps)
    base = sims[fractions[0]].state.bodies.position
    return {f: float((sim.state.bodies.position - base).abs().max()) for f, sim in sims.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--lobe-spacing", type=float, default=0.3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--fractions", type=float, nargs="+", default=[0.25, 0.15, 0.1, 0.35, 0.5],
                        help="skin fractions of the largest sphere radius; the first is the baseline")
    parser.add_argument("--warm", type=int, default=1500, help="steps of every case before timing (into the discharge)")
    parser.add_argument("--chunk", type=int, default=200, help="steps per case per round")
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--time-step-factor", type=float, default=1.0,
                        help="every case's step times this from the gate's opening on (> 0)")
    parser.add_argument("--fines-kept", action="store_true",
                        help="the sinter's whole sieve (sim.fines_cut_mm=null, as profile=lab_round runs it)")
    parser.add_argument("--same-bits", type=int, default=0, metavar="STEPS",
                        help="instead of timing: step every skin STEPS steps without reordering and print how far "
                             "its positions are from the first skin's")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON too")
    args = parser.parse_args()
    if not args.time_step_factor > 0:
        parser.error(f"--time-step-factor {args.time_step_factor}: expected > 0")
    if any(not 0 < f <= 2 for f in args.fractions) or len(set(args.fractions)) != len(args.fractions):
        parser.error(f"--fractions {args.fractions}: distinct values in (0, 2] expected")
    if args.chunk < 1 or args.rounds < 1 or args.warm < 0:
        parser.error("--chunk and --rounds must be >= 1 and --warm >= 0")
    if args.same_bits < 0:
        parser.error(f"--same-bits {args.same_bits}: expected a number of steps >= 1 (0: time the skins)")
    torch.set_num_threads(1)
    settled_member(args.lobe_spacing, args.seed, 0.8, fines_kept=args.fines_kept)  # fills and caches the member once
    if args.same_bits:
        for f, d in same_bits(args.lobe_spacing, args.seed, args.fractions, args.same_bits, args.fines_kept).items():
            print(f"  skin {f:5.3g} x r_max: largest position difference from {args.fractions[0]:g} after "
                  f"{args.same_bits} steps: {d:.3g} m")
        return
    sims = {}
    for f in args.fractions:
        sims[f] = member_with_skin(args.lobe_spacing, args.seed, f, args.time_step_factor, args.fines_kept)
        sims[f].advance(args.warm)
    spent = {f: 0.0 for f in args.fractions}
    rebuilds = {f: 0 for f in args.fractions}
    with CpuMonitor() as monitor:
        for r in range(args.rounds):
            for f in (args.fractions if r % 2 == 0 else args.fractions[::-1]):
                before = sims[f].state.rebuilds
                started = time.perf_counter()
                sims[f].advance(args.chunk)
                spent[f] += time.perf_counter() - started
                rebuilds[f] += sims[f].state.rebuilds - before
    steps = args.chunk * args.rounds
    base = args.fractions[0]
    other = monitor.other_cores
    print(f"lobe spacing {args.lobe_spacing}{' (fines kept)' if args.fines_kept else ''}, seed {args.seed}: "
          f"{int(sims[base].system.sphere_radius.numel())} "
          f"spheres, t = {sims[base].time:.3f} s at the end, {steps} steps of {sims[base].system.dt:.4g} s per case "
          f"after {args.warm}, one thread; "
          "other processes used " + (f"{other:.2f} cores" if other is not None else "? cores")
          + (" (figures low and noisy)" if other is not None and other > 0.1 else ""))
    out = {}
    for f in args.fractions:
        ms = 1e3 * spent[f] / steps
        per_rebuild = steps / max(rebuilds[f], 1)
        print(f"  skin {f:5.3g} x r_max ({1e3 * sims[f].system.skin:.2f} mm) {ms:7.2f} ms/step, "
              f"{per_rebuild:5.1f} steps per rebuild, {spent[base] / spent[f]:.3f}x")
        out[str(f)] = {"skin_m": sims[f].system.skin, "ms_per_step": ms, "steps_per_rebuild": per_rebuild,
                       "speedup": spent[base] / spent[f]}
    if args.json:
        print(json.dumps({"lobe_spacing": args.lobe_spacing, "fines_kept": args.fines_kept, "steps": steps, "warm": args.warm,
                          "time_step_factor": args.time_step_factor,
                          "other_cpu_cores": other, "cases": out}))


if __name__ == "__main__":
    main()
