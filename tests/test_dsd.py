"""Tests for bo/design/dsd.py: conference matrices, DSD construction, scaling, the paper's data and
the property checker.

Properties are checked here with exact integer arithmetic, independently of ``check_dsd``;
``check_dsd`` itself is checked against a brute-force loop and against designs with known
defects.
"""
from __future__ import annotations

import itertools
import runpy
from pathlib import Path

import numpy as np
import pytest

from bo.design import dsd
from bo.design.dsd import (
    PAPER_PARAMETER_NAMES,
    ParameterTable,
    check_dsd,
    code_design,
    conference_matrix,
    conference_order,
    definitive_screening_design,
    paper_design,
    paper_parameter_table,
    scale_design,
    supported_conference_orders,
)
from torchdem.errors import ConfigError

# Table 4 of Hadi, Pang & Schott, transcribed independently of bo/data: (low, mid, high).
TABLE4 = {
    "mu_s_pp": (0.368, 0.49, 0.613),
    "mu_r_pp": (0.045, 0.06, 0.075),
    "e_pp": (0.525, 0.7, 0.875),
    "mu_s_ss": (0.525, 0.7, 0.875),
    "mu_r_ss": (0.06, 0.08, 0.1),
    "e_ss": (0.263, 0.35, 0.438),
    "mu_s_pg": (0.285, 0.38, 0.475),
    "mu_r_pg": (0.045, 0.06, 0.075),
    "e_pg": (0.525, 0.7, 0.875),
    "mu_s_sg": (0.285, 0.38, 0.475),
    "mu_r_sg": (0.06, 0.08, 0.1),
    "e_sg": (0.3, 0.4, 0.5),
}

SUPPORTED_UP_TO_64 = (2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 24, 26, 28, 30, 32, 38, 40, 42, 44,
                      48, 50, 54, 56, 60, 62, 64)


def expected_order(n_factors: int, n_fake: int) -> int:
    total = n_factors + n_fake
    return total if total % 2 == 0 else total + 1


def design_cases():
    for k in range(2, 21):
        for n_fake in (0, 1, 2):
            if expected_order(k, n_fake) != 22:  # no conference matrix of order 22 exists
                yield k, n_fake
    yield 12, 2  # the paper
    yield 30, 0
    yield 29, 0


# --------------------------------------------------------------------------------------------
# Conference matrices
# --------------------------------------------------------------------------------------------

def test_supported_orders_are_the_documented_ones():
    assert supported_conference_orders() == SUPPORTED_UP_TO_64
    assert "2-20, 24-32, 38-44, 48-50, 54-56, 60-64" in dsd.__doc__


@pytest.mark.parametrize("order", SUPPORTED_UP_TO_64)
def test_conference_matrix_definition(order):
    c = conference_matrix(order)
    assert c.shape == (order, order)
    assert c.dtype.kind == "i"
    assert np.all(np.diag(c) == 0)
    off = c[~np.eye(order, dtype=bool)]
    assert np.all(np.abs(off) == 1)
    np.testing.assert_array_equal(c.T @ c, (order - 1) * np.eye(order, dtype=np.int64))
    np.testing.assert_array_equal(c @ c.T, (order - 1) * np.eye(order, dtype=np.int64))
    # Paley II (order = 2 mod 4) is symmetric, Paley I and doubled matrices skew-symmetric.
    if order % 4 == 2:
        np.testing.assert_array_equal(c, c.T)
    else:
        np.testing.assert_array_equal(c, -c.T)


def test_conference_matrix_returns_a_private_copy():
    c = conference_matrix(6)
    c[0, 1] = 99
    assert conference_matrix(6)[0, 1] == 1


@pytest.mark.parametrize("order, phrase", [
    (22, "no conference matrix of order 22 exists (21 is not a sum of two squares"),
    (34, "no conference matrix of order 34 exists (33 is not a sum of two squares"),
    (36, "this module has no construction of order 36 (one is known in the literature)"),
    (46, "this module has no construction of order 46 (one is known in the literature)"),
    (66, "this module has no construction of order 66"),
    (7, "even order >= 2 only, got 7"),
    (0, "even order >= 2 only, got 0"),
])
def test_conference_matrix_unsupported_orders(order, phrase):
    with pytest.raises(ConfigError) as err:
        conference_matrix(order)
    msg = str(err.value)
    assert f"order = {order}" in msg and phrase in msg
    assert "Supported orders up to 64: 2-20, 24-32" in msg


