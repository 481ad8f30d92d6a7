"""Main effects of a screening, pooled over its replicates, with standard errors and the DEM's
replicate scatter: what a change of one screened parameter does to every KPI, in physical units.

Contract
--------
``main_effects(results)`` fits, per KPI, one least-squares model of the KPI on the coded design's
main effects (an intercept and one slope per parameter) to every finite run of every replicate
together, and returns a frozen :class:`MainEffects`:

- ``effect[k, m]``: the change of KPI ``m`` from the low to the high level of parameter ``k``
  (twice the coefficient per coded unit), with its standard error ``effect_se`` from the fit's
  residual variance (replicate noise plus whatever the main effects leave unexplained: the
  honest error of a linear prediction);
- ``replicate_sd[m]``: the pooled standard deviation of one run about its design point's mean
  (the pure error, from the points with at least two finite replicates), the DEM's own scatter;
- ``residual_sd[m]``: the fit's residual standard deviation. ``residual_sd`` well above
  ``replicate_sd`` means curvature or interactions the main effects miss (lack of fit), and a
  shift predicted from ``effect`` is then rougher than its standard error says;
  ``lack_of_fit_p[m]`` is the p-value of the classical lack-of-fit F test (the residual's sum of
  squares beyond the pure error, per degree of freedom, against the pure error's).

``MainEffects.shift(parameter, start, end)`` is the linear prediction of the KPIs' change when the
parameter moves from ``start`` to ``end`` (``[n_kpi]``), and ``shift_se`` its standard error;
outside the screened range the prediction extrapolates the slope, which the screening cannot
check.

A definitive screening design is orthogonal in its main effects, so each slope here equals the
one a stepwise fit would give if it kept every parameter; the stepwise regressions of Table 5
(``bo.screening.stepwise``) decide which parameters matter, this module says by how much.

Reference: A. Hadi, Y. Pang, D. Schott, section 3.3 (the screening design and its replicates).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from bo.screening.stepwise import ScreeningResults
from torchdem.errors import ConfigError, out_of_range

__all__ = ["MainEffects", "main_effects", "least_squares"]


@dataclass(frozen=True)
class MainEffects:
    """Main effects of ``k`` screened parameters on ``m`` KPIs (module docstring).

    Attributes:
        parameter_names: ``[k]`` design order; ``kpi_names``: ``[m]``.
        low, high: ``[k]`` physical values of the coded levels -1 and +1.
        effect, effect_se: ``[k, m]`` KPI change from low to high, and its standard error.
        intercept: ``[m]`` the KPI at the design centre.
        replicate_sd, replicate_dof: ``[m]`` pooled pure-error sd of one run and its degrees of freedom.
        residual_sd, residual_dof: ``[m]`` the fit's residual sd and degrees of freedom.
        n_runs: ``[m]`` finite runs each fit used.
        lack_of_fit_p: ``[m]`` p-value of the lack-of-fit F test (NaN without pure error or
            without lack-of-fit degrees of freedom).
        source: where the screening came from, named in errors.
    """

    parameter_names: tuple[str, ...]
    kpi_names: tuple[str, ...]
    low: np.ndarray
    high: np.ndarray
    effect: np.ndarray
    effect_se: np.ndarray
    intercept: np.ndarray
    replicate_sd: np.ndarray
    replicate_dof: np.ndarray
    residual_sd: np.ndarray
    residual_dof: np.ndarray
    n_runs: np.ndarray
    lack_of_fit_p: np.ndarray
    source: str = "MainEffects"

    def index(self, parameter: str) -> int:
        if parameter not in self.parameter_names:
            raise ConfigError(f"{self.source}: parameter {parameter!r} was not screened; screened: "
                              f"{list(self.parameter_names)}")
        return self.parameter_names.index(parameter)

    def slope(self, parameter: str) -> np.ndarray:
        """``[m]`` KPI change per unit of the parameter (physical units)."""
        k = self.index(parameter)
        return self.effect[k] / (self.high[k] - self.low[k])

    def shift(self, parameter: str, start: float, end: float) -> np.ndarray:
        """``[m]`` linear prediction of the KPIs' change from ``parameter = start`` to ``end``."""
        return self.slope(parameter) * (float(end) - float(start))

    def shift_se(self, parameter: str, start: float, end: float) -> np.ndarray:
        """``[m]`` standard error of :meth:`shift`."""
        k = self.index(parameter)
        return self.effect_se[k] * abs(float(end) - float(start)) / (self.high[k] - self.low[k])

    def predict(self, values: dict[str, float]) -> np.ndarray:
        """``[m]`` the main-effects model's KPIs at a parameter set (parameters not given at the
        design centre)."""
        unknown = sorted(set(values) - set(self.parameter_names))
        if unknown:
            raise ConfigError(f"{self.source}: parameters {unknown} were not screened; screened: "
                              f"{list(self.parameter_names)}")
        out = self.intercept.copy()
        for name, value in values.items():
            k = self.index(name)
            out = out + self.shift(name, 0.5 * (self.low[k] + self.high[k]), value)
        return out


