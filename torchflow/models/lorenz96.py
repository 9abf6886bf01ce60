"""Lorenz-96: the data-assimilation benchmark (Lorenz 1996; Lorenz & Emanuel 1998).

``dx_i/dt = (x_{i+1} - x_{i-2}) x_{i-1} - x_i + F`` on a ring of ``d`` coordinates (indices mod d),
integrated by fourth-order Runge-Kutta over the time ``dt`` between observations in ``substeps``
equal steps; optional additive model noise ``N(0, model_noise^2 I)`` per observation interval. Every
``obs_every``-th coordinate is observed with noise ``N(0, obs_std^2 I)``. With ``F = 8`` the system is
chaotic for ``d >= 4``; the standard set-up of Sakov & Oke (2008), as DAPPER's
``mods/Lorenz96/sakov2008.py`` gives it, is ``d = 40``, ``dt = 0.05``, every coordinate observed,
``R = I``, no model noise.
"""

from __future__ import annotations

import math
from typing import Optional, Tuple

import torch
from torch.distributions import constraints as support

from torchflow.core import linalg
from torchflow.core.checks import allocation_failure, check_nonnegative, check_number, check_positive
from torchflow.core.covariances import DiagonalCovariance
from torchflow.core.errors import ArgumentError
from torchflow.models.base import GaussianStateSpaceModel
from torchflow.models.dynamics import RungeKuttaModel, isotropic_log_prob, rk4_steps
from torchflow.models.structure import Structure
from torchflow.models.trials import batch_jacobian, per_trial_structure, trial_names, trial_view

#: what an observation of a coordinate measures (``Lorenz96(obs_operator=...)``)
OBS_OPERATORS = ("identity", "abs", "square")


def lorenz96_tendency(x: torch.Tensor, forcing) -> torch.Tensor:
    """``dx/dt`` of Lorenz-96 for ``x (..., d)`` (periodic in the last dimension)."""
    return (torch.roll(x, -1, -1) - torch.roll(x, 2, -1)) * torch.roll(x, 1, -1) - x + forcing


def rk4(x: torch.Tensor, forcing, dt: float, substeps: int) -> torch.Tensor:
    """``x (..., d)`` moved by ``substeps`` classical Runge-Kutta steps of ``dt / substeps``."""
    return rk4_steps(lambda v: lorenz96_tendency(v, forcing), x, dt, substeps)


