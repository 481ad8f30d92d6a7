"""Which parameters move each KPI over every run a campaign made at one condition, and whether what is
left is noise (``bo.screening.response``): a linear fit on all finished runs that flowed, read only,
beside the lab's value and how many runs came within its CI.

    python scripts/kpi_response.py campaigns/table2/lab.sqlite --condition 50-50
    python scripts/kpi_response.py STORE --kpis segregation_rsd_horizontal --data my_lab.json
    python scripts/kpi_response.py campaigns/table2/discover_lab.sqlite --condition 75-25 --stage discovery-free_interaction

The effect is the KPI's change from the lowest to the highest value of the parameter that the runs
span (its standard error in brackets), largest |effect / se| first.
"""
from __future__ import annotations

import argparse
import math

import numpy as np

from bo.screening.pipeline import measured_name
from bo.screening.response import kpi_response, store_runs
from torchdem.drawdown import CALIBRATION_KPIS_DEM
from torchdem.errors import exit_on_bad_input
from torchdem.measured import load_measured

KPIS = (*CALIBRATION_KPIS_DEM, "segregation_rsd_horizontal", "segregation_rsd_vertical")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("stores", nargs="+", help="campaign stores (SQLite) of one model")
    parser.add_argument("--condition", default="50-50", help="the condition whose runs are fitted (default 50-50)")
    parser.add_argument("--stage", nargs="+", help="only these stages' runs (e.g. a discovery's discovery-free_interaction)")
    parser.add_argument("--kpis", nargs="+", default=list(KPIS), help="KPIs (default: the calibration's and segregation)")
    parser.add_argument("--data", default=None, help="measured-data JSON (default: the paper's Table 2)")
    parser.add_argument("--top", type=int, default=6, help="parameters shown per KPI (default 6)")
    args = parser.parse_args()
    runs = store_runs(args.stores, args.condition, args.stage)
    measured = load_measured(args.data).condition(args.condition).kpis
    source = f"{', '.join(args.stores)} at {args.condition}" + (f", stage {', '.join(args.stage)}" if args.stage else "")
    print(f"{len(runs)} runs that flowed at {args.condition} ({source})\n")
    print("| KPI | runs | range | residual sd | replicate sd (dof) | R^2 | lab (95 % CI) | runs in the lab's CI |")
    print("| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: |")
    fits = []
    for kpi in args.kpis:
        fit = kpi_response(runs, kpi, source)
        fits.append(fit)
        lab = measured.get(measured_name(kpi))
        inside = "" if lab is None else str(int(np.sum(np.abs(fit.values - lab.mean) <= lab.ci95)))
        lab_cell = "" if lab is None else f"{lab.mean:.4g} +- {lab.ci95:.2g}"
        replicate = "" if math.isnan(fit.replicate_sd) else f"{fit.replicate_sd:.3g} ({fit.replicate_dof})"
        print(f"| {kpi} | {len(fit.values)} | {fit.values.min():.3g} to {fit.values.max():.3g} | {fit.residual_sd:.3g} "
              f"| {replicate} | {fit.r2:.2f} | {lab_cell} | {inside} |")
    print("\nChange over each parameter's range run (se), largest |effect / se| first:\n")
    for fit in fits:
        order = np.argsort(-np.abs(fit.effect / fit.effect_se))[:args.top]
        print(f"- {fit.kpi}: " + ", ".join(
            f"{fit.parameters[i]} {fit.low[i]:.3g}-{fit.high[i]:.3g} {fit.effect[i]:+.3g} ({fit.effect_se[i]:.2g})"
            for i in order))


if __name__ == "__main__":
    exit_on_bad_input("kpi_response.py", main)
