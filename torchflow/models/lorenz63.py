"""Lorenz-63: the three-variable chaotic benchmark of data assimilation (Lorenz 1963).

``dx/dt = sigma (y - x)``, ``dy/dt = x (rho - z) - y``, ``dz/dt = x y - beta z`` with
``sigma = 10``, ``rho = 28``, ``beta = 8/3``, integrated by fourth-order Runge-Kutta over the time
``dt`` between observations in ``substeps`` equal steps, with optional additive model noise
``N(0, model_noise^2 I)`` per observation interval. The coordinates listed in ``observed`` are
measured with noise ``N(0, obs_std^2 I)``.

The defaults are the set-up of Sakov, Oliver & Bertino (2012), as DAPPER's
``mods/Lorenz63/sakov2012.py`` gives it: integration step 0.01, an observation every 25 steps
(``dt = 0.25``), all three coordinates observed with ``R = 2 I``, no model noise, and the initial
law ``N(mu_0, 2 I)`` with ``mu_0 = (1.509, -1.531, 25.46)``: the truth's initial state is drawn from
it and the filters start from it (the same prior in every trial).

The Jacobian of the integrated dynamics is the exact derivative of the Runge-Kutta map, carried
through the stages with the tendency's analytic ``3 x 3`` Jacobian (forward tangent propagation,
batched over all states): one pass of ``4 substeps`` small products instead of ``torch.func`` on
one state at a time; on the CPU in float64 with Numba installed, one compiled loop (under 1 ms a call
for a handful of states, where the torch pass costs its ~400 small operations' overhead).
"""

from __future__ import annotations

import importlib
import math
from collections import abc
from typing import Optional, Sequence, Tuple

import torch

from torchflow.core import linalg
from torchflow.core.checks import check_nonnegative, check_number, check_positive
from torchflow.core.errors import ArgumentError
from torchflow.models.base import GaussianStateSpaceModel
from torchflow.models.dynamics import RungeKuttaModel, isotropic_log_prob, rk4_steps, rk4_with_tangent
from torchflow.models.structure import Structure

_KERNEL: list = []  # [bool] once checked


def _kernel_available() -> bool:
    """Numba is installed and the compiled RK4-tangent kernel imports (checked once per process; any
    failure to import means the torch path runs)."""
    if not _KERNEL:
        try:
            importlib.import_module("torchflow.models._lorenz63_kernel")
            _KERNEL.append(True)
        except Exception:
            _KERNEL.append(False)
    return _KERNEL[0]


#: the mean of the initial law in Sakov et al. (2012) and DAPPER (a point near the attractor)
SAKOV2012_MEAN = (1.509, -1.531, 25.46)


def lorenz63_tendency(x: torch.Tensor, sigma: float = 10.0, rho: float = 28.0, beta: float = 8.0 / 3.0) -> torch.Tensor:
    """``dx/dt`` of Lorenz-63 for ``x (..., 3)``."""
    a, b, c = x.unbind(-1)
    return torch.stack((sigma * (b - a), a * (rho - c) - b, a * b - beta * c), -1)


def lorenz63_tendency_jacobian(
    x: torch.Tensor, sigma: float = 10.0, rho: float = 28.0, beta: float = 8.0 / 3.0
) -> torch.Tensor:
    """The tendency's Jacobian ``(..., 3, 3)`` at ``x (..., 3)``."""
    a, b, c = x.unbind(-1)
    one, zero = torch.ones_like(a), torch.zeros_like(a)
    rows = ((-sigma * one, sigma * one, zero), (rho - c, -one, -a), (b, a, -beta * one))
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


