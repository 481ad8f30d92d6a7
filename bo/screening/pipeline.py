"""The screening stage of a calibration (paper section 3.3): run a definitive screening design
through the campaign store and report it (Table 5, Fig. 10, Fig. 11, the Table-6 extension).

Contract
--------
``run_screening(store, executor, table, *, n_fake, seeds, condition, kpis, stage)`` builds the
coded DSD of ``table`` (``bo.design.dsd.definitive_screening_design(table.k, n_fake)``), scales it to
physical values with the table, and stores it in ``store`` under ``stage``: one batch per seed
(replicate), keyed ``dsd/<design id>/seed=<seed>``, each with the design's points and that one
seed. The design id is a hash of the parameter names, the levels and ``n_fake``, so

* a rerun with the same store reuses the stored batches and evaluates nothing that is done
  (``bo.campaign.executor.run_pending`` runs only pending tasks, also those a killed run left behind);
* raising the number of replicates keeps the replicates already run and adds only the new
  seeds' batches;
* another design (other parameters, levels or ``n_fake``) gets new batches in the same store.

It then runs every pending task of ``stage`` (``run_pending(..., wait=True)``; that includes
pending tasks of other designs stored under the same stage, e.g. of an interrupted earlier
screening) and assembles
``bo.screening.stepwise.ScreeningResults`` with ``kpi_values[run, replicate, kpi]``: KPI columns in the
order of ``kpis`` (names as the executor's outcomes carry them, e.g. the DEM's
``mass_flow_rate_full_kg_s``); a failed evaluation, an unmeasured KPI and every KPI of a run whose
discharge jammed (``kpi.loadcell.discharge_jammed``: its grains arched over the slot, so it measured
an undrained fill, not the lab's test; the surrogate leaves such runs out too) are NaN. Bad inputs
(``n_fake < 0``, a design order without a conference matrix, no seeds, repeated KPIs) raise
``ConfigError`` before anything is stored or run. A KPI that no finished evaluation carries is
an error naming the KPIs they do carry.

``analyse_and_report(results, measured, out_dir, ...)`` runs the analysis of section 3.3 and
3.4.1 and writes, into ``out_dir``:

* ``table5.md`` / ``table5.json``: the significance counts in the layout of Table 5 (over the
  kept KPIs; when every KPI is excluded, a note saying so and no rows);
* ``fig10_variance_shares.png``: parameter vs stochastic variance shares (Eqs. 4-6);
  KPIs with ``S > stochastic_threshold`` (or no variance, or fewer than two finite values)
  are flagged and excluded from Table 5 and the extension, as the paper excludes segregation;
* ``fig11_screening_vs_measured.png``: screening runs against the measured mean and 95 % CI;
* ``screening.json`` (everything, strict JSON, NaN as null) and ``screening.md`` (Table 5,
  variance table, extension proposal with its reasoning).

Measured values are full-box lab values. A DEM KPI ``<name>_full_<unit>`` (the slice's mass
KPI scaled to the full box) is compared with the measured ``<name>_<unit>``; the slice-only
mass KPIs (``mass_flow_rate_kg_s``, ``mass_lower_box_kg``, ``fill_mass_kg``, whose full-box
counterpart exists) are never compared with a measurement. Other KPIs compare by name.

Reference: A. Hadi, Y. Pang, D. Schott, section 3.3 (DSD, 5 replicates, variance
decomposition, Table 5) and 3.4.1 (Fig. 11, Table 6).
"""
from __future__ import annotations

import hashlib
import json
import math
import sqlite3
from dataclasses import dataclass
from dataclasses import field as dataclass_field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from bo.design.dsd import ParameterTable, definitive_screening_design, scale_design
from bo.campaign.executor import Executor, run_pending
from bo.screening.bounds import ExtensionProposal, PhysicalLimit, measured_mean_ci95, propose_extension
from bo.screening.stepwise import ScreeningAnalysis, ScreeningResults, analyse_screening
from bo.campaign.progress import open_read_only
from bo.campaign.store import CampaignStore
from bo.screening.variance import VarianceDecomposition, decompose_variance
from torchdem.errors import ConfigError, out_of_range
from kpi.loadcell import discharge_jammed