def test_conference_matrix_rejects_non_integer_order():
    with pytest.raises(ConfigError, match=r"order = 6\.0 .*expected an integer"):
        conference_matrix(6.0)


# --------------------------------------------------------------------------------------------
# DSD construction: exact properties
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("n_factors, n_fake", sorted(set(design_cases())))
def test_dsd_exact_properties(n_factors, n_fake):
    d = definitive_screening_design(n_factors, n_fake)
    m = expected_order(n_factors, n_fake)
    assert conference_order(n_factors, n_fake) == m
    assert d.shape == (2 * m + 1, n_factors)
    assert d.dtype == np.float64
    x = d.astype(np.int64)
    np.testing.assert_array_equal(x, d)  # entries are exact integers

    # three levels in every column, three zeros per column
    for j in range(n_factors):
        assert sorted(set(x[:, j].tolist())) == [-1, 0, 1]
    np.testing.assert_array_equal((x == 0).sum(axis=0), 3)

    # fold-over: run i + m mirrors run i; the last run is the centre run
    np.testing.assert_array_equal(x[m:2 * m], -x[:m])
    np.testing.assert_array_equal(x[-1], 0)

    # main effects orthogonal: X^T X = 2 (m - 1) I
    np.testing.assert_array_equal(x.T @ x, 2 * (m - 1) * np.eye(n_factors, dtype=np.int64))

    # main effects orthogonal to centred quadratic and centred 2FI columns; with n runs,
    # n * x_i . (q - mean q) = n * x_i . q - sum(x_i) * sum(q) is an exact integer.
    n = x.shape[0]
    quad = x**2
    j_idx, l_idx = np.triu_indices(n_factors, 1)
    twofi = x[:, j_idx] * x[:, l_idx]
    for other in (quad, twofi):
        scaled_inner = n * (x.T @ other) - np.outer(x.sum(axis=0), other.sum(axis=0))
        assert not scaled_inner.any()


def test_paper_case_has_29_runs_and_is_2k_plus_5():
    d = definitive_screening_design(12, n_fake=2)
    assert d.shape == (29, 12) == (2 * 12 + 5, 12)
    report = check_dsd(d)
    assert report.is_definitive_screening_design
    assert report.centre_runs == (28,)
    assert len(report.mirror_pairs) == 14


def test_fake_and_odd_columns_are_dropped_trailing_columns():
    np.testing.assert_array_equal(definitive_screening_design(12, 2),
                                  definitive_screening_design(14)[:, :12])
    np.testing.assert_array_equal(definitive_screening_design(11),
                                  definitive_screening_design(12)[:, :11])
    c = conference_matrix(14)
    np.testing.assert_array_equal(definitive_screening_design(14)[:14], c)


@pytest.mark.parametrize("n_factors, n_fake", [(21, 0), (22, 0), (20, 1), (20, 2)])
def test_unsupported_total_names_the_fix(n_factors, n_fake):
    with pytest.raises(ConfigError) as err:
        definitive_screening_design(n_factors, n_fake)
    msg = str(err.value)
    assert f"n_factors = {n_factors} with n_fake = {n_fake}" in msg
    assert "order 22" in msg and "no conference matrix of order 22 exists" in msg
    assert "Allowed n_factors + n_fake (up to 64): 2-20, 23-32, 37-44" in msg
    fix = 23 - n_factors if n_factors + n_fake < 23 else None
    assert f"n_fake = {fix} (conference order 24)" in msg
    definitive_screening_design(n_factors, fix)  # the suggested fix works


@pytest.mark.parametrize("kwargs, phrase", [
    (dict(n_factors=1), "n_factors = 1 is not allowed; expected an integer >= 2"),
    (dict(n_factors=0), "n_factors = 0 is not allowed; expected an integer >= 2"),
    (dict(n_factors=12, n_fake=-1), "n_fake = -1 is not allowed; expected an integer >= 0"),
    (dict(n_factors=12.0), "n_factors = 12.0 is not allowed; expected an integer"),
    (dict(n_factors=True), "n_factors = True is not allowed; expected an integer"),
    (dict(n_factors=12, n_fake=1.5), "n_fake = 1.5 is not allowed; expected an integer"),
])
def test_bad_design_arguments(kwargs, phrase):
    with pytest.raises(ConfigError) as err:
        definitive_screening_design(**kwargs)
    assert phrase in str(err.value)
    assert str(err.value).startswith("definitive_screening_design:")


