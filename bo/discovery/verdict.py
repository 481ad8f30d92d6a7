"""The statistics of discovery's verdict: the cells of a set of DEM runs against the lab, the
discrepancy test over them, each hypothesis's score, and the rules from the scores to a named cause.
Plain numbers in, plain data out: no DEM, no store (``bo.discovery.pipeline`` runs the DEM and
calls these; the module docstring there states the method, step by step).

Contract
--------
* :class:`Cell` (one KPI of one condition: DEM mean and standard error against the measured mean and
  its standard uncertainty, their z), :class:`Discrepancy` (step 1: the cells, chi^2, p-value),
  :class:`HypothesisScore` (step 2 for one hypothesis), :class:`GainRow` (step 4): frozen dataclasses.
* :func:`cells_of` ``(reps [C, r, K], conditions, kpis, lab, noise) -> [Cell]`` and
  :func:`discrepancy_of` (the same plus the chi^2 test); :func:`welch_dof` and
  :func:`chi2_equivalent` turn a z of estimated variances into a chi^2_1 term.
* Fits (step 2): :func:`expected_chi2_terms` (the chi^2 a fit minimises), :func:`must_beat` and
  :func:`win_probability` (whether a candidate's held-out runs are worth making).
* The verdict (step 3): :func:`fit_resolved` / :func:`fit_check` (can a fit be judged by its held-out
  runs?), :func:`prediction_astray`, :func:`gain_noise_sd` (the DEM-noise sd of a score difference),
  :func:`tied_with`, :func:`refit_verdict`, :func:`explained_share`; step 4: :func:`gain_rows`.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Mapping, Sequence

import numpy as np
from scipy import stats

from bo.discovery.replicate_noise import ReplicateNoise

if TYPE_CHECKING:
    from bo.discovery.pipeline import DiscoverySettings

__all__ = ["Cell", "Discrepancy", "HypothesisScore", "GainRow", "cells_of", "discrepancy_of", "welch_dof",
           "chi2_equivalent", "expected_chi2_terms", "must_beat", "win_probability", "fit_resolved",
           "prediction_astray", "fit_check", "tied_with", "refit_verdict", "explained_share", "gain_noise_sd",
           "gain_rows"]


@dataclass(frozen=True)
class Cell:
    """One KPI of one condition: DEM against the measurement (``se``, ``u``: standard
    uncertainties of the DEM mean and of the measured mean; ``z`` their normalised difference)."""

    condition: str
    kpi: str
    dem_mean: float
    dem_se: float
    n: int
    measured_mean: float
    measured_u: float
    z: float
    relative_error_pct: float
    dof: float = math.inf

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class Discrepancy:
    """Step 1: every cell, chi^2 over them, its degrees of freedom and p-value; ``noise``: the
    pooled DEM replicate noise the cells' standard errors come from."""

    cells: tuple[Cell, ...]
    chi2: float
    dof: int
    p_value: float
    significant: bool
    noise: ReplicateNoise
    chi2_equivalent: float = math.nan
    jammed: Mapping[str, int] = dataclasses.field(default_factory=dict)  # condition -> runs left out: jammed


