"""Write a calibration campaign's result: ``report.md``, ``calibration.json`` and the figures.

Contract
--------
``write_calibration_report(result, out_dir)`` writes into ``out_dir`` (the screening stage has
already written its own files into ``out_dir/screening/``):

* ``calibration.json`` (strict JSON, NaN as null): ``calibrated_parameters`` (the GA optimum,
  plus ``density_<material>`` when the bulk density check rescaled them: the final model),
  ``held_parameters`` (the model's parameters the campaign did not vary, which every run had),
  ``objective`` (KPIs, measured values, weights), ``screening`` (kept KPIs, selected parameters,
  bounds), ``surrogate`` (CV R^2 per round and per strategy, stop reason, points run),
  ``ga`` (Tables 8 and 9 per mode), ``attainable`` (per objective KPI, its surrogate range with
  the other KPIs inside the lab's CI, ``bo.surrogate.attainable``), ``verification`` /
  ``density`` / ``validation`` (per KPI: DEM mean, std, n, measured mean and CI, relative error
  in percent), ``dem_evaluations`` (per stage and total) and ``wall_time_s`` (per stage, of the
  process that wrote the report);
* ``report.md``: the same as tables, with the figures linked;
* ``fig13_actual_vs_predicted.png``, ``fig14_verification.png``, ``fig16_density.png`` (when the
  density check ran), ``fig18_validation.png`` (when validation conditions exist).

With ``paper`` (``torchdem.measured.load_paper_tables()``, for a campaign on the paper's own
Table 2) both files also set the result beside the paper's: calibrated parameters (Table 8),
verification errors (Table A.4), densities (Table A.5), validation errors (Table A.6), the
largest validation error and the DEM runs (:func:`paper_comparison`).

Returns ``{name: path}`` of every file written.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from bo.surrogate.acquisition import plot_actual_vs_predicted, target_reached
from bo.surrogate.attainable import format_attainable
from bo.calibration.pipeline import ATTAINABLE_MAX_JAM, CalibrationResult, KPIAgreement, objective_blocks
from bo.report.plots import write_relative_error_plot
from bo.screening.pipeline import json_ready, measured_name
from torchdem.drawdown import JAM_FRACTION

__all__ = ["write_calibration_report", "calibration_payload", "agreement_table", "paper_comparison",
           "validation_summary"]


def agreement_table(rows: Sequence[KPIAgreement]) -> list[str]:
    """Markdown rows: KPI, measured mean +- CI, DEM mean +- std (n), relative error, in CI; below
    them how many runs jammed and were left out, if any."""
    lines = ["| KPI | measured (95 % CI) | DEM mean +- std (n) | relative error | within CI |",
             "| --- | --- | --- | ---: | :---: |"]
    for a in rows:
        lines.append(f"| {a.kpi} | {a.measured_mean:.4g} +- {a.measured_ci95:.3g} | {a.dem_mean:.4g} +- "
                     f"{a.dem_std:.2g} ({a.n}) | {a.relative_error_pct:+.2f} % | {'yes' if a.within_ci else 'no'} |")
    jammed = max((a.jammed for a in rows), default=0)
    if jammed:
        lines += ["", f"{jammed} of {jammed + max(a.n for a in rows)} runs jammed (the grains arched over the slot) "
                  "and are left out of these means."]
    return lines


def _ga_json(result: CalibrationResult) -> dict:
    names = list(result.surrogate.parameters)
    out = {"mode": result.ga.mode, "strategy": result.ga.strategy, "strategy_note": result.ga.strategy_note,
           "jam_note": result.ga.jam_note, "jam_probability": result.ga.jam_probability,
           "notes": dict(result.ga.notes), "calibrated": dict(result.ga.calibrated)}
    for mode, summary in result.ga.summaries.items():
        out[mode] = None if summary is None else {
            "best_repetition": summary.best_index + 1,
            "repetitions": [{"repetition": r.index + 1, **{n: float(v) for n, v in zip(names, r.x)},
                             "fitness": r.fitness, "generations": r.n_generations} for r in summary.repetitions]}
    return out


def calibration_payload(result: CalibrationResult) -> dict:
    """The content of ``calibration.json``."""
    s, sur, scr = result.settings, result.surrogate, result.screening
    dens = result.density
    return json_ready({
        "condition": s.condition,
        "calibrated_parameters": dict(result.final_parameters),
        "held_parameters": dict(result.held_parameters),
        "objective": {"kpis": list(result.objective.kpi_names), "measured": list(result.objective.measured),
                      "weights": list(result.objective.weights)},
        "screening": {"kept_kpis": list(scr.calibration_kpis),
                      "excluded_kpis": [k for k in scr.results.kpi_names if k not in scr.calibration_kpis],
                      "selected_parameters": list(scr.analysis.selected_parameters) if scr.analysis else [],
                      "proposal": scr.proposal.to_dict() if scr.proposal is not None else None},
        "surrogate": {"parameters": list(sur.parameters),
                      "bounds": {n: [float(sur.bounds[0, j]), float(sur.bounds[1, j])]
                                 for j, n in enumerate(sur.parameters)},
                      "choice": result.parameter_choice_note,
                      "strategy": s.surrogate.config.strategy,
                      "replicates_per_point": len(s.surrogate.seeds), "noise": s.surrogate.noise,
                      "points_run": sur.points_run, "dropped_points": sur.dropped_points,
                      "reused_screening_points": sur.reused_points - sur.reused_design_points,
                      "reused_design_points": sur.reused_design_points, "reuse_note": sur.reuse_note,
                      "stopped_because": sur.stopped_because, "target_r2": s.surrogate.adaptive.target_r2,
                      "target_basis": s.surrogate.adaptive.target_basis,
                      "rounds": [{"round": r.index, "n_points": r.n_points, "kernel": r.kernel,
                                  "r2_mean": r.r2_mean, "r2_std": r.r2_std, "r2_ceiling": r.r2_ceiling,
                                  "r2_ceiling_learned": r.r2_ceiling_learned, "r2_explained": r.r2_explained}
                                 for r in sur.rounds],
                      "strategy_r2": {k: list(v) for k, v in sur.strategy_r2.items()},
                      "strategy_comparison": strategy_comparison(result)},
        "ga": _ga_json(result),
        "attainable": [r.to_dict() for r in result.attainable],
        "verification": [a.to_dict() for a in result.verification],
        "fresh_verification": (None if result.fresh_verification is None
                               else [a.to_dict() for a in result.fresh_verification]),
        "density": {"skipped_because": dens.skipped_because, "heap_dem_m": list(dens.heap_dem_m),
                    "heap_measured_m": dens.heap_measured_m, "ratio": dens.ratio, "densities": dict(dens.densities),
                    "verification": [a.to_dict() for a in dens.agreement]},
        "validation": {c: [a.to_dict() for a in rows] for c, rows in result.validation.items()},
        **({"verification_fitted": {c: [a.to_dict() for a in rows] for c, rows in result.verification_fitted.items()}}
           if result.verification_fitted else {}),
        "dem_evaluations": dict(result.evaluations),
        "wall_time_s": dict(result.wall_time_s),
    })


def strategy_comparison(result: CalibrationResult) -> dict:
    """Per strategy: the CV R^2 after every round and the surrogate stage's DEM runs (its own
    points x replicates, an earlier design's reused points included; reused screening points cost
    none) it took to first reach the target
    (None if it never did), on the same sampled data."""
    sur, s = result.surrogate, result.settings.surrogate
    r = len(s.seeds)
    out = {}
    for strategy, values in sur.strategy_r2.items():
        reached = next((rec.n_points for rec, v in zip(sur.rounds, values)
                        if target_reached(v, rec.stop_ceiling, s.adaptive)), None)
        out[strategy] = {"r2_per_round": list(values), "points_to_target": reached,
                         "dem_runs_to_target": None if reached is None
                         else max(reached - (sur.reused_points - sur.reused_design_points), 0) * r}
    return out


#: The paper's DEM cost: 29 screening runs x 5, 110 surrogate points x 5, verification 5, the
#: density step 5, validation 3 conditions x 5 (section 3, Table 7): whole-box runs.
PAPER_DEM_RUNS = 29 * 5 + 110 * 5 + 5 + 5 + 3 * 5


def paper_comparison(result: CalibrationResult, paper: Mapping) -> dict:
    """This campaign beside the paper's (see the module docstring), as plain data."""
    dem = paper["dem_vs_experiment"]
    table8 = paper["ga_calibration"][paper["ga_calibration"]["selected"]]

    def errors(rows: Sequence[KPIAgreement]) -> dict[str, float | None]:
        # None: no run measured it (every run jammed or failed)
        return {measured_name(a.kpi): a.relative_error_pct if math.isfinite(a.relative_error_pct) else None
                for a in rows}

    ours_val = {c: errors(rows) for c, rows in result.validation.items()}
    paper_val = {c: v["relative_error_percent"] for c, v in dem["validation"]["conditions"].items()}
    worst = [abs(e) for c, row in ours_val.items() for k, e in row.items() if k in paper_val.get(c, {}) and e is not None]
    verification = result.fresh_verification if result.fresh_verification is not None else result.verification
    model = {**result.held_parameters, **result.final_parameters}  # the whole set; held ones are not calibrated
    return {
        "parameters": {n: {"ours": model.get(n), "table8": table8.get(n), "held": n in result.held_parameters}
                       for n in dict.fromkeys(list(result.final_parameters) + list(table8)
                                              + list(result.held_parameters))},
        "verification": {"ours": errors(verification), "within_ci": {measured_name(a.kpi): a.within_ci
                                                                      for a in verification},
                         "table_a4": dem["calibration"]["relative_error_percent"]},
        "densities": {"ours": {k[len("density_"):]: v for k, v in model.items() if k.startswith("density_")}
                      or dict(result.density.densities),
                      "table_a5": paper["bulk_density_recalibration"]["particle_density_kg_m3"]},
        "validation": {"ours": ours_val, "table_a6": paper_val},
        "unmeasured_validation": [f"{c} {k}" for c, row in ours_val.items() for k, e in row.items() if e is None],
        "largest_validation_error_pct": {"ours": max(worst) if worst else None,
                                         "table_a6": max(abs(e) for row in paper_val.values() for e in row.values())},
        "dem_runs": {"ours": result.evaluations.get("total"), "paper": PAPER_DEM_RUNS},
    }