# --------------------------------------------------------------------------------------------
# Parameter tables and scaling
# --------------------------------------------------------------------------------------------

def test_paper_parameter_table_is_table4():
    table = paper_parameter_table()
    assert table.names == PAPER_PARAMETER_NAMES == tuple(TABLE4)
    assert table.source == "bo/data/table4_dsd_levels.json"
    for j, name in enumerate(table.names):
        assert (table.low[j], table.mid[j], table.high[j]) == TABLE4[name]


def test_table4_data_file_cites_the_paper():
    import json
    from importlib import resources
    for filename in ("table4_dsd_levels.json", "tableA1_paper_dsd.json"):
        data = json.loads((resources.files("bo") / "data" / filename).read_text())
        assert "Hadi, Pang, Schott" in data["source"]
        assert "Systematic DEM calibration of two-component mixtures" in data["source"]
    assert "Table 4" in json.loads(
        (resources.files("bo") / "data" / "table4_dsd_levels.json").read_text())["source"]


def test_scale_design_maps_codes_to_table4_levels():
    table = paper_parameter_table()
    coded = definitive_screening_design(12, n_fake=2)
    physical = scale_design(coded, table)
    assert physical.shape == coded.shape
    for j, name in enumerate(table.names):
        low, mid, high = TABLE4[name]
        expected = np.select([coded[:, j] == -1, coded[:, j] == 0, coded[:, j] == 1],
                             [low, mid, high], default=np.nan)
        np.testing.assert_array_equal(physical[:, j], expected)
    assert physical[-1].tolist() == [TABLE4[n][1] for n in table.names]  # centre run = mids
    np.testing.assert_array_equal(code_design(physical, table), coded)  # round trip


def test_scale_design_rejects_bad_input():
    table = paper_parameter_table()
    coded = definitive_screening_design(12, n_fake=2)
    with pytest.raises(ConfigError, match=r"shape \(29, 11\); expected \(runs, 12\).*mu_s_pp"):
        scale_design(coded[:, :11], table)
    bad = coded.copy()
    bad[3, 4] = 0.5
    with pytest.raises(ConfigError, match=r"run 3, parameter 'mu_r_ss' = 0\.5; expected a coded "
                                          r"level -1, 0 or \+1"):
        scale_design(bad, table)
    bad[3, 4] = 2.0
    with pytest.raises(ConfigError, match=r"'mu_r_ss' = 2\.0"):
        scale_design(bad, table)


@pytest.mark.parametrize("low, mid, high", [(0.5, 0.4, 0.6), (0.4, 0.4, 0.6), (0.4, 0.7, 0.6),
                                            (0.4, float("nan"), 0.6)])
def test_parameter_table_levels_out_of_order(low, mid, high):
    with pytest.raises(ConfigError) as err:
        ParameterTable(names=("mu_s_pp", "e_ss"), low=(0.368, low), mid=(0.49, mid),
                       high=(0.613, high), source="conf/material/test.yaml")
    msg = str(err.value)
    assert msg.startswith("conf/material/test.yaml:")
    assert "parameter 'e_ss'" in msg and f"low = {low!r}" in msg
    assert "expected finite levels with low < mid < high" in msg


def test_parameter_table_shape_errors():
    with pytest.raises(ConfigError,
                       match=r"number of parameters = 1 is not allowed; expected >= 2"):
        ParameterTable(names=("mu_s_pp",), low=(0.3,), mid=(0.4,), high=(0.5,))
    with pytest.raises(ConfigError, match=r"'high' has 1 values but there are 2 parameters"):
        ParameterTable(names=("a", "b"), low=(0.1, 0.1), mid=(0.2, 0.2), high=(0.3,))
    with pytest.raises(ConfigError, match=r"names must be unique; repeated: \['mu_s_pp'\]"):
        ParameterTable(names=("mu_s_pp", "mu_s_pp"), low=(0.1, 0.1), mid=(0.2, 0.2),
                       high=(0.3, 0.3))


