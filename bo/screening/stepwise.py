"""Screening analysis: stepwise regression on a definitive screening design, repeated per
replicate, and the paper's Table 5 (how often each parameter is significant, with its sign).

Contract
--------
``ScreeningResults`` holds what the screening runs produced: parameter names, the design (coded
-1 / 0 / +1 and physical values, ``[runs, k]``), one DEM seed per replicate, and the KPI values
``[runs, replicates, n_kpi]``. A replicate is one full pass over the design with one seed (the
paper repeats its 29-run DSD five times, section 3.3).

Failed measurements are ``NaN``. They are handled by dropping, per KPI and per replicate, the
runs whose value is NaN (listwise deletion) before the regression; ``StepwiseFit.n_runs_used``
says how many runs were left. A (KPI, replicate) pair with fewer than ``MIN_RUNS_PER_FIT`` finite
values is not fitted (``StepwiseFit.skipped`` gives the reason) and does not count in the
denominator of Table 5, so a cell reads ``+4/4`` rather than ``+4/5`` when one replicate failed.
Dropping runs breaks the orthogonality of the DSD; the regression stays valid, only less
efficient. ``inf`` is never a valid KPI value and is rejected.

``stepwise_regression(coded, y, names, p_threshold)`` is a bidirectional stepwise selection of
main effects (coded factors, intercept always in) with ordinary least squares from statsmodels.
It starts from the full main-effects model when that leaves at least ``MIN_ERROR_DF`` residual
degrees of freedom (a DSD's fake factors are there to give this error estimate), else from the
intercept alone:

1. forward: among the factors not in the model, fit the model plus each one and take the one
   with the smallest p-value (t-test of its coefficient); it enters if ``p < p_threshold``;
2. backward: refit; while the largest p-value in the model is ``> p_threshold``, remove it;
3. repeat until neither step changes the model (a model seen before also stops the loop).

Why the full start: forward selection from the intercept judges each factor against a residual
that still holds every other active effect, so several comparable effects mask each other. In a
13-run DSD (4 factors, 2 fake) with three equal effects of 1.2 per coded unit and noise 0.15, no
single factor reached p < 0.01 from the intercept (p ~ 0.03), although each has p < 1e-6 in the
full model.

A candidate that would leave no residual degree of freedom or make the design rank deficient is
not considered. The final model's ANOVA table (``StepwiseFit.anova``, computed on first use)
is statsmodels ``anova_lm(typ=2)`` (for the orthogonal DSD, type I, II and III sums of squares
coincide). The paper used JMP's "Fit Definitive Screening" platform with a p-value threshold
of 0.01; that platform also fits second-order effects in a second stage. With
``second_order=True`` the stepwise does the same, under strong heredity:

4. second stage: with the main effects found forced in, the squares (of factors screened at three
   levels) and two-factor interactions of those factors enter and leave by the same rule;
5. the main effects are then selected again against the smaller residual, the parents of the
   second-order terms kept; stages 4 and 5 repeat until neither changes.

Why: a DSD's main effects are orthogonal to every square and two-factor interaction, so the
estimates do not change, but a strong curvature or interaction left out inflates the residual
that tests them. On the lab geometry's screening (``profile=lab``), the sinter lobe spacing's
curvature and its interaction with the sinter-sinter friction left a residual sd of 3.4 deg on the
shear angle against a replicate noise of 1.5, and masked the pellet friction (removed at p = 0.023 and
0.033 in the two replicates); with those terms in, it entered at p = 0.0054 and 0.0038. Table 5
counts main effects only, either way.

``count_significance(fits, ...)`` tallies, per parameter and KPI, in how many analysed
replicates the parameter was in the final model with a positive and with a negative
coefficient. A parameter is *selected* when it is significant (either sign) in at least
``selection_fraction`` (default 0.8, i.e. 4 of 5) of the analysed replicates of at least one
KPI. ``SignificanceTable.to_markdown()`` and ``to_dict()`` give Table 5's layout: rows
parameters, columns KPIs, cells ``"+5/5"``, ``"-4/5"``, ``"+3/5, -1/5"`` (mixed signs) or
``""`` (never significant), and a last column ``selected`` yes/no.

``analyse_screening(results, ...)`` does both for every KPI (or a chosen subset, e.g. without
the segregation KPIs the variance decomposition excludes).

Reference: A. Hadi, Y. Pang, D. Schott, "Systematic DEM calibration of two-component mixtures
using AI-accelerated surrogate models", section 3.3 and Table 5.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from bo.design.dsd import ParameterTable, scale_design
from torchdem.errors import ConfigError, out_of_range

__all__ = [
    "MIN_RUNS_PER_FIT",
    "ScreeningResults",
    "StepwiseFit",
    "SignificanceTable",
    "ScreeningAnalysis",
    "stepwise_regression",
    "count_significance",
    "analyse_screening",
]

#: Fewest finite KPI values a (KPI, replicate) regression needs: intercept, one factor and one
#: residual degree of freedom.
MIN_RUNS_PER_FIT = 3
_LEVEL_ATOL = 1e-9  # coded levels must be -1, 0, +1 to this tolerance
_MAX_STEPWISE_ITERATIONS = 1000  # guard; a k-factor stepwise needs at most ~2k steps


def _check_fraction(name: str, value, source: str, allowed: str = "a number in (0, 1)",
                    include_one: bool = False) -> float:
    """Return ``value`` as a float in (0, 1) (or (0, 1] with ``include_one``), else raise."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise out_of_range(name, value, allowed, source)
    v = float(value)
    if not (0.0 < v < 1.0 or (include_one and v == 1.0)):
        raise out_of_range(name, value, allowed, source)
    return v


