"""Particle flows: a flow states the drift ``dx/dlambda = A x + b`` at a linearisation point;
one integrator (:func:`integrate_flow`) steps every flow over a lambda schedule.

Shapes: a *global* flow (EDH-type) linearises once per trial, so its coefficients are
``A (B, d, d)``, ``b (B, d)``; a *local* flow (LEDH-type) once per particle, ``A (B, N, d, d)``,
``b (B, N, d)``. The integrator migrates the particles ``(B, N, d)`` and the auxiliary
linearisation point(s) with the same coefficients and accumulates ``log|det(I + eps A)|``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import torch
from torch import nn

from .. import linalg
from ..schedules import ExponentialSchedule, LambdaSchedule


@dataclass
class FlowCoefficients:
    """Drift ``A x + b`` of one pseudo-time step.

    ``A`` is either an explicit tensor, ``(B, d, d)`` (global), ``(B, 1, d, d)`` (shared by a
    trial's particles) or ``(B, N, d, d)`` (local), or, when forming it would cost more than
    applying it, an operator ``apply_A(V)`` acting on stacked vectors ``V (..., d, k)``.

    Attributes:
        A: explicit matrix or ``None``.
        b: ``(B, d)`` or ``(B, N, d)``.
        log_det: ``log|det(I + eps A)|``, ``(B,)``, ``(B, 1)`` or ``(B, N)``.
        apply_A: operator form of A (used when ``A`` is ``None``).
    """

    A: Optional[torch.Tensor]
    b: torch.Tensor
    log_det: torch.Tensor
    apply_A: Optional[Callable[[torch.Tensor], torch.Tensor]] = None

    def drift(self, *points: torch.Tensor):
        """``A x + b`` for each ``x`` of ``points`` (each batched like ``b``)."""
        if self.A is not None:
            if self.A.dim() >= 4 and self.A.shape[-3] > 1 and len(points) > 1:
                AX = self.A @ torch.stack(points, -1)  # per-point A: one product for all vectors
                return [AX[..., i] + self.b for i in range(len(points))]
            return [linalg.matvec(self.A, x) + self.b for x in points]
        AX = self.apply_A(torch.stack(points, -1))  # one pass for all the vectors
        return [AX[..., i] + self.b for i in range(len(points))]


@dataclass
class FlowPrior:
    """The Gaussian prior a flow starts from, per trial (global) or per particle (local).

    Attributes:
        mean: ``eta_bar_0``, ``(B, d)`` or ``(B, N, d)``.
        scale_tril: lower Cholesky factor of the prior covariance P, ``(B, d, d)`` or ``(B, N, d, d)``.
    """

    mean: torch.Tensor
    scale_tril: torch.Tensor


@dataclass
class FlowOutput:
    """Result of :func:`integrate_flow`.

    Attributes:
        particles: ``(B, N, d)`` migrated particles (``eta_1``).
        log_det: ``(B, N)`` log|det| of the particle map ``eta_0 -> eta_1``.
        aux: final auxiliary point(s), ``(B, d)`` or ``(B, N, d)``.
    """

    particles: torch.Tensor
    log_det: torch.Tensor
    aux: torch.Tensor


class ParticleFlow(nn.Module):
    """Base class of flows. Subclasses implement :meth:`coefficients`.

    Attributes:
        local: linearise per particle (True) or once per trial at the migrating mean (False).
    """

    local: bool = False

    def coefficients(self, model, z: torch.Tensor, aux: torch.Tensor, prior: FlowPrior,
                     lam: torch.Tensor, eps: torch.Tensor) -> FlowCoefficients:
        """Drift at pseudo-time ``lam`` (after the step of size ``eps``), linearised at ``aux``.

        Args:
            model: the state-space model (measurement function, Jacobian, noise).
            z: ``(B, m)`` observation.
            aux: linearisation point(s), ``(B, d)`` (global) or ``(B, N, d)`` (local).
            prior: the flow's Gaussian prior, batched like ``aux``.
            lam, eps: 0-d tensors.
        """
        raise NotImplementedError


def _bcast_obs(z: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """``z (B, m)`` viewed to broadcast against points ``like (B, ..., d)``."""
    return z.reshape(z.shape[0], *([1] * (like.dim() - 2)), z.shape[-1])


def integrate_flow(
    flow: ParticleFlow,
    model,
    particles: torch.Tensor,
    z: torch.Tensor,
    prior: FlowPrior,
    schedule: Optional[LambdaSchedule] = None,
) -> FlowOutput:
    """Euler-integrate ``d eta / d lambda = A eta + b`` from lambda = 0 to 1.

    The auxiliary point starts at ``prior.mean`` and migrates with the same coefficients; for a
    local flow each particle has its own. The accumulated ``log|det(I + eps_j A_j)|`` is the
    log-Jacobian of the particle map, which the PF-PF weight needs.

    Args:
        flow: the flow (states A, b).
        model: state-space model.
        particles: ``(B, N, d)`` samples eta_0 from the prior.
        z: ``(B, m)``.
        prior: :class:`FlowPrior`, ``(B, d)`` (global) or ``(B, N, d)`` (local).
        schedule: lambda schedule (default: exponential, 29 steps, ratio 1.2).

    Returns:
        :class:`FlowOutput`.
    """
    schedule = schedule or ExponentialSchedule()
    eps_all, lam_all = schedule.steps(dtype=particles.dtype, device=particles.device)
    B, N, d = particles.shape
    aux = prior.mean
    log_det = torch.zeros(B, N, dtype=particles.dtype, device=particles.device)
    eta = particles
    if not flow.local:
        # A global flow moves every particle of a trial by the same affine map: compose it on
        # (d, d) matrices, M <- (I + eps A) M, c <- (I + eps A) c + eps b, and apply it once.
        eye = torch.eye(d, dtype=particles.dtype, device=particles.device)
        M = eye.expand(B, d, d)
        c = torch.zeros(B, d, dtype=particles.dtype, device=particles.device)
        for j in range(len(eps_all)):
            eps, lam = eps_all[j], lam_all[j]
            co = flow.coefficients(model, z, aux, prior, lam, eps)
            step = eye + eps * co.A  # (B, d, d)
            M = step @ M
            c = linalg.matvec(step, c) + eps * co.b
            aux = linalg.matvec(step, aux) + eps * co.b
            log_det = log_det + co.log_det.unsqueeze(-1)
        eta = torch.baddbmm(c.unsqueeze(1), particles, M.transpose(-1, -2))
        return FlowOutput(eta, log_det, aux)
    for j in range(len(eps_all)):
        eps, lam = eps_all[j], lam_all[j]
        c = flow.coefficients(model, z, aux, prior, lam, eps)
        d_eta, d_aux = c.drift(eta, aux)
        eta = eta + eps * d_eta
        aux = aux + eps * d_aux
        log_det = log_det + c.log_det
    return FlowOutput(eta, log_det, aux)
