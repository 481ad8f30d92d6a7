"""Gaussian-process surrogates of the calibration objective, cross-validated R^2, kernel choice.

Contract
--------
Data (NumPy, float64): ``X [n, d]`` DEM parameter sets inside ``bounds [2, d]`` (row 0 lower,
row 1 upper, ``lower < upper``; ``as_bounds`` validates, also accepting a ``ParameterTable``),
and either

* strategy ``"scalar"``: ``y [n]`` objective values (Eq. 7), one GP on them; or
* strategy ``"per_kpi"``: ``y [n, M]`` KPI values in ``ObjectiveSpec.kpi_names`` order, one
  independent GP per KPI (a batched multi-output ``SingleTaskGP``), the objective composed from
  their posteriors.

Optional ``y_var`` (same shape as ``y``) is the variance *of the mean* of the DEM replicates
at each point (``replicate_mean_and_variance`` computes it, ``sample variance / r``). With it
the GP uses fixed heteroscedastic observation noise ``max(y_var, noise_floor * var(y))``;
without it one homoscedastic noise level is learned. ``objective_from_replicates`` turns KPI
replicates into objective means and variances for the scalar strategy.

Every GP (``fit_surrogate``): double precision; inputs normalised to the unit cube with the
given bounds (``Normalize``), outcomes standardised (``Standardize``); constant mean; kernel
``ScaleKernel(base)`` with ARD base kernel chosen by name from ``KERNELS``:
``"exponential"`` (Matern 1/2), ``"squared_exponential"`` (RBF), ``"rational_quadratic"``,
``"matern52"``. Lengthscales carry the dimension-scaled log-normal prior of Hvarfner et al.
(2024) (BoTorch's default for ``SingleTaskGP``) and a lower bound of 0.025 in unit-cube units;
learned noise has a log-normal prior (mode ~1e-4 of the standardised variance) and a floor of
1e-4. Hyperparameters maximise the marginal log likelihood (``fit_gpytorch_mll``, L-BFGS-B).
The fit is deterministic for given data and ``seed``: ``seed=None`` starts from the prior
modes; an integer seed additionally fits from starting lengthscales drawn from the prior and
keeps whichever fit has the higher log marginal likelihood (plus log prior) -- a different
"training" of the same data, used for the GA repetitions of Table 9, that cannot be worse
than the prior-mode fit.

``Surrogate`` exposes the narrow interface the acquisition and GA code need:
``predict_mean(X [n, d]) -> [n]`` objective mean (NumPy; no grad, batched),
``predict_mean_tensor(X [..., d]) -> [...]`` (torch, double, differentiable),
``mc_objective()`` (a ``GenericMCObjective`` mapping posterior samples to the *negated*
objective so that maximising acquisition functions minimise it), ``observed_objective()``
(objective values at the training points), ``hyperparameters()`` (plain data).
For ``"per_kpi"`` the posterior mean of the objective at each point is a Monte-Carlo average of
Eq. 7 over ``n_mc_samples`` draws from the (independent, latent) KPI marginal posteriors using
fixed scrambled-Sobol normal base samples, so it is a deterministic, smooth function of X.

Cross-validation (``cross_validate``): points are assigned to ``n_folds`` folds by a seeded
permutation (``fold_assignment``); for every fold a GP is refitted on the other folds and
predicts the held-out points; R^2 = 1 - SS_res / SS_tot over all held-out predictions pooled.
For ``"per_kpi"`` the prediction is the composed objective mean and the actual value is Eq. 7
of the held-out KPIs. ``cross_validated_r2`` repeats this over seeds (default 5, as Table 7)
and reports mean and standard deviation (population std, ``ddof=0``); ``select_kernel`` picks
the kernel with the highest mean CV R^2 (ties: first in the given order).

The noise ceiling (``objective_noise_variance``, ``r2_ceiling``): a held-out value carries its
own DEM noise, which no surrogate can predict, so even the noise-free objective scores only
``E[R^2] = 1 - mean(noise variance) / var(actual)`` in cross-validation. With ``y_var`` known
(replicates or pooled replicate scatter) the ceiling follows from the data alone: for
``"scalar"`` the noise variance of a point is its ``y_var``; for ``"per_kpi"`` it is the
variance of Eq. 7 of ``y + e``, ``e ~ N(0, diag y_var)``, by fixed-seed Monte Carlo (the
delta method fails where a KPI sits on its measured value, at the kink of ``|.|``).
``R^2 / ceiling`` is the share of the explainable variance the surrogate explains.
``learned_noise_ceiling`` takes the noise instead from a GP that learns one noise level per
output on the points themselves (``noise * y_std^2``, back from the standardised units): where
the points' own noise is smaller than the given ``y_var`` (a surrogate's points, gathered where
the flow is steady, against a screening's corners), the ceiling from ``y_var`` is too low and a
CV R^2 can exceed it.

Paper: Hadi, Pang, Schott, section 3.4.3, Eqs. 9-15, Tables 7 and A.2.
"""
from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import torch
from botorch.acquisition.objective import GenericMCObjective
from botorch.fit import fit_gpytorch_mll
from botorch.models import SingleTaskGP
from botorch.models.transforms.input import Normalize
from botorch.models.transforms.outcome import Standardize
from gpytorch.constraints import GreaterThan
from gpytorch.kernels import MaternKernel, RBFKernel, RQKernel, ScaleKernel
from gpytorch.likelihoods import GaussianLikelihood
from gpytorch.mlls import ExactMarginalLogLikelihood
from gpytorch.priors import LogNormalPrior

