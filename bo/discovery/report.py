"""Write a model-discovery result: ``discovery.json``, ``discovery.md`` and the figures.

Contract
--------
``write_discovery_report(result, out_dir, extension_command=None, attainable=(), residue=None, gap=None)``
writes into ``out_dir`` (``attainable``: the calibration's "what the bounds allow",
``bo.surrogate.attainable``, from its calibration.json, reported beside the discrepancy and as
``calibration_attainable``; ``residue``: the upper box's residue per unit slope of the lab and of
the runs, ``bo.discovery.residue``, reported in a last section and as ``residue``; ``gap``: how far
the face stands above the heap, the lab's against the runs, ``bo.discovery.gap``, after it and as
``gap``):

* ``discovery.json`` (strict JSON, NaN as null): ``cause`` (a registry name or null),
  ``explanation``, ``discrepancy`` (chi^2, degrees of freedom, p-value, significant,
  ``dem_noise``: the pooled DEM replicate standard deviation per KPI and its degrees of
  freedom, and every cell: condition, KPI, DEM mean and standard error, measured mean and
  standard uncertainty, z, relative error), ``candidates`` (every hypothesis: name,
  description, parameters, bounds, parameters added, held-out chi^2 per condition of the DEM
  runs and as the surrogate predicted it, score, ``gain_noise_sd`` (the sd of its gain over
  ``parameters`` from DEM noise alone), in-sample chi^2, ``fit_check`` (the fit on every
  condition: the GP mean's misfit and the GP's own uncertainty as chi^2, the cells, resolved or
  not: ``bo.discovery.verdict.fit_check``), fitted values, the cells of its held-out
  runs, or why it was skipped), ``unresolved`` (the candidates whose fit is unresolved),
  ``errors`` (per held-out condition and KPI: measured, before and after with standard errors,
  relative errors and z), ``extension`` (the chosen mechanism's values fitted on every
  condition) and ``dem_evaluations`` (per stage and total);
* ``discovery.md``: the same as tables, with the command that uses the extension (when no
  cause is named, the best candidate's held-out errors next to the calibrated model's);
* ``discrepancy.png``: z per KPI and condition (|z| > 2 marked), and, when a cause was named,
  ``gain.png``: relative error per KPI and held-out condition before and after.

Returns ``{name: path}``.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from bo.discovery.pipeline import DiscoveryResult, jam_counts, jammed_runs_note
from bo.discovery.verdict import gain_rows
from bo.report.plots import save_png
from bo.screening.pipeline import json_ready
from bo.discovery.gap import GapCheck, format_gap
from bo.discovery.residue import ResidueCheck, format_residue
from bo.surrogate.attainable import AttainableRange, format_attainable

__all__ = ["write_discovery_report", "discovery_payload"]


def discovery_payload(result: DiscoveryResult) -> dict:
    d = result.discrepancy
    return json_ready({
        "cause": result.cause,
        "explanation": result.explanation,
        "tied": list(result.tied),
        "unresolved": list(result.unresolved),
        "discrepancy": {"chi2": d.chi2, "chi2_equivalent": d.chi2_equivalent, "dof": d.dof, "p_value": d.p_value,
                        "significant": d.significant, "jammed_runs": dict(d.jammed),
                        "dem_noise": d.noise.to_dict(), "cells": [c.to_dict() for c in d.cells]},
        "candidates": [{"name": h.name, "description": h.description, "parameters": list(h.parameters),
                        "bounds": {k: list(v) for k, v in h.bounds.items()}, "added_parameters": h.added,
                        "held_out_chi2": dict(h.held_out_chi2), "predicted_held_out_chi2": dict(h.predicted_chi2),
                        "score": h.score, "gain_noise_sd": h.gain_noise_sd, "in_sample_chi2": h.in_sample_chi2,
                        "fit_check": {"misfit_chi2": h.fit_misfit_chi2, "surrogate_chi2": h.fit_surrogate_chi2,
                                      "cells": h.fit_cells, "resolved": h.name not in result.unresolved,
                                      "astray": {c: {"dem_chi2": v[0], "predicted_chi2": v[1]}
                                                 for c, v in h.astray.items()}},
                        "fitted_all": dict(h.fitted_all), "fitted_without": {c: dict(v) for c, v in
                                                                             h.fitted_without.items()},
                        "design_points": h.points, "skipped": h.skipped, "pruned": h.pruned,
                        "win_probability": h.win_probability,
                        "held_out_failures": dict(h.held_out_failures),
                        "jammed_runs": {"design": dict(h.jammed_design), "held_out": dict(h.jammed_held_out)},
                        "held_out_cells": [c.to_dict() for c in h.held_out_cells],
                        "detectable": dict(h.detectable), "separable": dict(h.separable)}
                       for h in result.hypotheses],
        "errors": [g.to_dict() for g in result.gain],
        "extension": {"name": result.cause, "values": dict(result.extension)},
        "dem_evaluations": dict(result.evaluations),
    })


def _discrepancy_figure(result: DiscoveryResult) -> Figure:
    cells = [c for c in result.discrepancy.cells if math.isfinite(c.z)]
    conditions = list(dict.fromkeys(c.condition for c in cells))
    kpis = list(dict.fromkeys(c.kpi for c in cells))
    z = np.full((len(kpis), len(conditions)), np.nan)
    for c in cells:
        z[kpis.index(c.kpi), conditions.index(c.condition)] = c.z
    fig = Figure(figsize=(1.6 + 1.3 * len(conditions), 1.2 + 0.45 * len(kpis)), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    lim = max(3.0, float(np.nanmax(np.abs(z))) if np.isfinite(z).any() else 3.0)
    im = ax.imshow(z, cmap="RdBu_r", vmin=-lim, vmax=lim, aspect="auto")
    for (i, j), v in np.ndenumerate(z):
        if np.isfinite(v):
            ax.text(j, i, f"{v:+.1f}" + ("*" if abs(v) > 2 else ""), ha="center", va="center", fontsize=7)
    ax.set_xticks(range(len(conditions)), conditions, fontsize=7)
    ax.set_yticks(range(len(kpis)), [k.replace("_", " ") for k in kpis], fontsize=7)
    d = result.discrepancy
    ax.set_title(f"z = (DEM - lab) / u; chi2 {d.chi2:.1f} on {d.dof}, p = {d.p_value:.2g} (* |z| > 2)", fontsize=8)
    fig.colorbar(im, ax=ax, shrink=0.8)
    return fig


def _gain_figure(result: DiscoveryResult) -> Figure:
    rows = list(result.gain)
    labels = [f"{g.condition}\n{g.kpi.replace('_', ' ')}" for g in rows]
    fig = Figure(figsize=(min(11.0, 1.5 + 0.9 * len(rows)), 3.4), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(rows))
    err = lambda se, m: 0.0 if not math.isfinite(se) else se / abs(m) * 100  # noqa: E731
    ax.bar(x - 0.2, [g.before_error_pct for g in rows], 0.4, yerr=[err(g.before_se, g.measured_mean) for g in rows],
           label="calibrated model", capsize=2)
    ax.bar(x + 0.2, [g.after_error_pct for g in rows], 0.4, yerr=[err(g.after_se, g.measured_mean) for g in rows],
           label=f"with {result.cause} (fitted without the condition)", capsize=2)
    ax.axhline(0, color="k", lw=0.8)
    ax.set_xticks(x, labels, fontsize=6, rotation=30)
    ax.set_ylabel("relative error (%)")
    ax.legend(fontsize=7)
    ax.set_title("Held-out conditions: error before and after the extension", fontsize=9)
    return fig


def _gain_line(g) -> str:
    return (f"| {g.condition} | {g.kpi} | {g.measured_mean:.4g} +- {g.measured_u:.2g} | {g.before_mean:.4g} +- "
            f"{g.before_se:.2g} | {g.after_mean:.4g} +- {g.after_se:.2g} | {g.before_error_pct:+.1f} % | "
            f"{g.after_error_pct:+.1f} % |")


def write_discovery_report(result: DiscoveryResult, out_dir, extension_command: str | None = None,
                           attainable: Sequence[AttainableRange] = (),
                           residue: ResidueCheck | None = None, gap: GapCheck | None = None) -> dict[str, Path]:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = {"discrepancy_png": save_png(_discrepancy_figure(result), out / "discrepancy.png")}
    if result.gain:
        files["gain_png"] = save_png(_gain_figure(result), out / "gain.png")
    payload = discovery_payload(result)
    if extension_command:
        payload["extension"]["command"] = extension_command
    if attainable:
        payload["calibration_attainable"] = [r.to_dict() for r in attainable]
    if residue is not None:
        payload["residue"] = json_ready(residue.to_dict())
    if gap is not None:
        payload["gap"] = json_ready(gap.to_dict())
    files["json"] = out / "discovery.json"
    files["json"].write_text(json.dumps(payload, indent=2, allow_nan=False) + "\n")
    d = result.discrepancy
    lines = ["# Model discovery", "", f"**Cause: {result.cause or 'none'}.** {result.explanation}", "",
             "## 1. Discrepancy of the calibrated model", "",
             f"chi^2 = {d.chi2:.2f} on {d.dof} cells (each z mapped through its Student-t: {d.chi2_equivalent:.2f}), "
             f"p = {d.p_value:.3g}: "
             f"{'beyond' if d.significant else 'within'} measurement uncertainty and DEM stochasticity.", "",
             "DEM replicate scatter per KPI, pooled over every run of the discovery (sd, degrees of freedom): "
             + ", ".join(f"{k} {v['sd']:.3g} ({v['dof']})" for k, v in d.noise.to_dict().items())
             + "; a cell's se = sd / sqrt(n).", "",
             "| condition | KPI | measured +- u | DEM +- se (n) | error | z |", "| --- | --- | --- | --- | ---: | ---: |"]
    for c in d.cells:
        lines.append(f"| {c.condition} | {c.kpi} | {c.measured_mean:.4g} +- {c.measured_u:.2g} | {c.dem_mean:.4g} +- "
                     f"{c.dem_se:.2g} ({c.n}) | {c.relative_error_pct:+.1f} % | {c.z:+.2f}{' *' if abs(c.z) > 2 else ''} |")
    if d.jammed:
        lines += ["", "Runs of the calibrated set whose discharge jammed (the grains arched over the slot), left out of "
                  "the means and the noise: " + jam_counts(d.jammed) + "."]
    if attainable:
        lines += ["", "What the calibration's bounds allowed at its condition (its calibration.json): each KPI's surrogate "
                  "range over the box its GA searched with the other KPIs inside the lab's 95 % CI. A KPI whose range "
                  "misses the lab's interval cannot be matched with the others by any set in the bounds.", ""]
        lines += format_attainable(attainable)
    lines += ["", "![discrepancy](discrepancy.png)", "", "## 2. Candidate causes (leave-one-condition-out)", ""]
    if not result.hypotheses:
        lines.append("None fitted: " + ("no candidate was asked for (discovery.candidates = [])."
                                        if d.significant else "no significant discrepancy."))
    else:
        conds = list(dict.fromkeys(c for h in result.hypotheses for c in h.held_out_chi2))
        lines += ["| hypothesis | added parameters | " + " | ".join(f"held-out chi^2 {c}" for c in conds)
                  + " | score | gain's noise sd | fit on all conditions: misfit + surrogate chi^2 (cells) |",
                  "| --- | ---: | " + " | ".join("---:" for _ in conds) + " | ---: | ---: | --- |"]
        for h in result.hypotheses:
            if h.skipped:
                lines.append(f"| {h.name} | - | " + " | ".join("-" for _ in conds) + f" | skipped: {h.skipped} | - | - |")
                continue
            fit = ("-" if not h.fit_cells else f"{h.fit_misfit_chi2:.1f} + {h.fit_surrogate_chi2:.1f} ({h.fit_cells})"
                   + (" unresolved" if h.name in result.unresolved else ""))
            if h.pruned:  # no held-out runs: its GP's predictions, marked
                lines.append(f"| {h.name} | {h.added} | "
                             + " | ".join(f"{h.predicted_chi2[c]:.1f} (GP)" if c in h.predicted_chi2 else "-"
                                          for c in conds)
                             + f" | {h.score:.1f} (GP), not run | - | {fit} |")
                continue
            lines.append(f"| {h.name}{' **cause**' if h.name == result.cause else ''} | {h.added} | "
                         + " | ".join(f"{h.held_out_chi2.get(c, float('nan')):.1f}" for c in conds)
                         + f" | {h.score:.1f} | {'-' if math.isnan(h.gain_noise_sd) else f'{h.gain_noise_sd:.1f}'} | "
                         + f"{fit} |")
        failed = [f"- {h.name}: the held-out runs on {c} failed ({why})"
                  for h in result.hypotheses for c, why in h.held_out_failures.items()]
        failed += [f"- {h.name}: its fit without {c} stayed astray after refinement: the DEM's held-out chi^2 "
                   f"{v[0]:.1f} where its GP predicted {v[1]:.1f}" for h in result.hypotheses for c, v in h.astray.items()]
        failed += [f"- {h.name}: not run on its held-out conditions: {h.pruned}" for h in result.hypotheses
                   if h.pruned]
        failed += [f"- {note}" for note in map(jammed_runs_note, result.hypotheses) if note]
        lines += [""] + failed if failed else []
        scored = [h for h in result.hypotheses[1:] if h.skipped is None and h.held_out_cells]
        best = min(scored, key=lambda h: h.score) if scored else None
        if result.cause is None and best is not None:  # what the best candidate did, though not a cause
            lines += ["", f"The best candidate, {best.name}, on held-out conditions (not named a cause):", "",
                      "| condition | KPI | measured | calibrated model | with " + best.name + " | error before | "
                      "error after |", "| --- | --- | --- | --- | --- | ---: | ---: |"]
            lines += [_gain_line(g) for g in gain_rows(best, d)]
    seen = [(h, direction, v) for h in result.hypotheses for direction, v in h.detectable.items()]
    if seen:
        lines += ["", "### What these data could have detected", "",
                  "Smallest effect of each candidate, from its no-effect values towards an end of its prior, that "
                  "the discrepancy test detects with 80 % probability (from the candidate's GP models and the "
                  "cells' uncertainties), the addition that raises the test's power at the prior's end most, and "
                  "what each KPI the lab does not report would add (measured on every condition, as repeatably as "
                  "the DEM measures it) and each proposed condition (measured on the compared KPIs with the median "
                  "uncertainty of the measured ones).",
                  "", "| candidate | direction | smallest detectable effect | power at the prior's end | "
                  "best addition (power) | unreported KPIs and conditions: power, smallest effect |",
                  "| --- | --- | --- | ---: | --- | --- |"]
        for h, direction, v in seen:
            effect = ("not within the prior" if v["smallest_fraction"] is None else
                      f"{100 * v['smallest_fraction']:.0f} % of the way: "
                      + ", ".join(f"{k} {x:.4g}" for k, x in v["values"].items()))
            top = v["additions"][0] if v["additions"] else None
            proposed = [a for a in v["additions"] if a["name"].startswith(("kpi:", "condition:"))]
            extra = "; ".join(f"{a['name'].split(':', 1)[1]}: {a['power']:.2f}, "
                              + ("not within the prior" if a["smallest"] is None else f"{100 * a['smallest']:.0f} %")
                              for a in proposed) or "-"
            lines.append(f"| {h.name} | {direction} | {effect} | {v['power_at_prior_end']:.2f} | "
                         + (f"{top['description']} ({top['power']:.2f})" if top else "-") + f" | {extra} |")
    apart = [(h, direction, rivals) for h in result.hypotheses for direction, rivals in h.separable.items() if rivals]
    if apart:
        lines += ["", "### Which causes these data can tell apart", "",
                  "Each candidate at its prior's end against each rival that could be named instead (the calibrated "
                  "parameters refitted, or another candidate with them, at its best fit inside its ranges): the "
                  "power with which these cells reject the rival, from the candidates' GP models. The row names "
                  "the hardest rival; where its power is low, no verdict can tell the two apart from these data, and "
                  "the addition shown is the one that separates them best. All rivals are in discovery.json.",
                  "", "| candidate | direction | hardest rival | power against it | smallest effect told from every "
                  "rival | best addition against it (power) |", "| --- | --- | --- | ---: | --- | --- |"]
        for h, direction, rivals in apart:
            hardest = min(rivals, key=lambda r: rivals[r]["power"])
            v = rivals[hardest]
            smallest = [r["smallest_fraction"] for r in rivals.values()]
            effect = ("not within the prior" if any(x is None for x in smallest) else
                      f"{100 * max(smallest):.0f} % of the way")
            top = v["additions"][0] if v["additions"] else None
            lines.append(f"| {h.name} | {direction} | {hardest} | {v['power']:.2f} | {effect} | "
                         + (f"{top['description']} ({top['power']:.2f})" if top else "-") + " |")
    if result.gain:
        lines += ["", "## 3. Extension", "", "Values fitted on every condition: "
                  + ", ".join(f"{k} = {v:.4g}" for k, v in result.extension.items()) + "."]
        if extension_command:
            lines += ["", f"Use it in any command: `{extension_command}`"]
        lines += ["", "## 4. Gain on held-out conditions", "",
                  "| condition | KPI | measured | before | after | error before | error after |",
                  "| --- | --- | --- | --- | --- | ---: | ---: |"]
        lines += [_gain_line(g) for g in result.gain]
        lines += ["", "![gain](gain.png)"]
    if residue is not None:
        lines += ["", "## The upper box's residue per unit slope", "",
                  "R = (fill - lower box) / tan(shear angle) is the mass the upper box keeps per unit slope of its "
                  "face. For straight wedges it is rho_b a^2 L, set by the floor's ledge beside the slot and the bulk "
                  "density, not by the angle: a model whose R is not the lab's can match the shear angle or the lower "
                  "box, not both, whatever its contact parameters (`bo/discovery/residue.py`)."]
        lines += [""] + format_residue(residue, heading=False).splitlines()
    if gap is not None:
        lines += ["", "## How far the face stands above the heap", "",
                  "G = shear angle - angle of repose of one test, the lab's against every run of the stores: where no "
                  "run has both inside the lab's CIs, no value of the parameters or candidates run can close that "
                  "condition's misfit; its cause lies in what all of them share (`bo/discovery/gap.py`)."]
        far = gap.out_of_reach()
        if far:
            lines += ["", "Out of every run's reach: " + ", ".join(far) + "."]
        lines += [""] + format_gap(gap, heading=False).splitlines()
    lines += ["", "DEM evaluations: " + ", ".join(f"{k} {v}" for k, v in result.evaluations.items())]
    files["md"] = out / "discovery.md"
    files["md"].write_text("\n".join(lines) + "\n")
    return files
