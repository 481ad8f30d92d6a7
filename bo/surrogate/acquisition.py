"""Initial design, q-EI proposals and the adaptive-sampling loop (paper section 3.4.3, Fig. 13).

Contract
--------
``latin_hypercube(bounds, n_points=None, seed=0)`` -> ``[n, d]`` points in the box: a seeded
``scipy.stats.qmc.LatinHypercube`` design scaled to ``bounds [2, d]``; the default size is
``points_per_parameter * d`` (10 per parameter, Loeppky et al. 2009, 70 points for the paper's
7 parameters).

``propose_batch(model_or_config, X, y, bounds, q=10, seed=0)`` -> ``[q, d]`` NumPy array: the
batch maximising ``qLogExpectedImprovement`` for *minimising* the objective. Minimisation is
done by the surrogate's MC objective, which negates Eq. 7 (per_kpi: Eq. 7 of the KPI samples),
with ``best_f = -min(observed objective)``. ``model_or_config`` is a fitted ``Surrogate`` (used
as is) or a ``SurrogateConfig`` (a surrogate is fitted on ``X, y`` with ``seed=None``, i.e. the
deterministic prior-mode start). The acquisition uses a seeded scrambled-Sobol sampler and
``optimize_acqf`` over ``bounds`` with seeded Sobol initial conditions, under a forked,
seeded torch RNG: the same ``(X, y, bounds, q, seed)`` gives the same batch.

Adaptive sampling is a pure function of plain data plus a thin loop:

* ``SamplingState`` (frozen): all evaluations so far, ``X [n, d]``, ``y [n]`` or ``[n, M]``,
  optional ``y_var`` -- exactly what a store holds; rebuild it from stored rows to resume.
* ``next_step(state, bounds, settings, config, objective)`` decides deterministically what to
  evaluate next: while ``n < n_initial``, the remaining rows of the seeded LHS; otherwise it
  cross-validates the surrogate on all data (``RoundRecord``) and stops when the mean CV R^2
  reaches ``target_r2`` (``target_basis="explainable"``: when ``R^2 / ceiling`` does, the
  ceiling being the R^2 the DEM noise leaves attainable, ``bo.surrogate.gp.r2_ceiling``) or
  ``n >= budget``, else proposes ``min(q, budget - n)`` points with
  ``propose_batch(..., seed=settings.seed + n)``. Rounds are defined by counts: round 0 is
  the first ``n_initial`` points, round k adds the next ``q``. Determinism is in terms of
  the evaluated points only: a store interrupted in the middle of a batch should keep the
  proposed (pending) points and finish evaluating them, because ``next_step`` on a partial
  batch proposes afresh.
* ``adaptive_sampling(evaluate, bounds, budget=..., target_r2=...)`` (settings as an
  ``AdaptiveSettings`` and/or keyword overrides of its fields) loops ``next_step`` -> ``evaluate`` ->
  ``state.extend`` and returns every ``RoundRecord`` (round points and values, CV R^2 mean /
  std / per seed, chosen kernel, actual-vs-predicted held-out pairs). ``evaluate`` maps
  points ``[n, d]`` to values ``[n]`` (scalar) or ``[n, M]`` (per_kpi), or to a tuple
  ``(values, variance of the replicate mean)`` of equal shapes.

``plot_actual_vs_predicted(rounds, path)`` writes Fig. 13 (one panel per round, held-out CV
predictions against actual values, with the identity line) as a PNG using matplotlib's Agg
backend.

Every bad input (inverted bounds, ``q < 1``, a budget smaller than the initial design,
``target_r2`` outside (0, 1], wrong shapes) raises ``ConfigError`` naming value, allowed range
and source.
"""
from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch
from botorch.acquisition.logei import qLogExpectedImprovement
from botorch.optim import optimize_acqf
from botorch.sampling import SobolQMCNormalSampler
from scipy.stats import qmc

from bo.surrogate.objective import ObjectiveSpec
from bo.surrogate.gp import (KERNELS, DTYPE, CVSummary, Surrogate, SurrogateConfig, as_bounds,
                          cross_validated_r2, fit_surrogate, learned_noise_ceiling, objective_noise_variance,
                          r2_ceiling, _validate_data)
from torchdem.errors import ConfigError, out_of_range

