"""Generalised-hyperbolic skewed-t dynamics with Poisson counts (Septier & Peters 2016; Li & Coates
2017 §V; as used by Comandur, Li & Nannuru 2022 and, for the Gaussian fit, Pal & Coates 2019).

    x_k = alpha x_{k-1} + W_k gamma + sqrt(W_k) Sigma^{1/2} xi_k,   1/W_k ~ Gamma(nu/2, rate nu/2),
    z_k^c ~ Poisson(m1 exp(m2 x_k^c)),  one count per cell c (m = d).

Sigma is the spatial sensor-network covariance (:func:`sensor_network_covariance`). The transition
density is the multivariate GH skewed-t with location ``mu = alpha x_{k-1}``:

    log p(x | x_prev) = log c + log K_{(nu+d)/2}(zeta) + (x - mu)^T Sigma^{-1} gamma
                        + ((nu+d)/2) (log zeta - log(1 + q/nu)),
    q = (x - mu)^T Sigma^{-1} (x - mu),  zeta = sqrt((nu + q) gamma^T Sigma^{-1} gamma),
    log c = (1 - (nu+d)/2) log 2 - lgamma(nu/2) - (d/2) log(pi nu) - (1/2) log|Sigma|,

with ``log K`` from :func:`torchflow.core.special.log_bessel_k` (order 75.5 at d = 144). Flows, trackers
and Gaussian proposals use its Gaussian fit (as Pal & Coates 2019): mean ``alpha x + E[W] gamma`` and covariance
``Q_st = E[W] Sigma + Var[W] gamma gamma^T``. The measurement noise is state dependent
(``R = diag(m1 exp(m2 x))``, the Poisson variance at the linearisation point), declared as
``measurement_noise = "state_dependent_diagonal"``.

``nu`` must be an integer > 4 (so that Var[W] exists): ``1/W`` is then drawn exactly as a
chi-square over nu, ``sum_j eta_j^2 / nu`` with standard normals, from the caller's generator (or
per-trial streams) without rejection sampling.
"""

from __future__ import annotations

import math

import torch

from torchflow.core import linalg
from torchflow.core.checks import check_nonnegative, check_number, check_positive
from torchflow.core.errors import ArgumentError
from torchflow.core.special import log_bessel_k
from torchflow.models.base import GaussianStateSpaceModel
from torchflow.models.linear_gaussian import sensor_network_covariance
from torchflow.models.structure import Structure
from torchflow.models.trials import per_trial_structure, trial_view


