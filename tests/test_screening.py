"""Tests for bo/screening/stepwise.py: stepwise regression on a DSD, Table 5 counting, input checks.

Synthetic data: the paper's design size (12 factors + 2 fake, 29 runs, from
``bo.design.dsd.definitive_screening_design``) and a known linear model per KPI with 3-4 active
factors of known sign plus Gaussian noise (sd 0.4). The smallest effect is 0.7 per coded unit
and its standard error is 0.4 / sqrt(26) = 0.08 (t ~ 9), so missing an active factor is
essentially impossible and is asserted for every replicate. False entries are not: with 8-9
inactive factors and p < 0.01, some inactive factor enters in ~8 % of replicates
(1 - 0.99^8; 8.7 % measured over 150 replicates while writing these tests), so for a random
noise seed the ">= 4 of 5 exact" check fails about 5 % of the time (two or more false entries
among five). The noise seed is fixed (1); seeds 2025 and 3 happen to give two false entries in
one KPI, which is that 5 %, not a defect of the selection.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy import stats

from bo.design.dsd import ParameterTable, definitive_screening_design, paper_parameter_table
from bo.screening.stepwise import (
    ScreeningResults,
    SignificanceTable,
    StepwiseFit,
    analyse_screening,
    count_significance,
    stepwise_regression,
)
from torchdem.errors import ConfigError

KPIS = ("shear_angle_deg", "mass_lower_box_kg")
ACTIVE = {
    "shear_angle_deg": {"mu_s_pp": 2.0, "mu_r_pp": 1.5, "mu_s_pg": -1.0, "mu_s_sg": 0.8},
    "mass_lower_box_kg": {"mu_s_pp": -1.0, "e_pp": 0.7, "mu_r_pg": -0.9},
}
INTERCEPT = {"shear_angle_deg": 38.0, "mass_lower_box_kg": 33.0}
NOISE_SD = 0.4
SEEDS = (101, 102, 103, 104, 105)


def synthetic_values(table: ParameterTable, coded: np.ndarray, rng: np.random.Generator
                     ) -> np.ndarray:
    values = np.empty((coded.shape[0], len(SEEDS), len(KPIS)))
    for q, kpi in enumerate(KPIS):
        beta = np.array([ACTIVE[kpi].get(name, 0.0) for name in table.names])
        for r in range(len(SEEDS)):
            values[:, r, q] = INTERCEPT[kpi] + coded @ beta + rng.normal(0, NOISE_SD, len(coded))
    return values


@pytest.fixture(scope="module")
def results() -> ScreeningResults:
    table = paper_parameter_table()
    coded = definitive_screening_design(12, 2)
    values = synthetic_values(table, coded, np.random.default_rng(1))
    return ScreeningResults.from_parameter_table(table, coded, SEEDS, KPIS, values,
                                                 source="synthetic screening")


@pytest.fixture(scope="module")
def analysis(results):
    return analyse_screening(results)


def test_stepwise_recovers_active_set_and_signs(analysis, results):
    for kpi in KPIS:
        exact = 0
        for r in range(len(SEEDS)):
            fit = analysis.fit(kpi, r)
            signs = {p: fit.sign(p) for p in fit.selected}
            truth = {p: int(np.sign(b)) for p, b in ACTIVE[kpi].items()}
            exact += signs == truth
            assert all(signs.get(p) == sign for p, sign in truth.items()), (kpi, r, signs)
            assert fit.n_runs_used == 29 and fit.seed == SEEDS[r]
        assert exact >= 4, f"{kpi}: exact recovery in only {exact}/5 replicates"


def test_table5_layout_shows_active_factors_with_sign(analysis, results):
    table = analysis.table
    selected = set().union(*(ACTIVE[k] for k in KPIS))
    assert set(table.selected_parameters) == selected
    lines = table.to_markdown().splitlines()
    header = [c.strip() for c in lines[2].strip("|").split("|")]
    assert header == ["parameter", *KPIS, "selected"]
    assert set(lines[3].replace("|", "").split()) == {"-" * len(h) for h in header}
    rows = {cells[0]: cells for cells in
            ([c.strip() for c in line.strip("|").split("|")] for line in lines[4:])}
    assert list(rows) == list(results.parameter_names)
    for name, cells in rows.items():
        assert cells[-1] == ("yes" if name in selected else "no")
        for q, kpi in enumerate(KPIS):
            cell = cells[1 + q]
            if name in ACTIVE[kpi]:
                sign = "+" if ACTIVE[kpi][name] > 0 else "-"
                assert cell in (f"{sign}5/5", f"{sign}4/5"), (name, kpi, cell)
            else:
                # an inactive factor may enter by chance, but never in most replicates
                assert cell == "" or int(cell.split("/")[0][1:]) <= 1, (name, kpi, cell)
    as_dict = json.loads(json.dumps(table.to_dict()))
    assert as_dict["selected_parameters"] == [p for p in results.parameter_names if p in selected]
    for row, name in zip(as_dict["rows"], results.parameter_names):
        assert row["parameter"] == name
        assert row["cells"] == {kpi: rows[name][1 + q] for q, kpi in enumerate(KPIS)}
        assert row["selected"] == (name in selected)
    assert as_dict["replicates"] == {kpi: 5 for kpi in KPIS}


def _ols_p_values(x: np.ndarray, y: np.ndarray, columns: list[int]) -> np.ndarray:
    """Two-sided t-test p-values of OLS slopes, with numpy/scipy only (an oracle)."""
    design = np.column_stack([np.ones(len(y))] + [x[:, j] for j in columns])
    beta, *_ = np.linalg.lstsq(design, y, rcond=None)
    dof = len(y) - design.shape[1]
    sigma2 = float(np.sum((y - design @ beta) ** 2)) / dof
    se = np.sqrt(np.diag(np.linalg.inv(design.T @ design)) * sigma2)
    return 2 * stats.t.sf(np.abs(beta / se), dof)[1:]


def test_final_model_satisfies_both_stepwise_rules(analysis, results):
    """Every kept term has p <= threshold, every left-out term would enter with p >= threshold."""
    names = list(results.parameter_names)
    for kpi in KPIS:
        y = results.kpi_values[:, 0, KPIS.index(kpi)]
        fit = analysis.fit(kpi, 0)
        model = [names.index(p) for p in fit.selected]
        kept = _ols_p_values(results.coded, y, model)
        assert np.all(kept <= fit.p_threshold)
        np.testing.assert_allclose(kept, [fit.p_values[p] for p in fit.selected], rtol=1e-8)
        for j in set(range(12)) - set(model):
            assert _ols_p_values(results.coded, y, model + [j])[-1] >= fit.p_threshold


def test_anova_of_final_model_matches_orthogonal_sums_of_squares(analysis, results):
    """On the orthogonal DSD, SS_j = (x_j . y)^2 / (x_j . x_j) for each main effect."""
    x = results.coded
    y = results.kpi_values[:, 2, 0]
    fit = analysis.fit(KPIS[0], 2)
    assert list(fit.anova.index) == [*fit.selected, "Residual"]
    ss_total = float(np.sum((y - y.mean()) ** 2))
    explained = 0.0
    for p in fit.selected:
        col = x[:, results.parameter_names.index(p)]
        expected = float(col @ y) ** 2 / float(col @ col)
        assert fit.anova.loc[p, "sum_sq"] == pytest.approx(expected, rel=1e-9)
        explained += expected
    assert fit.anova.loc["Residual", "sum_sq"] == pytest.approx(ss_total - explained, rel=1e-9)
    assert fit.anova.loc["Residual", "df"] == 29 - 1 - len(fit.selected)
    assert fit.r_squared == pytest.approx(explained / ss_total, rel=1e-9)


def test_failed_measurements_are_dropped_and_denominators_follow(results):
    values = np.array(results.kpi_values)
    values[[0, 7, 20], 1, 0] = np.nan  # three failed runs in replicate 1
    values[:-2, 3, 0] = np.nan  # replicate 3 of the first KPI: only 2 finite values left
    damaged = ScreeningResults(results.parameter_names, results.coded, results.physical,
                               results.seeds, results.kpi_names, values, "damaged")
    analysis = analyse_screening(damaged, kpis=[KPIS[0]])
    assert analysis.fit(KPIS[0], 1).n_runs_used == 26
    skipped = analysis.fit(KPIS[0], 3)
    assert skipped.skipped and skipped.selected == () and skipped.anova is None
    table = analysis.table
    assert table.replicates == (4,)
    for name, beta in ACTIVE[KPIS[0]].items():
        assert table.cell(name, KPIS[0]) == ("+" if beta > 0 else "-") + "4/4"


def _fit(kpi: str, replicate: int, coefficients: dict[str, float], names) -> StepwiseFit:
    selected = tuple(p for p in names if p in coefficients)
    return StepwiseFit(kpi=kpi, replicate=replicate, seed=replicate, parameter_names=names,
                       selected=selected, coefficients={p: coefficients[p] for p in selected},
                       p_values={p: 1e-4 for p in selected}, intercept=0.0, r_squared=0.9,
                       n_runs_used=29, p_threshold=0.01, steps=())


def test_counting_selection_fraction_and_mixed_signs():
    names = ("mu_s_pp", "mu_r_pp", "e_pp")
    fits = [
        _fit("angle_of_repose_deg", 0, {"mu_s_pp": 1.0, "mu_r_pp": 0.5}, names),
        _fit("angle_of_repose_deg", 1, {"mu_s_pp": 1.0, "mu_r_pp": -0.5}, names),
        _fit("angle_of_repose_deg", 2, {"mu_s_pp": 1.0, "mu_r_pp": 0.5}, names),
        _fit("angle_of_repose_deg", 3, {"mu_s_pp": 1.0}, names),
        _fit("angle_of_repose_deg", 4, {"e_pp": -2.0}, names),
    ]
    table = count_significance(fits, names, ["angle_of_repose_deg"])
    assert table.cell("mu_s_pp", "angle_of_repose_deg") == "+4/5"
    assert table.cell("mu_r_pp", "angle_of_repose_deg") == "+2/5, -1/5"
    assert table.cell("e_pp", "angle_of_repose_deg") == "-1/5"
    assert table.sign("mu_r_pp", "angle_of_repose_deg") == 1
    assert table.selected_parameters == ("mu_s_pp",)  # 4/5 >= 80 %
    strict = count_significance(fits, names, ["angle_of_repose_deg"], selection_fraction=1.0)
    assert strict.selected_parameters == ()
    loose = count_significance(fits, names, ["angle_of_repose_deg"], selection_fraction=0.6)
    assert loose.selected_parameters == ("mu_s_pp", "mu_r_pp")  # 3/5 with either sign
    with pytest.raises(ConfigError, match="appears twice"):
        count_significance(fits + fits[:1], names, ["angle_of_repose_deg"])


def test_significance_table_checks_its_counts():
    names, kpis = ("mu_s_pp", "e_pp"), ("shear_angle_deg",)
    with pytest.raises(ConfigError, match="'e_pp' is significant for 'shear_angle_deg' in 6 "
                                          "replicates; expected at most the 5 analysed"):
        SignificanceTable(names, kpis, np.array([[5], [4]]), np.array([[0], [2]]), (5,), 0.01,
                          0.8)
    with pytest.raises(ConfigError, match=r"positive has shape \(1, 2\); expected \[parameters, "
                                          r"KPIs\] = \(2, 1\)"):
        SignificanceTable(names, kpis, np.zeros((1, 2)), np.zeros((2, 1)), (5,), 0.01, 0.8)


def test_results_round_trip_through_json_with_nan(results):
    values = np.array(results.kpi_values)
    values[4, 2, 1] = np.nan
    with_nan = ScreeningResults(results.parameter_names, results.coded, results.physical,
                                results.seeds, results.kpi_names, values, "with NaN")
    text = json.dumps(with_nan.to_dict(), allow_nan=False)
    back = ScreeningResults.from_dict(json.loads(text))
    assert back == with_nan and back != results
    assert math.isnan(back.kpi_values[4, 2, 1])
    with pytest.raises(ValueError):
        back.kpi_values[0, 0, 0] = 1.0  # read-only


# ---------------------------------------------------------------------------- bad input

def _two_factor(**overrides) -> dict:
    coded = definitive_screening_design(2)
    table = ParameterTable(("mu_s_pp", "e_pp"), (0.3, 0.5), (0.4, 0.7), (0.5, 0.9), "t.json")
    args = dict(parameter_names=table.names, coded=coded,
                physical=np.where(coded < 0, [0.3, 0.5], np.where(coded > 0, [0.5, 0.9],
                                                                  [0.4, 0.7])),
                seeds=(1, 2), kpi_names=("angle_of_repose_deg",),
                kpi_values=np.zeros((coded.shape[0], 2, 1)), source="screening.json")
    args.update(overrides)
    return args


def test_valid_two_factor_results_build():
    r = ScreeningResults(**_two_factor())
    assert r.levels() == {"mu_s_pp": (0.3, 0.5), "e_pp": (0.5, 0.9)}


def test_fewer_than_two_parameters_is_rejected():
    coded = np.array([[-1.0], [0.0], [1.0]])
    with pytest.raises(ConfigError) as err:
        ScreeningResults(**_two_factor(parameter_names=("mu_s_pp",), coded=coded,
                                       physical=coded * 0.1 + 0.4,
                                       kpi_values=np.zeros((3, 2, 1))))
    message = str(err.value)
    assert "screening.json" in message and "number of parameters = 1" in message
    assert ">= 2" in message


def test_levels_out_of_order_are_rejected():
    args = _two_factor()
    physical = np.array(args["physical"])
    physical[:, 1] = np.where(args["coded"][:, 1] < 0, 0.9, np.where(args["coded"][:, 1] > 0,
                                                                      0.5, 0.7))
    with pytest.raises(ConfigError) as err:
        ScreeningResults(**{**args, "physical": physical})
    message = str(err.value)
    assert "screening.json" in message and "'e_pp'" in message
    assert "0.9 (coded -1)" in message and "0.5 (coded +1)" in message
    assert "low < mid < high" in message


def test_kpi_array_of_wrong_shape_is_rejected():
    with pytest.raises(ConfigError) as err:
        ScreeningResults(**_two_factor(kpi_values=np.zeros((5, 3, 1))))
    message = str(err.value)
    assert "screening.json" in message and "(5, 3, 1)" in message
    assert "[runs, replicates, n_kpi] = (5, 2, 1)" in message


@pytest.mark.parametrize("bad, needle", [
    ({"coded": np.array([[-1, 1], [0.5, 0], [1, -1], [0, 0], [1, 1]])}, "= 0.5 is not allowed"),
    ({"seeds": (3, 3)}, "repeat a seed"),
    ({"kpi_values": np.full((5, 2, 1), np.inf)}, "inf"),
    ({"parameter_names": ("mu_s_pp", "mu_s_pp")}, "repeated: ['mu_s_pp']"),
])
def test_other_bad_results_are_rejected(bad, needle):
    with pytest.raises(ConfigError, match="screening.json") as err:
        ScreeningResults(**_two_factor(**bad))
    assert needle in str(err.value)


@pytest.mark.parametrize("value", [0.0, 1.0, 1.5, -0.01, True])
def test_p_threshold_outside_unit_interval_is_rejected(results, value):
    with pytest.raises(ConfigError) as err:
        analyse_screening(results, p_threshold=value)
    message = str(err.value)
    assert f"p_threshold = {value!r}" in message and "(0, 1)" in message
    assert "analyse_screening(synthetic screening)" in message


@pytest.mark.parametrize("value", [0.0, 1.2])
def test_selection_fraction_outside_range_is_rejected(results, value):
    with pytest.raises(ConfigError) as err:
        analyse_screening(results, selection_fraction=value)
    assert f"selection_fraction = {value!r}" in str(err.value) and "(0, 1]" in str(err.value)


def test_unknown_kpi_and_mismatched_inputs_are_named(results):
    with pytest.raises(ConfigError, match="'flow_kg_s' is not in the screening results; known"):
        analyse_screening(results, kpis=["flow_kg_s"])
    with pytest.raises(ConfigError, match=r"shape \(28,\); expected \(29,\)"):
        stepwise_regression(results.coded, np.zeros(28), results.parameter_names)
    with pytest.raises(ConfigError, match=r"shape \(29, 12\); expected \(runs, 11\)"):
        stepwise_regression(results.coded, np.zeros(29), results.parameter_names[:11])


def test_comparable_effects_do_not_mask_each_other_in_a_small_dsd():
    """13-run DSD (4 factors, 2 fake): three equal effects of 1.2 per coded unit, noise 0.15.
    From the intercept, each factor alone has p ~ 0.03 (the other two sit in its residual); the
    stepwise starts from the full model (8 residual df) and keeps exactly the three."""
    coded = definitive_screening_design(4, 2)
    rng = np.random.default_rng(7)
    y = 20.0 + coded @ np.array([1.2, 1.2, 1.2, 0.0]) + rng.normal(0.0, 0.15, len(coded))
    alone = [_ols_p_values(coded, y, [j])[-1] for j in range(3)]
    assert min(alone) > 0.01  # what forward selection from the intercept would see
    fit = stepwise_regression(coded, y, ["a", "b", "c", "d"], 0.01)
    assert fit.selected == ("a", "b", "c") and max(fit.p_values.values()) < 1e-6
    assert fit.steps[0].startswith("start from all 4 main effects (8 residual df)")
    # with too few runs for an error estimate it starts from the intercept
    few = stepwise_regression(coded[:6], y[:6], ["a", "b", "c", "d"], 0.01)
    assert not few.steps or not few.steps[0].startswith("start from all")


def _curved(seed: int, coded: np.ndarray) -> np.ndarray:
    """The lab screening's shape on a 33-run DSD: a strong factor with curvature and an interaction
    (x0), a second (x1), and a weak one (x2, 1.2 per coded unit) under noise 1."""
    a, b, c = coded[:, 0], coded[:, 1], coded[:, 2]
    rng = np.random.default_rng(seed)
    return 30 + 6 * a + 4 * a * a + 2 * a * b + 2 * b + 1.2 * c + rng.normal(0.0, 1.0, len(coded))


def test_the_second_stage_finds_a_weak_effect_that_curvature_masks():
    """Main effects only, the left-out square and interaction inflate the residual: the weak x2 is
    found in 4 of 20 noise draws. With the second stage (squares and interactions of the active
    factors, then the main effects again) it is found in all 20, and the two terms are named in at
    least 18 (19 measured). The estimates of the main effects do not move (a DSD's main effects are
    orthogonal to every second-order term)."""
    coded = definitive_screening_design(13, 2)
    names = [f"x{j}" for j in range(13)]
    plain = [stepwise_regression(coded, _curved(s, coded), names, 0.01) for s in range(20)]
    second = [stepwise_regression(coded, _curved(s, coded), names, 0.01, second_order=True) for s in range(20)]
    assert sum("x2" in f.selected for f in plain) <= 8
    assert all({"x0", "x1", "x2"} <= set(f.selected) for f in second)
    assert sum(set(f.second_order) == {"x0^2", "x0*x1"} for f in second) >= 18
    assert all(not f.second_order and not f.second_order_stage for f in plain)
    f = second[0]
    assert f.second_order_stage and abs(f.coefficients["x2"] - 1.2) < 0.5
    assert abs(f.coefficients["x0^2"] - 4.0) < 1.5 and abs(f.coefficients["x0*x1"] - 2.0) < 1.0
    assert f.p_values["x2"] < 0.01 and f.r_squared > plain[0].r_squared
    both = stepwise_regression(coded, _curved(0, coded), names, 0.01)
    assert both.coefficients["x0"] == pytest.approx(f.coefficients["x0"], abs=1e-9)
    assert list(f.anova.index) == ["x0", "x1", "x2", *f.second_order, "Residual"]
    assert f.summary()["second_order"] == list(f.second_order)


def test_the_second_stage_keeps_heredity_and_adds_nothing_to_a_plane():
    """Only squares and products of factors in the model are candidates; on a plane under noise the
    second stage names no term in 20 draws (each candidate is tested at p < 0.01), and Table 5 says
    which analysis made it."""
    coded = definitive_screening_design(13, 2)
    names = [f"x{j}" for j in range(13)]
    terms = 0
    for s in range(20):
        rng = np.random.default_rng(100 + s)
        y = 10 + 3 * coded[:, 0] - 2 * coded[:, 1] + rng.normal(0.0, 1.0, len(coded))
        f = stepwise_regression(coded, y, names, 0.01, second_order=True)
        assert {"x0", "x1"} <= set(f.selected)
        terms += len(f.second_order)
        parents = {p for t in f.second_order for p in t.replace("^2", "").split("*")}
        assert parents <= set(f.selected)
    assert terms <= 2
    results = ScreeningResults(parameter_names=tuple(names), coded=coded, physical=coded + 2.0, seeds=(0,),
                               kpi_names=("y",), kpi_values=(10 + 3 * coded[:, 0])[:, None, None]
                               + np.random.default_rng(0).normal(0, 1, (len(coded), 1, 1)))
    assert "squares and interactions" in analyse_screening(results, second_order=True).table.to_markdown()
    assert "squares and interactions" not in analyse_screening(results).table.to_markdown()
    assert analyse_screening(results, second_order=True).table.to_dict()["second_order"] is True