class Lorenz96(RungeKuttaModel, GaussianStateSpaceModel):
    """Lorenz-96 with observations of every ``obs_every``-th coordinate (module docstring).

    Args:
        d: number of coordinates (>= 4).
        forcing: F (8: chaotic).
        dt: model time between observations.
        substeps: Runge-Kutta steps per observation interval.
        obs_every: observe coordinates ``0, k, 2k, ...`` (``m = ceil(d / k)``).
        obs_std: observation noise standard deviation (R = obs_std^2 I).
        obs_operator: what is measured at an observed coordinate: ``"identity"`` (``x_i``, the
            default), ``"abs"`` (``|x_i|``) or ``"square"`` (``x_i^2``): the two nonlinear ones lose
            the sign, so the posterior is bimodal where ``x_i`` is near 0 (regime R3 of the
            data-assimilation scoreboard).
        obs_df: ``None`` (Gaussian errors, the default) or an integer ``nu >= 3``: Student-t errors with
            ``nu`` degrees of freedom and scale ``obs_std`` (heavy tails; regime R4 uses 3). The
            Gaussian form the Kalman-type filters use (``measurement_cov``) is then the t law's
            variance, ``obs_std^2 nu / (nu - 2)`` (moment matching); the density
            (``measurement_log_prob``, ``measurement_log_prob_terms``) is the t law's own.
        model_noise: standard deviation of the additive model noise per interval (0: none; the
            filters that weigh by the transition density then refuse the model, by name).
        prior_std: the filters' prior: ``N(x_0 + prior_std xi, prior_std^2 I)``, one draw per trial.
        spin_up: intervals integrated from ``F + N(0, 1)`` before ``x_0`` (onto the attractor).

    Per trial (:func:`torchflow.inference.per_trial_values`): ``forcing``, ``model_noise`` and
    ``obs_std`` may each hold one value per trial, ``(B,)`` (a sweep over F, say). While ``obs_std``
    is per trial R is declared ``"diagonal"``; while ``forcing`` is, the Jacobian of the dynamics is
    taken on the whole batch (forward mode) rather than one state at a time.

    Nothing of size ``d x d`` is formed unless a filter asks for it: the prior is a
    :class:`~torchflow.core.covariances.DiagonalCovariance` (``prior_std^2`` per coordinate), the
    densities and samplers use the scalar noise scales, and the ``(m, d)`` matrix H is built by
    :meth:`measurement_matrix` on demand (the Kalman-type filters). So the ensemble Kalman filters
    and the bootstrap PF run at ``d = 10^5`` and more.

    Shapes: states ``(..., d)``, observations ``(..., m)``.
    """

    structure = Structure(
        linear_measurement=True, measurement_noise="scalar", prior_covariance="diagonal", sites="ring"
    )
    #: the forcing and both noise scales may hold one value per trial, ``(B,)``
    per_trial_parameters = {
        "forcing": support.real,
        "model_noise": support.greater_than_eq(0.0),
        "obs_std": support.positive,
    }

    def __init__(
        self,
        *,
        d: int = 40,
        forcing: float = 8.0,
        dt: float = 0.05,
        substeps: int = 1,
        obs_every: int = 1,
        obs_std: float = 1.0,
        model_noise: float = 0.0,
        prior_std: float = 1.0,
        spin_up: int = 100,
        obs_operator: str = "identity",
        obs_df: Optional[int] = None,
    ):
        super().__init__()
        self.state_dim = check_number(
            "d", d, lambda v: v >= 4, "an integer >= 4 (the ring needs i-2 .. i+1)", integer=True
        )
        forcing = check_number("forcing", forcing)
        self.dt = check_positive("dt", dt)
        self.substeps = check_number("substeps", substeps, lambda v: v >= 1, "an integer >= 1", integer=True)
        self.obs_every = check_number(
            "obs_every",
            obs_every,
            lambda v: 1 <= v <= self.state_dim,
            f"an integer in [1, d = {self.state_dim}]",
            integer=True,
        )
        self.spin_up = check_number("spin_up", spin_up, lambda v: v >= 0, "an integer >= 0", integer=True)
        obs_std, model_noise = check_positive("obs_std", obs_std), check_nonnegative("model_noise", model_noise)
        check_positive("prior_std", prior_std)
        f64 = dict(dtype=torch.float64)
        try:
            observed = torch.arange(0, self.state_dim, self.obs_every)
        except RuntimeError as err:  # the first d-sized allocation: say which setting does not fit
            why = allocation_failure(err)
            if why is None:
                raise
            raise ArgumentError(
                f"d: {self.state_dim} coordinates do not fit in memory{why}: the model keeps the index of its "
                f"observed coordinates and every state takes {8 * self.state_dim / 2**30:.3g} GiB per trial; "
                "choose a smaller d"
            ) from None
        self.obs_dim = int(observed.numel())
        # first: the model's dtype is its first buffer's. F is a tensor (per trial in a sweep)
        self.register_buffer("forcing", torch.tensor(float(forcing), **f64))
        self.register_buffer("observed", observed)
        self.register_buffer("obs_std", torch.tensor(obs_std, **f64))
        self.register_buffer("model_noise", torch.tensor(model_noise, **f64))
        self.register_buffer("prior_std", torch.tensor(float(prior_std), **f64))
        if obs_operator not in OBS_OPERATORS:
            raise ArgumentError(f"obs_operator: expected one of {OBS_OPERATORS}, got {obs_operator!r}")
        #: ``"identity"``, ``"abs"`` or ``"square"`` (what an observation measures)
        self.obs_operator = obs_operator
        linear = obs_operator == "identity"
        if obs_df is not None:
            obs_df = check_number(
                "obs_df",
                obs_df,
                lambda v: v >= 3,
                "None (Gaussian errors) or an integer >= 3 (Student-t degrees of freedom: a finite variance)",
                integer=True,
            )
        #: Student-t degrees of freedom of the observation errors (``None``: Gaussian)
        self.obs_df = obs_df
        #: the variance of one observation error over obs_std^2 (1, or nu / (nu - 2) for Student-t)
        self._variance_factor = 1.0 if obs_df is None else obs_df / (obs_df - 2.0)
        self.structure = type(self).structure.replace(
            linear_measurement=linear,
            measurement_noise_scale=obs_std**2 * self._variance_factor,
            gaussian_measurement=obs_df is None,
            measurement_matrix_scale=1.0 if self.obs_every == 1 and linear else None,
        )

    def _per_trial_structure(self, names):
        return per_trial_structure(self, names, dynamics=False, measurement=False, noise="obs_std" in names)

    def _scale(self, value: torch.Tensor, x: Optional[torch.Tensor], event: int) -> torch.Tensor:
        """A scalar parameter (or one per trial, ``(B,)``) against states ``x (B, ..., d)`` with
        ``event`` trailing dims (``x=None``: ``(B, 1.., 1)``)."""
        return trial_view(value, 0, x, event)

    # ---- dynamics ----------------------------------------------------------------------------
    def transition_mean(self, x: torch.Tensor) -> torch.Tensor:
        return rk4(x, trial_view(self.forcing, 0, x), self.dt, self.substeps)

    def transition_jacobian(self, x: torch.Tensor) -> torch.Tensor:
        """``(..., d, d)``: by ``torch.func`` on single states, or on the whole batch (forward mode)
        while the forcing is per trial."""
        if "forcing" in trial_names(self):
            return batch_jacobian(self.transition_mean, x)
        return super().transition_jacobian(x)

    def _eye(self, n: int) -> torch.Tensor:
        return torch.eye(n, dtype=self.dtype, device=self.device)

    def transition_cov(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        return self._scale(self.model_noise, x, 2) ** 2 * self._eye(self.state_dim)

    def transition_scale_tril(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        return self._scale(self.model_noise, x, 2) * self._eye(self.state_dim)

    def transition_log_prob(self, x_next: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``log N(x_next; rk4(x), model_noise^2 I)`` elementwise (no ``(d, d)`` factor)."""
        resid = x_next - self.transition_mean(x)  # broadcast after the dynamics: rk4 once per state
        return isotropic_log_prob(resid, trial_view(self.model_noise, 0, resid))

    def sample_true_transition(self, x: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """:meth:`simulate`'s step: ``rk4(x) + model_noise * xi`` with the core's draws (``torch.randn``
        of ``x``'s shape), the noise factor applied as a scaling."""
        xi = torch.randn(x.shape, dtype=x.dtype, device=x.device, generator=generator)
        return self.transition_mean(x) + trial_view(self.model_noise, 0, x) * xi

    def sample_transition(self, x: torch.Tensor, generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """``rk4(x) + model_noise * xi``: the Gaussian transition with its scalar noise factor applied
        as a scaling (the same draws and values as the dense ``(d, d)`` factor, without its ``d^2``
        products per state, which dominate an ensemble step at d = 4000)."""
        xi = linalg.standard_normal(x.shape, dtype=x.dtype, device=x.device, generator=generator)
        return self.transition_mean(x) + trial_view(self.model_noise, 0, x) * xi

    # ---- measurement -------------------------------------------------------------------------
    def measurement_matrix(self) -> torch.Tensor:
        """``(m, d)``: ones at ``(j, observed[j])`` (built on each call: ``m d`` numbers); only for the
        linear ``obs_operator="identity"``."""
        if self.obs_operator != "identity":
            raise ArgumentError(
                f"obs_operator: the measurement {self.obs_operator!r} is nonlinear and has no "
                "matrix; use measurement_jacobian(x)"
            )
        H = torch.zeros(self.obs_dim, self.state_dim, dtype=self.dtype, device=self.device)
        return H.scatter_(-1, self.observed.unsqueeze(-1), 1.0)

    @property
    def H(self) -> torch.Tensor:
        """The measurement matrix (:meth:`measurement_matrix`)."""
        return self.measurement_matrix()

    def measure(self, x: torch.Tensor) -> torch.Tensor:
        v = x[..., self.observed]
        if self.obs_operator == "abs":
            return v.abs()
        return v.square() if self.obs_operator == "square" else v

    def measurement_jacobian(self, x: torch.Tensor) -> torch.Tensor:
        """``(..., m, d)``: the identity's rows of ones, or ``sign(x_i)`` / ``2 x_i`` at ``(j, observed[j])``."""
        if self.obs_operator == "identity":
            return super().measurement_jacobian(x)
        v = x[..., self.observed]
        slope = torch.sign(v) if self.obs_operator == "abs" else 2.0 * v  # (..., m)
        J = torch.zeros(*x.shape[:-1], self.obs_dim, self.state_dim, dtype=x.dtype, device=x.device)
        index = self.observed.view(*([1] * (x.dim() - 1)), -1, 1).expand(*x.shape[:-1], self.obs_dim, 1)
        return J.scatter(-1, index, slope.unsqueeze(-1))

    def measurement_cov(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        """``(m, m)``: the errors' variance times I (``obs_std^2``, or the Student-t law's
        ``obs_std^2 nu / (nu - 2)``)."""
        return self._scale(self.obs_std, x, 2) ** 2 * self._variance_factor * self._eye(self.obs_dim)

    def measurement_log_prob(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``log N(z; h(x), obs_std^2 I)`` elementwise (no ``(m, m)`` factor), or the Student-t law's."""
        if self.obs_df is not None:
            return self.measurement_log_prob_terms(z, x).sum(-1)
        h = self.measure(x)
        return isotropic_log_prob(z - h, trial_view(self.obs_std, 0, h))

    def measurement_log_prob_terms(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``log p(z_j | x)`` per observation ``(..., m)`` (NaN in ``z``: 0): Gaussian, or Student-t
        with ``obs_df`` degrees of freedom and scale ``obs_std``."""
        if self.obs_df is None:
            return super().measurement_log_prob_terms(z, x)
        h = self.measure(x)
        nu, scale = float(self.obs_df), trial_view(self.obs_std, 0, h)
        u = (z - h) / scale
        const = math.lgamma(0.5 * (nu + 1)) - math.lgamma(0.5 * nu) - 0.5 * math.log(nu * math.pi)
        terms = const - torch.log(scale) - 0.5 * (nu + 1) * torch.log1p(u * u / nu)
        return torch.where(torch.isnan(z), torch.zeros_like(terms), terms)

    def measurement_variance(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        """The errors' variance (``obs_std^2``, times ``nu / (nu - 2)`` for Student-t): a 0-d scalar,
        or one value per trial viewed against ``x`` (no ``(m, m)`` matrix)."""
        return trial_view(self.obs_std, 0, x) ** 2 * self._variance_factor

    def sample_measurement(self, x: torch.Tensor, generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """``h(x) + obs_std * xi`` with the core's draws (``torch.randn`` of ``(..., m)``); Student-t:
        ``xi / sqrt(chi2_nu / nu)``, the chi-square from ``nu`` more standard normals per observation."""
        mean = self.measure(x)
        xi = torch.randn(mean.shape, dtype=x.dtype, device=x.device, generator=generator)
        if self.obs_df is not None:
            g = torch.randn(*mean.shape, self.obs_df, dtype=x.dtype, device=x.device, generator=generator)
            xi = xi / (g.square().mean(-1)).sqrt()
        return mean + trial_view(self.obs_std, 0, mean) * xi

    # ---- initial law -------------------------------------------------------------------------
    def initial_state(self, batch_size: int, generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """``F + N(0, 1)`` per coordinate, then :attr:`spin_up` intervals of the dynamics."""
        xi = linalg.standard_normal(
            (batch_size, self.state_dim), dtype=self.dtype, device=self.device, generator=generator
        )
        x = self._scale(self.forcing, None, 1) + xi
        with torch.no_grad():
            for _ in range(self.spin_up):
                x = self.sample_transition(x, generator)
        return x

    def initial_belief(
        self, states0: torch.Tensor, generator: Optional[torch.Generator] = None
    ) -> Tuple[torch.Tensor, DiagonalCovariance]:
        """Mean ``x_0 + prior_std xi (B, d)`` and the diagonal covariance ``prior_std^2 I``
        (:class:`~torchflow.core.covariances.DiagonalCovariance`, variances ``(B, d)``: a view)."""
        xi = linalg.standard_normal(states0.shape, dtype=states0.dtype, device=states0.device, generator=generator)
        var = (self.prior_std**2).to(states0.dtype).expand(states0.shape)
        return states0 + self.prior_std * xi, DiagonalCovariance(var)


__all__ = ["Lorenz96", "lorenz96_tendency", "rk4"]
