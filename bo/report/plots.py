"""PNG figures of the screening analysis: Fig. 9 (time step), Fig. 10 (variance shares) and
Fig. 11 (screening runs vs measurement) of the paper.

Contract
--------
Each ``*_figure`` function builds and returns a ``matplotlib.figure.Figure`` from the typed
results of ``bo.studies.timestep``, ``bo.screening.variance`` and ``bo.screening.stepwise``; each ``write_*`` function
renders that figure with the Agg canvas to a PNG file and returns the path. The figures are
created without ``pyplot`` (``Figure`` + ``FigureCanvasAgg``), so no global backend is switched,
nothing is shown and no figure is left open, which makes them safe in headless workers and in
parallel with other plotting code.

* ``time_step_figure(choice)``: one panel per KPI, mean +- standard deviation (error bars) over
  the replicates against the time-step fraction, the chosen fraction as a dashed line;
* ``variance_shares_figure(decomposition)``: stacked bars of the parameter (P) and stochastic
  (S) shares in percent per KPI, the exclusion threshold as a line, excluded KPIs hatched;
* ``screening_vs_measured_figure(results, measured)``: one panel per KPI, every replicate value
  of every screening run (small dots) and the run means (markers) against the run number, with
  the measured mean as a line and its 95 % CI as a band;
* ``relative_error_figure(groups)``: Figs. 14, 16, 18, signed relative error per KPI and group.
"""
from __future__ import annotations

import math
import os
import pathlib
from typing import Mapping, Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from bo.screening.bounds import measured_mean_ci95
from bo.screening.stepwise import ScreeningResults
from bo.studies.timestep import TimeStepChoice
from bo.screening.variance import VarianceDecomposition
from torchdem.errors import ConfigError, out_of_range

__all__ = [
    "time_step_figure",
    "variance_shares_figure",
    "screening_vs_measured_figure",
    "write_time_step_plot",
    "write_variance_shares_plot",
    "write_screening_vs_measured_plot",
    "relative_error_figure",
    "write_relative_error_plot",
    "save_png",
]

_PANEL_SIZE_IN = (3.6, 2.8)


def _grid(n: int) -> tuple[int, int]:
    cols = min(n, 3)
    return math.ceil(n / cols), cols


def _panels(n: int) -> tuple[Figure, list]:
    rows, cols = _grid(n)
    fig = Figure(figsize=(_PANEL_SIZE_IN[0] * cols, _PANEL_SIZE_IN[1] * rows),
                 layout="constrained")
    FigureCanvasAgg(fig)
    axes = [fig.add_subplot(rows, cols, i + 1) for i in range(n)]
    return fig, axes


def save_png(fig: Figure, path: str | os.PathLike, dpi: int = 150) -> pathlib.Path:
    """Render ``fig`` with the Agg canvas to ``path`` (a ``.png`` file); return the path."""
    path = pathlib.Path(path)
    if isinstance(dpi, bool) or not isinstance(dpi, int) or not 10 <= dpi <= 1200:
        raise out_of_range("dpi", dpi, "an integer in [10, 1200]", "save_png")
    if path.suffix.lower() != ".png":
        raise ConfigError(f"save_png: path = {str(path)!r} is not allowed; expected a file "
                          f"name ending in .png")
    if not path.parent.is_dir():
        raise ConfigError(f"save_png: directory {str(path.parent)!r} of {str(path)!r} does not "
                          f"exist; expected an existing directory")
    FigureCanvasAgg(fig)  # attach the Agg canvas explicitly; savefig renders through it
    fig.savefig(path, dpi=dpi, format="png")
    return path


def _chosen_kpis(kpis: Sequence[str] | None, known: Sequence[str], source: str) -> list[str]:
    chosen = list(known if kpis is None else kpis)
    unknown = [k for k in chosen if k not in known]
    if unknown or not chosen:
        raise ConfigError(f"{source}: KPIs {unknown or chosen} are not allowed; expected a "
                          f"non-empty subset of {list(known)}")
    return chosen


