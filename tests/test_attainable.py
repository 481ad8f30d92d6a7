"""What the bounds allow (bo.surrogate.attainable): the range of one KPI's surrogate mean with the
others inside their CIs, against ranges worked out by hand for linear KPIs."""
import math

import numpy as np
import pytest

from bo.surrogate.attainable import AttainableSettings, attainable_ranges, format_attainable
from bo.surrogate.gp import SurrogateConfig, fit_surrogate
from bo.surrogate.objective import ObjectiveSpec
from torchdem.errors import ConfigError

# Two KPIs linear in two parameters on the unit box: a = x0 + x1, b = x0.
KPIS = ("a", "b")
#: The GP mean of a linear function fitted on 60 points reproduces it to about 1e-3; the GA's
#: optimum of a linear objective under linear constraints lies on the feasible set's edge to ~1e-3.
TOL = 0.02
FAST = AttainableSettings(pop_size=100, n_generations=80)


@pytest.fixture(scope="module")
def surrogate():
    rng = np.random.default_rng(3)
    x = rng.random((60, 2))
    y = np.column_stack([x[:, 0] + x[:, 1], x[:, 0]])
    objective = ObjectiveSpec(KPIS, (0.5, 0.2))
    return fit_surrogate(x, y, np.array([[0.0, 0.0], [1.0, 1.0]]),
                         SurrogateConfig(kernel="matern52", strategy="per_kpi"),
                         y_var=np.full_like(y, 1e-6), objective=objective)


def test_each_range_is_the_linear_programme_s(surrogate):
    # a with |b - 0.2| <= 0.05: x0 in [0.15, 0.25], x1 in [0, 1] -> a in [0.15, 1.25];
    # b with |a - 0.5| <= 0.1: x0 + x1 in [0.4, 0.6] -> b = x0 in [0, 0.6].
    a, b = attainable_ranges(surrogate, {"a": (0.5, 0.1), "b": (0.2, 0.05)}, ("x0", "x1"), settings=FAST)
    assert a.kpi == "a" and b.kpi == "b" and a.feasible and b.feasible
    assert a.low == pytest.approx(0.15, abs=TOL) and a.high == pytest.approx(1.25, abs=TOL)
    assert b.low == pytest.approx(0.0, abs=TOL) and b.high == pytest.approx(0.6, abs=TOL)
    assert a.at_high["x0"] == pytest.approx(0.25, abs=TOL) and a.at_high["x1"] == pytest.approx(1.0, abs=TOL)
    assert a.reaches and b.reaches
    assert a.without == {} and b.without == {}  # ranges that meet the lab are not explained
    assert 0 <= a.sd_high < 0.05


def test_a_measured_value_beyond_the_range_is_not_reached(surrogate):
    # a at 1.6 +- 0.1 with b inside 0.2 +- 0.05: a stops at 1.25
    a, _ = attainable_ranges(surrogate, {"a": (1.6, 0.1), "b": (0.2, 0.05)}, settings=FAST)
    assert a.feasible and a.high == pytest.approx(1.25, abs=TOL)
    assert not a.reaches
    assert "**no**" in "\n".join(format_attainable([a]))


def test_contradictory_other_kpis_give_no_range(surrogate):
    # b measured at 1.5 +- 0.1 lies beyond x0 <= 1: no point puts b inside its CI, so a has no range
    a, b = attainable_ranges(surrogate, {"a": (0.5, 0.1), "b": (1.5, 0.1)}, settings=FAST)
    assert not a.feasible and math.isnan(a.low) and math.isnan(a.high) and not a.reaches
    assert b.feasible and not b.reaches  # b itself is constrained by a only, and tops out at 0.6
    assert "none" in "\n".join(format_attainable([a]))


def test_a_narrower_box_or_a_constraint_narrows_the_range(surrogate):
    lab = {"a": (0.5, 0.1), "b": (0.2, 0.05)}
    a, _ = attainable_ranges(surrogate, lab, bounds=[[0.0, 0.0], [1.0, 0.5]], settings=FAST)
    assert a.high == pytest.approx(0.75, abs=TOL)
    # x1 <= 0.5 as a constraint, as the calibration caps the chance of a jam
    a, _ = attainable_ranges(surrogate, lab, settings=FAST, constraint=lambda x: x[:, 1] - 0.5)
    assert a.high == pytest.approx(0.75, abs=TOL) and a.at_high["x1"] <= 0.5 + 1e-9


