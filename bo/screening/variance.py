"""Variance decomposition of screening KPIs: parameters versus DEM stochasticity (Eqs. 4-6).

Contract
--------
``decompose_variance(kpi_values, kpi_names, stochastic_threshold=0.5)`` takes KPI values
``[runs, replicates, n_kpi]`` (a design point per run, one DEM seed per replicate, NaN for a
failed measurement) and returns, per KPI, the law of total variance (paper Eq. 4)::

    Var(Y) = Var(E[Y|X]) + E[Var(Y|X)]
             parameters    stochasticity

    P = Var(E[Y|X]) / Var(Y)      (Eq. 5, as a fraction; x100 for the paper's percent)
    S = E[Var(Y|X)] / Var(Y)      (Eq. 6)

evaluated on the empirical distribution of the finite values: ``X`` is the design point (run),
``E[Y|X]`` the mean of its finite replicates, ``Var(Y|X)`` their population variance
(``ddof = 0``), and each run is weighted by its number of finite replicates (equal weights when
nothing failed). With these choices Eq. 4 holds exactly (to rounding): ``total_variance`` equals
the population variance of all finite values and ``P + S = 1``. Runs with no finite value are
left out.

A KPI is *stochastic-dominated* when ``S > stochastic_threshold`` (default 0.5): DEM noise
explains more of its spread than the parameters do, so the screening cannot tell which
parameters matter and calibration must exclude it (the paper excludes both segregation KPIs,
section 3.3, Fig. 10). A KPI with zero total variance has undefined shares (NaN) and is also
excluded (it cannot discriminate parameter sets).

Estimator notes: this is the plug-in (sample) decomposition the paper describes. With ``r``
replicates and noise variance ``sigma^2``, the mean within-run variance estimates
``sigma^2 (r - 1) / r`` and the variance of run means carries about ``sigma^2 / r`` of noise, so
``S`` is biased low by roughly ``1 / r`` of the noise share (20 % of it with the paper's five
replicates). The bias vanishes as ``r`` grows; keep it in mind for KPIs near the threshold.

Reference: A. Hadi, Y. Pang, D. Schott, section 3.3, Eqs. 4-6, Fig. 10.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from torchdem.errors import ConfigError, out_of_range

__all__ = ["VarianceDecomposition", "decompose_variance", "decompose_screening_variance"]


@dataclass(frozen=True)
class VarianceDecomposition:
    """Per-KPI variance shares of parameters and DEM stochasticity (fractions in [0, 1]).

    Attributes:
        kpi_names: the KPIs, in input order.
        total_variance: ``Var(Y)`` per KPI, KPI unit squared.
        parameter_variance: ``Var(E[Y|X])`` per KPI.
        stochastic_variance: ``E[Var(Y|X)]`` per KPI.
        parameter_share, stochastic_share: P and S of Eqs. 5-6 as fractions (NaN when the
            total variance is 0).
        stochastic_dominated: per KPI, ``stochastic_share > stochastic_threshold``.
        stochastic_threshold: the threshold used.
        n_runs_used: runs with at least one finite value, per KPI.
        n_values_used: finite values, per KPI.
    """

    kpi_names: tuple[str, ...]
    total_variance: tuple[float, ...]
    parameter_variance: tuple[float, ...]
    stochastic_variance: tuple[float, ...]
    parameter_share: tuple[float, ...]
    stochastic_share: tuple[float, ...]
    stochastic_dominated: tuple[bool, ...]
    stochastic_threshold: float
    n_runs_used: tuple[int, ...]
    n_values_used: tuple[int, ...]

    @property
    def parameter_percent(self) -> tuple[float, ...]:
        """P of Eq. 5 in percent."""
        return tuple(100.0 * p for p in self.parameter_share)

    @property
    def stochastic_percent(self) -> tuple[float, ...]:
        """S of Eq. 6 in percent."""
        return tuple(100.0 * s for s in self.stochastic_share)

    @property
    def excluded_kpis(self) -> tuple[str, ...]:
        """KPIs calibration must exclude: stochastic-dominated or without any variance."""
        return tuple(k for k, dominated, s in zip(self.kpi_names, self.stochastic_dominated,
                                                  self.stochastic_share)
                     if dominated or math.isnan(s))

    @property
    def calibration_kpis(self) -> tuple[str, ...]:
        """KPIs fit for screening and calibration (the rest of ``kpi_names``)."""
        return tuple(k for k in self.kpi_names if k not in self.excluded_kpis)

    def share(self, kpi: str) -> tuple[float, float]:
        """(parameter share, stochastic share) of ``kpi``."""
        if kpi not in self.kpi_names:
            raise ConfigError(f"VarianceDecomposition: unknown KPI {kpi!r}; known: "
                              f"{list(self.kpi_names)}")
        i = self.kpi_names.index(kpi)
        return self.parameter_share[i], self.stochastic_share[i]

    def to_text(self) -> str:
        """Fixed-width table: KPI, total variance, P %, S %, verdict."""
        width = max(len("KPI"), *(len(k) for k in self.kpi_names))
        lines = [f"Variance decomposition (law of total variance); excluded when S > "
                 f"{self.stochastic_threshold:.0%}",
                 f"{'KPI'.ljust(width)}  {'Var(Y)':>11}  {'P params':>8}  {'S stoch':>8}  verdict"]
        for i, kpi in enumerate(self.kpi_names):
            if math.isnan(self.stochastic_share[i]):
                verdict = "EXCLUDE (no variance)"
            elif self.stochastic_dominated[i]:
                verdict = "EXCLUDE (stochasticity dominates)"
            else:
                verdict = "keep"
            lines.append(f"{kpi.ljust(width)}  {self.total_variance[i]:11.4g}  "
                         f"{self.parameter_percent[i]:7.1f}%  {self.stochastic_percent[i]:7.1f}%  "
                         f"{verdict}")
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.to_text()

    def to_dict(self) -> dict:
        """JSON-ready form, one entry per KPI (NaN shares written as None)."""
        def number(v: float):
            return None if math.isnan(v) else float(v)

        return {
            "stochastic_threshold": self.stochastic_threshold,
            "kpis": {
                kpi: {"total_variance": number(self.total_variance[i]),
                      "parameter_variance": number(self.parameter_variance[i]),
                      "stochastic_variance": number(self.stochastic_variance[i]),
                      "parameter_share": number(self.parameter_share[i]),
                      "stochastic_share": number(self.stochastic_share[i]),
                      "stochastic_dominated": self.stochastic_dominated[i],
                      "n_runs_used": self.n_runs_used[i],
                      "n_values_used": self.n_values_used[i]}
                for i, kpi in enumerate(self.kpi_names)},
            "excluded_kpis": list(self.excluded_kpis),
            "calibration_kpis": list(self.calibration_kpis),
        }


def decompose_variance(kpi_values, kpi_names: Sequence[str], stochastic_threshold: float = 0.5,
                       source: str = "decompose_variance") -> VarianceDecomposition:
    """Law-of-total-variance split of each KPI; see the module docstring.

    ``kpi_values`` is ``[runs, replicates, n_kpi]`` with ``n_kpi = len(kpi_names)``; NaN marks a
    failed measurement, inf is rejected. ``stochastic_threshold`` must be in (0, 1).
    """
    names = tuple(kpi_names)
    if not names or len(set(names)) != len(names):
        raise ConfigError(f"{source}: kpi_names = {list(names)!r} is not allowed; expected "
                          f"unique KPI names, at least one")
    if (isinstance(stochastic_threshold, bool)
            or not isinstance(stochastic_threshold, (int, float, np.floating))
            or not 0.0 < float(stochastic_threshold) < 1.0):
        raise out_of_range("stochastic_threshold", stochastic_threshold,
                           "a share of the total variance in (0, 1), e.g. 0.5", source)
    values = np.asarray(kpi_values, dtype=np.float64)
    if values.ndim != 3 or values.shape[2] != len(names) or values.shape[1] < 1:
        raise ConfigError(f"{source}: kpi_values has shape {values.shape}; expected [runs, "
                          f"replicates, n_kpi] with n_kpi = {len(names)} for {list(names)}")
    if np.isinf(values).any():
        run, rep, q = map(int, np.argwhere(np.isinf(values))[0])
        raise ConfigError(f"{source}: kpi_values[{run}, {rep}, {q}] ({names[q]}) is infinite; "
                          f"expected a finite number or NaN for a failed measurement")

    out = {key: [] for key in ("total", "param", "stoch", "p", "s", "dom", "runs", "n")}
    for q, kpi in enumerate(names):
        y = values[:, :, q]
        finite = np.isfinite(y)
        count = finite.sum(axis=1)  # finite replicates per run
        n = int(count.sum())
        if n < 2:
            raise ConfigError(f"{source}: KPI {kpi!r} has {n} finite values; expected at least 2 "
                              f"to estimate a variance")
        y0 = np.where(finite, y, 0.0)
        used = count > 0
        run_mean = np.where(used, y0.sum(axis=1) / np.maximum(count, 1), 0.0)
        weight = count / n  # P(X = run) on the empirical distribution
        grand = float((weight * run_mean).sum())
        within = np.where(finite, (y0 - run_mean[:, None]) ** 2, 0.0).sum(axis=1) \
            / np.maximum(count, 1)
        parameter = float((weight * (run_mean - grand) ** 2).sum())
        stochastic = float((weight * within).sum())
        total = parameter + stochastic  # == population variance of all finite values
        if total > 0.0:
            p_share, s_share = parameter / total, stochastic / total
        else:
            p_share = s_share = math.nan
        out["total"].append(total)
        out["param"].append(parameter)
        out["stoch"].append(stochastic)
        out["p"].append(p_share)
        out["s"].append(s_share)
        out["dom"].append(bool(s_share > stochastic_threshold))  # NaN compares False
        out["runs"].append(int(used.sum()))
        out["n"].append(n)
    return VarianceDecomposition(
        kpi_names=names, total_variance=tuple(out["total"]),
        parameter_variance=tuple(out["param"]), stochastic_variance=tuple(out["stoch"]),
        parameter_share=tuple(out["p"]), stochastic_share=tuple(out["s"]),
        stochastic_dominated=tuple(out["dom"]), stochastic_threshold=float(stochastic_threshold),
        n_runs_used=tuple(out["runs"]), n_values_used=tuple(out["n"]))


def decompose_screening_variance(results, stochastic_threshold: float = 0.5,
                                 kpis: Sequence[str] | None = None) -> VarianceDecomposition:
    """``decompose_variance`` on a ``bo.screening.stepwise.ScreeningResults`` (all KPIs or ``kpis``)."""
    source = f"decompose_screening_variance({results.source})"
    chosen = tuple(results.kpi_names if kpis is None else kpis)
    columns = [results.kpi_index(k, source) for k in chosen]
    return decompose_variance(results.kpi_values[:, :, columns], chosen, stochastic_threshold,
                              source)
