"""Time-step study (paper section 3.2.4, Fig. 9) and reduced-shear-modulus study analysis.

Contract
--------
``choose_time_step(fractions, kpi_values, kpi_names)`` takes KPI values
``[n_fractions, replicates, n_kpi]`` measured with the time step set to each fraction of the
Rayleigh time step (NaN for a failed measurement) and returns a ``TimeStepChoice``: mean and
standard deviation (``ddof = 1``) per fraction and KPI, and the largest fraction whose every
deciding KPI, at that fraction *and every smaller one*, passes both of the paper's criteria
relative to the smallest fraction (the reference, the most accurate run):

1. stable mean: ``|mean_f - mean_ref| <= max(ci95_diff, relative_tolerance * |mean_ref|)``,
   where ``ci95_diff = t(0.975, df) * sqrt(s_f^2 / n_f + s_ref^2 / n_ref)`` is the half-width of
   the Welch 95 % confidence interval of the difference of the two means (Welch-Satterthwaite
   ``df``). A difference the replicates cannot resolve, or one below the relative tolerance
   (default 2 %), counts as stable;
2. reproducible: ``std_f <= std_growth_factor * std_ref`` (default factor 2). With
   ``std_ref = 0`` (deterministic reference) any spread fails.

"Up to the selected time step" (the paper's wording) is why the pass must hold for every
smaller fraction too: a fraction that passes after one that failed is not chosen. Every fraction
needs at least two finite replicates of every deciding KPI. ``reasoning`` lists, per fraction,
what failed and why. With ``rayleigh_time_step_s`` the chosen step in seconds is reported too.

``summarise_shear_modulus_study(shear_moduli_pa, kpi_values, kpi_names, wall_times_s)`` does
the same comparison for runs with a reduced shear modulus ``G`` against the reference (largest
``G`` unless given): KPI change, relative change, whether the change is within the tolerance
of criterion 1, the speed-up expected from the Rayleigh time step (``dt ~ sqrt(rho / G)``, so
``sqrt(G_ref / G)`` at a fixed time-step fraction) and, given wall times, the measured speed-up
``wall_ref / wall_G``. ``recommended_modulus_pa`` is the smallest ``G`` such that it and every
larger ``G`` keep all KPIs within tolerance.

Reference: A. Hadi, Y. Pang, D. Schott, section 3.2.4, Eq. 3, Fig. 9 (15 % of the Rayleigh time
step, 5.91e-6 s, was chosen).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import stats

from torchdem.errors import ConfigError, out_of_range

__all__ = [
    "TimeStepChoice",
    "ShearModulusSummary",
    "choose_time_step",
    "summarise_shear_modulus_study",
    "mean_change_tolerance",
]


def _positive(name: str, value, source: str, allowed: str) -> float:
    if (isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer))
            or not math.isfinite(value) or value <= 0):
        raise out_of_range(name, value, allowed, source)
    return float(value)


def _kpi_stats(values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean, std (ddof 1, NaN below 2 values) and count over axis 1 of ``[n, reps, n_kpi]``."""
    finite = np.isfinite(values)
    count = finite.sum(axis=1)
    y0 = np.where(finite, values, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, y0.sum(axis=1) / count, np.nan)
        ss = np.where(finite, (y0 - mean[:, None, :]) ** 2, 0.0).sum(axis=1)
        std = np.where(count > 1, np.sqrt(ss / (count - 1)), np.nan)
    return mean, std, count


def mean_change_tolerance(std_ref: float, n_ref: int, std: float, n: int, mean_ref: float,
                          relative_tolerance: float) -> float:
    """Allowed ``|mean - mean_ref|``: max of the Welch 95 % CI half-width of the difference and
    ``relative_tolerance * |mean_ref|`` (criterion 1 of the module docstring)."""
    var = std_ref**2 / n_ref + std**2 / n
    if var > 0:
        df = var**2 / ((std_ref**2 / n_ref) ** 2 / (n_ref - 1) + (std**2 / n) ** 2 / (n - 1))
        ci = float(stats.t.ppf(0.975, df)) * math.sqrt(var)
    else:
        ci = 0.0
    return max(ci, relative_tolerance * abs(mean_ref))