__all__ = [
    "SLICE_ONLY_KPIS",
    "ScreenSettings",
    "ScreeningReport",
    "analyse_and_report",
    "design_id",
    "jammed_screening_runs",
    "json_ready",
    "measured_for",
    "run_screening",
    "screening_batch_key",
    "stored_screening",
]

#: Slice mass KPIs of the DEM; the lab measures the full box, so these are never compared.
SLICE_ONLY_KPIS = ("mass_flow_rate_kg_s", "mass_lower_box_kg", "fill_mass_kg")


@dataclass(frozen=True)
class ScreenSettings:
    """A screening stage, checked (``bo.cli.screen.screen_settings_from`` builds it from config).

    Attributes:
        table: levels of the screened parameters. n_fake: fake factors of the DSD.
        seeds: one replicate of the design per seed. condition: measured condition screened.
        kpis: DEM KPI names analysed. p_threshold, selection_fraction: stepwise regression and
            Table-5 selection. second_order: the stepwise's second stage (squares and
            interactions of the active factors, as JMP's definitive screening platform). stochastic_threshold: exclude a KPI whose stochastic share S is
            above it. extension_factor, extension_mode: the Table-6 extension rule.
        limits: screened parameter -> (low, high), the closed interval the extension may not
            leave (replacing the parameter's physical range, e.g. sliding friction at most 1 as the
            paper's Table 6 keeps it); see :meth:`physical_limits`.
    """

    table: ParameterTable
    n_fake: int
    seeds: tuple[int, ...]
    condition: str
    kpis: tuple[str, ...]
    p_threshold: float
    selection_fraction: float
    stochastic_threshold: float
    extension_factor: float
    extension_mode: str
    limits: Mapping[str, tuple[float, float]] = dataclass_field(default_factory=dict)
    second_order: bool = False

    def physical_limits(self) -> dict[str, PhysicalLimit]:
        """``limits`` as the extension rule's :class:`PhysicalLimit` (closed intervals)."""
        return {n: PhysicalLimit(float(lo), float(hi)) for n, (lo, hi) in self.limits.items()}


# --------------------------------------------------------------------------------------------
# Running the design through the store
# --------------------------------------------------------------------------------------------

def design_id(table: ParameterTable, n_fake: int) -> str:
    """Short hash naming a design: parameter names, their levels and the fake factors."""
    text = json.dumps({"names": list(table.names), "low": [repr(v) for v in table.low],
                       "mid": [repr(v) for v in table.mid], "high": [repr(v) for v in table.high],
                       "n_fake": int(n_fake)}, sort_keys=True)
    return f"k{table.k}-fake{int(n_fake)}-" + hashlib.sha256(text.encode()).hexdigest()[:12]


def screening_batch_key(table: ParameterTable, n_fake: int, seed: int) -> str:
    """Store batch key of one replicate (seed) of a design."""
    return f"dsd/{design_id(table, n_fake)}/seed={int(seed)}"


def _check_kpis(kpis, source: str) -> tuple[str, ...]:
    if isinstance(kpis, (str, bytes)):
        raise out_of_range("kpis", kpis, "a list of KPI names, e.g. ['shear_angle_deg']", source)
    names = tuple(kpis)
    if not names or any(not isinstance(k, str) or not k for k in names) or len(set(names)) != len(names):
        raise out_of_range("kpis", list(names), "a non-empty list of distinct KPI names", source)
    return names


