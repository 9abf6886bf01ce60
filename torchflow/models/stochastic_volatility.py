r"""Stochastic volatility: a log-variance that follows a stationary AR(1), returns that are Gaussian
given it.

    x_0 ~ N(mu, sigma^2 / (1 - rho^2))                       (the stationary law)
    x_t - mu = rho (x_{t-1} - mu) + sigma v_t,   v_t ~ N(0, 1)
    y_t | x_t ~ N(0, exp(x_t))

The parametrisation is that of ``particles.state_space_models.StochVol`` (Chopin & Papaspiliopoulos,
*An Introduction to Sequential Monte Carlo*, 2020): the same three names ``mu``, ``rho``, ``sigma``
with the same meaning, and its default parameters (Pitt & Shephard 1999's estimates for the GBP/USD
daily returns): ``mu = -1.02``, ``rho = 0.9702``, ``sigma = 0.178``. One difference of indexing:
particles observes ``y_0`` from ``x_0``, torchflow observes ``z_1`` from ``x_1`` (``x_0`` is the
initial state, never observed). Both ``x_0`` and ``x_1`` have the stationary law, so the laws of the
observed series, and hence the log-likelihoods of one series, are the same.

The measurement is not "a function of the state plus Gaussian noise": the particle filters weigh with
the exact density, and the flows and the Kalman family use one of two Gaussian forms, chosen by
``gaussian_form``:

* ``"returns"`` (default): the observations are the returns y; ``h(x) = 0`` and ``R(x) = exp(x)``.
  This Gaussian form is the exact law, but its measurement function has slope zero: a linearisation
  sees no information about x in y (it sits in R), so a flow does not move the particles and an
  EKF/UKF never updates (:func:`torchflow.proposals.flow.check_informative` warns).
* ``"log_squared"``: the observations are ``z = log(y^2 + offset)`` (:meth:`transform_observations`;
  ``offset = 0`` is the classical transform, a small ``offset > 0`` keeps a zero return finite). For
  ``offset = 0``, ``z = x + log(eps^2)`` with ``eps ~ N(0, 1)``: x plus a ``log chi^2_1`` variable, of
  mean ``psi(1/2) + log 2 = -1.2704`` and variance ``pi^2 / 2``; the Gaussian form is
  ``h(x) = x - 1.2704``, ``R = pi^2 / 2`` (Harvey, Ruiz & Shephard 1994's quasi-likelihood), an
  approximation that moves particles, with slope one.

The weights and the log-evidence are the returns' in both forms. In the log-squared form
:meth:`measurement_log_prob` reads the return's square back from z (``y^2 = exp(z) - offset``) and
gives ``log N(y; 0, exp(x))``: the exact measurement density of y, up to the Jacobian of the
transform, which does not depend on x (so the weights are those of the exact ``log chi^2_1`` density
of z) and which it leaves out, so that a filter's log-evidence is ``log p(y_{1:T})`` whatever the
form, and exact for every return, zero included. The density of z itself is
:meth:`log_squared_log_prob` (``offset = 0``): ``p(z | x) = p(y | x) |y|``, because ``y -> log y^2`` is
two-to-one (``p_z(z) = 2 p_y(y) |dy/dz|`` with ``|dy/dz| = |y| / 2``), so
``log p(z_{1:T}) = log p(y_{1:T}) + sum_t log|y_t|``. The Kalman family's log-evidence in the
log-squared form is that of the Gaussian approximation of z.

Shapes: states ``(..., 1)``, observations ``(..., 1)``.
"""

from __future__ import annotations

import math
from typing import Optional, Tuple

import torch
from torch.distributions import constraints as support

from torchflow.core import constraints, linalg
from torchflow.core.checks import check_choice, check_learnable, check_nonnegative, check_number, check_positive
from torchflow.core.errors import ArgumentError
from torchflow.models.base import GaussianStateSpaceModel
from torchflow.models.structure import Structure
from torchflow.models.trials import per_trial_structure, trial_view

