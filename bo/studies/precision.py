"""Is float32 accurate enough? Equivalence of draw down KPIs in two floating-point precisions.

Contract
--------
A precision study runs the same condition and parameters in float64 and float32, one replicate
per seed (``bo.studies.pipeline.run_precision_study``). For every KPI with a lab margin,
:func:`precision_verdict` asks whether the float32 mean equals the float64 mean within the
margin, by two one-sided tests (TOST, Welch's t, ``statsmodels.stats.weightstats.ttost_ind``):
equivalent when the larger of the two one-sided p-values is below ``alpha`` (equivalently, the
``1 - 2 alpha`` confidence interval of the difference lies inside ``(-margin, margin)``).

The margin of a KPI is the lab's 95 % CI half-width of that KPI (the paper's Table 2 for the
condition), so "equivalent" means: the change of precision moves the KPI by less than the lab
can resolve. With the DEM's replicate scatter ``sd`` (pooled over both precisions) the study
also states the power: the probability that TOST declares equivalence at ``n`` seeds per
precision when the true difference is zero,

    power(n) = max(0, 2 F_t(margin / SE - t_{1-alpha, df}; df) - 1),  SE = sd sqrt(2 / n),  df = 2n - 2,

and the seeds needed for the target power (at least ``minimum_seeds``). A KPI whose test is not
passed although its power is reached fails: float32 moves it. One whose power is not reached is
``undecided``: run it with more seeds (``replicates``; the store shares the seeds already run, so only the new ones run).

``paired=True`` tests paired runs instead (run ``i`` of both variants has the same seed,
parameters and condition, as ``scripts/rerun_equivalence.py`` makes them): TOST on the mean paired
difference (``statsmodels.stats.weightstats.ttost_paired``), ``sd`` the scatter of the
differences, ``SE = sd / sqrt(n)`` and ``df = n - 1`` in the power.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Mapping, Sequence

import numpy as np
from scipy import stats
from statsmodels.stats.weightstats import ttost_ind, ttost_paired

from torchdem.errors import ConfigError, out_of_range

__all__ = ["tost_power", "seeds_for_power", "KPIEquivalence", "PrecisionVerdict", "precision_verdict"]


def tost_power(sd: float, margin: float, n: int, alpha: float = 0.05, paired: bool = False) -> float:
    """Power of TOST with ``n`` runs per group (``paired``: ``n`` pairs, ``sd`` that of the
    differences), scatter ``sd``, true difference 0 (module docstring)."""
    if n < 2 or not sd > 0 or not margin > 0:
        raise out_of_range("(sd, margin, n)", (sd, margin, n), "sd > 0, margin > 0, n >= 2", "tost_power")
    se = sd / math.sqrt(n) if paired else sd * math.sqrt(2.0 / n)
    df = n - 1 if paired else 2 * n - 2
    return max(0.0, 2.0 * float(stats.t.cdf(margin / se - stats.t.ppf(1 - alpha, df), df)) - 1.0)


def seeds_for_power(sd: float, margin: float, alpha: float = 0.05, power: float = 0.8, minimum: int = 10,
                    maximum: int = 10_000, paired: bool = False) -> int | None:
    """Smallest ``n >= minimum`` per group (or pairs) with ``tost_power >= power``; None if above ``maximum``."""
    n = max(2, minimum)
    while n <= maximum:
        if tost_power(sd, margin, n, alpha, paired) >= power:
            return n
        n += 1
    return None


@dataclass(frozen=True)
class KPIEquivalence:
    """TOST of one KPI, float32 (``b``) against float64 (``a``).

    Attributes:
        kpi: KPI name. margin: equivalence margin (the lab's 95 % CI half-width), KPI unit.
        n_a, n_b: finite runs per precision. mean_a, mean_b: their means. difference: mean_b - mean_a.
        sd: replicate scatter pooled over both precisions (paired: the scatter of the differences).
            ci_low, ci_high: the (1 - 2 alpha) CI of the difference (Welch; paired: t on the
            differences). p_value: the larger one-sided p-value.
        power: TOST power at min(n_a, n_b) seeds for the pooled sd. seeds_needed: per precision
            for the target power (None: more than 10,000).
        verdict: ``"equivalent"``, ``"not equivalent"`` (power reached, test failed) or
            ``"undecided"`` (power not reached: run ``seeds_needed`` seeds).
    """

    kpi: str
    margin: float
    n_a: int
    n_b: int
    mean_a: float
    mean_b: float
    difference: float
    sd: float
    ci_low: float
    ci_high: float
    p_value: float
    power: float
    seeds_needed: int | None
    verdict: str


@dataclass(frozen=True)
class PrecisionVerdict:
    """The study's answer: one :class:`KPIEquivalence` per KPI with a margin."""

    labels: tuple[str, str]
    alpha: float
    target_power: float
    rows: tuple[KPIEquivalence, ...]
    skipped: Mapping[str, str]

    @property
    def equivalent(self) -> bool:
        return bool(self.rows) and all(r.verdict == "equivalent" for r in self.rows)

    @property
    def failing(self) -> tuple[str, ...]:
        return tuple(r.kpi for r in self.rows if r.verdict == "not equivalent")

    def to_dict(self) -> dict:
        return {"labels": list(self.labels), "alpha": self.alpha, "target_power": self.target_power,
                "equivalent": self.equivalent, "failing": list(self.failing),
                "rows": [asdict(r) for r in self.rows], "skipped": dict(self.skipped)}

    def to_text(self) -> str:
        a, b = self.labels
        lines = [f"Equivalence of {b} to {a} (TOST, alpha {self.alpha}, margin = the lab's 95 % CI half-width; "
                 f"power for a true difference of 0, target {self.target_power:.0%})",
                 f"| KPI | margin | n {a} / {b} | mean {a} | mean {b} | difference (90 % CI) | sd | p | power | "
                 "seeds for target | verdict |",
                 "| --- | ---: | ---: | ---: | ---: | --- | ---: | ---: | ---: | ---: | --- |"]
        for r in self.rows:
            lines.append(f"| {r.kpi} | {r.margin:.4g} | {r.n_a} / {r.n_b} | {r.mean_a:.4g} | {r.mean_b:.4g} | "
                         f"{r.difference:+.3g} ({r.ci_low:+.3g}, {r.ci_high:+.3g}) | {r.sd:.3g} | {r.p_value:.3g} | "
                         f"{r.power:.2f} | {r.seeds_needed if r.seeds_needed is not None else '>10000'} | "
                         f"{r.verdict} |")
        for k, why in self.skipped.items():
            lines.append(f"- {k}: not tested ({why})")
        if self.equivalent:
            lines.append(f"Verdict: {b} is equivalent to {a} on every tested KPI.")
        elif self.failing:
            lines.append(f"Verdict: {b} is NOT equivalent to {a} on {list(self.failing)}.")
        else:
            undecided = [r.kpi for r in self.rows if r.verdict == "undecided"]
            lines.append(f"Verdict: undecided on {undecided}: the runs have less than {self.target_power:.0%} "
                         "power; run it with more seeds (replicates).")
        return "\n".join(lines)


def precision_verdict(values_a: np.ndarray, values_b: np.ndarray, kpi_names: Sequence[str],
                      margins: Mapping[str, float], *, labels: tuple[str, str] = ("float64", "float32"),
                      alpha: float = 0.05, power: float = 0.8, minimum_seeds: int = 10,
                      paired: bool = False) -> PrecisionVerdict:
    """TOST per KPI of ``values_b`` against ``values_a`` (``[runs, n_kpi]`` each, NaN for failed
    runs and unmeasured KPIs; ``paired``: row ``i`` of both is one pair, and a pair counts where
    both are measured); KPIs without a margin are skipped (see the module docstring)."""
    source = "precision_verdict"
    a, b = np.asarray(values_a, dtype=float), np.asarray(values_b, dtype=float)
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != len(kpi_names) or b.shape[1] != len(kpi_names):
        raise ConfigError(f"{source}: values must be [runs, {len(kpi_names)}] each; got {a.shape} and {b.shape}")
    if paired and a.shape != b.shape:
        raise ConfigError(f"{source}: paired values must have the same shape; got {a.shape} and {b.shape}")
    if not 0 < alpha < 0.5 or not 0 < power < 1:
        raise out_of_range("(alpha, power)", (alpha, power), "alpha in (0, 0.5), power in (0, 1)", source)
    rows, skipped = [], {}
    for j, kpi in enumerate(kpi_names):
        margin = margins.get(kpi)
        if margin is None or not math.isfinite(margin) or margin <= 0:
            skipped[kpi] = "no lab margin"
            continue
        if paired:
            both = np.isfinite(a[:, j]) & np.isfinite(b[:, j])
            xa, xb = a[both, j], b[both, j]
        else:
            xa, xb = a[:, j][np.isfinite(a[:, j])], b[:, j][np.isfinite(b[:, j])]
        if len(xa) < 2 or len(xb) < 2:
            skipped[kpi] = f"fewer than 2 measured {'pairs' if paired else 'runs'} ({len(xa)} and {len(xb)})"
            continue
        if paired:
            sd = float((xb - xa).std(ddof=1))
        else:
            sd = math.sqrt(((len(xa) - 1) * xa.var(ddof=1) + (len(xb) - 1) * xb.var(ddof=1))
                           / (len(xa) + len(xb) - 2))
        diff = float(xb.mean() - xa.mean())
        if sd == 0:  # identical runs within each precision (paired: identical differences): the difference is exact
            p = 0.0 if abs(diff) < margin else 1.0
            lo = hi = diff
            pw, need = 1.0, max(2, minimum_seeds)
        elif paired:
            p, _, _ = ttost_paired(xb, xa, -margin, margin)
            half = float(stats.t.ppf(1 - alpha, len(xa) - 1)) * sd / math.sqrt(len(xa))
            lo, hi = diff - half, diff + half
            pw = tost_power(sd, margin, len(xa), alpha, paired=True)
            need = seeds_for_power(sd, margin, alpha, power, minimum_seeds, paired=True)
        else:
            p, _, _ = ttost_ind(xb, xa, -margin, margin, usevar="unequal")
            se = math.sqrt(xa.var(ddof=1) / len(xa) + xb.var(ddof=1) / len(xb))
            va, vb = xa.var(ddof=1) / len(xa), xb.var(ddof=1) / len(xb)
            df = (va + vb) ** 2 / (va ** 2 / (len(xa) - 1) + vb ** 2 / (len(xb) - 1)) if va + vb > 0 else 1.0
            half = float(stats.t.ppf(1 - alpha, df)) * se
            lo, hi = diff - half, diff + half
            pw = tost_power(sd, margin, min(len(xa), len(xb)), alpha)
            need = seeds_for_power(sd, margin, alpha, power, minimum_seeds)
        p = float(p)
        verdict = "equivalent" if p < alpha else ("not equivalent" if pw >= power else "undecided")
        rows.append(KPIEquivalence(kpi=kpi, margin=float(margin), n_a=len(xa), n_b=len(xb), mean_a=float(xa.mean()),
                                   mean_b=float(xb.mean()), difference=diff, sd=sd, ci_low=lo, ci_high=hi,
                                   p_value=p, power=pw, seeds_needed=need, verdict=verdict))
    return PrecisionVerdict(labels=labels, alpha=alpha, target_power=power, rows=tuple(rows), skipped=skipped)