def _check_names(what: str, names, source: str, minimum: int = 1) -> tuple[str, ...]:
    names = tuple(names)
    if len(names) < minimum:
        raise out_of_range(f"number of {what}", len(names), f">= {minimum}", source)
    bad = [n for n in names if not isinstance(n, str) or not n]
    if bad:
        raise ConfigError(f"{source}: {what} {bad!r} are not allowed; expected non-empty strings")
    if len(set(names)) != len(names):
        dupes = sorted({n for n in names if names.count(n) > 1})
        raise ConfigError(f"{source}: {what} must be unique; repeated: {dupes}")
    return names


def _readonly(array: np.ndarray) -> np.ndarray:
    array = np.array(array, dtype=np.float64, copy=True)
    array.setflags(write=False)
    return array


# --------------------------------------------------------------------------------------------
# Results of the screening runs
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class ScreeningResults:
    """KPIs measured on a screening design, replicated with different DEM seeds.

    Attributes:
        parameter_names: the k screened parameters (``mu_s_pp``, ...), design column order.
        coded: coded design ``[runs, k]``, entries -1, 0 or +1 (float64, read-only).
        physical: the same design in physical units ``[runs, k]`` (read-only). In every column
            the coded levels map to one physical value each, increasing: low < mid < high.
        seeds: one DEM seed per replicate (unique).
        kpi_names: KPI names with their unit (``angle_of_repose_deg``, ...).
        kpi_values: ``[runs, replicates, n_kpi]`` float64, read-only; NaN marks a failed
            measurement (see the module docstring), inf is rejected.
        source: where the results came from (a file, a campaign), named in every error.

    Equality compares all fields (arrays elementwise, NaN equal to NaN).
    """

    parameter_names: tuple[str, ...]
    coded: np.ndarray
    physical: np.ndarray
    seeds: tuple[int, ...]
    kpi_names: tuple[str, ...]
    kpi_values: np.ndarray
    source: str = "ScreeningResults"

    def __post_init__(self) -> None:
        src = self.source
        names = _check_names("parameter names", self.parameter_names, src)
        k = len(names)
        if k < 2:
            raise out_of_range("number of parameters", k, ">= 2 (a screening design varies at "
                               "least two parameters)", src)
        object.__setattr__(self, "parameter_names", names)
        coded = np.asarray(self.coded, dtype=np.float64)
        if coded.ndim != 2 or coded.shape[1] != k:
            raise ConfigError(f"{src}: coded design has shape {coded.shape}; expected (runs, {k}) "
                              f"with one column per parameter {list(names)}")
        runs = coded.shape[0]
        if runs < MIN_RUNS_PER_FIT:
            raise out_of_range("number of runs", runs, f">= {MIN_RUNS_PER_FIT}", src)
        code = np.rint(coded)
        bad = ~np.isfinite(coded) | (np.abs(coded - code) > _LEVEL_ATOL) | (np.abs(code) > 1)
        if bad.any():
            run, col = map(int, np.argwhere(bad)[0])
            raise ConfigError(f"{src}: coded design run {run}, parameter '{names[col]}' = "
                              f"{float(coded[run, col])!r} is not allowed; expected a coded level "
                              f"-1, 0 or +1")
        physical = np.asarray(self.physical, dtype=np.float64)
        if physical.shape != coded.shape:
            raise ConfigError(f"{src}: physical design has shape {physical.shape}; expected "
                              f"{coded.shape}, the shape of the coded design")
        if not np.all(np.isfinite(physical)):
            run, col = map(int, np.argwhere(~np.isfinite(physical))[0])
            raise ConfigError(f"{src}: physical design run {run}, parameter '{names[col]}' = "
                              f"{float(physical[run, col])!r}; expected a finite number")
        for j, name in enumerate(names):
            levels = {}
            for c in np.unique(code[:, j]):
                values = physical[code[:, j] == c, j]
                if np.ptp(values) > 1e-9 * max(1.0, float(np.max(np.abs(values)))):
                    raise ConfigError(
                        f"{src}: parameter '{name}' has physical values {sorted(set(values))} at "
                        f"coded level {int(c):+d}; expected one physical value per coded level")
                levels[int(c)] = float(values[0])
            if len(levels) < 2:
                raise ConfigError(f"{src}: parameter '{name}' is at coded level "
                                  f"{list(levels)} in every run; expected at least two levels")
            ordered = [levels[c] for c in sorted(levels)]
            if not all(a < b for a, b in zip(ordered, ordered[1:])):
                shown = ", ".join(f"{v!r} (coded {c:+d})" for c, v in sorted(levels.items()))
                raise ConfigError(
                    f"{src}: parameter '{name}' has physical levels {shown}, which are out of "
                    f"order; expected low < mid < high for coded -1 < 0 < +1")
        seeds = tuple(self.seeds)
        if not seeds or any(isinstance(s, bool) or not isinstance(s, (int, np.integer))
                            for s in seeds):
            raise out_of_range("seeds", self.seeds, "a non-empty sequence of integers, one per "
                               "replicate", src)
        seeds = tuple(int(s) for s in seeds)
        if len(set(seeds)) != len(seeds):
            raise ConfigError(f"{src}: seeds {list(seeds)} repeat a seed; expected one distinct "
                              f"seed per replicate")
        kpis = _check_names("KPI names", self.kpi_names, src)
        values = np.asarray(self.kpi_values, dtype=np.float64)
        expected = (runs, len(seeds), len(kpis))
        if values.shape != expected:
            raise ConfigError(
                f"{src}: kpi_values has shape {values.shape}; expected [runs, replicates, n_kpi] "
                f"= {expected} ({runs} design runs, {len(seeds)} seeds, KPIs {list(kpis)})")
        if np.isinf(values).any():
            run, rep, q = map(int, np.argwhere(np.isinf(values))[0])
            raise ConfigError(f"{src}: kpi_values[{run}, {rep}, {q}] ({kpis[q]}) = "
                              f"{float(values[run, rep, q])!r}; expected a finite number or NaN "
                              f"for a failed measurement")
        object.__setattr__(self, "coded", _readonly(code))
        object.__setattr__(self, "physical", _readonly(physical))
        object.__setattr__(self, "seeds", seeds)
        object.__setattr__(self, "kpi_names", kpis)
        object.__setattr__(self, "kpi_values", _readonly(values))

    @classmethod
    def from_parameter_table(cls, table: ParameterTable, coded, seeds: Sequence[int],
                             kpi_names: Sequence[str], kpi_values,
                             source: str | None = None) -> "ScreeningResults":
        """Build from a ``ParameterTable`` and a coded design; physical values by level lookup."""
        return cls(parameter_names=table.names, coded=np.asarray(coded, dtype=np.float64),
                   physical=scale_design(coded, table), seeds=tuple(seeds),
                   kpi_names=tuple(kpi_names), kpi_values=kpi_values,
                   source=source or table.source)

    @property
    def n_runs(self) -> int:
        return int(self.coded.shape[0])

    @property
    def n_replicates(self) -> int:
        return len(self.seeds)

    def kpi_index(self, kpi: str, source: str | None = None) -> int:
        """Column of ``kpi`` in ``kpi_values``; the error lists the known KPIs."""
        if kpi not in self.kpi_names:
            raise ConfigError(f"{source or self.source}: KPI {kpi!r} is not in the screening "
                              f"results; known KPIs: {list(self.kpi_names)}")
        return self.kpi_names.index(kpi)

    def levels(self) -> dict[str, tuple[float, float]]:
        """Parameter name -> (lowest, highest) physical value in the design (the screened range)."""
        return {name: (float(self.physical[:, j].min()), float(self.physical[:, j].max()))
                for j, name in enumerate(self.parameter_names)}

    def run_means(self, kpi: str) -> np.ndarray:
        """Mean over the finite replicates of each run, ``[runs]`` (NaN where all failed)."""
        values = self.kpi_values[:, :, self.kpi_index(kpi)]
        finite = np.isfinite(values)
        total = np.where(finite, values, 0.0).sum(axis=1)
        count = finite.sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(count > 0, total / np.maximum(count, 1), np.nan)

    def to_dict(self) -> dict:
        """JSON-ready form (NaN written as None); ``from_dict`` reads it back equal."""
        values = self.kpi_values.astype(object)
        values[~np.isfinite(self.kpi_values)] = None
        return {"parameter_names": list(self.parameter_names), "coded": self.coded.tolist(),
                "physical": self.physical.tolist(), "seeds": list(self.seeds),
                "kpi_names": list(self.kpi_names), "kpi_values": values.tolist(),
                "source": self.source}

    @classmethod
    def from_dict(cls, data: Mapping, source: str = "ScreeningResults.from_dict"
                  ) -> "ScreeningResults":
        """Inverse of ``to_dict``; ``None`` KPI values become NaN."""
        keys = ("parameter_names", "coded", "physical", "seeds", "kpi_names", "kpi_values")
        missing = [key for key in keys if key not in data]
        if missing:
            raise ConfigError(f"{source}: keys {missing} are missing; expected all of {list(keys)}")
        values = np.array(data["kpi_values"], dtype=object)
        values = np.where(values == None, np.nan, values).astype(np.float64)  # noqa: E711
        return cls(parameter_names=tuple(data["parameter_names"]), coded=data["coded"],
                   physical=data["physical"], seeds=tuple(data["seeds"]),
                   kpi_names=tuple(data["kpi_names"]), kpi_values=values,
                   source=data.get("source", source))

    def __eq__(self, other) -> bool:
        if not isinstance(other, ScreeningResults):
            return NotImplemented
        return (self.parameter_names == other.parameter_names and self.seeds == other.seeds
                and self.kpi_names == other.kpi_names and self.source == other.source
                and np.array_equal(self.coded, other.coded)
                and np.array_equal(self.physical, other.physical)
                and np.array_equal(self.kpi_values, other.kpi_values, equal_nan=True))

    __hash__ = None  # type: ignore[assignment]  # holds arrays