def _check_values(values, n_points: int, what: str, kpi_names: Sequence[str], source: str):
    names = tuple(kpi_names)
    if not names or len(set(names)) != len(names):
        raise ConfigError(f"{source}: kpi_names = {list(names)!r} is not allowed; expected "
                          f"unique KPI names, at least one")
    arr = np.asarray(values, dtype=np.float64)
    expected = f"[{what}, replicates, n_kpi] = ({n_points}, replicates >= 2, {len(names)})"
    if arr.ndim != 3 or arr.shape[0] != n_points or arr.shape[2] != len(names) or arr.shape[1] < 2:
        raise ConfigError(f"{source}: kpi_values has shape {arr.shape}; expected {expected} for "
                          f"KPIs {list(names)}")
    if np.isinf(arr).any():
        idx = tuple(int(i) for i in np.argwhere(np.isinf(arr))[0])
        raise ConfigError(f"{source}: kpi_values{list(idx)} is infinite; expected a finite "
                          f"number or NaN for a failed measurement")
    return arr, names


def _deciding(kpis, names, source) -> tuple[str, ...]:
    chosen = tuple(names if kpis is None else kpis)
    unknown = [k for k in chosen if k not in names]
    if unknown or not chosen:
        raise ConfigError(f"{source}: deciding KPIs {unknown or list(chosen)} are not allowed; "
                          f"expected a non-empty subset of {list(names)}")
    return chosen


@dataclass(frozen=True, eq=False)
class TimeStepChoice:
    """Statistics of a time-step study and the chosen fraction of the Rayleigh time step.

    Attributes:
        fractions: time-step fractions, ascending (the first is the reference).
        kpi_names: KPIs, column order of the arrays.
        mean, std: ``[n_fractions, n_kpi]`` mean and standard deviation (ddof 1) over replicates.
        n: ``[n_fractions, n_kpi]`` finite replicates.
        mean_stable, std_stable: ``[n_fractions, n_kpi]`` criteria 1 and 2 (True for KPIs that
            do not decide).
        allowed_change: ``[n_fractions, n_kpi]`` the tolerance of criterion 1.
        deciding_kpis: KPIs the choice is based on.
        chosen_fraction: the largest fraction passing, with all smaller ones, for every
            deciding KPI.
        chosen_time_step_s: ``chosen_fraction * rayleigh_time_step_s`` or None.
        relative_tolerance, std_growth_factor: the criteria's settings.
        reasoning: human-readable lines.
    """

    fractions: tuple[float, ...]
    kpi_names: tuple[str, ...]
    mean: np.ndarray
    std: np.ndarray
    n: np.ndarray
    mean_stable: np.ndarray
    std_stable: np.ndarray
    allowed_change: np.ndarray
    deciding_kpis: tuple[str, ...]
    chosen_fraction: float
    chosen_time_step_s: float | None
    relative_tolerance: float
    std_growth_factor: float
    reasoning: tuple[str, ...]

    def to_text(self) -> str:
        width = max(len("fraction"), *(len(k) for k in self.kpi_names))
        lines = ["Time-step study: mean +- std per fraction of the Rayleigh time step"]
        lines.append("  ".join(["fraction".ljust(width)] + [f"{f:>16.3g}" for f in self.fractions]))
        for j, kpi in enumerate(self.kpi_names):
            cells = [f"{m:9.4g} +-{s:5.2g}" for m, s in zip(self.mean[:, j], self.std[:, j])]
            lines.append("  ".join([kpi.ljust(width)] + [f"{c:>16}" for c in cells]))
        return "\n".join(lines + [""] + list(self.reasoning))

    def __str__(self) -> str:
        return self.to_text()

    def to_dict(self) -> dict:
        return {
            "fractions": list(self.fractions), "kpis": list(self.kpi_names),
            "mean": self.mean.tolist(), "std": np.where(np.isnan(self.std), None,
                                                        self.std).tolist(),
            "n": self.n.tolist(), "mean_stable": self.mean_stable.tolist(),
            "std_stable": self.std_stable.tolist(), "deciding_kpis": list(self.deciding_kpis),
            "chosen_fraction": self.chosen_fraction, "chosen_time_step_s": self.chosen_time_step_s,
            "relative_tolerance": self.relative_tolerance,
            "std_growth_factor": self.std_growth_factor, "reasoning": list(self.reasoning)}


