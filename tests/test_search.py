"""bo.surrogate.search.multistart_minimum: known minima of smooth functions (inside the box, on
its boundary, the global one of several basins), no worse than the GA on a real GP fit, and bad
input named."""
import numpy as np
import pytest

from bo.surrogate.ga import GASettings, minimise_surrogate
from bo.surrogate.search import multistart_minimum
from torchdem.errors import ConfigError


def test_quadratic_minimum_inside_the_box_to_1e_6():
    centre = np.array([0.3, -1.2, 4.0])
    res = multistart_minimum(lambda x: ((x - centre) ** 2 * [1.0, 10.0, 0.1]).sum(-1),
                             [[0.0, -2.0, 3.0], [1.0, 0.0, 8.0]], samples=256)
    assert res.x == pytest.approx(centre, abs=1e-5)
    assert res.fitness == pytest.approx(0.0, abs=1e-9)
    assert 256 < res.n_evaluations < 5000


def test_minimum_on_the_boundary():
    res = multistart_minimum(lambda x: (x ** 2).sum(-1), [[1.0, 2.0], [3.0, 5.0]], samples=64)
    assert res.x == pytest.approx([1.0, 2.0], abs=1e-9)
    assert res.fitness == pytest.approx(5.0, abs=1e-9)


def test_global_minimum_of_several_basins():
    # Rastrigin in 2-D over [-4.5, 4.5]^2: 81 local minima, the global one (0) at the origin
    def rastrigin(x):
        return 20 + (x ** 2 - 10 * np.cos(2 * np.pi * x)).sum(-1)
    res = multistart_minimum(rastrigin, [[-4.5, -4.5], [4.5, 4.5]], samples=1024, starts=3, seed=1)
    assert res.x == pytest.approx([0.0, 0.0], abs=1e-5)
    assert res.fitness == pytest.approx(0.0, abs=1e-8)


def test_no_worse_than_the_ga_on_a_gp_chi2():
    from bo.surrogate.gp import SurrogateConfig, fit_surrogate
    from bo.surrogate.objective import ObjectiveSpec
    rng = np.random.default_rng(0)
    b = np.array([[0.0, 0.0], [1.0, 1.0]])
    X = rng.random((20, 2))
    y = np.stack([np.sin(3 * X[:, 0]) + X[:, 1] ** 2, np.cos(2 * X[:, 1]) * X[:, 0]], axis=1)
    y = y + 0.01 * rng.standard_normal(y.shape)
    target = np.array([0.8, 0.3])
    sur = fit_surrogate(X, y, b, SurrogateConfig(kernel="matern52", strategy="per_kpi"),
                        objective=ObjectiveSpec(("a", "b"), tuple(target), source="test"))

    def chi2(x):
        mean, var = sur.predict_outputs(x)
        return (((mean - target) ** 2 + var) / 0.01).sum(-1)
    mine = multistart_minimum(chi2, b, samples=512)
    ga = min((minimise_surrogate(chi2, b, GASettings(pop_size=200, n_generations=200, stall_generations=30), seed=k)
              for k in range(3)), key=lambda r: r.fitness)
    assert mine.fitness <= ga.fitness + 1e-6 * max(1.0, abs(ga.fitness))
    assert mine.n_evaluations < ga.n_evaluations / 5


@pytest.mark.parametrize("kwargs, named", [
    ({"bounds": [[0.0, 1.0], [1.0, 1.0]]}, "bounds"),
    ({"samples": 1}, "samples"),
    ({"starts": 0}, "starts"),
])
def test_bad_input_is_named(kwargs, named):
    args = {"bounds": [[0.0, 0.0], [1.0, 1.0]], **kwargs}
    with pytest.raises(ConfigError, match=named):
        multistart_minimum(lambda x: x.sum(-1), args.pop("bounds"), **args)


def test_a_function_nowhere_finite_is_an_error():
    with pytest.raises(ConfigError, match="not finite"):
        multistart_minimum(lambda x: np.full(len(x), np.nan), [[0.0], [1.0]], samples=16)
