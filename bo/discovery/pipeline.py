"""Model discovery: where a calibrated model disagrees with the measurements, which candidate
mechanism explains it, and what that mechanism gains on conditions it was not fitted on.

Contract
--------
``run_discovery(store, executor_for, model, calibrated, measured, settings)`` works through the
campaign store (``bo.campaign.store``; resumable, nothing repeated) in four steps; ``executor_for(model)``
returns an executor (``bo.campaign.executor``) that evaluates a ``torchdem.model.DrawDownModel``.

1. Discrepancy (stage ``discrepancy``): the calibrated model on every measured condition with
   ``settings.seeds``. For every condition c and KPI k: DEM mean and its standard error
   ``se = s_k / sqrt(r)``, the measured mean and its standard uncertainty ``u``
   (``Condition.standard_uncertainty``: ``ci95 / t(0.975, n - 1)`` with n - 1 degrees of freedom
   when the data state the n lab repeats, else ``ci95 / 1.96``), and
   ``z = (DEM - lab) / sqrt(se^2 + u^2)``. Both variances are estimates, so under the null z is
   Student-t with the Welch-Satterthwaite degrees of freedom
   ``nu = (se^2 + u^2)^2 / (se^4 / dof_s + u^4 / dof_u)``, not normal: each z is mapped to the
   chi^2_1 value of the same tail probability, ``q = chi2_1.isf(2 t_nu.sf(|z|))``, and
   ``sum q`` over the cells, against a chi^2 distribution of as many degrees of freedom, is the
   probability that measurement uncertainty and DEM stochasticity alone explain the
   disagreement (uniform under the null: tests/test_discovery_calibration.py); the discrepancy is
   ``significant`` when it is below ``settings.alpha``. ``chi2`` reports ``sum z^2``. ``s_k`` is the DEM
   replicate scatter of KPI k pooled over groups of replicates (``bo.discovery.replicate_noise``; a cell's
   own 2 or 3 runs give a standard error too noisy to divide by): for this test, over the
   discrepancy runs of every condition.
2. Hypotheses (stage ``discovery-<name>``): ``parameters`` (the calibrated parameters named in
   ``settings.refit`` free within ``+- refit_fraction`` of their value; no new physics) and every
   candidate of the registry (``torchdem.mechanisms``; ``settings.candidates`` or all available), each
   with its extra parameters and prior ranges plus the refit ones. With no candidate
   (``candidates`` empty) and ``refit`` given, ``parameters`` is fitted alone and
   :func:`refit_verdict` says whether it predicts the held-out conditions better than the calibrated
   set: whether the misfit lies in the values a one-condition calibration gave those parameters
   (the model's parameters, calibrated or held). Per hypothesis: a Latin
   hypercube of ``max(min_points, points_per_parameter x d)`` points, each run on every condition
   with ``fit_seeds``, and one GP per (condition, KPI) (``bo.surrogate.gp``, per-output strategy).
   Leave-one-condition-out: for each condition c, the parameters that minimise the chi^2 of the
   other conditions (the GP's expected chi^2, minimised by ``bo.surrogate.search``, or the GA of
   ``bo.surrogate.ga`` with ``fit_search="ga"``) are run with the DEM on c (``settings.seeds``); the
   held-out chi^2 of c is that of these runs against the measurement (as in step 1). The surrogate
   only fits; it never scores (a poor GP's wide predictive variance would flatter its hypothesis;
   its prediction is reported as ``predicted_chi2``). A hypothesis with no free parameter
   (``parameters`` with ``refit`` empty) is the calibrated model itself, scored on the
   discrepancy runs. Score = sum of held-out chi^2 + ``penalty`` x (parameters it adds beyond the
   ``parameters`` hypothesis) (an AIC-like penalty). Every held-out chi^2, and the discrepancy
   reported, use one noise estimate ``s_k`` pooled over every run of the discovery (discrepancy,
   design and refinement points, held-out runs of every hypothesis), so no hypothesis is scored with
   a luckier noise estimate than another. One exception: when a fit is refined (step 3), the held-out
   runs of the round its refinement replaced are not pooled, only those of the round it is scored
   on (rules 1-5; pooling them too would add their degrees of freedom and change stored outcomes,
   so it would be a new rules version). The GP's noise is the design's pooled ``s_k^2 / fit replicates``
   (learned by the GP when the design runs each point once). The fits minimise the chi^2 the
   held-out runs are scored by: per cell ``((mu - y)^2 + sigma_GP^2) / (s_k^2 / r + u^2)`` with r
   the held-out replicates and ``s_k`` pooled over the discrepancy runs and the design's replicates.
   Held-out runs only where they can change the verdict: a candidate whose fit is resolved and whose
   own GP gives it a probability below ``prune_probability`` of scoring below the ``parameters``
   hypothesis less step 3's threshold (:func:`win_probability`; the GP's posterior and the held-out
   runs' noise, the threshold's noise sd from its predicted cells) makes none: it is reported with
   its GP's predicted score, ``pruned``, and can be neither named nor tied. Nor does a fit that is
   unresolved and about to be refined (below): its verdict waits on the refined fits' runs.
3. Cause: none while the discrepancy, with the noise pooled over every run, is not significant;
   else the candidate with the lowest score, if it beats the ``parameters`` hypothesis by more
   than ``max(margin, 2 x gain_noise_sd)``; else none: no candidate explains the discrepancy
   better than the parameters and noise. If another candidate also beats it so and lies within
   ``max(margin, 2 sd)`` of the best (sd: the DEM-noise sd of the two scores' difference), the
   candidates cannot be told apart: none is named and ``DiscoveryResult.tied`` lists them
   (:func:`tied_with`). Nor is one named while another candidate's fit is unresolved: its
   surrogate, at the parameters fitted on every condition, cannot reproduce those conditions
   and its own uncertainty there exceeds the data's (:func:`fit_check`); its held-out runs were
   made at a guess and cannot rule it out (``DiscoveryResult.unresolved``). Before the verdict,
   a fit so unresolved, or one with a left-out fit astray (its DEM runs miss the held-out
   condition far beyond its GP's prediction, :func:`prediction_astray`), is refined
   ``escalations`` times: the DEM runs the points its fits chose, on every condition, and the GP,
   the fits and the held-out runs are made again. A named cause comes with the share of the calibrated model's chi^2 it
   removes on the held-out cells and, when the extended model still misses there beyond noise,
   the statement that it is partial and what remains (:func:`explained_share`). ``gain_noise_sd`` is the standard deviation the score
   difference would have from DEM noise alone if both hypotheses predicted the same means: per
   cell, z = (m + e) / s with e ~ N(0, se^2) has Var(z^2) = 4 (m/s)^2 (se/s)^2 + 2 (se/s)^4; the
   two hypotheses' held-out runs are independent, so their variances add, with m the mean of the
   two offsets (the measurement is common to both and cancels). Where the model misses a cell by
   many standard errors, noise alone moves that cell's z^2 by tens, and a fixed margin would
   name whichever candidate's runs happened to land closer. If the discrepancy is not
   significant, no hypothesis is fitted (unless ``always_score``) and the cause is none.
4. Gain: the chosen mechanism's held-out runs of step 2 next to the calibrated model's runs of
   step 1: error per KPI and condition before and after, each with its uncertainty. The
   mechanism's values fitted on all conditions are the extension (``DiscoveryResult.extension``).

Jammed runs. A run whose discharge jammed (``discharge_jammed`` 1: the grains arched over the slot,
:data:`torchdem.drawdown.JAM_FRACTION`) measured no discharge: its flow and level surfaces read 0. As
in the calibration's verification (``bo.calibration.pipeline.agreement``), such a run is left out of
every KPI mean, of the GPs' data and of the pooled noise, and counted (``Discrepancy.jammed``,
``HypothesisScore.jammed_design`` and ``jammed_held_out``, condition -> runs); averaged in, one such
run would move a held-out flow by a third and the pooled replicate scatter of every KPI many times
over, and with it every z of every hypothesis. A condition whose held-out runs all jammed has no
prediction: its held-out chi^2 is infinite, as for runs that failed.

The statistics of these steps (the cells, the test, the fits' chi^2 and the rules from the scores to
a cause) are plain functions of numbers in ``bo.discovery.verdict``; this module runs the DEM through
the store and calls them. Everything returned is plain data; ``bo.discovery.report`` writes
``discovery.json`` and figures.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import warnings
from dataclasses import dataclass
from typing import Callable, Mapping, Sequence

import numpy as np

from kpi.loadcell import discharge_jammed
from bo.surrogate.acquisition import latin_hypercube
from torchdem.model import DrawDownModel
from bo.campaign.executor import Executor, run_pending
from bo.surrogate.ga import GASettings, minimise_surrogate
from bo.surrogate.search import multistart_minimum
from torchdem.mechanisms import Mechanism, ModelContext, model_context, registry
from bo.surrogate.objective import ObjectiveSpec
from bo.discovery.replicate_noise import ReplicateNoise
from bo.discovery.verdict import (Cell, Discrepancy, GainRow, HypothesisScore, cells_of, discrepancy_of,
                                  expected_chi2_terms, explained_share, fit_check, fit_resolved, gain_noise_sd,
                                  gain_rows, must_beat, prediction_astray, refit_verdict, tied_with, win_probability)
from bo.screening.pipeline import measured_for, measured_name
from bo.campaign.store import CampaignStore, EvaluationRecord
from bo.surrogate.gp import SurrogateConfig, fit_surrogate
from torchdem.errors import ConfigError, out_of_range
from torchdem.measured import MeasuredData

__all__ = ["PARAMETERS", "VERDICT_RULES", "rules_of", "DiscoverySettings", "DiscoveryResult", "discovery_stages",
           "measure_discrepancy", "run_discovery", "detectability", "refit_bounds"]

#: Name of the no-new-physics hypothesis (the calibrated parameters refitted).
PARAMETERS = "parameters"


class JammedDesign(ConfigError):
    """A candidate's design has too few points that flowed on every condition to be fitted, because
    its runs jammed: the candidate is left out of the verdict with this reason."""


#: Version of the rules from the discrepancy to the verdict. A power study keys each twin's outcome
#: by it (``bo.discovery.power``), so outcomes of older rules are neither mixed with newer ones nor
#: silently reused. 1: the fits weighed each cell by the lab's uncertainty alone when the design
#: ran each point once, and there was no fit check; 2: the DEM noise of the held-out mean in every
#: fit's chi^2, and :func:`fit_check`; 3: each fit searched by a Sobol sample and L-BFGS-B polish
#: (``fit_search="multistart"``) instead of three GA runs; 4: a fit left unresolved by
#: :func:`fit_check` has the DEM run the points it chose and is refitted (``escalations`` times)
#: before the verdict; 5: a candidate whose own GP gives it less than ``prune_probability`` of beating
#: the ``parameters`` hypothesis by the margin is not run on its held-out conditions
#: (:func:`win_probability`), nor is an unresolved fit before its refinement.
VERDICT_RULES = 5


def rules_of(settings: "DiscoverySettings") -> int:
    """The verdict rules a discovery with ``settings`` applies: ``VERDICT_RULES``, or 4 with
    ``prune_probability`` 0 (every fit then runs on its held-out conditions, an unresolved one also
    before its refinement: those runs' scatter joins the pooled noise every score is divided by, so
    rules 4 are kept whole, not mixed with 5)."""
    return VERDICT_RULES if settings.prune_probability > 0 else 4


def discovery_stages(names: Sequence[str] | None = None) -> tuple[str, ...]:
    """Store stages discovery uses (for ``CampaignStore(extra_stages=...)``)."""
    names = sorted(registry()) if names is None else list(names)
    return ("discrepancy", f"discovery-{PARAMETERS}", *(f"discovery-{n}" for n in names))


@dataclass(frozen=True)
class DiscoverySettings:
    """Settings of ``run_discovery`` (see the module docstring).

    Attributes:
        kpis: DEM KPI names compared (each needs a measurement in some condition).
        seeds: replicates of the discrepancy and gain runs. fit_seeds: replicates of every
            hypothesis design point.
        candidates: registry names tried; None: every mechanism available for the model; ():
            the discrepancy only.
        refit: calibrated parameters free in every hypothesis; refit_fraction: their range,
            ``value x (1 +- fraction)`` (friction >= 0, restitution in (0, 1]).
        points_per_parameter, min_points: design size per hypothesis.
        escalations: times a hypothesis whose fit is unresolved (:func:`fit_check`) has the DEM
            run the points its fits chose (on every condition and each left-out one, with
            ``fit_seeds``) and its GP refitted with them before it is scored. Unlike the design,
            these runs depend on the data.
        alpha: significance of the discrepancy test. penalty: held-out chi^2 per added
            parameter. margin: held-out chi^2 a cause must gain over the parameters hypothesis.
        always_score: fit the hypotheses even without a significant discrepancy.
        fit_search: how each fit minimises the GP's expected chi^2: ``"multistart"`` (a Sobol
            sample of ``search_samples`` points, the ``fit_starts`` best distinct ones polished by
            L-BFGS-B; ``bo.surrogate.search``) or ``"ga"`` (``fit_starts`` independent runs of the GA
            ``ga``, seeds ``seed + k``); the best kept. kernel: GP kernel. seed: LHS, Sobol and GA seed.
        proposed_kpis: DEM KPIs the lab does not report (the heap height, say) that "what to
            measure next" weighs as additions; each candidate's design runs measure them, its GP
            models them, and the lab is assumed to measure them as repeatably as the DEM does.
        proposed_conditions: conditions of the model the lab has not measured (another mass ratio,
            the reverse layering) that "what to measure next" weighs as additions, each measured
            on the compared KPIs; every candidate's design also runs on them (its DEM cost grows
            by their number over the measured conditions'), its GP models them, and the lab is
            assumed to measure them with the median standard uncertainty of its measured conditions.
        prune_probability: a candidate whose fit is resolved and whose own GP gives it a
            probability below this of scoring better than the ``parameters`` hypothesis by
            ``margin`` (:func:`win_probability`) is not run on its held-out conditions: it could
            not be named, and on an expensive geometry its held-out runs are a third of its
            cost. 0 (the default): every candidate is run. On the mini box's 210 power-study twins
            0.01 pruned the true cause in 45 of the 180 twins with an effect (its GP is more
            certain than its runs bear out), and the right cause was named in 34 instead of 39.
    """

    kpis: tuple[str, ...]
    seeds: tuple[int, ...] = (0, 1, 2)
    fit_seeds: tuple[int, ...] = (0, 1)
    candidates: tuple[str, ...] | None = None
    refit: tuple[str, ...] = ()
    refit_fraction: float = 0.2
    points_per_parameter: int = 5
    min_points: int = 6
    escalations: int = 1
    alpha: float = 0.05
    penalty: float = 2.0
    margin: float = 4.0
    always_score: bool = False
    ga: GASettings = GASettings(pop_size=200, n_generations=200, stall_generations=30)
    kernel: str = "matern52"
    seed: int = 0
    fit_starts: int = 3
    fit_search: str = "multistart"
    search_samples: int = 1024
    proposed_kpis: tuple[str, ...] = ("max_heap_height_m",)
    proposed_conditions: tuple[str, ...] = ()
    prune_probability: float = 0.0

    def validate(self, source: str = "discovery") -> "DiscoverySettings":
        if isinstance(self.proposed_kpis, str) or len(set(self.proposed_kpis)) != len(self.proposed_kpis):
            raise out_of_range("proposed_kpis", self.proposed_kpis, "a list of distinct DEM KPI names", source)
        if isinstance(self.proposed_conditions, str) \
                or len(set(self.proposed_conditions)) != len(self.proposed_conditions) \
                or not all(isinstance(c, str) and c for c in self.proposed_conditions):
            raise out_of_range("proposed_conditions", self.proposed_conditions,
                               "a list of distinct condition names of the model", source)
        if not self.kpis or len(set(self.kpis)) != len(self.kpis):
            raise out_of_range("kpis", self.kpis, "a non-empty list of distinct DEM KPI names", source)
        for name in ("seeds", "fit_seeds"):
            s = getattr(self, name)
            if not s or len(set(s)) != len(s):
                raise out_of_range(name, s, "a non-empty list of distinct seeds", source)
        if not 0 < self.refit_fraction < 1:
            raise out_of_range("refit_fraction", self.refit_fraction, "a fraction in (0, 1)", source)
        if not 0 < self.alpha < 1:
            raise out_of_range("alpha", self.alpha, "a probability in (0, 1)", source)
        if not (isinstance(self.prune_probability, (int, float)) and 0 <= self.prune_probability < 1):
            raise out_of_range("prune_probability", self.prune_probability, "a probability in [0, 1) (0: never "
                               "prune)", source)
        for name in ("penalty", "margin"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise out_of_range(name, getattr(self, name), "a finite number >= 0", source)
        if isinstance(self.fit_starts, bool) or not isinstance(self.fit_starts, int) or self.fit_starts < 1:
            raise out_of_range("fit_starts", self.fit_starts, "an integer >= 1", source)
        if self.fit_search not in ("multistart", "ga"):
            raise out_of_range("fit_search", self.fit_search, "'multistart' or 'ga'", source)
        if isinstance(self.search_samples, bool) or not isinstance(self.search_samples, int) \
                or self.search_samples < 16:
            raise out_of_range("search_samples", self.search_samples, "an integer >= 16", source)
        if isinstance(self.escalations, bool) or not isinstance(self.escalations, int) or self.escalations < 0:
            raise out_of_range("escalations", self.escalations, "an integer >= 0", source)
        for name in ("points_per_parameter", "min_points"):
            if isinstance(getattr(self, name), bool) or not isinstance(getattr(self, name), int) \
                    or getattr(self, name) < 2:
                raise out_of_range(name, getattr(self, name), "an integer >= 2", source)
        return self


@dataclass(frozen=True)
class DiscoveryResult:
    """Everything ``run_discovery`` found (plain data); ``tied``: the candidates that each explain
    the discrepancy but that the data cannot tell apart (no cause is then named); ``unresolved``:
    the candidates whose surrogate could not reproduce the conditions it was fitted on
    (:func:`fit_check`), which therefore cannot be ruled out."""

    discrepancy: Discrepancy
    hypotheses: tuple[HypothesisScore, ...]
    cause: str | None
    explanation: str
    gain: tuple[GainRow, ...]
    extension: Mapping[str, float]
    evaluations: Mapping[str, int]
    tied: tuple[str, ...] = ()
    unresolved: tuple[str, ...] = ()


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------

def _key(*parts) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=repr).encode()).hexdigest()[:12]


#: Two points a fit chose are the same experiment when each fitted parameter agrees within this
#: share of its range: the DEM's scatter is far larger than such a step, while the fit itself,
#: computed again on another machine (another BLAS, another vector width), moves in the 12th digit.
SAME_POINT = 1e-6


def _fitted_batch(store: CampaignStore, stage: str, key: str, points: Sequence[Mapping[str, float]],
                  seeds: Sequence[int], conditions: Sequence[str], names: Sequence[str],
                  b: np.ndarray) -> tuple[str, list[dict[str, float]]]:
    """Key and points of a batch of fitted points: a stored batch of the same kind (``key`` up to its
    last ``/``) and the same experiment (:data:`SAME_POINT`, ``CampaignStore.near_batch``) with its
    stored points, so that a resumed or repeated analysis runs nothing again and goes on from the
    very points it ran; else ``key`` (hashed from the points) with ``points``."""
    tolerance = {n: SAME_POINT * float(hi - lo) for n, lo, hi in zip(names, b[0], b[1])}
    found = store.near_batch(stage, key[:key.rindex("/") + 1], points, seeds=list(seeds),
                             conditions=list(conditions), tolerance=tolerance)
    return found if found is not None else (key, [dict(p) for p in points])


def _lab(measured: MeasuredData, kpis: Sequence[str]) -> dict[tuple[str, str], tuple[float, float, float]]:
    """(condition, DEM KPI) -> (measured mean, standard uncertainty, its degrees of freedom), measured
    cells only (``Condition.standard_uncertainty``)."""
    out = {}
    for c in measured.names:
        condition = measured.condition(c)
        for kpi, value in measured_for(kpis, condition.kpis).items():
            u, dof = condition.standard_uncertainty(measured_name(kpi))
            out[(c, kpi)] = (float(value.mean), float(u), float(dof))
    return out


def _run(store: CampaignStore, executor: Executor, stage: str, key: str, points: Sequence[Mapping[str, float]],
         seeds: Sequence[int], conditions: Sequence[str], kpis: Sequence[str]) -> np.ndarray:
    """Run (resume) a batch; ``[n_points, n_conditions, r, K]`` KPI values (NaN: failed/unmeasured)."""
    return _run_together(store, executor, stage, [(key, points, seeds, conditions)], kpis)[0]


def _run_together(store: CampaignStore, executor: Executor, stage: str,
                  batches: Sequence[tuple[str, Sequence[Mapping[str, float]], Sequence[int], Sequence[str]]],
                  kpis: Sequence[str]) -> list[np.ndarray]:
    """Run (resume) several batches ``(key, points, seeds, conditions)`` of one stage at once, so
    that every worker of the executor has work (one condition's few held-out runs fill one worker;
    run one after the other, the conditions of a hypothesis left the others idle). Returns each
    batch's ``[n_points, n_conditions, r, K]`` KPI values (NaN: failed/unmeasured)."""
    stored = [store.batch(stage, key, lambda points=points: [dict(p) for p in points], seeds=list(seeds),
                          conditions=list(conditions)) for key, points, seeds, conditions in batches]
    run_pending(store, executor, stage)
    return [_collect(store, stage, key, len(points), seeds, conditions, kpis)
            for points, (key, _, seeds, conditions) in zip(stored, batches)]


