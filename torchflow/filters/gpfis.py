"""Gaussian particle flow importance sampling (GPFIS; Bunch & Godsill 2016): the
particle filter with the GPFIS proposal (:class:`~torchflow.proposals.GPFISProposal`; the transport
is :func:`~torchflow.flows.gpfis.gpfis_flow`)."""

from __future__ import annotations

from typing import Optional

from torchflow.core.errors import ArgumentError
from torchflow.filters.base import ParticleFilter
from torchflow.flows.gpfis import gpfis_flow
from torchflow.flows.schedules import LambdaSchedule
from torchflow.proposals import GPFISProposal


class GaussianParticleFlowImportanceSampler(ParticleFilter):
    """GPFIS particle filter (Bunch & Godsill 2016): every particle is moved from the Gaussian
    transition by its own progressively linearised Gaussian flow (:func:`gpfis_flow`), and weighted
    by ``p(x | x_prev) p(z | x) / q(x)`` with the flow's exact Jacobian in ``q``.

    The transition must be Gaussian (``sample_transition``/``transition_scale_tril``), the
    measurement term Gaussian (the flows' :class:`~torchflow.flows.GaussianMeasurement`).

    Args:
        model: state-space model.
        n_particles: N.
        schedule: lambda grid (default exponential, 29 steps, ratio 1.2).
        root: transport root, ``"cholesky"`` (default) or ``"symmetric"`` (:mod:`torchflow.flows.gpfis`).
        jacobian: each step's Jacobian, ``"analytic"`` (default: the derivative written out, with
            the model's :meth:`~torchflow.models.GaussianStateSpaceModel.measurement_hessian_blocks`) or
            ``"autodiff"`` (forward mode through the whole step); the symmetric root always uses
            autodiff.
        gamma: diffusion rate; only 0 (deterministic, Bunch & Godsill's suggestion followed by
            Li & Coates 2016) is implemented.
        other arguments: see :class:`~torchflow.filters.ParticleFilter`.
    """

    random_stream = "gpfis"

    def __init__(
        self,
        model,
        *,
        schedule: Optional[LambdaSchedule] = None,
        root: str = "cholesky",
        jacobian: str = "analytic",
        gamma: float = 0.0,
        **kwargs,
    ):
        if isinstance(gamma, bool) or not isinstance(gamma, (int, float)) or gamma != 0:
            raise ArgumentError(f"gamma: only the deterministic GPFIS (gamma = 0) is implemented, got {gamma!r}")
        super().__init__(model, GPFISProposal(model, schedule, root, jacobian), **kwargs)


GPFIS = GaussianParticleFlowImportanceSampler

__all__ = ["gpfis_flow", "GPFISProposal", "GaussianParticleFlowImportanceSampler", "GPFIS"]
