"""Tests of bo/surrogate/ga.py: known minima of shifted quadratics, the 0.9 restriction, vectorised
surrogate evaluation, Table 9 summary, validation. Small GA settings (population 60-80,
80 generations); the defaults stay the paper's Table A.3."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from bo.surrogate.acquisition import latin_hypercube
from bo.surrogate.ga import GASettings, ga_bounds, minimise_surrogate, repeated_ga
from bo.surrogate.gp import Surrogate
from torchdem.errors import ConfigError

torch.set_num_threads(1)

BOX = np.array([[0.0, 0.075, 0.5], [1.0, 0.24, 1.0]])
CENTRE = np.array([0.3, 0.16, 0.95])  # third coordinate above the 0.9 restriction
SMALL = GASettings(pop_size=60, n_generations=80)


def shifted_quadratic(X: np.ndarray) -> np.ndarray:
    return (((X - CENTRE) / (BOX[1] - BOX[0])) ** 2).sum(axis=1)


def test_paper_defaults():
    s = GASettings()
    assert (s.pop_size, s.n_generations, s.crossover_prob, s.mutation_prob, s.f_tolerance) == \
        (1000, 2000, 0.6, 0.05, 1e-6)
    assert s.restriction_limit == 0.9 and not s.restricted


def test_ga_finds_shifted_quadratic_minimum_and_calls_vectorised():
    calls = []

    def fitness(X):
        calls.append(X.shape[0])
        return shifted_quadratic(X)

    res = minimise_surrogate(fitness, BOX, SMALL, seed=1)
    assert np.allclose(res.x, CENTRE, atol=0.01 * (BOX[1] - BOX[0]))
    assert res.fitness < 1e-3
    assert np.all(np.array(calls) == 60) and len(calls) == res.n_generations
    assert res.n_evaluations == sum(calls)


def test_restricted_ga_respects_0_9():
    settings = GASettings(pop_size=60, n_generations=80, restricted=True)
    b = ga_bounds(BOX, settings)
    assert np.array_equal(b[1], [0.9, 0.24, 0.9]) and np.array_equal(b[0], BOX[0])
    res = minimise_surrogate(shifted_quadratic, BOX, settings, seed=1)
    assert np.all(res.x <= 0.9)
    assert res.x[2] == pytest.approx(0.9, abs=1e-3)  # constrained optimum on the cap
    assert np.allclose(res.x[:2], CENTRE[:2], atol=0.01 * (BOX[1, :2] - BOX[0, :2]))


def test_f_tolerance_stops_before_the_generation_limit():
    settings = GASettings(pop_size=40, n_generations=2000, f_tolerance=1e-3,
                          stall_generations=10)
    res = minimise_surrogate(shifted_quadratic, BOX, settings, seed=0)
    assert res.n_generations < 200


def test_repeated_ga_on_surrogates_table9(monkeypatch):
    X = latin_hypercube(BOX, 25, seed=0)
    y = shifted_quadratic(X)
    sizes = []
    original = Surrogate.predict_mean

    def counting(self, P):
        sizes.append(len(P))
        return original(self, P)

    monkeypatch.setattr(Surrogate, "predict_mean", counting)
    settings = GASettings(pop_size=80, n_generations=60, restricted=True)
    summary = repeated_ga(X, y, BOX, n_repetitions=2, settings=settings, seed=0)
    assert set(sizes) == {80}  # the whole population in one batched call per generation
    assert len(summary.repetitions) == 2
    fitness = [r.fitness for r in summary.repetitions]
    assert summary.best.fitness == min(fitness)
    best = summary.best.x
    assert np.all(best <= 0.9)
    assert np.allclose(best, [0.3, 0.16, 0.9], atol=0.05 * (BOX[1] - BOX[0]))
    text = summary.to_text(["mu_s_pp", "mu_r_pp", "e_pp"])
    assert "mu_r_pp" in text and "restricted" in text and text.count("*") == 1


@pytest.mark.parametrize("kwargs, match", [
    (dict(crossover_prob=1.5), r"crossover_prob = 1.5 .*\[0, 1\]"),
    (dict(mutation_prob=-0.1), r"mutation_prob"),
    (dict(pop_size=1), r"pop_size = 1 .*>= 2"),
    (dict(f_tolerance=0.0), r"f_tolerance"),
])
def test_bad_settings(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        GASettings(**kwargs)


def test_bad_bounds():
    with pytest.raises(ConfigError, match="inverted"):
        minimise_surrogate(shifted_quadratic, BOX[::-1], SMALL)
    with pytest.raises(ConfigError, match=r"lower bound 0.95.*restriction limit 0.9"):
        ga_bounds([[0.0, 0.95], [1.0, 1.0]], GASettings(restricted=True))
    with pytest.raises(ConfigError, match="fitness returned shape"):
        minimise_surrogate(lambda X: X, BOX, SMALL)


def test_restricted_mode_caps_the_coefficients_only():
    """The paper keeps friction and restitution below 0.9 (restricted mode). Given the names, a
    density or a lobe spacing beside them keeps its bounds (a density's lower bound of 3240 kg/m^3
    made restricted mode refuse the whole box before); without names every parameter is capped."""
    bounds = np.array([[0.37, 0.525, 0.15, 3240.0], [0.86, 1.0, 0.2679, 3960.0]])
    names = ["mu_s_pp", "e_pp", "lobe_spacing_sinter", "density_pellet"]
    b = ga_bounds(bounds, GASettings(restricted=True), names)
    np.testing.assert_allclose(b, [[0.37, 0.525, 0.15, 3240.0], [0.86, 0.9, 0.2679, 3960.0]])
    np.testing.assert_allclose(ga_bounds(bounds, GASettings(restricted=False), names), bounds)
    with pytest.raises(ConfigError, match=r"parameter 3 has lower bound 3240.0, which is not below"):
        ga_bounds(bounds, GASettings(restricted=True))
    with pytest.raises(ConfigError, match=r"parameter 'e_pp' has lower bound 0.95"):
        ga_bounds(np.array([[0.1, 0.95], [0.5, 1.0]]), GASettings(restricted=True), ["mu_s_pp", "e_pp"])
    with pytest.raises(ConfigError, match=r"2 names \['mu_s_pp', 'e_pp'\] for 4 parameters"):
        ga_bounds(bounds, GASettings(restricted=True), ["mu_s_pp", "e_pp"])
    res = minimise_surrogate(lambda X: ((X[:, 1] - 0.99) ** 2 + ((X[:, 3] - 3900.0) / 1000) ** 2), bounds,
                             GASettings(pop_size=60, n_generations=60, restricted=True), seed=0, names=names)
    assert res.x[1] <= 0.9 + 1e-12 and res.x[3] > 3600.0
