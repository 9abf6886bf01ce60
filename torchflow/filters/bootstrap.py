"""Bootstrap particle filter (Gordon, Salmond & Smith 1993)."""
from __future__ import annotations

import torch

from .. import linalg
from .base import ParticleFilterBase, ParticleState


class BootstrapParticleFilter(ParticleFilterBase):
    """Bootstrap PF: propose from the transition, weight by the likelihood, resample when the
    ESS falls below ``ess_threshold * N``.

    Particles ``(B, N, d)``, log-weights ``(B, N)``; the estimate is the weighted mean before
    resampling. See :class:`~torchflow.filters.base.ParticleFilterBase` for the arguments.
    """

    random_stream = "bpf"

    def init(self, mean, cov, n_particles=None, generator=None):
        N = self._resolve_n(n_particles)
        B, d = mean.shape
        L = linalg.safe_cholesky(cov)
        particles = linalg.sample_mvn(mean, L, (N,), generator)  # (B, N, d)
        lw = torch.full((B, N), -torch.log(torch.tensor(float(N))).item(), dtype=mean.dtype, device=mean.device)
        zero = torch.zeros(B, dtype=mean.dtype, device=mean.device)
        return ParticleState(particles, lw, mean, torch.full_like(zero, float(N)), zero,
                             torch.zeros(B, dtype=torch.bool, device=mean.device))

    def step(self, state, z, generator=None):
        x = self.model.sample_transition(state.particles, generator)  # (B, N, d)
        z1 = z.unsqueeze(1)
        ll = self.per_particle(lambda xs: self.model.measurement_log_prob(z1, xs), x)  # (B, N)
        return self.weight_and_resample(x, state.log_weights, ll, generator, state.step + 1,
                                        fallback=state.particles, n_repaired=state.n_repaired)
