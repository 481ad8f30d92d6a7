"""Definitive screening designs (DSD): construction, scaling, and a property checker.

Contract
--------
``definitive_screening_design(n_factors, n_fake)`` returns the coded design of Jones &
Nachtsheim (2011), built from a conference matrix as in Xiao, Lin & Bai (2012)::

    D = [ C ; -C ; 0 ]        (2m + 1 runs, levels -1 / 0 / +1)

where ``C`` is a conference matrix of order ``m``: zero diagonal, +-1 off the diagonal and
``C^T C = (m - 1) I``. The order is ``m = n_factors + n_fake`` when that total is even and
``n_factors + n_fake + 1`` when it is odd (the extra column is dropped, standard practice).
Fake factors are extra columns that are built and then dropped, so the returned array has
``n_factors`` columns and ``2m + 1`` rows; they buy extra runs and degrees of freedom. The
paper's 12 factors with 2 fake factors give ``m = 14`` and 29 runs, which the paper (after JMP)
counts as ``2k + 5`` with ``k = 12``.

Every returned design has, exactly (integer arithmetic in float64):

* three levels -1, 0, +1 in every column, three zeros per column (one in ``C``, one in
  ``-C``, the centre run);
* fold-over: every run's mirror ``-run`` is also a run; the last run is the centre run;
* main effects mutually orthogonal: ``X^T X = 2 (m - 1) I``;
* every main-effect column has zero inner product with every centred quadratic column
  ``x_j^2 - mean(x_j^2)`` and every centred two-factor interaction column
  ``x_j x_l - mean(x_j x_l)`` (the fold-over makes every cubic term vanish).

Conference matrices (``conference_matrix(order)``), each checked when built:

* order 2: ``[[0, 1], [1, 0]]``;
* Paley I, skew-symmetric, order ``q + 1`` for a prime power ``q = 3 (mod 4)``:
  4, 8, 12, 20, 24, 28, 32, 44, 48, 60, ...;
* Paley II, symmetric, order ``q + 1`` for a prime power ``q = 1 (mod 4)``:
  6, 10, 14, 18, 26, 30, 38, 42, 50, 54, 62, ...;
* doubling of a skew conference matrix ``S`` of order n (``H = S + I`` is skew-Hadamard,
  ``[[H, H], [-H^T, H^T]] - I`` is a skew conference matrix of order 2n): 16, 40, 56, 64, ...

Supported orders up to 64: 2-20, 24-32, 38-44, 48-50, 54-56, 60-64 (even orders only).
Orders 22, 34 and 58 have no conference matrix at all (for an order m = 2 mod 4, m - 1 must be
a sum of two squares; Belevitch 1950); conference matrices of orders 36, 46 (Mathon 1978) and
52 are known but not constructed here. Asking for an unsupported order raises an error that
lists the allowed ``n_factors + n_fake`` and the smallest ``n_fake`` that works.

Scaling to physical values uses a ``ParameterTable`` (names, low, mid, high): coded -1/0/+1
map to low/mid/high. ``paper_parameter_table()`` is the paper's Table 4 and ``paper_design()``
its Table A.1 (physical values), both shipped in ``bo/data``. ``code_design`` maps physical
values back to the nearest level within a tolerance.

``check_dsd(coded)`` reports which of the properties above a coded design has; it does not
assume its input is a DSD. See its docstring for the exact quantities.

References: B. Jones, C. J. Nachtsheim, "A class of three-level designs for definitive
screening in the presence of second-order effects", J. Qual. Technol. 43 (2011) 1-15;
L. Xiao, D. K. J. Lin, F. Bai, "Constructing definitive screening designs using conference
matrices", J. Qual. Technol. 44 (2012) 2-8; R. E. A. C. Paley, "On orthogonal matrices",
J. Math. Phys. 12 (1933) 311-320.
Paper: A. Hadi, Y. Pang, D. Schott, "Systematic DEM calibration of two-component mixtures
using AI-accelerated surrogate models", section 3.3, Tables 4 and A.1.
"""
from __future__ import annotations

import functools
import itertools
import json
from dataclasses import dataclass
from importlib import resources
from typing import Mapping, Sequence

import numpy as np

from torchdem.errors import ConfigError, out_of_range

__all__ = [
    "ParameterTable",
    "DSDReport",
    "PAPER_PARAMETER_NAMES",
    "conference_matrix",
    "conference_order",
    "supported_conference_orders",
    "definitive_screening_design",
    "scale_design",
    "code_design",
    "paper_parameter_table",
    "paper_design",
    "check_dsd",
]