__all__ = [
    "AcquisitionSettings",
    "AdaptiveSettings",
    "SamplingState",
    "RoundRecord",
    "NextStep",
    "AdaptiveResult",
    "latin_hypercube",
    "propose_batch",
    "next_step",
    "round_record",
    "best_kernel_cv",
    "record_from_cv",
    "adaptive_sampling",
    "plot_actual_vs_predicted",
    "target_reached",
    "state_ceiling",
    "state_learned_ceiling",
    "TARGET_BASES",
    "MIN_CEILING",
]

#: What ``AdaptiveSettings.target_r2`` is a share of: the observed objective's variance (the
#: paper) or the part of it the DEM noise leaves explainable.
TARGET_BASES: tuple[str, ...] = ("total", "explainable")
#: Below this noise ceiling the explained share ``R^2 / ceiling`` is a ratio of two noisy small
#: numbers, and the ``"explainable"`` rule leaves the stop to the budget.
MIN_CEILING = 0.5


def _require_int(name: str, value, minimum: int, source: str) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise out_of_range(name, value, f"an integer >= {minimum}", source)


# --------------------------------------------------------------------------------------------
# Initial design
# --------------------------------------------------------------------------------------------

def latin_hypercube(bounds, n_points: int | None = None, *, points_per_parameter: int = 10,
                    seed: int = 0) -> np.ndarray:
    """Seeded Latin hypercube ``[n, d]`` in ``bounds``; ``n`` defaults to
    ``points_per_parameter * d``."""
    src = "latin_hypercube"
    b = as_bounds(bounds, src)
    d = b.shape[1]
    _require_int("points_per_parameter", points_per_parameter, 1, src)
    n = points_per_parameter * d if n_points is None else n_points
    _require_int("n_points", n, 1, src)
    unit = qmc.LatinHypercube(d=d, seed=np.random.default_rng(seed)).random(n)
    return qmc.scale(unit, b[0], b[1])


# --------------------------------------------------------------------------------------------
# One batch of proposals
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class AcquisitionSettings:
    """Numerical settings of the qLogEI maximisation.

    Attributes:
        num_restarts: L-BFGS-B restarts of ``optimize_acqf`` (>= 1).
        raw_samples: Sobol candidates screened for the restarts (>= num_restarts).
        mc_samples: quasi-MC posterior samples of the acquisition (>= 16).
        maxiter: L-BFGS-B iterations per restart (>= 1).
    """

    num_restarts: int = 10
    raw_samples: int = 512
    mc_samples: int = 256
    maxiter: int = 200

    def __post_init__(self) -> None:
        src = "AcquisitionSettings"
        _require_int("num_restarts", self.num_restarts, 1, src)
        _require_int("raw_samples", self.raw_samples, self.num_restarts, src)
        _require_int("mc_samples", self.mc_samples, 16, src)
        _require_int("maxiter", self.maxiter, 1, src)


