"""Genetic-algorithm minimisation of the surrogate mean (paper section 3.5, Tables 8, 9, A.3).

Contract
--------
``minimise_surrogate(fitness, bounds, settings, seed)`` runs pymoo's single-objective ``GA``
over the box and returns the best point and fitness (``GAResult``). ``fitness`` is a fitted
``Surrogate`` (its objective posterior mean, evaluated for the whole population at once under
``torch.no_grad`` in double precision) or any vectorised callable ``[n, d] -> [n]``.

``GASettings`` defaults are the paper's Table A.3: population 1000, at most 2000 generations,
crossover probability 0.6 (SBX, probability that a mating is recombined), mutation probability
0.05 (polynomial mutation, probability that each variable of an offspring is mutated), and
function tolerance 1e-6: the run stops when the best fitness has improved by less than 1e-6
over each of ``stall_generations`` (50, MATLAB's default MaxStallGenerations) consecutive
generations, or at the generation limit. Tournament selection and fitness survival are
pymoo's defaults.

Restricted optimisation (``restricted=True``): the upper bound of every friction and restitution
coefficient becomes ``min(upper, restriction_limit)`` with ``restriction_limit = 0.9`` (the paper
keeps friction and restitution below 0.9); a restricted parameter whose lower bound is not below
the limit is an error. Given the parameter names (``names=``), only the coefficients (``mu_*``,
``e_*``) are restricted, not a density or a clump's lobe spacing; without names every parameter
is. Unrestricted: the whole box.

``repeated_ga(X, y, bounds, config, n_repetitions=10)`` trains the surrogate ``n_repetitions``
times (training seeds ``seed + i``, see ``fit_surrogate``) and runs the GA on each (GA seed
``seed + i``); ``GASummary`` lists per repetition the best parameters and fitness, and
``best`` is the repetition with the lowest fitness (Table 9). ``GASummary.to_text(names)``
prints the table. With ``jam=`` (a :class:`bo.surrogate.jam.JamModel`, when runs of the data
jammed) the fitness is the expected objective of one run, ``(1 - p) f + p jammed_objective``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from pymoo.algorithms.soo.nonconvex.ga import GA
from pymoo.core.problem import Problem
from pymoo.core.termination import TerminateIfAny
from pymoo.operators.crossover.sbx import SBX
from pymoo.operators.mutation.pm import PM
from pymoo.optimize import minimize
from pymoo.termination.ftol import SingleObjectiveSpaceTermination
from pymoo.termination.max_gen import MaximumGenerationTermination
from pymoo.termination.robust import RobustTermination

from bo.surrogate.objective import ObjectiveSpec
from bo.surrogate.gp import Surrogate, SurrogateConfig, as_bounds, fit_surrogate
from bo.surrogate.jam import JamModel, expected_objective
from torchdem.errors import ConfigError, out_of_range

__all__ = ["GASettings", "GAResult", "GARepetition", "GASummary", "ga_bounds",
           "minimise_surrogate", "repeated_ga"]


def _require_int(name: str, value, minimum: int, source: str) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise out_of_range(name, value, f"an integer >= {minimum}", source)


def _require_probability(name: str, value, source: str) -> None:
    if not (isinstance(value, (int, float)) and not isinstance(value, bool)
            and 0.0 <= value <= 1.0):
        raise out_of_range(name, value, "a probability in [0, 1]", source)


@dataclass(frozen=True)
class GASettings:
    """GA settings; defaults are the paper's Table A.3.

    Attributes:
        pop_size: individuals per generation (>= 2).
        n_generations: maximum number of generations (>= 1).
        crossover_prob: probability that a mating is recombined (SBX), in [0, 1].
        mutation_prob: per-variable mutation probability (polynomial mutation), in [0, 1].
        f_tolerance: stop when the best fitness improves by less than this over
            ``stall_generations`` consecutive generations (> 0).
        stall_generations: window of the tolerance test (>= 1).
        restricted: intersect the upper bounds with ``restriction_limit``.
        restriction_limit: the restricted upper bound (paper: 0.9).
        eliminate_duplicates: pymoo's duplicate elimination of offspring (off by default:
            with crossover probability 0.6 and sparse mutation many offspring are parent clones
            and the re-mating loop dominates the run time).
    """

    pop_size: int = 1000
    n_generations: int = 2000
    crossover_prob: float = 0.6
    mutation_prob: float = 0.05
    f_tolerance: float = 1e-6
    stall_generations: int = 50
    restricted: bool = False
    restriction_limit: float = 0.9
    eliminate_duplicates: bool = False

    def __post_init__(self) -> None:
        src = "GASettings"
        _require_int("pop_size", self.pop_size, 2, src)
        _require_int("n_generations", self.n_generations, 1, src)
        _require_probability("crossover_prob", self.crossover_prob, src)
        _require_probability("mutation_prob", self.mutation_prob, src)
        if not (isinstance(self.f_tolerance, (int, float)) and math.isfinite(self.f_tolerance)
                and self.f_tolerance > 0):
            raise out_of_range("f_tolerance", self.f_tolerance, "a finite number > 0", src)
        _require_int("stall_generations", self.stall_generations, 1, src)
        if not isinstance(self.restricted, bool):
            raise out_of_range("restricted", self.restricted, "True or False", src)
        if not (isinstance(self.restriction_limit, (int, float))
                and math.isfinite(self.restriction_limit)):
            raise out_of_range("restriction_limit", self.restriction_limit, "a finite number",
                               src)


@dataclass(frozen=True)
class GAResult:
    """Best point of one GA run.

    Attributes:
        x: ``[d]`` best parameters; fitness: fitness at x (surrogate mean of Eq. 7).
        n_generations: generations evaluated, the initial population included;
        n_evaluations: fitness evaluations (points).
        bounds: ``[2, d]`` box searched (restricted or not); seed: GA seed.
    """

    x: np.ndarray
    fitness: float
    n_generations: int
    n_evaluations: int
    bounds: np.ndarray
    seed: int


@dataclass(frozen=True)
class GARepetition:
    """One row of Table 9: surrogate training ``index`` and its GA optimum."""

    index: int
    seed: int
    x: np.ndarray
    fitness: float
    n_generations: int


@dataclass(frozen=True)
class GASummary:
    """All repetitions (Table 9); ``best_index`` has the lowest fitness."""

    repetitions: tuple[GARepetition, ...]
    best_index: int
    restricted: bool

    @property
    def best(self) -> GARepetition:
        return self.repetitions[self.best_index]

    def to_text(self, names: Sequence[str] | None = None, digits: int = 2) -> str:
        """Table 9 as text; the best repetition is marked with ``*``."""
        d = self.best.x.shape[0]
        names = list(names) if names is not None else [f"x{j + 1}" for j in range(d)]
        if len(names) != d:
            raise ConfigError(f"GASummary.to_text: {len(names)} names for {d} parameters; "
                              f"expected one name per parameter")
        width = max(8, digits + 4, *(len(n) for n in names))
        head = "rep  " + " ".join(n.rjust(width) for n in names) + "   fitness"
        lines = [f"GA over {len(self.repetitions)} surrogate trainings "
                 f"({'restricted' if self.restricted else 'unrestricted'})", head]
        for rep in self.repetitions:
            mark = "*" if rep.index == self.best.index else " "
            vals = " ".join(f"{v:{width}.{digits}f}" for v in rep.x)
            lines.append(f"{rep.index + 1:>3}{mark} {vals}   {rep.fitness:.4f}")
        return "\n".join(lines)


def restricted_columns(names: Sequence[str] | None, d: int) -> np.ndarray:
    """``[d]`` bool: the parameters restricted optimisation caps, the friction and restitution
    coefficients (``mu_*``, ``e_*``) among ``names``; every one when ``names`` is None."""
    if names is None:
        return np.ones(d, dtype=bool)
    if len(names) != d:
        raise ConfigError(f"ga_bounds: {len(names)} names {list(names)} for {d} parameters; expected one per parameter")
    return np.array([n.startswith(("mu_", "e_")) for n in names], dtype=bool)


def ga_bounds(bounds, settings: GASettings = GASettings(), names: Sequence[str] | None = None) -> np.ndarray:
    """The box the GA searches: ``bounds``, with the upper bounds of the restricted parameters
    (:func:`restricted_columns`) capped at the restriction limit when ``settings.restricted``."""
    src = "ga_bounds"
    b = as_bounds(bounds, src)
    if settings.restricted:
        limit = settings.restriction_limit
        capped = restricted_columns(names, b.shape[1])
        bad = np.flatnonzero(capped & (b[0] >= limit))
        if bad.size:
            j = int(bad[0])
            label = f"parameter {j}" if names is None else f"parameter {names[j]!r}"
            raise ConfigError(f"{src}: {label} has lower bound {float(b[0, j])!r}, which "
                              f"is not below the restriction limit {limit!r}; expected lower < "
                              f"{limit} for restricted optimisation")
        b[1] = np.where(capped, np.minimum(b[1], limit), b[1])
    return b


class _FitnessProblem(Problem):
    """Whole-population evaluation: pymoo hands ``X [pop, d]`` and receives ``F [pop, 1]``."""

    def __init__(self, fitness: Callable[[np.ndarray], np.ndarray], b: np.ndarray):
        super().__init__(n_var=b.shape[1], n_obj=1, xl=b[0], xu=b[1], elementwise=False)
        self._fitness = fitness
        self.n_batches = 0  # one batched evaluation per generation (the first: initial pop)

    def _evaluate(self, X, out, *args, **kwargs):
        self.n_batches += 1
        f = np.asarray(self._fitness(np.asarray(X, dtype=np.float64)), dtype=np.float64)
        if f.shape != (X.shape[0],):
            raise ConfigError(f"minimise_surrogate: fitness returned shape {f.shape} for "
                              f"{X.shape[0]} points; expected [{X.shape[0]}]")
        out["F"] = f[:, None]


def minimise_surrogate(fitness: Surrogate | Callable[[np.ndarray], np.ndarray], bounds,
                       settings: GASettings = GASettings(), seed: int = 0,
                       names: Sequence[str] | None = None) -> GAResult:
    """GA minimum of the surrogate mean (or a vectorised ``[n, d] -> [n]`` callable); ``names``
    decide which parameters restricted optimisation caps (:func:`ga_bounds`)."""
    src = "minimise_surrogate"
    b = ga_bounds(bounds, settings, names)
    if isinstance(fitness, Surrogate):
        if fitness.d != b.shape[1]:
            raise ConfigError(f"{src}: bounds have {b.shape[1]} parameters but the surrogate "
                              f"has {fitness.d}; expected the same d")
        fn = fitness.predict_mean  # batched, torch.no_grad, double
    elif callable(fitness):
        fn = fitness
    else:
        raise ConfigError(f"{src}: fitness = {type(fitness).__name__} is not allowed; expected "
                          f"a Surrogate or a callable [n, d] -> [n]")
    algorithm = GA(pop_size=settings.pop_size,
                   crossover=SBX(prob=settings.crossover_prob),
                   mutation=PM(prob=1.0, prob_var=settings.mutation_prob),
                   eliminate_duplicates=settings.eliminate_duplicates)
    termination = TerminateIfAny(
        RobustTermination(SingleObjectiveSpaceTermination(tol=settings.f_tolerance,
                                                          only_feas=True),
                          period=settings.stall_generations),
        MaximumGenerationTermination(settings.n_generations))
    problem = _FitnessProblem(fn, b)
    res = minimize(problem, algorithm, termination, seed=seed, verbose=False)
    x = np.asarray(res.X, dtype=np.float64).reshape(-1)
    return GAResult(x=x, fitness=float(np.asarray(res.F).reshape(-1)[0]),
                    n_generations=problem.n_batches,
                    n_evaluations=int(res.algorithm.evaluator.n_eval), bounds=b, seed=seed)


def repeated_ga(X, y, bounds, config: SurrogateConfig = SurrogateConfig(), *,
                n_repetitions: int = 10, settings: GASettings = GASettings(), seed: int = 0,
                y_var=None, objective: ObjectiveSpec | None = None,
                names: Sequence[str] | None = None, jam: JamModel | None = None,
                jammed_objective: float = 1.0) -> GASummary:
    """Table 9: ``n_repetitions`` surrogate trainings, a GA on each, lowest fitness wins.
    ``jam``: the probability that a run jams (:mod:`bo.surrogate.jam`); the GA then minimises the
    expected objective of one run, ``(1 - p) f + p jammed_objective``."""
    _require_int("n_repetitions", n_repetitions, 1, "repeated_ga")
    reps = []
    for i in range(n_repetitions):
        surrogate = fit_surrogate(X, y, bounds, config, y_var=y_var, objective=objective,
                                  seed=seed + i)
        fitness = surrogate if jam is None else expected_objective(surrogate.predict_mean, jam, jammed_objective)
        res = minimise_surrogate(fitness, bounds, settings, seed=seed + i, names=names)
        reps.append(GARepetition(index=i, seed=seed + i, x=res.x, fitness=res.fitness,
                                 n_generations=res.n_generations))
    best = int(np.argmin([r.fitness for r in reps]))
    return GASummary(repetitions=tuple(reps), best_index=best, restricted=settings.restricted)
