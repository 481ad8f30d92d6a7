"""Tests for bo/screening/bounds.py: screening range vs measurement and the proposed bounds.

The screening results are synthetic (paper-sized DSD on the paper's Table 4 levels, known
linear effects, small noise), the measurements are the paper's Table 2 (50-50 condition,
shipped in torchdem/data), so the cases mirror section 3.4.1: the measured shear angle lies
above every screening run and all its drivers have a + effect, so their high bounds must rise.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from bo.design.dsd import definitive_screening_design, paper_parameter_table
from bo.screening.bounds import (
    PhysicalLimit,
    compare_ranges,
    default_physical_limit,
    propose_extension,
)
from bo.screening.stepwise import ScreeningResults, SignificanceTable, analyse_screening
from torchdem.errors import ConfigError
from torchdem.measured import load_measured

MEASURED = load_measured().condition("50-50").kpis  # Table 2
KPIS = ("angle_of_repose_deg", "shear_angle_deg", "mass_flow_rate_kg_s")
# intercept, {parameter: effect per coded unit}
MODEL = {
    # inside: 29.47 lies within 29.5 +- ~1.5
    "angle_of_repose_deg": (29.5, {"mu_r_pp": 1.0, "e_pp": -0.5}),
    # measured 42.51 above the range ~36 +- 3: raise the + drivers' high bounds
    "shear_angle_deg": (36.0, {"mu_s_pp": 1.5, "mu_r_pp": 1.0, "mu_s_pg": 0.8}),
    # measured 10.29 below the range ~12 +- 0.7: lower e_pp (+ effect) and raise mu_s_sg (-)
    "mass_flow_rate_kg_s": (12.0, {"e_pp": 0.4, "mu_s_sg": -0.3}),
}


@pytest.fixture(scope="module")
def screening():
    table = paper_parameter_table()
    coded = definitive_screening_design(12, 2)
    rng = np.random.default_rng(5)
    values = np.empty((29, 5, len(KPIS)))
    for q, kpi in enumerate(KPIS):
        intercept, effects = MODEL[kpi]
        beta = np.array([effects.get(n, 0.0) for n in table.names])
        values[:, :, q] = intercept + (coded @ beta)[:, None] + rng.normal(0, 0.05, (29, 5))
    results = ScreeningResults.from_parameter_table(table, coded, range(5), KPIS, values,
                                                    source="synthetic screening")
    return results, analyse_screening(results).table


def test_compare_ranges_places_measurements(screening):
    results, _ = screening
    comparisons = {c.kpi: c for c in compare_ranges(results, MEASURED)}
    assert [c.position for c in comparisons.values()] == ["inside", "above", "below"]
    shear = comparisons["shear_angle_deg"]
    means = results.run_means("shear_angle_deg")
    assert (shear.simulated_min, shear.simulated_max) == (means.min(), means.max())
    assert shear.measured_mean == 42.51 and shear.measured_ci95 == 1.62
    assert shear.direction == 1 and not shear.ci_overlaps
    assert comparisons["mass_flow_rate_kg_s"].direction == -1


def test_extension_moves_the_right_bound_in_the_right_direction(screening):
    results, table = screening
    assert set(table.selected_parameters) == {"mu_s_pp", "mu_r_pp", "e_pp", "mu_s_pg", "mu_s_sg"}
    proposal = propose_extension(results, table, MEASURED)
    levels = paper_parameter_table()
    low = dict(zip(levels.names, levels.low))
    high = dict(zip(levels.names, levels.high))

    def width(p):
        return high[p] - low[p]

    expected = {
        "mu_s_pp": (low["mu_s_pp"], high["mu_s_pp"] + width("mu_s_pp")),  # shear up, + effect
        "mu_r_pp": (low["mu_r_pp"], high["mu_r_pp"] + width("mu_r_pp")),
        "mu_s_pg": (low["mu_s_pg"], high["mu_s_pg"] + width("mu_s_pg")),
        "e_pp": (low["e_pp"] - width("e_pp"), high["e_pp"]),  # flow down, + effect
        "mu_s_sg": (low["mu_s_sg"], high["mu_s_sg"] + width("mu_s_sg")),  # flow down, - effect
    }
    assert set(proposal.proposed_bounds) == set(expected)
    for p, (lo, hi) in expected.items():
        assert proposal.proposed_bounds[p] == pytest.approx((lo, hi), abs=1e-12), p
        assert proposal.screened_bounds[p] == (low[p], high[p])
    moves = {(m.parameter, m.side): m for m in proposal.moves}
    assert set(moves) == {("mu_s_pp", "high"), ("mu_r_pp", "high"), ("mu_s_pg", "high"),
                          ("e_pp", "low"), ("mu_s_sg", "high")}
    assert moves[("e_pp", "low")].kpis == ("mass_flow_rate_kg_s",)
    assert not any(m.limited for m in proposal.moves)
    text = str(proposal)
    assert "shear_angle_deg: measured 42.51 +- 1.62 lies above" in text
    assert "mu_s_pp has a + effect on shear_angle_deg (5/5 replicates)" in text
    assert "angle_of_repose_deg" in text and "no change needed" in text
    json.dumps(proposal.to_dict(), allow_nan=False)


def test_factor_and_physical_limits(screening):
    results, table = screening
    proposal = propose_extension(results, table, MEASURED, factor=2.0)
    # e_pp low: 0.525 - 2 x 0.35 < 0, restitution is in (0, 1]: halfway to the open limit
    assert proposal.proposed_bounds["e_pp"] == pytest.approx((0.525 / 2, 0.875))
    assert [m.limited for m in proposal.moves if m.parameter == "e_pp"] == [True]
    assert proposal.proposed_bounds["mu_s_pp"] == pytest.approx((0.368, 0.613 + 2 * 0.245))
    capped = propose_extension(results, table, MEASURED, limits={"mu_s_pp": PhysicalLimit(0, 0.7)})
    assert capped.proposed_bounds["mu_s_pp"] == (0.368, 0.7)
    assert "would leave the physical limit [0, 0.7], so it is capped at the limit" in str(capped)
    assert "so it is set halfway to the open limit" in str(proposal)  # e_pp, limit (0, 1]


def test_shift_mode_starts_the_new_range_at_the_old_bound(screening):
    results, table = screening
    proposal = propose_extension(results, table, MEASURED, mode="shift")
    # as the paper's Table 6 does for mu_s_pp: the new low is the screened high
    assert proposal.proposed_bounds["mu_s_pp"] == pytest.approx((0.613, 0.858))
    assert proposal.proposed_bounds["e_pp"] == pytest.approx((0.175, 0.525))


def _table(positive: dict, negative: dict, kpis, names) -> SignificanceTable:
    pos = np.array([[positive.get((p, k), 0) for k in kpis] for p in names])
    neg = np.array([[negative.get((p, k), 0) for k in kpis] for p in names])
    return SignificanceTable(parameter_names=tuple(names), kpi_names=tuple(kpis), positive=pos,
                             negative=neg, replicates=(5,) * len(kpis), p_threshold=0.01,
                             selection_fraction=0.8)


def test_conflicting_kpis_extend_both_bounds_and_limits_hold(screening):
    results, _ = screening
    names = results.parameter_names
    kpis = ("shear_angle_deg", "mass_flow_rate_kg_s")
    # shear must rise (+ effect -> high), flow must fall (+ effect -> low): conflict on mu_r_pp.
    # e_sg: + on shear, its high bound (0.5) rises by 0.2; mu_r_sg: + on flow -> low 0.06 - 0.04.
    table = _table({("mu_r_pp", kpis[0]): 5, ("mu_r_pp", kpis[1]): 4, ("e_sg", kpis[0]): 5,
                    ("mu_r_sg", kpis[1]): 5}, {}, kpis, names)
    proposal = propose_extension(results, table, MEASURED, mode="shift")
    assert proposal.proposed_bounds["mu_r_pp"] == pytest.approx((0.015, 0.105))
    assert "opposite moves" in str(proposal)
    assert proposal.proposed_bounds["e_sg"] == pytest.approx((0.5, 0.7))  # shifted up
    assert proposal.proposed_bounds["mu_r_sg"] == pytest.approx((0.02, 0.06))  # shifted down
    big = propose_extension(results, table, MEASURED, factor=3.0)
    assert big.proposed_bounds["e_sg"] == (0.3, 1.0)  # restitution capped at 1
    assert big.proposed_bounds["mu_r_sg"] == (0.0, 0.1)  # friction capped at 0
    again = propose_extension(results, _table({("e_pp", kpis[0]): 5}, {}, kpis, names),
                              MEASURED, limits={"e_pp": PhysicalLimit(0, 0.875, low_open=True)})
    assert again.proposed_bounds["e_pp"] == (0.525, 0.875) and again.moves == ()
    assert "already at the physical limit" in str(again)


def test_mixed_signs_do_not_move_a_bound(screening):
    results, _ = screening
    kpis = ("shear_angle_deg",)
    table = _table({("mu_s_ss", kpis[0]): 2}, {("mu_s_ss", kpis[0]): 2}, kpis,
                   results.parameter_names)
    proposal = propose_extension(results, table, MEASURED)
    assert proposal.proposed_bounds == {"mu_s_ss": (0.525, 0.875)} and proposal.moves == ()
    assert "mixed signs; not moved" in str(proposal)


def test_default_limits_follow_parameter_names():
    assert default_physical_limit("mu_s_pg").low == 0 and math.isinf(
        default_physical_limit("mu_r_ss").high)
    e = default_physical_limit("e_sg")
    assert not e.contains(0.0) and e.contains(1.0) and e.contains(1e-6)
    assert default_physical_limit("young_modulus_pa") is None
    # the material parameters a campaign can calibrate: a trilobe's lobe spacing lies in (0, 0.3]
    lobe = default_physical_limit("lobe_spacing_sinter")
    assert lobe.contains(0.3) and not lobe.contains(0.31) and not lobe.contains(0.0)
    density = default_physical_limit("density_pellet")
    assert density.contains(3602.4) and not density.contains(0.0)


# ---------------------------------------------------------------------------- bad input

def test_missing_measured_kpi_is_named(screening):
    results, table = screening
    partial = {k: v for k, v in MEASURED.items() if k != "mass_flow_rate_kg_s"}
    with pytest.raises(ConfigError) as err:
        propose_extension(results, table, partial)
    message = str(err.value)
    assert "synthetic screening" in message and "'mass_flow_rate_kg_s'" in message
    assert "measured KPIs: ['angle_of_repose_deg'" in message


def test_parameters_must_match(screening):
    results, table = screening
    renamed = SignificanceTable(("mu_s_pp",) + table.parameter_names[1:-1] + ("cohesion_pa",),
                                table.kpi_names, table.positive, table.negative,
                                table.replicates, table.p_threshold, table.selection_fraction)
    with pytest.raises(ConfigError, match=r"missing \['e_sg'\], unexpected \['cohesion_pa'\]"
                                          r"; expected \['mu_s_pp', .*, 'e_sg'\]") as err:
        propose_extension(results, renamed, MEASURED)
    assert str(err.value).startswith("propose_extension(synthetic screening):")
    with pytest.raises(ConfigError, match=r"limits given for unknown parameters \['mu_x'\]"):
        propose_extension(results, table, MEASURED, limits={"mu_x": PhysicalLimit(0, 1)})


@pytest.mark.parametrize("factor", [0, -1.0, math.inf])
def test_bad_factor_is_rejected(screening, factor):
    results, table = screening
    with pytest.raises(ConfigError) as err:
        propose_extension(results, table, MEASURED, factor=factor)
    assert f"factor = {factor!r}" in str(err.value) and "> 0" in str(err.value)


def test_bad_mode_and_kpis_are_rejected(screening):
    results, table = screening
    with pytest.raises(ConfigError, match="mode = 'widen'.*'extend' or 'shift'"):
        propose_extension(results, table, MEASURED, mode="widen")
    with pytest.raises(ConfigError, match=r"\['segregation_rsd_vertical'\] are not in the "):
        propose_extension(results, table, MEASURED, kpis=["segregation_rsd_vertical"])
