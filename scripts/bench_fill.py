"""Rained fill of the CPU slice (50-50, 40 kg) at a sinter lobe spacing: top of the loose stack,
bodies, smallest gap between spheres of different bodies, and placement time, packed by bounding
spheres and by lobes (``run.fill_packing``).

Usage::

    python scripts/bench_fill.py [--lobe-spacing 0.3] [--seed 0] [--json]

A packing that overflows the column prints its error instead of figures.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np
from hydra import compose, initialize_config_dir
from scipy.spatial import cKDTree

from bo.cli.common import model_from, plain_config
from torchdem.cli import CONF_DIR
from torchdem.errors import ConfigError
from torchdem.integrate import sphere_positions


def fill_figures(model, lobe_spacing: float, packing: str, seed: int) -> dict:
    m = dataclasses.replace(model, settings=dataclasses.replace(model.settings, fill_packing=packing))
    started = time.perf_counter()
    try:
        system, state, (n,) = m.test_for("50-50", [{"lobe_spacing_sinter": lobe_spacing}]).build([seed], [0])
    except ConfigError as exc:
        return {"packing": packing, "error": str(exc), "seconds": round(time.perf_counter() - started, 2)}
    seconds = time.perf_counter() - started
    x = sphere_positions(system, state.bodies).numpy()
    r, body = system.sphere_radius[0].numpy(), system.sphere_body[0].numpy()
    period = model.geometry.slice_depth if model.geometry.periodic[1] else None
    pairs = cKDTree(x).query_pairs(2 * float(r.max()) + 1e-3, output_type="ndarray")
    d = x[pairs[:, 0]] - x[pairs[:, 1]]
    if period:
        d[:, 1] -= period * np.round(d[:, 1] / period)
    other = body[pairs[:, 0]] != body[pairs[:, 1]]
    gap = np.linalg.norm(d, axis=1) - r[pairs[:, 0]] - r[pairs[:, 1]]
    return {"packing": packing, "bodies": int(n), "top_m": round(float((x[:, 2] + r).max()), 4),
            "min_gap_mm": round(1e3 * float(gap[other].min()), 4), "seconds": round(seconds, 2)}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--lobe-spacing", type=float, default=0.3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        plain = plain_config(compose("study", overrides=["study=precision", "study_profile=precision"]))
    model = model_from(plain)
    g = model.geometry
    out = {"lobe_spacing": args.lobe_spacing, "allowed_top_m": g.upper_bottom_z + 3 * g.upper_height,
           "fills": [fill_figures(model, args.lobe_spacing, p, args.seed) for p in ("bounding", "lobes")]}
    if args.json:
        print(json.dumps(out, indent=2))
        return
    print(f"slice, 50-50, 40 kg, lobe spacing {args.lobe_spacing}; the stack may reach {out['allowed_top_m']:.2f} m")
    for f in out["fills"]:
        if "error" in f:
            print(f"  {f['packing']:8s}: fails after {f['seconds']} s: {f['error']}")
        else:
            print(f"  {f['packing']:8s}: {f['bodies']} bodies, top {f['top_m']} m, smallest gap {f['min_gap_mm']} mm, "
                  f"{f['seconds']} s")


if __name__ == "__main__":
    main()
