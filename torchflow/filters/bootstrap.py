"""Bootstrap particle filter (Gordon, Salmond & Smith 1993)."""
from __future__ import annotations

import math

import torch

from .. import linalg
from ..proposals import BootstrapProposal
from .base import ParticleFilterBase, ParticleState


class BootstrapParticleFilter(ParticleFilterBase):
    """Bootstrap PF: propose from the transition, weight by the likelihood, resample when the
    ESS falls below ``ess_threshold * N``.

    Particles ``(B, N, d)``, log-weights ``(B, N)``; the estimate is the weighted mean before
    resampling. See :class:`~torchflow.filters.base.ParticleFilterBase` for the arguments.
    """

    random_stream = "bpf"

    def __init__(self, model, **kwargs):
        super().__init__(model, **kwargs)
        self.proposal = BootstrapProposal()

    def init(self, mean, cov, n_particles=None, generator=None):
        N = self._resolve_n(n_particles)
        B, d = mean.shape
        L = linalg.safe_cholesky(cov)
        particles = linalg.sample_mvn(mean, L, (N,), generator)  # (B, N, d)
        lw = torch.full((B, N), -math.log(N), dtype=mean.dtype, device=mean.device)
        zero = torch.zeros(B, dtype=mean.dtype, device=mean.device)
        return ParticleState(particles, lw, mean, torch.full_like(zero, float(N)), zero,
                             torch.zeros(B, dtype=torch.bool, device=mean.device))