def validation_summary(result: CalibrationResult, paper: Mapping | None = None) -> list[str]:
    """The validation in a few console lines: per validated condition, the largest |relative error|
    over the objective's KPIs (the four of Table A.6 for the paper's campaign) and how many of them lie
    inside the lab's 95 % CI; then the largest over every condition, beside the paper's own where
    ``paper`` (:func:`paper_comparison`) is given. [] when nothing was validated."""
    kpis = objective_blocks(result.objective, result.settings.condition)[0][1]
    lines, worst = [], None
    for condition, rows in result.validation.items():
        rows = [a for a in rows if a.kpi in kpis]
        measured = [a for a in rows if math.isfinite(a.relative_error_pct)]
        if not measured:
            lines.append(f"  validation {condition:14s} no run measured the objective's KPIs "
                         "(every run jammed or failed)")
            continue
        a = max(measured, key=lambda a: abs(a.relative_error_pct))
        lines.append(f"  validation {condition:14s} largest |error| {abs(a.relative_error_pct):.2f} % ({a.kpi}); "
                     f"{sum(r.within_ci for r in rows)} of {len(rows)} objective KPIs inside the lab's 95 % CI")
        if worst is None or abs(a.relative_error_pct) > worst[0]:
            worst = (abs(a.relative_error_pct), condition, a.kpi)
    if worst is not None:
        theirs = "" if paper is None else \
            f"; the paper's (Table A.6) {paper_comparison(result, paper)['largest_validation_error_pct']['table_a6']:.2f} %"
        lines.append(f"largest validation |error| {worst[0]:.2f} % ({worst[1]}, {worst[2]}){theirs}")
    return lines