def test_parameter_table_from_records_missing_parameters():
    records = [{"name": n, "low": lo, "mid": mi, "high": hi} for n, (lo, mi, hi) in TABLE4.items()]
    table = ParameterTable.from_records(records[::-1], "t.json",
                                        required_names=PAPER_PARAMETER_NAMES)
    assert table.names == PAPER_PARAMETER_NAMES  # reordered to the required order
    with pytest.raises(ConfigError) as err:
        ParameterTable.from_records(records[:10], "t.json", required_names=PAPER_PARAMETER_NAMES)
    assert "t.json: parameters do not match" in str(err.value)
    assert "missing ['mu_r_sg', 'e_sg']" in str(err.value)
    typo = records[:11] + [{"name": "e_gs", "low": 0.3, "mid": 0.4, "high": 0.5}]
    with pytest.raises(ConfigError, match=r"missing \['e_sg'\], unexpected \['e_gs'\]"):
        ParameterTable.from_records(typo, "t.json", required_names=PAPER_PARAMETER_NAMES)
    no_high = [dict(records[0]), records[1]]
    del no_high[0]["high"]
    with pytest.raises(ConfigError, match=r"t.json: parameter record 0 \('mu_s_pp'\) lacks "
                                          r"\['high'\]"):
        ParameterTable.from_records(no_high, "t.json")


# --------------------------------------------------------------------------------------------
# The paper's Table A.1 and code_design
# --------------------------------------------------------------------------------------------

def test_paper_design_codes_onto_table4_levels():
    table = paper_parameter_table()
    physical = paper_design()
    assert physical.shape == (29, 12)
    # spot checks against the paper's Table A.1
    assert physical[0].tolist() == [0.613, 0.06, 0.525, 0.525, 0.1, 0.263, 0.285, 0.045, 0.875,
                                    0.475, 0.1, 0.3]
    assert physical[1, 0] == 0.4905 and physical[7, 5] == 0.3505
    coded = code_design(physical, table)
    assert set(np.unique(coded).tolist()) == {-1.0, 0.0, 1.0}
    assert coded[1, 0] == 0 and coded[2, 0] == 0 and coded[7, 5] == 0  # 0.4905 / 0.3505 -> mid
    # middle-level entries of A.1 are (low + high) / 2 of Table 4
    levels = table.levels()
    mids = np.where(coded == 0, physical, np.nan)
    for j in range(12):
        col = mids[:, j][~np.isnan(mids[:, j])]
        np.testing.assert_allclose(col, (levels[j, 0] + levels[j, 2]) / 2, rtol=0, atol=1e-12)
    # back to physical with Table 4 levels: equal except the two rounded middle levels
    diff = np.argwhere(scale_design(coded, table) != physical)
    assert {table.names[j] for _, j in diff} == {"mu_s_pp", "e_ss"}


def test_code_design_rejects_values_off_every_level():
    table = paper_parameter_table()
    physical = paper_design()
    physical[4, 6] = 0.33  # mu_s_pg between low 0.285 and mid 0.38
    with pytest.raises(ConfigError) as err:
        code_design(physical, table)
    msg = str(err.value)
    assert "run 4, parameter 'mu_s_pg' = 0.33 is not on any level" in msg
    assert "low 0.285, mid 0.38, high 0.475" in msg and "bo/data/table4_dsd_levels.json" in msg
    # a tight tolerance rejects the paper's unrounded middle level 0.4905 (Table 4 says 0.49)
    with pytest.raises(ConfigError, match=r"run 1, parameter 'mu_s_pp' = 0\.4905"):
        code_design(paper_design(), table, tolerance=0.001)
    with pytest.raises(ConfigError, match=r"tolerance = 0\.7 is not allowed"):
        code_design(paper_design(), table, tolerance=0.7)


# --------------------------------------------------------------------------------------------
# check_dsd
# --------------------------------------------------------------------------------------------

