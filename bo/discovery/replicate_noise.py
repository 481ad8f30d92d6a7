"""DEM replicate noise per KPI, pooled over every group of replicates a study ran.

Why pooled: discovery compares DEM means of a few replicates (often 2) with measurements. The
standard error of one cell's mean estimated from its own 2 runs has 1 degree of freedom: its
square is a chi^2_1 variate times sigma^2, so it is below a tenth of the truth one time in four
and the cell's z then reads 3 x too large (z follows a t-distribution with 1 dof, which has no
variance). The replicate scatter of a KPI is a property of the test (packing, discharge), and
changes little between nearby parameter sets or between mixtures of the same box. Pooling the
within-group sums of squares of every group run (every condition, design point, held-out set)
gives one variance per KPI with many degrees of freedom; a cell's standard error is then
``sqrt(variance_k / n)``.

Contract
--------
``ReplicateNoise.of(kpis, groups)``: ``groups`` are arrays ``[..., r, K]`` whose last-but-one axis
holds the replicates of one group (NaN: missing). For KPI k::

    dof_k      = sum_g (n_gk - 1)                 over groups with n_gk >= 2
    variance_k = sum_g sum_i (x_gik - mean_gk)^2 / dof_k      (NaN when dof_k = 0)

``a.pooled(b)`` combines two estimates (sums of squares and dof add). ``se(k, n)`` is
``sqrt(variance_k / n)`` (NaN when unknown or n = 0).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

__all__ = ["ReplicateNoise"]


@dataclass(frozen=True)
class ReplicateNoise:
    """Pooled replicate variance per KPI.

    Attributes:
        kpis: KPI names, length K.
        sum_squares: ``[K]`` within-group sums of squared deviations.
        dof: ``[K]`` degrees of freedom, ``sum_g (n_g - 1)``.
    """

    kpis: tuple[str, ...]
    sum_squares: tuple[float, ...]
    dof: tuple[int, ...]

    @classmethod
    def of(cls, kpis: Sequence[str], groups: Iterable[np.ndarray]) -> "ReplicateNoise":
        K = len(kpis)
        ss, dof = np.zeros(K), np.zeros(K, dtype=np.int64)
        for g in groups:
            g = np.asarray(g, dtype=np.float64)
            if g.ndim < 2 or g.shape[-1] != K:
                raise ValueError(f"replicate groups: expected [..., r, {K}] for KPIs {list(kpis)}, got {g.shape}")
            x = g.reshape(-1, g.shape[-2], K)
            finite = np.isfinite(x)
            n = finite.sum(axis=1)                                      # [G, K]
            mean = np.where(n > 0, np.nansum(x, axis=1) / np.maximum(n, 1), 0.0)
            dev = np.where(finite, x - mean[:, None, :], 0.0)
            ok = n >= 2
            ss += np.where(ok, (dev ** 2).sum(axis=1), 0.0).sum(axis=0)
            dof += np.where(ok, n - 1, 0).sum(axis=0)
        return cls(tuple(kpis), tuple(map(float, ss)), tuple(map(int, dof)))

    def pooled(self, other: "ReplicateNoise") -> "ReplicateNoise":
        if other.kpis != self.kpis:
            raise ValueError(f"replicate noise: KPIs differ: {list(self.kpis)} and {list(other.kpis)}")
        return ReplicateNoise(self.kpis, tuple(a + b for a, b in zip(self.sum_squares, other.sum_squares)),
                              tuple(a + b for a, b in zip(self.dof, other.dof)))

    def variance(self, kpi: str) -> float:
        k = self.kpis.index(kpi)
        return self.sum_squares[k] / self.dof[k] if self.dof[k] > 0 else math.nan

    def se(self, kpi: str, n: int) -> float:
        """Standard error of a mean of ``n`` replicates (NaN when the variance is unknown or n = 0)."""
        return math.sqrt(self.variance(kpi) / n) if n > 0 else math.nan

    def to_dict(self) -> dict:
        return {k: {"sd": math.sqrt(self.variance(k)) if self.dof[i] > 0 else math.nan, "dof": self.dof[i]}
                for i, k in enumerate(self.kpis)}