def main_effects(results: ScreeningResults) -> MainEffects:
    """Fit the main effects of ``results`` on all replicates together (module docstring)."""
    coded, values = results.coded, results.kpi_values  # [runs, k], [runs, r, m]
    runs, k = coded.shape
    r, m = values.shape[1], values.shape[2]
    x = np.column_stack([np.ones(runs), coded])  # [runs, 1 + k]
    levels = results.levels()
    low = np.array([levels[n][0] for n in results.parameter_names])
    high = np.array([levels[n][1] for n in results.parameter_names])
    effect, effect_se = np.full((k, m), np.nan), np.full((k, m), np.nan)
    intercept = np.full(m, np.nan)
    residual_sd, residual_dof, n_runs = np.full(m, np.nan), np.zeros(m, dtype=int), np.zeros(m, dtype=int)
    for j in range(m):
        y = values[:, :, j]  # [runs, r]
        finite = np.isfinite(y)
        rows = np.repeat(np.arange(runs)[:, None], r, axis=1)[finite]
        xj, yj = x[rows], y[finite]
        fit = least_squares(xj, yj)
        if fit is None:
            raise out_of_range(f"finite runs of {results.kpi_names[j]}", len(yj),
                               f"enough for {1 + k} coefficients and one residual degree of freedom",
                               results.source)
        beta, se, s2, dof = fit
        intercept[j] = beta[0]
        effect[:, j] = 2.0 * beta[1:]
        effect_se[:, j] = 2.0 * se[1:]
        residual_sd[j], residual_dof[j], n_runs[j] = np.sqrt(s2), dof, len(yj)
    replicate_sd, replicate_dof = _pure_error(values)
    lack_dof = residual_dof - replicate_dof
    with np.errstate(invalid="ignore", divide="ignore"):
        lack_ms = (residual_sd ** 2 * residual_dof - replicate_sd ** 2 * replicate_dof) / lack_dof
        f_value = np.maximum(lack_ms, 0.0) / replicate_sd ** 2
    usable = (lack_dof > 0) & (replicate_dof > 0) & np.isfinite(f_value)
    lack_of_fit_p = np.where(usable, stats.f.sf(np.where(usable, f_value, 0.0), np.maximum(lack_dof, 1),
                                                np.maximum(replicate_dof, 1)), np.nan)
    return MainEffects(parameter_names=tuple(results.parameter_names), kpi_names=tuple(results.kpi_names),
                       low=low, high=high, effect=effect, effect_se=effect_se, intercept=intercept,
                       replicate_sd=replicate_sd, replicate_dof=replicate_dof, residual_sd=residual_sd,
                       residual_dof=residual_dof, n_runs=n_runs, lack_of_fit_p=lack_of_fit_p, source=results.source)


def least_squares(x: np.ndarray, y: np.ndarray,
                  weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, float, int] | None:
    """Least squares of ``y [n]`` on the columns of ``x [n, p]``: ``(coefficients [p], their
    standard errors [p], residual variance, residual degrees of freedom)``, or None when ``x`` has
    rank below ``p`` or no residual degree of freedom is left. ``weights [n]`` (inverse variances)
    make it weighted: each row scaled by the root of its weight, the residual variance that of the
    scaled rows."""
    if weights is not None:
        root = np.sqrt(np.asarray(weights, dtype=float))
        x, y = x * root[:, None], y * root
    dof = len(y) - x.shape[1]
    if dof < 1 or np.linalg.matrix_rank(x) < x.shape[1]:
        return None
    beta, *_ = np.linalg.lstsq(x, y, rcond=None)
    resid = y - x @ beta
    s2 = float(resid @ resid) / dof
    return beta, np.sqrt(s2 * np.diag(np.linalg.inv(x.T @ x))), s2, dof


def _pure_error(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``([m], [m])`` pooled within-point sd of ``values [runs, r, m]`` and its degrees of freedom
    (NaN and 0 where no point has two finite replicates)."""
    finite = np.isfinite(values)
    count = finite.sum(1)  # [runs, m]
    mean = np.where(finite, values, 0.0).sum(1) / np.maximum(count, 1)
    squares = np.where(finite, (values - mean[:, None, :]) ** 2, 0.0).sum(1)  # [runs, m]
    dof = np.where(count >= 2, count - 1, 0).sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        sd = np.where(dof > 0, np.sqrt(np.where(count >= 2, squares, 0.0).sum(0) / np.maximum(dof, 1)), np.nan)
    return sd, dof