@dataclass(frozen=True)
class HypothesisScore:
    """Step 2 for one hypothesis.

    Attributes:
        name: ``"parameters"`` or a registry name. description: the mechanism in words.
        parameters: free parameter names; bounds: name -> (low, high); added: how many are new
            physics (beyond the refit ones).
        held_out_chi2: condition -> chi^2 of the DEM runs on that condition with the parameters
            fitted without it (``held_out_cells``: those runs' cells).
        predicted_chi2: condition -> the same chi^2 as the surrogate predicted it (for reference;
            a poor surrogate's wide predictive variance would flatter it, so it does not score).
        fitted_without: condition -> parameters fitted without that condition.
        fitted_all: parameters fitted on every condition; in_sample_chi2: their surrogate chi^2.
        score: sum of held-out chi^2 + penalty x added. points: design points run.
        skipped: why the hypothesis was not fitted (unavailable for this model, or too few of its
            design points flowed on every condition: :class:`JammedDesign`), else None.
        gain_noise_sd: standard deviation of (score of ``parameters`` - this score) from DEM noise
            alone (step 3); NaN for ``parameters`` itself.
        detectable: direction (``"high"``/``"low"``: towards that end of the prior from the
            mechanism's no-effect values) -> the smallest effect the discrepancy test detects with
            80 % probability with these data (``fraction`` of the way, ``values``), its power at the
            prior's end and what would raise it (:func:`detectability`); empty for a mechanism
            without no-effect values.
        separable: direction -> rival hypothesis -> the power with which these cells would tell
            this mechanism, at its prior's end, from the rival at the rival's best fit, the
            smallest effect told apart with 80 % probability and what would raise the power
            (:func:`separability`); empty as ``detectable``.
        held_out_failures: condition -> why its held-out runs gave no value for some measured KPI
            (the fitted parameters could not be simulated there, e.g. a fill that does not fit the
            box); that condition's held-out chi^2, hence the score, is then infinite: a hypothesis
            that cannot predict a condition does not explain it.
        fit_misfit_chi2, fit_surrogate_chi2: the in-sample chi^2 at ``fitted_all`` split into the
            GP mean's misfit, ``sum (mu - y)^2 / (s^2 + u^2)``, and the GP's own uncertainty,
            ``sum sigma_GP^2 / (s^2 + u^2)``; fit_cells: the cells fitted (:func:`fit_check`).
        astray: condition -> (the DEM's held-out chi^2, the GP's prediction) where a left-out fit
            went astray (:func:`prediction_astray`) even after ``escalations`` (reported; the
            refinement is the remedy, the verdict does not wait on it).
        win_probability: the probability, by its own GP, that its held-out runs would score better
            than the ``parameters`` hypothesis by the margin (:func:`win_probability`; NaN when
            not computed: pruning off, or the fit unresolved). pruned: why its held-out runs were not made (the probability was below
            ``prune_probability``), else None; a pruned candidate's score is its GP's prediction
            and it can be neither named nor tied.
        jammed_design, jammed_held_out: condition -> runs of the design (its refinements included)
            and of the held-out runs whose discharge jammed, left out of the GPs' data and the
            means (``bo.discovery.pipeline``'s docstring); only conditions with such runs.
    """

    name: str
    description: str
    parameters: tuple[str, ...]
    bounds: Mapping[str, tuple[float, float]]
    added: int
    held_out_chi2: Mapping[str, float]
    fitted_without: Mapping[str, Mapping[str, float]]
    fitted_all: Mapping[str, float]
    in_sample_chi2: float
    score: float
    points: int
    skipped: str | None = None
    held_out_cells: tuple[Cell, ...] = ()
    predicted_chi2: Mapping[str, float] = dataclasses.field(default_factory=dict)
    held_out_failures: Mapping[str, str] = dataclasses.field(default_factory=dict)
    gain_noise_sd: float = math.nan
    detectable: Mapping[str, Mapping] = dataclasses.field(default_factory=dict)
    separable: Mapping[str, Mapping] = dataclasses.field(default_factory=dict)
    fit_misfit_chi2: float = math.nan
    fit_surrogate_chi2: float = math.nan
    fit_cells: int = 0
    astray: Mapping[str, tuple[float, float]] = dataclasses.field(default_factory=dict)
    win_probability: float = math.nan
    pruned: str | None = None
    jammed_design: Mapping[str, int] = dataclasses.field(default_factory=dict)
    jammed_held_out: Mapping[str, int] = dataclasses.field(default_factory=dict)


@dataclass(frozen=True)
class GainRow:
    """Step 4: one KPI of one held-out condition, before and after the extension."""

    condition: str
    kpi: str
    measured_mean: float
    measured_u: float
    before_mean: float
    before_se: float
    after_mean: float
    after_se: float
    before_error_pct: float
    after_error_pct: float
    before_z: float
    after_z: float

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def welch_dof(se: float, dof_se: float, u: float, dof_u: float) -> float:
    """Welch-Satterthwaite degrees of freedom of ``se^2 + u^2`` (inf: both known exactly)."""
    a, b = se ** 2, u ** 2
    den = (a * a / dof_se if a > 0 and math.isfinite(dof_se) else 0.0) + (b * b / dof_u if b > 0 and math.isfinite(dof_u)
                                                                           else 0.0)
    return (a + b) ** 2 / den if den > 0 else math.inf


