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


def test_bad_input_names_the_value(surrogate):
    with pytest.raises(ConfigError, match="lack \\['b'\\]"):
        attainable_ranges(surrogate, {"a": (0.5, 0.1)}, settings=FAST)
    with pytest.raises(ConfigError, match="95 % half-widths"):
        attainable_ranges(surrogate, {"a": (0.5, -0.1), "b": (0.2, 0.05)}, settings=FAST)
    with pytest.raises(ConfigError, match="pop_size"):
        attainable_ranges(surrogate, {"a": (0.5, 0.1), "b": (0.2, 0.05)}, settings=AttainableSettings(pop_size=1))
    scalar = fit_surrogate(surrogate.train_X, surrogate.train_Y[:, 0], surrogate.bounds, SurrogateConfig())
    with pytest.raises(ConfigError, match="expected 'per_kpi'"):
        attainable_ranges(scalar, {"a": (0.5, 0.1), "b": (0.2, 0.05)})