# --------------------------------------------------------------------------------------------
# Stepwise regression
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class StepwiseFit:
    """Final model of one stepwise regression (one KPI, one replicate).

    Attributes:
        kpi: KPI name.
        replicate: replicate index (0-based), ``seed`` its DEM seed (None if not known).
        parameter_names: all candidate factors, design order.
        selected: factors in the final model, design order.
        coefficients: factor -> coefficient per coded unit (half the low-to-high effect).
        p_values: factor -> p-value of its t-test in the final model.
        intercept: fitted intercept (the KPI at the design centre).
        r_squared: coefficient of determination of the final model (NaN if skipped).
        n_runs_used: finite KPI values the fit used.
        p_threshold: entry / removal threshold.
        steps: the selection history, e.g. ``"enter mu_s_pp (p = 3.1e-06)"``.
        skipped: why the pair was not fitted (too few finite values), else ``""``.
        coded_used, values_used: the coded design rows ``[n_runs_used, k]`` and KPI values
            ``[n_runs_used]`` the fit used (failed runs dropped); None if not recorded.
        second_order: second-order terms in the final model (``"a^2"``, ``"a*b"``, design order
            of their factors), their coefficients and p-values in ``coefficients`` and
            ``p_values`` beside the main effects'; empty without the second stage.

    ``anova`` (a property, computed on first use and cached, because the formula machinery
    costs about as much as the whole selection) is statsmodels ``anova_lm(typ=2)`` of the final
    model, index = selected factors + ``"Residual"``; None if skipped or the data were not
    recorded.
    """

    kpi: str
    replicate: int
    seed: int | None
    parameter_names: tuple[str, ...]
    selected: tuple[str, ...]
    coefficients: Mapping[str, float]
    p_values: Mapping[str, float]
    intercept: float
    r_squared: float
    n_runs_used: int
    p_threshold: float
    steps: tuple[str, ...]
    skipped: str = ""
    coded_used: np.ndarray | None = field(default=None, repr=False)
    values_used: np.ndarray | None = field(default=None, repr=False)
    second_order: tuple[str, ...] = ()
    second_order_stage: bool = False

    @functools.cached_property
    def anova(self) -> pd.DataFrame | None:
        if self.skipped or self.coded_used is None or self.values_used is None:
            return None
        terms = [(self.parameter_names.index(p),) for p in self.selected] + [
            _parse_term(t, self.parameter_names) for t in self.second_order]
        columns = np.column_stack([_term_column(self.coded_used, t) for t in terms]) if terms \
            else np.empty((len(self.values_used), 0))
        names = list(self.selected) + list(self.second_order)
        return _anova_table(columns, self.values_used, list(range(len(terms))), names)

    def sign(self, parameter: str) -> int:
        """+1 / -1 if ``parameter`` is in the final model with that coefficient sign, else 0."""
        if parameter not in self.parameter_names:
            raise ConfigError(f"StepwiseFit({self.kpi}, replicate {self.replicate}): unknown "
                              f"parameter {parameter!r}; known: {list(self.parameter_names)}")
        c = self.coefficients.get(parameter, 0.0)
        return int(np.sign(c)) if parameter in self.selected else 0

    def summary(self) -> dict:
        """JSON-ready summary (no ANOVA table)."""
        return {"kpi": self.kpi, "replicate": self.replicate, "seed": self.seed,
                "selected": list(self.selected),
                "coefficients": dict(self.coefficients), "p_values": dict(self.p_values),
                "intercept": self.intercept, "r_squared": self.r_squared,
                "n_runs_used": self.n_runs_used, "steps": list(self.steps),
                "skipped": self.skipped, "second_order": list(self.second_order)}