def run_screening(store: CampaignStore, executor: Executor, table: ParameterTable, *, n_fake: int,
                  seeds: Sequence[int], condition: str, kpis: Sequence[str],
                  stage: str = "screening") -> ScreeningResults:
    """Run (or resume) the DSD of ``table`` with one replicate per seed; see the module docstring."""
    source = "run_screening"
    if not isinstance(table, ParameterTable):
        raise out_of_range("table", table, "a bo.design.dsd.ParameterTable", source)
    if isinstance(n_fake, bool) or not isinstance(n_fake, (int, np.integer)) or n_fake < 0:
        raise out_of_range("n_fake", n_fake, "an integer >= 0 (number of fake factors)", source)
    kpis = _check_kpis(kpis, source)
    if isinstance(seeds, (str, bytes)) or not isinstance(seeds, Sequence) or not seeds \
            or any(isinstance(s, bool) or not isinstance(s, (int, np.integer)) for s in seeds) \
            or len(set(int(s) for s in seeds)) != len(seeds):
        raise out_of_range("seeds", seeds, "a non-empty sequence of distinct ints, one per replicate",
                           source)
    seeds = [int(s) for s in seeds]
    if not isinstance(condition, str) or not condition:
        raise out_of_range("condition", condition, "a condition name such as '50-50'", source)
    store.check_stage(stage, source)
    coded = definitive_screening_design(table.k, int(n_fake))  # ConfigError for bad sizes
    physical = scale_design(coded, table)
    points = [dict(zip(table.names, (float(v) for v in row))) for row in physical]

    keys = {}
    for seed in seeds:
        key = screening_batch_key(table, n_fake, seed)
        stored = store.batch(stage, key, lambda: points, seeds=[seed], conditions=[condition])
        if len(stored) != len(points) or any(
                s.keys() != p.keys() or any(not math.isclose(s[n], p[n], rel_tol=1e-12, abs_tol=0.0)
                                            for n in p) for s, p in zip(stored, points)):
            raise ConfigError(f"{store.path}: batch {stage}/{key} holds other points than the design "
                              f"of {table.source}; use a new store")
        keys[seed] = key
    run_pending(store, executor, stage)

    values = np.full((len(points), len(seeds), len(kpis)), np.nan)
    carried: set[str] = set()
    for r, seed in enumerate(seeds):
        for rec in store.records(stage, batch_key=keys[seed], condition=condition):
            if rec.status != "done" or rec.kpis is None:
                continue
            carried.update(rec.kpis)
            if not discharge_jammed(rec.kpis):
                values[rec.point_index, r] = [rec.kpis.get(k, math.nan) for k in kpis]
    if carried:
        missing = [k for k in kpis if k not in carried]
        if missing:
            raise ConfigError(f"{source}: KPIs {missing} are in no finished evaluation of stage "
                              f"{stage!r}; the evaluations carry {sorted(carried)}")
    values[~np.isfinite(values)] = np.nan  # inf is never a measurement
    return ScreeningResults.from_parameter_table(
        table, coded, seeds, kpis, values,
        source=f"{store.path} {stage} dsd/{design_id(table, n_fake)} condition {condition}")


def jammed_screening_runs(store: CampaignStore, table: ParameterTable, *, n_fake: int, seeds: Sequence[int],
                          condition: str, kpis: Sequence[str], stage: str = "screening"
                          ) -> tuple[np.ndarray, np.ndarray]:
    """``(jammed [runs, r] bool, values [runs, r, M])``: the runs of the stored DSD of ``table`` (one
    replicate per seed, ``r``) whose discharge jammed, and the KPIs ``kpis`` (``M``) they measured, NaN
    for every other run. :func:`run_screening` reads those runs as NaN (they measured no test); a
    surrogate that reuses the screening's points reads them as it reads its own jammed runs. Only the
    store is read; a batch it does not hold yet has no jammed run."""
    kpis = _check_kpis(kpis, "jammed_screening_runs")
    n_runs = definitive_screening_design(table.k, int(n_fake)).shape[0]
    jammed = np.zeros((n_runs, len(seeds)), dtype=bool)
    values = np.full((n_runs, len(seeds), len(kpis)), np.nan)
    for r, seed in enumerate(seeds):
        for rec in store.records(stage, batch_key=screening_batch_key(table, n_fake, seed), condition=condition,
                                 status="done"):
            if rec.kpis is not None and discharge_jammed(rec.kpis):
                jammed[rec.point_index, r] = True
                values[rec.point_index, r] = [rec.kpis.get(k, math.nan) for k in kpis]
    values[~np.isfinite(values)] = np.nan
    return jammed, values