def time_step_figure(choice: TimeStepChoice, kpis: Sequence[str] | None = None) -> Figure:
    """Fig. 9: KPI mean +- std against the fraction of the Rayleigh time step."""
    chosen = _chosen_kpis(kpis, choice.kpi_names, "time_step_figure")
    fig, axes = _panels(len(chosen))
    x = np.asarray(choice.fractions) * 100.0
    for ax, kpi in zip(axes, chosen):
        j = choice.kpi_names.index(kpi)
        ax.errorbar(x, choice.mean[:, j], yerr=np.nan_to_num(choice.std[:, j]), marker="o",
                    capsize=3, label="mean +- std")
        ax.axvline(choice.chosen_fraction * 100.0, color="k", linestyle="--",
                   label=f"chosen {choice.chosen_fraction:.0%}")
        ax.set_xlabel("time step (% of Rayleigh time step)")
        ax.set_ylabel(kpi)
        ax.legend(fontsize="small")
    return fig


def variance_shares_figure(decomposition: VarianceDecomposition) -> Figure:
    """Fig. 10: stacked bars of the parameter and stochastic variance shares per KPI."""
    d = decomposition
    fig = Figure(figsize=(max(4.0, 1.3 * len(d.kpi_names) + 1.5), 4.0), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(d.kpi_names))
    p = np.nan_to_num(np.asarray(d.parameter_percent))
    s = np.nan_to_num(np.asarray(d.stochastic_percent))
    excluded = [k in d.excluded_kpis for k in d.kpi_names]
    hatch = ["//" if e else "" for e in excluded]
    ax.bar(x, p, color="tab:blue", label="DEM parameters (P)", hatch=hatch)
    ax.bar(x, s, bottom=p, color="tab:orange", label="stochasticity (S)", hatch=hatch)
    ax.axhline(100.0 * (1.0 - d.stochastic_threshold), color="k", linestyle=":",
               label=f"exclusion: S > {d.stochastic_threshold:.0%}")
    ax.set_xticks(x, [k + ("\n(excluded)" if e else "") for k, e in zip(d.kpi_names, excluded)],
                  rotation=30, ha="right", fontsize="small")
    ax.set_ylim(0, 100)
    ax.set_ylabel("variance contribution (%)")
    ax.legend(fontsize="small", loc="upper left", bbox_to_anchor=(1.0, 1.0))
    return fig


def screening_vs_measured_figure(results: ScreeningResults, measured: Mapping,
                                 kpis: Sequence[str] | None = None) -> Figure:
    """Fig. 11: screening KPI values per run against the measured mean and 95 % CI band.

    ``measured`` maps KPI -> ``KPIValue`` (or ``{"mean", "ci95"}``); ``kpis`` defaults to the
    screening KPIs that are measured.
    """
    source = "screening_vs_measured_figure"
    if kpis is None:
        kpis = [k for k in results.kpi_names if k in measured]
    chosen = _chosen_kpis(kpis, results.kpi_names, source)
    fig, axes = _panels(len(chosen))
    runs = np.arange(1, results.n_runs + 1)
    for ax, kpi in zip(axes, chosen):
        mean, ci95 = measured_mean_ci95(measured, kpi, source)
        values = results.kpi_values[:, :, results.kpi_index(kpi, source)]
        xs = np.repeat(runs, results.n_replicates)
        ax.plot(xs, values.ravel(), ".", color="0.6", markersize=3, label="replicates")
        ax.plot(runs, results.run_means(kpi), "o", color="tab:blue", markersize=4,
                label="run mean")
        ax.axhspan(mean - ci95, mean + ci95, color="tab:red", alpha=0.2, label="measured 95 % CI")
        ax.axhline(mean, color="tab:red", label="measured mean")
        ax.set_xlabel("screening run")
        ax.set_ylabel(kpi)
        ax.legend(fontsize="x-small")
    return fig


def write_time_step_plot(choice: TimeStepChoice, path: str | os.PathLike,
                         kpis: Sequence[str] | None = None, dpi: int = 150) -> pathlib.Path:
    """Write ``time_step_figure`` to a PNG file."""
    return save_png(time_step_figure(choice, kpis), path, dpi)


def write_variance_shares_plot(decomposition: VarianceDecomposition,
                               path: str | os.PathLike, dpi: int = 150) -> pathlib.Path:
    """Write ``variance_shares_figure`` to a PNG file."""
    return save_png(variance_shares_figure(decomposition), path, dpi)


def write_screening_vs_measured_plot(results: ScreeningResults, measured: Mapping,
                                     path: str | os.PathLike,
                                     kpis: Sequence[str] | None = None,
                                     dpi: int = 150) -> pathlib.Path:
    """Write ``screening_vs_measured_figure`` to a PNG file."""
    return save_png(screening_vs_measured_figure(results, measured, kpis), path, dpi)


