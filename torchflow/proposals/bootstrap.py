"""The bootstrap proposal (Gordon, Salmond & Smith 1993): ``q`` is the transition."""

from __future__ import annotations

from torchflow.proposals.base import Proposal, Proposed


class BootstrapProposal(Proposal):
    """``q = p(x_k | x_{k-1})``: draw from the transition; the weight is the likelihood."""

    uses_transition_density = False
    graph_safe = True
    diagonal_prior = True  # the prior's covariance is not carried: its variances suffice
    gaussian_form = False  # the core's transition sampler and measurement density suffice

    @property
    def has_ancestor_law(self) -> bool:
        return True  # the transition: the filter evaluates it between every pair

    def propose(self, particles, log_weights, estimate, z, carry, generator, *, chunk=None) -> Proposed:
        x = self.model.sample_transition(particles, generator)  # (B, N, d)
        return Proposed(x, None, fallback=particles)