def test_check_dsd_on_paper_table_a1():
    table = paper_parameter_table()
    report = check_dsd(code_design(paper_design(), table))
    # runs 1, 8, 10, 15, 16, 19, 21 (1-based, as in the paper) have no mirror
    assert report.runs_without_mirror == (0, 7, 9, 14, 15, 18, 20)
    assert report.mirror_pairs == ((1, 2), (3, 10), (4, 17), (5, 22), (6, 27), (8, 23), (11, 28),
                                   (12, 25), (13, 16), (19, 24), (21, 26))
    assert report.centre_runs == () and not report.has_centre_run
    assert report.three_levels
    assert report.zeros_per_column == (2, 1, 2, 2, 2, 1, 1, 2, 2, 1, 1, 2)
    assert sorted(report.zeros_per_run) == [0] * 10 + [1] * 19
    assert report.column_sums == (1, -2, -1, -3, 1, 2, -2, 1, 7, 0, 4, -1)
    assert report.main_effect_max_abs_inner == 5.0
    assert report.main_effect_worst == (0, 2)  # mu_s_pp . e_pp
    assert not report.main_effects_orthogonal
    assert not report.main_effects_orthogonal_to_second_order
    assert not report.is_definitive_screening_design
    text = report.to_text("paper", table.names)
    assert "runs without a mirror                 : 1, 8, 10, 15, 16, 19, 21" in text
    assert "centre run present                    : NO" in text


def brute_force_second_order(x):
    """Loop oracle: max |x_i . (q - mean q)| over quadratic and 2FI columns."""
    n, k = x.shape
    quad = max(abs(sum(x[r, i] * (x[r, j] ** 2 - np.mean(x[:, j] ** 2)) for r in range(n)))
               for i in range(k) for j in range(k))
    twofi = max(abs(sum(x[r, i] * (x[r, j] * x[r, l] - np.mean(x[:, j] * x[:, l]))
                        for r in range(n)))
                for i in range(k) for j, l in itertools.combinations(range(k), 2))
    return quad, twofi


def test_check_dsd_matches_brute_force_on_random_design():
    rng = np.random.default_rng(7)
    x = rng.integers(-1, 2, size=(11, 4)).astype(float)
    report = check_dsd(x)
    quad, twofi = brute_force_second_order(x)
    assert report.main_vs_quadratic_max_abs_inner == pytest.approx(quad, abs=1e-12)
    assert report.main_vs_interaction_max_abs_inner == pytest.approx(twofi, abs=1e-12)
    gram = x.T @ x
    assert report.main_effect_max_abs_inner == np.max(np.abs(gram[~np.eye(4, dtype=bool)]))
    corr = np.corrcoef(x.T)
    assert report.main_effect_max_abs_corr == pytest.approx(
        np.max(np.abs(corr[~np.eye(4, dtype=bool)])), abs=1e-12)


def test_check_dsd_detects_broken_designs():
    d = definitive_screening_design(6)
    assert check_dsd(d).is_definitive_screening_design

    flipped = d.copy()
    flipped[2, 3] *= -1  # run 2 loses its mirror (run 8) and orthogonality breaks
    report = check_dsd(flipped)
    assert report.runs_without_mirror == (2, 8)
    assert report.has_centre_run and report.three_levels
    assert not report.main_effects_orthogonal
    assert not report.is_definitive_screening_design

    no_centre = check_dsd(d[:-1])
    assert no_centre.centre_runs == () and no_centre.fold_over
    assert not no_centre.is_definitive_screening_design

    half = d.copy()
    half[0, 1] = 0.5
    report = check_dsd(half)
    assert report.columns_not_three_level == (1,)
    assert report.runs_without_mirror == (0, 6)

    duplicated = np.vstack([d[:1], d[:1], -d[:1], d[-1:]])  # r, r, -r, centre
    report = check_dsd(duplicated)
    assert report.mirror_pairs == ((0, 2),) and report.runs_without_mirror == (1,)

    with pytest.raises(ConfigError, match=r"check_dsd: coded design has shape \(5,\)"):
        check_dsd(np.zeros(5))


def test_check_paper_dsd_script_prints_both_reports(capsys):
    script = Path(__file__).resolve().parents[1] / "scripts" / "check_paper_dsd.py"
    runpy.run_path(str(script), run_name="__main__")
    out = capsys.readouterr().out
    assert "Paper, Table A.1" in out and "Ours, definitive_screening_design(12, n_fake=2)" in out
    assert out.count("definitive screening design           : NO") == 1
    assert out.count("definitive screening design           : yes") == 1
