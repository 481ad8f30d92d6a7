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

Several ``--condition`` values (the same measured condition on several geometries of a geometry
study) print each one's power and then compare their shifts with the first's, KPI by KPI: the
ratio (where the first geometry's shift exceeds twice its standard error) and the difference in
standard errors. This tells whether a cheaper geometry (the walled
slice) shows the shift the reference geometry shows, i.e. whether it can stand in for it::

    python scripts/detectability_from_store.py --store campaigns/table2/lab_effects.sqlite \\
        --condition "50-50|mirror=True|slice_depth=0.1" "50-50|mirror=False|slice_depth=0.04" \\
        --parameter coh_pp --null 0 --effect 13333

``--versus PARAMETER NULL EFFECT [STORE]`` sets another mechanism's shift on the first condition
beside this one and prints the power of telling the two apart (``distinguishing_power``): the
probability that these cells reject the other mechanism at its best-fitting magnitude. Low power
means no discovery can name the right one of the two from these data. Cohesion against a change
of wall friction, on the lab geometry::

    python scripts/detectability_from_store.py --store campaigns/table2/lab_effects.sqlite \\
        --condition "50-50|mirror=True|slice_depth=0.1" --parameter coh_pp --null 0 --effect 13333 \\
        --versus mu_s_pg 0.9 0.3 campaigns/geometry_lab.sqlite

The null set of a mechanism is the set at its null value that differs from its effect set in the
fewest parameters (a store of several mechanisms holds several sets at each null value).
"""
from __future__ import annotations

import argparse
import json
import math
import sqlite3

import numpy as np

from bo.discovery.detectable import detection_power, distinguishing_power, smallest_detectable
from bo.screening.pipeline import measured_name
from torchdem.drawdown import CALIBRATION_KPIS_DEM
from torchdem.measured import load_measured
from torchdem.errors import exit_on_bad_input

KPIS = CALIBRATION_KPIS_DEM


def runs(store: str, condition: str, parameter: str, null: float, effect: float) -> tuple[np.ndarray, np.ndarray]:
    """KPIs (rows: runs, columns: ``KPIS``; NaN where a run did not measure one) of the finished
    runs of ``condition`` in the parameter set with ``parameter = effect`` and in the set with
    ``parameter = null`` that differs from it in the fewest parameters (a store of several
    mechanisms holds several sets at the null value: the Table 8 set, and each other mechanism's)."""
    sets: dict[str, list[list[float]]] = {}
    con = sqlite3.connect(store)
    for params, kpis in con.execute("SELECT params, kpis FROM evaluations WHERE status = 'done' AND condition = ?",
                                    (condition,)):
        k = json.loads(kpis)
        sets.setdefault(params, []).append([math.nan if k.get(name) is None else float(k[name]) for name in KPIS])
    con.close()
    parsed = {key: json.loads(key) for key in sets}
    effects = [key for key, p in parsed.items() if p.get(parameter) == effect]
    if len(effects) != 1:
        raise SystemExit(f"{store}: condition {condition!r} holds {len(effects)} parameter sets with {parameter} = "
                         f"{effect}; need exactly one")
    target = parsed[effects[0]]
    # (number of parameters that differ from the effect set, set) of every set at the null value
    nulls = sorted((sum(p.get(k) != target.get(k) for k in set(p) | set(target)), key)
                   for key, p in parsed.items() if p.get(parameter) == null)
    if not nulls or (len(nulls) > 1 and nulls[0][0] == nulls[1][0]):
        raise SystemExit(f"{store}: condition {condition!r} holds {len(nulls)} parameter sets with {parameter} = "
                         f"{null}; need one that differs from the effect set in fewer parameters than the others")
    a = np.array(sets[nulls[0][1]]).reshape(-1, len(KPIS))
    b = np.array(sets[effects[0]]).reshape(-1, len(KPIS))
    if len(a) < 2 or len(b) < 2:
        raise SystemExit(f"{store}: condition {condition!r} holds {len(a)} runs at {parameter} = {null} and "
                         f"{len(b)} at {effect}; need at least 2 of each")
    return a, b


def shift_and_scatter(null: np.ndarray, effect: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per KPI over the runs that measured it: the shift of the means, the pooled replicate sd and
    the standard error of the shift."""
    n0, n1 = np.isfinite(null).sum(0), np.isfinite(effect).sum(0)
    shift = np.nanmean(effect, 0) - np.nanmean(null, 0)
    sd = np.sqrt((np.nanvar(null, 0, ddof=1) * (n0 - 1) + np.nanvar(effect, 0, ddof=1) * (n1 - 1)) / (n0 + n1 - 2))
    return shift, sd, sd * np.sqrt(1.0 / n0 + 1.0 / n1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--store", required=True)
    parser.add_argument("--condition", required=True, nargs="+",
                        help="the runs' condition, as stored; several: compare their shifts with the first's")
    parser.add_argument("--parameter", required=True, help="the parameter whose value tells the two sets apart")
    parser.add_argument("--null", type=float, required=True, help="its value in the reference set")
    parser.add_argument("--effect", type=float, required=True, help="its value in the changed set")
    parser.add_argument("--measured", default="hadi2025_pellet_sinter.json")
    parser.add_argument("--dem-replicates", type=int, nargs="+", default=[3, 5])
    parser.add_argument("--versus", nargs="+", action="append", default=[], metavar="ARG",
                        help="PARAMETER NULL EFFECT [STORE]: another mechanism's shift (its store if not --store) "
                             "on the first condition; can the data tell the two apart? (repeatable)")
    args = parser.parse_args()
    versus = []
    for spec in args.versus:
        if len(spec) not in (3, 4):
            raise SystemExit(f"--versus {' '.join(spec)}: expected PARAMETER NULL EFFECT [STORE]")
        try:
            versus.append((spec[0], float(spec[1]), float(spec[2]), spec[3] if len(spec) == 4 else args.store))
        except ValueError:
            raise SystemExit(f"--versus {' '.join(spec)}: NULL and EFFECT must be numbers") from None
    measured = load_measured(args.measured)
    shifts, first = [], None
    for condition_name in args.condition:
        null, effect = runs(args.store, condition_name, args.parameter, args.null, args.effect)
        condition = measured.condition(condition_name.split("|")[0])
        u = np.array([condition.standard_uncertainty(measured_name(k))[0] for k in KPIS])
        shift, sd, se = shift_and_scatter(null, effect)
        shifts.append((condition_name, shift, se))
        first = first or (shift, sd, u)
        print(f"{args.parameter} {args.null} -> {args.effect} on {condition_name} ({len(null)} and {len(effect)} "
              f"runs); lab repeats: {condition.replicates or 'not stated (u = ci95 / 1.96)'}")
        for name, d, s, uu in zip(KPIS, shift, sd, u):
            print(f"  {name:26s} shift {d:+8.3f}   DEM replicate sd {s:6.3f}   lab u {uu:6.3f}")
        for r in args.dem_replicates:
            sigma = np.sqrt((sd / math.sqrt(r)) ** 2 + u ** 2)
            t = smallest_detectable(lambda f: f * shift, sigma)
            print(f"  {r} DEM runs per cell: power {detection_power(shift, sigma):.3f}; smallest detectable fraction "
                  f"of the shift (80 %): {'not within 1' if t is None else f'{t:.2f}'}")
    reference, ref_shift, ref_se = shifts[0]
    for condition_name, shift, se in shifts[1:]:
        print(f"shift on {condition_name} against {reference}:")
        for name, d, e, d0, e0 in zip(KPIS, shift, se, ref_shift, ref_se):
            # a ratio only where the reference shift stands out of its own noise
            ratio = f"{d / d0:+6.2f}" if abs(d0) > 2 * e0 else "     -"
            z = (d - d0) / math.hypot(e, e0)
            print(f"  {name:26s} {d:+8.3f} (se {e:.3f}) against {d0:+8.3f} (se {e0:.3f}): ratio {ratio}, "
                  f"difference {z:+5.1f} se")
    shift, sd, u = first
    for parameter, null_value, effect_value, store in versus:
        other, _, _ = shift_and_scatter(*runs(store, reference, parameter, null_value, effect_value))
        print(f"against {parameter} {null_value} -> {effect_value} ({store}) on {reference}: shift "
              + " ".join(f"{d:+.3f}" for d in other))
        for r in args.dem_replicates:
            sigma = np.sqrt((sd / math.sqrt(r)) ** 2 + u ** 2)
            a, b = shift / sigma, other / sigma
            cosine = float(a @ b / math.sqrt(float(a @ a) * float(b @ b)))
            print(f"  {r} DEM runs per cell: cosine of the two shifts in units of sigma {cosine:+.3f}; power to reject "
                  f"it at its best magnitude {distinguishing_power(shift, other, sigma):.3f}")


if __name__ == "__main__":
    exit_on_bad_input("detectability_from_store.py", main)
