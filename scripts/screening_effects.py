"""What each screened parameter does to the KPIs, read from a campaign store's screening: the main
effects with their standard errors (``bo.screening.effects``), how detectable each parameter's
change is against the lab's measurement of the screening's condition, which pairs of parameters
those cells can tell apart, and where the main-effects model puts the lab inside given bounds.

Nothing runs: the screening's finished runs are read (read-only, a campaign may be writing the
store meanwhile). Example, the lab campaign's screening against Table 2's 50-50::

    python scripts/screening_effects.py campaigns/table2/lab.sqlite
    python scripts/screening_effects.py campaigns/table2/lab.sqlite --lab-fit mu_r_pp=0.045:0.24 mu_r_pg=0.045:0.24

Detection: discovery's discrepancy test (``bo.discovery.detectable``) on the condition's cells,
each with the lab's standard uncertainty and the DEM scatter of ``--dem-replicates`` runs (the
screening's pooled replicate sd), against the shift of a parameter over its whole screened range
(one condition only, so a lower bound for a discovery that measures every condition). "Tell
apart": the probability that the cells reject the other parameter at its best-fitting change
(``distinguishing_power``); low means these data cannot say which of the two moved.

``--lab-fit NAME=LOW:HIGH ...`` minimises Eq. 7 (equal weights, absolute relative errors) of the
main-effects model over the screened ranges, with the given parameters' bounds replaced: outside
the screened range the slopes are extrapolated, which the screening cannot check, so this says
where to look, and a DEM run there says whether it holds
(``scripts/run_parameter_set.py``). ``--objective ci`` minimises instead the largest distance of a
KPI from the lab's mean in units of its 95 % CI half-width, the verification's test (below 1: all four
inside the lab's CI).
"""
from __future__ import annotations

import argparse
import math

import numpy as np
from scipy import optimize

from bo.discovery.detectable import detection_power, distinguishing_power, smallest_detectable
from bo.screening.effects import main_effects
from bo.screening.pipeline import measured_name, stored_screening
from torchdem.drawdown import CALIBRATION_KPIS_DEM
from torchdem.errors import ConfigError, exit_on_bad_input
from torchdem.measured import load_measured

KPIS = CALIBRATION_KPIS_DEM
SHORT = ("AoR", "shear", "flow", "lower box")


def parse_bounds(items: list[str]) -> dict[str, tuple[float, float]]:
    """``NAME=LOW:HIGH`` items as bounds."""
    out = {}
    for item in items:
        name, _, span = item.partition("=")
        low, _, high = span.partition(":")
        try:
            out[name] = (float(low), float(high))
        except ValueError:
            raise ConfigError(f"--lab-fit {item!r}: expected NAME=LOW:HIGH, e.g. mu_r_pg=0.045:0.24") from None
        if not out[name][0] < out[name][1]:
            raise ConfigError(f"--lab-fit {item!r}: LOW must be below HIGH")
    return out