# --------------------------------------------------------------------------------------------
# Analysis and report
# --------------------------------------------------------------------------------------------

def stored_screening(path, kpis: Sequence[str], *, stage: str = "screening",
                     condition: str | None = None) -> ScreeningResults:
    """The screening a campaign store holds, read only (nothing is run or written; a campaign may
    be writing the store meanwhile): ``ScreeningResults`` of the finished runs of ``stage``, one
    replicate per batch (seed), KPI columns in the order of ``kpis``, NaN where a run is not done
    or did not measure a KPI; parameters in the order the store keeps them (by name). The coded
    levels come back from the points: per parameter its
    lowest, middle and highest value are -1, 0 and +1. The stage must hold one design (one point
    set) at one ``condition`` (or the one given). A run whose discharge jammed is NaN, as in
    :func:`run_screening`."""
    source = f"{path} stage {stage!r}"
    kpis = _check_kpis(kpis, source)
    if not Path(path).is_file():
        raise ConfigError(f"{path}: no campaign store at this path")
    conn = open_read_only(Path(path), source)
    try:
        batches = conn.execute("SELECT batch_key, points, seeds FROM batches WHERE stage = ? ORDER BY created_at, rowid",
                               (stage,)).fetchall()
        rows = conn.execute("SELECT batch_key, point_index, condition, status, kpis FROM evaluations WHERE stage = ?",
                            (stage,)).fetchall()
    except sqlite3.DatabaseError as exc:
        raise ConfigError(f"{source}: not a readable campaign store ({exc})") from exc
    finally:
        conn.close()
    if not batches:
        raise ConfigError(f"{source}: the store holds no batch of this stage")
    designs = {points for _, points, _ in batches}
    if len(designs) != 1:
        raise ConfigError(f"{source}: the stage holds {len(designs)} designs (batches "
                          f"{[key for key, _, _ in batches]}); expected one")
    conditions = sorted({r[2] for r in rows})
    if condition is None:
        if len(conditions) != 1:
            raise ConfigError(f"{source}: runs at conditions {conditions}; name one (condition=)")
        condition = conditions[0]
    elif condition not in conditions:
        raise out_of_range("condition", condition, f"one of {conditions}", source)
    points = json.loads(batches[0][1])
    names = tuple(points[0])
    physical = np.array([[float(p[n]) for n in names] for p in points])
    coded = np.zeros_like(physical)
    for j, name in enumerate(names):
        levels = np.unique(physical[:, j])
        if len(levels) not in (2, 3):
            raise ConfigError(f"{source}: parameter {name!r} takes {len(levels)} values {levels.tolist()} in the "
                              "design; a screening design has 2 or 3 levels")
        coded[:, j] = np.searchsorted(levels, physical[:, j]) * (2.0 / (len(levels) - 1)) - 1.0
    seeds = []
    for key, _, seed_json in batches:
        batch_seeds = json.loads(seed_json)
        if len(batch_seeds) != 1:
            raise ConfigError(f"{source}: batch {key} has seeds {batch_seeds}; a screening batch has one")
        seeds.append(int(batch_seeds[0]))
    column = {key: r for r, (key, _, _) in enumerate(batches)}
    values = np.full((len(points), len(batches), len(kpis)), np.nan)
    for key, index, cond, status, kpi_json in rows:
        if cond == condition and status == "done" and kpi_json:
            measured = json.loads(kpi_json)
            if discharge_jammed(measured):
                continue
            values[index, column[key]] = [math.nan if measured.get(k) is None else float(measured[k]) for k in kpis]
    values[~np.isfinite(values)] = np.nan
    return ScreeningResults(parameter_names=names, coded=coded, physical=physical, seeds=tuple(seeds),
                            kpi_names=kpis, kpi_values=values, source=f"{source} condition {condition}")