class SkewedTPoisson(GaussianStateSpaceModel):
    """GH skewed-t dynamics on a sensor grid with Poisson count measurements (Septier & Peters 2016;
    Li & Coates 2017 §V).

    Args:
        d: state dimension, a perfect square (144 default; 400 works).
        alpha: AR coefficient (0.9).
        gamma: skewness, a number (``gamma * 1_d``; 0.3) .
        nu: degrees of freedom, an integer > 4 (7).
        alpha0, alpha1, beta: Sigma's sensor-network constants (3, 0.01, 20).
        m1, m2: Poisson rate ``m1 exp(m2 x)`` (1, 1/3).
        mean_shift: the Gaussian fit's mean includes ``E[W] gamma`` (True, as Pal & Coates 2019) or not (False:
            Li & Coates' published code's noise-free propagation ``alpha x``).
        steps: a default horizon for experiments (30, as Comandur et al. 2022), not used by the model itself.

    Per trial (:func:`torchflow.inference.per_trial_values`): ``alpha``, ``m1`` and ``m2`` may each hold
    one value per trial, ``(B,)``. While ``alpha`` is per trial the model declares no
    ``linear_dynamics`` (its callers read one transition matrix); the Jacobian ``alpha I`` comes from
    :meth:`transition_jacobian`, each trial's. (``gamma``, ``nu`` and Sigma's constants are fixed: the
    transition covariance and the density's constants are computed from them once.)
    """

    #: linear location, a skewed-t transition (its Gaussian form is the moment fit), R = diag(lambda(x)),
    #: and z_c counts cell c only (lambda_c = m1 exp(m2 x_c)): a diagonal measurement Jacobian
    structure = Structure(
        linear_dynamics=True,
        gaussian_transition=False,
        gaussian_measurement=False,
        measurement_noise="state_dependent_diagonal",
        measurement_jacobian_diagonal=True,
    )

    #: the AR coefficient and the Poisson rate's constants may hold one value per trial, ``(B,)``
    per_trial_parameters = ("alpha", "m1", "m2")

    def __init__(
        self,
        *,
        d: int = 144,
        alpha: float = 0.9,
        gamma: float = 0.3,
        nu: int = 7,
        alpha0: float = 3.0,
        alpha1: float = 0.01,
        beta: float = 20.0,
        m1: float = 1.0,
        m2: float = 1.0 / 3.0,
        mean_shift: bool = True,
    ):
        super().__init__()
        if isinstance(d, bool) or not isinstance(d, int) or d < 1 or round(math.sqrt(d)) ** 2 != d:
            raise ArgumentError(f"d: expected a perfect square (144, 400, ...), got {d!r}")
        if isinstance(nu, bool) or not isinstance(nu, int) or nu <= 4:
            raise ArgumentError(
                f"nu: expected an integer > 4 (Var[W] must exist; 1/W is drawn as chi2_nu / nu), got {nu!r}"
            )
        for name, value in (("alpha", alpha), ("gamma", gamma), ("m2", m2)):
            check_number(name, value)
        check_nonnegative("alpha0", alpha0)
        for name, value in (("alpha1", alpha1), ("beta", beta), ("m1", m1)):
            check_positive(name, value)
        g = round(math.sqrt(d))
        self.state_dim = self.obs_dim = d
        self.nu, self.mean_shift = nu, bool(mean_shift)
        f64 = dict(dtype=torch.float64)
        Sigma = sensor_network_covariance(g, alpha0, alpha1, beta)
        self.register_buffer("Sigma", Sigma)
        self.register_buffer("Sigma_tril", linalg.safe_cholesky(Sigma))
        self.register_buffer("gamma", torch.full((d,), float(gamma), **f64))
        for name, value in (("alpha", alpha), ("m1", m1), ("m2", m2)):
            self.register_buffer(name, torch.tensor(float(value), **f64))
        self.EW = nu / (nu - 2)
        self.VarW = 2 * nu * nu / ((nu - 2) ** 2 * (nu - 4))
        Q = self.EW * Sigma + self.VarW * torch.outer(self.gamma, self.gamma)
        self.register_buffer("Q_st", Q)
        self.register_buffer("Q_st_tril", linalg.safe_cholesky(Q))
        # Sigma^{-1} gamma and gamma^T Sigma^{-1} gamma, once
        Sg = torch.cholesky_solve(self.gamma.unsqueeze(-1), self.Sigma_tril).squeeze(-1)
        self.register_buffer("Sigma_inv_gamma", Sg)
        self.register_buffer("gSg", (self.gamma * Sg).sum())
        if not bool(torch.isfinite(Q).all() and torch.isfinite(self.gSg)):
            raise ArgumentError(
                f"gamma: the skewness {gamma!r} overflows the transition covariance E[W] Sigma + Var[W] "
                "gamma gamma^T or gamma^T Sigma^-1 gamma (with alpha0, alpha1, beta given); expected a "
                "smaller skewness or noise floor alpha1"
            )
        k = (nu + d) / 2
        self._log_c = (
            (1 - k) * math.log(2)
            - math.lgamma(nu / 2)
            - 0.5 * d * math.log(math.pi * nu)
            - 0.5 * float(linalg.chol_logdet(self.Sigma_tril))
        )

    def _per_trial_structure(self, names):
        return per_trial_structure(self, names, dynamics="alpha" in names, measurement=False, noise=False)

    # ---- dynamics --------------------------------------------------------------------------
    def location(self, x):
        """``mu = alpha x``, the GH location."""
        return trial_view(self.alpha, 0, x) * x

    def transition_mean(self, x):
        return self.location(x) + (self.EW * self.gamma if self.mean_shift else 0.0)

    def transition_matrix(self):
        """``alpha I``: ``(d, d)``, or ``(B, d, d)`` per trial."""
        alpha = self.alpha.reshape(*self.alpha.shape, 1, 1)
        return alpha * torch.eye(self.state_dim, dtype=self.Sigma.dtype, device=self.Sigma.device)

    def transition_jacobian(self, x):
        """``alpha I`` at every state ``x (..., d)`` (each trial's, per trial): ``(..., d, d)``."""
        d = self.state_dim
        eye = torch.eye(d, dtype=x.dtype, device=x.device)
        return (trial_view(self.alpha, 0, x, 2) * eye).expand(*x.shape[:-1], d, d)

    def transition_cov(self, x=None):
        return self.Q_st

    def transition_scale_tril(self, x=None):
        return self.Q_st_tril

    def sample_transition(self, x, generator=None):
        """An exact GH skewed-t draw: ``W = nu / chi2_nu`` from nu squared standard normals."""
        eta = linalg.standard_normal((*x.shape[:-1], self.nu), dtype=x.dtype, device=x.device, generator=generator)
        W = self.nu / eta.pow(2).sum(-1, keepdim=True)
        xi = linalg.standard_normal(x.shape, dtype=x.dtype, device=x.device, generator=generator)
        return self.location(x) + W * self.gamma + W.sqrt() * linalg.matvec(self.Sigma_tril, xi)

    def check_observations(self, observations):
        """Counts: ``(B, T, d)`` non-negative integers, or NaN where not observed (a clear error names
        the first bad one)."""
        observations = super().check_observations(observations)
        bad = ((observations < 0) | (observations != observations.round())) & ~torch.isnan(observations)
        if bool(bad.any()):
            b, t, c = [int(v) for v in torch.nonzero(bad)[0]]
            raise ArgumentError(
                f"observations: expected Poisson counts (non-negative integers), got "
                f"{float(observations[b, t, c])!r} at trial {b}, step {t}, cell {c}"
            )
        return observations

    def transition_log_prob(self, x_next, x):
        """The exact GH skewed-t log-density ``(...)`` (module docstring)."""
        r = x_next - self.location(x)
        u = linalg.solve_triangular(self.Sigma_tril, r.unsqueeze(-1), upper=False).squeeze(-1)
        q = u.pow(2).sum(-1)
        k = (self.nu + self.state_dim) / 2
        zeta = torch.sqrt((self.nu + q) * self.gSg)
        return (
            self._log_c
            + log_bessel_k(k, zeta)
            + (r * self.Sigma_inv_gamma).sum(-1)
            + k * (torch.log(zeta) - torch.log1p(q / self.nu))
        )

    # ---- measurement -----------------------------------------------------------------------
    def measure(self, x):
        """Poisson rates ``m1 exp(m2 x)`` (the measurement's mean)."""
        return trial_view(self.m1, 0, x) * torch.exp(trial_view(self.m2, 0, x) * x)

    def measurement_cov(self, x=None):
        if x is None:
            raise ArgumentError("SkewedTPoisson.measurement_cov: R depends on the state (Poisson variance); pass x")
        return torch.diag_embed(self.measure(x))

    def measurement_scale_tril(self, x=None):
        if x is None:
            raise ArgumentError("SkewedTPoisson.measurement_scale_tril: R depends on the state; pass x")
        return torch.diag_embed(self.measure(x).sqrt())

    def measurement_jacobian(self, x):
        return torch.diag_embed(trial_view(self.m2, 0, x) * self.measure(x))

    def linearize_measurement_diagonal(self, x):
        """``(lambda, m2 lambda, sqrt(lambda))`` with ``lambda = m1 exp(m2 x)``: the diagonals of
        :meth:`linearize_measurement` and :meth:`measurement_scale_tril`, elementwise."""
        lam = self.measure(x)
        return lam, trial_view(self.m2, 0, x) * lam, lam.sqrt()

    def measurement_log_prob(self, z, x):
        """Poisson log-likelihood ``sum_c z_c log lam_c - lam_c - log z_c!`` (the full pmf)."""
        return self._count_terms(z, x).sum(-1)

    def measurement_log_prob_observed(self, z, x, observed):
        """The counts are independent given x: the sum of :meth:`measurement_log_prob`'s terms over
        the observed cells (``observed (..., m)``)."""
        terms = self._count_terms(z, x)
        return torch.where(observed, terms, torch.zeros_like(terms)).sum(-1)

    def _count_terms(self, z, x):
        lam = self.measure(x)
        return z * torch.log(lam) - lam - torch.lgamma(z + 1)

    def sample_measurement(self, x, generator=None):
        return torch.poisson(self.measure(x), generator=generator)

    # ---- truth and prior -------------------------------------------------------------------
    def initial_state(self, batch_size, generator=None):
        return torch.zeros(batch_size, self.state_dim, dtype=self.Sigma.dtype, device=self.Sigma.device)

    def initial_belief(self, states0, generator=None):
        """``x_0 = 0`` known: mean 0 and a machine-epsilon covariance (Li & Coates 2017 §V)."""
        B, d = states0.shape
        eps = torch.finfo(states0.dtype).eps
        eye = torch.eye(d, dtype=states0.dtype, device=states0.device)
        return torch.zeros_like(states0), (eps * eye).expand(B, d, d).clone()

    def declared_prior(self, batch_size: int):
        """:meth:`initial_belief` without true states (the prior does not depend on them)."""
        return self.initial_belief(self.Sigma.new_zeros(batch_size, self.state_dim))

    def sample_true_transition(self, x, generator):
        """:meth:`simulate` draws from the exact GH skewed-t transition."""
        return self.sample_transition(x, generator)