def at_bound(value: float, bound: tuple[float, float]) -> bool:
    """Within a thousandth of the range of either end."""
    tolerance = 1e-3 * (bound[1] - bound[0])
    return min(abs(value - bound[0]), abs(value - bound[1])) <= tolerance


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("store")
    parser.add_argument("--stage", default="screening")
    parser.add_argument("--condition", help="the screening's condition (default: the one it ran)")
    parser.add_argument("--measured", default="hadi2025_pellet_sinter.json")
    parser.add_argument("--dem-replicates", type=int, default=3, help="DEM runs per cell of a discovery")
    parser.add_argument("--lab-fit", nargs="*", metavar="NAME=LOW:HIGH",
                        help="minimise Eq. 7 of the main-effects model; these bounds replace the screened ones")
    parser.add_argument("--objective", choices=("eq7", "ci"), default="eq7",
                        help="with --lab-fit: Eq. 7, or the largest |model - lab| / CI half-width")
    args = parser.parse_args()
    results = stored_screening(args.store, KPIS, stage=args.stage, condition=args.condition)
    fit = main_effects(results)
    condition_name = results.source.rsplit("condition ", 1)[-1]
    condition = load_measured(args.measured).condition(condition_name.split("|")[0])
    lab = np.array([condition.kpis[measured_name(k)].mean for k in KPIS])
    u = np.array([condition.standard_uncertainty(measured_name(k))[0] for k in KPIS])
    ci = np.array([condition.kpis[measured_name(k)].ci95 for k in KPIS])
    sigma = np.sqrt(fit.replicate_sd ** 2 / args.dem_replicates + u ** 2)

    print(f"{results.source}: {int(np.isfinite(results.kpi_values[..., 0]).sum())} runs, "
          f"{results.n_replicates} replicates of {results.n_runs} points")
    print("\n| KPI | lab | design centre | replicate sd (dof) | residual sd (dof) | lack of fit p |\n"
          "| --- | ---: | ---: | ---: | ---: | ---: |")
    for m, name in enumerate(SHORT):
        print(f"| {name} | {lab[m]:.2f} | {fit.intercept[m]:.2f} | {fit.replicate_sd[m]:.3f} ({fit.replicate_dof[m]}) "
              f"| {fit.residual_sd[m]:.3f} ({fit.residual_dof[m]}) | {fit.lack_of_fit_p[m]:.2g} |")

    print(f"\nChange from the low to the high level (standard error); detection at {condition_name} alone with "
          f"{args.dem_replicates} DEM runs per cell:\n")
    print("| parameter | range | " + " | ".join(SHORT) + " | power | smallest detectable fraction |")
    print("| --- | --- |" + " ---: |" * (len(SHORT) + 2))
    power = {}
    scatter_known = bool(np.all(np.isfinite(sigma)) and np.all(sigma > 0))  # no replicate yet: no DEM scatter
    for k, name in enumerate(fit.parameter_names):
        shift = fit.effect[k]
        cells = " | ".join(f"{d:+.2f} ({s:.2f})" for d, s in zip(shift, fit.effect_se[k]))
        if not scatter_known:
            power[name] = math.nan
            print(f"| {name} | {fit.low[k]:.4g}-{fit.high[k]:.4g} | {cells} | - | - |")
            continue
        power[name] = detection_power(shift, sigma)
        t = smallest_detectable(lambda f: f * shift, sigma)
        print(f"| {name} | {fit.low[k]:.4g}-{fit.high[k]:.4g} | {cells} | {power[name]:.3f} | "
              f"{'not within 1' if t is None else f'{t:.2f}'} |")
    if not scatter_known:
        print("\nPower: - until a design point has two finished replicates (the DEM scatter comes from them).")

    seen = [n for n in fit.parameter_names if power[n] >= 0.8]
    if len(seen) >= 2:
        print("\nTell apart (row: the true change over its whole range; column: the other parameter at its "
              "best-fitting change; power to reject it), the parameters detected with power >= 0.8:\n")
        print("| true \\ other | " + " | ".join(seen) + " |\n| --- |" + " ---: |" * len(seen))
        for a in seen:
            row = [("-" if a == b else f"{distinguishing_power(fit.effect[fit.index(a)], fit.effect[fit.index(b)], sigma):.2f}")
                   for b in seen]
            print(f"| {a} | " + " | ".join(row) + " |")

    if args.lab_fit is not None:
        bounds = {n: (float(lo), float(hi)) for n, lo, hi in zip(fit.parameter_names, fit.low, fit.high)}
        given = parse_bounds(args.lab_fit)
        unknown = sorted(set(given) - set(bounds))
        if unknown:
            raise ConfigError(f"--lab-fit: {unknown} were not screened; screened: {list(fit.parameter_names)}")
        bounds.update(given)
        names = list(fit.parameter_names)
        box = [bounds[n] for n in names]

        def objective(x):  # Eq. 7, or the largest miss in CI half-widths
            miss = np.abs(fit.predict(dict(zip(names, x))) - lab)
            return float(np.max(miss / ci) if args.objective == "ci" else np.mean(miss / np.abs(lab)))

        rng = np.random.default_rng(0)
        best = min((optimize.minimize(objective, [rng.uniform(lo, hi) for lo, hi in box], bounds=box, method="Powell")
                    for _ in range(20)), key=lambda r: r.fun)
        at = dict(zip(names, best.x))
        what = "Eq. 7" if args.objective == "eq7" else "The largest |model - lab| / CI half-width"
        print(f"\n{what} of the main-effects model, minimised within the screened ranges"
              f"{' and ' + ', '.join(args.lab_fit) if given else ''}: {best.fun:.4f}")
        print("| KPI | model | lab |\n| --- | ---: | ---: |")
        for name, p, y in zip(SHORT, fit.predict(at), lab):
            print(f"| {name} | {p:.2f} | {y:.2f} |")
        outside = [n for n in names if not fit.low[fit.index(n)] - 1e-12 <= at[n] <= fit.high[fit.index(n)] + 1e-12]
        print("at " + " ".join(f"{n}={v:.4g}" for n, v in at.items()))
        print("extrapolated beyond the screened range: " + (", ".join(outside) if outside else "none")
              + "; at a bound: " + (", ".join(n for n in names if at_bound(at[n], bounds[n])) or "none"))


if __name__ == "__main__":
    exit_on_bad_input("screening_effects.py", main)
