"""Covariances carried by a particle filter's state, typed by what they belong to.

A PF-PF tracks the flow's prior covariance with an EKF/UKF, either once per trial (global and
clustered linearisation points) or once per particle (per-particle points, LEDH); the type says
which, and so how resampling treats it:

* :class:`TrialCovariance` ``(B, d, d)``: one per trial; resampling leaves it alone.
* :class:`ParticleCovariance` ``(B, N, d, d)``: one per particle; resampled with the particles.
  ``identical=True`` (declared by the filter: an EKF on a linear model gives every particle the
  same covariance) stores one ``(B, 1, d, d)`` that broadcasts, and resampling leaves it alone.

Clusters are rebuilt every step (:class:`~torchflow.flows.points.ClusteredPoints`), so a
per-cluster covariance never outlives a step: a clustered flow is given the trial's covariance at
its K points, ``(B, 1, d, d)`` broadcast over clusters.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import torch


@dataclass
class Covariance:
    """Base: ``matrix`` and how it follows resampling (:meth:`resampled`)."""

    matrix: torch.Tensor

    #: the tracker predicts at each particle (True) or at the trial's estimate (False)
    per_particle = False

    def resampled(self, index: torch.Tensor) -> "Covariance":
        """This covariance after the particles were resampled with ``index (B, N)``."""
        return self

    def transported(self, plan: torch.Tensor) -> "Covariance":
        """This covariance after transport resampling: new particle ``j`` is ``sum_i plan[b, i, j]
        x_i`` (``plan (B, N, N)``, columns summing to one)."""
        return self

    def like(self, matrix: torch.Tensor) -> "Covariance":
        """The same type with a new ``matrix`` (the step's updated covariance)."""
        return replace(self, matrix=matrix)


@dataclass
class TrialCovariance(Covariance):
    """One covariance per trial, ``(B, d, d)``."""


@dataclass
class ParticleCovariance(Covariance):
    """One covariance per particle, ``(B, N, d, d)``; with ``identical=True`` a single ``(B, 1, d, d)``
    that every particle shares (declared, e.g. an EKF on a linear model)."""

    identical: bool = False
    per_particle = True

    def resampled(self, index: torch.Tensor) -> "Covariance":
        if self.identical:
            return self
        from .resampling import gather_particles

        return self.like(gather_particles(self.matrix, index))

    def transported(self, plan: torch.Tensor) -> "Covariance":
        """Each new particle carries the same convex combination of the covariances (still
        positive definite)."""
        if self.identical:
            return self
        return self.like(torch.einsum("bij,bi...->bj...", plan.to(self.matrix.dtype), self.matrix))


__all__ = ["Covariance", "TrialCovariance", "ParticleCovariance"]