#: The paper's 12 DEM parameters in its column order (Table 4 / Table A.1). ``e`` is the
#: coefficient of restitution (the paper's C_r); suffixes: pp pellet-pellet, ss sinter-sinter,
#: pg pellet-geometry, sg sinter-geometry.
PAPER_PARAMETER_NAMES: tuple[str, ...] = (
    "mu_s_pp", "mu_r_pp", "e_pp",
    "mu_s_ss", "mu_r_ss", "e_ss",
    "mu_s_pg", "mu_r_pg", "e_pg",
    "mu_s_sg", "mu_r_sg", "e_sg",
)

_TABLE4_FILE = "table4_dsd_levels.json"
_TABLEA1_FILE = "tableA1_paper_dsd.json"
_LISTED_ORDERS_UP_TO = 64  # how far error messages list the supported orders
# Orders <= 64 with a conference matrix in the literature but no construction here: 36 and 52
# (skew-Hadamard matrices, e.g. Goethals-Seidel arrays), 46 (Mathon 1978).
_KNOWN_BUT_NOT_CONSTRUCTED = frozenset({36, 46, 52})


# --------------------------------------------------------------------------------------------
# Small finite fields GF(p^r), enough for the Paley constructions.
# --------------------------------------------------------------------------------------------

def _prime_power(q: int) -> tuple[int, int] | None:
    """Return ``(p, r)`` with ``q = p**r`` and p prime, or None if q is not a prime power."""
    if q < 2:
        return None
    p = next(d for d in range(2, q + 1) if q % d == 0)  # smallest divisor is prime
    r, rest = 0, q
    while rest % p == 0:
        rest //= p
        r += 1
    return (p, r) if rest == 1 else None


def _poly_mod(a: list[int], f: list[int], p: int) -> list[int]:
    """Remainder of a by the monic f over GF(p); coefficients lowest degree first."""
    a = [c % p for c in a]
    while len(a) >= len(f):
        lead = a[-1]
        if lead:
            shift = len(a) - len(f)
            for i, c in enumerate(f):
                a[shift + i] = (a[shift + i] - lead * c) % p
        a.pop()
    return a


def _monic_polys(p: int, degree: int):
    """All monic polynomials of the given degree over GF(p), lowest degree coefficient first."""
    for low in itertools.product(range(p), repeat=degree):
        yield list(low) + [1]