def chi2_equivalent(z: float, dof: float) -> float:
    """The chi^2_1 value with the tail probability of a Student-t ``z`` of ``dof`` degrees of freedom."""
    if not math.isfinite(dof):
        return z * z
    return float(stats.chi2.isf(2.0 * stats.t.sf(abs(z), dof), 1))


def cells_of(reps: np.ndarray, conditions: Sequence[str], kpis: Sequence[str],
             lab: Mapping[tuple[str, str], tuple[float, float]], noise: ReplicateNoise) -> list[Cell]:
    """Cells of ``reps [C, r, K]`` against the lab (only measured cells); the DEM mean's standard
    error from the pooled replicate noise (``bo.discovery.replicate_noise``), not from the cell's own runs."""
    cells = []
    for i, c in enumerate(conditions):
        for j, k in enumerate(kpis):
            if (c, k) not in lab:
                continue
            v = reps[i, :, j][np.isfinite(reps[i, :, j])]
            n = int(v.size)
            mean = float(v.mean()) if n else math.nan
            se = noise.se(k, n)
            m, u, dof_u = lab[(c, k)]
            var = (se if math.isfinite(se) else 0.0) ** 2 + u ** 2
            z = (mean - m) / math.sqrt(var) if n and var > 0 else math.nan
            dof = welch_dof(se if math.isfinite(se) else 0.0, noise.dof[noise.kpis.index(k)], u, dof_u)
            cells.append(Cell(c, k, mean, se, n, m, u, z, (mean - m) / m * 100 if m else math.nan, dof))
    return cells


def discrepancy_of(reps: np.ndarray, conditions: Sequence[str], kpis: Sequence[str],
                   lab: Mapping[tuple[str, str], tuple[float, float]], noise: ReplicateNoise,
                   alpha: float, jammed_runs: Mapping[str, int] | None = None) -> Discrepancy:
    """Step 1 on ``reps [C, r, K]``: the cells (:func:`cells_of`), chi^2 = sum z^2 over the finite ones,
    and the test's p-value from their chi^2-equivalents (:func:`chi2_equivalent`) against chi^2 of as
    many degrees of freedom; significant below ``alpha``. ``jammed_runs``: condition -> runs left out."""
    cells = cells_of(reps, conditions, kpis, lab, noise)
    finite = [c for c in cells if math.isfinite(c.z)]
    chi2 = float(sum(c.z ** 2 for c in finite))
    equivalent = float(sum(chi2_equivalent(c.z, c.dof) for c in finite))
    p = float(stats.chi2.sf(equivalent, len(finite))) if finite else math.nan
    return Discrepancy(tuple(cells), chi2, len(finite), p, bool(finite) and p < alpha, noise, equivalent,
                       dict(jammed_runs or {}))


def expected_chi2_terms(mean: np.ndarray, gp_var: np.ndarray, dem_var: np.ndarray, lab_mean: np.ndarray,
                         lab_var: np.ndarray) -> np.ndarray:
    """chi^2 terms expected under the GP posterior, E[(f - y)^2] / (u^2 + s^2) with
    E[(f - y)^2] = (mu - y)^2 + sigma_GP^2: the GP's uncertainty adds to the misfit (putting it in
    the denominator instead would reward the least known corners of the parameter box)."""
    return ((mean - lab_mean) ** 2 + gp_var) / (dem_var + lab_var)


def must_beat(reference: HypothesisScore, keys: Sequence[tuple[str, str]], mean: np.ndarray, gp_var: np.ndarray,
               dem_var: np.ndarray, lab_mean: np.ndarray, lab_var: np.ndarray, margin: float) -> float:
    """The held-out chi^2 (penalty not counted) a candidate must get below to be named: the
    ``reference``'s score less ``max(margin, 2 x gain_noise_sd)``, the gain's noise sd taken between
    the reference's held-out cells and the cells ``keys`` as the candidate's GP predicts them (means
    ``mean``, standard errors ``sqrt(dem_var)``), as step 3 takes it from the runs."""
    s2 = dem_var + lab_var
    z = np.where(s2 > 0, (mean - lab_mean) / np.sqrt(np.where(s2 > 0, s2, 1.0)), np.nan)
    cells = [Cell(c, k, float(m), math.sqrt(max(float(d), 0.0)), 0, float(y), math.sqrt(max(float(v), 0.0)),
                  float(zc), math.nan)
             for (c, k), m, d, y, v, zc in zip(keys, mean, dem_var, lab_mean, lab_var, z)]
    return reference.score - max(margin, 2 * gain_noise_sd(reference.held_out_cells, cells))


