"""Materials, per-pair interaction tables and the derived contact constants.

Contract:
- A :class:`Material` holds intrinsic properties (shear modulus G [Pa], Poisson ratio nu,
  solid density rho [kg/m^3]); walls are materials too (their density is unused).
- :class:`InteractionTable` holds the calibrated interaction coefficients for every ordered
  material pair and every ensemble member: tensors of shape ``[B, M, M]``, symmetric in the
  last two axes. Member ``b`` of a batched ensemble may use its own coefficients and its own
  particle densities (``density`` ``[B, M]``).
- The effective moduli and the damping factor follow the Hertz-Mindlin (no-slip) model as
  implemented in EDEM and LIGGGHTS (see :mod:`torchdem.contact`).

Every constructor validates its input and raises :class:`torchdem.errors.ConfigError`
naming the value, the allowed range and the source (config key or argument).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Mapping, Sequence

import torch

from torchdem.errors import ConfigError, out_of_range

Tensor = torch.Tensor


@dataclass(frozen=True)
class Material:
    """Intrinsic properties of one material (particles or geometry).

    Attributes:
        name: unique name (``"pellet"``, ``"sinter"``, ``"steel"``).
        shear_modulus: G in Pa, > 0.
        poisson_ratio: nu in (-1, 0.5).
        density: solid density in kg/m^3 (> 0 for particle materials; ignored for walls).
    """

    name: str
    shear_modulus: float
    poisson_ratio: float
    density: float = 0.0

    def validate(self, source: str = "Material") -> "Material":
        src = f"{source}[{self.name}]"
        if not (self.shear_modulus > 0 and math.isfinite(self.shear_modulus)):
            raise out_of_range("shear_modulus", self.shear_modulus, "a finite value > 0 Pa", src)
        if not (-1.0 < self.poisson_ratio < 0.5):
            raise out_of_range("poisson_ratio", self.poisson_ratio, "a value in (-1, 0.5)", src)
        if not (self.density >= 0 and math.isfinite(self.density)):
            raise out_of_range("density", self.density, "a finite value >= 0 kg/m^3", src)
        return self

    @property
    def young_modulus(self) -> float:
        """E = 2 G (1 + nu) in Pa."""
        return 2.0 * self.shear_modulus * (1.0 + self.poisson_ratio)


COEFFICIENT_RANGES: dict[str, tuple[float, float, bool, bool]] = {
    # name: (low, high, low_inclusive, high_inclusive)
    "mu_s": (0.0, math.inf, True, False),
    "mu_r": (0.0, math.inf, True, False),
    "restitution": (0.0, 1.0, False, True),
    "rolling_damping": (0.0, math.inf, True, False),
    "cohesion": (0.0, math.inf, True, False),
}
#: Coefficients a pair may leave out, with their default (every other one is required).
OPTIONAL_COEFFICIENTS = {"rolling_damping": 0.0, "cohesion": 0.0}


def _range_text(low: float, high: float, lo_inc: bool, hi_inc: bool) -> str:
    return f"{'[' if lo_inc else '('}{low}, {high}{']' if hi_inc else ')'}"


def check_coefficient(name: str, values: Tensor, source: str) -> None:
    """Raise ConfigError if any entry of ``values`` is outside the allowed range of ``name``.

    NaN marks a pair that was not given (e.g. wall-wall) and is not checked here; the system
    builder rejects undefined pairs that can actually touch.
    """
    low, high, lo_inc, hi_inc = COEFFICIENT_RANGES[name]
    values = values[~torch.isnan(values)]
    ok = torch.isfinite(values) | (values == math.inf)
    ok &= (values >= low) if lo_inc else (values > low)
    ok &= (values <= high) if hi_inc else (values < high)
    if not bool(ok.all()):
        bad = values[~ok].flatten()[0].item()
        raise out_of_range(name, bad, _range_text(low, high, lo_inc, hi_inc), source)


@dataclass(frozen=True)
class InteractionTable:
    """Interaction coefficients for every material pair and ensemble member.

    Attributes (all ``[B, M, M]``, symmetric, dimensionless):
        mu_s: coefficient of sliding (Coulomb) friction.
        mu_r: coefficient of rolling friction (plastic limit of the rolling torque is
            ``mu_r * R_eff * F_n``).
        restitution: coefficient of restitution, in (0, 1].
        rolling_damping: viscous rolling damping ratio eta_r of the EPSD model (0 disables it).
        cohesion: SJKR cohesion energy density k_c, J/m^3 (0: no cohesion; see
            :func:`torchdem.contact.sjkr_cohesion`).
    And ``density`` ``[B, M]`` in kg/m^3: particle density per member and material.
    """

    mu_s: Tensor
    mu_r: Tensor
    restitution: Tensor
    rolling_damping: Tensor
    density: Tensor
    cohesion: Tensor | None = None

    def __post_init__(self):
        if self.cohesion is None:
            object.__setattr__(self, "cohesion", torch.where(torch.isnan(self.mu_s), self.mu_s,
                                                             torch.zeros_like(self.mu_s)))

    @property
    def batch(self) -> int:
        return self.mu_s.shape[0]

    def validate(self, source: str = "InteractionTable") -> "InteractionTable":
        for name in ("mu_s", "mu_r", "restitution", "rolling_damping", "cohesion"):
            values = getattr(self, name)
            check_coefficient(name, values, source)
            if not torch.equal(torch.nan_to_num(values, nan=-1.0), torch.nan_to_num(values.transpose(1, 2), nan=-1.0)):
                raise ConfigError(f"{source}: {name} table is not symmetric in the material pair")
        if not bool((torch.isfinite(self.density) & (self.density >= 0)).all()):
            raise out_of_range("density", self.density.min().item(), "finite values >= 0 kg/m^3", source)
        return self


def _as_member_tensor(value, batch: int, name: str, source: str, dtype, device) -> Tensor:
    t = torch.as_tensor(value, dtype=dtype, device=device)
    if t.ndim == 0:
        return t.expand(batch).clone()
    if t.ndim == 1 and t.shape[0] == batch:
        return t.clone()
    raise ConfigError(
        f"{source}: {name} must be a scalar or a sequence of length B={batch} (one per ensemble "
        f"member); got shape {tuple(t.shape)}"
    )


def interaction_table(
    materials: Sequence[Material],
    pairs: Mapping[tuple[str, str], Mapping[str, object]],
    batch: int = 1,
    density: Mapping[str, object] | None = None,
    *,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str = "cpu",
    source: str = "interaction_table",
) -> InteractionTable:
    """Build a validated :class:`InteractionTable` from named pairs.

    Args:
        materials: the M materials; their order defines material ids.
        pairs: ``{(name_a, name_b): {"mu_s": v, "mu_r": v, "restitution": v,
            "rolling_damping": v, "cohesion": v}}``; each v is a scalar or a length-B sequence
            (one value per ensemble member). Every unordered pair of materials that can touch
            must appear once (either order); pairs left out (wall-wall) stay undefined (NaN) and
            the system builder refuses a system in which an undefined pair can touch.
            ``rolling_damping`` and ``cohesion`` default to 0.
        batch: B, the number of ensemble members.
        density: optional per-material density override, scalar or length-B per name
            (defaults to ``Material.density``).
    """
    names = [m.name for m in materials]
    if len(set(names)) != len(names):
        raise ConfigError(f"{source}: material names must be unique, got {names}")
    for m in materials:
        m.validate(source)
    if batch < 1:
        raise out_of_range("batch", batch, "an integer >= 1", source)
    index = {n: k for k, n in enumerate(names)}
    M = len(names)
    tables = {k: torch.full((batch, M, M), float("nan"), dtype=dtype, device=device)
              for k in ("mu_s", "mu_r", "restitution", "rolling_damping", "cohesion")}
    for (a, b), coeffs in pairs.items():
        for n in (a, b):
            if n not in index:
                raise ConfigError(f"{source}: pair ({a}, {b}) names unknown material {n!r}; known: {names}")
        unknown = set(coeffs) - set(tables)
        if unknown:
            raise ConfigError(f"{source}: pair ({a}, {b}) has unknown coefficient(s) {sorted(unknown)}; "
                              f"allowed: {sorted(tables)}")
        for key in tables:
            if key not in coeffs and key not in OPTIONAL_COEFFICIENTS:
                raise ConfigError(f"{source}: pair ({a}, {b}) is missing {key!r}")
            value = coeffs.get(key, OPTIONAL_COEFFICIENTS.get(key))
            v = _as_member_tensor(value, batch, key, f"{source}[{a},{b}]", dtype, device)
            check_coefficient(key, v, f"{source}[{a},{b}]")
            ia, ib = index[a], index[b]
            tables[key][:, ia, ib] = v
            tables[key][:, ib, ia] = v
    dens = torch.empty((batch, M), dtype=dtype, device=device)
    for k, m in enumerate(materials):
        value = (density or {}).get(m.name, m.density)
        dens[:, k] = _as_member_tensor(value, batch, f"density[{m.name}]", source, dtype, device)
    table = InteractionTable(density=dens, **tables)
    return table.validate(source)


def effective_young_modulus(E1: Tensor, nu1: Tensor, E2: Tensor, nu2: Tensor) -> Tensor:
    """Hertz effective modulus: 1/E* = (1 - nu1^2)/E1 + (1 - nu2^2)/E2  [Pa]."""
    return 1.0 / ((1 - nu1 ** 2) / E1 + (1 - nu2 ** 2) / E2)


def effective_shear_modulus(E1: Tensor, nu1: Tensor, E2: Tensor, nu2: Tensor) -> Tensor:
    """Mindlin effective shear modulus: 1/G* = 2(2-nu1)(1+nu1)/E1 + 2(2-nu2)(1+nu2)/E2  [Pa]."""
    return 1.0 / (2 * (2 - nu1) * (1 + nu1) / E1 + 2 * (2 - nu2) * (1 + nu2) / E2)


def damping_beta(restitution: Tensor) -> Tensor:
    """beta = ln(e) / sqrt(ln(e)^2 + pi^2) (<= 0), the EDEM/LIGGGHTS Hertz-Mindlin damping factor.

    With the damping force -2 sqrt(5/6) beta sqrt(S_n m*) v_n acting throughout the contact
    (attractive at the very end, as in LIGGGHTS with ``limitForce off``) a binary Hertz
    collision rebounds with exactly the input restitution e, independent of impact speed.
    """
    log_e = torch.log(restitution)
    return log_e / torch.sqrt(log_e ** 2 + math.pi ** 2)


def rayleigh_time_step(radius: float, density: float, shear_modulus: float, poisson_ratio: float) -> float:
    """Rayleigh time step (Eq. 3 of Hadi et al.): pi r sqrt(rho/G) / (0.1631 nu + 0.8766) [s]."""
    return math.pi * radius * math.sqrt(density / shear_modulus) / (0.1631 * poisson_ratio + 0.8766)


@dataclass(frozen=True)
class MaterialTables:
    """Per-member, per-pair constants derived once from materials and coefficients.

    Attributes (``[B, M, M]`` unless noted):
        young_eff: E* [Pa]; shear_eff: G* [Pa]; beta: damping factor (<= 0);
        mu_s, mu_r, rolling_damping, cohesion: as in :class:`InteractionTable`;
        density: ``[B, M]`` kg/m^3.
    """

    young_eff: Tensor
    shear_eff: Tensor
    beta: Tensor
    mu_s: Tensor
    mu_r: Tensor
    rolling_damping: Tensor
    density: Tensor
    cohesion: Tensor

    @property
    def n_materials(self) -> int:
        return self.young_eff.shape[-1]

    CONTACT_FIELDS = ("young_eff", "shear_eff", "beta", "mu_s", "mu_r", "rolling_damping", "cohesion")

    @functools.cached_property
    def stacked(self) -> Tensor:
        """``[7, B * M * M]``: the :attr:`CONTACT_FIELDS` tables flattened, one row each, so
        that one ``index_select`` along the columns gathers all of them for a contact list,
        each row contiguous."""
        return torch.stack([getattr(self, f).reshape(-1) for f in self.CONTACT_FIELDS])

    LAW_FIELDS = ("young_eff", "shear_eff", "beta", "mu_s", "mu_r", "rolling_damping")

    @functools.cached_property
    def law_table(self) -> Tensor:
        """``[6, B * M * M]``: the :attr:`LAW_FIELDS` tables (the constants of the contact law), in
        the row order the C++ pair kernel reads."""
        return torch.stack([getattr(self, f).reshape(-1) for f in self.LAW_FIELDS])

    def gather(self, index: Tensor) -> dict[str, Tensor]:
        """The :attr:`CONTACT_FIELDS` at flat pair-table indices ``index`` ``[P]``: ``[P]`` each."""
        rows = torch.index_select(self.stacked, 1, index)
        return dict(zip(self.CONTACT_FIELDS, rows.unbind(0)))


def material_tables(materials: Sequence[Material], table: InteractionTable) -> MaterialTables:
    """Derive the per-pair contact constants for every member (see :class:`MaterialTables`)."""
    dtype, device = table.mu_s.dtype, table.mu_s.device
    E = torch.tensor([m.young_modulus for m in materials], dtype=dtype, device=device)
    nu = torch.tensor([m.poisson_ratio for m in materials], dtype=dtype, device=device)
    E1, E2 = E[:, None], E[None, :]
    n1, n2 = nu[:, None], nu[None, :]
    B = table.batch
    young = effective_young_modulus(E1, n1, E2, n2).expand(B, -1, -1).contiguous()
    shear = effective_shear_modulus(E1, n1, E2, n2).expand(B, -1, -1).contiguous()
    return MaterialTables(
        young_eff=young,
        shear_eff=shear,
        beta=damping_beta(table.restitution),
        mu_s=table.mu_s,
        mu_r=table.mu_r,
        rolling_damping=table.rolling_damping,
        density=table.density,
        cohesion=table.cohesion,
    )