def _collect(store: CampaignStore, stage: str, key: str, n_points: int, seeds: Sequence[int],
             conditions: Sequence[str], kpis: Sequence[str]) -> np.ndarray:
    """The stored KPIs of a batch, ``[n_points, n_conditions, r, K]`` (NaN: failed, unmeasured or
    jammed: a jammed run measured no discharge, module docstring)."""
    out = np.full((n_points, len(conditions), len(seeds), len(kpis)), np.nan)
    ci = {c: i for i, c in enumerate(conditions)}
    si = {s: i for i, s in enumerate(seeds)}
    for rec in store.records(stage, batch_key=key, status="done"):
        if rec.condition in ci and rec.seed in si and rec.kpis is not None and not discharge_jammed(rec.kpis):
            out[rec.point_index, ci[rec.condition], si[rec.seed]] = [rec.kpis.get(k, math.nan) for k in kpis]
    out[~np.isfinite(out)] = np.nan
    return out


def jam_counts(counts: Mapping[str, int]) -> str:
    """``"50-50 2, 25-75 1"`` for condition -> jammed runs (``"none"`` when empty)."""
    return ", ".join(f"{c} {n}" for c, n in counts.items()) or "none"


def jammed_runs_note(h: "HypothesisScore") -> str:
    """Where a hypothesis's runs jammed, for the echo and the report (empty when none did)."""
    if not (h.jammed_design or h.jammed_held_out):
        return ""
    return (f"{h.name}: runs whose discharge jammed, left out of its GPs and means: design "
            f"{jam_counts(h.jammed_design)}; held out {jam_counts(h.jammed_held_out)}")