#: Monte Carlo draws of :func:`win_probability` (its resolution is 1 / WIN_SAMPLES).
WIN_SAMPLES = 20_000


def win_probability(mean: np.ndarray, gp_var: np.ndarray, dem_var: np.ndarray, lab_mean: np.ndarray,
                    lab_var: np.ndarray, target: float, seed: int = 0) -> float:
    """Probability, by a fit's own GP, that the held-out chi^2 of its DEM runs falls below ``target``.

    Per held-out cell (arrays over the cells of every left-out condition) the DEM mean will be
    ``f + e``: ``f ~ N(mean, gp_var)``, the GP's posterior at the left-out fit, and ``e ~ N(0,
    dem_var)``, the noise of a mean of the held-out runs. Its chi^2 term is ``(f + e - y)^2 /
    (dem_var + lab_var)``, y the measured mean, as the held-out cells are scored (step 2). The
    cells' GPs are independent (one per cell), so the terms are. Monte Carlo with
    ``WIN_SAMPLES`` draws from a seeded generator: the same fit gets the same answer. A cell with
    no uncertainty at all (``dem_var + lab_var`` 0) is left out. Unlike
    :func:`expected_chi2_terms`, the GP's uncertainty here widens the distribution instead of
    raising its mean, so an uncertain GP is given its chance."""
    arrays = [np.asarray(a, dtype=np.float64).ravel() for a in (mean, gp_var, dem_var, lab_mean, lab_var)]
    mean, gp_var, dem_var, lab_mean, lab_var = arrays
    keep = (dem_var + lab_var) > 0
    if not keep.any():
        return math.nan
    s = np.sqrt(dem_var[keep] + lab_var[keep])
    spread = np.sqrt(np.maximum(gp_var[keep], 0.0) + dem_var[keep])
    draws = np.random.default_rng(seed).standard_normal((WIN_SAMPLES, int(keep.sum())))
    z = (mean[keep] - lab_mean[keep] + spread * draws) / s
    return float(((z ** 2).sum(axis=1) < target).mean())


def fit_resolved(misfit: float, surrogate_chi2: float, cells: int, d: int, alpha: float) -> tuple[bool, float]:
    """``(resolved, p)`` of :func:`fit_check` from a fit's two chi^2 parts (``misfit``: the GP mean's,
    ``surrogate_chi2``: its own uncertainty's) over ``cells`` cells and ``d`` parameters."""
    if cells == 0 or not (math.isfinite(misfit) and math.isfinite(surrogate_chi2)):
        return True, math.nan
    p = float(stats.chi2.sf(misfit + surrogate_chi2, max(cells - d, 1)))
    return bool(p >= alpha or surrogate_chi2 <= cells), p


#: A left-out fit is astray when its DEM held-out chi^2 lies beyond this upper quantile of the
#: noncentral chi^2 its GP predicts (a discovery makes some 30 such checks).
ASTRAY_P = 0.001


def prediction_astray(dem_chi2: float, predicted: float, cells: int) -> bool:
    """Whether the DEM's held-out chi^2 of a left-out fit (``cells`` cells) exceeds its GP's
    prediction beyond noise: above the ``1 - ASTRAY_P`` quantile of a noncentral chi^2 of ``cells``
    degrees of freedom and mean ``predicted`` (noncentrality ``predicted - cells``, at least 0). A
    DEM chi^2 below the prediction never counts: the GP erred on the safe side."""
    if cells == 0 or not (math.isfinite(dem_chi2) and math.isfinite(predicted)):
        return False
    lam = max(predicted - cells, 0.0)
    limit = stats.ncx2.isf(ASTRAY_P, cells, lam) if lam > 0 else stats.chi2.isf(ASTRAY_P, cells)
    return dem_chi2 > max(float(limit), predicted)


