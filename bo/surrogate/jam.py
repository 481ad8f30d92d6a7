"""The probability that a run jams: a Gaussian-process classifier on the runs of a campaign.

Near the rolling and sliding frictions that steepen a residue most, the grains of a draw down
test can arch over the slot and stop the discharge (``kpi.loadcell.discharge_jammed``). Whether a
run does is chance: at the same parameters one seed jams and the next flows. A surrogate of the
KPIs of the runs that flowed knows nothing of it, so its optimum may lie where a fifth of the
runs jam. The lab's discharges never jammed; a calibrated set that does is a miss.

``fit_jam_model(X, jammed, bounds)`` fits ``P(jam | x)``: one Bernoulli observation per run,
``X [n, d]`` the parameter sets inside ``bounds [2, d]`` and ``jammed [n, r]`` (bool, or float
with NaN for a run not made). The latent function is a GP (double precision, inputs normalised to
the unit cube, constant mean, Matern 5/2 with ARD lengthscales under the dimension-scaled
log-normal prior of :mod:`bo.surrogate.gp`), the likelihood Bernoulli with a probit link, the
posterior variational with the distinct training points as inducing points (the exact posterior
family for this likelihood), fitted by the variational ELBO with Adam from a fixed start, so a fit
is deterministic for given data. ``JamModel.probability(X [m, d]) -> [m]`` is the predictive
``P(jam)``, which averages the probit over the latent posterior: far from every jam it falls to
the base rate the constant mean learned, never to an overconfident 0.

:func:`expected_objective` composes it with an objective surrogate: one run at ``x`` is a flowing
run of objective ``f(x)`` with probability ``1 - p(x)`` and a jammed one of objective ``f_jam``
(Eq. 7 of the jammed runs' KPIs) with probability ``p(x)``, so the expected objective of a run is
``(1 - p) f + p f_jam``. The GA minimises that (``bo.surrogate.ga.repeated_ga(jam=...)``). A
scalar surrogate of Eq. 7 already scores a point with a jammed run as the worst miss of those that
flowed (``bo.calibration.pipeline._objective_data``); the expected objective adds the risk on top
of that, so on the scalar strategy the GA keeps further from the jams than the risk alone asks.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import gpytorch
import numpy as np
import torch
from gpytorch.constraints import GreaterThan
from gpytorch.kernels import MaternKernel, ScaleKernel
from gpytorch.likelihoods import BernoulliLikelihood
from gpytorch.means import ConstantMean
from gpytorch.models import ApproximateGP
from gpytorch.variational import CholeskyVariationalDistribution, VariationalStrategy

from bo.surrogate.gp import _MIN_LENGTHSCALE, _lengthscale_prior, as_bounds
from torchdem.errors import ConfigError

DTYPE = torch.float64

#: Adam steps of the variational fit (its ELBO changes by less than 1e-4 over the last 100 on a
#: campaign's 170 points and 6 jams).
ITERATIONS = 400


class _Classifier(ApproximateGP):
    def __init__(self, inducing: torch.Tensor):
        d = inducing.shape[1]
        prior = _lengthscale_prior(d)
        strategy = VariationalStrategy(self, inducing, CholeskyVariationalDistribution(inducing.shape[0]),
                                       learn_inducing_locations=False)
        super().__init__(strategy)
        self.mean_module = ConstantMean()
        self.covar_module = ScaleKernel(MaternKernel(
            nu=2.5, ard_num_dims=d, lengthscale_prior=prior,
            lengthscale_constraint=GreaterThan(_MIN_LENGTHSCALE, transform=None, initial_value=prior.mode)))

    def forward(self, x):
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))


@dataclass(frozen=True)
class JamModel:
    """``P(jam | x)`` of one run (see the module docstring).

    Attributes:
        bounds: ``[2, d]`` the box the inputs were normalised with.
        n_runs: runs it was fitted on; n_jammed: of them, jammed.
    """

    model: _Classifier
    likelihood: BernoulliLikelihood
    bounds: np.ndarray
    n_runs: int
    n_jammed: int

    def probability(self, X) -> np.ndarray:
        """``[m]`` predictive probability that one run at each row of ``X [m, d]`` jams."""
        x = torch.as_tensor(np.atleast_2d(np.asarray(X, dtype=np.float64)), dtype=DTYPE)
        b = torch.as_tensor(self.bounds, dtype=DTYPE)
        with torch.no_grad(), gpytorch.settings.fast_computations(False):
            p = self.likelihood(self.model((x - b[0]) / (b[1] - b[0]))).probs
        return p.numpy().astype(np.float64)


def fit_jam_model(X, jammed, bounds, *, iterations: int = ITERATIONS) -> JamModel | None:
    """``P(jam | x)`` from ``X [n, d]`` and ``jammed [n, r]`` (bool, or float with NaN where a run
    was not made); None when no run jammed (nothing to learn, and every objective stays as it was)."""
    src = "fit_jam_model"
    b = as_bounds(bounds)
    x = np.asarray(X, dtype=np.float64)
    j = np.asarray(jammed, dtype=np.float64)
    if j.ndim == 1:
        j = j[:, None]
    if x.ndim != 2 or x.shape[1] != b.shape[1] or j.shape[0] != x.shape[0]:
        raise ConfigError(f"{src}: X of shape {x.shape} and jammed of shape {j.shape} are not allowed; "
                          f"expected X [n, {b.shape[1]}] and jammed [n, r] with the same n")
    ran = np.isfinite(j)
    if not np.isin(j[ran], (0.0, 1.0)).all():
        raise ConfigError(f"{src}: jammed holds {sorted(set(j[ran].tolist()) - {0.0, 1.0})[:3]}; expected 0/1 "
                          "(or NaN for a run not made)")
    rows = np.repeat(np.arange(x.shape[0]), ran.sum(axis=1))
    target = j[ran]
    if not target.any():
        return None
    unit = (x - b[0]) / (b[1] - b[0])
    inducing = torch.as_tensor(np.unique(unit, axis=0), dtype=DTYPE)
    train_x = torch.as_tensor(unit[rows], dtype=DTYPE)
    train_y = torch.as_tensor(target, dtype=DTYPE)
    with torch.random.fork_rng():
        torch.manual_seed(0)
        model = _Classifier(inducing).to(DTYPE)
        likelihood = BernoulliLikelihood().to(DTYPE)
        rate = float(target.mean())
        model.mean_module.constant.data.fill_(float(torch.distributions.Normal(0.0, 1.0).icdf(
            torch.tensor(rate, dtype=DTYPE))))
        model.train(), likelihood.train()
        mll = gpytorch.mlls.VariationalELBO(likelihood, model, num_data=train_y.numel())
        opt = torch.optim.Adam([*model.parameters(), *likelihood.parameters()], lr=0.05)
        with gpytorch.settings.fast_computations(False):
            for _ in range(iterations):
                opt.zero_grad()
                loss = -mll(model(train_x), train_y)
                loss.backward()
                opt.step()
        model.eval(), likelihood.eval()
    return JamModel(model=model, likelihood=likelihood, bounds=b, n_runs=int(target.size),
                    n_jammed=int(target.sum()))


def expected_objective(objective: Callable[[np.ndarray], np.ndarray], jam: JamModel | None,
                       jammed_objective: float) -> Callable[[np.ndarray], np.ndarray]:
    """``X [m, d] -> [m]``: ``(1 - p) objective(X) + p jammed_objective`` with ``p`` the jam
    probability of one run; ``objective`` itself when ``jam`` is None."""
    if jam is None:
        return objective

    def fitness(X: np.ndarray) -> np.ndarray:
        p = jam.probability(X)
        return (1.0 - p) * np.asarray(objective(X), dtype=np.float64) + p * jammed_objective

    return fitness