def _jams(store: CampaignStore, stage: str, keys: Sequence[str]) -> dict[str, int]:
    """Condition -> done runs of the batches ``keys`` of ``stage`` whose discharge jammed (only
    conditions with such runs)."""
    out: dict[str, int] = {}
    for key in keys:
        for rec in store.records(stage, batch_key=key, status="done"):
            if rec.kpis is not None and discharge_jammed(rec.kpis):
                out[rec.condition] = out.get(rec.condition, 0) + 1
    return out


def _unmeasured(reps: np.ndarray, condition: str, kpis: Sequence[str],
                lab: Mapping[tuple[str, str], tuple[float, float]]) -> list[str]:
    """Measured KPIs of ``condition`` that no run of ``reps [r, K]`` gave."""
    return [k for j, k in enumerate(kpis) if (condition, k) in lab and not np.isfinite(reps[:, j]).any()]


# --------------------------------------------------------------------------------------------
# step 1
# --------------------------------------------------------------------------------------------

BASELINE_RUNS = 2
"""Runs of the calibrated set made elsewhere that a condition needs to take them as its discrepancy runs."""


def runs_of_set(records: Sequence[EvaluationRecord], calibrated: Mapping[str, float],
                conditions: Sequence[str], rel: float = 1e-9) -> dict[str, list[EvaluationRecord]]:
    """The done runs among ``records`` (of another store, the same model) made at the calibrated set:
    every parameter a run names has the calibrated value (within ``rel``; the calibration stores only
    its own parameters, the rest being the model's fixed ones), grouped by condition (those of
    ``conditions`` only), one run per seed (the first)."""
    out: dict[str, dict[int, EvaluationRecord]] = {c: {} for c in conditions}
    for r in records:
        if r.status != "done" or r.kpis is None or r.condition not in out or not r.params:
            continue
        if all(k in calibrated and math.isclose(float(v), float(calibrated[k]), rel_tol=rel, abs_tol=1e-12)
               for k, v in r.params.items()):
            out[r.condition].setdefault(r.seed, r)
    return {c: list(runs.values()) for c, runs in out.items()}