def fit_check(h: HypothesisScore, alpha: float) -> tuple[bool, str]:
    """Does ``h``'s fit reproduce the conditions it was fitted on, and if not, is its surrogate to
    blame? Returns ``(resolved, why)``.

    At the parameters fitted on every condition the surrogate's expected chi^2 is
    ``fit_misfit_chi2 + fit_surrogate_chi2`` over ``fit_cells`` cells. When that is consistent with
    ``fit_cells - d`` degrees of freedom (p >= ``alpha``) the fit reproduces its data. When it is
    not, the GP's own uncertainty decides. If it is no larger than the data's
    (``fit_surrogate_chi2 <= fit_cells``), the GP knows where the hypothesis fits best and the
    hypothesis itself cannot reproduce the data (resolved: its held-out runs judge it fairly). If
    it is larger (per cell on average, sigma_GP^2 > s^2 / r + u^2), the design is too sparse to
    say where the hypothesis fits best; its held-out runs were made at a guess, so they cannot rule
    it out (unresolved). A left-out fit astray (``h.astray``) is refined, not judged here: after the
    refinement its held-out runs are the DEM's own evidence at the point its GP then chose."""
    if not h.parameters or h.fit_cells == 0:
        return True, ""
    resolved, p = fit_resolved(h.fit_misfit_chi2, h.fit_surrogate_chi2, h.fit_cells, len(h.parameters), alpha)
    if resolved:
        return True, ""
    dof = max(h.fit_cells - len(h.parameters), 1)
    return False, (f"{h.name}'s surrogate cannot reproduce the conditions it was fitted on (expected chi^2 "
                   f"{h.fit_misfit_chi2 + h.fit_surrogate_chi2:.1f} on {dof} degrees of freedom, p = {p:.2g}, of "
                   f"which {h.fit_surrogate_chi2:.1f} is the GP's own uncertainty at the fit, more than the "
                   f"{h.fit_cells} cells' measurement and DEM uncertainty; {h.points} design points)")


def tied_with(best: HypothesisScore, candidates: Sequence[HypothesisScore], reference: HypothesisScore,
              margin: float) -> list[HypothesisScore]:
    """The candidates that also beat ``reference`` by their own threshold and whose score is within
    ``max(margin, 2 sd)`` of ``best``'s, sd the DEM-noise sd of the two scores' difference
    (:func:`gain_noise_sd` between the two candidates' held-out cells): those the data cannot tell
    from ``best``."""
    out = []
    for h in candidates:
        if h is best or not math.isfinite(h.score):
            continue
        beats = h.score < reference.score - max(margin, 2 * h.gain_noise_sd)
        close = h.score - best.score < max(margin, 2 * gain_noise_sd(best.held_out_cells, h.held_out_cells))
        if beats and close:
            out.append(h)
    return sorted(out, key=lambda h: h.score)


def refit_verdict(refit: HypothesisScore, discrepancy: Discrepancy, settings: DiscoverySettings) -> str:
    """``discovery.refit`` without candidates: does fitting the refit parameters on the other conditions
    predict each condition better than the calibrated set does? The calibrated set's chi^2 on the same
    cells (the discrepancy's, from its runs) against the refit's held-out chi^2, by step 3's rule: the
    refit must gain more than ``max(margin, 2 x the gain's DEM-noise sd)``. The calibrated set was fitted
    on one of these conditions, so the comparison favours it there."""
    before = {(c.condition, c.kpi): c for c in discrepancy.cells}
    cells = [c for c in refit.held_out_cells if (c.condition, c.kpi) in before and math.isfinite(c.z)]
    base = {}
    for c in cells:
        base[c.condition] = base.get(c.condition, 0.0) + before[c.condition, c.kpi].z ** 2
    total = sum(base.values())
    need = max(settings.margin, 2 * refit.gain_noise_sd)
    per = "; ".join(f"{c} {base.get(c, math.nan):.1f} -> {v:.1f}" for c, v in refit.held_out_chi2.items())
    names = ", ".join(settings.refit)
    rule = f"a gain must exceed max(margin {settings.margin:g}, 2 x its DEM-noise sd) = {need:.1f}"
    if refit.score < total - need:
        share, partial, remaining = explained_share(refit, discrepancy, settings.alpha)
        text = (f"Refitting {names} on the other conditions predicts the held-out conditions better than the "
                f"calibrated set: chi^2 {total:.1f} -> {refit.score:.1f} ({per}; {rule}), {100 * share:.0f} % "
                f"less. The misfit lies, at least in part, in the values the calibration gave these parameters on "
                f"its own condition.")
        return text + (f" What is left: {remaining}" if partial else "")
    return (f"Refitting {names} on the other conditions does not predict the held-out conditions better than the "
            f"calibrated set: chi^2 {total:.1f} -> {refit.score:.1f} ({per}; {rule}). Within their ranges "
            f"(+- {100 * settings.refit_fraction:g} %), the misfit is not in the values the calibration gave them.")