from bo.design.dsd import ParameterTable
from bo.surrogate.objective import ObjectiveSpec
from torchdem.errors import ConfigError, out_of_range

__all__ = [
    "KERNELS",
    "STRATEGIES",
    "SurrogateConfig",
    "Surrogate",
    "CVResult",
    "CVSummary",
    "KernelSelection",
    "as_bounds",
    "replicate_mean_and_variance",
    "objective_from_replicates",
    "make_kernel",
    "fit_surrogate",
    "fold_assignment",
    "r2_score",
    "cross_validate",
    "cross_validated_r2",
    "select_kernel",
    "objective_noise_variance",
    "r2_ceiling",
    "learned_noise_ceiling",
]

DTYPE = torch.float64

#: Kernel names accepted by ``SurrogateConfig.kernel`` (paper Table A.2).
KERNELS: tuple[str, ...] = ("exponential", "squared_exponential", "rational_quadratic",
                            "matern52")
#: Surrogate strategies: one GP on the objective, or one GP per KPI composed by Eq. 7.
STRATEGIES: tuple[str, ...] = ("scalar", "per_kpi")

_MIN_LENGTHSCALE = 0.025   # unit-cube units, as BoTorch's default kernel
_MIN_LEARNED_NOISE = 1e-4  # standardised units, as BoTorch's default likelihood
_PREDICT_CHUNK = 4096      # points per posterior call in predict_mean


@dataclass(frozen=True)
class SurrogateConfig:
    """How to build a surrogate.

    Attributes:
        kernel: one of ``KERNELS``.
        strategy: one of ``STRATEGIES``; ``"per_kpi"`` needs an ``ObjectiveSpec``.
        n_mc_samples: Monte-Carlo samples for the composed objective mean (``"per_kpi"``),
            >= 16.
        noise_floor: lower bound of a fixed observation-noise variance as a fraction of
            ``var(y)`` (per output), >= 0; keeps the kernel matrix well conditioned when
            replicates agree exactly.
    """

    kernel: str = "matern52"
    strategy: str = "scalar"
    n_mc_samples: int = 512
    noise_floor: float = 1e-6

    def __post_init__(self) -> None:
        src = "SurrogateConfig"
        if self.kernel not in KERNELS:
            raise out_of_range("kernel", self.kernel, f"one of {list(KERNELS)}", src)
        if self.strategy not in STRATEGIES:
            raise out_of_range("strategy", self.strategy, f"one of {list(STRATEGIES)}", src)
        if isinstance(self.n_mc_samples, bool) or not isinstance(self.n_mc_samples, int) \
                or self.n_mc_samples < 16:
            raise out_of_range("n_mc_samples", self.n_mc_samples, "an integer >= 16", src)
        if not (math.isfinite(self.noise_floor) and self.noise_floor >= 0):
            raise out_of_range("noise_floor", self.noise_floor, "a finite fraction >= 0", src)


# --------------------------------------------------------------------------------------------
# Input validation
# --------------------------------------------------------------------------------------------