def test_what_holds_a_range_is_each_constraint_released_in_turn(surrogate):
    # a at 1.6 +- 0.1 needs x0 >= 0.5 (x1 <= 1); b at 0.2 +- 0.05 needs x0 <= 0.25: they contradict each
    # other, and each reaches its lab value once the other's CI is released.
    a, b = attainable_ranges(surrogate, {"a": (1.6, 0.1), "b": (0.2, 0.05)}, ("x0", "x1"), settings=FAST)
    assert not a.reaches and not b.reaches
    assert set(a.without) == {"b"} and a.without["b"] == pytest.approx(1.6, abs=TOL) and a.held_by == ("b",)
    assert set(b.without) == {"a"} and b.without["a"] == pytest.approx(0.2, abs=TOL) and b.held_by == ("a",)
    # With x1 <= 0.5 besides and a at 1.7 +- 0.1: a stops at 0.75; released from b it gets to x0 + x1 =
    # 1.5, released from the cap to 0.25 + 1 = 1.25; neither reaches 1.6, so no single constraint holds it.
    a, _ = attainable_ranges(surrogate, {"a": (1.7, 0.1), "b": (0.2, 0.05)}, settings=FAST,
                             constraint=lambda x: x[:, 1] - 0.5, constraint_name="cap")
    assert a.high == pytest.approx(0.75, abs=TOL)
    assert a.without["b"] == pytest.approx(1.5, abs=TOL) and a.without["cap"] == pytest.approx(1.25, abs=TOL)
    assert a.held_by == ()
    text = "\n".join(format_attainable([a]))
    assert "without b | without cap | held by" in text and "no single constraint" in text
    # b at 1.5 is out of the box: a's other constraints never hold together, released or not (b's own)
    a, b = attainable_ranges(surrogate, {"a": (0.5, 0.1), "b": (1.5, 0.1)}, settings=FAST)
    assert not a.feasible and a.without["b"] == pytest.approx(0.5, abs=TOL) and a.held_by == ("b",)
    assert b.without["a"] == pytest.approx(1.0, abs=TOL) and b.held_by == ()
    # no range is explained with explain off (nor one that meets the lab: the first test)
    a, _ = attainable_ranges(surrogate, {"a": (1.6, 0.1), "b": (0.2, 0.05)},
                             settings=AttainableSettings(pop_size=100, n_generations=80, explain=False))
    assert a.without == {} and "held by" not in "\n".join(format_attainable([a]))


def test_a_range_round_trips_through_strict_json(surrogate):
    import json
    ranges = attainable_ranges(surrogate, {"a": (0.5, 0.1), "b": (1.5, 0.1)}, settings=FAST)
    text = json.dumps([r.to_dict() for r in ranges], allow_nan=False)
    back = [type(r).from_dict(d) for r, d in zip(ranges, json.loads(text))]
    assert [r.kpi for r in back] == ["a", "b"] and back[1].without == pytest.approx(ranges[1].without)
    assert math.isnan(back[0].low) and not back[0].feasible
    old = ranges[1].to_dict()
    del old["without"]  # a calibration.json written before ``without`` existed
    assert type(ranges[1]).from_dict(old).without == {}


def test_bad_input_names_the_value(surrogate):
    with pytest.raises(ConfigError, match="lack \\['b'\\]"):
        attainable_ranges(surrogate, {"a": (0.5, 0.1)}, settings=FAST)
    with pytest.raises(ConfigError, match="95 % half-widths"):
        attainable_ranges(surrogate, {"a": (0.5, -0.1), "b": (0.2, 0.05)}, settings=FAST)
    with pytest.raises(ConfigError, match="constraint_name = 'a'"):
        attainable_ranges(surrogate, {"a": (0.5, 0.1), "b": (0.2, 0.05)}, constraint=lambda x: x[:, 0],
                          constraint_name="a")
    with pytest.raises(ConfigError, match="explain"):
        attainable_ranges(surrogate, {"a": (0.5, 0.1), "b": (0.2, 0.05)}, settings=AttainableSettings(explain="yes"))
    with pytest.raises(ConfigError, match="pop_size"):
        attainable_ranges(surrogate, {"a": (0.5, 0.1), "b": (0.2, 0.05)}, settings=AttainableSettings(pop_size=1))
    scalar = fit_surrogate(surrogate.train_X, surrogate.train_Y[:, 0], surrogate.bounds, SurrogateConfig())
    with pytest.raises(ConfigError, match="expected 'per_kpi'"):
        attainable_ranges(scalar, {"a": (0.5, 0.1), "b": (0.2, 0.05)})
