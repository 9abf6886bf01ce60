"""Bootstrap particle filter (Gordon, Salmond & Smith 1993)."""

from __future__ import annotations

from torchflow.filters.base import ParticleFilter


class BootstrapParticleFilter(ParticleFilter):
    """Bootstrap PF: propose from the transition, weight by the likelihood, resample when the
    ESS falls below ``ess_threshold * N``: :class:`~torchflow.filters.ParticleFilter` with the
    :class:`~torchflow.proposals.BootstrapProposal` (its arguments, ``proposal`` aside).

    Particles ``(B, N, d)``, log-weights ``(B, N)``; the estimate is the weighted mean before
    resampling.
    """

    random_stream = "bpf"

    def __init__(self, model, **kwargs):
        super().__init__(model, None, **kwargs)