def measure_discrepancy(store: CampaignStore, executor: Executor, calibrated: Mapping[str, float],
                        measured: MeasuredData, settings: DiscoverySettings,
                        baseline: tuple[str, Mapping[str, Sequence[EvaluationRecord]]] | None = None
                        ) -> tuple[Discrepancy, np.ndarray]:
    """Step 1 (see the module docstring), with the replicate noise pooled over these runs; also
    returns the replicates ``[C, r, K]`` (NaN beyond a condition's runs). ``baseline``: (its store's
    path, condition -> runs of the calibrated set made there, :func:`runs_of_set`): a condition with
    at least ``BASELINE_RUNS`` such runs takes them instead of running ``settings.seeds`` (they are imported into
    this store, :meth:`CampaignStore.adopt`); the others run as usual."""
    conditions = list(measured.names)
    source, given = baseline if baseline is not None else ("", {})
    adopted = [c for c in conditions if len(given.get(c, ())) >= BASELINE_RUNS]
    ran = [c for c in conditions if c not in adopted]
    parts: dict[str, np.ndarray] = {}
    keys: list[str] = []
    if ran:
        key = "calibrated/" + _key(sorted(calibrated.items()), list(settings.seeds), ran)
        keys.append(key)
        reps = _run(store, executor, "discrepancy", key, [dict(calibrated)], settings.seeds, ran,
                    settings.kpis)[0]
        parts.update({c: reps[i] for i, c in enumerate(ran)})
    for c in adopted:
        seeds = sorted(r.seed for r in given[c])
        key = "calibrated/" + _key(sorted(calibrated.items()), seeds, [c], "adopted")
        keys.append(key)
        store.batch("discrepancy", key, lambda: [dict(calibrated)], seeds=seeds, conditions=[c])
        store.adopt("discrepancy", key, given[c], source)
        parts[c] = _collect(store, "discrepancy", key, 1, seeds, [c], settings.kpis)[0, 0]
    width = max(len(v) for v in parts.values())
    reps = np.full((len(conditions), width, len(settings.kpis)), np.nan)
    for i, c in enumerate(conditions):
        reps[i, :len(parts[c])] = parts[c]
    discrepancy = discrepancy_of(reps, conditions, settings.kpis, _lab(measured, settings.kpis),
                               ReplicateNoise.of(settings.kpis, [reps]), settings.alpha,
                               _jams(store, "discrepancy", keys))
    if not discrepancy.dof:
        failed = store.records("discrepancy", batch_key=key, status="failed")
        if failed:  # the runs failed: say so (and why), not that the KPIs do not match
            raise RuntimeError(f"discrepancy: {len(failed)} DEM run(s) of the calibrated model failed and none gave "
                               f"a KPI; the first ({failed[0].condition}, seed {failed[0].seed}): {failed[0].error} "
                               f"(all errors in {store.path}, table evaluations)")
        raise ConfigError(f"discrepancy: no KPI of {list(settings.kpis)} was both simulated and measured; measured "
                          f"KPIs: {sorted({k for c in measured.names for k in measured.condition(c).kpis})}")
    return discrepancy, reps


# --------------------------------------------------------------------------------------------
# step 2
# --------------------------------------------------------------------------------------------

def refit_bounds(calibrated: Mapping[str, float], names: Sequence[str], fraction: float) -> dict[str, tuple]:
    """``{name: (low, high)}``: each ``discovery.refit`` parameter free within ``+- fraction`` of its
    calibrated value (restitution capped at 1, never below 0). A name the calibrated set lacks raises
    ``ConfigError``, so torchdem-discover and :func:`run_discovery` check it before the first run."""
    out = {}
    for n in names:
        if n not in calibrated:
            raise ConfigError(f"discovery.refit: {n!r} is not a calibrated parameter; calibrated: {sorted(calibrated)}")
        v = float(calibrated[n])
        lo, hi = v * (1 - fraction), v * (1 + fraction)
        if n.startswith("e_"):
            hi = min(hi, 1.0)
        out[n] = (max(lo, 0.0), hi) if hi > max(lo, 0.0) else (0.0, max(fraction, 1e-6))
    return out


@dataclass(frozen=True)
class _Fitted:
    """Step 2 for one hypothesis before it is scored: ``hypothesis`` without its held-out chi^2
    and score (those need the noise pooled over every hypothesis), ``held_reps`` condition ->
    ``[r, K]`` held-out replicates (the discrepancy runs for a hypothesis without free
    parameters), and ``groups``, replicate groups ``[..., r, K]`` of its runs for the pooled noise."""

    hypothesis: HypothesisScore
    held_reps: Mapping[str, np.ndarray]
    groups: tuple[np.ndarray, ...]
    predict: Callable[[Sequence[Mapping[str, float]]], list[dict[tuple[str, str], float]]] | None = None
    proposed_sd: Mapping[str, float] = dataclasses.field(default_factory=dict)