def measured_name(kpi: str) -> str:
    """The measured KPI of a DEM KPI: a reduced box's ``<x>_full_<unit>`` (its mass scaled to the
    whole box) is the lab's ``<x>_<unit>``; other names are their own."""
    return kpi.replace("_full_", "_", 1)


def measured_for(kpi_names: Sequence[str], measured: Mapping) -> dict:
    """Measured entry for each screening KPI that has one (see the module docstring):
    ``<x>_full_<unit>`` <- measured ``<x>_<unit>``; slice-only mass KPIs get none."""
    out = {}
    for kpi in kpi_names:
        if kpi in SLICE_ONLY_KPIS:
            continue
        name = measured_name(kpi)
        if name in measured:
            out[kpi] = measured[name]
    return out


def json_ready(value):
    """JSON-ready copy: numpy scalars to Python, non-finite floats to None."""
    if isinstance(value, Mapping):
        return {str(k): json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_ready(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


@dataclass(frozen=True)
class ScreeningReport:
    """What ``analyse_and_report`` found and wrote.

    Attributes:
        results: the screening results analysed.
        variance: variance decomposition of the KPIs with at least two finite values.
        unmeasurable_kpis: KPIs with fewer than two finite values (excluded, not decomposed).
        calibration_kpis: KPIs kept for Table 5 and calibration.
        analysis: stepwise fits and Table 5, None when no KPI was kept.
        proposal: the parameter-space extension, None without a kept and measured KPI.
        files: name -> path of every file written.
        text: the Markdown report (also in ``screening.md``).
    """

    results: ScreeningResults
    variance: VarianceDecomposition | None
    unmeasurable_kpis: tuple[str, ...]
    calibration_kpis: tuple[str, ...]
    analysis: ScreeningAnalysis | None
    proposal: ExtensionProposal | None
    files: Mapping[str, Path]
    text: str


def analyse_and_report(results: ScreeningResults, measured: Mapping, out_dir, *,
                       p_threshold: float = 0.01, selection_fraction: float = 0.8,
                       stochastic_threshold: float = 0.5, extension_factor: float = 1.0,
                       extension_mode: str = "extend",
                       limits: Mapping[str, PhysicalLimit] | None = None,
                       second_order: bool = False,
                       title: str = "Screening") -> ScreeningReport:
    """Table 5, variance shares, extension, Fig. 10/11; see the module docstring.

    ``measured`` maps measured KPI names to ``torchdem.measured.KPIValue`` (or
    ``{"mean", "ci95"}``), e.g. ``load_measured().condition("50-50").kpis``.
    """
    from bo.report.plots import write_screening_vs_measured_plot, write_variance_shares_plot

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {}
    finite = np.isfinite(results.kpi_values).sum(axis=(0, 1))
    unmeasurable = tuple(k for k, n in zip(results.kpi_names, finite) if n < 2)
    decomposable = [k for k in results.kpi_names if k not in unmeasurable]
    variance = None
    if decomposable:
        cols = [results.kpi_index(k) for k in decomposable]
        variance = decompose_variance(results.kpi_values[:, :, cols], decomposable, stochastic_threshold,
                                      source=f"analyse_and_report({results.source})")
        files["fig10"] = write_variance_shares_plot(variance, out / "fig10_variance_shares.png")
    calibration = variance.calibration_kpis if variance is not None else ()
    analysis = None
    if calibration:
        analysis = analyse_screening(results, p_threshold, selection_fraction, kpis=calibration,
                                     second_order=second_order)
    no_table = (f"No Table 5: every KPI {list(results.kpi_names)} is excluded (stochasticity dominates, "
                f"no variance, or not measurable); see the variance decomposition.")
    files["table5_md"] = out / "table5.md"
    files["table5_md"].write_text((analysis.table.to_markdown() if analysis is not None else no_table) + "\n")
    files["table5_json"] = out / "table5.json"
    files["table5_json"].write_text(json.dumps(json_ready(
        analysis.table.to_dict() if analysis is not None else
        {"kpis": [], "rows": [], "selected_parameters": [], "note": no_table}), indent=2, allow_nan=False) + "\n")
    lab = measured_for(results.kpi_names, measured)
    plotted = [k for k in results.kpi_names if k in lab and k not in unmeasurable]
    if plotted:
        files["fig11"] = write_screening_vs_measured_plot(results, lab, out / "fig11_screening_vs_measured.png",
                                                          kpis=plotted)
    proposal = None
    compared = [k for k in calibration if k in lab]
    if analysis is not None and compared:
        proposal = propose_extension(results, analysis.table, lab, factor=extension_factor,
                                     mode=extension_mode, limits=limits, kpis=compared)

    lines = [f"# {title}", "",
             f"Design: {results.n_runs} runs x {results.n_replicates} replicates (seeds "
             f"{list(results.seeds)}), parameters {list(results.parameter_names)}.",
             f"Source: {results.source}", "", "## Variance decomposition (Fig. 10)", ""]
    if variance is not None:
        lines += ["```", variance.to_text(), "```"]
    for k in unmeasurable:
        lines.append(f"- {k}: EXCLUDE (fewer than 2 finite values; the KPI could not be measured)")
    excluded = (variance.excluded_kpis if variance is not None else ()) + unmeasurable
    lines += ["", f"Excluded from Table 5 and calibration: {list(excluded) or 'none'}.",
              f"Kept: {list(calibration) or 'none'}.", "", "## Table 5: significant parameters", ""]
    lines += [analysis.table.to_markdown() if analysis is not None else no_table]
    if analysis is not None:
        lines += ["", f"Selected parameters: {list(analysis.selected_parameters) or 'none'}"]
    lines += ["", "## Parameter-space extension (Table 6 rule)", ""]
    if proposal is not None:
        lines += ["```", proposal.to_text(), "```"]
    else:
        lines.append("No extension proposed: no kept KPI has a measurement to compare with.")
    if not [k for k in results.kpi_names if k in lab]:
        lines.append("(No screening KPI has a measured counterpart.)")
    lines += ["", "## Figures", ""]
    lines += [f"- {p.name}" for k, p in files.items() if k.startswith("fig")]
    text = "\n".join(lines) + "\n"
    files["screening_md"] = out / "screening.md"
    files["screening_md"].write_text(text)

    payload = {
        "results": results.to_dict(),
        "unmeasurable_kpis": list(unmeasurable),
        "variance": variance.to_dict() if variance is not None else None,
        "excluded_kpis": list(excluded),
        "calibration_kpis": list(calibration),
        "table5": analysis.table.to_dict() if analysis is not None else None,
        "fits": [f.summary() for f in analysis.fits] if analysis is not None else [],
        "measured": {k: dict(zip(("mean", "ci95"), measured_mean_ci95(lab, k, "analyse_and_report")))
                     for k in lab},
        "extension": proposal.to_dict() if proposal is not None else None,
        "settings": {"p_threshold": p_threshold, "selection_fraction": selection_fraction,
                     "second_order": bool(second_order),
                     "stochastic_threshold": stochastic_threshold,
                     "extension_factor": extension_factor, "extension_mode": extension_mode},
    }
    files["screening_json"] = out / "screening.json"
    files["screening_json"].write_text(json.dumps(json_ready(payload), indent=2, allow_nan=False) + "\n")
    return ScreeningReport(results=results, variance=variance, unmeasurable_kpis=unmeasurable,
                           calibration_kpis=tuple(calibration), analysis=analysis, proposal=proposal,
                           files=dict(files), text=text)
