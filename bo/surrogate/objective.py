"""Calibration objective: weighted sum of absolute relative KPI errors (paper Eqs. 7-8).

Contract
--------
``ObjectiveSpec`` holds the KPI names, the measured (experimental) value of each KPI and a
weight per KPI. Weights default to equal (``1 / M``); given weights must be finite, ``>= 0``
and sum to 1 within ``1e-9``. Measured values must be finite and non-zero (Eq. 8 divides by
them). The spec is a frozen dataclass; every validation error is a ``ConfigError`` that names
the bad value, the allowed range and the spec's ``source``.

``spec(simulated)`` (alias ``spec.weighted_relative_error``) evaluates::

    WS = sum_m w_m |(y_DEM,m - y_Exp,m) / y_Exp,m|          (Eqs. 7 and 8)

vectorised over points. ``simulated`` is either

* an array / tensor of shape ``[..., M]`` whose last axis follows ``kpi_names`` (a NumPy
  array gives a NumPy array of shape ``[...]``, a torch tensor gives a tensor of the same dtype
  and device, differentiable, so the same function composes posterior samples inside an
  acquisition function: samples ``[S, b, q, M] -> [S, b, q]``), or
* a mapping ``{kpi name: values [...]}`` holding exactly the spec's KPIs (an unknown or a
  missing KPI is an error).

``spec.relative_errors(simulated)`` returns the signed errors ``(y_DEM - y_Exp) / y_Exp`` of
shape ``[..., M]`` (the paper's Fig. 14 plots them in percent).

Paper: A. Hadi, Y. Pang, D. Schott, "Systematic DEM calibration of two-component mixtures
using AI-accelerated surrogate models", section 3.4.2.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import torch

from torchdem.errors import ConfigError, out_of_range

__all__ = ["ObjectiveSpec", "WEIGHT_SUM_TOLERANCE"]

#: Allowed deviation of the weight sum from 1.
WEIGHT_SUM_TOLERANCE = 1e-9


@dataclass(frozen=True)
class ObjectiveSpec:
    """KPIs, their measured values and weights for the objective of Eqs. 7-8.

    Attributes:
        kpi_names: KPI names (unique, non-empty strings), e.g. ``("angle_of_repose",
            "shear_angle", "mass_flow_rate", ...)``; their order is the order of the last axis
            of every KPI array passed to this spec.
        measured: experimental value ``y_Exp`` per KPI (finite, non-zero), in the KPI's unit.
        weights: ``w_m`` per KPI, ``>= 0``, summing to 1 within 1e-9; ``None`` (default) means
            equal weights ``1 / M`` as in the paper.
        source: where the spec came from (config key, file or function), named in errors.
    """

    kpi_names: tuple[str, ...]
    measured: tuple[float, ...]
    weights: tuple[float, ...] | None = None
    source: str = "ObjectiveSpec"

    def __post_init__(self) -> None:
        src = self.source
        names = self.kpi_names
        if isinstance(names, str) or not isinstance(names, Sequence):
            raise ConfigError(f"{src}: kpi_names = {names!r} is not allowed; expected a sequence "
                              f"of KPI names such as ('angle_of_repose', 'shear_angle')")
        names = tuple(names)
        if not names:
            raise out_of_range("kpi_names", names, "at least one KPI name", src)
        bad = [n for n in names if not isinstance(n, str) or not n]
        if bad:
            raise ConfigError(f"{src}: KPI names {bad!r} are not allowed; expected non-empty "
                              f"strings")
        if len(set(names)) != len(names):
            dupes = sorted({n for n in names if names.count(n) > 1})
            raise ConfigError(f"{src}: KPI names must be unique; repeated: {dupes}")
        object.__setattr__(self, "kpi_names", names)
        m = len(names)

        measured = self._floats("measured", self.measured, m)
        for name, value in zip(names, measured):
            if not math.isfinite(value) or value == 0.0:
                raise out_of_range(f"measured[{name!r}]", value,
                                   "a finite, non-zero measured value (Eq. 8 divides by it)", src)
        object.__setattr__(self, "measured", measured)

        if self.weights is None:
            weights = tuple(1.0 / m for _ in names)
        else:
            weights = self._floats("weights", self.weights, m)
            for name, w in zip(names, weights):
                if not math.isfinite(w) or w < 0.0:
                    raise out_of_range(f"weights[{name!r}]", w, "a finite weight >= 0", src)
            total = math.fsum(weights)
            if abs(total - 1.0) > WEIGHT_SUM_TOLERANCE:
                raise ConfigError(
                    f"{src}: weights = {weights!r} sum to {total!r}; expected weights that sum "
                    f"to 1 within {WEIGHT_SUM_TOLERANCE:g} (Eq. 7)")
        object.__setattr__(self, "weights", weights)

    def _floats(self, field: str, values, m: int) -> tuple[float, ...]:
        if isinstance(values, (str, bytes)) or not isinstance(values, Sequence | np.ndarray):
            raise ConfigError(f"{self.source}: {field} = {values!r} is not allowed; expected "
                              f"{m} numbers, one per KPI {list(self.kpi_names)}")
        if len(values) != m:
            raise ConfigError(f"{self.source}: {field} has {len(values)} values but there are "
                              f"{m} KPIs {list(self.kpi_names)}; expected one value per KPI")
        try:
            return tuple(float(v) for v in values)
        except (TypeError, ValueError) as err:
            raise ConfigError(f"{self.source}: {field} = {values!r} must be numbers") from err

    # ----------------------------------------------------------------------------------------
    @classmethod
    def from_measured(cls, measured: Mapping[str, float],
                      weights: Mapping[str, float] | None = None,
                      source: str = "ObjectiveSpec.from_measured") -> "ObjectiveSpec":
        """Build from ``{kpi: measured value}`` and optional ``{kpi: weight}``.

        KPI order follows ``measured``. A weight for a KPI that has no measured value, or a
        missing weight, is an error.
        """
        names = tuple(measured)
        w = None
        if weights is not None:
            unknown = [k for k in weights if k not in measured]
            missing = [k for k in names if k not in weights]
            if unknown or missing:
                raise ConfigError(
                    f"{source}: weights do not match the measured KPIs; unknown KPI(s) "
                    f"{unknown}, missing {missing}; expected exactly {list(names)}")
            w = tuple(weights[k] for k in names)
        return cls(kpi_names=names, measured=tuple(measured[k] for k in names), weights=w,
                   source=source)

    @property
    def n_kpis(self) -> int:
        """Number of KPIs ``M``."""
        return len(self.kpi_names)

    def index(self, kpi: str) -> int:
        """Column of ``kpi`` in KPI arrays; an unknown KPI raises ``ConfigError``."""
        if kpi not in self.kpi_names:
            raise ConfigError(f"{self.source}: unknown KPI {kpi!r}; expected one of "
                              f"{list(self.kpi_names)}")
        return self.kpi_names.index(kpi)

    def as_array(self, simulated) -> np.ndarray | torch.Tensor:
        """KPI values as ``[..., M]`` (tensors stay tensors); validates names and shape."""
        if isinstance(simulated, Mapping):
            unknown = [k for k in simulated if k not in self.kpi_names]
            missing = [k for k in self.kpi_names if k not in simulated]
            if unknown or missing:
                raise ConfigError(
                    f"{self.source}: simulated KPIs do not match the spec; unknown KPI(s) "
                    f"{unknown}, missing {missing}; expected exactly {list(self.kpi_names)}")
            cols = [simulated[k] for k in self.kpi_names]
            if all(torch.is_tensor(c) for c in cols):
                return torch.stack(torch.broadcast_tensors(*cols), dim=-1)
            return np.stack(np.broadcast_arrays(*[np.asarray(c, dtype=np.float64)
                                                  for c in cols]), axis=-1)
        if not torch.is_tensor(simulated):
            simulated = np.asarray(simulated, dtype=np.float64)
        if simulated.ndim < 1 or simulated.shape[-1] != self.n_kpis:
            raise ConfigError(
                f"{self.source}: simulated KPIs have shape {tuple(simulated.shape)}; expected "
                f"[..., {self.n_kpis}] with the last axis in the order {list(self.kpi_names)}")
        return simulated

    def _constants(self, like):
        if torch.is_tensor(like):
            kw = dict(dtype=like.dtype if like.is_floating_point() else torch.float64,
                      device=like.device)
            return torch.tensor(self.measured, **kw), torch.tensor(self.weights, **kw)
        return np.asarray(self.measured), np.asarray(self.weights)

    def relative_errors(self, simulated):
        """Signed relative errors ``(y_DEM - y_Exp) / y_Exp``, shape ``[..., M]``."""
        y = self.as_array(simulated)
        measured, _ = self._constants(y)
        return (y - measured) / measured

    def weighted_relative_error(self, simulated):
        """``sum_m w_m |RE_m|`` (Eqs. 7-8), shape ``[...]`` (array in, array out)."""
        y = self.as_array(simulated)
        measured, weights = self._constants(y)
        return (abs((y - measured) / measured) * weights).sum(-1)

    __call__ = weighted_relative_error