def _fit_hypothesis(name: str, mechanism: Mechanism | None, model: DrawDownModel, context: ModelContext,
                    store: CampaignStore, executor_for: Callable[[DrawDownModel], Executor],
                    calibrated: Mapping[str, float], measured: MeasuredData, settings: DiscoverySettings,
                    baseline_reps: np.ndarray, echo: Callable[[str], None],
                    reference: HypothesisScore | None = None) -> _Fitted:
    """Step 2 for one hypothesis. ``reference``: the ``parameters`` hypothesis, scored; with it, a
    resolved fit whose own GP gives it less than ``settings.prune_probability`` of beating it as
    step 3 requires makes no held-out runs (pruned, :func:`win_probability`)."""
    conditions = list(measured.names)
    kpis = list(settings.kpis)
    lab = _lab(measured, kpis)
    bounds = refit_bounds(calibrated, settings.refit, settings.refit_fraction)
    extra = {} if mechanism is None else dict(mechanism.parameters(context))
    bounds.update(extra)
    names = tuple(bounds)
    description = "the calibrated parameters refitted, no new physics" if mechanism is None else mechanism.description
    if not names:  # the calibrated model as is: its held-out runs are the discrepancy runs
        return _Fitted(HypothesisScore(name, description, (), {}, 0, {}, {c: {} for c in conditions}, {}, math.nan,
                                       math.nan, 0), {c: baseline_reps[i] for i, c in enumerate(conditions)}, ())
    b = np.array([[bounds[n][0] for n in names], [bounds[n][1] for n in names]], dtype=np.float64)
    size = max(settings.min_points, settings.points_per_parameter * len(names))
    hyp_model = model if mechanism is None else mechanism.apply(model)
    # a candidate's design also runs on the proposed conditions (a batch of its own, so that a
    # store's design batches stay as they are)
    unmeasured = list(settings.proposed_conditions) if mechanism is not None else []
    read = kpis + [k for k in settings.proposed_kpis if k not in kpis and mechanism is not None]
    cells = [(i, c, j, k) for i, c in enumerate(conditions) for j, k in enumerate(kpis) if (c, k) in lab]
    lab_mean = np.array([lab[(c, k)][0] for _, c, _, k in cells])
    lab_var = np.array([lab[(c, k)][1] ** 2 for _, c, _, k in cells])
    output_names = tuple(f"{c}|{k}" for _, c, _, k in cells)
    spec = ObjectiveSpec(output_names, tuple(np.where(lab_mean == 0, 1.0, lab_mean)), source=f"hypothesis {name}")
    cond_of = np.array([c for _, c, _, _ in cells])
    X = np.zeros((0, len(names)))
    every_run = None
    design_keys: list[str] = []
    X_new = latin_hypercube(b, size, seed=settings.seed)
    for round_ in range(settings.escalations + 1):
        # Round 0 is the design: it does not depend on the data, so it runs once in a store and every
        # data set reuses it. Each later round (only while the fit is unresolved) runs the points the
        # fits chose, where the GP knew too little: the fit on every condition and each left-out fit.
        points = [{**calibrated, **dict(zip(names, map(float, x)))} for x in X_new]
        if round_ == 0:
            design_key = f"lhs/{_key(names, b.tolist(), size, settings.seed)}"
        else:
            design_key, points = _fitted_batch(
                store, f"discovery-{name}", f"refine/{_key(names, X_new.tolist(), list(settings.fit_seeds))}", points,
                settings.fit_seeds, conditions, names, b)
            X_new = np.array([[p[n] for n in names] for p in points])
        design_keys.append(design_key)
        with executor_for(hyp_model) as executor:
            design = [(design_key, points, settings.fit_seeds, conditions)]
            if unmeasured:
                design.append((f"{design_key}/conditions/{_key(unmeasured)}", points, settings.fit_seeds, unmeasured))
            runs = np.concatenate(_run_together(store, executor, f"discovery-{name}", design, read), axis=1)
        X = np.concatenate([X, X_new])
        every_run = runs if every_run is None else np.concatenate([every_run, runs])
        n_points = X.shape[0]
        reps = every_run[:, :len(conditions), :, :len(kpis)]  # [points, measured conditions, seeds, compared KPIs]
        # outputs: measured (condition, KPI) cells; y = replicate means, y_var = variance of the mean
        counts = np.stack([np.isfinite(reps[:, i, :, j]).sum(axis=1) for i, _, j, _ in cells], axis=1)
        with warnings.catch_warnings():  # a point with no finite replicate: NaN, not usable
            warnings.simplefilter("ignore", RuntimeWarning)
            Y = np.stack([np.nanmean(reps[:, i, :, j], axis=1) for i, _, j, _ in cells], axis=1)
        usable = (counts >= min(2, len(settings.fit_seeds))).all(axis=1) & np.isfinite(Y).all(axis=1)
        jammed_design = _jams(store, f"discovery-{name}", design_keys)
        if usable.sum() < max(4, len(names) + 2):
            failed = [r for k in design_keys for r in store.records(f"discovery-{name}", batch_key=k, status="failed")]
            first = (f"; {len(failed)} run(s) failed, the first ({failed[0].condition}, seed {failed[0].seed}, "
                     + ", ".join(f"{n} = {failed[0].params[n]:.4g}" for n in names if n in failed[0].params)
                     + f"): {failed[0].error}") if failed else ""
            if jammed_design:
                first += f"; runs whose discharge jammed (left out): {jam_counts(jammed_design)}"
            message = (f"discovery: hypothesis {name!r}: only {int(usable.sum())} of {n_points} design points "
                       f"have every KPI measured on every condition{first} (all runs in {store.path})")
            # a prior whose runs jam (a physical outcome the lab's test never had) is left out of the
            # verdict with this reason; runs that failed are a broken set-up and stop the discovery
            raise (JammedDesign if jammed_design and not failed and mechanism is not None else ConfigError)(message)
        V = None
        if len(settings.fit_seeds) > 1:  # variance of each design point's mean, from the design's pooled noise
            design_noise = ReplicateNoise.of(kpis, [reps[usable]])
            V = np.array([[design_noise.variance(k) for _, _, _, k in cells]]) / np.maximum(counts, 1)
            V = np.where(np.isfinite(V), V, 0.0)
        surrogate = fit_surrogate(X[usable], Y[usable], b, SurrogateConfig(kernel=settings.kernel, strategy="per_kpi"),
                                  y_var=None if V is None else V[usable], objective=spec)
        # The fits minimise the chi^2 that the held-out runs will be scored by: a mean of
        # len(settings.seeds) DEM runs against the lab, so each cell's denominator carries that mean's
        # variance, the DEM noise pooled over the discrepancy runs and the design's replicates (with one
        # run per design point the design has none; leaving the DEM noise out then weighed the KPIs by
        # the lab's uncertainty alone and made every surrogate fit look far off its data).
        fit_noise = ReplicateNoise.of(kpis, [baseline_reps] + ([reps[usable]] if len(settings.fit_seeds) > 1 else []))
        dem_var = np.array([fit_noise.variance(k) for _, _, _, k in cells]) / len(settings.seeds)
        dem_var = np.where(np.isfinite(dem_var), dem_var, 0.0)

        def fit(mask: np.ndarray, surrogate=surrogate, dem_var=dem_var) -> dict[str, float]:
            def chi2(x: np.ndarray) -> np.ndarray:
                mean, var = surrogate.predict_outputs(x)
                return expected_chi2_terms(mean[:, mask], var[:, mask], dem_var[mask], lab_mean[mask],
                                            lab_var[mask]).sum(-1)
            # several starts: the verdict must not hinge on one search that stalled
            if settings.fit_search == "multistart":
                res = multistart_minimum(chi2, b, samples=settings.search_samples, starts=settings.fit_starts,
                                         seed=settings.seed)
            else:
                res = min((minimise_surrogate(chi2, b, settings.ga, seed=settings.seed + k)
                           for k in range(settings.fit_starts)), key=lambda r: r.fitness)
            return dict(zip(names, map(float, res.x)))

        every = fit(np.ones(len(cells), dtype=bool))
        mean, var = surrogate.predict_outputs(np.array([[every[n] for n in names]]))
        misfit = float((((mean[0] - lab_mean) ** 2) / (dem_var + lab_var)).sum())
        surrogate_chi2 = float((var[0] / (dem_var + lab_var)).sum())
        predicted, without, held_cells = {}, {}, []
        for c in conditions:
            train = cond_of != c
            if not train.any() or not (~train).any():
                continue
            x = fit(train)
            mean, var = surrogate.predict_outputs(np.array([[x[n] for n in names]]))
            test = ~train
            held_cells.append((mean[0, test], var[0, test], dem_var[test], lab_mean[test], lab_var[test]))
            predicted[c] = float(expected_chi2_terms(*held_cells[-1]).sum())
            without[c] = x
        resolved = fit_resolved(misfit, surrogate_chi2, len(cells), len(names), settings.alpha)[0]
        p_win, beat = math.nan, math.nan
        if resolved and reference is not None and held_cells and len(without) == len(conditions):
            arrays = [np.concatenate(a) for a in zip(*held_cells)]  # cells in condition order, as ``cells``
            keys = [(c, k) for _, c, _, k in cells]
            beat = must_beat(reference, keys, *arrays, settings.margin) - settings.penalty * len(extra)
            p_win = win_probability(*arrays, beat, seed=settings.seed)
        pruned = resolved and p_win < settings.prune_probability
        # the held-out predictions checked with the DEM: each condition run with the parameters
        # fitted without it; under rules 5 not for a pruned fit (it could not be named), nor for an
        # unresolved one that is refined next (its verdict waits on the refined fits' runs)
        held: dict[str, np.ndarray] = {}
        failures: dict[str, str] = {}
        held_out = {}
        waits = rules_of(settings) >= 5 and not resolved and round_ < settings.escalations
        if not (pruned or waits):
            for c, x in without.items():
                point = {**calibrated, **x}
                key, point = _fitted_batch(store, f"discovery-{name}",
                                           f"held-out/{c}/" + _key(sorted(point.items()), list(settings.seeds)),
                                           [point], settings.seeds, [c], names, b)
                held_out[c] = (key, point, settings.seeds, [c])
        runs = []
        if held_out:
            if math.isfinite(p_win):  # why these runs are worth their cost, before they are made
                echo(f"  {name}: by its own GP, a probability of {p_win:.2g} that its held-out runs score below "
                     f"{beat:.1f}; running them ({sum(len(v[2]) for v in held_out.values())} runs)")
            with executor_for(hyp_model) as executor:  # every condition's runs at once (_run_together)
                runs = _run_together(store, executor, f"discovery-{name}", list(held_out.values()), kpis)
        jammed_held_out: dict[str, int] = {}
        for (c, (key, *_)), reps_c in zip(held_out.items(), runs):
            held[c] = reps_c[0, 0]
            jams = _jams(store, f"discovery-{name}", [key]).get(c, 0)
            if jams:
                jammed_held_out[c] = jams
            missing = _unmeasured(held[c], c, kpis, lab)
            if missing:  # the fitted parameters could not be simulated here: no prediction, no score
                failed = store.records(f"discovery-{name}", batch_key=key, status="failed")
                failures[c] = (f"every run's discharge jammed ({jams} of {len(settings.seeds)}): the fitted "
                               f"parameters arch the grains over the slot, where the lab's discharge flowed"
                               if jams and not failed else
                               f"{', '.join(missing)} not measured in any run"
                               + (f"; first error: {failed[0].error}" if failed else "")
                               + (f"; {jams} run(s) jammed" if jams else ""))
        # A left-out fit astray: its DEM runs miss the held-out condition by far more than its GP
        # predicted there, so the GP misjudged the point, and the verdict must not hinge on it.
        astray = {}
        for c, reps_c in held.items():
            if c in failures:
                continue
            test = cond_of == c
            dem_chi2 = float(((np.nanmean(reps_c[:, [kpis.index(k) for _, cc, _, k in cells if cc == c]], axis=0)
                               - lab_mean[test]) ** 2 / (dem_var[test] + lab_var[test])).sum())
            if prediction_astray(dem_chi2, predicted[c], int(test.sum())):
                astray[c] = (dem_chi2, predicted[c])
        if (resolved and not astray) or round_ == settings.escalations:
            break
        chosen = [every, *without.values()]
        X_new = np.unique(np.array([[x[n] for n in names] for x in chosen]), axis=0)
        why = ([] if resolved else ["its GP's uncertainty at the fit exceeds the data's"]) + [
            f"the DEM misses {c} with chi^2 {v[0]:.1f} where its GP predicted {v[1]:.1f}" for c, v in astray.items()]
        echo(f"  {name}: fit unresolved with {n_points} design points ({'; '.join(why)}); the DEM runs the "
             f"{len(X_new)} fitted points")
    in_sample = misfit + surrogate_chi2  # expected_chi2_terms, split in its two parts
    why_pruned = None
    if pruned:
        why_pruned = (f"by its own GP, a probability of {p_win:.2g} (below {settings.prune_probability:g}) that its "
                      f"held-out runs score below {beat:.1f} (the calibrated parameters' {reference.score:.1f} less "
                      f"max(margin, 2 x the gain's noise sd) and {settings.penalty:g} per added parameter); its GP "
                      f"predicts a held-out chi^2 of "
                      f"{sum(predicted.values()):.1f}, so its held-out runs were not made")
    echo(f"  {name}: {len(names)} parameters, {n_points} points fitted; surrogate held-out chi^2 "
         + ", ".join(f"{c} {v:.1f}" for c, v in predicted.items())
         + (f"; pruned: {why_pruned}" if why_pruned else ""))
    hypothesis = HypothesisScore(name, description, names, {n: tuple(map(float, bounds[n])) for n in names},
                                 len(extra), {}, without, every, in_sample, math.nan, n_points,
                                 predicted_chi2=predicted, held_out_failures=failures,
                                 fit_misfit_chi2=misfit, fit_surrogate_chi2=surrogate_chi2, fit_cells=len(cells),
                                 astray=astray, win_probability=p_win, pruned=why_pruned,
                                 jammed_design=jammed_design, jammed_held_out=jammed_held_out)
    jam_note = jammed_runs_note(hypothesis)
    if jam_note:
        echo(f"  {jam_note}")
    keys = [(c, k) for _, c, _, k in cells]
    wanted = [(c, k) for c in conditions for k in read[len(kpis):]] + [(c, k) for c in unmeasured for k in kpis]
    proposed, proposed_sd = _proposed_models(name, every_run, conditions + unmeasured, read, wanted,
                                             read[len(kpis):], X, b, usable, settings)

    def predict(xs: Sequence[Mapping[str, float]]) -> list[dict[tuple[str, str], float]]:
        if not xs:
            return []
        at = np.array([[float(x[n]) for n in names] for x in xs])
        mean, _ = surrogate.predict_outputs(at)
        out = [dict(zip(keys, map(float, row))) for row in mean]
        if proposed is not None:
            extra, _ = proposed[0].predict_outputs(at)
            for o, row in zip(out, extra):
                o.update(zip(proposed[1], map(float, row)))
        return out

    return _Fitted(hypothesis, held, (reps, *(r[None] for r in held.values())), predict, proposed_sd)