def _paper_markdown(c: Mapping) -> list[str]:
    f = lambda v, fmt=".3g": "-" if v is None else format(v, fmt)  # noqa: E731
    lines = ["## Beside the paper (Hadi et al.)", "", "| parameter | this campaign | Table 8 |", "| --- | ---: | ---: |"]
    lines += [f"| {n} | {f(v['ours'])}{' (held)' if v['held'] else ''} | {f(v['table8'])} |"
              for n, v in c["parameters"].items()]
    ver = c["verification"]
    lines += ["", "| verification, 50-50 | this campaign | within the lab's CI | Table A.4 |", "| --- | ---: | :---: | ---: |"]
    lines += [f"| {k} | {f(ver['ours'].get(k), '+.2f')} % | {'yes' if ver['within_ci'].get(k) else 'no'} | "
              f"{f(v, '+.2f')} % |" for k, v in ver["table_a4"].items()]
    dens = c["densities"]
    lines += ["", "Particle densities (kg/m^3): this campaign " + (", ".join(f"{m} {v:.0f}" for m, v in dens["ours"].items())
                                                                   or "nominal") +
              "; Table A.5 " + ", ".join(f"{m} {v:.0f}" for m, v in dens["table_a5"].items()) + ".", ""]
    val = c["validation"]
    lines += ["| validation | KPI | this campaign | Table A.6 |", "| --- | --- | ---: | ---: |"]
    for cond, row in val["table_a6"].items():
        lines += [f"| {cond} | {k} | {f(val['ours'].get(cond, {}).get(k), '+.2f')} % | {f(v, '+.2f')} % |"
                  for k, v in row.items()]
    worst, runs = c["largest_validation_error_pct"], c["dem_runs"]
    missing = c.get("unmeasured_validation") or []
    lines += ["", f"Largest validation |error|: this campaign {f(worst['ours'], '.2f')} %, the paper {worst['table_a6']:.2f} %"
              + (f" (left out, measured by no run: every run jammed or failed: {', '.join(missing)})" if missing else "")
              + f". DEM runs: this campaign {runs['ours']}, the paper about {runs['paper']} (whole box).", ""]
    return lines


