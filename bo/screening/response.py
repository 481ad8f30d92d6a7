"""What a campaign's parameters do to one KPI over every run it made: a linear fit on all of them.

A screening measures main effects on its own design. A campaign store holds far more: the
screening, the surrogate's rounds, verification and validation, a discovery's design points, all
at one model. Fitting a KPI linearly on the parameters over every finished run of one condition
says which parameters move it across the space the campaign explored, and whether what is left
is noise: the fit's residual sd against the replicate sd pooled over the parameter sets that were
run more than once. That is the question behind leaving a KPI out of a calibration as noise (the
paper leaves segregation out because its DSD variance was mostly stochastic): if the parameters
explain much of its spread, it is not noise in this model.

Contract:

* :func:`store_runs` ``(stores, condition, stages) -> [(parameters, KPIs)]``: every finished run of one
  condition in the stores (read only) that did not jam, of the given stages (None: every stage).
* :func:`kpi_response` ``(runs, kpi, source) -> KPIResponse``: ``runs`` are ``(parameters, KPIs)``
  pairs of one condition (the caller drops jammed runs). Parameters are those every run carries and
  that vary; each is coded to [-1, 1] over the range the runs span, so an effect is the KPI's change
  from the lowest to the highest value run (ordinary least squares with an intercept,
  :func:`bo.screening.effects.least_squares`). Runs without a finite value of ``kpi`` are left out.
  Too few runs for the fit raise :class:`~torchdem.errors.ConfigError` naming the count and ``source``.
* ``KPIResponse.r2``: the share of the KPI's variance over the runs the fit explains;
  ``replicate_sd``: the pooled sd within parameter sets run two or more times (NaN if none).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from bo.campaign.progress import finished_runs
from bo.screening.effects import least_squares
from kpi.loadcell import discharge_jammed
from torchdem.errors import ConfigError


@dataclass(frozen=True)
class KPIResponse:
    """A linear fit of one KPI on the parameters over a campaign's runs.

    Attributes:
        kpi: the KPI's name.
        parameters: ``[k]`` the parameters fitted (carried by every run, not constant).
        low, high: ``[k]`` the range each parameter spans over the runs.
        effect, effect_se: ``[k]`` the KPI's change from ``low`` to ``high`` and its standard error.
        values: ``[n]`` the KPI over the runs fitted.
        residual_sd: sd of what the fit leaves (n - 1 - k degrees of freedom).
        replicate_sd, replicate_dof: the pooled sd within repeated parameter sets, its degrees of freedom.
    """

    kpi: str
    parameters: tuple[str, ...]
    low: np.ndarray
    high: np.ndarray
    effect: np.ndarray
    effect_se: np.ndarray
    values: np.ndarray
    residual_sd: float
    replicate_sd: float
    replicate_dof: int

    @property
    def r2(self) -> float:
        """Share of the KPI's variance over the runs that the fit explains (1 - residual / total)."""
        n, k = len(self.values), len(self.parameters)
        total = float(np.var(self.values, ddof=1))
        return 1.0 - self.residual_sd ** 2 * (n - 1 - k) / ((n - 1) * total) if total > 0 else math.nan


def _pooled_replicate_sd(keys: Sequence[str], values: np.ndarray) -> tuple[float, int]:
    groups: dict[str, list[float]] = {}
    for key, v in zip(keys, values):
        groups.setdefault(key, []).append(float(v))
    squares, dof = 0.0, 0
    for group in groups.values():
        if len(group) >= 2:
            squares += float(np.sum((np.array(group) - np.mean(group)) ** 2))
            dof += len(group) - 1
    return (math.sqrt(squares / dof), dof) if dof else (math.nan, 0)


def store_runs(stores: Sequence[str | Path], condition: str,
               stages: Sequence[str] | None = None) -> list[tuple[dict, dict]]:
    """``(parameters, KPIs)`` of every finished run of ``condition`` in ``stores`` that did not jam, of
    ``stages`` (None: every stage); the stores are opened read only."""
    return [(p, k) for path in stores for stage, c, _, p, k in finished_runs(Path(path), "kpi_response")
            if c == condition and not discharge_jammed(k) and (not stages or stage in stages)]


def kpi_response(runs: Sequence[tuple[Mapping[str, float], Mapping[str, float]]], kpi: str,
                 source: str = "runs") -> KPIResponse:
    """Fit ``kpi`` linearly on the parameters over ``runs`` (module docstring)."""
    runs = [(p, k) for p, k in runs if math.isfinite(float(k.get(kpi, math.nan)))]
    if not runs:
        raise ConfigError(f"{source}: no run has a finite {kpi!r}")
    shared = sorted(set.intersection(*(set(p) for p, _ in runs)))
    x = np.array([[float(p[n]) for n in shared] for p, _ in runs]).reshape(len(runs), len(shared))
    low, high = x.min(0), x.max(0)
    varied = high > low
    names = tuple(n for n, v in zip(shared, varied) if v)
    low, high, x = low[varied], high[varied], x[:, varied]
    y = np.array([float(k[kpi]) for _, k in runs])
    coded = 2.0 * (x - low) / (high - low) - 1.0
    fit = least_squares(np.column_stack([np.ones(len(y)), coded]), y)
    if fit is None:
        raise ConfigError(f"{source}: {len(y)} runs with a finite {kpi!r} cannot fit {len(names)} parameters "
                          f"({', '.join(names)}) and an intercept with a residual left; expected at least "
                          f"{len(names) + 2} runs at distinct parameter sets")
    beta, se, s2, _ = fit
    keys = [json.dumps({n: p[n] for n in shared}, sort_keys=True) for p, _ in runs]
    replicate_sd, replicate_dof = _pooled_replicate_sd(keys, y)
    return KPIResponse(kpi=kpi, parameters=names, low=low, high=high, effect=2.0 * beta[1:], effect_se=2.0 * se[1:],
                       values=y, residual_sd=math.sqrt(s2), replicate_sd=replicate_sd, replicate_dof=replicate_dof)