def as_bounds(bounds, source: str = "bounds") -> np.ndarray:
    """Validated box ``[2, d]`` (float64, fresh copy): row 0 lower, row 1 upper, lower < upper.

    Accepts an array-like ``[2, d]`` or a ``ParameterTable`` (its low and high levels).
    """
    if isinstance(bounds, ParameterTable):
        b = np.array([bounds.low, bounds.high], dtype=np.float64)
    else:
        try:
            b = np.array(bounds, dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise ConfigError(f"{source}: bounds = {bounds!r} must be numbers of shape [2, d]"
                              ) from err
    if b.ndim != 2 or b.shape[0] != 2 or b.shape[1] < 1:
        raise ConfigError(f"{source}: bounds have shape {b.shape}; expected [2, d] (row 0 lower "
                          f"bounds, row 1 upper bounds, d >= 1 parameters)")
    if not np.all(np.isfinite(b)):
        raise ConfigError(f"{source}: bounds contain non-finite values {b.tolist()}; expected "
                          f"finite numbers")
    bad = np.flatnonzero(~(b[0] < b[1]))
    if bad.size:
        j = int(bad[0])
        raise ConfigError(f"{source}: bounds of parameter {j} are lower = {float(b[0, j])!r}, "
                          f"upper = {float(b[1, j])!r}; expected lower < upper (are the bounds "
                          f"inverted?)")
    return b


def _as_points(X, d: int, name: str, source: str, bounds: np.ndarray | None = None
               ) -> np.ndarray:
    x = np.asarray(X, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != d:
        raise ConfigError(f"{source}: {name} has shape {x.shape}; expected [n, {d}] (one column "
                          f"per parameter)")
    if not np.all(np.isfinite(x)):
        raise ConfigError(f"{source}: {name} contains non-finite values at rows "
                          f"{sorted(set(np.argwhere(~np.isfinite(x))[:, 0].tolist()))[:5]}")
    if bounds is not None:
        tol = 1e-9 * (bounds[1] - bounds[0])
        outside = (x < bounds[0] - tol) | (x > bounds[1] + tol)
        if outside.any():
            i, j = map(int, np.argwhere(outside)[0])
            raise ConfigError(f"{source}: {name}[{i}, {j}] = {float(x[i, j])!r} is outside the "
                              f"bounds [{float(bounds[0, j])!r}, {float(bounds[1, j])!r}] of "
                              f"parameter {j}")
    return x


def _validate_data(X, y, bounds, config: SurrogateConfig, y_var, objective: ObjectiveSpec | None,
                   source: str, min_points: int = 2):
    """Checked float64 copies ``(bounds [2,d], X [n,d], Y [n,m], Yvar [n,m] | None)``."""
    b = as_bounds(bounds, source)
    d = b.shape[1]
    x = _as_points(X, d, "X", source, b)
    n = x.shape[0]
    yy = np.asarray(y, dtype=np.float64)
    if config.strategy == "scalar":
        if yy.ndim == 2 and yy.shape[1] == 1:
            yy = yy[:, 0]
        if yy.shape != (n,):
            raise ConfigError(f"{source}: y has shape {yy.shape}; expected [{n}] objective values "
                              f"(strategy 'scalar', one per row of X)")
        yy = yy[:, None]
    else:
        if objective is None:
            raise ConfigError(f"{source}: strategy 'per_kpi' needs an ObjectiveSpec (objective="
                              f"...) to compose the KPIs; got objective = None")
        m = objective.n_kpis
        if yy.shape != (n, m):
            raise ConfigError(f"{source}: y has shape {yy.shape}; expected [{n}, {m}] KPI values "
                              f"(strategy 'per_kpi', columns {list(objective.kpi_names)})")
    if n < min_points:
        raise out_of_range("number of points", n, f">= {min_points}", source)
    if not np.all(np.isfinite(yy)):
        raise ConfigError(f"{source}: y contains non-finite values at rows "
                          f"{sorted(set(np.argwhere(~np.isfinite(yy))[:, 0].tolist()))[:5]}")
    yv = None
    if y_var is not None:
        yv = np.asarray(y_var, dtype=np.float64).reshape(-1, 1) if config.strategy == "scalar" \
            else np.asarray(y_var, dtype=np.float64)
        if yv.shape != yy.shape:
            raise ConfigError(f"{source}: y_var has shape {np.shape(y_var)}; expected the shape "
                              f"of y, {np.asarray(y).shape}")
        if not np.all(np.isfinite(yv)) or np.any(yv < 0):
            raise ConfigError(f"{source}: y_var must be finite variances >= 0 (variance of the "
                              f"replicate mean); got min {np.nanmin(yv)!r}")
    return b, x, yy, yv


# --------------------------------------------------------------------------------------------
# Replicates
# --------------------------------------------------------------------------------------------

def replicate_mean_and_variance(replicates, axis: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Mean over DEM replicates and the variance of that mean (``s^2 / r``, ``ddof=1``).

    ``replicates`` is e.g. ``[n, r]`` (objective) or ``[n, r, M]`` (KPIs) with ``r >= 2``
    replicates along ``axis``.
    """
    a = np.asarray(replicates, dtype=np.float64)
    if a.ndim < 2 or a.shape[axis] < 2:
        raise ConfigError(f"replicate_mean_and_variance: replicates have shape {a.shape}; "
                          f"expected >= 2 replicates along axis {axis} (e.g. [n, r] or [n, r, M])")
    r = a.shape[axis]
    return a.mean(axis=axis), a.var(axis=axis, ddof=1) / r


def objective_from_replicates(objective: ObjectiveSpec, kpi_replicates
                              ) -> tuple[np.ndarray, np.ndarray]:
    """Objective value and its variance per point from KPI replicates ``[n, r, M]``.

    The value is Eq. 7 of the replicate-mean KPIs (the paper averages the KPIs, then forms the
    objective). Its variance is the delta-method variance of that mean: Eq. 7 linearised at
    the mean KPIs (gradient ``w_m sign(ybar_m - y_Exp,m) / |y_Exp,m|``) applied to every
    replicate, sample variance over replicates (so KPI covariances count) divided by ``r``.
    """
    a = np.asarray(kpi_replicates, dtype=np.float64)
    m = objective.n_kpis
    if a.ndim != 3 or a.shape[1] < 2 or a.shape[2] != m:
        raise ConfigError(f"objective_from_replicates: kpi_replicates have shape {a.shape}; "
                          f"expected [n, r >= 2, {m}] (KPIs {list(objective.kpi_names)})")
    mean = a.mean(axis=1)
    measured = np.asarray(objective.measured)
    grad = np.asarray(objective.weights) * np.sign(mean - measured) / np.abs(measured)  # [n, M]
    linear = np.einsum("nrm,nm->nr", a, grad)
    return objective(mean), linear.var(axis=1, ddof=1) / a.shape[1]


# --------------------------------------------------------------------------------------------
# Kernels and models
# --------------------------------------------------------------------------------------------

def _lengthscale_prior(d: int) -> LogNormalPrior:
    # Hvarfner et al. (2024): log-lengthscale ~ N(sqrt(2) + log(d) / 2, 3).
    return LogNormalPrior(loc=math.sqrt(2.0) + 0.5 * math.log(d), scale=math.sqrt(3.0))


def make_kernel(name: str, d: int, batch_shape: torch.Size = torch.Size()) -> ScaleKernel:
    """``ScaleKernel`` over an ARD base kernel named in ``KERNELS``, for unit-cube inputs."""
    if name not in KERNELS:
        raise out_of_range("kernel", name, f"one of {list(KERNELS)}", "make_kernel")
    prior = _lengthscale_prior(d)
    common = dict(ard_num_dims=d, batch_shape=batch_shape, lengthscale_prior=prior,
                  lengthscale_constraint=GreaterThan(_MIN_LENGTHSCALE, transform=None,
                                                     initial_value=prior.mode))
    if name == "exponential":
        base = MaternKernel(nu=0.5, **common)
    elif name == "matern52":
        base = MaternKernel(nu=2.5, **common)
    elif name == "squared_exponential":
        base = RBFKernel(**common)
    else:
        base = RQKernel(**common)
    return ScaleKernel(base, batch_shape=batch_shape)


def _build_model(x: np.ndarray, yy: np.ndarray, yv: np.ndarray | None, b: np.ndarray,
                 config: SurrogateConfig) -> SingleTaskGP:
    n, d = x.shape
    m = yy.shape[1]
    batch = torch.Size([m]) if m > 1 else torch.Size()
    train_x = torch.as_tensor(x, dtype=DTYPE)
    train_y = torch.as_tensor(yy, dtype=DTYPE)
    train_yvar = None
    likelihood = None
    if yv is not None:
        floor = config.noise_floor * np.maximum(yy.var(axis=0, ddof=1), 1e-300)
        train_yvar = torch.as_tensor(np.maximum(yv, floor[None, :]), dtype=DTYPE)
    else:
        noise_prior = LogNormalPrior(loc=-4.0, scale=1.0)
        likelihood = GaussianLikelihood(
            noise_prior=noise_prior, batch_shape=batch,
            noise_constraint=GreaterThan(_MIN_LEARNED_NOISE, transform=None,
                                         initial_value=noise_prior.mode))
    return SingleTaskGP(
        train_x, train_y, train_Yvar=train_yvar, likelihood=likelihood,
        covar_module=make_kernel(config.kernel, d, batch),
        outcome_transform=Standardize(m=m),
        input_transform=Normalize(d=d, bounds=torch.as_tensor(b, dtype=DTYPE)),
    )


def _fit(model: SingleTaskGP, seed: int | None) -> float:
    """Maximise the marginal likelihood in place; return the final log MAP value."""
    with torch.random.fork_rng():
        torch.manual_seed(0 if seed is None else seed)
        if seed is not None:  # a different "training": start from a prior draw
            base = model.covar_module.base_kernel
            draw = base.lengthscale_prior.sample(base.lengthscale.shape)
            base.lengthscale = draw.clamp(2 * _MIN_LENGTHSCALE, 20.0).to(DTYPE)
        mll = ExactMarginalLogLikelihood(model.likelihood, model)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fit_gpytorch_mll(mll)
        model.train()
        with torch.no_grad():
            value = float(mll(model(*model.train_inputs), model.train_targets).sum())
    model.eval()
    return value


@dataclass(frozen=True, eq=False)
class Surrogate:
    """A fitted surrogate of the objective (see the module docstring).

    Attributes:
        model: the fitted BoTorch model (outputs: 1 objective or M KPIs), in eval mode.
        config: how it was built.
        bounds: ``[2, d]`` box used to normalise inputs.
        train_X: ``[n, d]`` training inputs; train_Y: ``[n, m]`` training outputs
            (m = 1 scalar, M per_kpi); train_Yvar: ``[n, m]`` fixed noise or None.
        objective: the ``ObjectiveSpec`` (required for ``"per_kpi"``, optional otherwise).
        seed: the training seed (None = prior-mode start).
    """

    model: SingleTaskGP
    config: SurrogateConfig
    bounds: np.ndarray
    train_X: np.ndarray
    train_Y: np.ndarray
    train_Yvar: np.ndarray | None
    objective: ObjectiveSpec | None
    seed: int | None
    _base_samples: torch.Tensor | None = field(default=None, repr=False)

    @property
    def d(self) -> int:
        return self.bounds.shape[1]

    def observed_objective(self) -> np.ndarray:
        """Objective values ``[n]`` of the training data (Eq. 7 of the KPIs for per_kpi)."""
        if self.config.strategy == "scalar":
            return self.train_Y[:, 0].copy()
        return self.objective(self.train_Y)

    def compose(self, samples: torch.Tensor) -> torch.Tensor:
        """Objective of model outputs ``[..., m] -> [...]`` (identity for scalar)."""
        if self.config.strategy == "scalar":
            return samples[..., 0]
        return self.objective(samples)

    def mc_objective(self) -> GenericMCObjective:
        """MC objective for BoTorch acquisition functions: samples ``[..., q, m] -> [..., q]``,
        the *negated* objective, so maximising the acquisition minimises Eq. 7."""
        return GenericMCObjective(lambda samples, X=None: -self.compose(samples))

    def predict_mean_tensor(self, X: torch.Tensor) -> torch.Tensor:
        """Posterior mean of the objective at ``X [..., d]`` (double), shape ``[...]``.

        Scalar: the GP posterior mean. per_kpi: MC average of Eq. 7 over the KPI marginal
        posteriors with fixed base samples (deterministic in X, differentiable).
        """
        X = X.to(DTYPE)
        post = self.model.posterior(X.unsqueeze(-2))  # marginals: batch [...], q = 1
        mean = post.mean.squeeze(-2)  # [..., m]
        if self.config.strategy == "scalar":
            return mean[..., 0]
        std = post.variance.squeeze(-2).clamp_min(0.0).sqrt()
        eps = self._base_samples.to(device=X.device)  # [S, m]
        eps = eps.view(eps.shape[0], *([1] * (mean.dim() - 1)), eps.shape[-1])
        return self.objective(mean + std * eps).mean(dim=0)

    def predict_mean(self, X) -> np.ndarray:
        """Objective posterior mean ``[n]`` at ``X [n, d]`` (NumPy; no grad; chunked batches)."""
        x = _as_points(X, self.d, "X", "Surrogate.predict_mean")
        out = np.empty(x.shape[0])
        with torch.no_grad():
            for start in range(0, x.shape[0], _PREDICT_CHUNK):
                chunk = torch.as_tensor(x[start:start + _PREDICT_CHUNK], dtype=DTYPE)
                out[start:start + _PREDICT_CHUNK] = self.predict_mean_tensor(chunk).numpy()
        return out

    def predict_outputs(self, X) -> tuple[np.ndarray, np.ndarray]:
        """Latent posterior mean and variance of the model outputs, each ``[n, m]``."""
        x = _as_points(X, self.d, "X", "Surrogate.predict_outputs")
        with torch.no_grad():
            post = self.model.posterior(torch.as_tensor(x, dtype=DTYPE).unsqueeze(-2))
            return post.mean.squeeze(-2).numpy(), post.variance.squeeze(-2).numpy()

    def hyperparameters(self) -> dict:
        """Fitted hyperparameters as plain data (NumPy arrays; per output for per_kpi).

        Keys: ``kernel``, ``lengthscale [m, d]`` (unit-cube units), ``outputscale [m]``,
        ``mean_constant [m]``, ``noise [m]`` (learned, standardised units) or None,
        ``alpha [m]`` (rational quadratic only) or None, ``y_mean [m]``, ``y_std [m]``
        (the Standardize constants).
        """
        model = self.model
        m = self.train_Y.shape[1]
        covar = model.covar_module
        base = covar.base_kernel
        ot = model.outcome_transform

        def rows(t: torch.Tensor, width: int | None = None) -> np.ndarray:
            a = t.detach().numpy()
            return a.reshape(m, width) if width else a.reshape(m)

        learned = self.train_Yvar is None
        return {
            "kernel": self.config.kernel,
            "lengthscale": rows(base.lengthscale, self.d),
            "outputscale": rows(covar.outputscale),
            "mean_constant": rows(model.mean_module.constant),
            "noise": rows(model.likelihood.noise.reshape(m, -1)[:, 0]) if learned else None,
            "alpha": rows(base.alpha) if isinstance(base, RQKernel) else None,
            "y_mean": rows(ot.means),
            "y_std": rows(ot.stdvs),
        }


def fit_surrogate(X, y, bounds, config: SurrogateConfig = SurrogateConfig(), *, y_var=None,
                  objective: ObjectiveSpec | None = None, seed: int | None = None) -> Surrogate:
    """Fit a GP surrogate (see the module docstring for shapes, transforms and noise)."""
    b, x, yy, yv = _validate_data(X, y, bounds, config, y_var, objective, "fit_surrogate")
    model = _build_model(x, yy, yv, b, config)
    value = _fit(model, None)
    if seed is not None:
        # Another training from a random start; keep it only if its likelihood is higher, so
        # a bad local optimum can never replace the prior-mode fit.
        other = _build_model(x, yy, yv, b, config)
        if _fit(other, seed) > value:
            model = other
    base = None
    if config.strategy == "per_kpi":
        sobol = torch.quasirandom.SobolEngine(dimension=yy.shape[1], scramble=True, seed=0)
        u = sobol.draw(config.n_mc_samples, dtype=DTYPE).clamp(1e-10, 1 - 1e-10)
        base = torch.distributions.Normal(0.0, 1.0).icdf(u)
    return Surrogate(model=model, config=config, bounds=b, train_X=x, train_Y=yy,
                     train_Yvar=yv, objective=objective, seed=seed, _base_samples=base)


# --------------------------------------------------------------------------------------------
# Cross-validation and kernel selection
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class CVResult:
    """One k-fold cross-validation: pooled held-out predictions.

    Attributes:
        r2: ``1 - SS_res / SS_tot`` over all held-out points.
        actual: ``[n]`` objective values of the data; predicted: ``[n]`` held-out predictions.
        folds: ``[n]`` fold index of each point; seed: the fold-assignment seed; kernel.
        fold_hyperparameters: ``Surrogate.hyperparameters()`` of the GP fitted without fold
            k, for k = 0 .. n_folds - 1 (plain data, for records and independent checks).
    """

    r2: float
    actual: np.ndarray
    predicted: np.ndarray
    folds: np.ndarray
    seed: int
    kernel: str
    fold_hyperparameters: tuple[dict, ...] = ()


@dataclass(frozen=True)
class CVSummary:
    """CV R^2 over several fold-assignment seeds (Table 7: mean +- std over 5 seeds)."""

    kernel: str
    mean: float
    std: float
    per_seed: tuple[float, ...]
    results: tuple[CVResult, ...]


@dataclass(frozen=True)
class KernelSelection:
    """Kernel with the highest mean CV R^2 and the summary of every candidate."""

    best: str
    summaries: dict

    @property
    def best_summary(self) -> CVSummary:
        return self.summaries[self.best]


def fold_assignment(n: int, n_folds: int, seed: int) -> np.ndarray:
    """Fold index ``[n]`` in ``0..n_folds-1``: a seeded permutation dealt round-robin, so fold
    sizes differ by at most one. ``2 <= n_folds <= n``."""
    src = "fold_assignment"
    if isinstance(n_folds, bool) or not isinstance(n_folds, (int, np.integer)) or n_folds < 2:
        raise out_of_range("n_folds", n_folds, "an integer >= 2", src)
    if n_folds > n:
        raise out_of_range("n_folds", n_folds, f"<= the number of points ({n})", src)
    folds = np.empty(n, dtype=np.int64)
    folds[np.random.default_rng(seed).permutation(n)] = np.arange(n) % n_folds
    return folds


def r2_score(actual, predicted) -> float:
    """Coefficient of determination ``1 - sum (a - p)^2 / sum (a - mean a)^2``."""
    a = np.asarray(actual, dtype=np.float64)
    p = np.asarray(predicted, dtype=np.float64)
    ss_tot = float(np.sum((a - a.mean()) ** 2))
    if ss_tot == 0.0:
        raise ConfigError("r2_score: actual values are all equal; R^2 is undefined")
    return 1.0 - float(np.sum((a - p) ** 2)) / ss_tot


def cross_validate(X, y, bounds, config: SurrogateConfig = SurrogateConfig(), *, y_var=None,
                   objective: ObjectiveSpec | None = None, n_folds: int = 5, seed: int = 0,
                   fit_seed: int | None = None) -> CVResult:
    """k-fold CV of the surrogate (refitted per fold); see the module docstring."""
    src = "cross_validate"
    b, x, yy, yv = _validate_data(X, y, bounds, config, y_var, objective, src)
    folds = fold_assignment(x.shape[0], n_folds, seed)
    predicted = np.empty(x.shape[0])
    hyper = []
    for k in range(n_folds):
        test = folds == k
        train = ~test
        yk = yy[train] if config.strategy == "per_kpi" else yy[train, 0]
        yvk = None if yv is None else (yv[train] if config.strategy == "per_kpi"
                                       else yv[train, 0])
        model = fit_surrogate(x[train], yk, b, config, y_var=yvk, objective=objective,
                              seed=fit_seed)
        predicted[test] = model.predict_mean(x[test])
        hyper.append(model.hyperparameters())
    actual = yy[:, 0] if config.strategy == "scalar" else objective(yy)
    return CVResult(r2=r2_score(actual, predicted), actual=actual, predicted=predicted,
                    folds=folds, seed=seed, kernel=config.kernel,
                    fold_hyperparameters=tuple(hyper))


def cross_validated_r2(X, y, bounds, config: SurrogateConfig = SurrogateConfig(), *, y_var=None,
                       objective: ObjectiveSpec | None = None, n_folds: int = 5,
                       seeds: Sequence[int] = (0, 1, 2, 3, 4)) -> CVSummary:
    """CV R^2 mean and std (``ddof=0``) over fold-assignment ``seeds`` (Table 7)."""
    seeds = tuple(seeds)
    if not seeds:
        raise out_of_range("seeds", seeds, "at least one seed", "cross_validated_r2")
    results = tuple(cross_validate(X, y, bounds, config, y_var=y_var, objective=objective,
                                   n_folds=n_folds, seed=s) for s in seeds)
    r2 = np.array([r.r2 for r in results])
    return CVSummary(kernel=config.kernel, mean=float(r2.mean()), std=float(r2.std()),
                     per_seed=tuple(float(v) for v in r2), results=results)


def objective_noise_variance(y, y_var, objective: ObjectiveSpec | None = None, strategy: str = "scalar", *,
                             n_samples: int = 4096, seed: int = 0) -> np.ndarray:
    """``[n]`` noise variance of the objective value of each point (see the module docstring).

    ``y``/``y_var``: ``[n]`` objective values and their variances (``"scalar"``), or ``[n, M]``
    KPI means and their variances (``"per_kpi"``, with ``objective``)."""
    src = "objective_noise_variance"
    if strategy not in STRATEGIES:
        raise out_of_range("strategy", strategy, f"one of {list(STRATEGIES)}", src)
    yy = np.asarray(y, dtype=np.float64)
    vv = np.asarray(y_var, dtype=np.float64)
    if vv.shape != yy.shape:
        raise ConfigError(f"{src}: y_var has shape {vv.shape}; expected the shape of y {yy.shape}")
    if not np.all(np.isfinite(vv)) or np.any(vv < 0):
        raise out_of_range("y_var", vv[~(np.isfinite(vv) & (vv >= 0))][:3].tolist(), "finite values >= 0", src)
    if strategy == "scalar":
        return vv.reshape(-1).copy()
    if objective is None or yy.ndim != 2 or yy.shape[1] != objective.n_kpis:
        raise ConfigError(f"{src}: strategy 'per_kpi' needs y of shape [n, M] and objective=ObjectiveSpec(...) "
                          f"with M KPIs; got y of shape {yy.shape}")
    e = np.random.default_rng(seed).standard_normal((n_samples, 1, yy.shape[1]))
    samples = np.asarray(objective(yy[None] + e * np.sqrt(vv)[None]))  # [S, n]
    return samples.var(axis=0, ddof=1)


def r2_ceiling(actual, noise_var) -> float:
    """Expected CV R^2 of a surrogate that predicts the noise-free objective exactly:
    ``1 - mean(noise_var) / var(actual)`` (``actual [n]`` objective values, ``noise_var [n]``
    their noise variances). At most 1; may be <= 0 where noise swamps the design's spread."""
    a = np.asarray(actual, dtype=np.float64).reshape(-1)
    v = np.asarray(noise_var, dtype=np.float64).reshape(-1)
    if a.shape != v.shape or a.size < 2:
        raise ConfigError(f"r2_ceiling: {a.size} actual values and {v.size} noise variances; expected as many, >= 2")
    spread = float(a.var())
    if spread == 0.0:
        raise ConfigError("r2_ceiling: actual values are all equal; R^2 is undefined")
    return 1.0 - float(v.mean()) / spread


def learned_noise_ceiling(X, y, bounds, config: SurrogateConfig = SurrogateConfig(), *,
                          objective: ObjectiveSpec | None = None) -> float:
    """``r2_ceiling`` of ``y`` (``[n]`` scalar, ``[n, M]`` per_kpi) with the noise a GP with a
    learned noise level fits to these points (module docstring)."""
    surrogate = fit_surrogate(X, y, bounds, config, y_var=None, objective=objective)
    h = surrogate.hyperparameters()
    per_output = np.asarray(h["noise"], dtype=np.float64) * np.asarray(h["y_std"], dtype=np.float64) ** 2  # [m]
    yy = np.asarray(y, dtype=np.float64)
    noise = np.broadcast_to(per_output if yy.ndim == 2 else per_output[0], yy.shape)
    return r2_ceiling(surrogate.observed_objective(), objective_noise_variance(yy, noise, objective, config.strategy))


def select_kernel(X, y, bounds, config: SurrogateConfig = SurrogateConfig(), *,
                  kernels: Sequence[str] = KERNELS, y_var=None,
                  objective: ObjectiveSpec | None = None, n_folds: int = 5,
                  seeds: Sequence[int] = (0, 1, 2, 3, 4)) -> KernelSelection:
    """Kernel among ``kernels`` with the highest mean CV R^2 (``config`` gives the rest)."""
    kernels = tuple(kernels)
    if not kernels:
        raise out_of_range("kernels", kernels, f"a non-empty subset of {list(KERNELS)}",
                           "select_kernel")
    summaries = {}
    for name in kernels:
        cfg = dataclasses.replace(config, kernel=name)
        summaries[name] = cross_validated_r2(X, y, bounds, cfg, y_var=y_var, objective=objective,
                                             n_folds=n_folds, seeds=seeds)
    best = max(kernels, key=lambda k: summaries[k].mean)  # first wins ties
    return KernelSelection(best=best, summaries=summaries)