def write_calibration_report(result: CalibrationResult, out_dir: str | Path,
                             paper: Mapping | None = None) -> dict[str, Path]:
    """Write the report files (see the module docstring)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {}
    sur, dens = result.surrogate, result.density
    files["fig13"] = plot_actual_vs_predicted(sur.rounds, out / "fig13_actual_vs_predicted.png")
    if result.verification:
        files["fig14"] = write_relative_error_plot({result.settings.condition: result.verification},
                                                   out / "fig14_verification.png",
                                                   "Verification of the calibrated set (Fig. 14)")
    if dens.agreement:
        files["fig16"] = write_relative_error_plot({result.settings.condition: dens.agreement},
                                                   out / "fig16_density.png",
                                                   "With recalibrated particle densities (Fig. 16)")
    if any(result.validation.values()):
        files["fig18"] = write_relative_error_plot({c: rows for c, rows in result.validation.items() if rows},
                                                   out / "fig18_validation.png", "Validation (Fig. 18)")
    payload = calibration_payload(result)
    if paper is not None:
        payload["paper_comparison"] = json_ready(paper_comparison(result, paper))
    files["json"] = out / "calibration.json"
    files["json"].write_text(json.dumps(payload, indent=2, allow_nan=False) + "\n")
    files["md"] = out / "report.md"
    files["md"].write_text(_markdown(result, payload, files))
    return files


def _markdown(result: CalibrationResult, payload: Mapping, files: Mapping[str, Path]) -> str:
    s, sur, ga, dens = result.settings, result.surrogate, result.ga, result.density
    obj = result.objective
    lines = [f"# DEM calibration, condition {s.condition}", ""]
    lines += ["## Calibrated parameters", "", "| parameter | value |", "| --- | ---: |"]
    lines += [f"| {k} | {v:.4g} |" for k, v in result.final_parameters.items()]
    if result.held_parameters:
        lines += ["", "Held (every run has them; the campaign does not vary them): "
                  + ", ".join(f"{k} {v:.6g}" for k, v in result.held_parameters.items()) + "."]
    lines += ["", f"Objective (Eq. 7): KPIs {list(obj.kpi_names)}, measured {list(obj.measured)}, "
              f"weights {[round(w, 4) for w in obj.weights]}.", ""]
    lines += ["## 1. Screening", "", f"See [screening/screening.md](screening/screening.md). Kept KPIs: "
              f"{list(result.screening.calibration_kpis)}. {result.parameter_choice_note}.", ""]
    lines += ["## 2. Surrogate (Table 7, Fig. 13)", "",
              f"{len(sur.parameters)} parameters, {len(s.surrogate.seeds)} replicates per point"
              + (f" (noise of single runs: {s.surrogate.noise})" if len(s.surrogate.seeds) == 1 else "") + ", strategy "
              f"`{s.surrogate.config.strategy}`; {sur.points_run} points run ({sur.dropped_points} without usable "
              f"KPIs); stopped because: {sur.stopped_because}."
              + (f" Reused: {sur.reuse_note}." if sur.reuse_note else ""), "",
              "| parameter | low | high |", "| --- | ---: | ---: |"]
    lines += [f"| {n} | {sur.bounds[0, j]:.4g} | {sur.bounds[1, j]:.4g} |" for j, n in enumerate(sur.parameters)]
    strategies = list(sur.strategy_r2)
    # the noise ceiling: the CV R^2 that the DEM noise of the held-out points leaves attainable
    with_ceiling = any(math.isfinite(rec.r2_ceiling) for rec in sur.rounds)
    extra_head = " | noise ceiling | with learned noise | explained share" if with_ceiling else ""
    lines += ["", "| round | points | kernel | " + " | ".join(f"CV R^2 {t}" for t in strategies) + extra_head + " |",
              "| --- | ---: | --- | " + " | ".join("---:" for _ in strategies) + (" | ---: | ---: | ---:" if with_ceiling else "")
              + " |"]
    fmt = lambda v: f"{v:.3f}" if math.isfinite(v) else "-"  # noqa: E731
    for i, rec in enumerate(sur.rounds):
        cells = [f"{sur.strategy_r2[t][i]:.3f}" + (f" +- {rec.r2_std:.3f}" if t == s.surrogate.config.strategy else "")
                 for t in strategies]
        if with_ceiling:
            cells += [fmt(rec.r2_ceiling), fmt(rec.r2_ceiling_learned), fmt(rec.r2_explained)]
        lines.append(f"| {rec.index} | {rec.n_points} | {rec.kernel} | " + " | ".join(cells) + " |")
    comp = payload["surrogate"]["strategy_comparison"]
    basis = s.surrogate.adaptive.target_basis
    lines += [""] + [f"- `{t}`: reached R^2 >= {s.surrogate.adaptive.target_r2}"
                     + (" of the explainable variance " if basis == "explainable" else " ")
                     + (f"after {c['points_to_target']} points ({c['dem_runs_to_target']} DEM runs)"
                        if c["points_to_target"] is not None else "in no round") for t, c in comp.items()]
    if len(strategies) > 1:
        lines.append("  (every variant cross-validated on the points the run's strategy sampled)")
    lines += ["", f"![Fig. 13]({files['fig13'].name})", "", "## 3. Genetic algorithm (Tables 8, 9)", ""]
    if ga.strategy_note:
        lines += [ga.strategy_note + ".", ""]
    if ga.jam_note:
        lines += [ga.jam_note + f"; at the calibrated set p = {ga.jam_probability:.3f}.", ""]
    for mode, summary in ga.summaries.items():
        if summary is None:
            lines.append(f"- {mode}: not run ({ga.notes.get(mode, '')})")
            continue
        lines += [f"### {mode}" + (" (calibrated set)" if mode == ga.mode else ""), "",
                  "| repetition | " + " | ".join(sur.parameters) + " | fitness |",
                  "| ---: | " + " | ".join("---:" for _ in sur.parameters) + " | ---: |"]
        for r in summary.repetitions:
            mark = " **best**" if r.index == summary.best_index else ""
            lines.append(f"| {r.index + 1}{mark} | " + " | ".join(f"{v:.3f}" for v in r.x) + f" | {r.fitness:.4f} |")
        lines.append("")
    if "choice" in ga.notes:
        lines += [ga.notes["choice"], ""]
    if result.attainable:
        lines += ["### What the bounds allow", "",
                  "Per objective KPI, the range of its per-KPI surrogate mean over the box the GA searched while every "
                  "other objective KPI's mean stays inside the lab's 95 % CI (`bo.surrogate.attainable`)"
                  + (f" and the chance that a run jams, by the GA's classifier, stays at most {ATTAINABLE_MAX_JAM:.0%}"
                     if ga.jam_note else "") + ". Where a "
                  "range does not meet the lab's interval, no parameter set in the bounds matches all the KPIs by "
                  "the surrogate, and what is left is the model's (`torchdem-discover`).", ""]
        lines += format_attainable(result.attainable) + [""]
    lines += ["## 4. Verification (Fig. 14, Table A.4)", ""] + agreement_table(result.verification)
    if result.fresh_verification is not None:
        lines += ["", f"The same {len(s.verification_seeds)} runs made again on the machine that wrote this report "
                  "(none taken from the store):", ""] + agreement_table(result.fresh_verification)
    for c, rows in result.verification_fitted.items():
        lines += ["", f"On {c}, whose KPIs the objective fits too (`objective.conditions`; no blind check):", ""] \
            + agreement_table(rows)
    if "fig14" in files:
        lines += ["", f"![Fig. 14]({files['fig14'].name})"]
    lines += ["", "## 5. Bulk density (Figs. 15-16, Table A.5)", ""]
    if dens.skipped_because is not None:
        lines.append(f"Skipped: {dens.skipped_because}.")
    else:
        lines += [f"Heap height: DEM {np.mean(dens.heap_dem_m):.4g} m (mean of {len(dens.heap_dem_m)}), measured "
                  f"{dens.heap_measured_m:.4g} m; ratio H_DEM/H_Exp = {dens.ratio:.4f}. Densities: "
                  + ", ".join(f"{m} {v:.1f} kg/m^3" for m, v in dens.densities.items()), ""]
        lines += agreement_table(dens.agreement) + ["", f"![Fig. 16]({files['fig16'].name})"]
    lines += ["", "## 6. Validation (Fig. 18, Table A.6)", ""]
    if not result.validation:
        lines.append("No other measured condition to validate on.")
    for c, rows in result.validation.items():
        lines += [f"### {c}", ""] + agreement_table(rows) + [""]
    if "fig18" in files:
        lines += [f"![Fig. 18]({files['fig18'].name})", ""]
    if "paper_comparison" in payload:
        lines += _paper_markdown(payload["paper_comparison"])
    ev, wall = result.evaluations, result.wall_time_s
    lines += ["## Cost", "", "| stage | DEM evaluations |", "| --- | ---: |"]
    lines += [f"| {k} | {v} |" for k, v in ev.items()]
    if result.discharge_not_ended:
        lines += ["", "Runs stopped while the upper box still emptied (their lower-box mass and photos are not the "
                  "end state the lab measures; `run.max_discharge_time_s`): "
                  + ", ".join(f"{k} {v}" for k, v in result.discharge_not_ended.items()) + "."]
    if result.discharge_jammed:
        lines += ["", f"Runs whose discharge jammed (less than {100 * JAM_FRACTION:g} % of the fill left the upper box; their shear angle "
                  "reads 0 deg, the fill's level surface, so the objective counts the miss): "
                  + ", ".join(f"{k} {v}" for k, v in result.discharge_jammed.items()) + "."]
    lines += ["", "| stage | wall time (this process) |", "| --- | ---: |"]
    lines += [f"| {k} | {v:.1f} s |" for k, v in wall.items()]
    lines.append(f"| total | {math.fsum(wall.values()):.1f} s |")
    return "\n".join(lines) + "\n"
