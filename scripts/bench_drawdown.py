"""Draw down benchmark: wall time of one default ``drawdown_slice`` run and of a batch of 10.

Prints figures; it is not a test and asserts nothing about speed.

Contract: composes the same config as ``torchdem-simulate`` (``conf/simulate.yaml`` with the
CPU profile: ``geometry=drawdown_slice``, ``mixture=pellet_sinter_50_50``, ``sim=cpu``) plus
any Hydra overrides given after ``--``, then times ``DrawDownTest.run`` for B = 1 and for a
batch of B = ``--batch`` replicates (one ensemble). For each it prints the bodies and spheres
per member, steps, time step, wall time split into fill (particle placement) and simulation,
particle-steps per second, and the CPU other processes used meanwhile (figures taken with
``other cores`` above ~0.1 are low). ``--json`` prints one JSON object.

Issue target on the 2-core reference machine: one run within 2 minutes, a batch of 10 within
10 minutes.

Usage: ``python scripts/bench_drawdown.py [--batch 10] [--json] [--skip-single | --skip-batch] [-- sim.compile=true ...]``
"""
from __future__ import annotations

import argparse
import json
import sys

import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from torchdem import config
from torchdem.cli import CONF_DIR
from torchdem.cpu_monitor import CpuMonitor
from torchdem.drawdown import DrawDownTest


def make_test(overrides: list[str]) -> DrawDownTest:
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        c = OmegaConf.to_container(compose(config_name="simulate", overrides=overrides), resolve=True)
    return DrawDownTest(config.mixture_from(c["mixture"]), config.geometry_from(c["geometry"]),
                        config.contact_from(c["contact"]), config.run_settings_from(c["sim"], c["run"]))


def time_run(test: DrawDownTest, members: int) -> dict:
    with CpuMonitor() as cpu:
        result = test.run(replicates=members)
    spheres, steps, fill_s = result.spheres, int(result.steps), result.build_time_s
    sim_s = result.wall_time_s - fill_s
    out = {"members": members, "bodies_per_member": result.particles, "spheres_per_member": spheres, "steps": steps,
           "dt_s": result.dt, "wall_s": result.wall_time_s, "fill_s": fill_s, "simulation_s": sim_s,
           "particle_steps_per_s": members * spheres * steps / max(sim_s, 1e-9),
           "other_cores": cpu.other_cores,
           "kpis_member0": result.kpis[0], "not_measured_member0": result.errors[0],
           "mass_balance_member0": result.conservation[0]}
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--batch", type=int, default=10)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--skip-single", action="store_true")
    parser.add_argument("--skip-batch", action="store_true")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. sim.compile=true")
    args = parser.parse_args(argv)
    test = make_test(args.overrides)
    log = (lambda *a: print(*a, file=sys.stderr)) if args.json else print
    log(f"torch {torch.__version__}, threads {torch.get_num_threads()}, mixture {test.mixture.name}, "
        f"slice {test.geometry.slice_depth} m, G {test.settings.shear_modulus}, fines cut {test.settings.fines_cut}")
    figures = {}
    for name, members in (("single", 1), ("batch", args.batch)):
        if (name == "single" and args.skip_single) or (name == "batch" and args.skip_batch):
            continue
        r = time_run(test, members)
        figures[name] = r
        log(f"{name:6s} B={members:3d}: {r['spheres_per_member']} spheres/member, {r['steps']} steps of "
            f"{r['dt_s']:.3g} s; wall {r['wall_s']:.1f} s (fill {r['fill_s']:.1f} s, simulation "
            f"{r['simulation_s']:.1f} s); {r['particle_steps_per_s']:.3g} particle-steps/s; other cores "
            f"{r['other_cores'] if r['other_cores'] is None else round(r['other_cores'], 2)}")
    if args.json:
        print(json.dumps(figures, indent=2, default=float))


if __name__ == "__main__":
    main()