def _proposed_models(name: str, reps: np.ndarray, conditions: Sequence[str], read: Sequence[str],
                     wanted: Sequence[tuple[str, str]], proposed: Sequence[str], X: np.ndarray, b: np.ndarray,
                     usable: np.ndarray, settings: DiscoverySettings):
    """GP models of the cells the lab does not measure (``wanted``: the proposed KPIs on every
    measured condition, every compared KPI on the proposed conditions), from the design's runs
    ``reps [points, conditions, seeds, len(read)]``, and the DEM replicate sd of each proposed KPI;
    ``(None, {})`` when there is no such cell or too few points."""
    if not wanted or len(settings.fit_seeds) < 2:
        return None, {}
    ci, ki = {c: i for i, c in enumerate(conditions)}, {k: j for j, k in enumerate(read)}
    columns = np.stack([reps[:, ci[c], :, ki[k]] for c, k in wanted], axis=-1)  # [points, seeds, cells]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        Y = np.nanmean(columns, axis=1)
    ok = usable & np.isfinite(Y).all(axis=1)
    if ok.sum() < max(4, X.shape[1] + 2):
        return None, {}
    kpis = list(dict.fromkeys(k for _, k in wanted))
    noise = ReplicateNoise.of(kpis, [reps[ok][..., [ki[k] for k in kpis]]])
    sd = {k: math.sqrt(noise.variance(k)) for k in kpis}
    counts = np.isfinite(columns).sum(axis=1)
    V = np.array([[sd[k] ** 2 for _, k in wanted]]) / np.maximum(counts, 1)
    mean = Y[ok].mean(axis=0)
    spec = ObjectiveSpec(tuple(f"{c}|{k}" for c, k in wanted), tuple(np.where(mean == 0, 1.0, mean).tolist()),
                         source=f"hypothesis {name} (unmeasured cells)")
    model = fit_surrogate(X[ok], Y[ok], b, SurrogateConfig(kernel=settings.kernel, strategy="per_kpi"),
                          y_var=np.where(np.isfinite(V[ok]), V[ok], 0.0), objective=spec)
    return (model, list(wanted)), {k: sd[k] for k in proposed if k in sd}


def _score(f: _Fitted, kpis: Sequence[str], lab: Mapping[tuple[str, str], tuple[float, float]],
           noise: ReplicateNoise, penalty: float) -> HypothesisScore:
    """Held-out chi^2 of ``f``'s DEM runs against the measurements with the pooled ``noise``."""
    h = f.hypothesis
    if h.pruned:  # no held-out runs: the GP's prediction stands in the report, it never scores
        return dataclasses.replace(h, score=float(sum(h.predicted_chi2.values()) + penalty * h.added))
    cells: list[Cell] = []
    held: dict[str, float] = {}
    for c, reps in f.held_reps.items():
        c_cells = cells_of(reps[None], [c], kpis, lab, noise)
        cells += c_cells
        held[c] = math.inf if c in h.held_out_failures else float(sum(x.z ** 2 for x in c_cells
                                                                       if math.isfinite(x.z)))
    score = float(sum(held.values()) + penalty * h.added)
    if not h.parameters:  # the calibrated model as is: nothing was predicted, its runs are the fit
        h = dataclasses.replace(h, predicted_chi2=dict(held), in_sample_chi2=score)
    return dataclasses.replace(h, held_out_chi2=held, score=score, held_out_cells=tuple(cells))


# --------------------------------------------------------------------------------------------
# steps 3 and 4
# --------------------------------------------------------------------------------------------