def choose_time_step(fractions: Sequence[float], kpi_values, kpi_names: Sequence[str], *,
                     relative_tolerance: float = 0.02, std_growth_factor: float = 2.0,
                     kpis: Sequence[str] | None = None,
                     rayleigh_time_step_s: float | None = None) -> TimeStepChoice:
    """Largest stable, reproducible time-step fraction; see the module docstring.

    ``fractions`` are fractions of the Rayleigh time step in (0, 1], any order (sorted here,
    ``kpi_values`` rows with them). ``kpis`` restricts the deciding KPIs (default all).
    """
    source = "choose_time_step"
    f = np.asarray(fractions, dtype=np.float64)
    if f.ndim != 1 or f.size < 2 or not np.all(np.isfinite(f)) or np.any(f <= 0) \
            or np.any(f > 1) or np.unique(f).size != f.size:
        raise out_of_range("fractions", np.atleast_1d(f).tolist(), "at least two distinct "
                           "fractions of the Rayleigh time step in (0, 1]", source)
    values, names = _check_values(kpi_values, f.size, "n_fractions", kpi_names, source)
    rel = _positive("relative_tolerance", relative_tolerance, source,
                    "a relative tolerance > 0, e.g. 0.02")
    growth = _positive("std_growth_factor", std_growth_factor, source,
                       "a factor >= 1, e.g. 2.0")
    if growth < 1:
        raise out_of_range("std_growth_factor", std_growth_factor, "a factor >= 1, e.g. 2.0",
                           source)
    if rayleigh_time_step_s is not None:
        _positive("rayleigh_time_step_s", rayleigh_time_step_s, source, "a time step > 0 in s")
    deciding = _deciding(kpis, names, source)
    order = np.argsort(f)
    f, values = f[order], values[order]
    mean, std, n = _kpi_stats(values)
    cols = [names.index(k) for k in deciding]
    short = np.argwhere(n[:, cols] < 2)
    if short.size:
        i, c = map(int, short[0])
        raise ConfigError(f"{source}: KPI {deciding[c]!r} at fraction {f[i]:g} has "
                          f"{int(n[i, cols[c]])} finite replicates; expected at least 2")

    mean_ok = np.ones_like(mean, dtype=bool)
    std_ok = np.ones_like(mean, dtype=bool)
    allowed = np.zeros_like(mean)
    for i in range(f.size):
        for j in cols:
            allowed[i, j] = mean_change_tolerance(std[0, j], n[0, j], std[i, j], n[i, j],
                                                  mean[0, j], rel)
            mean_ok[i, j] = abs(mean[i, j] - mean[0, j]) <= allowed[i, j]
            std_ok[i, j] = std[i, j] <= growth * std[0, j]

    reasoning = [f"reference: fraction {f[0]:g} (smallest); criteria: |mean - mean_ref| <= "
                 f"max(Welch 95 % CI of the difference, {rel:g} x |mean_ref|) and std <= "
                 f"{growth:g} x std_ref; deciding KPIs: {', '.join(deciding)}"]
    chosen = 0
    for i in range(1, f.size):
        failures = []
        for j in cols:
            if not mean_ok[i, j]:
                failures.append(f"{names[j]} mean {mean[i, j]:.4g} differs from {mean[0, j]:.4g} "
                                f"by {abs(mean[i, j] - mean[0, j]):.3g} > {allowed[i, j]:.3g}")
            if not std_ok[i, j]:
                failures.append(f"{names[j]} std {std[i, j]:.3g} > {growth:g} x "
                                f"{std[0, j]:.3g}")
        if failures:
            reasoning.append(f"fraction {f[i]:g}: fails: " + "; ".join(failures))
        else:
            reasoning.append(f"fraction {f[i]:g}: all deciding KPIs stable and reproducible")
        if not failures and chosen == i - 1:
            chosen = i
    step_s = None if rayleigh_time_step_s is None else float(f[chosen] * rayleigh_time_step_s)
    tail = "" if step_s is None else f" = {step_s:.3g} s"
    note = ("" if chosen == f.size - 1 else
            f"; fraction {f[chosen + 1]:g} is the first that fails")
    reasoning.append(f"chosen: fraction {f[chosen]:g}{tail} (largest fraction with it and every "
                     f"smaller one passing{note})")
    for arr in (mean, std, n, mean_ok, std_ok, allowed):
        arr.setflags(write=False)
    return TimeStepChoice(
        fractions=tuple(float(v) for v in f), kpi_names=names, mean=mean, std=std, n=n,
        mean_stable=mean_ok, std_stable=std_ok, allowed_change=allowed, deciding_kpis=deciding,
        chosen_fraction=float(f[chosen]), chosen_time_step_s=step_s, relative_tolerance=rel,
        std_growth_factor=growth, reasoning=tuple(reasoning))