def explained_share(cause: HypothesisScore, discrepancy: Discrepancy, alpha: float) -> tuple[float, bool, str]:
    """Share of the calibrated model's chi^2 on the held-out cells that ``cause`` removes, whether
    the extended model still misses beyond noise there (its held-out chi^2-equivalent against a
    chi^2 of as many cells, below ``alpha``: a partial cause) and, if so, what remains."""
    before = {(c.condition, c.kpi): c for c in discrepancy.cells}
    cells = [c for c in cause.held_out_cells if (c.condition, c.kpi) in before and math.isfinite(c.z)]
    base = sum(before[c.condition, c.kpi].z ** 2 for c in cells)
    after = sum(c.z ** 2 for c in cells)
    share = 1.0 - after / base if base > 0 else math.nan
    q = sum(chi2_equivalent(c.z, c.dof) for c in cells)
    p = float(stats.chi2.sf(q, len(cells))) if cells else math.nan
    if not (cells and p < alpha):
        return share, False, ""
    worst = sorted(cells, key=lambda c: -abs(c.z))[:3]
    remaining = (f"with it the held-out cells still disagree beyond noise (chi^2 {after:.1f} on {len(cells)} cells, "
                 f"p = {p:.3g}); largest: " + ", ".join(f"{c.kpi} on {c.condition} {c.relative_error_pct:+.1f} % "
                                                         f"(z {c.z:+.1f})" for c in worst) + ".")
    return share, True, remaining


def gain_noise_sd(reference: Sequence[Cell], candidate: Sequence[Cell]) -> float:
    """Standard deviation of ``sum z_ref^2 - sum z_cand^2`` over the cells both have, from DEM
    noise alone when both predict the same means (``bo.discovery.pipeline``'s docstring, step 3); inf
    when a cell's DEM standard error is unknown while the cells differ."""
    ref = {(c.condition, c.kpi): c for c in reference}
    var = 0.0
    for b in candidate:
        a = ref.get((b.condition, b.kpi))
        if a is None or not (math.isfinite(a.z) and math.isfinite(b.z)):
            continue
        m = 0.5 * ((a.dem_mean - a.measured_mean) + (b.dem_mean - b.measured_mean))
        for c in (a, b):
            se = c.dem_se if math.isfinite(c.dem_se) else 0.0
            s2 = se ** 2 + c.measured_u ** 2
            if s2 > 0:
                var += 4 * m ** 2 * se ** 2 / s2 ** 2 + 2 * se ** 4 / s2 ** 2
    return math.sqrt(var)


def gain_rows(chosen: HypothesisScore, baseline: Discrepancy) -> list[GainRow]:
    """Step 4: every held-out cell of ``chosen`` next to the calibrated model's cell."""
    before = {(c.condition, c.kpi): c for c in baseline.cells}
    rows = []
    for a in chosen.held_out_cells:
        b = before.get((a.condition, a.kpi))
        if b is None:
            continue
        rows.append(GainRow(a.condition, a.kpi, a.measured_mean, a.measured_u, b.dem_mean, b.dem_se, a.dem_mean,
                            a.dem_se, b.relative_error_pct, a.relative_error_pct, b.z, a.z))
    return rows