def run_discovery(store: CampaignStore, executor_for: Callable[[DrawDownModel], Executor], model: DrawDownModel,
                  calibrated: Mapping[str, float], measured: MeasuredData, settings: DiscoverySettings,
                  echo: Callable[[str], None] = print,
                  baseline: tuple[str, Mapping[str, Sequence[EvaluationRecord]]] | None = None) -> DiscoveryResult:
    """Steps 1-4 (see the module docstring); ``baseline``: runs of the calibrated set made elsewhere
    that step 1 takes instead of running it (:func:`measure_discrepancy`)."""
    settings = settings.validate()
    missing = [c for c in measured.names if c not in model.conditions]
    if missing:
        raise ConfigError(f"discovery: conditions {missing} of the measured data have no mixture in the model "
                          f"(model conditions: {sorted(model.conditions)})")
    if len(measured.names) < 2:
        raise ConfigError(f"discovery: {len(measured.names)} condition(s) in the measured data; leave-one-condition-out "
                          "needs at least 2")
    bad = [c for c in settings.proposed_conditions if c not in model.conditions or c in measured.names]
    if bad:
        raise out_of_range("discovery.proposed_conditions", list(settings.proposed_conditions),
                           f"conditions of the model {sorted(model.conditions)} that the data do not measure "
                           f"(measured: {list(measured.names)}); not so: {bad}", "discovery")
    context = model_context(model, calibrated)
    mechanisms = registry()
    names = list(settings.candidates) if settings.candidates is not None else sorted(mechanisms)
    unknown = [n for n in names if n not in mechanisms]
    if unknown:
        raise ConfigError(f"discovery.candidates: {unknown} are not in the registry (torchdem/mechanisms/); known: "
                          f"{sorted(mechanisms)}")
    refit_bounds(calibrated, settings.refit, settings.refit_fraction)  # names checked before the first run
    conditions = list(measured.names)
    kpis = list(settings.kpis)
    lab = _lab(measured, kpis)
    with executor_for(model) as executor:
        discrepancy, reps = measure_discrepancy(store, executor, calibrated, measured, settings, baseline)
    if baseline is not None:
        taken = {c: len(v) for c, v in baseline[1].items() if len(v) >= BASELINE_RUNS}
        echo(f"discrepancy: the calibrated set's runs taken from {baseline[0]}: "
             + (", ".join(f"{c} {n}" for c, n in taken.items()) or "none matched"))
    if discrepancy.jammed:
        echo("discrepancy: runs of the calibrated set whose discharge jammed, left out of the means and the noise: "
             + jam_counts(discrepancy.jammed))
    echo(f"discrepancy: chi^2 {discrepancy.chi2:.1f} on {discrepancy.dof} cells, p = {discrepancy.p_value:.3g} "
         f"({'beyond' if discrepancy.significant else 'within'} measurement uncertainty and DEM noise; noise pooled "
         f"over these runs)")
    hypotheses: list[HypothesisScore] = []
    cause, explanation, tied, unresolved = None, "", (), ()
    if not names and not settings.refit:
        explanation = (f"discovery.candidates = []: only the discrepancy was measured (chi^2 = {discrepancy.chi2:.1f} "
                       f"on {discrepancy.dof} cells, p = {discrepancy.p_value:.3g}); no candidate was scored.")
    elif not discrepancy.significant and not settings.always_score:
        explanation = (f"The model agrees with the measurements within their uncertainty and the DEM's stochasticity "
                       f"(chi^2 = {discrepancy.chi2:.1f} on {discrepancy.dof} cells, p = {discrepancy.p_value:.3g} >= "
                       f"{settings.alpha}): there is nothing to explain, so no candidate was fitted.")
    elif not names:  # discovery.refit alone: is the misfit in the values the calibration gave these parameters?
        echo(f"fitting hypotheses: {PARAMETERS} alone (discovery.refit: {', '.join(settings.refit)})")
        fitted = _fit_hypothesis(PARAMETERS, None, model, context, store, executor_for, calibrated, measured,
                                 settings, reps, echo)
        noise = discrepancy.noise.pooled(ReplicateNoise.of(kpis, fitted.groups))
        discrepancy = discrepancy_of(reps, conditions, kpis, lab, noise, settings.alpha, discrepancy.jammed)
        refit = _score(fitted, kpis, lab, noise, settings.penalty)
        refit = dataclasses.replace(refit, gain_noise_sd=gain_noise_sd(discrepancy.cells, refit.held_out_cells))
        hypotheses = [refit]
        echo(f"  {PARAMETERS}: held-out chi^2 (DEM) " + ", ".join(f"{c} {v:.1f}" for c, v in
                                                                refit.held_out_chi2.items()))
        explanation = refit_verdict(refit, discrepancy, settings)
    else:
        echo(f"fitting hypotheses: {PARAMETERS}, " + ", ".join(names))
        fitted = [_fit_hypothesis(PARAMETERS, None, model, context, store, executor_for, calibrated, measured,
                                  settings, reps, echo)]
        # what a candidate must beat, with the noise of the discrepancy runs (pruning only)
        to_beat = _score(fitted[0], kpis, lab, discrepancy.noise, settings.penalty) \
            if settings.prune_probability > 0 else None
        skipped: list[HypothesisScore] = []

        def skip(n: str, why: str) -> None:  # not fitted: out of the verdict, with the reason
            skipped.append(HypothesisScore(n, mechanisms[n].description, (), {}, 0, {}, {}, {}, math.nan,
                                           math.inf, 0, skipped=why))
            echo(f"  {n}: skipped ({why})")

        for n in names:
            why = mechanisms[n].available(context)
            if why is not None:
                skip(n, why)
                continue
            try:
                fitted.append(_fit_hypothesis(n, mechanisms[n], model, context, store, executor_for, calibrated,
                                              measured, settings, reps, echo, reference=to_beat))
            except JammedDesign as err:
                skip(n, str(err))
        # every chi^2 with one noise estimate: pooled over all runs of the discovery
        noise = discrepancy.noise
        for f in fitted:
            noise = noise.pooled(ReplicateNoise.of(kpis, f.groups))
        discrepancy = discrepancy_of(reps, conditions, kpis, lab, noise, settings.alpha, discrepancy.jammed)
        echo("DEM replicate noise pooled over every run (sd, dof): "
             + ", ".join(f"{k} {v['sd']:.3g} ({v['dof']})" for k, v in noise.to_dict().items())
             + f"; discrepancy chi^2 {discrepancy.chi2:.1f}, p = {discrepancy.p_value:.3g}")
        scored = {f.hypothesis.name: _score(f, kpis, lab, noise, settings.penalty) for f in fitted}
        # each candidate's shifts along its prior, predicted once for both reports below
        effects = {f.hypothesis.name: effect_shifts(f, mechanisms[f.hypothesis.name], context, calibrated)
                   for f in fitted[1:]}
        for f in fitted[1:]:
            h = scored[f.hypothesis.name]
            scored[h.name] = dataclasses.replace(h, detectable=detectability(
                f, mechanisms[h.name], context, calibrated, discrepancy, measured, settings.alpha,
                dem_replicates=len(settings.seeds), effects=effects[h.name],
                proposed_conditions=settings.proposed_conditions))
        separable = separability(fitted, mechanisms, context, calibrated, discrepancy, measured, settings.alpha,
                                 dem_replicates=len(settings.seeds), effects=effects,
                                 proposed_conditions=settings.proposed_conditions)
        for n, v in separable.items():
            scored[n] = dataclasses.replace(scored[n], separable=v)
        scored.update({h.name: h for h in skipped})
        hypotheses = [scored[PARAMETERS]] + [scored[n] for n in names]
        for h in hypotheses:
            if h.skipped is None and h.pruned is None:
                echo(f"  {h.name}: held-out chi^2 (DEM) " + ", ".join(f"{c} {v:.1f}" for c, v in h.held_out_chi2.items())
                     + f"; score {h.score:.1f}"
                     + "".join(f"; held-out runs on {c} failed: {why}" for c, why in h.held_out_failures.items()))
        reference = hypotheses[0]
        hypotheses = [reference] + [h if h.skipped or h.pruned else dataclasses.replace(
            h, gain_noise_sd=gain_noise_sd(reference.held_out_cells, h.held_out_cells)) for h in hypotheses[1:]]
        candidates = [h for h in hypotheses[1:] if h.skipped is None and h.pruned is None]
        pruned = [h.name for h in hypotheses[1:] if h.pruned]
        best = min(candidates, key=lambda h: h.score) if candidates else None
        need = max(settings.margin, 2 * best.gain_noise_sd) if best is not None else math.nan
        rule = (f"held-out chi^2 + {settings.penalty:g} per added parameter; a cause must gain more than "
                f"max(margin {settings.margin:g}, 2 x the gain's DEM-noise sd) = {need:.1f}")
        rivals = tied_with(best, candidates, reference, settings.margin) if best is not None else []
        checks = {h.name: fit_check(h, settings.alpha) for h in candidates}
        unresolved = tuple(n for n, (resolved, _) in checks.items() if not resolved)
        blocking = [n for n in unresolved if best is None or n != best.name]
        if not discrepancy.significant:
            # the discrepancy runs' own noise had called it significant; with the noise pooled over
            # every run of the discovery it is not, so there is nothing to explain
            explanation = (f"With the DEM noise pooled over every run of the discovery, the calibrated model "
                           f"agrees with the measurements within noise (chi^2 = {discrepancy.chi2:.1f} on "
                           f"{discrepancy.dof} cells, p = {discrepancy.p_value:.3g} >= {settings.alpha}); the "
                           f"discrepancy runs' own noise estimate had called it significant. No cause is named"
                           + (f" (the best candidate, {best.name}, scores {best.score:.1f} against "
                              f"{reference.score:.1f})." if best is not None else "."))
        elif best is not None and best.score < reference.score - need and rivals:
            tied = (best.name, *(r.name for r in rivals))
            explanation = (f"The candidates {list(tied)} cannot be told apart: each beats refitting the calibrated "
                           f"parameters alone (score {reference.score:.1f}; {rule}), and their scores ("
                           + ", ".join(f"{h.name} {h.score:.1f}" for h in (best, *rivals))
                           + ") differ by less than max(margin, 2 x the DEM-noise sd of their difference). No cause "
                           "is named: a condition or KPI that separates them, or more replicates, would decide.")
        elif best is not None and best.score < reference.score - need and blocking:
            explanation = (f"{best.name} predicts the held-out conditions best (score {best.score:.1f} against "
                           f"{reference.score:.1f}; {rule}), but it cannot be named: "
                           + "; ".join(checks[n][1] for n in blocking)
                           + f". A candidate whose fit is this uncertain is not ruled out by its held-out runs. "
                           f"More design points per parameter (discovery.points_per_parameter, now "
                           f"{settings.points_per_parameter}) or fit replicates would decide.")
        elif best is not None and best.score < reference.score - need:
            cause = best.name
            explanation = (f"{best.name} ({best.description}) predicts the held-out conditions best: score "
                           f"{best.score:.1f} against {reference.score:.1f} for refitting the calibrated parameters "
                           f"alone ({rule}).")
            share, partial, remaining = explained_share(best, discrepancy, settings.alpha)
            explanation += (f" On the held-out conditions it removes {100 * share:.0f} % of the calibrated model's "
                            f"chi^2.")
            if partial:
                explanation += f" The cause is partial: {remaining}"
        else:
            explanation = ("No candidate explains the discrepancy better than the calibrated parameters and noise: "
                           + (f"the best, {best.name}, scores {best.score:.1f} against {reference.score:.1f} "
                              f"({rule})." if best is not None else
                              "by its own GP no candidate could beat them." if pruned else
                              "no candidate could be fitted."))
        if pruned:
            explanation += (f" Not run on their held-out conditions, since by their own GPs they could not be "
                            f"named (probability below {settings.prune_probability:g}): {', '.join(pruned)}.")
    echo(f"cause: {cause}. {explanation}")
    gain: list[GainRow] = []
    extension: dict[str, float] = {}
    if cause is not None:
        chosen = next(h for h in hypotheses if h.name == cause)
        extension = {n: v for n, v in chosen.fitted_all.items() if n in chosen.parameters}
        gain = gain_rows(chosen, discrepancy)
    evaluations = {}
    for stage in discovery_stages(names):
        c = store.counts(stage)
        if c["done"] + c["failed"]:
            evaluations[stage] = c["done"] + c["failed"]
    evaluations["total"] = sum(evaluations.values())
    return DiscoveryResult(discrepancy, tuple(hypotheses), cause, explanation, tuple(gain), extension, evaluations,
                           tied=tuple(tied), unresolved=unresolved)


