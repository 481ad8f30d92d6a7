"""Tests of bo/surrogate/objective.py: Eqs. 7-8 against hand-computed values, vectorisation, validation."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from bo.surrogate.objective import ObjectiveSpec
from torchdem.errors import ConfigError

KPIS = ("angle_of_repose", "shear_angle", "mass_flow_rate", "drawdown_angle")
MEASURED = (30.0, 40.0, 10.0, 35.0)


def spec(**kw) -> ObjectiveSpec:
    return ObjectiveSpec(KPIS, MEASURED, **kw)


def test_equal_weights_by_default_and_hand_value():
    s = spec()
    assert s.weights == (0.25, 0.25, 0.25, 0.25)
    sim = np.array([33.0, 38.0, 10.5, 35.0])
    # |3/30| + |-2/40| + |0.5/10| + 0 = 0.1 + 0.05 + 0.05 + 0
    assert s(sim) == pytest.approx(0.25 * 0.2, abs=1e-15)
    assert np.allclose(s.relative_errors(sim), [0.1, -0.05, 0.05, 0.0])


def test_custom_weights_and_exact_match_is_zero():
    s = spec(weights=(0.4, 0.3, 0.2, 0.1))
    assert s(np.array(MEASURED)) == 0.0
    sim = np.array([36.0, 40.0, 10.0, 35.0])  # 20 % error in the first KPI only
    assert s(sim) == pytest.approx(0.4 * 0.2)


def test_vectorised_numpy_and_torch_batches_agree():
    rng = np.random.default_rng(0)
    s = spec(weights=(0.1, 0.2, 0.3, 0.4))
    sims = np.array(MEASURED) * (1 + 0.2 * rng.standard_normal((5, 3, 4)))
    out = s(sims)
    assert out.shape == (5, 3)
    loop = np.array([[sum(w * abs((v - m) / m) for w, v, m in zip(s.weights, p, MEASURED))
                      for p in row] for row in sims])
    assert np.allclose(out, loop, rtol=0, atol=1e-14)
    # torch: posterior samples [S, b, q, M] -> [S, b, q], same dtype, differentiable
    t = torch.tensor(sims, dtype=torch.float64, requires_grad=True)
    tout = s(t)
    assert tout.dtype == torch.float64 and tout.shape == (5, 3)
    assert np.allclose(tout.detach().numpy(), out, atol=1e-14)
    tout.sum().backward()
    assert torch.isfinite(t.grad).all()


def test_mapping_input_and_from_measured():
    s = ObjectiveSpec.from_measured(dict(zip(KPIS, MEASURED)),
                                    weights={k: 0.25 for k in KPIS}, source="conf/objective")
    sim = {k: np.array([v, 1.1 * v]) for k, v in zip(KPIS, MEASURED)}
    assert np.allclose(s(sim), [0.0, 0.1])
    assert s.index("mass_flow_rate") == 2


@pytest.mark.parametrize("weights, match", [
    ((0.3, 0.3, 0.3, 0.3), "sum to 1"),
    ((0.5, 0.5, 0.5, -0.5), ">= 0"),
    ((0.5, 0.5), "one value per KPI"),
])
def test_bad_weights(weights, match):
    with pytest.raises(ConfigError, match=match) as err:
        spec(weights=weights, source="conf/objective.yaml")
    assert "conf/objective.yaml" in str(err.value)


def test_weights_sum_tolerance_is_1e_9():
    spec(weights=(0.25, 0.25, 0.25, 0.25 + 5e-10))  # accepted
    with pytest.raises(ConfigError, match="sum to"):
        spec(weights=(0.25, 0.25, 0.25, 0.25 + 5e-9))


def test_measured_zero_and_unknown_kpi_are_errors():
    with pytest.raises(ConfigError, match=r"measured\['shear_angle'\] = 0.0 .*non-zero"):
        ObjectiveSpec(KPIS, (30.0, 0.0, 10.0, 35.0))
    s = spec()
    with pytest.raises(ConfigError, match=r"unknown KPI\(s\) \['porosity'\]"):
        s({**{k: 1.0 for k in KPIS}, "porosity": 0.4})
    with pytest.raises(ConfigError, match=r"missing \['drawdown_angle'\]"):
        s({k: 1.0 for k in KPIS[:3]})
    with pytest.raises(ConfigError, match="unknown KPI 'porosity'"):
        s.index("porosity")
    with pytest.raises(ConfigError, match=r"unknown KPI\(s\) \['porosity'\]"):
        ObjectiveSpec.from_measured({"a": 1.0}, weights={"a": 0.5, "porosity": 0.5})
    with pytest.raises(ConfigError, match=r"expected \[\.\.\., 4\]"):
        s(np.ones((3, 5)))
    with pytest.raises(ConfigError, match="unique"):
        ObjectiveSpec(("a", "a"), (1.0, 2.0))