class Lorenz63(RungeKuttaModel, GaussianStateSpaceModel):
    """Lorenz-63 observed with Gaussian noise (module docstring).

    Args:
        sigma, rho, beta: the equations' parameters (10, 28, 8/3: chaotic).
        dt: model time between observations (0.25: 25 steps of 0.01 as in Sakov et al. 2012).
        substeps: Runge-Kutta steps per observation interval.
        observed: the measured coordinates (indices into ``(x, y, z)``; default all three).
        obs_std: observation noise standard deviation (``R = obs_std^2 I``; default ``sqrt(2)``).
        model_noise: standard deviation of the additive model noise per interval (0: none, the
            deterministic dynamics of the benchmark; filters that weigh by the transition density
            then refuse the model by name or, where they offer it, use a kernel density instead).
        prior_mean: the mean of the initial law (the truth's and the filters').
        prior_std: its standard deviation per coordinate (default ``sqrt(2)``: ``C = 2 I``).

    Shapes: states ``(..., 3)``, observations ``(..., m)``.
    """

    structure = Structure(linear_measurement=True, measurement_noise="scalar", prior_covariance="dense")

    def __init__(
        self,
        *,
        sigma: float = 10.0,
        rho: float = 28.0,
        beta: float = 8.0 / 3.0,
        dt: float = 0.25,
        substeps: int = 25,
        observed: Sequence[int] = (0, 1, 2),
        obs_std: float = math.sqrt(2.0),
        model_noise: float = 0.0,
        prior_mean: Sequence[float] = SAKOV2012_MEAN,
        prior_std: float = math.sqrt(2.0),
    ):
        super().__init__()
        self.state_dim = 3
        self.sigma, self.rho, self.beta = (
            check_number(n, v) for n, v in (("sigma", sigma), ("rho", rho), ("beta", beta))
        )
        self.dt = check_positive("dt", dt)
        self.substeps = check_number("substeps", substeps, lambda v: v >= 1, "an integer >= 1", integer=True)
        obs = list(observed) if isinstance(observed, abc.Sequence) and not isinstance(observed, str) else None
        if (
            not obs
            or any(isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < 3 for i in obs)
            or len(set(obs)) != len(obs)
        ):
            raise ArgumentError(
                f"observed: expected distinct coordinate indices in 0..2 (a non-empty list), got {observed!r}"
            )
        mean = list(prior_mean) if isinstance(prior_mean, abc.Sequence) and not isinstance(prior_mean, str) else None
        if mean is None or len(mean) != 3:
            raise ArgumentError(f"prior_mean: expected 3 numbers, got {prior_mean!r}")
        mean = [check_number(f"prior_mean[{i}]", v) for i, v in enumerate(mean)]
        obs_std = check_positive("obs_std", obs_std)
        model_noise = check_nonnegative("model_noise", model_noise)
        check_positive("prior_std", prior_std)
        self.obs_dim = len(obs)
        f64 = dict(dtype=torch.float64)
        self.register_buffer("prior_mean", torch.tensor(mean, **f64))  # first: the model's dtype is its first buffer's
        self.register_buffer("observed", torch.tensor(obs, dtype=torch.long))
        self.register_buffer("obs_std", torch.tensor(float(obs_std), **f64))
        self.register_buffer("model_noise", torch.tensor(float(model_noise), **f64))
        self.register_buffer("prior_std", torch.tensor(float(prior_std), **f64))
        self.structure = type(self).structure.replace(
            measurement_noise_scale=obs_std**2,
            measurement_matrix_scale=1.0 if obs == [0, 1, 2] else None,
            measurement_support=None if obs == [0, 1, 2] else tuple(obs),
        )

    def _tendency(self, x):
        return lorenz63_tendency(x, self.sigma, self.rho, self.beta)

    def _tendency_jacobian(self, x):
        return lorenz63_tendency_jacobian(x, self.sigma, self.rho, self.beta)

    # ---- dynamics ----------------------------------------------------------------------------
    def transition_mean(self, x: torch.Tensor) -> torch.Tensor:
        return rk4_steps(self._tendency, x, self.dt, self.substeps)

    def transition_jacobian(self, x: torch.Tensor) -> torch.Tensor:
        """``(..., 3, 3)``: the exact derivative of the Runge-Kutta map (module docstring), for any
        batch of states in one pass (compiled on the CPU where Numba is installed)."""
        return self.transition_mean_and_jacobian(x)[1]

    def transition_mean_and_jacobian(self, x: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """``(g(x) (..., 3), dg/dx (..., 3, 3))`` in one pass. On the CPU in float64, for states that
        record no gradient and where Numba is installed, one compiled loop
        (:mod:`torchflow.models._lorenz63_kernel`: the same numbers to round-off, about 1e-15
        relative); elsewhere the batched torch tangents."""
        if x.device.type == "cpu" and x.dtype == torch.float64 and not x.requires_grad and _kernel_available():
            from torchflow.models._lorenz63_kernel import rk4_tangent

            flat = x.detach().reshape(-1, 3).contiguous().numpy()
            mean, jac = rk4_tangent(flat, self.dt / self.substeps, self.substeps, self.sigma, self.rho, self.beta)
            return torch.from_numpy(mean).reshape(x.shape), torch.from_numpy(jac).reshape(*x.shape, 3)
        return rk4_with_tangent(self._tendency, self._tendency_jacobian, x, self.dt, self.substeps)

    def _eye(self, n: int) -> torch.Tensor:
        return torch.eye(n, dtype=self.dtype, device=self.device)

    def transition_cov(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        return self.model_noise**2 * self._eye(3)

    def transition_scale_tril(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        return self.model_noise * self._eye(3)

    def transition_log_prob(self, x_next: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``log N(x_next; g(x), model_noise^2 I)``."""
        return isotropic_log_prob(x_next - self.transition_mean(x), self.model_noise)

    def sample_transition(self, x: torch.Tensor, generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """``g(x) + model_noise * xi`` (the draw is made without model noise too: the same stream either way)."""
        xi = linalg.standard_normal(x.shape, dtype=x.dtype, device=x.device, generator=generator)
        return self.transition_mean(x) + self.model_noise * xi

    def sample_true_transition(self, x: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        return self.sample_transition(x, generator)

    # ---- measurement -------------------------------------------------------------------------
    def measurement_matrix(self) -> torch.Tensor:
        """``(m, 3)``: ones at ``(j, observed[j])``."""
        return self._eye(3)[self.observed]

    def measure(self, x: torch.Tensor) -> torch.Tensor:
        return x[..., self.observed]

    def measurement_cov(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        return self.obs_std**2 * self._eye(self.obs_dim)

    def measurement_variance(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        return self.obs_std**2

    def measurement_log_prob(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``log N(z; x_observed, obs_std^2 I)``."""
        return isotropic_log_prob(z - self.measure(x), self.obs_std)

    def sample_measurement(self, x: torch.Tensor, generator: Optional[torch.Generator] = None) -> torch.Tensor:
        mean = self.measure(x)
        xi = torch.randn(mean.shape, dtype=x.dtype, device=x.device, generator=generator)
        return mean + self.obs_std * xi

    # ---- initial law -------------------------------------------------------------------------
    def initial_state(self, batch_size: int, generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """``x_0 ~ N(prior_mean, prior_std^2 I)`` ``(B, 3)``."""
        xi = linalg.standard_normal((batch_size, 3), dtype=self.dtype, device=self.device, generator=generator)
        return self.prior_mean + self.prior_std * xi

    def initial_belief(
        self, states0: torch.Tensor, generator: Optional[torch.Generator] = None
    ) -> Tuple[torch.Tensor, torch.Tensor]:
        """The initial law itself for every trial (it does not look at the truth): mean ``(B, 3)``
        and covariance ``prior_std^2 I`` ``(B, 3, 3)``."""
        return self.declared_prior(states0.shape[0])

    def declared_prior(self, batch_size: int) -> Tuple[torch.Tensor, torch.Tensor]:
        mean = self.prior_mean.expand(batch_size, 3).clone()
        cov = (self.prior_std**2 * self._eye(3)).expand(batch_size, 3, 3).clone()
        return mean, cov


__all__ = ["Lorenz63", "lorenz63_tendency", "lorenz63_tendency_jacobian"]