def detectability(f: _Fitted, mechanism: Mechanism, context: ModelContext, calibrated: Mapping[str, float],
                  discrepancy: Discrepancy, measured: MeasuredData, alpha: float, dem_replicates: int = 3,
                  effects: Sequence[tuple] | None = None, proposed_conditions: Sequence[str] = ()) -> dict[str, dict]:
    """For each direction from the mechanism's no-effect values to an end of its prior: the
    smallest effect the discrepancy test would detect with 80 % probability with these data,
    using the hypothesis's GP models for the shifts and the discrepancy cells' uncertainties
    (``bo.discovery.detectable``), its power at the prior's end and the additions ranked. A
    proposed KPI (``f.proposed_sd``: KPI -> DEM replicate sd) enters as measured on every
    condition with the DEM's standard error over ``dem_replicates`` runs and a lab standard
    uncertainty of the same sd over the lab's repeats (their number where the data state it,
    else ``dem_replicates``). ``effects``: :func:`effect_shifts` of ``f``, if already predicted."""
    from bo.discovery.detectable import what_to_measure_next

    null = mechanism.null(context)
    if null is None or f.predict is None:
        return {}
    prior = mechanism.parameters(context)
    cells, new_kpis, new_conditions = _power_cells(f, discrepancy, measured, dem_replicates, proposed_conditions)
    if not cells:
        return {}
    out = {}
    for direction, end, shift in (effect_shifts(f, mechanism, context, calibrated) if effects is None else effects):
        ranked = what_to_measure_next(cells, shift, reference=1.0, alpha=alpha, new_kpis=new_kpis,
                                      new_conditions=new_conditions)
        now = next(a for a in ranked if a.name == "as is")
        out[direction] = {"smallest_fraction": now.smallest,
                          "values": None if now.smallest is None else
                          {p: null[p] + now.smallest * (end[p] - null[p]) for p in prior},
                          "power_at_prior_end": now.power,
                          "additions": [dataclasses.asdict(a) for a in ranked if a.name != "as is"]}
    return out


def effect_shifts(f: _Fitted, mechanism: Mechanism, context: ModelContext, calibrated: Mapping[str, float],
                  grid: int = 41) -> list[tuple[str, dict[str, float], Callable[[float], dict]]]:
    """For each direction (``"high"``, ``"low"``) whose end of the mechanism's prior differs from
    its no-effect values: (direction, end values, ``shift(t)``), the cells' shift that ``f``'s GP
    models predict at ``null + t (end - null)`` against the calibrated parameters with ``null``.
    The scan grid of ``bo.discovery.detectable.smallest_effect`` is predicted in one batch and
    the shift interpolated linearly between its points (the GP mean is smooth on a grid of
    ``1 / (grid - 1)``). Empty for a mechanism without no-effect values or a hypothesis without
    GP models."""
    null = mechanism.null(context)
    if null is None or f.predict is None:
        return []
    prior = mechanism.parameters(context)
    base = {**calibrated, **null}
    reference = f.predict([base])[0]
    ts = np.linspace(0.0, 1.0, grid)
    out = []
    for direction, side in (("high", 1), ("low", 0)):
        end = {p: prior[p][side] for p in prior}
        if all(abs(end[p] - null[p]) <= 1e-12 * max(1.0, abs(null[p])) for p in prior):
            continue
        points = [{**base, **{p: null[p] + t * (end[p] - null[p]) for p in prior}} for t in ts]
        table = {k: np.array([now[k] - reference[k] for now in f.predict(points)]) for k in reference}

        def shift(t: float, table: dict = table) -> dict[tuple[str, str], float]:
            return {k: float(np.interp(t, ts, v)) for k, v in table.items()}

        out.append((direction, end, shift))
    return out


def _power_cells(f: _Fitted, discrepancy: Discrepancy, measured: MeasuredData, dem_replicates: int,
                 proposed_conditions: Sequence[str] = ()) -> tuple[list, dict, dict]:
    """The discrepancy cells with their uncertainties; the KPIs ``f`` proposes with their (DEM
    standard error, lab standard uncertainty) as :func:`detectability` states them; and the
    proposed conditions, each with (DEM standard error over ``dem_replicates`` runs from the
    pooled noise, the median lab standard uncertainty of the measured conditions) per compared
    KPI."""
    from bo.discovery.detectable import CellUncertainty

    cells = [CellUncertainty(c.condition, c.kpi, c.dem_se, c.measured_u, c.n, measured.condition(c.condition).replicates)
             for c in discrepancy.cells if math.isfinite(c.dem_se) and c.dem_se + c.measured_u > 0]
    repeats = [measured.condition(c).replicates for c in measured.names]
    n_lab = min(repeats) if all(repeats) else dem_replicates
    new_kpis = {k: (sd / math.sqrt(dem_replicates), sd / math.sqrt(n_lab)) for k, sd in f.proposed_sd.items()
                if math.isfinite(sd) and sd > 0}
    kpis = list(dict.fromkeys(c.kpi for c in cells))
    per_kpi = {k: (discrepancy.noise.se(k, dem_replicates), float(np.median([c.u for c in cells if c.kpi == k])))
               for k in kpis}
    new_conditions = {c: {k: v for k, v in per_kpi.items() if math.isfinite(v[0])} for c in proposed_conditions}
    return cells, new_kpis, new_conditions


def _directions(predict: Callable[[Sequence[Mapping[str, float]]], list[dict]], at: Mapping[str, float],
                bounds: Mapping[str, tuple[float, float]]) -> tuple[list[dict], list[tuple[float, float]]]:
    """A hypothesis's free directions at ``at``: per parameter the shift from the low to the high
    end of its range (the others held), and the magnitudes that keep it inside the range."""
    free = [(p, lo, hi) for p, (lo, hi) in bounds.items() if hi > lo]
    ends = predict([{**at, p: v} for p, lo, hi in free for v in (hi, lo)])
    columns = [{k: up[k] - down[k] for k in up} for up, down in zip(ends[::2], ends[1::2])]
    return columns, [((lo - at[p]) / (hi - lo), (hi - at[p]) / (hi - lo)) for p, lo, hi in free]


def separability(fitted: Sequence[_Fitted], mechanisms: Mapping[str, Mechanism], context: ModelContext,
                 calibrated: Mapping[str, float], discrepancy: Discrepancy, measured: MeasuredData, alpha: float,
                 dem_replicates: int = 3, effects: Mapping[str, Sequence[tuple]] | None = None,
                 proposed_conditions: Sequence[str] = ()) -> dict[str, dict[str, dict]]:
    """Could these data tell each candidate from the others? For each candidate ``A`` with
    no-effect values and each direction towards an end of its prior, ``A``'s GP models give the
    shift of the cells (and of the KPIs it proposes) as its effect grows; each rival, the
    calibrated parameters refitted (``parameters``) or another candidate ``B`` with them, may move
    the cells along its free directions inside its ranges: the refit parameters' as ``A``'s GP
    models them, ``B``'s own as ``B``'s GP models them from its no-effect values.
    ``bo.discovery.detectable.what_separates`` gives the power of rejecting the rival at its best
    fit when ``A`` is at its prior's end, the smallest effect of ``A`` told apart with 80 %
    probability, and the additions ranked. ``effects``: name -> :func:`effect_shifts`, if
    already predicted. Returns name -> direction -> rival -> {"power", "smallest_fraction",
    "additions"}."""
    from bo.discovery.detectable import what_separates

    by_name = {f.hypothesis.name: f for f in fitted}
    refit = by_name.get(PARAMETERS)
    refit_bounds = dict(refit.hypothesis.bounds) if refit is not None else {}
    usable = {n: f for n, f in by_name.items() if n != PARAMETERS and f.predict is not None
              and mechanisms[n].null(context) is not None}
    own = {n: _directions(g.predict, {**calibrated, **mechanisms[n].null(context)},
                          dict(mechanisms[n].parameters(context))) for n, g in usable.items()}
    out: dict[str, dict[str, dict]] = {}
    for name, f in usable.items():
        cells, new_kpis, new_conditions = _power_cells(f, discrepancy, measured, dem_replicates,
                                                       proposed_conditions)
        if not cells:
            continue
        refit_columns, refit_limits = _directions(f.predict, {**calibrated, **mechanisms[name].null(context)},
                                                  refit_bounds)
        rivals = {PARAMETERS: (refit_columns, refit_limits)}
        rivals.update({other: (refit_columns + own[other][0], refit_limits + own[other][1])
                       for other in usable if other != name})
        mine = {}
        shifts = effects[name] if effects is not None and name in effects else \
            effect_shifts(f, mechanisms[name], context, calibrated)
        for direction, _, shift in shifts:
            mine[direction] = {}
            for other, (columns, limits) in rivals.items():
                ranked = what_separates(cells, shift, columns, limits, alpha=alpha, new_kpis=new_kpis,
                                        new_conditions=new_conditions)
                now = next(a for a in ranked if a.name == "as is")
                mine[direction][other] = {"power": now.power, "smallest_fraction": now.smallest,
                                          "additions": [dataclasses.asdict(a) for a in ranked if a.name != "as is"]}
        if mine:
            out[name] = mine
    return out