def _fit_ols(x: np.ndarray, y: np.ndarray, columns: Sequence[int]):
    import statsmodels.api as sm  # heavy import, deferred until a fit is needed

    design = np.column_stack([np.ones(len(y))] + [x[:, j] for j in columns])
    return sm.OLS(y, design).fit()


def _p(value: float) -> float:
    """A NaN p-value (zero coefficient and zero residual) counts as not significant."""
    return 1.0 if not np.isfinite(value) else float(value)


#: Residual degrees of freedom the full main-effects model must leave to start the stepwise from it.
MIN_ERROR_DF = 3


def _term_name(term: tuple[int, ...], names: Sequence[str]) -> str:
    """``(j,)`` -> ``a``; ``(j, j)`` -> ``a^2``; ``(j, l)`` -> ``a*b``."""
    if len(term) == 1:
        return names[term[0]]
    return f"{names[term[0]]}^2" if term[0] == term[1] else f"{names[term[0]]}*{names[term[1]]}"


def _parse_term(name: str, names: Sequence[str]) -> tuple[int, ...]:
    """Inverse of ``_term_name``."""
    if name.endswith("^2"):
        j = names.index(name[:-2])
        return (j, j)
    a, b = name.split("*")
    return (names.index(a), names.index(b))


def _term_column(x: np.ndarray, term: tuple[int, ...]) -> np.ndarray:
    """The model column of a term: a factor, a square or a product of two factors."""
    column = x[:, term[0]].copy()
    for j in term[1:]:
        column = column * x[:, j]
    return column


