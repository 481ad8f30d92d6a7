"""Time the neighbour search of one lab-geometry member (profile=lab, 50-50) on one thread, with one
grid and with the small spheres on a finer grid of their own at several split radii.

The member is filled (rained fill, then ``--settle`` s of simulated time so the bed rests as it does
when the gate opens) once per lobe spacing and seed and cached in ``.bench_cache/``. Each case then
times ``neighbors.find_pairs`` (the C++ column search) ``--repeat`` times, the cases interleaved so
that the machine's drift hits them alike, and prints the median and the fastest time per call and
the list's length (the same in every case: the test suite checks it pair for pair).

Usage::

    python scripts/bench_search.py [--lobe-spacing 0.3] [--seed 0] [--settle 0.8] [--splits 0.3 0.4 0.5 0.6]
"""
from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from bo.cli.common import model_from, plain_config
from torchdem.cli import CONF_DIR
from torchdem.integrate import sphere_positions, sphere_active
from torchdem.neighbors import find_pairs, with_split
from torchdem.simulation import Simulation

CACHE = Path(__file__).resolve().parents[1] / ".bench_cache"


def member_system(lobe_spacing: float, seed: int, device: str = "cpu", fines_kept: bool = False,
                  skin_fraction: float | None = None):
    """System and rained state of one lab member (profile=lab, 50-50); ``fines_kept``: the sinter's whole
    sieve (``sim.fines_cut_mm=null``, as profile=lab_fines runs it) instead of the fines scalped below 10 mm;
    ``skin_fraction``: ``sim.skin_fraction`` (None: the profile's 0.25)."""
    overrides = ["profile=lab", *(["sim.fines_cut_mm=null"] if fines_kept else []),
                 *([] if skin_fraction is None else [f"sim.skin_fraction={skin_fraction}"])]
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        plain = plain_config(compose("calibrate", overrides=overrides))
    test = model_from(plain).test_for("50-50", [{"lobe_spacing_sinter": lobe_spacing}])
    system, state, _ = test.build([seed], [0], device=device)
    return system, state


def settled_member(lobe_spacing: float, seed: int, settle: float, device: str = "cpu", fines_kept: bool = False):
    """The system and state of one lab member (:func:`member_system`) after ``settle`` s, cached on disk
    (a state cached on one device loads onto ``device``)."""
    system, state = member_system(lobe_spacing, seed, device, fines_kept)
    path = CACHE / f"search_lab_s{lobe_spacing:g}_seed{seed}_t{settle:g}{'_fines' if fines_kept else ''}.pt"
    if path.exists():
        return Simulation.load(path, system)
    sim = Simulation(system, state)
    started = time.perf_counter()
    sim.run_until(settle)
    print(f"settled {settle} s in {time.perf_counter() - started:.0f} s; cached in {path}")
    CACHE.mkdir(exist_ok=True)
    sim.save(path)
    return sim


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--lobe-spacing", type=float, default=0.3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--settle", type=float, default=0.8, help="simulated time before timing, s")
    parser.add_argument("--splits", type=float, nargs="+", default=[0.3, 0.4, 0.5, 0.6],
                        help="split radii as fractions of the largest sphere radius")
    parser.add_argument("--repeat", type=int, default=20)
    parser.add_argument("--json", action="store_true", help="print the figures as JSON too")
    args = parser.parse_args()
    torch.set_num_threads(1)
    sim = settled_member(args.lobe_spacing, args.seed, args.settle)
    system, state = sim.system, sim.state
    xs = sphere_positions(system, state.bodies)
    radius, body = system.sphere_radius.reshape(-1), system.sphere_body_flat
    active = sphere_active(system, state.bodies)
    r_max = float(radius[active].max())
    grids = {"one grid": system.grid}
    for f in args.splits:
        grids[f"split {f:.2f} r_max"] = with_split(system.grid, f * r_max, system.skin)
    times: dict[str, list[float]] = {k: [] for k in grids}
    pairs = {}
    for _ in range(args.repeat):
        for name, grid in grids.items():
            started = time.perf_counter()
            i, _j = find_pairs(xs, radius, body, active, system.n_spheres, grid, system.skin)
            times[name].append(time.perf_counter() - started)
            pairs[name] = int(i.numel())
    n = int(active.sum())
    print(f"lobe spacing {args.lobe_spacing}, seed {args.seed}, t = {args.settle} s: {n} spheres, radius "
          f"{float(radius[active].min()) * 1e3:.2f}-{r_max * 1e3:.2f} mm, skin {system.skin * 1e3:.2f} mm, "
          f"{pairs['one grid']} pairs; one thread, {args.repeat} calls per case")
    out = {}
    base = statistics.median(times["one grid"])
    for name, grid in grids.items():
        med, best = statistics.median(times[name]), min(times[name])
        small = int((radius[active] <= grid.split).sum()) if grid.split > 0 else 0
        print(f"  {name:18s} median {med * 1e3:7.2f} ms  best {best * 1e3:7.2f} ms  ({base / med:.2f}x)  "
              f"small spheres {small}, fine cells {grid.fine_dims}, pairs {pairs[name]}")
        out[name] = {"median_ms": med * 1e3, "best_ms": best * 1e3, "pairs": pairs[name], "small": small}
    if args.json:
        print(json.dumps({"lobe_spacing": args.lobe_spacing, "spheres": n, "cases": out}))


if __name__ == "__main__":
    main()