def propose_batch(model_or_config: Surrogate | SurrogateConfig, X, y, bounds, q: int = 10,
                  seed: int = 0, *, y_var=None, objective: ObjectiveSpec | None = None,
                  settings: AcquisitionSettings = AcquisitionSettings()) -> np.ndarray:
    """``q`` new points ``[q, d]`` maximising qLogEI for minimisation (module docstring)."""
    src = "propose_batch"
    _require_int("q", q, 1, src)
    if isinstance(model_or_config, SurrogateConfig):
        surrogate = fit_surrogate(X, y, bounds, model_or_config, y_var=y_var,
                                  objective=objective)
        b = surrogate.bounds
    elif isinstance(model_or_config, Surrogate):
        surrogate = model_or_config
        b, _, _, _ = _validate_data(X, y, bounds, surrogate.config, y_var, surrogate.objective,
                                    src, min_points=1)
        if b.shape != surrogate.bounds.shape:
            raise ConfigError(f"{src}: bounds have shape {b.shape} but the surrogate was fitted "
                              f"on bounds of shape {surrogate.bounds.shape}; expected the same d")
    else:
        raise ConfigError(f"{src}: model_or_config = {type(model_or_config).__name__} is not "
                          f"allowed; expected a fitted Surrogate or a SurrogateConfig")
    yy = np.asarray(y, dtype=np.float64)
    observed = yy.reshape(-1) if surrogate.config.strategy == "scalar" \
        else surrogate.objective(yy)
    best_f = -float(np.min(observed))  # maximisation of the negated objective
    bounds_t = torch.as_tensor(b, dtype=DTYPE)
    with torch.random.fork_rng(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.manual_seed(seed)
        acqf = qLogExpectedImprovement(
            model=surrogate.model, best_f=best_f,
            sampler=SobolQMCNormalSampler(sample_shape=torch.Size([settings.mc_samples]),
                                          seed=seed),
            objective=surrogate.mc_objective())
        candidates, _ = optimize_acqf(
            acqf, bounds=bounds_t, q=q, num_restarts=settings.num_restarts,
            raw_samples=settings.raw_samples,
            options={"seed": seed, "maxiter": settings.maxiter})
    x = candidates.detach().numpy().reshape(q, -1)
    return np.clip(x, b[0], b[1])


# --------------------------------------------------------------------------------------------
# Adaptive sampling: plain-data state, deterministic decisions, thin loop
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class AdaptiveSettings:
    """Settings of the adaptive-sampling loop.

    Attributes:
        budget: maximum number of evaluated points (>= n_initial).
        n_initial: initial LHS size; None means ``points_per_parameter * d``.
        points_per_parameter: LHS points per parameter when ``n_initial`` is None (paper: 10).
        q: points per adaptive round (paper: 10), >= 1.
        target_r2: stop when the mean CV R^2 reaches this, in (0, 1] (paper: 0.95).
        target_basis: what ``target_r2`` is a share of. ``"total"`` (the paper): the variance of
            the observed objective, noise included, so a noisy objective may never reach 0.95.
            ``"explainable"``: the variance left once the DEM noise is taken out, ``R^2 /
            ceiling`` (``RoundRecord.r2_explained``); it needs the points' noise (``y_var``), and
            while the ceiling is below ``MIN_CEILING`` (noise swamps the design's spread) only
            the budget stops the loop.
        n_folds: folds of the CV R^2, >= 2.
        cv_seeds: fold-assignment seeds; mean and std over them (paper: 5 seeds).
        kernels: candidate kernels; with more than one, every round picks the one with the
            highest mean CV R^2 and proposes with it.
        seed: seed of the LHS and base of the proposal seeds (``seed + n``).
        acquisition: ``AcquisitionSettings`` of ``propose_batch``.
    """

    budget: int
    n_initial: int | None = None
    points_per_parameter: int = 10
    q: int = 10
    target_r2: float = 0.95
    target_basis: str = "total"
    n_folds: int = 5
    cv_seeds: tuple[int, ...] = (0, 1, 2, 3, 4)
    kernels: tuple[str, ...] = ("matern52",)
    seed: int = 0
    acquisition: AcquisitionSettings = AcquisitionSettings()

    def __post_init__(self) -> None:
        src = "AdaptiveSettings"
        _require_int("budget", self.budget, 1, src)
        if self.n_initial is not None:
            _require_int("n_initial", self.n_initial, 2, src)
            if self.budget < self.n_initial:
                raise out_of_range("budget", self.budget, f">= the initial design size "
                                   f"n_initial = {self.n_initial}", src)
        _require_int("points_per_parameter", self.points_per_parameter, 1, src)
        _require_int("q", self.q, 1, src)
        if not (isinstance(self.target_r2, (int, float)) and 0.0 < self.target_r2 <= 1.0):
            raise out_of_range("target_r2", self.target_r2, "a number in (0, 1]", src)
        if self.target_basis not in TARGET_BASES:
            raise out_of_range("target_basis", self.target_basis, f"one of {list(TARGET_BASES)}", src)
        _require_int("n_folds", self.n_folds, 2, src)
        object.__setattr__(self, "cv_seeds", tuple(self.cv_seeds))
        if not self.cv_seeds:
            raise out_of_range("cv_seeds", self.cv_seeds, "at least one seed", src)
        object.__setattr__(self, "kernels", tuple(self.kernels))
        bad = [k for k in self.kernels if k not in KERNELS]
        if not self.kernels or bad:
            raise out_of_range("kernels", self.kernels, f"a non-empty subset of {list(KERNELS)}",
                               src)

    def initial_size(self, d: int, reused: int = 0) -> int:
        """Initial design size for ``d`` parameters. Checks the budget against the points the stage
        runs for it: the design less ``reused`` points already run (screening points inside the
        bounds), to no less than half of it."""
        n = self.n_initial if self.n_initial is not None else self.points_per_parameter * d
        runs = max(n - reused, math.ceil(n / 2)) if reused > 0 else n
        if self.budget < runs:
            less = f", less {reused} points already run, to no less than half" if reused > 0 else ""
            raise out_of_range("budget", self.budget, f">= the {runs} points the initial design runs "
                               f"({self.points_per_parameter} points x {d} parameters{less})",
                               "AdaptiveSettings")
        if n < self.n_folds:
            raise out_of_range("n_folds", self.n_folds, f"<= the initial design size {n}",
                               "AdaptiveSettings")
        return n


@dataclass(frozen=True)
class SamplingState:
    """All evaluations so far (plain data; rebuild from a store to resume).

    Attributes:
        X: ``[n, d]`` evaluated points, in evaluation order.
        y: ``[n]`` objective values (scalar) or ``[n, M]`` KPI values (per_kpi).
        y_var: variance of the replicate mean, shape of ``y``, or None.
    """

    X: np.ndarray
    y: np.ndarray
    y_var: np.ndarray | None = None

    @classmethod
    def empty(cls, d: int, n_outputs: int | None = None) -> "SamplingState":
        """No evaluations yet; ``n_outputs`` None for scalar, M for per_kpi."""
        shape = (0,) if n_outputs is None else (0, n_outputs)
        return cls(np.zeros((0, d)), np.zeros(shape), None)

    @property
    def n(self) -> int:
        return int(self.X.shape[0])

    def extend(self, X_new, y_new, y_var_new=None) -> "SamplingState":
        """A new state with the evaluations appended (shapes checked)."""
        x = np.asarray(X_new, dtype=np.float64)
        yy = np.asarray(y_new, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != self.X.shape[1]:
            raise ConfigError(f"SamplingState.extend: X_new has shape {x.shape}; expected "
                              f"[k, {self.X.shape[1]}]")
        if yy.shape != (x.shape[0],) + self.y.shape[1:]:
            raise ConfigError(f"SamplingState.extend: values have shape {yy.shape}; expected "
                              f"{(x.shape[0],) + self.y.shape[1:]} (one per point)")
        if (y_var_new is None) != (self.y_var is None) and self.n > 0:
            raise ConfigError("SamplingState.extend: every evaluation must come with a replicate "
                              "variance, or none may")
        yv = None
        if y_var_new is not None:
            v = np.asarray(y_var_new, dtype=np.float64)
            if v.shape != yy.shape:
                raise ConfigError(f"SamplingState.extend: variances have shape {v.shape}; "
                                  f"expected {yy.shape}")
            yv = v if self.y_var is None else np.concatenate([self.y_var, v])
        return SamplingState(np.concatenate([self.X, x]), np.concatenate([self.y, yy]), yv)


@dataclass(frozen=True)
class RoundRecord:
    """What one round added and how good the surrogate was on all data after it.

    Attributes:
        index: 0 for the initial design, k for the k-th adaptive round.
        n_points: points evaluated after this round.
        X: ``[k, d]`` the round's points; y: their values (``[k]`` or ``[k, M]``).
        kernel: kernel with the best mean CV R^2 (the one used for the next proposal).
        r2_mean, r2_std, r2_per_seed: CV R^2 over ``cv_seeds`` (Table 7).
        actual, predicted: ``[n_points]`` objective values and held-out CV predictions of
            the first CV seed (Fig. 13).
        r2_ceiling: the CV R^2 the points' DEM noise leaves attainable
            (``bo.surrogate.gp.r2_ceiling``); NaN where the noise is not known.
        r2_ceiling_learned: the same with the noise level a GP learns on the points
            (``bo.surrogate.gp.learned_noise_ceiling``); NaN where not computed.
    """

    index: int
    n_points: int
    X: np.ndarray
    y: np.ndarray
    kernel: str
    r2_mean: float
    r2_std: float
    r2_per_seed: tuple[float, ...]
    actual: np.ndarray
    predicted: np.ndarray
    r2_ceiling: float = math.nan
    r2_ceiling_learned: float = math.nan

    @property
    def stop_ceiling(self) -> float:
        """The ceiling the stop rule counts against: the higher of the two (the smaller noise),
        so a noise estimate too large for these points cannot stop the rounds early; NaN when
        neither is known."""
        known = [c for c in (self.r2_ceiling, self.r2_ceiling_learned) if math.isfinite(c)]
        return max(known) if known else math.nan

    @property
    def r2_explained(self) -> float:
        """Share of the explainable variance explained, ``r2_mean / stop_ceiling`` (NaN while the
        ceiling is unknown or below ``MIN_CEILING``)."""
        if not (self.stop_ceiling >= MIN_CEILING):
            return math.nan
        return self.r2_mean / self.stop_ceiling

    def reached(self, settings: "AdaptiveSettings") -> bool:
        """Whether this round meets the stop rule of ``settings`` (``target_r2`` on its basis)."""
        return target_reached(self.r2_mean, self.stop_ceiling, settings)


def target_reached(r2_mean: float, ceiling: float, settings: AdaptiveSettings) -> bool:
    """The stop rule: ``r2_mean >= target_r2`` (basis ``"total"``), or ``r2_mean / ceiling >=
    target_r2`` with ``ceiling >= MIN_CEILING`` (basis ``"explainable"``)."""
    if settings.target_basis == "total":
        return r2_mean >= settings.target_r2
    return bool(ceiling >= MIN_CEILING and r2_mean / ceiling >= settings.target_r2)


def state_learned_ceiling(state: "SamplingState", bounds, settings: "AdaptiveSettings", config: SurrogateConfig,
                          objective: ObjectiveSpec | None = None) -> float:
    """``learned_noise_ceiling`` of the points of ``state`` where the stop rule uses it (basis
    ``"explainable"``, the points' noise known); NaN otherwise."""
    if state.y_var is None or settings.target_basis != "explainable" or state.n < 2:
        return math.nan
    return learned_noise_ceiling(state.X, state.y, bounds, config, objective=objective)


def state_ceiling(state: "SamplingState", config: SurrogateConfig,
                  objective: ObjectiveSpec | None = None) -> float:
    """``r2_ceiling`` of the objective values of ``state`` (NaN without ``y_var``)."""
    if state.y_var is None or state.n < 2:
        return math.nan
    y = np.asarray(state.y, dtype=np.float64)
    actual = y.reshape(-1) if config.strategy == "scalar" else np.asarray(objective(y))
    if float(actual.var()) == 0.0:
        return math.nan
    return r2_ceiling(actual, objective_noise_variance(y, state.y_var, objective, config.strategy))


@dataclass(frozen=True)
class NextStep:
    """Decision of ``next_step``: points to evaluate next, or why the loop is done.

    Attributes:
        points: ``[k, d]`` next points (``k = 0`` when done).
        done: True when sampling should stop.
        reason: ``"initial_design"``, ``"propose"``, ``"target_r2"`` or ``"budget"``.
        record: the ``RoundRecord`` of the round just completed (None during the initial
            design).
    """

    points: np.ndarray
    done: bool
    reason: str
    record: RoundRecord | None


@dataclass(frozen=True)
class AdaptiveResult:
    """Outcome of ``adaptive_sampling``: final state, per-round records, stop reason."""

    state: SamplingState
    rounds: tuple[RoundRecord, ...]
    stopped_because: str


def _round_bounds(n: int, n_initial: int, q: int) -> tuple[int, int, int]:
    """``(index, start, stop)`` of the round that ends at the n-th point."""
    if n <= n_initial:
        return 0, 0, n
    index = math.ceil((n - n_initial) / q)
    return index, n_initial + (index - 1) * q, n


def best_kernel_cv(state: SamplingState, bounds, settings: AdaptiveSettings,
                   config: SurrogateConfig = SurrogateConfig(),
                   objective: ObjectiveSpec | None = None) -> CVSummary:
    """Cross-validated R^2 of every candidate kernel on all ``state`` data; the best summary."""
    b = as_bounds(bounds, "best_kernel_cv")
    best: CVSummary | None = None
    for kernel in settings.kernels:
        summary = cross_validated_r2(state.X, state.y, b, dataclasses.replace(config,
                                     kernel=kernel), y_var=state.y_var, objective=objective,
                                     n_folds=settings.n_folds, seeds=settings.cv_seeds)
        if best is None or summary.mean > best.mean:
            best = summary
    return best


def round_record(state: SamplingState, bounds, settings: AdaptiveSettings,
                 config: SurrogateConfig = SurrogateConfig(),
                 objective: ObjectiveSpec | None = None) -> RoundRecord:
    """The round that ended at the last point of ``state`` (at least the initial design),
    with the best kernel's cross-validated R^2 on all data (Table 7, Fig. 13)."""
    b = as_bounds(bounds, "round_record")
    n_initial = settings.initial_size(b.shape[1])
    if state.n < n_initial:
        raise ConfigError(f"round_record: {state.n} points evaluated; a round ends at or after the "
                          f"initial design of {n_initial} points")
    best = best_kernel_cv(state, b, settings, config, objective)
    index, start, stop = _round_bounds(state.n, n_initial, settings.q)
    return record_from_cv(best, index, state.n, state.X[start:stop], state.y[start:stop],
                          ceiling=state_ceiling(state, config, objective),
                          learned_ceiling=state_learned_ceiling(state, b, settings,
                                                                dataclasses.replace(config, kernel=best.kernel), objective))


def record_from_cv(summary: CVSummary, index: int, n_points: int, X, y,
                   ceiling: float = math.nan, learned_ceiling: float = math.nan) -> RoundRecord:
    """``RoundRecord`` of round ``index`` (its points ``X``, values ``y``) from a CV summary."""
    first = summary.results[0]
    return RoundRecord(index=index, n_points=n_points, X=np.array(X, copy=True),
                       y=np.array(y, copy=True), kernel=summary.kernel, r2_mean=summary.mean,
                       r2_std=summary.std, r2_per_seed=summary.per_seed,
                       actual=first.actual.copy(), predicted=first.predicted.copy(),
                       r2_ceiling=float(ceiling), r2_ceiling_learned=float(learned_ceiling))


def next_step(state: SamplingState, bounds, settings: AdaptiveSettings,
              config: SurrogateConfig = SurrogateConfig(),
              objective: ObjectiveSpec | None = None) -> NextStep:
    """Deterministic decision from the evaluations so far (see the module docstring)."""
    src = "next_step"
    b = as_bounds(bounds, src)
    d = b.shape[1]
    n_initial = settings.initial_size(d)
    if state.X.ndim != 2 or state.X.shape[1] != d:
        raise ConfigError(f"{src}: state.X has shape {state.X.shape}; expected [n, {d}]")
    n = state.n
    if n < n_initial:
        design = latin_hypercube(b, n_initial, seed=settings.seed)
        return NextStep(points=design[n:], done=False, reason="initial_design", record=None)

    record = round_record(state, b, settings, config, objective)
    empty = np.zeros((0, d))
    if record.reached(settings):
        return NextStep(points=empty, done=True, reason="target_r2", record=record)
    if n >= settings.budget:
        return NextStep(points=empty, done=True, reason="budget", record=record)
    points = propose_batch(dataclasses.replace(config, kernel=record.kernel), state.X, state.y, b,
                           q=min(settings.q, settings.budget - n), seed=settings.seed + n,
                           y_var=state.y_var, objective=objective,
                           settings=settings.acquisition)
    return NextStep(points=points, done=False, reason="propose", record=record)


def _call_evaluate(evaluate: Callable, points: np.ndarray, state: SamplingState):
    out = evaluate(points)
    values, var = out if isinstance(out, tuple) else (out, None)
    values = np.asarray(values, dtype=np.float64)
    expected = (points.shape[0],) + state.y.shape[1:]
    if values.shape != expected:
        raise ConfigError(f"adaptive_sampling: evaluate returned values of shape {values.shape} "
                          f"for {points.shape[0]} points; expected {expected}")
    return values, var


def adaptive_sampling(evaluate: Callable, bounds, settings: AdaptiveSettings | None = None, *,
                      config: SurrogateConfig = SurrogateConfig(),
                      objective: ObjectiveSpec | None = None,
                      state: SamplingState | None = None,
                      on_round: Callable[[RoundRecord], None] | None = None,
                      **setting_overrides) -> AdaptiveResult:
    """Run the adaptive-sampling loop until ``target_r2`` or the budget.

    Settings come from ``settings`` and/or keyword overrides of its fields, e.g.
    ``adaptive_sampling(evaluate, bounds, budget=110, target_r2=0.95)``; ``budget`` is
    required. ``state`` resumes from earlier evaluations (default: none). ``on_round`` is
    called with every ``RoundRecord`` as soon as it is computed (e.g. to store or plot it).
    """
    src = "adaptive_sampling"
    fields = {f.name for f in dataclasses.fields(AdaptiveSettings)}
    unknown = sorted(set(setting_overrides) - fields)
    if unknown:
        raise ConfigError(f"{src}: unknown setting(s) {unknown}; expected fields of "
                          f"AdaptiveSettings: {sorted(fields)}")
    if settings is None:
        if "budget" not in setting_overrides:
            raise ConfigError(f"{src}: no budget given; expected budget=<max evaluations> or "
                              f"settings=AdaptiveSettings(budget=...)")
        settings = AdaptiveSettings(**setting_overrides)
    elif setting_overrides:
        settings = dataclasses.replace(settings, **setting_overrides)
    b = as_bounds(bounds, src)
    d = b.shape[1]
    settings.initial_size(d)  # budget vs initial design, before any evaluation
    if config.strategy == "per_kpi" and objective is None:
        raise ConfigError(f"{src}: strategy 'per_kpi' needs objective=ObjectiveSpec(...)")
    if state is None:
        state = SamplingState.empty(d, objective.n_kpis if config.strategy == "per_kpi"
                                    else None)
    rounds: list[RoundRecord] = []
    while True:
        step = next_step(state, b, settings, config, objective)
        if step.record is not None:
            rounds.append(step.record)
            if on_round is not None:
                on_round(step.record)
        if step.done:
            return AdaptiveResult(state=state, rounds=tuple(rounds),
                                  stopped_because=step.reason)
        values, var = _call_evaluate(evaluate, step.points, state)
        state = state.extend(step.points, values, var)


# --------------------------------------------------------------------------------------------
# Fig. 13
# --------------------------------------------------------------------------------------------

def plot_actual_vs_predicted(rounds: Sequence[RoundRecord], path, *,
                             title: str = "Actual vs predicted (held-out CV)") -> Path:
    """PNG with one panel per round: held-out predictions vs actual objective values, the
    identity line, and the round's CV R^2 (mean +- std). Returns the path written."""
    if not rounds:
        raise ConfigError("plot_actual_vs_predicted: no rounds to plot; expected >= 1 "
                          "RoundRecord")
    # A bare Figure renders with the Agg canvas without touching pyplot's global backend.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    n = len(rounds)
    cols = min(n, 3)
    rows = math.ceil(n / cols)
    fig = Figure(figsize=(4.0 * cols, 4.0 * rows))
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, cols, squeeze=False)
    lo = min(float(min(r.actual.min(), r.predicted.min())) for r in rounds)
    hi = max(float(max(r.actual.max(), r.predicted.max())) for r in rounds)
    pad = 0.05 * (hi - lo or 1.0)
    for ax, rec in zip(axes.flat, rounds):
        new = np.zeros(rec.n_points, dtype=bool)
        new[rec.n_points - rec.X.shape[0]:] = True
        ax.scatter(rec.actual[~new], rec.predicted[~new], s=14, c="tab:blue",
                   label="earlier points")
        ax.scatter(rec.actual[new], rec.predicted[new], s=14, c="tab:red",
                   label="this round")
        ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], "k--", lw=1)
        ax.set_xlim(lo - pad, hi + pad)
        ax.set_ylim(lo - pad, hi + pad)
        name = "initial design" if rec.index == 0 else f"iteration {rec.index}"
        ax.set_title(f"{name}: n = {rec.n_points}\nR$^2$ = {rec.r2_mean:.3f} "
                     f"$\\pm$ {rec.r2_std:.3f} ({rec.kernel})", fontsize=9)
        ax.set_xlabel("actual objective")
        ax.set_ylabel("predicted objective")
        ax.legend(fontsize=7, loc="upper left")
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    fig.suptitle(title)
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    return out