def _select(x: np.ndarray, values: np.ndarray, candidates: Sequence[int], forced: Sequence[int],
            start: Sequence[int], threshold: float, labels: Sequence[str], steps: list[str]) -> list[int]:
    """Bidirectional stepwise over the columns ``candidates`` of ``x`` (module docstring, steps 1-3),
    with the columns ``forced`` always in the model and ``start`` the first model; returns the
    chosen candidates in the order they stand in the model. ``steps`` gets the history."""
    n = len(values)
    forced, model = list(forced), list(start)
    seen = {frozenset(model)}
    for _ in range(_MAX_STEPWISE_ITERATIONS):
        changed = False
        # Forward: the candidate with the smallest p-value enters if p < threshold.
        best_j, best_p = None, math.inf
        if n - (len(forced) + len(model) + 2) >= 1:
            for j in candidates:
                if j in model or j in forced:
                    continue
                trial = forced + model + [j]
                design = np.column_stack([np.ones(n), x[:, trial]])
                if np.linalg.matrix_rank(design) < design.shape[1]:
                    continue  # collinear (e.g. after dropping failed runs) or constant column
                p = _p(_fit_ols(x, values, trial).pvalues[-1])
                if p < best_p:
                    best_j, best_p = j, p
        if best_j is not None and best_p < threshold:
            model.append(best_j)
            steps.append(f"enter {labels[best_j]} (p = {best_p:.3g})")
            changed = True
        # Backward: remove the least significant term while its p-value exceeds the threshold.
        while model:
            pvalues = [_p(p) for p in _fit_ols(x, values, forced + model).pvalues[1 + len(forced):]]
            worst = int(np.argmax(pvalues))
            if pvalues[worst] <= threshold:
                break
            steps.append(f"remove {labels[model[worst]]} (p = {pvalues[worst]:.3g})")
            del model[worst]
            changed = True
        state = frozenset(model)
        if not changed:
            break
        if state in seen:
            steps.append("stop: model repeats an earlier one")
            break
        seen.add(state)
    return model


def _second_order_candidates(x: np.ndarray, model: Sequence[int]) -> list[tuple[int, int]]:
    """Squares of the model's factors seen at three levels, and their pairwise products."""
    active = sorted(model)
    terms = [(j, j) for j in active if len(np.unique(x[:, j])) >= 3]
    terms += [(a, b) for i, a in enumerate(active) for b in active[i + 1:]]
    return terms


