"""The calibration campaign of Hadi et al. sections 3.3-3.7 as one resumable pipeline.

Contract
--------
``run_calibration(store, executor, settings, measured, out_dir)`` runs, in order, every stage
through the SQLite campaign store (``bo.campaign.store``) and the executor (``bo.campaign.executor``), so a
campaign killed at any point (SIGKILL included) and started again with the same store loses no
finished DEM run and repeats none: stored batches are reused, only pending evaluations run,
and the GA result is kept as a store artifact.

1. ``screening`` (store stage ``screening``): the definitive screening design with replicate
   seeds and its analysis (``bo.screening.pipeline``): KPIs dominated by DEM noise are excluded (Eqs. 4-6),
   Table 5 selects the parameters, the Table-6 rule proposes the calibration bounds.
   With ``objective_conditions`` Eq. 7 also counts the KPIs of other measured conditions (another
   fill's), each named ``<kpi>@<condition>`` (:func:`at_condition`): the calibrated condition's KPIs
   and theirs, equal weights per condition, so a parameter that only a second fill shows (how
   friction divides between the materials) is calibrated instead of guessed. Every surrogate point
   and the verification run on them too, and they are not validated (they are no blind check).
2. ``surrogate`` (stages ``initial`` and ``round-<k>``): a Latin hypercube of
   ``points_per_parameter x d`` points, each run with every replicate seed; then rounds of ``q``
   batch expected-improvement points (qLogEI) until the mean cross-validated R^2 reaches
   ``target_r2`` or ``budget`` points are spent. The objective is Eq. 7 of the replicate-mean
   KPIs with the delta-method variance of the replicate mean as GP observation noise
   (strategy ``scalar``), or one GP per KPI composed by Eq. 7 (``per_kpi``). Optionally the
   other strategy is cross-validated on the same data after every round, which answers
   "which strategy reaches R^2 >= 0.95 with fewer DEM runs" on equal data. With
   ``reuse_screening`` the screening's design points are data too (:func:`screening_points`) and
   the Latin hypercube shrinks by as many points, to no less than half its size.
3. ``ga`` (artifact): the GA on the surrogate mean over ``ga_repetitions`` surrogate trainings
   (Table 9), restricted (friction and restitution <= 0.9) and unrestricted (Table 8); the lowest fitness of
   the chosen mode is the calibrated set. The GA's surrogate is the rounds' strategy, or with
   ``ga_strategy`` another one or ``"best"``: the strategy whose Eq. 7 cross-validated better in
   the last round (the surrogate that predicts the objective best out of sample picks the point).
   Beside it, ``attainable`` (artifact, :func:`attainable_stage`): per objective KPI, the range of
   its per-KPI surrogate mean over the box the GA searched with every other objective KPI inside
   the lab's 95 % CI (``bo.surrogate.attainable``): whether any set in the bounds matches them all.
4. ``verification`` (stage ``verification``): the calibrated set with the verification seeds;
   relative error per KPI (Fig. 14, Table A.4). With ``fresh_verification`` the same runs are
   made again in a batch of their own that takes nothing from the store (batch key
   ``fresh/...``): a resumed campaign, such as a shipped store, is then verified on the machine
   that resumes it, beside the campaign's own verification.
5. ``density`` (stage ``density``): bulk density check (section 3.6): the DEM's maximum heap
   height in the lower box against the measured one; every particle density is multiplied by
   the mean ratio H_DEM / H_Exp and the calibrated set is verified again (Figs. 15-16,
   Table A.5). Skipped, with the reason, when the measured data carry no heap height.
6. ``validation`` (stage ``validation``): the other measured conditions (mass ratios, reverse
   layering) with the calibrated set; pellet-sinter interaction parameters stay the average of
   the pure ones (Fig. 18, Table A.6).

Names: KPIs are DEM names (``torchdem.drawdown.KPI_UNITS``); a DEM ``<x>_full_<unit>`` KPI (a
slice's mass scaled to the full box) is compared with the measured ``<x>_<unit>``
(``bo.screening.pipeline.measured_for``). A parameter ``density_<material>`` is a solid density
(``bo.campaign.dem``). Everything returned is plain data; ``bo.calibration.report`` writes it.

Reference: A. Hadi, Y. Pang, D. Schott, "Systematic DEM calibration of two-component mixtures
using AI-accelerated surrogate models", sections 3.3-3.7, Tables 5-9, A.4-A.6.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from bo.surrogate.acquisition import (AdaptiveSettings, RoundRecord, SamplingState, best_kernel_cv, latin_hypercube,
                                      propose_batch, state_ceiling, state_learned_ceiling)
from kpi.loadcell import discharge_jammed, discharge_state
from torchdem.model import DENSITY_PREFIX
from bo.calibration.plan import campaign_plan
from bo.campaign.executor import Executor, run_pending
from bo.surrogate.attainable import AttainableRange, AttainableSettings, attainable_ranges
from bo.surrogate.ga import GASettings, GASummary, ga_bounds, repeated_ga
from bo.surrogate.jam import fit_jam_model
from bo.surrogate.objective import ObjectiveSpec
from bo.screening.pipeline import (ScreeningReport, ScreenSettings, analyse_and_report, jammed_screening_runs,
                                   json_ready, measured_for, run_screening)
from bo.screening.stepwise import ScreeningResults
from bo.campaign.store import CampaignStore
from bo.surrogate.gp import STRATEGIES, SurrogateConfig, as_bounds, cross_validated_r2, fit_surrogate
from torchdem.errors import ConfigError, out_of_range
from torchdem.measured import MeasuredData

__all__ = [
    "EXTRA_STAGES",
    "HEAP_HEIGHT_KPI",
    "KPIAgreement",
    "SurrogateStageSettings",
    "CalibrationSettings",
    "SurrogateOutcome",
    "GAOutcome",
    "DensityOutcome",
    "CalibrationResult",
    "agreement",
    "run_calibration",
]

#: Store stages the campaign uses besides ``bo.campaign.store.STAGES`` and ``round-<k>``.
EXTRA_STAGES = ("density",)
#: DEM KPI compared with the measured heap height in the bulk density check.
HEAP_HEIGHT_KPI = "max_heap_height_m"
_GA_MODES = ("restricted", "unrestricted")
#: ``ga_strategy`` value: the strategy whose Eq. 7 cross-validated best in the last round.
GA_BEST = "best"


# --------------------------------------------------------------------------------------------
# Settings
# --------------------------------------------------------------------------------------------

#: The GP observation noise of points run once (``SurrogateStageSettings.noise``).
NOISE_MODELS = ("learned", "pooled")


@dataclass(frozen=True)
class SurrogateStageSettings:
    """The surrogate stage.

    Attributes:
        parameters: calibrated parameter names; None: those Table 5 selects (if it selects
            none, every screened parameter, and the report says so).
        bounds: name -> (low, high); None: the Table-6 proposal (the screened range for
            parameters it does not move). Given bounds must cover ``parameters``.
        seeds: replicate seeds of every point (>= 2 gives the replicate-mean variance).
        adaptive: LHS size, q, target R^2, budget (points), CV folds and seeds, kernels.
        config: GP kernel / strategy (``kernel`` is replaced by each round's best kernel).
        compare_strategies: also cross-validate the other strategy after every round.
        added: name -> (low, high) of parameters calibrated besides ``parameters`` (or Table 5's
            selection): densities, a mechanism's parameters (``lobe_spacing_sinter``).
        noise: the GP's observation noise: ``"learned"`` (one noise level fitted with the GP where
            points have one replicate; a point's own replicate-mean variance where it has more) or
            ``"pooled"`` (fixed: the replicate scatter of the screening's runs pooled over its
            design, :func:`pooled_replicate_covariance`, divided by each point's number of runs).
        reuse_screening: the screening's design points enter the surrogate's data as points already
            run (:func:`screening_points`), and the initial Latin hypercube shrinks by as many
            points, to no less than half its size.
        limits: name -> (low, high) the calibrated range of that parameter may not leave: a
            bound from the Table-6 proposal or the screened range beyond it is moved onto it, so
            a screening may look past where the model stays physical (a trilobe's lobes part
            above a lobe spacing of 1 / (2 + sqrt 3)) while the calibration does not.
        reuse_designs: batch keys of earlier initial designs in the store (a design the campaign
            ran part of before its bounds changed): their finished points inside the bounds enter
            the surrogate's data as points already run (:func:`design_points`), after the
            screening's, and the initial Latin hypercube shrinks by as many.
        jam_conditions: measured conditions (not the calibrated one) that every point this stage
            runs also runs on, with the same seeds, to see whether its discharge jams there. Their
            KPIs never enter the objective; their runs join the calibrated condition's as
            observations of the jam classifier (:mod:`bo.surrogate.jam`), so the GA keeps away from
            where a fill the lab saw flow arches over the slot, which a calibration on one fill
            does not see (a pellet-rich fill arches where 50-50 flows). A validation condition
            named here is still a blind check of its KPIs, not of whether it jams. (Conditions whose
            KPIs enter the objective are ``CalibrationSettings.objective_conditions``.)
    """

    parameters: tuple[str, ...] | None
    bounds: Mapping[str, tuple[float, float]] | None
    seeds: tuple[int, ...]
    adaptive: AdaptiveSettings
    config: SurrogateConfig = SurrogateConfig()
    compare_strategies: bool = True
    added: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    noise: str = "learned"
    reuse_screening: bool = False
    limits: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    reuse_designs: tuple[str, ...] = ()
    jam_conditions: tuple[str, ...] = ()


@dataclass(frozen=True)
class CalibrationSettings:
    """Everything a calibration campaign needs besides the store, executor and measured data.

    Attributes:
        condition: measured condition calibrated (the paper: ``"50-50"``).
        screening: the screening stage (its ``condition`` must equal ``condition``).
        objective_kpis: DEM KPI names of Eq. 7; None: the screening's kept KPIs that have a
            measurement. weights: KPI -> weight (sum 1); None: equal weights.
        surrogate: the surrogate stage.
        ga: GA settings (``restricted`` is ignored: both modes run). ga_repetitions: surrogate
            trainings (Table 9). ga_mode: which mode's optimum is the calibrated set.
        verification_seeds: seeds of the verification runs (the paper: 5).
        density_recalibration: run the bulk density check when the data have a heap height.
        validation_conditions: conditions validated; None: every other measured condition.
        validation_seeds: seeds of every validation condition.
        validate_with_density: validate with the recalibrated densities (when recalibrated).
        seed: seed of the GA repetitions.
        fresh_verification: run the verification again, sharing no stored run (see stage 4).
        ga_strategy: the surrogate strategy the GA minimises: None (the rounds' strategy), one of
            ``STRATEGIES``, or ``"best"`` (the one with the higher CV R^2 of Eq. 7 in the last
            round; the rounds' own when the other was not cross-validated).
        attainable: the GAs of what the bounds allow (:func:`attainable_stage`), and whether it
            says what holds each range that misses.
        objective_conditions: measured conditions besides ``condition`` whose KPIs enter Eq. 7
            (as ``<kpi>@<condition>``, the calibrated condition's weights divided by the number of
            conditions): every surrogate point and the verification run on them, the screening's
            points (run on ``condition`` only) do not count as surrogate data, and they are left
            out of the validation. () calibrates on ``condition`` alone, as the paper.
    """

    condition: str
    screening: ScreenSettings
    objective_kpis: tuple[str, ...] | None
    weights: Mapping[str, float] | None
    surrogate: SurrogateStageSettings
    ga: GASettings
    ga_repetitions: int = 10
    ga_mode: str = "restricted"
    verification_seeds: tuple[int, ...] = (0, 1, 2, 3, 4)
    density_recalibration: bool = True
    validation_conditions: tuple[str, ...] | None = None
    validation_seeds: tuple[int, ...] = (0, 1, 2, 3, 4)
    validate_with_density: bool = True
    seed: int = 0
    fresh_verification: bool = False
    ga_strategy: str | None = None
    attainable: AttainableSettings = AttainableSettings()
    objective_conditions: tuple[str, ...] = ()

    def validate(self, source: str = "calibration") -> "CalibrationSettings":
        if self.screening.condition != self.condition:
            raise ConfigError(f"{source}: the screening condition {self.screening.condition!r} is not the "
                              f"calibrated condition {self.condition!r}")
        if self.ga_mode not in _GA_MODES:
            raise out_of_range("ga_mode", self.ga_mode, f"one of {list(_GA_MODES)}", source)
        if isinstance(self.ga_repetitions, bool) or not isinstance(self.ga_repetitions, int) \
                or self.ga_repetitions < 1:
            raise out_of_range("ga_repetitions", self.ga_repetitions, "an integer >= 1", source)
        for name in ("verification_seeds", "validation_seeds"):
            seeds = getattr(self, name)
            if not seeds or len(set(seeds)) != len(seeds):
                raise out_of_range(name, seeds, "a non-empty list of distinct ints", source)
        s = self.surrogate
        if not s.seeds or len(set(s.seeds)) != len(s.seeds):
            raise out_of_range("surrogate.seeds", s.seeds, "a non-empty list of distinct ints", source)
        if self.condition in s.jam_conditions or len(set(s.jam_conditions)) != len(s.jam_conditions):
            raise out_of_range("surrogate.jam_conditions", list(s.jam_conditions),
                               f"distinct measured conditions other than the calibrated {self.condition!r}", source)
        fitted = self.objective_conditions
        if self.condition in fitted or len(set(fitted)) != len(fitted):
            raise out_of_range("objective.conditions", list(fitted),
                               f"distinct measured conditions other than the calibrated {self.condition!r}", source)
        both = [c for c in fitted if c in (self.validation_conditions or ())]
        if both:
            raise out_of_range("validation.conditions", list(self.validation_conditions),
                               f"conditions other than objective.conditions {both} (those are fitted, no blind check)",
                               source)
        if s.config.strategy not in STRATEGIES:
            raise out_of_range("surrogate.strategy", s.config.strategy, f"one of {list(STRATEGIES)}", source)
        if self.ga_strategy is not None and self.ga_strategy not in (*STRATEGIES, GA_BEST):
            raise out_of_range("ga.strategy", self.ga_strategy,
                               f"null (the surrogate's strategy) or one of {[*STRATEGIES, GA_BEST]}", source)
        return self


# --------------------------------------------------------------------------------------------
# Results (plain data)
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class KPIAgreement:
    """DEM replicates of one KPI against the measurement (a bar of Figs. 14, 16, 18).

    Attributes:
        kpi: DEM KPI name. dem_mean, dem_std: over the finite replicates (std ddof 1; NaN for
            one value). n: finite replicates. measured_mean, measured_ci95: the lab's.
        relative_error_pct: ``(dem_mean - measured_mean) / measured_mean * 100``.
        within_ci: ``|dem_mean - measured_mean| <= measured_ci95``.
        jammed: runs left out because their discharge jammed (:func:`agreement`).
    """

    kpi: str
    dem_mean: float
    dem_std: float
    n: int
    measured_mean: float
    measured_ci95: float
    relative_error_pct: float
    within_ci: bool
    jammed: int = 0

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class SurrogateOutcome:
    """What the surrogate stage evaluated and how good the surrogate became.

    Attributes:
        parameters: names of the ``d`` calibrated parameters; bounds: ``[2, d]``.
        state: points with a usable objective (``X [n, d]``, ``y``, ``y_var``).
        kpi_replicates: ``[n, r, M]`` KPI values of those points (objective KPIs).
        rounds: one ``RoundRecord`` per round (round 0: the reused screening points and the
            LHS). stopped_because: ``"target_r2"`` or ``"budget"``. points_run: design points this
            stage evaluated (failed ones included; the reused ones not). dropped_points: points
            without a usable objective (fewer than ``min(2, r)`` finite replicates of some KPI).
        reused_points: points run before this stage's design among the data (the screening's,
            ``reuse_screening``, and an earlier design's, ``reuse_designs``); reused_design_points:
            the earlier design's among them (run by this stage, so they cost DEM runs); reuse_note:
            what was reused and what was left out, for the report.
        strategy_r2: strategy -> CV R^2 mean per round (the run's strategy and, when compared,
            the other one on the same data; with pooled noise also ``"<strategy>, learned noise"``:
            the run's strategy with a learned noise level, on the same data).
        jammed: ``[n, r]`` bool, runs of ``kpi_replicates`` whose discharge jammed (None: not
            recorded); noise: ``[M, M]`` pooled covariance of one run (``noise: pooled``) or None.
            With them another strategy's data follow from ``kpi_replicates`` (:func:`_objective_data`).
        elsewhere: ``[n, c * r, M]`` KPI values of the same points' runs on the ``c`` jam conditions
            (``SurrogateStageSettings.jam_conditions``, condition-major; NaN: not run, as for the
            reused points), and jammed_elsewhere ``[n, c * r]`` bool, those whose discharge jammed;
            None without jam conditions.
    """

    parameters: tuple[str, ...]
    bounds: np.ndarray
    state: SamplingState
    kpi_replicates: np.ndarray
    rounds: tuple[RoundRecord, ...]
    stopped_because: str
    points_run: int
    dropped_points: int
    strategy_r2: Mapping[str, tuple[float, ...]]
    reused_points: int = 0
    reuse_note: str = ""
    reused_design_points: int = 0
    jammed: np.ndarray | None = None
    noise: np.ndarray | None = None
    elsewhere: np.ndarray | None = None
    jammed_elsewhere: np.ndarray | None = None


@dataclass(frozen=True)
class GAOutcome:
    """Table 8/9: the GA summaries per mode and the calibrated set; ``strategy``: the surrogate
    strategy the GA minimised, ``strategy_note``: why (empty when it is the rounds' own by default).
    ``jam_note``: when runs of the surrogate stage jammed, how the GA weighed the risk
    (:func:`_jam_flags`); ``jam_probability``: the chance that one run of the calibrated set jams,
    by that model (None when no run jammed)."""

    summaries: Mapping[str, GASummary | None]
    notes: Mapping[str, str]
    mode: str
    calibrated: Mapping[str, float]
    strategy: str = "scalar"
    strategy_note: str = ""
    jam_note: str = ""
    jam_probability: float | None = None


@dataclass(frozen=True)
class DensityOutcome:
    """Bulk density check: heap heights, ratio, new densities, re-verification."""

    skipped_because: str | None
    heap_dem_m: tuple[float, ...] = ()
    heap_measured_m: float = math.nan
    ratio: float = math.nan
    densities: Mapping[str, float] = field(default_factory=dict)
    agreement: tuple[KPIAgreement, ...] = ()


@dataclass(frozen=True)
class CalibrationResult:
    """Everything the campaign found (``bo.calibration.report`` writes it)."""

    settings: CalibrationSettings
    screening: ScreeningReport
    objective: ObjectiveSpec
    parameter_choice_note: str
    surrogate: SurrogateOutcome
    ga: GAOutcome
    verification: tuple[KPIAgreement, ...]
    density: DensityOutcome
    validation: Mapping[str, tuple[KPIAgreement, ...]]
    final_parameters: Mapping[str, float]
    evaluations: Mapping[str, int]
    wall_time_s: Mapping[str, float]
    fresh_verification: tuple[KPIAgreement, ...] | None = None
    discharge_not_ended: Mapping[str, int] = field(default_factory=dict)
    discharge_jammed: Mapping[str, int] = field(default_factory=dict)
    attainable: tuple[AttainableRange, ...] = ()
    held_parameters: Mapping[str, float] = field(default_factory=dict)  # the model's, less the calibrated ones
    verification_fitted: Mapping[str, tuple[KPIAgreement, ...]] = field(default_factory=dict)  # objective_conditions'


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------

def _key(*parts) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=repr).encode()).hexdigest()[:12]


#: Significant digits of the floats an artifact key hashes (:func:`_data_key`).
KEY_DIGITS = 9


def _canonical(value):
    """``value`` with arrays as lists and every float rounded to :data:`KEY_DIGITS` significant digits."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, (float, np.floating)):
        return float(f"{float(value):.{KEY_DIGITS}g}") if math.isfinite(value) else float(value)
    if isinstance(value, (list, tuple)):
        return [_canonical(v) for v in value]
    if isinstance(value, dict):
        return {k: _canonical(v) for k, v in value.items()}
    return value


def _data_key(*parts) -> str:
    """The key of an artifact computed from the stored runs (a round's cross-validation, the GA, what
    the bounds allow). The data it hashes (replicate means, pooled noise) are sums whose last bits
    depend on the machine and the numpy build, so their floats are hashed to :data:`KEY_DIGITS`
    significant digits: a shipped store's artifacts are then found on the user's machine too."""
    return _key(*_canonical(list(parts)))


def _stored(store: CampaignStore, name: str, compute: Callable[[], dict]) -> dict:
    """The artifact ``name``, computed (and stored) when the store does not hold it yet."""
    value = store.get_artifact(name, None)
    if value is None:
        value = compute()
        store.put_artifact(name, value)
    return value


def _replicates(store: CampaignStore, stage: str, key: str, n_points: int, seeds: Sequence[int],
                condition: str, kpis: Sequence[str]) -> np.ndarray:
    """``[n_points, r, M]`` KPI values of a stored batch (NaN: failed or unmeasured)."""
    index = {s: r for r, s in enumerate(seeds)}
    out = np.full((n_points, len(seeds), len(kpis)), np.nan)
    for rec in store.records(stage, batch_key=key, condition=condition, status="done"):
        if rec.seed in index and rec.kpis is not None:
            out[rec.point_index, index[rec.seed]] = [rec.kpis.get(k, math.nan) for k in kpis]
    out[~np.isfinite(out)] = np.nan
    return out


def _run_batch(store: CampaignStore, executor: Executor, stage: str, key: str,
               make_points: Callable[[], Sequence[Mapping[str, float]]], seeds: Sequence[int],
               conditions: Sequence[str], share: bool = True) -> list[dict[str, float]]:
    """The points of batch ``(stage, key)``, all its runs done. Only that batch's runs are claimed:
    another batch of the stage is a design the campaign asked for before (the screening's
    selection changed), never run unless the campaign comes back to it."""
    points = store.batch(stage, key, make_points, seeds=list(seeds), conditions=list(conditions), share=share)
    run_pending(store, executor, stage, batch_key=key)
    return points


def _jammed_runs(replicates: np.ndarray, kpis: Sequence[str]) -> np.ndarray:
    """``[r]`` bool: the runs of ``replicates [r, M]`` whose discharge jammed (none when ``kpis``
    lacks ``JAMMED``)."""
    if JAMMED not in kpis:
        return np.zeros(replicates.shape[0], dtype=bool)
    return replicates[:, list(kpis).index(JAMMED)] == 1


def agreement(replicates: np.ndarray, kpis: Sequence[str], measured: Mapping) -> tuple[KPIAgreement, ...]:
    """Per KPI with a measurement: DEM mean/std over ``replicates [r, M]`` vs the lab.

    When ``kpis`` holds ``JAMMED``, the runs whose discharge jammed are left out of every KPI and
    counted (``KPIAgreement.jammed``): their grains arched over the slot, so they measured no
    discharge (flow 0, level surfaces 0 deg), and a lab whose test arched would repeat it. Averaged
    in, one such run of five moves the flow by a fifth; left out, the report says how often the set
    jams beside what it gives when it flows."""
    lab = measured_for(kpis, measured)
    jam = _jammed_runs(replicates, kpis)
    out = []
    for j, kpi in enumerate(kpis):
        if kpi not in lab:
            continue
        v = replicates[~jam, j]
        v = v[np.isfinite(v)]
        mean = float(v.mean()) if v.size else math.nan
        std = float(v.std(ddof=1)) if v.size > 1 else math.nan
        m = lab[kpi]
        mm, ci = float(m.mean), float(m.ci95)
        out.append(KPIAgreement(kpi=kpi, dem_mean=mean, dem_std=std, n=int(v.size), measured_mean=mm,
                                measured_ci95=ci, relative_error_pct=(mean - mm) / mm * 100.0,
                                within_ci=bool(abs(mean - mm) <= ci), jammed=int(jam.sum())))
    return tuple(out)


#: The KPI a run reports its jammed discharge by (``torchdem.drawdown.JAM_FRACTION``).
JAMMED = "discharge_jammed"

#: Between a KPI and the condition it was measured on in an objective's KPI name (:func:`at_condition`).
CONDITION_MARK = "@"


def at_condition(kpi: str, condition: str) -> str:
    """The objective's name of ``kpi`` measured on another ``condition`` than the calibrated one:
    ``shear_angle_deg@75-25`` (``CalibrationSettings.objective_conditions``)."""
    return f"{kpi}{CONDITION_MARK}{condition}"


def objective_blocks(objective: ObjectiveSpec, condition: str) -> tuple[tuple[str, tuple[str, ...]], ...]:
    """``((condition, DEM KPI names), ...)``: the conditions whose runs the objective's KPIs are read
    from, the calibrated ``condition`` first, each with its KPIs in the objective's order (every
    condition has the same KPIs, :func:`objective_for`). Concatenated they are the objective's KPI axis."""
    blocks: dict[str, list[str]] = {condition: []}
    for name in objective.kpi_names:
        kpi, _, where = name.partition(CONDITION_MARK)
        blocks.setdefault(where or condition, []).append(kpi)
    return tuple((c, tuple(k)) for c, k in blocks.items())


def objective_measurements(objective: ObjectiveSpec, condition: str, measured: MeasuredData) -> dict:
    """``{objective KPI name: the lab's Measurement}`` (mean and 95 % CI), each KPI's from its condition."""
    out = {}
    for where, kpis in objective_blocks(objective, condition):
        lab = measured_for(kpis, measured.condition(where).kpis)
        out.update({(k if where == condition else at_condition(k, where)): v for k, v in lab.items()})
    return out

#: Fewest screening points inside the surrogate's bounds whose replicates the pooled noise is taken
#: from; with fewer it is pooled over every screening point.
MIN_POOLED_POINTS = 8


def screening_points_inside(results: ScreeningResults, names: Sequence[str], bounds: np.ndarray,
                            nominal: Mapping[str, float] | None = None) -> np.ndarray:
    """``[runs]`` bool: the screening's design points inside ``bounds [2, d]`` of ``names``: a
    screened parameter by its value at the point, another by ``nominal[name]`` (the value every
    screening run had) where given; a parameter neither screened nor in ``nominal`` does not count."""
    inside = np.ones(results.n_runs, dtype=bool)
    tol = 1e-9 * (bounds[1] - bounds[0])
    for j, n in enumerate(names):
        if n in results.parameter_names:
            value = results.physical[:, results.parameter_names.index(n)]
        elif nominal is not None and n in nominal:
            value = float(nominal[n])
        else:
            continue
        inside &= (value >= bounds[0, j] - tol[j]) & (value <= bounds[1, j] + tol[j])
    return inside


def pooled_replicate_covariance(kpi_reps: np.ndarray) -> tuple[np.ndarray, int]:
    """``([M, M] covariance, degrees of freedom)`` of single DEM runs about their point's mean,
    pooled over every point of ``[n, r, M]`` replicates with two or more runs whose M KPIs are
    all finite: sum of the deviations' outer products / sum of (runs - 1). Raises when no point
    has two such runs."""
    n, r, m = kpi_reps.shape
    scatter, dof = np.zeros((m, m)), 0
    for i in range(n):
        rows = kpi_reps[i][np.isfinite(kpi_reps[i]).all(axis=1)]
        if rows.shape[0] >= 2:
            dev = rows - rows.mean(axis=0)
            scatter += dev.T @ dev
            dof += rows.shape[0] - 1
    if dof == 0:
        raise ConfigError(f"pooled replicate noise: none of {n} points has two runs with every KPI measured")
    return scatter / dof, dof


def _objective_data(kpi_reps: np.ndarray, objective: ObjectiveSpec, strategy: str,
                    pooled: np.ndarray | None = None, need: int | None = None,
                    jammed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(usable [n] bool, y, y_var)`` from ``[n, r, M]`` replicates (finite ones only).
    ``pooled``: ``[M, M]`` covariance of one run (:func:`pooled_replicate_covariance`); a point
    of ``k`` finite runs then has the noise ``pooled / k``. Without it a point's noise is its own
    replicate-mean variance, and the noise of points measured once is left to the GP.
    ``need``: finite runs a point needs to be usable (default ``min(2, r)``).

    ``jammed [n, r]`` bool: runs whose discharge jammed (``kpi.loadcell.discharge_jammed``). Their
    KPIs are those of a box that did not flow (flow 0, shear angle 0 deg): one such point among a
    hundred took a GP of Eq. 7 from a CV R^2 of 0.87 to none, because no smooth surface passes
    through it and its neighbours. A jammed run is no KPI sample of the flowing regime, so the
    per-KPI models leave it out; the scalar objective gives a point with a jammed run the worst
    Eq. 7 of the points that flowed (the region is a miss, and the search keeps away from it) with
    the noise of its runs as measured."""
    n, r, m = kpi_reps.shape
    need = min(2, r) if need is None else need
    jam = np.zeros((n, r), dtype=bool) if jammed is None else np.asarray(jammed, dtype=bool).reshape(n, r)
    if strategy == "per_kpi" and jam.any():
        kpi_reps = np.where(jam[:, :, None], np.nan, kpi_reps)
    finite = np.isfinite(kpi_reps)
    usable = (finite.sum(axis=1) >= need).all(axis=1)
    ys, vs = [], []
    for i in np.flatnonzero(usable):
        rows = kpi_reps[i][finite[i].all(axis=1)]
        if rows.shape[0] < need:  # every KPI finite somewhere, but not together in need rows
            usable[i] = False
            continue
        mean = rows.mean(axis=0)
        k = rows.shape[0]
        if strategy == "per_kpi":
            ys.append(mean)
            vs.append(np.diag(pooled) / k if pooled is not None
                      else None if k == 1 else rows.var(axis=0, ddof=1) / k)
        else:
            measured, weights = np.asarray(objective.measured), np.asarray(objective.weights)
            ys.append(float(objective(mean)))
            # delta method, as bo.surrogate.gp.objective_from_replicates
            grad = weights * np.sign(mean - measured) / np.abs(measured)
            vs.append(float(grad @ pooled @ grad) / k if pooled is not None
                      else None if k == 1 else float((rows @ grad).var(ddof=1) / k))
    y = np.asarray(ys, dtype=np.float64).reshape((-1,) if strategy == "scalar" else (-1, m))
    y_var = None if (not vs or any(v is None for v in vs)) else np.asarray(vs, dtype=np.float64).reshape(y.shape)
    if strategy == "scalar":
        missed = jam.any(axis=1)[usable]
        if missed.any() and (~missed).any():
            y = np.where(missed, y[~missed].max(), y)
    return usable, y, y_var


# --------------------------------------------------------------------------------------------
# Stages
# --------------------------------------------------------------------------------------------

def screening_stage(store: CampaignStore, executor: Executor, s: ScreenSettings, measured: Mapping,
                    out_dir: Path) -> ScreeningReport:
    """Stage 1: DSD runs (resumable) and the section 3.3 / 3.4.1 analysis, written to out_dir."""
    results = run_screening(store, executor, s.table, n_fake=s.n_fake, seeds=list(s.seeds),
                            condition=s.condition, kpis=list(s.kpis), stage="screening")
    return analyse_and_report(results, measured, out_dir, p_threshold=s.p_threshold,
                              selection_fraction=s.selection_fraction,
                              stochastic_threshold=s.stochastic_threshold,
                              extension_factor=s.extension_factor, extension_mode=s.extension_mode,
                              limits=s.physical_limits(), second_order=s.second_order,
                              title=f"Screening of {s.table.k} parameters, condition {s.condition}")


def choose_parameters(screening: ScreeningReport, s: SurrogateStageSettings
                      ) -> tuple[tuple[str, ...], np.ndarray, str]:
    """Calibrated parameters and their ``[2, d]`` bounds, with a note saying where they came from."""
    table = screening.results
    screened = table.levels()
    if s.parameters is not None:
        names, note = tuple(s.parameters), "parameters given in the config"
    elif screening.analysis is not None and screening.analysis.selected_parameters:
        names = tuple(screening.analysis.selected_parameters)
        note = f"Table 5 selected {list(names)}"
    else:
        names = tuple(table.parameter_names)
        note = (f"Table 5 selected no parameter (no KPI had a significant effect in enough replicates), so "
                f"every screened parameter {list(names)} is calibrated")
    proposed = dict(screening.proposal.proposed_bounds) if screening.proposal is not None else {}
    if s.added:
        names = tuple(n for n in names if n not in s.added) + tuple(s.added)
        note += f", and {list(s.added)} added by the config (surrogate.added)"
    rows = []
    for n in names:
        if n in s.added:
            rows.append(tuple(s.added[n]))
        elif s.bounds is not None:
            if n not in s.bounds:
                raise ConfigError(f"surrogate.bounds: no bounds for calibrated parameter {n!r}; given for "
                                  f"{sorted(s.bounds)}")
            rows.append(tuple(s.bounds[n]))
        elif n in proposed:
            rows.append(tuple(proposed[n]))
        elif n in screened:
            rows.append(tuple(screened[n]))
        else:
            raise ConfigError(f"surrogate.parameters: {n!r} was not screened, so it needs surrogate.bounds")
    where = "the config" if s.bounds is not None else (
        "the Table-6 proposal" if proposed else "the screened ranges (no extension was proposed)")
    cut = []
    for i, n in enumerate(names):
        if n not in s.limits:
            continue
        lo, hi = s.limits[n]
        new = (max(rows[i][0], lo), min(rows[i][1], hi))
        if not new[0] < new[1]:
            raise ConfigError(f"surrogate.limits.{n} = {list(s.limits[n])} leaves nothing of its range "
                              f"[{rows[i][0]:g}, {rows[i][1]:g}] from {where}")
        if new != tuple(rows[i]):
            cut.append(f"{n} [{rows[i][0]:g}, {rows[i][1]:g}] -> [{new[0]:g}, {new[1]:g}]")
            rows[i] = new
    bounds = as_bounds(np.array(rows, dtype=np.float64).T, "surrogate.bounds")
    return names, bounds, f"{note}; bounds from {where}" + (f", cut by surrogate.limits: {', '.join(cut)}" if cut else "")


def screening_points(results: ScreeningResults, names: Sequence[str], bounds: np.ndarray, kpis: Sequence[str],
                     nominal: Mapping[str, float], jams: tuple[np.ndarray, np.ndarray] | None = None
                     ) -> tuple[np.ndarray, np.ndarray, str, np.ndarray]:
    """The screening's design points as surrogate data: ``(X [n, d], reps [n, r, M], note, jammed [n, r])``.
    The screening reads a run that jammed as NaN (it measured nothing); ``jams``, ``(jammed [runs, r] bool,
    values [runs, r, M])`` of :func:`bo.screening.pipeline.jammed_screening_runs`, puts those runs back with
    the KPIs they measured and flags them in ``jammed``, so the surrogate stage reads them as its own jammed
    runs (the scalar objective's worst miss, the jam classifier's observations); without it ``jammed`` is
    all False and such a run is one not made.

    Each calibrated parameter (``names``, ``d``) takes the point's screened value or, where the
    screening did not vary it, ``nominal[name]``: the value every screening run had (a
    ``density_<material>``'s nominal density). ``reps`` are the screening's replicate values of
    ``kpis`` (``M``). Points outside ``bounds [2, d]`` (the Table-6 rule may move a bound inside
    the screened range) are left out. The parameters screened but not calibrated vary over these
    points as in the screening; Table 5 found no effect of theirs significant, so what they add
    is scatter, which the points' noise does not count. Raises ConfigError for a calibrated
    parameter that was neither screened nor has a nominal value."""
    screened = list(results.parameter_names)
    cols = []
    for n in names:
        if n in screened:
            cols.append(results.physical[:, screened.index(n)])
        elif n in nominal:
            cols.append(np.full(results.n_runs, float(nominal[n])))
        else:
            raise ConfigError(f"surrogate.reuse_screening: calibrated parameter {n!r} was not screened (screened: "
                              f"{screened}) and has no nominal value (known: {sorted(nominal)}), so the screening's "
                              f"points do not say where they lie in it; set surrogate.reuse_screening=false")
    X = np.stack(cols, axis=1).astype(np.float64).reshape(results.n_runs, len(names))
    inside = screening_points_inside(results, names, bounds, nominal)
    reps = results.kpi_values[:, :, [results.kpi_index(k) for k in kpis]]
    jammed = np.zeros(reps.shape[:2], dtype=bool)
    if jams is not None:
        jammed, values = np.asarray(jams[0], dtype=bool), np.asarray(jams[1], dtype=np.float64)
        if jammed.shape != reps.shape[:2] or values.shape != reps.shape:
            raise ConfigError(f"screening_points: jams of shapes {jammed.shape} and {values.shape}; expected "
                              f"{reps.shape[:2]} and {reps.shape}, the screening's runs, replicates and KPIs {list(kpis)}")
        reps = np.where(jammed[:, :, None], values, reps)
    varied = [n for n in screened if n not in names]
    n_jammed = int(jammed[inside].any(axis=1).sum())
    note = (f"{int(inside.sum())} of the screening's {results.n_runs} design points reused as surrogate data "
            f"({results.n_replicates} runs each)"
            + (f"; {int((~inside).sum())} left out, outside the bounds" if not inside.all() else "")
            + (f"; {varied} vary over them as screened" if varied else "")
            + (f"; {n_jammed} with a run that jammed" if n_jammed else ""))
    return X[inside], np.array(reps[inside]), note, np.array(jammed[inside])


def design_points(store: CampaignStore, keys: Sequence[str], names: Sequence[str], bounds: np.ndarray,
                  seeds: Sequence[int], condition: str | Sequence[str], kpis: Sequence[str],
                  nominal: Mapping[str, float] | None = None) -> tuple[np.ndarray, np.ndarray, str, np.ndarray]:
    """The finished points of earlier initial designs as surrogate data: ``(X [n, d], reps [n, r, M],
    note, jammed [n, r])`` for the ``initial`` batches ``keys`` of ``store`` and the rounds that followed them
    (``round-<k>`` batches of the same key: an earlier campaign's whole surrogate stage), the runs of
    ``condition`` with one of ``seeds`` (``r``), KPIs ``kpis`` (``M``). Several conditions give their KPIs one after the other
    (``M = c * len(kpis)``, NaN where a condition was not run: an objective over several conditions).
    A point with no finished run, or outside ``bounds [2, d]``, is left out (the note counts them).
    ``jammed``: the seeds whose run on any of the conditions jammed (``kpi.loadcell.discharge_jammed``),
    their KPIs as stored (a box that did not flow), so that the surrogate stage reads them as it reads
    its own jammed runs: with an objective condition a jam-only condition was, an earlier campaign's
    jammed run there would otherwise be an observation of Eq. 7 ten times the others.
    A calibrated parameter the design did not vary takes ``nominal[name]``, the value its runs had
    (the model's held value: a campaign that calibrates one more parameter reuses the design of one
    that held it). Raises ConfigError for a key the store does not hold, or a batch whose points vary
    a parameter not in ``names`` or lack one of ``names`` that ``nominal`` does not give."""
    nominal = dict(nominal or {})
    conditions = [condition] if isinstance(condition, str) else list(condition)
    column = {c: j * len(kpis) for j, c in enumerate(conditions)}
    width = len(conditions) * len(kpis)
    held = [k for _, k in store.batch_keys("initial")]
    X, reps, jams, not_run = [], [], [], 0
    index = {int(seed): r for r, seed in enumerate(seeds)}
    tol = 1e-9 * (bounds[1] - bounds[0])
    for key in keys:
        if key not in held:
            raise ConfigError(f"surrogate.reuse_designs: {store.path} holds no initial design {key!r}; it holds "
                              f"{held}")
        stages = [s for s, k in store.batch_keys() if k == key and (s == "initial" or s.startswith("round-"))]
        records = [rec for s in stages for rec in store.records(s, batch_key=key)]
        points: dict[tuple[str, int], tuple[dict, np.ndarray, np.ndarray]] = {}
        for rec in records:
            if set(rec.params) - set(names) or set(names) - set(rec.params) - set(nominal):
                raise ConfigError(f"surrogate.reuse_designs: design {key!r} varies {sorted(rec.params)}; the "
                                  f"calibration varies {sorted(names)}"
                                  + (f" (those it did not vary need the model's value: known {sorted(nominal)})"
                                     if not set(rec.params) - set(names) else ""))
            if rec.status != "done" or rec.condition not in column or rec.seed not in index or rec.kpis is None:
                continue
            _, values, stuck = points.setdefault((rec.stage, rec.point_index), (
                rec.params, np.full((len(seeds), width), np.nan), np.zeros(len(seeds), dtype=bool)))
            j = column[rec.condition]
            values[index[rec.seed], j:j + len(kpis)] = [rec.kpis.get(k, math.nan) for k in kpis]
            stuck[index[rec.seed]] |= discharge_jammed(rec.kpis)
        not_run += len({(rec.stage, rec.point_index) for rec in records}) - len(points)
        for i in sorted(points, key=lambda sp: (stages.index(sp[0]), sp[1])):
            X.append([points[i][0].get(n, nominal.get(n)) for n in names])
            reps.append(points[i][1])
            jams.append(points[i][2])
    X_all = np.array(X, dtype=np.float64).reshape(len(X), len(names))
    reps_all = np.array(reps, dtype=np.float64).reshape(len(reps), len(seeds), width)
    reps_all[~np.isfinite(reps_all)] = np.nan
    inside = np.all((X_all >= bounds[0] - tol) & (X_all <= bounds[1] + tol), axis=1)
    outside = int((~inside).sum())
    X_out, reps_out = X_all[inside], reps_all[inside]
    jammed = np.array(jams, dtype=bool).reshape(len(jams), len(seeds))[inside]
    note = (f"{len(X_out)} finished points of the earlier design{'s' if len(keys) > 1 else ''} {list(keys)} reused"
            + (f"; {outside} left out, outside the bounds" if outside else "")
            + (f"; {not_run} never run" if not_run else "")
            + (f"; {int(jammed.any(axis=1).sum())} jammed" if jammed.any() else ""))
    return X_out, reps_out, note, jammed


def _padded(reps: np.ndarray, width: int) -> np.ndarray:
    """``[n, r, ...]`` replicates as ``[n, width, ...]`` (``width >= r``), the extra runs not run: NaN,
    or False for ``[n, r]`` jam flags."""
    flags = reps.dtype == bool
    out = np.full((reps.shape[0], width, *reps.shape[2:]), False if flags else np.nan, bool if flags else np.float64)
    out[:, :reps.shape[1]] = reps
    return out


def _joined(first: tuple[np.ndarray, np.ndarray, str, np.ndarray], second: tuple[np.ndarray, np.ndarray, str, np.ndarray]
            ) -> tuple[np.ndarray, np.ndarray, str, np.ndarray]:
    """Two sets of points already run, one after the other; replicates padded to the wider (the runs
    added neither measured nor jammed)."""
    width = max(first[1].shape[1], second[1].shape[1])
    both = lambda j: np.concatenate([_padded(first[j], width), _padded(second[j], width)])  # noqa: E731
    return np.concatenate([first[0], second[0]]), both(1), f"{first[2]}; {second[2]}", both(3)


def surrogate_stage(store: CampaignStore, executor: Executor, *, condition: str, names: Sequence[str],
                    bounds: np.ndarray, objective: ObjectiveSpec, s: SurrogateStageSettings,
                    echo: Callable[[str], None] = print, pooled: np.ndarray | None = None,
                    prior: tuple[np.ndarray, np.ndarray, str, np.ndarray] | None = None) -> SurrogateOutcome:
    """Stage 2: LHS then qLogEI rounds through the store until the target R^2 or the budget.
    ``pooled``: ``[M, M]`` one-run covariance of the objective's KPIs for ``s.noise == "pooled"``.
    ``prior``: points already run, ``(X [n0, d], reps [n0, r0, M], note, jammed [n0, r0])``
    (:func:`screening_points`, :func:`design_points`):
    they join the data before the LHS, which shrinks by the usable ones to no less than half its
    size; the budget counts the points this stage runs. With ``s.jam_conditions`` every point this
    stage runs runs on them too, and their runs are kept for the jam classifier only. An objective
    with KPIs of other conditions (:func:`objective_blocks`) has every point run on those too, each
    seed's runs read as one observation of all its KPIs (jammed when any of them jammed); ``prior``
    then gives the calibrated condition's KPIs only, and the others are NaN (not run)."""
    names = tuple(names)
    d = len(names)
    a, config = s.adaptive, s.config
    kpis = objective.kpi_names
    blocks = objective_blocks(objective, condition)
    if prior is not None and prior[1].shape[2] != len(kpis):  # run on the calibrated condition only
        m0 = prior[1].shape[2]
        prior = (prior[0], np.concatenate([prior[1], np.full(prior[1].shape[:2] + (len(kpis) - m0,), np.nan)],
                                          axis=2), prior[2], prior[3])
    need = min(2, len(s.seeds))
    if prior is not None:
        X0, reps0, reuse_note, jam0 = prior
        n0 = X0.shape[0]
        n0_usable = int(_objective_data(reps0, objective, config.strategy, pooled, need, jam0)[0].sum()) if n0 else 0
        full = a.initial_size(d, reused=n0_usable)  # the budget covers the points the design runs
        n_initial = max(full - n0_usable, math.ceil(full / 2))
    else:
        X0, reps0, reuse_note, n0 = np.zeros((0, d)), np.zeros((0, len(s.seeds), len(kpis))), "", 0
        jam0 = np.zeros((0, len(s.seeds)), dtype=bool)
        full = n_initial = a.initial_size(d)
    key = _key("surrogate", names, bounds.tolist(), list(s.seeds), a.seed, n_initial, a.q, config.strategy,
               list(kpis), list(objective.measured), list(objective.weights),
               *([X0.tolist(), reps0.tolist()] if prior is not None else []),
               *([("jam_conditions", list(s.jam_conditions))] if s.jam_conditions else []))
    fitted = [c for c, _ in blocks]
    jam_only = [c for c in s.jam_conditions if c not in fitted]  # an objective condition's runs feed it anyway
    conditions = [*fitted, *jam_only]
    own = list(blocks[0][1])  # every condition's KPIs, as the calibrated condition's
    rows = lambda X: [dict(zip(names, map(float, x))) for x in X]  # noqa: E731
    width = max(len(s.seeds), reps0.shape[1])
    padded = functools.partial(_padded, width=width)

    def evaluated(stage: str, points: Sequence[Mapping[str, float]]
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(X [n, d], reps [n, width, M], jammed [n, width], elsewhere [n, c * width, m + 1])``, the
        last the jam conditions' runs (``m`` KPIs of one condition) with their jam flag in the last column."""
        X = np.array([[p[n] for n in names] for p in points], dtype=np.float64).reshape(len(points), d)
        runs = [padded(_replicates(store, stage, f"{key}", len(points), s.seeds, c, own + [JAMMED]))
                for c in conditions]
        mine = runs[:len(fitted)]
        reps = np.concatenate([r[..., :-1] for r in mine], axis=2)
        jammed = np.any([r[..., -1] == 1 for r in mine], axis=0)
        return X, reps, jammed, np.concatenate(runs[len(fitted):], axis=1) if jam_only \
            else np.zeros((len(points), 0, len(own) + 1))

    if prior is not None:
        echo(f"      {reuse_note}; initial design {n_initial} points instead of {full}")
    points = _run_batch(store, executor, "initial", key,
                        lambda: rows(latin_hypercube(bounds, n_initial, seed=a.seed)), s.seeds, conditions)
    X_new, reps_new, jam_new, elsewhere_new = evaluated("initial", points)
    X_all, reps_all = np.concatenate([X0, X_new]), np.concatenate([padded(reps0), reps_new])
    # the reused points' jammed runs are read as the stage's own (an earlier design's, on the objective's
    # conditions); they were not run on the jam conditions
    jam_all = np.concatenate([padded(jam0), jam_new])
    elsewhere_all = np.concatenate([np.full((n0,) + elsewhere_new.shape[1:], np.nan), elsewhere_new])
    other = [t for t in STRATEGIES if t != config.strategy] if s.compare_strategies else []
    # with fixed pooled noise, the GP that learns its noise is cross-validated on the same points too
    learned = f"{config.strategy}, learned noise" if pooled is not None else None
    r2: dict[str, list[float]] = {config.strategy: [], **{t: [] for t in other}, **({learned: []} if learned else {})}
    rounds: list[RoundRecord] = []
    k = 0
    while True:
        usable, y, y_var = _objective_data(reps_all, objective, config.strategy, pooled, need, jam_all)
        state = SamplingState(X_all[usable], y, y_var)
        if state.n < max(a.n_folds, 2):
            raise ConfigError(f"surrogate stage: only {state.n} of {X_all.shape[0]} points have usable KPIs "
                              f"{list(kpis)} (the rest failed or could not be measured); the GP needs at least "
                              f"{max(a.n_folds, 2)}. Check the DEM runs in {store.path}")
        start = n0 + n_initial + (k - 1) * a.q if k else 0  # the round's first point

        def cross_validate_round() -> dict:
            best = best_kernel_cv(state, bounds, a, config, objective)
            variants = {}
            for t in other:
                u, yy, vv = _objective_data(reps_all, objective, t, pooled, need, jam_all)
                variants[t] = cross_validated_r2(X_all[u], yy, bounds, dataclasses.replace(config, strategy=t,
                                                 kernel=best.kernel), y_var=vv, objective=objective,
                                                 n_folds=a.n_folds, seeds=a.cv_seeds).mean
            if learned:
                u, yy, _ = _objective_data(reps_all, objective, config.strategy, need=need, jammed=jam_all)
                variants[learned] = cross_validated_r2(X_all[u], yy, bounds, dataclasses.replace(config, kernel=best.kernel),
                                                       y_var=None, objective=objective, n_folds=a.n_folds,
                                                       seeds=a.cv_seeds).mean
            # the ceiling with the noise a GP learns on these points: the stop counts against the
            # higher of the two ceilings (RoundRecord.stop_ceiling)
            learned_ceiling = state_learned_ceiling(state, bounds, a, dataclasses.replace(config, kernel=best.kernel),
                                                    objective)
            first = best.results[0]
            return json_ready({"kernel": best.kernel, "mean": best.mean, "std": best.std, "per_seed": list(best.per_seed),
                               "actual": first.actual.tolist(), "predicted": first.predicted.tolist(),
                               "variants": variants, "learned_ceiling": learned_ceiling})  # NaN as null (strict JSON)

        # A round's cross-validation (hundreds of GP fits) is kept in the store, keyed by its data, so
        # a resumed campaign (make run on the shipped store) does not fit them again.
        cv = _stored(store, f"surrogate-cv/{key}/{k}/" + _data_key(
            state.X.tolist(), np.asarray(state.y).tolist(), None if state.y_var is None else np.asarray(state.y_var).tolist(),
            list(a.kernels), list(a.cv_seeds), a.n_folds, sorted(r2)), cross_validate_round)
        num = lambda v: math.nan if v is None else float(v)  # noqa: E731
        record = RoundRecord(index=k, n_points=state.n, X=X_all[start:][usable[start:]].copy(),
                             y=np.array(y[int(usable[:start].sum()):], copy=True), kernel=cv["kernel"],
                             r2_mean=num(cv["mean"]), r2_std=num(cv["std"]), r2_per_seed=tuple(map(num, cv["per_seed"])),
                             actual=np.array(cv["actual"], dtype=np.float64),
                             predicted=np.array(cv["predicted"], dtype=np.float64),
                             r2_ceiling=state_ceiling(state, config, objective),
                             r2_ceiling_learned=num(cv.get("learned_ceiling")))
        rounds.append(record)
        r2[config.strategy].append(record.r2_mean)
        for t, value in cv["variants"].items():
            r2[t].append(num(value))
        extra = "".join(f", {t} {r2[t][-1]:.3f}" for t in r2 if t != config.strategy)
        ceiling = (f"; noise ceiling {record.r2_ceiling:.3f} (learned noise {record.r2_ceiling_learned:.3f}), "
                   f"{record.r2_explained:.3f} of the explainable" if math.isfinite(record.r2_ceiling) else "")
        echo(f"surrogate round {k}: {X_all.shape[0]} points ({state.n} usable), CV R^2 {record.r2_mean:.3f} "
             f"+/- {record.r2_std:.3f} ({record.kernel}, {config.strategy}{extra}{ceiling})")
        if record.reached(a):
            reason = "target_r2"
            break
        if X_all.shape[0] - n0 >= a.budget:
            reason = "budget"
            break
        k += 1
        q = min(a.q, a.budget - (X_all.shape[0] - n0))
        seed = a.seed + X_all.shape[0]
        stage = f"round-{k}"
        batch = _run_batch(store, executor, stage, key, lambda: rows(propose_batch(
            dataclasses.replace(config, kernel=record.kernel), state.X, state.y, bounds, q=q, seed=seed,
            y_var=state.y_var, objective=objective, settings=a.acquisition)), s.seeds, conditions)
        X_new, reps_new, jam_new, elsewhere_new = evaluated(stage, batch)
        X_all = np.concatenate([X_all, X_new])
        reps_all = np.concatenate([reps_all, reps_new])
        jam_all = np.concatenate([jam_all, jam_new])
        elsewhere_all = np.concatenate([elsewhere_all, elsewhere_new])
    usable, _, _ = _objective_data(reps_all, objective, config.strategy, pooled, need, jam_all)
    elsewhere = elsewhere_all[usable]
    return SurrogateOutcome(parameters=names, bounds=bounds, state=state, kpi_replicates=reps_all[usable],
                            rounds=tuple(rounds), stopped_because=reason, points_run=int(X_all.shape[0]) - n0,
                            dropped_points=int((~usable).sum()),
                            strategy_r2={t: tuple(v) for t, v in r2.items()}, reused_points=n0,
                            reuse_note=reuse_note, jammed=jam_all[usable], noise=pooled,
                            elsewhere=elsewhere[..., :-1] if jam_only else None,
                            jammed_elsewhere=elsewhere[..., -1] == 1 if jam_only else None)


def _summary_to_json(summary: GASummary) -> dict:
    return {"best_index": summary.best_index, "restricted": summary.restricted,
            "repetitions": [{"index": r.index, "seed": r.seed, "x": [float(v) for v in r.x],
                             "fitness": float(r.fitness), "n_generations": int(r.n_generations)}
                            for r in summary.repetitions]}


def _summary_from_json(data: Mapping) -> GASummary:
    from bo.surrogate.ga import GARepetition

    reps = tuple(GARepetition(index=int(r["index"]), seed=int(r["seed"]), x=np.asarray(r["x"], dtype=np.float64),
                              fitness=float(r["fitness"]), n_generations=int(r["n_generations"]))
                 for r in data["repetitions"])
    return GASummary(repetitions=reps, best_index=int(data["best_index"]), restricted=bool(data["restricted"]))


def ga_strategy_for(surrogate: SurrogateOutcome, settings: CalibrationSettings) -> tuple[str, str]:
    """``(strategy, why)``: the surrogate strategy the GA minimises (``settings.ga_strategy``) and
    a sentence for the report (empty when it is the rounds' own by default)."""
    own = settings.surrogate.config.strategy
    wanted = settings.ga_strategy
    if wanted is None:
        return own, ""
    if wanted != GA_BEST:
        return wanted, f"The GA minimises the {wanted} surrogate (ga.strategy); the rounds used {own}"
    r2 = {t: surrogate.strategy_r2.get(t, ()) for t in STRATEGIES}
    last = {t: v[-1] for t, v in r2.items() if v and math.isfinite(v[-1])}
    if len(last) < len(STRATEGIES):
        return own, (f"The GA minimises the {own} surrogate, the only strategy cross-validated (ga.strategy: "
                     f"best needs surrogate.compare_strategies)")
    best = max(last, key=lambda t: (last[t], t == own))
    return best, (f"The GA minimises the {best} surrogate, whose Eq. 7 cross-validated best in the last round "
                  "(CV R^2 " + ", ".join(f"{t} {v:.3f}" for t, v in last.items()) + "; ga.strategy: best)")


def _jam_flags(surrogate: SurrogateOutcome, objective: ObjectiveSpec) -> tuple[np.ndarray | None, float]:
    """``(flags, jammed objective)``: the surrogate stage's runs as ``flags [n, r]`` (1 jammed,
    0 flowed, NaN not made), with the jam conditions' runs as ``c * r`` more columns, and Eq. 7 of
    the jammed runs' mean KPIs (a jammed run measures a box that did not flow on any fill, so it is
    scored against the calibrated condition's lab as it is); ``(None, 1.0)`` when no run jammed.
    The points whose every run jammed are among them when the rounds' strategy is scalar (per_kpi
    rounds drop such points)."""
    if surrogate.jammed is None:
        return None, 1.0
    reps, jammed = surrogate.kpi_replicates, surrogate.jammed
    if surrogate.elsewhere is not None:
        # an objective over several conditions has several times one condition's KPIs: a jam
        # condition's run is scored on each of them, a box that did not flow on any fill
        reps = np.concatenate([reps, np.tile(surrogate.elsewhere, reps.shape[2] // surrogate.elsewhere.shape[2])],
                              axis=1)
        jammed = np.concatenate([jammed, surrogate.jammed_elsewhere], axis=1)
    if not jammed.any():
        return None, 1.0
    flags = np.where(np.isfinite(reps).all(axis=2), jammed, np.nan)
    return flags, float(objective(reps[jammed].mean(axis=0)))


def ga_stage(store: CampaignStore, surrogate: SurrogateOutcome, objective: ObjectiveSpec,
             settings: CalibrationSettings, echo: Callable[[str], None] = print) -> GAOutcome:
    """Stage 3: repeated GA on the final surrogate (of :func:`ga_strategy_for`'s strategy), both
    modes; cached as a store artifact."""
    st = surrogate.state
    strategy, why = ga_strategy_for(surrogate, settings)
    config = dataclasses.replace(settings.surrogate.config, kernel=surrogate.rounds[-1].kernel, strategy=strategy)
    X, y, y_var = st.X, st.y, st.y_var
    if strategy != settings.surrogate.config.strategy:  # the same points' data for the other strategy
        usable, y, y_var = _objective_data(surrogate.kpi_replicates, objective, strategy, surrogate.noise,
                                           min(2, len(settings.surrogate.seeds)), surrogate.jammed)
        X = st.X[usable]
    if why:
        echo(f"      {why}")
    flags, jammed_objective = _jam_flags(surrogate, objective)
    run_on = list(dict.fromkeys([settings.condition, *settings.objective_conditions, *settings.surrogate.jam_conditions]))
    where = "" if len(run_on) == 1 else f" on {', '.join(run_on)}"
    jam_note = "" if flags is None else (
        f"{int(np.nansum(flags))} of the surrogate stage's {int(np.isfinite(flags).sum())} runs{where} jammed (Eq. 7 of "
        f"a jammed run {jammed_objective:.2f}), so the GA minimises the expected Eq. 7 of one run, (1 - p) f + p "
        f"{jammed_objective:.2f}, with p the chance that it jams by a GP classifier of those runs")
    if jam_note:
        echo(f"      {jam_note}")
    name = "ga/" + _data_key(X.tolist(), np.asarray(y).tolist(), None if y_var is None else
                        np.asarray(y_var).tolist(), dataclasses.asdict(settings.ga), settings.ga_repetitions,
                        settings.seed, config.kernel, config.strategy,
                        *(() if flags is None else ("jam", np.nan_to_num(flags, nan=-1.0).tolist())))
    cached = store.get_artifact(name, None)
    summaries: dict[str, GASummary | None] = {}
    notes: dict[str, str] = {}
    if cached is not None:
        for mode in _GA_MODES:
            summaries[mode] = _summary_from_json(cached[mode]) if cached[mode] is not None else None
        notes = dict(cached["notes"])
        jam_p = dict(cached.get("jam_probability") or {})
    else:
        jam = None if flags is None else fit_jam_model(st.X, flags, surrogate.bounds)
        for mode in _GA_MODES:
            ga = dataclasses.replace(settings.ga, restricted=(mode == "restricted"))
            try:
                summaries[mode] = repeated_ga(X, y, surrogate.bounds, config,
                                              n_repetitions=settings.ga_repetitions, settings=ga,
                                              seed=settings.seed, y_var=y_var, objective=objective,
                                              names=surrogate.parameters, jam=jam,
                                              jammed_objective=jammed_objective)
            except ConfigError as exc:  # e.g. a lower bound above the restriction limit
                summaries[mode] = None
                notes[mode] = str(exc)
        # the chance that one run of each mode's optimum jams, kept so a resumed campaign needs no refit
        jam_p = {} if jam is None else {m: float(jam.probability(v.best.x[None, :])[0])
                                        for m, v in summaries.items() if v is not None}
        store.put_artifact(name, {m: (_summary_to_json(v) if v is not None else None) for m, v in summaries.items()}
                           | {"notes": notes, "jam_probability": jam_p})
    mode = settings.ga_mode if summaries.get(settings.ga_mode) is not None else next(
        (m for m in _GA_MODES if summaries[m] is not None), None)
    if mode is None:
        raise ConfigError(f"GA: no mode could run: {notes}")
    if mode != settings.ga_mode:
        notes["choice"] = f"ga_mode {settings.ga_mode!r} could not run ({notes.get(settings.ga_mode)}); used {mode!r}"
    best = summaries[mode].best
    calibrated = {n: float(v) for n, v in zip(surrogate.parameters, best.x)}
    p_jam = jam_p.get(mode)  # the chance per mode (jam_p) -> the chosen mode's
    echo(f"GA ({mode}, {strategy}, {settings.ga_repetitions} surrogate trainings): fitness {best.fitness:.4f} at "
         + ", ".join(f"{n} = {v:.4g}" for n, v in calibrated.items())
         + ("" if p_jam is None else f"; P(jam) {p_jam:.3f}"))
    return GAOutcome(summaries=summaries, notes=notes, mode=mode, calibrated=calibrated, strategy=strategy,
                     strategy_note=why, jam_note=jam_note, jam_probability=p_jam)


#: The chance that one run jams, by the GA's classifier, that a set may have and still count as matching
#: the lab in :func:`attainable_stage` (the lab's discharges never jammed).
ATTAINABLE_MAX_JAM = 0.05
#: That cap's name where the report says what holds a range (``AttainableRange.without``).
ATTAINABLE_JAM_NAME = "jam cap"


def attainable_stage(store: CampaignStore, surrogate: SurrogateOutcome, objective: ObjectiveSpec,
                     settings: CalibrationSettings, ga: GAOutcome, lab: Mapping,
                     echo: Callable[[str], None] = print) -> tuple[AttainableRange, ...]:
    """``lab``: the lab's measurement of each objective KPI (:func:`objective_measurements`).
    Per objective KPI, the range of one per-KPI surrogate's mean (the points the GA's surrogate
    was trained on, the last round's kernel, the first training seed) over the box of the chosen GA
    mode, with the other objective KPIs inside the lab's 95 % CI (:mod:`bo.surrogate.attainable`) and,
    when runs of the surrogate stage jammed, a chance of jamming of at most :data:`ATTAINABLE_MAX_JAM`
    by the GA's classifier (:mod:`bo.surrogate.jam`), and for every range that misses the lab what
    each of those constraints holds it from; cached as a store artifact."""
    usable, y, y_var = _objective_data(surrogate.kpi_replicates, objective, "per_kpi", surrogate.noise,
                                       min(2, len(settings.surrogate.seeds)), surrogate.jammed)
    X = surrogate.state.X[usable]
    b = ga_bounds(surrogate.bounds, dataclasses.replace(settings.ga, restricted=(ga.mode == "restricted")),
                  surrogate.parameters)
    measured = {k: (float(v.mean), float(v.ci95)) for k, v in lab.items() if k in objective.kpi_names}
    if set(measured) != set(objective.kpi_names):
        return ()
    config = dataclasses.replace(settings.surrogate.config, kernel=surrogate.rounds[-1].kernel, strategy="per_kpi")
    flags, _ = _jam_flags(surrogate, objective)
    name = "attainable/" + _data_key(X.tolist(), y.tolist(), None if y_var is None else y_var.tolist(), b.tolist(),
                                sorted(measured.items()), config.kernel, settings.seed,
                                dataclasses.asdict(settings.attainable),
                                *(() if flags is None else ("jam", ATTAINABLE_MAX_JAM,
                                                            np.nan_to_num(flags, nan=-1.0).tolist())))
    cached = store.get_artifact(name, None)
    if cached is not None:
        ranges = tuple(AttainableRange.from_dict(r) for r in cached)
    else:
        model = fit_surrogate(X, y, surrogate.bounds, config, y_var=y_var, objective=objective, seed=settings.seed)
        jam = None if flags is None else fit_jam_model(surrogate.state.X, flags, surrogate.bounds)
        cap = None if jam is None else (lambda x: jam.probability(x) - ATTAINABLE_MAX_JAM)
        ranges = attainable_ranges(model, measured, surrogate.parameters, b, settings.attainable, seed=settings.seed,
                                   constraint=cap, constraint_name=ATTAINABLE_JAM_NAME)
        store.put_artifact(name, [r.to_dict() for r in ranges])
    for r in ranges:
        echo(f"      {r.kpi}: " + (f"{r.low:.4g} to {r.high:.4g}" if r.feasible else "no set")
             + f" with the other KPIs inside the lab's CI (lab {r.measured:.4g} +- {r.ci95:.3g})")
    return ranges


def verify(store: CampaignStore, executor: Executor, stage: str, params: Mapping[str, float],
           seeds: Sequence[int], conditions: Sequence[str], kpis: Sequence[str],
           fresh: bool = False) -> dict[str, np.ndarray]:
    """Run one parameter set on conditions with seeds (resumable); ``{condition: [r, M]}``.
    ``fresh``: a batch of its own (key ``fresh/set/...``) whose runs are all computed here,
    none taken from the same runs stored elsewhere."""
    key = ("fresh/" if fresh else "") + "set/" + _key(sorted(params.items()))
    _run_batch(store, executor, stage, key, lambda: [dict(params)], seeds, conditions, share=not fresh)
    return {c: _replicates(store, stage, key, 1, seeds, c, kpis)[0] for c in conditions}


def density_stage(store: CampaignStore, executor: Executor, settings: CalibrationSettings,
                  params: Mapping[str, float], verification: np.ndarray, kpis: Sequence[str],
                  measured: MeasuredData, densities: Mapping[str, float]) -> DensityOutcome:
    """Stage 5: heap height ratio, densities times the ratio, re-verification."""
    if not settings.density_recalibration:
        return DensityOutcome(skipped_because="density_recalibration is off in the config")
    lab = measured.condition(settings.condition).kpis
    if HEAP_HEIGHT_KPI not in lab:
        return DensityOutcome(skipped_because=(
            f"the measured data have no {HEAP_HEIGHT_KPI!r} for condition {settings.condition!r} (the paper "
            f"reports only the ratio H_DEM/H_Exp = 0.93 of its own DEM, Fig. 15)"))
    # a jammed run's lower box holds a few kilograms: no heap of the test
    heights = verification[~_jammed_runs(verification, kpis), list(kpis).index(HEAP_HEIGHT_KPI)]
    heights = heights[np.isfinite(heights)]
    if heights.size == 0:
        return DensityOutcome(skipped_because="no verification run measured a heap height")
    h_exp = float(lab[HEAP_HEIGHT_KPI].mean)
    ratio = float(np.mean(heights / h_exp))
    new = {m: rho * ratio for m, rho in densities.items()}
    reps = verify(store, executor, "density", {**params, **{DENSITY_PREFIX + m: v for m, v in new.items()}},
                  settings.verification_seeds, [settings.condition], kpis)[settings.condition]
    return DensityOutcome(skipped_because=None, heap_dem_m=tuple(float(h) for h in heights), heap_measured_m=h_exp,
                          ratio=ratio, densities=new, agreement=agreement(reps, kpis, lab))


# --------------------------------------------------------------------------------------------
# The campaign
# --------------------------------------------------------------------------------------------

def objective_for(settings: CalibrationSettings, screening: ScreeningReport, measured: Mapping,
                  data: MeasuredData | None = None) -> ObjectiveSpec:
    """Eq. 7 over the configured KPIs, or over the screening's kept KPIs that have a measurement,
    on the calibrated condition (``measured``: its KPIs) and on each of ``settings.objective_conditions``
    (read from ``data``, the whole measured data), each KPI's weight shared equally among the conditions."""
    lab = measured_for(settings.screening.kpis if settings.objective_kpis is None else settings.objective_kpis,
                       measured)
    if settings.objective_kpis is None:
        kpis = [k for k in screening.calibration_kpis if k in lab]
        if not kpis:
            raise ConfigError(f"objective.kpis = null: the screening kept {list(screening.calibration_kpis)}, none of "
                              f"which has a measurement; set objective.kpis")
    else:
        kpis = list(settings.objective_kpis)
        missing = [k for k in kpis if k not in lab]
        if missing:
            raise ConfigError(f"objective.kpis: {missing} have no measurement for condition {settings.condition!r} "
                              f"(measured: {sorted(measured)}; a DEM '<x>_full_<unit>' KPI compares with '<x>_<unit>')")
    weights = None if settings.weights is None else {k: settings.weights.get(k) for k in kpis}
    if weights is not None and (set(settings.weights) - set(kpis) or any(w is None for w in weights.values())):
        raise ConfigError(f"objective.weights: {dict(settings.weights)} must give a weight to exactly the KPIs {kpis}")
    values = {k: float(lab[k].mean) for k in kpis}
    fitted = settings.objective_conditions
    if fitted:
        if data is None:
            raise ConfigError(f"objective.conditions {list(fitted)}: the measured data of those conditions are needed")
        for c in fitted:  # their names are checked against the data with the others (validation_conditions)
            there = measured_for(kpis, data.condition(c).kpis)
            missing = [k for k in kpis if k not in there]
            if missing:
                raise ConfigError(f"objective.conditions: condition {c!r} has no measurement of {missing} "
                                  f"({data.origin}); every objective condition needs the objective's KPIs {kpis}")
            values.update({at_condition(k, c): float(there[k].mean) for k in kpis})
        share = 1.0 / (1 + len(fitted))
        base = weights or {k: 1.0 / len(kpis) for k in kpis}
        weights = {name: base[name.partition(CONDITION_MARK)[0]] * share for name in values}
    return ObjectiveSpec.from_measured(values, weights, source="objective")


def validation_conditions(settings: CalibrationSettings, measured: MeasuredData) -> tuple[str, ...]:
    """The conditions validated; checks every condition name against the measured data."""
    if settings.condition not in measured.names:
        raise out_of_range("condition", settings.condition, f"a condition of the measured data {list(measured.names)}",
                           f"config (measured data {measured.origin})")
    fitted = (settings.condition, *settings.objective_conditions)
    validation = (tuple(c for c in measured.names if c not in fitted)
                  if settings.validation_conditions is None else tuple(settings.validation_conditions))
    for key, names in (("validation.conditions", validation), ("surrogate.jam_conditions",
                                                               settings.surrogate.jam_conditions),
                       ("objective.conditions", settings.objective_conditions)):
        unknown = [c for c in names if c not in measured.names]
        if unknown:
            raise ConfigError(f"{key}: {unknown} are not in the measured data {list(measured.names)} "
                              f"({measured.origin})")
    return validation


def run_calibration(store: CampaignStore, executor: Executor, settings: CalibrationSettings,
                    measured: MeasuredData, out_dir: str | Path, densities: Mapping[str, float],
                    echo: Callable[[str], None] = print, held: Mapping[str, float] | None = None
                    ) -> CalibrationResult:
    """Run (or resume) every stage; see the module docstring. ``densities`` are the model's
    material densities (kg/m^3), which the bulk density check rescales. ``held``: the parameters
    every run of the model has (``DrawDownModel.fixed``); the result reports those the campaign
    did not calibrate beside the calibrated set (``held_parameters``)."""
    settings = settings.validate()
    validation = validation_conditions(settings, measured)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    lab = measured.condition(settings.condition).kpis
    walls: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(stage: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        walls[stage] = round(now - clock, 3)
        clock = now

    echo(f"plan: {campaign_plan(settings, measured).text()}")
    echo(f"[1/6] screening: {settings.screening.table.k} parameters, {len(settings.screening.seeds)} replicates")
    screening = screening_stage(store, executor, settings.screening, lab, out / "screening")
    lap("screening")
    objective = objective_for(settings, screening, lab, measured)
    blocks = objective_blocks(objective, settings.condition)
    own = blocks[0][1]  # the calibrated condition's objective KPIs (every condition's)
    names, bounds, note = choose_parameters(screening, settings.surrogate)
    echo(f"[2/6] surrogate: {note}; objective KPIs {list(objective.kpi_names)}")
    pooled = None
    if settings.surrogate.noise == "pooled":
        table = screening.results
        reps = table.kpi_values[:, :, [table.kpi_index(k) for k in own]]
        inside = screening_points_inside(table, names, bounds)
        where = "the screening's replicates"
        if not inside.all() and inside.sum() >= MIN_POOLED_POINTS:
            # the noise of the region calibrated: outside it (a shape the calibration excludes) the
            # scatter can differ
            reps, where = reps[inside], f"the replicates of the {int(inside.sum())} screening points inside the bounds"
        pooled, dof = pooled_replicate_covariance(reps)
        echo(f"      GP noise of single runs pooled from {where} ({dof} degrees of freedom): "
             + ", ".join(f"{k} sd {math.sqrt(pooled[j, j]):.3g}" for j, k in enumerate(own))
             + (f"; the same for a run on {settings.objective_conditions[0] if len(blocks) == 2 else 'each other objective condition'}"
                ", independent of the calibrated condition's (the screening ran no other)" if len(blocks) > 1 else ""))
        pooled = np.kron(np.eye(len(blocks)), pooled)
    prior = None
    nominal = {DENSITY_PREFIX + m: float(rho) for m, rho in densities.items()}  # every earlier run's densities
    if settings.surrogate.reuse_screening and len(blocks) > 1:
        echo("      the screening's points are no surrogate data: they were not run on "
             + ", ".join(settings.objective_conditions))
    elif settings.surrogate.reuse_screening:
        screened = settings.screening
        prior = screening_points(screening.results, names, bounds, own, nominal, jams=jammed_screening_runs(
            store, screened.table, n_fake=screened.n_fake, seeds=list(screened.seeds), condition=screened.condition,
            kpis=own))
    n_earlier = 0
    if settings.surrogate.reuse_designs:
        earlier = design_points(store, settings.surrogate.reuse_designs, names, bounds, settings.surrogate.seeds,
                                [c for c, _ in blocks], own, {**(held or {}), **nominal})
        prior, n_earlier = (earlier if prior is None else _joined(prior, earlier)), len(earlier[0])
    surrogate = surrogate_stage(store, executor, condition=settings.condition, names=names, bounds=bounds,
                                objective=objective, s=settings.surrogate, echo=echo, pooled=pooled, prior=prior)
    surrogate = dataclasses.replace(surrogate, reused_design_points=n_earlier)
    lap("surrogate")
    echo("[3/6] genetic algorithm on the surrogate")
    ga = ga_stage(store, surrogate, objective, settings, echo)
    echo("      what the bounds allow: each KPI's surrogate range with the others inside the lab's CI")
    attainable = attainable_stage(store, surrogate, objective, settings, ga, objective_measurements(
        objective, settings.condition, measured), echo)
    lap("ga")
    kpis = tuple(dict.fromkeys(list(own) + [HEAP_HEIGHT_KPI]
                               + [k for k in settings.screening.kpis if k in measured_for(settings.screening.kpis, lab)]
                               + [JAMMED]))  # jammed runs are counted, not averaged (agreement)
    echo(f"[4/6] verification: {len(settings.verification_seeds)} replicates of the calibrated set")
    fitted = [c for c, _ in blocks]
    if len(fitted) > 1:
        echo(f"      on {', '.join(fitted)}: the objective's conditions")
    ver_runs = verify(store, executor, "verification", ga.calibrated, settings.verification_seeds, fitted, kpis)
    ver = ver_runs[settings.condition]
    verification = agreement(ver, kpis, lab)
    verification_fitted = {c: agreement(ver_runs[c], kpis, measured.condition(c).kpis) for c in fitted[1:]}
    fresh = None
    if settings.fresh_verification:
        echo(f"      and again on this machine ({len(settings.verification_seeds)} runs, none taken from the store)")
        fresh = agreement(verify(store, executor, "verification", ga.calibrated, settings.verification_seeds,
                                 [settings.condition], kpis, fresh=True)[settings.condition], kpis, lab)
    lap("verification")
    echo("[5/6] bulk density check")
    density = density_stage(store, executor, settings, ga.calibrated, ver, kpis, measured, densities)
    lap("density")
    final = dict(ga.calibrated)
    if density.skipped_because is None and settings.validate_with_density:
        final.update({DENSITY_PREFIX + m: v for m, v in density.densities.items()})
    echo(f"[6/6] validation on {list(validation)}")
    val = {}
    if validation:
        runs = verify(store, executor, "validation", final, settings.validation_seeds, validation, kpis)
        val = {c: agreement(runs[c], kpis, measured.condition(c).kpis) for c in validation}
    lap("validation")
    evaluations, not_ended, jammed = {}, {}, {}
    for rec_stage in ["screening", "initial"] + [f"round-{k}" for k in range(1, len(surrogate.rounds))] \
            + ["verification", "density", "validation"]:
        c = store.counts(rec_stage, computed_only=True)  # a row that took a stored run's result is no DEM run
        evaluations[rec_stage] = c["done"] + c["failed"]
        done = [r.kpis or {} for r in store.records(rec_stage, status="done")]
        # runs stopped while the upper box still emptied (run.max_discharge_time_s reached or null)
        cut = sum(discharge_state(k) == "not ended" for k in done)
        if cut:
            not_ended[rec_stage] = cut
        jams = sum(map(discharge_jammed, done))  # the grains arched over the slot (torchdem.drawdown.JAM_FRACTION)
        if jams:
            jammed[rec_stage] = jams
    evaluations["total"] = sum(evaluations.values())
    return CalibrationResult(settings=settings, screening=screening, objective=objective, parameter_choice_note=note,
                             surrogate=surrogate, ga=ga, verification=verification, density=density,
                             validation=val, final_parameters=final, evaluations=evaluations, wall_time_s=walls,
                             fresh_verification=fresh, discharge_not_ended=not_ended,
                             discharge_jammed=jammed, attainable=attainable,
                             held_parameters={k: float(v) for k, v in (held or {}).items() if k not in final},
                             verification_fitted=verification_fitted)