#: E[log chi^2_1] = digamma(1/2) + log 2
LOG_CHI2_MEAN = -1.2703628454614782
#: Var[log chi^2_1] = trigamma(1/2) = pi^2 / 2
LOG_CHI2_VAR = math.pi**2 / 2
LOG_2PI = math.log(2 * math.pi)
#: the Gaussian forms (``gaussian_form``)
FORMS = ("returns", "log_squared")


class StochasticVolatility(GaussianStateSpaceModel):
    r"""Stochastic volatility in ``particles``' parametrisation (module docstring).

    Args:
        mu: mean of the log-variance x (``particles``' ``mu``; -1.02).
        rho: autoregressive coefficient, in (-1, 1) (``rho``; 0.9702).
        sigma: standard deviation of the log-variance's innovation, > 0 (``sigma``; 0.178).
        gaussian_form: ``"returns"`` (the observations are the returns; ``h(x) = 0``,
            ``R(x) = exp(x)``) or ``"log_squared"`` (the observations are ``log(y^2 + offset)``;
            ``h(x) = x - 1.2704``, ``R = pi^2 / 2``).
        offset: the log-squared transform's offset, >= 0 (default 0: exact; a zero return then has
            no finite transform and :meth:`transform_observations` refuses it). Unused by the
            returns form.
        learnable: parameters to learn, a subset of ``["mu", "rho", "sigma"]`` (``True``: all).
            ``mu`` is a plain ``nn.Parameter``; ``rho`` lives in (-1, 1) (a scaled sigmoid) and
            ``sigma`` is positive (its logarithm is learnt), by construction
            (:mod:`torchflow.core.constraints`).

    Structure: a Gaussian, affine transition (not ``linear_dynamics``: the mean has the offset
    ``(1 - rho) mu``); ``m = d = 1`` (a diagonal Jacobian); R state-dependent
    (``exp(x)``, returns form) or the constant scalar ``pi^2 / 2`` (log-squared form).
    """

    state_dim = 1
    obs_dim = 1
    #: mu, rho and sigma may hold one value per trial, ``(B,)`` (MCMC chains: :mod:`torchflow.inference`)
    per_trial_parameters = {"mu": support.real, "rho": support.interval(-1.0, 1.0), "sigma": support.positive}
    structure = Structure(measurement_noise="state_dependent_diagonal", measurement_jacobian_diagonal=True)

    def __init__(
        self,
        *,
        mu: float = -1.02,
        rho: float = 0.9702,
        sigma: float = 0.178,
        gaussian_form: str = "returns",
        offset: float = 0.0,
        learnable=False,
    ):
        super().__init__()
        mu = check_number("mu", mu)
        rho = check_number("rho", rho, lambda v: -1 < v < 1, "a number in (-1, 1) (a stationary AR(1))")
        sigma = check_positive("sigma", sigma)
        self.gaussian_form = check_choice("gaussian_form", gaussian_form, FORMS)
        self.offset = check_nonnegative("offset", offset)
        f64 = dict(dtype=torch.float64)
        for name, value in (("mu", mu), ("rho", rho), ("sigma", sigma)):
            self.register_buffer(name, torch.tensor(value, **f64))
        learn = check_learnable(learnable, ("mu", "rho", "sigma"))
        if "mu" in learn:
            mu_value = self.mu
            del self._buffers["mu"]
            self.mu = torch.nn.Parameter(mu_value)
        if "rho" in learn:
            constraints.constrain(self, "rho", (-1.0, 1.0))
        if "sigma" in learn:
            constraints.constrain(self, "sigma", "positive")
        if self.gaussian_form == "log_squared":
            self.structure = type(self).structure.replace(
                measurement_noise="scalar", measurement_noise_scale=LOG_CHI2_VAR
            )

    def _per_trial_structure(self, names):
        return per_trial_structure(self, names, noise=False)  # mu, rho, sigma: the transition alone

    def _view(self, p: torch.Tensor, x: torch.Tensor, core: int = 1) -> torch.Tensor:
        """A parameter (a scalar, or one value per trial ``(B,)``) viewed against ``x (B, ..., 1)``,
        with ``core`` trailing singleton dimensions."""
        return trial_view(p, 0, x, core)

    # ---- the stationary law ------------------------------------------------------------------
    def stationary_var(self) -> torch.Tensor:
        """``sigma^2 / (1 - rho^2)``, the variance of x_t under the stationary law (a scalar)."""
        return self.sigma**2 / (1 - self.rho**2)

    def initial_state(self, batch_size: int, generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """``x_0 (B, 1)`` from the stationary law ``N(mu, sigma^2 / (1 - rho^2))``."""
        xi = linalg.standard_normal((batch_size, 1), dtype=self.dtype, device=self.device, generator=generator)
        return self._view(self.mu, xi) + self._view(self.stationary_var(), xi).sqrt() * xi

    def initial_belief(
        self, states0: torch.Tensor, generator: Optional[torch.Generator] = None
    ) -> Tuple[torch.Tensor, torch.Tensor]:
        """The stationary law for every trial, whatever the truth: mean ``(B, 1)``, covariance ``(B, 1, 1)``."""
        return self.declared_prior(states0.shape[0])

    def declared_prior(self, batch_size: int) -> Tuple[torch.Tensor, torch.Tensor]:
        """The stationary law ``N(mu, sigma^2 / (1 - rho^2))`` (no true state needed; differentiable in
        the parameters): ``(B, 1)``, ``(B, 1, 1)``."""
        ones = torch.ones(batch_size, 1, dtype=self.dtype, device=self.device)
        return self._view(self.mu, ones) * ones, self._view(self.stationary_var(), ones, 2) * ones.unsqueeze(-1)

    # ---- dynamics ----------------------------------------------------------------------------
    def transition_mean(self, x: torch.Tensor) -> torch.Tensor:
        """``mu + rho (x - mu)``: ``(..., 1) -> (..., 1)``."""
        mu = self._view(self.mu, x)
        return mu + self._view(self.rho, x) * (x - mu)

    def transition_cov(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        """``sigma^2`` as ``(1, 1)`` (per-trial values: ``(B, ..., 1, 1)`` against ``x``)."""
        return self.transition_scale_tril(x) ** 2

    def transition_scale_tril(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        if self.sigma.dim() == 0:
            return self.sigma.reshape(1, 1)
        if x is None:
            return self.sigma.reshape(-1, 1, 1)
        return self._view(self.sigma, x, 2)

    def transition_jacobian(self, x: torch.Tensor) -> torch.Tensor:
        """``rho``, as ``(..., 1, 1)``."""
        return (self._view(self.rho, x) * torch.ones_like(x)).unsqueeze(-1)

    def sample_transition(self, x: torch.Tensor, generator: Optional[torch.Generator] = None) -> torch.Tensor:
        xi = linalg.standard_normal(x.shape, dtype=x.dtype, device=x.device, generator=generator)
        return self.transition_mean(x) + self._view(self.sigma, x) * xi

    def transition_log_prob(self, x_next: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``log N(x_next; mu + rho (x - mu), sigma^2)`` -> ``(...)``."""
        mean = self.transition_mean(x)
        sigma = self._view(self.sigma, mean if mean.dim() >= x_next.dim() else x_next)
        r = ((x_next - mean) / sigma).squeeze(-1)
        return -0.5 * (LOG_2PI + r * r) - torch.log(sigma).squeeze(-1)

    # ---- measurement: the Gaussian form ------------------------------------------------------
    def measure(self, x: torch.Tensor) -> torch.Tensor:
        """h(x): ``0`` (returns) or ``x + E[log chi^2_1] = x - 1.2704`` (log-squared); ``(..., 1)``."""
        return x * 0.0 if self.gaussian_form == "returns" else x + LOG_CHI2_MEAN

    def measurement_jacobian(self, x: torch.Tensor) -> torch.Tensor:
        """dh/dx: ``0`` (returns) or ``1`` (log-squared), ``(..., 1, 1)``."""
        return self._slope(x).unsqueeze(-1)

    def _slope(self, x: torch.Tensor) -> torch.Tensor:
        return torch.zeros_like(x) if self.gaussian_form == "returns" else torch.ones_like(x)

    def measurement_cov(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        """R: ``exp(x) (..., 1, 1)`` (returns; needs x) or ``pi^2 / 2`` as ``(1, 1)`` (log-squared)."""
        return self.measurement_scale_tril(x) ** 2

    def measurement_scale_tril(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        if self.gaussian_form == "log_squared":
            return torch.full((1, 1), math.sqrt(LOG_CHI2_VAR), dtype=self.dtype, device=self.device)
        if x is None:
            raise ArgumentError(
                "StochasticVolatility.measurement_scale_tril: R = exp(x) depends on the state "
                "(gaussian_form='returns'); pass x"
            )
        return torch.exp(0.5 * x).unsqueeze(-1)

    def linearize_measurement_diagonal(self, x: torch.Tensor):
        """``(h(x), dh/dx, R^(1/2))`` elementwise, each ``(..., 1)``."""
        h = self.measure(x)
        sd = torch.exp(0.5 * x) if self.gaussian_form == "returns" else torch.full_like(x, math.sqrt(LOG_CHI2_VAR))
        return h, self._slope(x), sd

    # ---- measurement: the exact law -----------------------------------------------------------
    def returns_squared(self, z: torch.Tensor) -> torch.Tensor:
        """``y^2`` from an observation: ``z^2`` (returns) or ``exp(z) - offset`` (log-squared, floored
        at 0 against round-off); same shape."""
        if self.gaussian_form == "returns":
            return z * z
        return (torch.exp(z) - self.offset).clamp_min(0.0)

    def measurement_log_prob(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``log N(y; 0, exp(x))`` -> ``(...)``, with y the return that ``z (..., 1)`` holds (itself,
        or read back from its log-square: module docstring)."""
        x = x.squeeze(-1)
        return -0.5 * (LOG_2PI + x + self.returns_squared(z).squeeze(-1) * torch.exp(-x))

    def log_squared_log_prob(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """The exact density of ``z = log y^2`` (no offset): ``log p(z | x)`` of ``z - x ~ log chi^2_1``,
        ``-(log 2 pi)/2 + (w - exp(w))/2`` at ``w = z - x``; ``(..., 1), (..., 1) -> (...)``."""
        w = (z - x).squeeze(-1)
        return -0.5 * LOG_2PI + 0.5 * (w - torch.exp(w))

    def sample_measurement(self, x: torch.Tensor, generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """A return ``exp(x/2) eps`` (returns form) or its transform ``log(exp(x) eps^2 + offset)``."""
        xi = linalg.standard_normal(x.shape, dtype=x.dtype, device=x.device, generator=generator)
        if self.gaussian_form == "returns":
            return torch.exp(0.5 * x) * xi
        z = x + torch.log(xi * xi)
        return z if self.offset == 0 else torch.logaddexp(z, torch.full_like(z, math.log(self.offset)))

    def transform_observations(self, returns: torch.Tensor) -> torch.Tensor:
        """The observations this model's filters read, from the returns ``(B, T, 1)`` (any shape):
        the returns themselves (returns form) or ``log(y^2 + offset)`` (log-squared form). A filter's
        log-evidence on them is ``log p(y_{1:T})`` in both forms (module docstring).

        Raises:
            ArgumentError: a zero return with ``offset = 0`` (its log-square is ``-inf``), naming the count
                and the first index.
        """
        if self.gaussian_form == "returns":
            return returns
        z = torch.log(returns * returns + self.offset)
        bad = ~torch.isfinite(z)
        if bool(bad.any()):
            first = tuple(int(i) for i in torch.nonzero(bad)[0])
            raise ArgumentError(
                f"returns: {int(bad.sum())} value(s) whose log-square is not finite (first at index "
                f"{first}: {float(returns[first])!r}); a zero return needs offset > 0 "
                "(StochasticVolatility(gaussian_form='log_squared', offset=...))"
            )
        return z

    def extra_repr(self) -> str:
        return f"gaussian_form={self.gaussian_form!r}" + (f", offset={self.offset:g}" if self.offset else "")


__all__ = ["StochasticVolatility", "LOG_CHI2_MEAN", "LOG_CHI2_VAR"]