def stepwise_regression(coded, y, parameter_names: Sequence[str], p_threshold: float = 0.01,
                        *, kpi: str = "y", replicate: int = 0, seed: int | None = None,
                        second_order: bool = False,
                        source: str = "stepwise_regression") -> StepwiseFit:
    """Bidirectional stepwise OLS on main effects, then (``second_order``) on the squares and
    interactions of the factors found; see the module docstring for the rules.

    ``coded`` is ``[runs, k]`` (coded factors), ``y`` ``[runs]`` with NaN for failed runs (those
    runs are dropped). ``p_threshold`` in (0, 1): enter if ``p < p_threshold``, remove if
    ``p > p_threshold``. Returns a skipped ``StepwiseFit`` when fewer than
    ``MIN_RUNS_PER_FIT`` values are finite.
    """
    threshold = _check_fraction("p_threshold", p_threshold, source,
                                "a p-value threshold in (0, 1), e.g. 0.01")
    names = _check_names("parameter names", parameter_names, source)
    x = np.asarray(coded, dtype=np.float64)
    values = np.asarray(y, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != len(names):
        raise ConfigError(f"{source}: coded design has shape {x.shape}; expected (runs, "
                          f"{len(names)}) for parameters {list(names)}")
    if values.shape != (x.shape[0],):
        raise ConfigError(f"{source}: KPI values for {kpi!r} have shape {values.shape}; expected "
                          f"({x.shape[0]},), one per design run")
    if not np.all(np.isfinite(x)):
        raise ConfigError(f"{source}: coded design contains non-finite values; expected -1/0/+1")
    keep = np.isfinite(values)
    x, values = x[keep], values[keep]
    n = int(keep.sum())
    common = dict(kpi=kpi, replicate=int(replicate), seed=seed, parameter_names=names,
                  p_threshold=threshold, n_runs_used=n)
    if n < MIN_RUNS_PER_FIT:
        return StepwiseFit(selected=(), coefficients=MappingProxyType({}),
                           p_values=MappingProxyType({}), intercept=math.nan, r_squared=math.nan,
                           steps=(),
                           skipped=f"{n} finite values; a fit needs >= {MIN_RUNS_PER_FIT}",
                           **common)

    steps: list[str] = []
    full = np.column_stack([np.ones(n), x])
    start: list[int] = []
    if n - full.shape[1] >= MIN_ERROR_DF and np.linalg.matrix_rank(full) == full.shape[1]:
        start = list(range(len(names)))
        steps.append(f"start from all {len(names)} main effects ({n - full.shape[1]} residual df)")
    model = _select(x, values, range(len(names)), [], start, threshold, names, steps)
    terms: list[tuple[int, int]] = []
    if second_order and model:
        for _ in range(len(names) + 1):  # each round must change the main effects to go on
            candidates = _second_order_candidates(x, model)
            if not candidates:
                break
            extended = np.column_stack([x] + [_term_column(x, t) for t in candidates])
            labels = list(names) + [_term_name(t, names) for t in candidates]
            k = len(names)
            steps.append("second stage: squares and interactions of " + ", ".join(names[j] for j in sorted(model)))
            chosen = _select(extended, values, range(k, k + len(candidates)), model, [], threshold, labels, steps)
            terms = [candidates[c - k] for c in chosen]
            parents = sorted({j for t in terms for j in t})
            x_terms = np.column_stack([x] + [_term_column(x, t) for t in terms])
            forced = parents + list(range(k, k + len(terms)))
            free = [j for j in model if j not in parents]
            steps.append("main effects again, beside " + (", ".join(labels[c] for c in chosen) or "no second-order term"))
            again = parents + _select(x_terms, values, [j for j in range(k) if j not in parents], forced, free,
                                      threshold, names, steps)
            if sorted(again) == sorted(model):
                break
            model = again
        else:
            steps.append("stop: the main effects did not settle")
        terms = [t for t in terms if all(j in model for j in t)]
    model.sort()
    columns = [(j,) for j in model] + terms
    design = np.column_stack([_term_column(x, t) for t in columns]) if columns else np.empty((n, 0))
    fit = _fit_ols(design, values, list(range(len(columns))))
    labels = [_term_name(t, names) for t in columns]
    selected = tuple(names[j] for j in model)
    return StepwiseFit(
        selected=selected,
        coefficients=MappingProxyType({n_: float(c) for n_, c in zip(labels, fit.params[1:])}),
        p_values=MappingProxyType({n_: float(p) for n_, p in zip(labels, fit.pvalues[1:])}),
        intercept=float(fit.params[0]),
        r_squared=float(fit.rsquared) if columns else 0.0,
        steps=tuple(steps),
        coded_used=_readonly(x), values_used=_readonly(values),
        second_order=tuple(labels[len(model):]), second_order_stage=bool(second_order),
        **common)


def _anova_table(x: np.ndarray, y: np.ndarray, model: Sequence[int],
                 names: Sequence[str]) -> pd.DataFrame:
    """``anova_lm(typ=2)`` of the final model, rows named after the parameters."""
    import statsmodels.formula.api as smf
    from statsmodels.stats.anova import anova_lm

    # Formula terms use safe aliases so any parameter name works; rows are renamed back.
    aliases = {f"x{j}": names[j] for j in model}
    frame = pd.DataFrame({f"x{j}": x[:, j] for j in model})
    frame["kpi"] = y
    formula = "kpi ~ " + (" + ".join(aliases) if aliases else "1")
    table = anova_lm(smf.ols(formula, data=frame).fit(), typ=2)
    return table.rename(index=aliases)


# --------------------------------------------------------------------------------------------
# Table 5: counting significance over replicates
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class SignificanceTable:
    """How often each parameter is significant per KPI, with its sign (the paper's Table 5).

    Attributes:
        parameter_names: rows, design order.
        kpi_names: columns.
        positive, negative: ``[k, n_kpi]`` int arrays, replicates in which the parameter was
            in the final model with a positive / negative coefficient.
        replicates: per KPI, the number of analysed (not skipped) replicates, the denominator.
        p_threshold: the stepwise threshold used.
        selection_fraction: a parameter is selected if ``(positive + negative) / replicates``
            reaches this fraction for at least one KPI.
        second_order: the fits had the second stage (squares and interactions of the active
            factors in the model); the counts are of main effects either way.
    """

    parameter_names: tuple[str, ...]
    kpi_names: tuple[str, ...]
    positive: np.ndarray
    negative: np.ndarray
    replicates: tuple[int, ...]
    p_threshold: float
    selection_fraction: float
    second_order: bool = False

    def __post_init__(self) -> None:
        src = "SignificanceTable"
        names = _check_names("parameter names", self.parameter_names, src)
        kpis = _check_names("KPI names", self.kpi_names, src)
        shape = (len(names), len(kpis))
        replicates = tuple(int(r) for r in self.replicates)
        if len(replicates) != len(kpis) or any(r < 0 for r in replicates):
            raise ConfigError(f"{src}: replicates = {list(self.replicates)!r} is not allowed; "
                              f"expected {len(kpis)} counts >= 0, one per KPI {list(kpis)}")
        for field_name in ("positive", "negative"):
            counts = np.asarray(getattr(self, field_name))
            if counts.shape != shape or np.any(counts < 0) or np.any(counts != np.rint(counts)):
                raise ConfigError(f"{src}: {field_name} has shape {counts.shape}; expected "
                                  f"[parameters, KPIs] = {shape} of counts >= 0")
            counts = counts.astype(np.int64)
            counts.setflags(write=False)
            object.__setattr__(self, field_name, counts)
        over = (self.positive + self.negative) > np.asarray(replicates)[None, :]
        if over.any():
            i, j = map(int, np.argwhere(over)[0])
            raise ConfigError(f"{src}: '{names[i]}' is significant for '{kpis[j]}' in "
                              f"{int(self.positive[i, j] + self.negative[i, j])} replicates; "
                              f"expected at most the {replicates[j]} analysed")
        _check_fraction("selection_fraction", self.selection_fraction, src,
                        "a fraction of replicates in (0, 1], e.g. 0.8", include_one=True)
        object.__setattr__(self, "parameter_names", names)
        object.__setattr__(self, "kpi_names", kpis)
        object.__setattr__(self, "replicates", replicates)

    @property
    def significant(self) -> np.ndarray:
        """``[k, n_kpi]`` replicates in which the parameter was significant (either sign)."""
        return self.positive + self.negative

    @property
    def significant_for_kpi(self) -> np.ndarray:
        """``[k, n_kpi]`` bool: significant in >= ``selection_fraction`` of the replicates."""
        denominator = np.asarray(self.replicates, dtype=np.float64)[None, :]
        # 1e-9 absorbs rounding, e.g. 0.8 * 5 = 4.000000000000001.
        return (denominator > 0) & (self.significant >= self.selection_fraction * denominator
                                    - 1e-9)

    @property
    def selected(self) -> tuple[bool, ...]:
        """Per parameter: selected for calibration (significant enough for some KPI)."""
        return tuple(bool(v) for v in self.significant_for_kpi.any(axis=1))

    @property
    def selected_parameters(self) -> tuple[str, ...]:
        return tuple(n for n, s in zip(self.parameter_names, self.selected) if s)

    def _index(self, parameter: str, kpi: str) -> tuple[int, int]:
        if parameter not in self.parameter_names:
            raise ConfigError(f"SignificanceTable: unknown parameter {parameter!r}; known: "
                              f"{list(self.parameter_names)}")
        if kpi not in self.kpi_names:
            raise ConfigError(f"SignificanceTable: unknown KPI {kpi!r}; known: "
                              f"{list(self.kpi_names)}")
        return self.parameter_names.index(parameter), self.kpi_names.index(kpi)

    def sign(self, parameter: str, kpi: str) -> int:
        """Majority sign of the significant effects of ``parameter`` on ``kpi``: +1, -1 or 0
        (never significant, or as often positive as negative)."""
        i, j = self._index(parameter, kpi)
        return int(np.sign(int(self.positive[i, j]) - int(self.negative[i, j])))

    def cell(self, parameter: str, kpi: str) -> str:
        """Table 5 cell: ``"+5/5"``, ``"-4/5"``, ``"+3/5, -1/5"`` or ``""``."""
        i, j = self._index(parameter, kpi)
        pos, neg, total = int(self.positive[i, j]), int(self.negative[i, j]), self.replicates[j]
        parts = ([f"+{pos}/{total}"] if pos else []) + ([f"-{neg}/{total}"] if neg else [])
        return ", ".join(parts)

    def to_markdown(self) -> str:
        """Table 5 as a Markdown table; the header notes the threshold and fraction."""
        header = ["parameter", *self.kpi_names, "selected"]
        rows = [[name, *(self.cell(name, kpi) for kpi in self.kpi_names),
                 "yes" if chosen else "no"]
                for name, chosen in zip(self.parameter_names, self.selected)]
        widths = [max(len(str(r[c])) for r in [header, *rows]) for c in range(len(header))]

        def line(cells) -> str:
            return "| " + " | ".join(str(c).ljust(w) for c, w in zip(cells, widths)) + " |"

        lines = [
            f"Significant main effects (stepwise, p < {self.p_threshold:g}"
            + ("; squares and interactions of the active factors in the model" if self.second_order else "")
            + "); a cell counts the "
            f"replicates with a +/- effect; selected = significant in >= "
            f"{self.selection_fraction:.0%} of the replicates for at least one KPI.",
            "",
            line(header),
            "| " + " | ".join("-" * w for w in widths) + " |",
            *(line(r) for r in rows),
        ]
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """JSON-ready form of the table (plain ints, strings and bools)."""
        return {
            "p_threshold": self.p_threshold,
            "selection_fraction": self.selection_fraction,
            "second_order": self.second_order,
            "kpis": list(self.kpi_names),
            "replicates": {kpi: int(n) for kpi, n in zip(self.kpi_names, self.replicates)},
            "rows": [
                {"parameter": name,
                 "cells": {kpi: self.cell(name, kpi) for kpi in self.kpi_names},
                 "positive": {k: int(self.positive[i, j]) for j, k in enumerate(self.kpi_names)},
                 "negative": {k: int(self.negative[i, j]) for j, k in enumerate(self.kpi_names)},
                 "selected": chosen}
                for i, (name, chosen) in enumerate(zip(self.parameter_names, self.selected))],
            "selected_parameters": list(self.selected_parameters),
        }


def count_significance(fits: Sequence[StepwiseFit], parameter_names: Sequence[str],
                       kpi_names: Sequence[str], selection_fraction: float = 0.8,
                       source: str = "count_significance") -> SignificanceTable:
    """Tally the final models of ``fits`` into a ``SignificanceTable`` (Table 5).

    Every fit must be for one of ``kpi_names`` and have the candidate set ``parameter_names``;
    a (KPI, replicate) pair may appear only once. Skipped fits are not counted.
    """
    fraction = _check_fraction("selection_fraction", selection_fraction, source,
                               "a fraction of replicates in (0, 1], e.g. 0.8", include_one=True)
    names = _check_names("parameter names", parameter_names, source)
    kpis = _check_names("KPI names", kpi_names, source)
    positive = np.zeros((len(names), len(kpis)), dtype=np.int64)
    negative = np.zeros_like(positive)
    replicates = [0] * len(kpis)
    seen: set[tuple[str, int]] = set()
    thresholds = {f.p_threshold for f in fits}
    if len(thresholds) > 1:
        raise ConfigError(f"{source}: fits use different p-value thresholds {sorted(thresholds)}; "
                          f"expected one threshold for the whole table")
    for f in fits:
        if f.kpi not in kpis:
            raise ConfigError(f"{source}: a fit is for KPI {f.kpi!r}, not in the table's KPIs "
                              f"{list(kpis)}")
        if tuple(f.parameter_names) != names:
            raise ConfigError(f"{source}: the fit for {f.kpi!r}, replicate {f.replicate} has "
                              f"parameters {list(f.parameter_names)}; expected {list(names)}")
        if (f.kpi, f.replicate) in seen:
            raise ConfigError(f"{source}: KPI {f.kpi!r}, replicate {f.replicate} appears twice")
        seen.add((f.kpi, f.replicate))
        if f.skipped:
            continue
        j = kpis.index(f.kpi)
        replicates[j] += 1
        for name in f.selected:
            i = names.index(name)
            if f.coefficients[name] > 0:
                positive[i, j] += 1
            elif f.coefficients[name] < 0:
                negative[i, j] += 1
    return SignificanceTable(parameter_names=names, kpi_names=kpis, positive=positive,
                             negative=negative, replicates=tuple(replicates),
                             p_threshold=thresholds.pop() if thresholds else math.nan,
                             selection_fraction=fraction,
                             second_order=any(f.second_order_stage for f in fits))


@dataclass(frozen=True, eq=False)
class ScreeningAnalysis:
    """All stepwise fits of a screening study and their Table 5.

    Attributes:
        fits: one ``StepwiseFit`` per (KPI, replicate), KPI-major order.
        table: the ``SignificanceTable`` built from ``fits``.
    """

    fits: tuple[StepwiseFit, ...]
    table: SignificanceTable

    def fit(self, kpi: str, replicate: int) -> StepwiseFit:
        for f in self.fits:
            if f.kpi == kpi and f.replicate == replicate:
                return f
        raise ConfigError(f"ScreeningAnalysis: no fit for KPI {kpi!r}, replicate {replicate}; "
                          f"KPIs {list(self.table.kpi_names)}")

    @property
    def selected_parameters(self) -> tuple[str, ...]:
        return self.table.selected_parameters

    def to_dict(self) -> dict:
        """JSON-ready: the table and a summary of every fit."""
        return {"table": self.table.to_dict(), "fits": [f.summary() for f in self.fits]}


def analyse_screening(results: ScreeningResults, p_threshold: float = 0.01,
                      selection_fraction: float = 0.8, kpis: Sequence[str] | None = None,
                      second_order: bool = False) -> ScreeningAnalysis:
    """Stepwise regression for every KPI (or ``kpis``) and replicate, and their Table 5
    (``second_order``: with the second stage, see the module docstring)."""
    source = f"analyse_screening({results.source})"
    _check_fraction("p_threshold", p_threshold, source, "a p-value threshold in (0, 1), e.g. 0.01")
    _check_fraction("selection_fraction", selection_fraction, source,
                    "a fraction of replicates in (0, 1], e.g. 0.8", include_one=True)
    chosen = results.kpi_names if kpis is None else _check_names("KPI names", kpis, source)
    fits = []
    for kpi in chosen:
        q = results.kpi_index(kpi, source)
        for r, seed in enumerate(results.seeds):
            fits.append(stepwise_regression(results.coded, results.kpi_values[:, r, q],
                                            results.parameter_names, p_threshold, kpi=kpi,
                                            replicate=r, seed=seed, second_order=second_order,
                                            source=source))
    table = count_significance(fits, results.parameter_names, chosen, selection_fraction, source)
    return ScreeningAnalysis(fits=tuple(fits), table=table)