def _irreducible_poly(p: int, r: int) -> list[int]:
    """The first monic irreducible polynomial of degree r over GF(p) (trial division)."""
    for f in _monic_polys(p, r):
        if all(any(_poly_mod(f, g, p)) for d in range(1, r // 2 + 1) for g in _monic_polys(p, d)):
            return f
    raise RuntimeError(f"no irreducible polynomial of degree {r} over GF({p}) found")  # unreachable


def _quadratic_character_matrix(q: int) -> np.ndarray:
    """Jacobsthal matrix ``Q[i, j] = chi(a_i - a_j)`` over GF(q), chi the quadratic character."""
    p, r = _prime_power(q)  # type: ignore[misc]  # callers pass prime powers only
    digits = np.array([[(e // p**i) % p for i in range(r)] for e in range(q)], dtype=np.int64)
    weights = p ** np.arange(r)

    def encode(coeffs: np.ndarray) -> np.ndarray:
        return (coeffs % p) @ weights

    if r == 1:
        products = [(a * a) % p for a in range(1, q)]
    else:
        f = _irreducible_poly(p, r)
        products = []
        for a in range(1, q):
            sq = np.convolve(digits[a], digits[a])  # polynomial square, degree <= 2r - 2
            red = _poly_mod([int(c) for c in sq], f, p)
            products.append(int(encode(np.array(red + [0] * (r - len(red))))))
    squares = set(products)
    chi = np.array([0] + [1 if a in squares else -1 for a in range(1, q)], dtype=np.int64)
    difference = encode(digits[:, None, :] - digits[None, :, :])
    return chi[difference]


# --------------------------------------------------------------------------------------------
# Conference matrices
# --------------------------------------------------------------------------------------------

def _is_sum_of_two_squares(n: int) -> bool:
    return any(int(round((n - a * a) ** 0.5)) ** 2 == n - a * a for a in range(int(n**0.5) + 1))


def _construction(order: int) -> str | None:
    """Name of the construction used for ``order``, or None if this module has none."""
    if order == 2:
        return "order 2"
    if order < 2 or order % 2:
        return None
    if _prime_power(order - 1) is not None:
        return "Paley I" if (order - 1) % 4 == 3 else "Paley II"
    # Doubling needs a skew half (Paley I or doubled); the order-2 matrix here is symmetric,
    # and order 4 is Paley I anyway.
    if order % 4 == 0 and _construction(order // 2) in ("Paley I", "doubling"):
        return "doubling"
    return None


def supported_conference_orders(max_order: int = _LISTED_ORDERS_UP_TO) -> tuple[int, ...]:
    """Orders ``<= max_order`` for which ``conference_matrix`` has a construction."""
    return tuple(m for m in range(2, max_order + 1) if _construction(m) is not None)


def _verify_conference(c: np.ndarray, order: int, construction: str) -> None:
    n = c.shape[0]
    ok = (
        c.shape == (order, order)
        and np.all(np.diag(c) == 0)
        and np.all(np.abs(c[~np.eye(n, dtype=bool)]) == 1)
        and np.array_equal(c.T @ c, (n - 1) * np.eye(n, dtype=c.dtype))
    )
    if not ok:  # a bug in this module, not bad input
        raise RuntimeError(
            f"{construction} construction of order {order} is not a conference matrix")


@functools.lru_cache(maxsize=None)
def _conference_matrix_cached(order: int) -> np.ndarray:
    kind = _construction(order)
    if kind == "order 2":
        c = np.array([[0, 1], [1, 0]], dtype=np.int64)
    elif kind in ("Paley I", "Paley II"):
        q = order - 1
        jacobsthal = _quadratic_character_matrix(q)
        ones = np.ones(q, dtype=np.int64)
        c = np.zeros((order, order), dtype=np.int64)
        c[0, 1:] = 1
        c[1:, 0] = ones if kind == "Paley II" else -ones
        c[1:, 1:] = jacobsthal
    elif kind == "doubling":
        h = _conference_matrix_cached(order // 2) + np.eye(order // 2, dtype=np.int64)
        c = np.block([[h, h], [-h.T, h.T]]) - np.eye(order, dtype=np.int64)
    else:
        raise _unsupported_order_error(order, "conference_matrix: order", order)
    _verify_conference(c, order, kind)
    c.setflags(write=False)
    return c


def conference_matrix(order: int) -> np.ndarray:
    """Conference matrix of the given order (int64, a fresh writable copy).

    Zero diagonal, +-1 elsewhere, ``C^T C = (order - 1) I``; verified when built. Paley II
    matrices are symmetric, Paley I and doubled ones skew-symmetric. See the module docstring
    for the supported orders; others raise ``ConfigError``.
    """
    _require_int("order", order, "conference_matrix(order)")
    return _conference_matrix_cached(int(order)).copy()


def _unsupported_reason(order: int) -> str:
    """Why ``conference_matrix`` has no matrix of this order."""
    if order < 2 or order % 2:
        return f"conference matrices have even order >= 2 only, got {order}"
    if order % 4 == 2 and not _is_sum_of_two_squares(order - 1):
        return (f"no conference matrix of order {order} exists ({order - 1} is not a sum of two "
                f"squares, Belevitch 1950)")
    known = " (one is known in the literature)" if order in _KNOWN_BUT_NOT_CONSTRUCTED else ""
    return f"this module has no construction of order {order}{known}"


def _unsupported_order_error(order: int, name: str, value) -> ConfigError:
    return ConfigError(
        f"{name} = {value!r} is not supported: {_unsupported_reason(order)}. Supported orders "
        f"up to {_LISTED_ORDERS_UP_TO}: {_ranges(supported_conference_orders(), step=2)}"
    )


def conference_order(n_factors: int, n_fake: int = 0) -> int:
    """Order of the conference matrix a DSD for ``n_factors + n_fake`` columns is built from.

    The total when it is even, the total plus one when it is odd. Raises ``ConfigError`` for bad
    inputs or an unsupported order, naming ``n_factors``, the allowed totals and the smallest
    ``n_fake`` that would work.
    """
    source = "definitive_screening_design"
    _require_int("n_factors", n_factors, source)
    _require_int("n_fake", n_fake, source)
    if n_factors < 2:
        raise out_of_range("n_factors", n_factors, "an integer >= 2 (a DSD screens at least two "
                           "factors)", source)
    if n_fake < 0:
        raise out_of_range("n_fake", n_fake, "an integer >= 0 (number of fake factors)", source)
    total = n_factors + n_fake
    order = total + (total % 2)
    if _construction(order) is None:
        fix = next(f for f in itertools.count(n_fake + 1)
                   if _construction(n_factors + f + (n_factors + f) % 2) is not None)
        allowed = _ranges(
            tuple(t for t in range(2, _LISTED_ORDERS_UP_TO + 1)
                  if _construction(t + t % 2) is not None))
        raise ConfigError(
            f"{source}: n_factors = {n_factors} with n_fake = {n_fake} ({total} columns) needs a "
            f"conference matrix of order {order}: {_unsupported_reason(order)}. "
            f"Allowed n_factors + n_fake (up to "
            f"{_LISTED_ORDERS_UP_TO}): {allowed}. Add fake factors, e.g. n_fake = {fix} "
            f"(conference order {n_factors + fix + (n_factors + fix) % 2})."
        )
    return order


def definitive_screening_design(n_factors: int, n_fake: int = 0) -> np.ndarray:
    """Coded DSD, shape ``(2m + 1, n_factors)``, levels -1.0 / 0.0 / +1.0 (float64).

    ``m = conference_order(n_factors, n_fake)``. Rows ``0..m-1`` are the conference matrix
    ``C`` (first ``n_factors`` columns), rows ``m..2m-1`` are ``-C`` (row ``i + m`` mirrors row
    ``i``), and the last row is the centre run. Fake factors and the extra column for an odd
    total are the trailing columns of ``C`` and are dropped. Deterministic: no randomisation
    of run order (randomise when running the experiments, not here).
    """
    m = conference_order(n_factors, n_fake)
    c = _conference_matrix_cached(m)[:, :n_factors].astype(np.float64)
    return np.vstack([c, -c, np.zeros((1, n_factors))])


# --------------------------------------------------------------------------------------------
# Parameter tables and scaling
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ParameterTable:
    """Low / middle / high levels of the screened parameters, coded -1 / 0 / +1.

    Attributes:
        names: parameter names in the field's words (e.g. ``mu_s_pp``), unique, design
            column order.
        low, mid, high: levels in SI / dimensionless units, one per name, ``low < mid < high``.
            ``mid`` need not be ``(low + high) / 2`` (the paper's Table 4 rounds it).
        source: where the table came from (a file or function), named in every error.
    """

    names: tuple[str, ...]
    low: tuple[float, ...]
    mid: tuple[float, ...]
    high: tuple[float, ...]
    source: str = "ParameterTable"

    def __post_init__(self) -> None:
        for field in ("names", "low", "mid", "high"):
            object.__setattr__(self, field, tuple(getattr(self, field)))
        k = len(self.names)
        if k < 2:
            raise out_of_range("number of parameters", k, ">= 2 (a DSD screens at least two "
                               "factors)", self.source)
        bad_names = [n for n in self.names if not isinstance(n, str) or not n]
        if bad_names:
            raise ConfigError(f"{self.source}: parameter names {bad_names!r} are not allowed; "
                              f"expected non-empty strings such as 'mu_s_pp'")
        if len(set(self.names)) != k:
            dupes = sorted({n for n in self.names if self.names.count(n) > 1})
            raise ConfigError(f"{self.source}: parameter names must be unique; repeated: {dupes}")
        for field in ("low", "mid", "high"):
            values = getattr(self, field)
            if len(values) != k:
                raise ConfigError(
                    f"{self.source}: '{field}' has {len(values)} values but there are {k} "
                    f"parameters {list(self.names)}; expected one value per parameter")
            try:
                floats = tuple(float(v) for v in values)
            except (TypeError, ValueError) as err:
                raise ConfigError(f"{self.source}: '{field}' = {values!r} must be numbers") from err
            object.__setattr__(self, field, floats)
        for name, lo, mi, hi in zip(self.names, self.low, self.mid, self.high):
            if not all(np.isfinite((lo, mi, hi))) or not lo < mi < hi:
                raise ConfigError(
                    f"{self.source}: parameter '{name}' has low = {lo!r}, mid = {mi!r}, "
                    f"high = {hi!r}; expected finite levels with low < mid < high")

    @property
    def k(self) -> int:
        """Number of parameters."""
        return len(self.names)

    def levels(self) -> np.ndarray:
        """Levels as an array of shape ``(k, 3)``: columns low, mid, high."""
        return np.array([self.low, self.mid, self.high], dtype=np.float64).T

    @classmethod
    def from_records(cls, records: Sequence[Mapping], source: str,
                     required_names: Sequence[str] | None = None) -> "ParameterTable":
        """Build from records ``{"name", "low", "mid", "high"}`` (e.g. parsed JSON).

        ``required_names``, if given, must all be present (any order in ``records``); the table
        then follows the order of ``required_names``. Extra parameters are an error too, so a
        typo cannot silently drop a factor.
        """
        by_name: dict[str, Mapping] = {}
        for i, rec in enumerate(records):
            missing = [key for key in ("name", "low", "mid", "high") if key not in rec]
            if missing:
                raise ConfigError(
                    f"{source}: parameter record {i} ({rec.get('name', '?')!r}) lacks "
                    f"{missing}; every record needs name, low, mid, high")
            if rec["name"] in by_name:
                raise ConfigError(f"{source}: parameter '{rec['name']}' appears twice")
            by_name[rec["name"]] = rec
        names = list(by_name)
        if required_names is not None:
            missing = [n for n in required_names if n not in by_name]
            extra = [n for n in by_name if n not in required_names]
            if missing or extra:
                raise ConfigError(
                    f"{source}: parameters do not match the expected set; missing {missing}, "
                    f"unexpected {extra}; expected exactly {list(required_names)}")
            names = list(required_names)
        return cls(
            names=tuple(names),
            low=tuple(by_name[n]["low"] for n in names),
            mid=tuple(by_name[n]["mid"] for n in names),
            high=tuple(by_name[n]["high"] for n in names),
            source=source,
        )


def _as_design(values, name: str, table: ParameterTable, source: str) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != table.k:
        raise ConfigError(
            f"{source}: {name} has shape {arr.shape}; expected (runs, {table.k}) with one column "
            f"per parameter of {table.source}: {list(table.names)}")
    if not np.all(np.isfinite(arr)):
        run, col = map(int, np.argwhere(~np.isfinite(arr))[0])
        raise ConfigError(f"{source}: {name}[{run}, {col}] ({table.names[col]}) = "
                          f"{float(arr[run, col])!r}; expected a finite number")
    return arr


def scale_design(coded, table: ParameterTable) -> np.ndarray:
    """Physical design: coded -1 / 0 / +1 in column j become ``table.low/mid/high[j]``.

    ``coded`` has shape ``(runs, table.k)`` with entries exactly -1, 0 or +1 (up to 1e-9);
    anything else raises ``ConfigError`` naming the run, parameter and value. This is a level
    lookup; it agrees with an affine map of the codes only when ``mid = (low + high) / 2``.
    """
    source = "scale_design"
    x = _as_design(coded, "coded design", table, source)
    code = np.rint(x)
    bad = (np.abs(x - code) > 1e-9) | (np.abs(code) > 1)
    if bad.any():
        run, col = map(int, np.argwhere(bad)[0])
        raise ConfigError(f"{source}: coded design run {run}, parameter '{table.names[col]}' = "
                          f"{float(x[run, col])!r}; expected a coded level -1, 0 or +1")
    levels = table.levels()  # (k, 3)
    return levels[np.arange(table.k)[None, :], (code + 1).astype(np.int64)]


def code_design(physical, table: ParameterTable, tolerance: float = 0.02) -> np.ndarray:
    """Coded design (-1.0 / 0.0 / +1.0) from physical values, by nearest level.

    A value is coded as the level (low, mid or high of its parameter) nearest to it, and must
    lie within ``tolerance * (high - low) / 2`` of that level; otherwise ``ConfigError`` names
    the run, parameter, value and levels. The tolerance absorbs rounded levels: the paper's
    Table A.1 uses the midpoint 0.4905 for mu_s_pp where Table 4 prints 0.49 (0.4 % of the half
    range). ``tolerance`` must be in (0, 0.5).
    """
    source = "code_design"
    if not 0.0 < tolerance < 0.5:
        raise out_of_range("tolerance", tolerance, "a fraction of the half range in (0, 0.5)",
                           source)
    x = _as_design(physical, "physical design", table, source)
    levels = table.levels()  # (k, 3)
    distance = np.abs(x[:, :, None] - levels[None, :, :])  # (runs, k, 3)
    nearest = distance.argmin(axis=2)
    allowed = tolerance * (levels[:, 2] - levels[:, 0]) / 2.0
    off = distance.min(axis=2) > allowed[None, :]
    if off.any():
        run, col = map(int, np.argwhere(off)[0])
        lo, mi, hi = levels[col]
        raise ConfigError(
            f"{source}: physical design run {run}, parameter '{table.names[col]}' = "
            f"{float(x[run, col])!r} is not on any level of {table.source}: low {lo}, mid {mi}, "
            f"high {hi} (allowed distance {allowed[col]:.4g} = tolerance {tolerance} x half range)")
    return nearest.astype(np.float64) - 1.0


# --------------------------------------------------------------------------------------------
# The paper's data (bo/data)
# --------------------------------------------------------------------------------------------

def _load_data(filename: str) -> tuple[dict, str]:
    path = resources.files("bo") / "data" / filename
    source = f"bo/data/{filename}"
    try:
        return json.loads(path.read_text(encoding="utf-8")), source
    except (OSError, json.JSONDecodeError) as err:
        raise ConfigError(f"{source}: cannot read the packaged data file ({err})") from err


def paper_parameter_table() -> ParameterTable:
    """The paper's Table 4 (levels of the 12 DEM parameters), from ``bo/data``.

    Names and order are ``PAPER_PARAMETER_NAMES``; mid is Table 4's printed middle level.
    """
    data, source = _load_data(_TABLE4_FILE)
    return ParameterTable.from_records(data["parameters"], source=source,
                                       required_names=PAPER_PARAMETER_NAMES)


def paper_design() -> np.ndarray:
    """The paper's Table A.1, physical values, shape ``(29, 12)``, run 1 first.

    Columns follow ``PAPER_PARAMETER_NAMES`` (= ``paper_parameter_table().names``).
    """
    data, source = _load_data(_TABLEA1_FILE)
    if tuple(data.get("parameters", ())) != PAPER_PARAMETER_NAMES:
        raise ConfigError(f"{source}: 'parameters' = {data.get('parameters')!r}; expected "
                          f"{list(PAPER_PARAMETER_NAMES)}")
    runs = np.asarray(data["runs"], dtype=np.float64)
    if runs.shape != (29, len(PAPER_PARAMETER_NAMES)):
        raise ConfigError(f"{source}: 'runs' has shape {runs.shape}; expected (29, 12)")
    return runs


# --------------------------------------------------------------------------------------------
# Property checker
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class DSDReport:
    """Which definitive-screening properties a coded design has. Indices are 0-based.

    Attributes:
        n_runs, n_factors: design shape.
        levels_per_column: sorted distinct values of each column.
        columns_not_three_level: columns whose distinct values are not exactly {-1, 0, +1}.
        zeros_per_column: number of 0 entries in each column.
        zeros_per_run: number of 0 entries in each run.
        column_sums: sum of each column (0 for a balanced column).
        mirror_pairs: pairs ``(i, j)``, ``i < j``, with run j = -run i (each run used once).
        runs_without_mirror: runs left unpaired (a centre run is its own mirror).
        centre_runs: runs with every factor at 0.
        main_effect_max_abs_inner: max over i != j of ``|x_i . x_j|`` (raw coded columns).
        main_effect_max_abs_corr: max over i != j of ``|corr(x_i, x_j)|`` (Pearson).
        main_vs_quadratic_max_abs_inner: max over all i, j of ``|x_i . (x_j^2 - mean(x_j^2))|``.
        main_vs_quadratic_max_abs_corr: max over all i, j of ``|corr(x_i, x_j^2)|``.
        main_vs_interaction_max_abs_inner: max over all i and all j < l of
            ``|x_i . (x_j x_l - mean(x_j x_l))|`` (i may equal j or l).
        main_vs_interaction_max_abs_corr: same pairs, ``|corr(x_i, x_j x_l)|``.
        main_effect_worst, main_vs_quadratic_worst, main_vs_interaction_worst: where the
            max ``|inner|`` occurs, ``(i, j)``, ``(i, j)`` for ``x_i`` vs ``x_j^2`` and
            ``(i, j, l)`` for ``x_i`` vs ``x_j x_l``; empty when that max is within ``atol``.
        atol: tolerance used for the boolean verdicts.

    The inner products with centred second-order columns equal the inner products of the
    centred columns on both sides (a centred column is orthogonal to the constant), i.e. they
    measure orthogonality after adjusting for the intercept. Pearson correlations divide the
    centred inner product by both centred norms; a pair in which a centred column is
    identically zero (a constant column, e.g. ``x_1 x_2`` of the 2-factor DSD) has correlation
    defined as 0.
    """

    n_runs: int
    n_factors: int
    levels_per_column: tuple[tuple[float, ...], ...]
    columns_not_three_level: tuple[int, ...]
    zeros_per_column: tuple[int, ...]
    zeros_per_run: tuple[int, ...]
    column_sums: tuple[float, ...]
    mirror_pairs: tuple[tuple[int, int], ...]
    runs_without_mirror: tuple[int, ...]
    centre_runs: tuple[int, ...]
    main_effect_max_abs_inner: float
    main_effect_max_abs_corr: float
    main_effect_worst: tuple[int, ...]
    main_vs_quadratic_max_abs_inner: float
    main_vs_quadratic_max_abs_corr: float
    main_vs_quadratic_worst: tuple[int, ...]
    main_vs_interaction_max_abs_inner: float
    main_vs_interaction_max_abs_corr: float
    main_vs_interaction_worst: tuple[int, ...]
    atol: float = 1e-9

    @property
    def three_levels(self) -> bool:
        return not self.columns_not_three_level

    @property
    def fold_over(self) -> bool:
        return not self.runs_without_mirror

    @property
    def has_centre_run(self) -> bool:
        return bool(self.centre_runs)

    @property
    def main_effects_orthogonal(self) -> bool:
        return self.main_effect_max_abs_inner <= self.atol

    @property
    def main_effects_orthogonal_to_second_order(self) -> bool:
        return (self.main_vs_quadratic_max_abs_inner <= self.atol
                and self.main_vs_interaction_max_abs_inner <= self.atol)

    @property
    def is_definitive_screening_design(self) -> bool:
        """All of: three levels, fold-over, centre run, the orthogonalities above."""
        return (self.three_levels and self.fold_over and self.has_centre_run
                and self.main_effects_orthogonal and self.main_effects_orthogonal_to_second_order)

    def to_text(self, title: str = "design", factor_names: Sequence[str] | None = None) -> str:
        """Human-readable report; runs are numbered from 1 as in the paper.

        ``factor_names`` (one per column) label the columns; default ``x1, x2, ...``.
        """
        names = (list(factor_names) if factor_names is not None
                 else [f"x{j + 1}" for j in range(self.n_factors)])
        if len(names) != self.n_factors:
            raise ConfigError(f"DSDReport.to_text: {len(names)} factor_names for "
                              f"{self.n_factors} columns; expected one name per column")

        def runs(idx) -> str:
            return ", ".join(str(i + 1) for i in idx) if len(idx) else "none"

        def verdict(ok: bool) -> str:
            return "yes" if ok else "NO"

        def where(worst: tuple[int, ...], template: str) -> str:
            return f"; worst {template.format(*(names[i] for i in worst))}" if worst else ""

        def number(v: float) -> str:
            return f"{v:.6g}"

        rows = [
            ("three levels -1/0/+1 in every column", verdict(self.three_levels)
             + ("" if self.three_levels else
                f" (columns {', '.join(names[j] for j in self.columns_not_three_level)})")),
            ("zeros per column", str(list(self.zeros_per_column))),
            ("column sums", f"[{', '.join(number(v) for v in self.column_sums)}]"),
            ("runs with 0 / 1 / >1 zeros",
             f"{sum(z == 0 for z in self.zeros_per_run)} / "
             f"{sum(z == 1 for z in self.zeros_per_run)} / "
             f"{sum(z > 1 for z in self.zeros_per_run)}"),
            ("fold-over (every run has its mirror)",
             f"{verdict(self.fold_over)}; {len(self.mirror_pairs)} mirror pairs"),
            ("mirror pairs (runs)",
             ", ".join(f"{i + 1}-{j + 1}" for i, j in self.mirror_pairs) or "none"),
            ("runs without a mirror", runs(self.runs_without_mirror)),
            ("centre run present", verdict(self.has_centre_run)
             + (f" (runs {runs(self.centre_runs)})" if self.centre_runs else "")),
            ("main effects, max |x_i . x_j|, i != j",
             f"{number(self.main_effect_max_abs_inner)} (max |corr| "
             f"{self.main_effect_max_abs_corr:.4f})" + where(self.main_effect_worst, "{} . {}")),
            ("main vs centred x_j^2, max |inner|",
             f"{number(self.main_vs_quadratic_max_abs_inner)} (max |corr| "
             f"{self.main_vs_quadratic_max_abs_corr:.4f})"
             + where(self.main_vs_quadratic_worst, "{} . {}^2")),
            ("main vs centred x_j*x_l, max |inner|",
             f"{number(self.main_vs_interaction_max_abs_inner)} (max |corr| "
             f"{self.main_vs_interaction_max_abs_corr:.4f})"
             + where(self.main_vs_interaction_worst, "{} . {}*{}")),
            ("definitive screening design", verdict(self.is_definitive_screening_design)),
        ]
        width = max(len(label) for label, _ in rows)
        lines = [f"{title}: {self.n_runs} runs x {self.n_factors} factors"]
        lines += [f"  {label.ljust(width)} : {value}" for label, value in rows]
        return "\n".join(lines)


def _max_abs_inner_and_corr(main: np.ndarray, other: np.ndarray, atol: float,
                            mask: np.ndarray | None = None) -> tuple[float, float, tuple[int, int]]:
    """Max ``|x_i . (o_c - mean o_c)|``, max ``|Pearson corr|``, and ``(i, c)`` of the max inner.

    Taken over all columns i of ``main`` and c of ``other`` (where ``mask`` is True). A centred
    column with every entry within ``atol`` of 0 is constant: its correlations are 0.
    """
    centred_other = other - other.mean(axis=0)
    centred_main = main - main.mean(axis=0)
    inner = main.T @ centred_other  # == centred_main.T @ centred_other
    constant = np.outer(np.abs(centred_main).max(axis=0) <= atol,
                        np.ones(other.shape[1], dtype=bool))
    constant |= (np.abs(centred_other).max(axis=0) <= atol)[None, :]
    norms = np.outer(np.linalg.norm(centred_main, axis=0), np.linalg.norm(centred_other, axis=0))
    corr = np.where(constant, 0.0, inner / np.where(constant, 1.0, norms))
    if mask is not None:
        inner, corr = np.where(mask, inner, 0.0), np.where(mask, corr, 0.0)
    worst = np.unravel_index(int(np.argmax(np.abs(inner))), inner.shape)
    return float(np.max(np.abs(inner))), float(np.max(np.abs(corr))), (int(worst[0]), int(worst[1]))


def _mirror_pairs(x: np.ndarray, atol: float) -> tuple[list[tuple[int, int]], list[int]]:
    """Greedy one-to-one pairing of runs with their mirrors (runs rounded to ``atol``)."""
    key = [tuple(np.round(row / max(atol, 1e-12)).astype(np.int64)) for row in x]
    waiting: dict[tuple, list[int]] = {}
    pairs: list[tuple[int, int]] = []
    for i, k in enumerate(key):
        if not any(k):  # centre run: its own mirror
            continue
        mirror = tuple(-v for v in k)
        if waiting.get(mirror):
            pairs.append((waiting[mirror].pop(0), i))
        else:
            waiting.setdefault(k, []).append(i)
    unpaired = sorted(i for idx in waiting.values() for i in idx)
    return sorted(pairs), unpaired


def check_dsd(coded, atol: float = 1e-9) -> DSDReport:
    """Report the DSD properties of a coded design (runs x factors); see ``DSDReport``.

    Works on any real matrix with at least two columns and two runs; it does not require the
    entries to be -1, 0, +1 (it reports it). ``atol`` decides the boolean verdicts and equality
    of entries when matching mirror runs and centre runs.
    """
    source = "check_dsd"
    x = np.asarray(coded, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 2 or x.shape[1] < 2:
        raise ConfigError(f"{source}: coded design has shape {x.shape}; expected (runs >= 2, "
                          f"factors >= 2)")
    if not np.all(np.isfinite(x)):
        raise ConfigError(f"{source}: coded design contains non-finite values at "
                          f"{np.argwhere(~np.isfinite(x))[0].tolist()}; expected finite numbers")
    if not atol > 0:
        raise out_of_range("atol", atol, "a positive tolerance", source)
    n, k = x.shape
    is_zero = np.abs(x) <= atol

    levels = tuple(tuple(float(v) for v in np.unique(np.round(x[:, j] / atol) * atol))
                   for j in range(k))
    not_three = tuple(j for j in range(k)
                      if len(levels[j]) != 3
                      or not np.allclose(levels[j], (-1.0, 0.0, 1.0), rtol=0, atol=atol))
    pairs, unpaired = _mirror_pairs(x, atol)

    off_diag = ~np.eye(k, dtype=bool)
    gram = np.where(off_diag, x.T @ x, 0.0)  # raw (uncentred) main-effect inner products
    main_worst = np.unravel_index(int(np.argmax(np.abs(gram))), gram.shape)
    main_inner = float(np.max(np.abs(gram)))
    _, main_corr, _ = _max_abs_inner_and_corr(x, x, atol, off_diag)
    quad_inner, quad_corr, quad_worst = _max_abs_inner_and_corr(x, x**2, atol)
    j_idx, l_idx = np.triu_indices(k, 1)
    twofi_inner, twofi_corr, (i_2fi, c_2fi) = _max_abs_inner_and_corr(
        x, x[:, j_idx] * x[:, l_idx], atol)

    return DSDReport(
        n_runs=n,
        n_factors=k,
        levels_per_column=levels,
        columns_not_three_level=not_three,
        zeros_per_column=tuple(int(z) for z in is_zero.sum(axis=0)),
        zeros_per_run=tuple(int(z) for z in is_zero.sum(axis=1)),
        column_sums=tuple(float(s) for s in x.sum(axis=0)),
        mirror_pairs=tuple(pairs),
        runs_without_mirror=tuple(unpaired),
        centre_runs=tuple(int(i) for i in np.flatnonzero(is_zero.all(axis=1))),
        main_effect_max_abs_inner=main_inner,
        main_effect_max_abs_corr=main_corr,
        main_effect_worst=(int(main_worst[0]), int(main_worst[1])) if main_inner > atol else (),
        main_vs_quadratic_max_abs_inner=quad_inner,
        main_vs_quadratic_max_abs_corr=quad_corr,
        main_vs_quadratic_worst=quad_worst if quad_inner > atol else (),
        main_vs_interaction_max_abs_inner=twofi_inner,
        main_vs_interaction_max_abs_corr=twofi_corr,
        main_vs_interaction_worst=((i_2fi, int(j_idx[c_2fi]), int(l_idx[c_2fi]))
                                   if twofi_inner > atol else ()),
        atol=atol,
    )


# --------------------------------------------------------------------------------------------
# Small helpers
# --------------------------------------------------------------------------------------------

def _require_int(name: str, value, source: str) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise out_of_range(name, value, "an integer", source)


def _ranges(values: Sequence[int], step: int = 1) -> str:
    """Compact listing: (2, 4, 6, 10) with step 2 -> '2-6, 10'."""
    parts: list[str] = []
    start = prev = None
    for v in values:
        if start is None:
            start = prev = v
        elif v == prev + step:
            prev = v
        else:
            parts.append(f"{start}" if start == prev else f"{start}-{prev}")
            start = prev = v
    if start is not None:
        parts.append(f"{start}" if start == prev else f"{start}-{prev}")
    return ", ".join(parts)