@dataclass(frozen=True, eq=False)
class ShearModulusSummary:
    """KPI change and speed-up of runs with a reduced shear modulus.

    Attributes:
        shear_moduli_pa: the moduli, descending (the reference is the largest unless given).
        reference_modulus_pa: the modulus compared against.
        kpi_names: KPIs, column order.
        mean, std: ``[n_G, n_kpi]`` over replicates (std ddof 1).
        change: ``mean - mean_ref``; relative_change: ``change / |mean_ref|``.
        within_tolerance: ``[n_G, n_kpi]`` criterion 1 of the module docstring.
        expected_speedup: ``sqrt(G_ref / G)`` per modulus (Rayleigh time step ~ G^-1/2).
        measured_speedup: ``wall_ref / wall_G`` per modulus, or None without wall times.
        recommended_modulus_pa: smallest G with it and every larger G within tolerance.
        reasoning: human-readable lines.
    """

    shear_moduli_pa: tuple[float, ...]
    reference_modulus_pa: float
    kpi_names: tuple[str, ...]
    mean: np.ndarray
    std: np.ndarray
    change: np.ndarray
    relative_change: np.ndarray
    within_tolerance: np.ndarray
    expected_speedup: tuple[float, ...]
    measured_speedup: tuple[float, ...] | None
    recommended_modulus_pa: float
    reasoning: tuple[str, ...]

    def to_text(self) -> str:
        lines = ["Reduced shear modulus study (change relative to G_ref = "
                 f"{self.reference_modulus_pa:.3g} Pa)"]
        for i, g in enumerate(self.shear_moduli_pa):
            speed = f"expected speed-up {self.expected_speedup[i]:.2f}x"
            if self.measured_speedup is not None:
                speed += f", measured {self.measured_speedup[i]:.2f}x"
            changes = ", ".join(
                f"{k} {self.relative_change[i, j]:+.1%}"
                + ("" if self.within_tolerance[i, j] else " (beyond tolerance)")
                for j, k in enumerate(self.kpi_names))
            lines.append(f"G = {g:.3g} Pa: {speed}; {changes}")
        return "\n".join(lines + [""] + list(self.reasoning))

    def __str__(self) -> str:
        return self.to_text()


