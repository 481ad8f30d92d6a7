"""How detectable is the difference between two parameter sets of a study store, against a measured
condition? The power of discovery's discrepancy test (``bo.discovery.detectable``) for the KPI
shift measured between the sets' DEM runs, with the lab's standard uncertainty of that condition
and the DEM's pooled replicate scatter, and the smallest fraction of the shift (scaled linearly)
it detects with 80 % probability.

Example: the lab geometry's wall friction (``campaigns/geometry_lab.sqlite``, the Table 8 set
against the same set with mu_s_pg = mu_s_sg = 0.3, 3 seeds each) against Table 2's 50-50::

    python scripts/detectability_from_store.py --store campaigns/geometry_lab.sqlite \\
        --condition "50-50|mirror=True|slice_depth=0.1" --parameter mu_s_pg --null 0.9 --effect 0.3

Only the measured condition's cells enter (one condition of Table 2), so the power is a lower
bound for a discovery that measures every condition.
"""
from __future__ import annotations

import argparse
import json
import math
import sqlite3

import numpy as np

from bo.discovery.detectable import detection_power, smallest_detectable
from bo.screening.pipeline import measured_name
from torchdem.measured import load_measured

KPIS = ("angle_of_repose_deg", "shear_angle_deg", "mass_flow_rate_full_kg_s", "mass_lower_box_full_kg")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--store", required=True)
    parser.add_argument("--condition", required=True, help="the runs' condition, as stored")
    parser.add_argument("--parameter", required=True, help="the parameter whose value tells the two sets apart")
    parser.add_argument("--null", type=float, required=True, help="its value in the reference set")
    parser.add_argument("--effect", type=float, required=True, help="its value in the changed set")
    parser.add_argument("--measured", default="hadi2025_pellet_sinter.json")
    parser.add_argument("--dem-replicates", type=int, nargs="+", default=[3, 5])
    args = parser.parse_args()
    base = args.condition.split("|")[0]
    values: dict[float, list[list[float]]] = {args.null: [], args.effect: []}
    con = sqlite3.connect(args.store)
    for params, kpis in con.execute("SELECT params, kpis FROM evaluations WHERE status = 'done' AND condition = ?",
                                    (args.condition,)):
        value = json.loads(params).get(args.parameter)
        if value in values:
            k = json.loads(kpis)
            values[value].append([math.nan if k.get(name) is None else float(k[name]) for name in KPIS])
    null, effect = np.array(values[args.null]), np.array(values[args.effect])
    if len(null) < 2 or len(effect) < 2:
        raise SystemExit(f"{args.store}: condition {args.condition!r} holds {len(null)} runs at {args.parameter} = "
                         f"{args.null} and {len(effect)} at {args.effect}; need at least 2 of each")
    condition = load_measured(args.measured).condition(base)
    u = np.array([condition.standard_uncertainty(measured_name(k))[0] for k in KPIS])
    # per KPI over the runs that measured it (NaN: the lab method could not, e.g. no heap edge)
    n0, n1 = np.isfinite(null).sum(0), np.isfinite(effect).sum(0)
    shift = np.nanmean(effect, 0) - np.nanmean(null, 0)
    sd = np.sqrt((np.nanvar(null, 0, ddof=1) * (n0 - 1) + np.nanvar(effect, 0, ddof=1) * (n1 - 1)) / (n0 + n1 - 2))
    print(f"{args.parameter} {args.null} -> {args.effect} on {args.condition} ({len(null)} and {len(effect)} runs); "
          f"lab repeats: {condition.replicates or 'not stated (u = ci95 / 1.96)'}")
    for name, d, s, uu in zip(KPIS, shift, sd, u):
        print(f"  {name:26s} shift {d:+8.3f}   DEM replicate sd {s:6.3f}   lab u {uu:6.3f}")
    for r in args.dem_replicates:
        sigma = np.sqrt((sd / math.sqrt(r)) ** 2 + u ** 2)
        t = smallest_detectable(lambda f: f * shift, sigma)
        print(f"  {r} DEM runs per cell: power {detection_power(shift, sigma):.3f}; smallest detectable fraction of "
              f"the shift (80 %): {'not within 1' if t is None else f'{t:.2f}'}")


if __name__ == "__main__":
    main()
