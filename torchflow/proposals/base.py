"""The proposal contract: ``q(x_k | x_{k-1}, z_k)`` as a module fed tensors, never the filter.

A particle filter step (:class:`~torchflow.filters.ParticleFilter`) is ``propose`` -> weigh
(``log p(x | x_prev) + log p(z | x) - log q``, in the filter, once) -> estimate -> resample. A
proposal only says how particles are drawn and with what density, from explicit tensors: the
previous particles and log-weights, the previous estimate, z, the state it carries between steps
(a tracked covariance), a generator, and the largest block of particles to evaluate at once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import torch
from torch import nn

from torchflow.core import tuning
from torchflow.core.covariances import Covariance
from torchflow.core.errors import ArgumentTypeError
from torchflow.models.base import StateSpaceModel, require_gaussian
from torchflow.models.structure import bytes_per_point


@dataclass
class Proposed:
    """What a proposal returns for one step.

    Attributes:
        particles: ``(B, N, d)`` the proposed ``x_k``.
        log_q: ``(B, N)`` log proposal density of each particle given its parent, or ``None``
            when ``q`` is the transition itself (the weight is then the likelihood alone).
        cov: the state the proposal carries to the next step (a tracked
            :class:`~torchflow.core.covariances.Covariance`: per trial, or per particle and resampled
            with them), or ``None``.
        fallback: ``(B, N, d)`` finite positions for particles repaired by ``nonfinite="recover"``.
        log_evidence: ``(B,)`` the tracker's Gaussian log-evidence of ``z`` (proposals that track a
            belief; the unweighted flow filters report it), else ``None``.
        ancestor_law: with :attr:`Proposal.report_ancestor_law`, the Gaussian law of ``x`` given
            each slot's parent, ``(mean (B, N, d), scale_tril (B, N|1, d, d))``: what the marginal
            weights' proposal mixture is made of (:mod:`torchflow.filters.marginal`); else ``None``.
    """

    particles: torch.Tensor
    log_q: Optional[torch.Tensor]
    cov: Optional[Covariance] = None
    fallback: Optional[torch.Tensor] = None
    log_evidence: Optional[torch.Tensor] = None
    ancestor_law: Optional[Tuple[torch.Tensor, torch.Tensor]] = None


class Proposal(nn.Module):
    """Base class of the proposals.

    Args:
        model: the :class:`~torchflow.models.StateSpaceModel` whose transition the proposal draws
            from (a submodule: the filter that holds the proposal holds the same model).

    Subclasses implement :meth:`propose`; those that carry a state between steps implement
    :meth:`init_carry`; :meth:`bytes_per_trial` is the one memory formula the chunk planner reads.

    Attributes:
        uses_transition_density: the filter weighs this proposal's particles by
            ``p(x_k | x_{k-1})`` (True but for the bootstrap proposal and the unweighted flows),
            so the model needs a positive definite transition covariance
            (:meth:`~torchflow.filters.ParticleFilter.check_model`).
        gaussian_form: the proposal reads the model's Gaussian form (a
            :class:`~torchflow.models.GaussianStateSpaceModel`; checked at construction).
        graph_safe: :meth:`propose` makes the same kernels and the same draws (kinds, shapes) at
            every step of one layout, with no host read, so the filter's whole step may be replayed
            from a CUDA graph (:mod:`torchflow.filters.graph_step`), when the model declares the
            same. Declared by each class itself, not inherited (a subclass may draw otherwise):
            the bootstrap proposal and the deterministic flows' proposal (with graph-safe points).
        diagonal_prior: :meth:`init_carry` does not read the prior covariance, so the filter may
            start from a :class:`~torchflow.core.covariances.DiagonalCovariance` without its ``d x d``
            matrix. Declared by each class itself, not inherited: the bootstrap proposal.
        report_ancestor_law: set by a filter with marginal weights: :meth:`propose` also returns
            :attr:`Proposed.ancestor_law` (proposals with :attr:`has_ancestor_law`).
    """

    uses_transition_density: bool = True
    graph_safe: bool = False
    diagonal_prior: bool = False
    #: the proposal reads the model's Gaussian form (all but the bootstrap proposal)
    gaussian_form: bool = True
    report_ancestor_law: bool = False

    @property
    def has_ancestor_law(self) -> bool:
        """Whether the density of a particle given any parent is available for marginal weights:
        the transition itself (``log_q is None``) or a Gaussian :attr:`Proposed.ancestor_law`."""
        return False

    def __init__(self, model: StateSpaceModel):
        super().__init__()
        if not isinstance(model, StateSpaceModel):
            raise ArgumentTypeError(f"model: expected a torchflow StateSpaceModel, got {type(model).__name__}")
        if self.gaussian_form:
            require_gaussian(model, type(self).__name__)
        self.model = model

    def init_carry(self, cov: torch.Tensor, n_particles: int) -> Optional[Covariance]:
        """The state carried into the first step, from the prior covariance ``cov (B, d, d)``."""
        return None

    def propose(
        self,
        particles: torch.Tensor,
        log_weights: torch.Tensor,
        estimate: torch.Tensor,
        z: torch.Tensor,
        carry: Optional[Covariance],
        generator,
        *,
        chunk: Optional[int] = None,
    ) -> Proposed:
        """Particles for observation ``z (B, m)``.

        Args:
            particles: ``(B, N, d)`` the previous particles (after resampling).
            log_weights: ``(B, N)`` their normalised log-weights.
            estimate: ``(B, d)`` the previous weighted-mean estimate (before resampling).
            z: ``(B, m)``.
            carry: what the previous step returned as :attr:`Proposed.cov` (or :meth:`init_carry`).
            generator: ``torch.Generator`` or per-trial :class:`~torchflow.core.random.TrialStreams`.
            chunk: evaluate per-particle work in blocks of at most this many particles (``None``:
                the proposal's own choice).
        """
        raise NotImplementedError

    def bytes_per_trial(self, n_particles: int) -> int:
        """Rough peak memory of one trial in one step with ``n_particles`` (weighing included)."""
        d, m = self.model.state_dim, self.model.obs_dim
        N = int(n_particles)
        return 8 * N * (6 * d + 3 * m + 8) + N * bytes_per_point(self.model)

    def preferred_chunk_trials(self, n_particles: int) -> Optional[int]:
        """Largest number of trials per call that runs at full speed (``None``: memory decides).
        Whole-cloud passes stay cache-resident up to a measured size (:mod:`torchflow.core.tuning`)."""
        per_trial = int(n_particles) * self.model.state_dim * torch.finfo(self.model.dtype).bits // 8
        return max(1, tuning.get().cache_bytes_per_call // max(per_trial, 1))
