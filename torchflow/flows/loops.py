"""The pseudo-time loops of the fused flow kernels (:mod:`torchflow.flows.kernels.steps`).

:func:`run_flow` integrates a flow at per-particle points with the kernel that
:func:`torchflow.flows.select.flow_kernel` chose; it returns what the reference loop
(:func:`torchflow.flows.integrate._integrate`) returns for the same inputs, to round-off.
"""

from __future__ import annotations

import torch

from torchflow.core import linalg
from torchflow.core.errors import ArgumentError
from torchflow.flows import select
from torchflow.flows.base import FlowOutput, _gather_points
from torchflow.flows.kernels import steps


def run_flow(
    kernel: str,
    flow,
    measurement,
    particles: torch.Tensor,
    prior,
    index,
    eps_all,
    lam_all,
    generator,
    proposal,
    noise,
    start=None,
) -> FlowOutput:
    """Integrate ``flow`` with ``kernel`` (``"lanes"``, ``"diagonal"`` or ``"gromov"``).

    Args: as :func:`torchflow.flows.integrate._integrate` (``prior`` at per-particle points
    ``(B, N, d)``, ``eps_all`` the pair ``(device steps, host steps)``); no Gaussian image.
    """
    B, N, d = particles.shape
    eps_all = eps_all[0]
    prior = prior.reduced(measurement.support)
    measurement.prepare(particles)
    aux, eta = (prior.mean if start is None else start), particles
    k = d if measurement.support is None else len(measurement.support)
    lams, epss = lam_all.to(torch.float64), eps_all.to(torch.float64)
    eta, aux = eta.contiguous(), aux.contiguous()
    if kernel == "gromov":
        return _gromov(flow, measurement, eta, aux, prior, proposal, lams, epss, k, generator, noise)
    log_det = torch.zeros(B, aux.shape[-2], dtype=particles.dtype, device=particles.device)
    if kernel == "diagonal":
        log_det = log_det.to(torch.float64)
        step = steps.DiagonalSteps(prior.scale_tril, prior.cov_cols, prior.mean, lams, epss)
        for j in range(len(eps_all)):
            rows = measurement.at_diagonal(aux)  # W's diagonal and y without d x d matrices, where the model gives them
            if rows is None:
                lin = measurement.at(aux)
                rows = (lin.diag if lin.diag is not None else lin.W.diagonal(dim1=-2, dim2=-1), lin.y)
            eta, aux = step(j, eta, aux, log_det, *rows)
        log_det = log_det.to(particles.dtype)
    elif kernel == "lanes":
        inside = select.measured_inside(measurement, prior.support, k)
        step = steps.ParticleSteps(
            prior.cols,
            prior.cols_support,
            prior.cov_cols,
            prior.mean,
            prior.support,
            lams,
            epss,
            inside,
            measurement.inv_sigma,
            measurement.z_scaled if inside is not None else None,
            form=select.gpu_form(),
            float32=select.gpu_float32(),
        )
        for j in range(len(eps_all)):
            if inside is not None:
                eta, aux = step(j, eta, aux, log_det)
            else:
                lin = measurement.at(aux, prior.support)
                eta, aux = step(j, eta, aux, log_det, lin.W, lin.y)
    else:
        raise ArgumentError(f"kernel: expected one of {select.FLOW_KERNELS}, got {kernel!r}")
    log_det = log_det.expand(B, N) if index is None else _gather_points(log_det.unsqueeze(-1), index).squeeze(-1)
    return FlowOutput(eta, log_det, aux)


def _gromov(flow, measurement, eta, aux, prior, proposal, lams, epss, k, generator, noise) -> FlowOutput:
    """The Gromov flow's pseudo-steps and, given ``proposal``, its tracked Gaussian law."""
    B, N, d = eta.shape
    track = flow.stochastic and proposal is not None
    if track:  # the law N(mu (B, N, d), Sig (B, N|1, d, d)) the particles were drawn from
        mu, Sig = proposal.mean.expand(B, N, d), proposal.scale_tril @ proposal.scale_tril.transpose(-1, -2)
        Sig = Sig.expand(B, 1, d, d) if Sig.dim() == 2 else Sig
    inside = select.measured_inside(measurement, prior.support, k)
    step = steps.GromovSteps(
        prior.cols,
        prior.cols_support,
        prior.support,
        lams,
        epss,
        inside,
        measurement.inv_sigma,
        measurement.z_scaled if inside is not None else None,
    )
    shape = (B, N, measurement.z.shape[-1])  # the diffusion N (W^T xi) draws one normal per measurement row
    for j in range(len(epss)):
        lin = None if inside is not None else measurement.at(aux, prior.support)
        xi = (
            noise(j, shape)
            if noise is not None
            else linalg.standard_normal(shape, dtype=eta.dtype, device=eta.device, generator=generator)
        )
        eta, aux, mu_j, Sig_j = step(
            j, eta, aux, mu if track else None, Sig if track else None, xi, *(() if lin is None else (lin.W, lin.y))
        )
        if track:
            mu, Sig = mu_j, Sig_j
    if track:  # each particle's log-density under its law
        Sig = linalg.symmetrize(Sig)
        log_q = linalg.mvn_log_prob(eta, mu, linalg.safe_cholesky(Sig))
        return FlowOutput(eta, None, aux, log_proposal=log_q, proposal_mean=mu, proposal_cov=Sig)
    return FlowOutput(eta, None, aux)
