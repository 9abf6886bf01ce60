"""The unscented particle filter's proposal (van der Merwe, Doucet, de Freitas & Wan 2000).

Every particle carries its own Gaussian belief ``N(x_{k-1}^i, P_{k-1}^i)``. Each step a UKF (or, with
``covariance="ekf"``, an EKF: the extended Kalman particle filter of Doucet et al.) predicts and
updates that belief with ``z_k``, and the particle is drawn from the result:

    (x_bar^i, P_hat^i) = UKF(x_{k-1}^i, P_{k-1}^i, z_k),    x_k^i ~ N(x_bar^i, P_hat^i),
    log q(x_k^i | x_{k-1}^i, z_k) = log N(x_k^i; x_bar^i, P_hat^i),

and carries ``P_hat^i`` to the next step (resampled with the particle). The particle filter weighs
``p(x_k | x_{k-1}) p(z_k | x_k) / q``, so the evidence estimate stays unbiased whatever the
tracker's approximation. The noise enters additively (the model's transition and measurement
covariances), not through an augmented state.

``prior="transition"`` is the other classical choice: each particle's prediction is the transition
``N(f(x_{k-1}^i), Q)`` itself (no carried covariance), and the tracker's update of it linearises the
optimal importance density ``p(x_k | x_{k-1}^i, z_k)`` (Doucet, Godsill & Andrieu 2000, local
linearisation). The published UPF (``prior="posterior"``) predicts from the carried posterior
``P_{k-1}^i``, which is wider than ``Q``: its draws move further towards ``z_k`` than the
transition density supports, and the weights ``p(x_k | x_{k-1}) / q`` can collapse when ``Q`` is small
(acoustic tracking).
"""

from __future__ import annotations

from typing import Optional

from torchflow.core import linalg
from torchflow.core.covariances import ParticleCovariance
from torchflow.core.errors import ArgumentError
from torchflow.core.trackers import tracker
from torchflow.models.structure import bytes_per_point
from torchflow.proposals.base import Proposal, Proposed


class UnscentedProposal(Proposal):
    """A per-particle UKF (or EKF) as the proposal (module docstring).

    Args:
        model: the state-space model (Gaussian noise; its Gaussian fit otherwise).
        covariance: ``"ukf"`` (default, the UPF) or ``"ekf"`` (the extended Kalman PF).
        alpha, beta, kappa: the UKF's sigma-point settings
            (:class:`~torchflow.core.trackers.UnscentedTransform`; ``kappa=None`` is ``3 - d``).
        prior: ``"posterior"`` (the published UPF: predict each particle's carried posterior) or
            ``"transition"`` (predict ``N(f(x^i), Q)``: the linearised optimal proposal).
    """

    random_stream = "upf"

    def __init__(
        self,
        model,
        covariance: str = "ukf",
        alpha: float = 1.0,
        beta: float = 2.0,
        kappa: Optional[float] = None,
        prior: str = "posterior",
    ):
        super().__init__(model)
        if prior not in ("posterior", "transition"):
            raise ArgumentError(f"prior: expected 'posterior' or 'transition', got {prior!r}")
        sigma = dict(alpha=alpha, beta=beta, kappa=kappa) if covariance == "ukf" else {}
        self.covariance, self.prior = covariance, prior
        self.tracker = tracker(model, covariance, **sigma)

    def init_carry(self, cov, n_particles):
        if self.prior == "transition":
            return None
        B, d = cov.shape[0], cov.shape[-1]
        # a linear model's tracked covariances do not depend on the particle (EKF and UKF are exact)
        identical = self.model.structure.linear_dynamics and self.model.structure.linear_measurement
        P = cov.unsqueeze(1)
        return ParticleCovariance(P if identical else P.expand(B, int(n_particles), d, d), identical=identical)

    def propose(self, particles, log_weights, estimate, z, carry, generator, *, chunk=None) -> Proposed:
        if carry is None:  # prior="transition": N(f(x), Q) per particle
            m_pred = self.model.transition_mean(particles)
            P_pred = self.model.transition_cov(m_pred)  # broadcasts: (d, d) or (B, N, d, d)
        else:
            m_pred, P_pred = self.tracker.predict(particles, carry.matrix)  # (B, N, d), (B, N|1, d, d)
        mean, P_post, _ = self.tracker.update(m_pred, P_pred, z.unsqueeze(1))
        if carry is not None and carry.identical:  # equal for every particle (sigma points broadcast them)
            P_post = P_post[:, :1]
        L = linalg.safe_cholesky(P_post)
        xi = linalg.standard_normal(
            particles.shape, dtype=particles.dtype, device=particles.device, generator=generator
        )
        x = mean + linalg.matvec(L, xi)
        return Proposed(
            x, linalg.mvn_log_prob(x, mean, L), cov=None if carry is None else carry.like(P_post), fallback=m_pred
        )

    def bytes_per_trial(self, n_particles):
        N, d, m = int(n_particles), self.model.state_dim, self.model.obs_dim
        s = 2 * d + 1  # sigma points per particle
        per_particle = s * (2 * d + 2 * m) + 8 * d * d + 4 * m * m + 2 * m * d + 12 * d + 4 * m
        return 8 * N * per_particle + N * s * bytes_per_point(self.model) + super().bytes_per_trial(N)

    def extra_repr(self) -> str:
        return f"covariance={self.covariance!r}, prior={self.prior!r}"
