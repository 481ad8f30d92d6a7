"""Tests of bo/surrogate/jam.py: the jam classifier finds where runs jam on known probabilities,
and the GA on the expected objective leaves a region where the objective alone has its minimum
but runs jam (the lab campaign's optimum, where 1 of 5 verification runs arched over the slot).

Known model: on the unit square a run jams with probability 0.7 where x0 + x1 > 1.4 and 0.02
elsewhere; 240 points, one run each, seed 0."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from bo.surrogate.ga import GASettings, minimise_surrogate, repeated_ga
from bo.surrogate.jam import expected_objective, fit_jam_model
from torchdem.errors import ConfigError

torch.set_num_threads(1)

BOX = np.array([[0.0, 0.0], [1.0, 1.0]])


def true_jam_probability(X: np.ndarray) -> np.ndarray:
    return np.where(X[:, 0] + X[:, 1] > 1.4, 0.7, 0.02)


@pytest.fixture(scope="module")
def campaign():
    rng = np.random.default_rng(0)
    X = rng.uniform(size=(240, 2))
    jammed = rng.uniform(size=(240, 1)) < true_jam_probability(X)[:, None]
    return X, jammed, fit_jam_model(X, jammed, BOX)


def test_the_classifier_finds_where_runs_jam(campaign):
    X, jammed, model = campaign
    assert (model.n_runs, model.n_jammed) == (240, int(jammed.sum()))
    p = model.probability(np.array([[0.95, 0.95], [0.85, 0.8], [0.2, 0.2], [0.5, 0.3], [0.0, 1.0]]))
    # deep in the jamming corner within 0.25 of the true 0.7; far from it below 0.08 (true 0.02)
    assert abs(p[0] - 0.7) < 0.25 and abs(p[1] - 0.7) < 0.25
    assert p[2] < 0.08 and p[3] < 0.08
    assert np.all((p > 0) & (p < 1))
    # on the data, the runs that jammed were given the higher probability on average
    q = model.probability(X)
    assert q[jammed[:, 0]].mean() > 3 * q[~jammed[:, 0]].mean()


def test_runs_not_made_are_left_out_and_no_jam_means_no_model():
    X = np.random.default_rng(1).uniform(size=(30, 2))
    flags = np.zeros((30, 2))
    flags[:, 1] = np.nan  # second replicate never ran
    assert fit_jam_model(X, flags, BOX) is None
    flags[0, 0] = 1.0
    model = fit_jam_model(X, flags, BOX, iterations=50)
    assert (model.n_runs, model.n_jammed) == (30, 1)
    f = lambda x: np.zeros(len(x))  # noqa: E731
    assert expected_objective(f, None, 1.0) is f


def test_bad_flags_are_refused_with_the_value():
    X = np.zeros((3, 2))
    with pytest.raises(ConfigError, match=r"jammed holds \[2\.0\]"):
        fit_jam_model(X, np.array([[0.0], [2.0], [1.0]]), BOX)
    with pytest.raises(ConfigError, match=r"X \[n, 2\]"):
        fit_jam_model(X, np.zeros((4, 1)), BOX)


def test_the_ga_on_the_expected_objective_leaves_the_jamming_corner(campaign):
    _, _, model = campaign
    centre = np.array([0.9, 0.9])  # the objective's own minimum lies where 70 % of runs jam
    f = lambda X: ((X - centre) ** 2).sum(axis=1)  # noqa: E731
    settings = GASettings(pop_size=60, n_generations=60)
    plain = minimise_surrogate(f, BOX, settings, seed=0)
    aware = minimise_surrogate(expected_objective(f, model, 1.0), BOX, settings, seed=0)
    assert np.allclose(plain.x, centre, atol=0.02)
    # the expected objective of one run: (1 - p) f + p 1; at the plain optimum it is p ~ 0.7, so
    # the GA goes to the edge of the corner, where the true probability is the base rate
    assert true_jam_probability(aware.x[None, :])[0] == 0.02
    assert model.probability(aware.x[None, :])[0] < 0.2
    assert aware.fitness < float(expected_objective(f, model, 1.0)(plain.x[None, :])[0]) - 0.3


def test_repeated_ga_takes_the_jam_model(campaign):
    X, _, model = campaign
    y = ((X - 0.9) ** 2).sum(axis=1)
    summary = repeated_ga(X, y, BOX, n_repetitions=1, settings=GASettings(pop_size=40, n_generations=30),
                          jam=model, jammed_objective=1.0)
    assert true_jam_probability(summary.best.x[None, :])[0] == 0.02