def summarise_shear_modulus_study(shear_moduli_pa: Sequence[float], kpi_values,
                                  kpi_names: Sequence[str], wall_times_s=None, *,
                                  reference_modulus_pa: float | None = None,
                                  relative_tolerance: float = 0.02,
                                  kpis: Sequence[str] | None = None) -> ShearModulusSummary:
    """KPI change and speed-up per shear modulus; see the module docstring.

    ``kpi_values`` is ``[n_G, replicates, n_kpi]``; ``wall_times_s`` is ``[n_G]`` or
    ``[n_G, replicates]`` (averaged over replicates) or None. ``kpis`` restricts the KPIs that
    decide ``recommended_modulus_pa``.
    """
    source = "summarise_shear_modulus_study"
    g = np.asarray(shear_moduli_pa, dtype=np.float64)
    if g.ndim != 1 or g.size < 2 or not np.all(np.isfinite(g)) or np.any(g <= 0) \
            or np.unique(g).size != g.size:
        raise out_of_range("shear_moduli_pa", np.atleast_1d(g).tolist(), "at least two distinct "
                           "shear moduli > 0 in Pa", source)
    values, names = _check_values(kpi_values, g.size, "n_moduli", kpi_names, source)
    rel = _positive("relative_tolerance", relative_tolerance, source,
                    "a relative tolerance > 0, e.g. 0.02")
    deciding = _deciding(kpis, names, source)
    g_ref = float(g.max()) if reference_modulus_pa is None else float(reference_modulus_pa)
    if g_ref not in g:
        raise out_of_range("reference_modulus_pa", reference_modulus_pa,
                           f"one of the studied moduli {sorted(g.tolist())}", source)
    walls = None
    if wall_times_s is not None:
        walls = np.asarray(wall_times_s, dtype=np.float64)
        if walls.ndim == 2:
            walls = np.nanmean(walls, axis=1)
        if walls.shape != g.shape or not np.all(np.isfinite(walls)) or np.any(walls <= 0):
            raise ConfigError(f"{source}: wall_times_s = {np.asarray(wall_times_s).tolist()!r} is "
                              f"not allowed; expected positive times in s, shape ({g.size},) or "
                              f"({g.size}, replicates)")
    order = np.argsort(-g)
    g, values = g[order], values[order]
    walls = None if walls is None else walls[order]
    ref = int(np.flatnonzero(g == g_ref)[0])
    mean, std, n = _kpi_stats(values)
    change = mean - mean[ref]
    with np.errstate(invalid="ignore", divide="ignore"):
        relative = change / np.abs(mean[ref])
    within = np.zeros_like(mean, dtype=bool)
    for i in range(g.size):
        for j in range(len(names)):
            if n[i, j] < 2 or n[ref, j] < 2:
                raise ConfigError(f"{source}: KPI {names[j]!r} at G = {g[i]:g} Pa or the "
                                  f"reference has fewer than 2 finite replicates; expected >= 2")
            allowed = mean_change_tolerance(std[ref, j], n[ref, j], std[i, j], n[i, j],
                                            mean[ref, j], rel)
            within[i, j] = abs(change[i, j]) <= allowed
    expected = tuple(math.sqrt(g_ref / v) for v in g)
    measured = None if walls is None else tuple(float(walls[ref] / w) for w in walls)
    cols = [names.index(k) for k in deciding]
    recommended = ref
    reasoning = []
    for i in range(ref + 1, g.size):
        bad = [names[j] for j in cols if not within[i, j]]
        if bad:
            reasoning.append(f"G = {g[i]:.3g} Pa changes {', '.join(bad)} beyond the tolerance")
        elif recommended == i - 1:
            recommended = i
    reasoning.append(f"recommended: G = {g[recommended]:.3g} Pa, the smallest modulus with it and "
                     f"every larger one within tolerance (expected speed-up "
                     f"{expected[recommended]:.2f}x"
                     + ("" if measured is None else f", measured {measured[recommended]:.2f}x")
                     + ")")
    for arr in (mean, std, change, relative, within):
        arr.setflags(write=False)
    return ShearModulusSummary(
        shear_moduli_pa=tuple(float(v) for v in g), reference_modulus_pa=g_ref,
        kpi_names=names, mean=mean, std=std, change=change, relative_change=relative,
        within_tolerance=within, expected_speedup=expected, measured_speedup=measured,
        recommended_modulus_pa=float(g[recommended]), reasoning=tuple(reasoning))