def relative_error_figure(groups: Mapping[str, Sequence], title: str = "DEM vs measurement") -> Figure:
    """Figs. 14, 16 and 18: signed relative error in percent per KPI (bars, one colour per group,
    e.g. per condition), the DEM replicate spread as error bars and the measurement's 95 % CI as a
    grey band per KPI (both relative to the measured mean). ``groups`` maps a label to a sequence
    of ``bo.calibration.pipeline.KPIAgreement``."""
    if not groups or not any(groups.values()):
        raise ConfigError("relative_error_figure: no agreements to plot; expected a mapping label -> "
                          "non-empty sequence of KPIAgreement")
    kpis = list(dict.fromkeys(a.kpi for rows in groups.values() for a in rows))
    fig = Figure(figsize=(min(11.0, max(4.0, 1.1 * len(kpis) + 1.5)), 3.6),
                 layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    width = 0.8 / len(groups)
    for j, kpi in enumerate(kpis):
        ci = [a.measured_ci95 / abs(a.measured_mean) * 100 for rows in groups.values() for a in rows
              if a.kpi == kpi]
        if ci:
            ax.fill_between([j - 0.45, j + 0.45], -ci[0], ci[0], color="0.85", lw=0)
    for g, (label, rows) in enumerate(groups.items()):
        by = {a.kpi: a for a in rows}
        xs = [j - 0.4 + width * (g + 0.5) for j, k in enumerate(kpis) if k in by]
        vals = [by[k].relative_error_pct for k in kpis if k in by]
        errs = [0.0 if not math.isfinite(by[k].dem_std) else by[k].dem_std / abs(by[k].measured_mean) * 100
                for k in kpis if k in by]
        ax.bar(xs, vals, width * 0.9, yerr=errs, capsize=3, label=label)
    ax.axhline(0.0, color="k", lw=0.8)
    ax.set_xticks(range(len(kpis)))
    ax.set_xticklabels([k.replace("_", " ") for k in kpis], rotation=15, fontsize=7)
    ax.set_ylabel("relative error (%)")
    ax.set_title(title, fontsize=9)
    if len(groups) > 1:
        ax.legend(fontsize=7)
    return fig


def write_relative_error_plot(groups: Mapping[str, Sequence], path: str | os.PathLike,
                              title: str = "DEM vs measurement") -> pathlib.Path:
    """Render ``relative_error_figure`` to a PNG."""
    return save_png(relative_error_figure(groups, title), path)


def power_figure(rows: Sequence) -> Figure:
    """Detection and right-cause rate (Wilson 95 % bars) against effect size (fraction of the
    prior) per mechanism of a power study (``bo.discovery.power.PowerRow``); the null's
    false-alarm rate at 0 in every panel."""
    null = [r for r in rows if r.mechanism == "null"]
    names = sorted({r.mechanism for r in rows if r.mechanism != "null"})
    if not names:
        raise ConfigError("power_figure: no mechanism rows to plot")
    fig, axes = _panels(len(names))
    for ax, name in zip(axes, names):
        mine = sorted((r for r in rows if r.mechanism == name), key=lambda r: r.fraction)
        for attr, colour, label, dx in (("detection", "tab:blue", "discrepancy detected", -0.012),
                                        ("right_rate", "tab:green", "right cause named", 0.0),
                                        ("wrong_rate", "tab:red", "other cause named", 0.012)):
            x = [r.fraction + dx for r in mine]  # side by side where the rates coincide
            rate = np.array([getattr(r, attr) for r in mine])
            ax.errorbar(x, rate[:, 0], yerr=[rate[:, 0] - rate[:, 1], rate[:, 2] - rate[:, 0]], marker="o",
                        color=colour, capsize=3, label=label)
        for r in null:
            ax.errorbar([0.0], [r.wrong_rate[0]], yerr=[[r.wrong_rate[0] - r.wrong_rate[1]],
                                                        [r.wrong_rate[2] - r.wrong_rate[0]]],
                        marker="s", color="k", capsize=3, label="null: a cause named")
        ax.axhline(0.8, color="0.6", linestyle="--", linewidth=0.8)
        ax.set_ylim(-0.02, 1.02)
        ax.set_title(name, fontsize="small")
        ax.set_xlabel("effect (fraction of the prior)")
        ax.set_ylabel("share of labs")
        ax.legend(fontsize="x-small")
    return fig


def write_power_plot(rows: Sequence, path: str | os.PathLike, dpi: int = 150) -> pathlib.Path:
    """Write ``power_figure`` to a PNG file."""
    return save_png(power_figure(rows), path, dpi)
