"""Flow-induced Gaussian-mixture importance sampling (Zhang, Khojasteh, Atanasov & Meyer 2024, eqs 6-7):
the flow moves the parameters of every prior component, and the flowed mixture is the proposal."""

from __future__ import annotations

import math
from typing import Optional

import torch
from torch import nn

from torchflow.core import linalg
from torchflow.core.errors import ArgumentError, ArgumentTypeError
from torchflow.flows import FlowPrior, ParticleFlow, flow_gaussian
from torchflow.flows.integrate import EVALUATE_AT
from torchflow.flows.schedules import LambdaSchedule, resolve_schedule

RATIOS = ("mixture", "component")


class FlowedMixtureProposal(nn.Module):
    """Flow-induced Gaussian-mixture importance sampling (Zhang, Khojasteh, Atanasov &
    Meyer 2024, eqs 6-7).

    Instead of moving particles, the flow moves the *parameters* of every prior component
    (:func:`~torchflow.flows.flow_gaussian`): component n of the prior ``f = sum_n w_n N(mu_n, P_n)``
    becomes ``N(mu'_n, P'_n)``, and ``q = sum_n w_n N(mu'_n, P'_n)`` is the proposal. Each component
    draws the same number of samples (stratified); with ``ratio="mixture"`` (default) the weight of
    a sample is the full-mixture ratio ``omega = f(x) l(x) / q(x)``, with ``ratio="component"`` the
    cheaper per-component ratio ``N(x; mu_n, P_n) l(x) / N(x; mu'_n, P'_n)``. Either way
    ``sum_n w_n mean_i omega_ni`` is an unbiased estimate of ``int f l dx``, however coarse the
    lambda grid (a bad grid only makes q a poor proposal). The flows: ``pfi_d`` = EDH (Q = 0),
    ``pfi_s`` = Gromov, ``pfi_os`` = optimised diffusion.

    Everything is batched over any leading dimensions (runs x components x measurements): no
    Python loop over them.

    Args:
        flow: a :class:`~torchflow.flows.ParticleFlow` (its points are ignored: one point per
            component, its migrating mean).
        schedule: lambda schedule (default exponential, 29 steps, ratio 1.2; Zhang et al. use
            :class:`~torchflow.flows.schedules.GeometricSchedule` grids).
        ratio: ``"mixture"`` or ``"component"``.
        evaluate_at: ``"end"`` (default) or ``"start"``: the pseudo-time of each step's flow
            coefficients (:func:`~torchflow.flows.flow_gaussian`).
    """

    def __init__(
        self,
        flow: ParticleFlow,
        schedule: Optional[LambdaSchedule] = None,
        ratio: str = "mixture",
        evaluate_at: str = "end",
    ):
        super().__init__()
        if not isinstance(flow, ParticleFlow):
            raise ArgumentTypeError(f"flow: expected a torchflow ParticleFlow, got {type(flow).__name__}")
        if ratio not in RATIOS:
            raise ArgumentError(f"ratio: expected one of {RATIOS}, got {ratio!r}")
        if evaluate_at not in EVALUATE_AT:
            raise ArgumentError(f"evaluate_at: expected one of {EVALUATE_AT}, got {evaluate_at!r}")
        self.flow, self.schedule, self.ratio, self.evaluate_at = flow, resolve_schedule(schedule), ratio, evaluate_at

    def flowed(self, means: torch.Tensor, scale_trils: torch.Tensor, measurement):
        """``(means', covs')`` of every component ``(..., G, d)``, ``(..., G, d, d)`` flowed by the
        measurement term, whose ``z`` has one row per component (``prod(...) * G`` rows, in the
        order of ``means.reshape(-1, d)``)."""
        *batch, G, d = means.shape
        mu = means.reshape(-1, d)
        L = scale_trils.expand(*batch, G, d, d).reshape(-1, d, d)
        mu1, P1 = flow_gaussian(self.flow, measurement, FlowPrior(mu, L), self.schedule, self.evaluate_at)
        return mu1.reshape(*batch, G, d), P1.reshape(*batch, G, d, d)

    def sample(
        self,
        log_w: torch.Tensor,
        means: torch.Tensor,
        scale_trils: torch.Tensor,
        flowed_means: torch.Tensor,
        flowed_scale_trils: torch.Tensor,
        log_likelihood,
        n_samples: int,
        generator,
    ):
        """Draw ``n_samples`` from every flowed component and weigh them.

        Args:
            log_w: ``(B, G)`` log prior mixture weights (normalised).
            means, scale_trils: prior components ``(B, G, d)``, ``(B, G, d, d)``.
            flowed_means, flowed_scale_trils: the proposal's components, same shapes.
            log_likelihood: ``x (B, G, n, d) -> (B, G, n)``, log l(x).
            n_samples: samples per component.
            generator: ``torch.Generator`` or per-trial streams (``B`` leading).

        Returns:
            ``(x (B, G, n, d), log_weights (B, G, n), log_evidence (B,))``: samples, their log
            weights ``log w_n + log omega_ni`` (``omega = f l / q`` or the per-component ratio;
            the draws are stratified, n per component, so each sample carries its component's
            weight) and the log of the unbiased estimate ``sum_n w_n mean_i omega_ni`` of
            ``int f l dx`` (= the log of the mean of the weights times G).
        """
        B, G, d = means.shape
        xi = linalg.standard_normal((B, G, n_samples, d), dtype=means.dtype, device=means.device, generator=generator)
        x = flowed_means.unsqueeze(2) + xi @ flowed_scale_trils.transpose(-1, -2)
        if self.ratio == "component":
            log_f = linalg.mvn_log_prob(x, means.unsqueeze(2), scale_trils.unsqueeze(2))
            log_q = linalg.mvn_log_prob(x, flowed_means.unsqueeze(2), flowed_scale_trils.unsqueeze(2))
        else:
            log_f = _mixture_log_prob(x, log_w, means, scale_trils)
            log_q = _mixture_log_prob(x, log_w, flowed_means, flowed_scale_trils)
        log_omega = log_f + log_likelihood(x) - log_q
        log_weights = log_w.unsqueeze(-1) + log_omega
        log_ev = torch.logsumexp(log_weights, (-2, -1)) - math.log(n_samples)
        return x, log_weights, log_ev

    def extra_repr(self) -> str:
        return f"ratio={self.ratio!r}, evaluate_at={self.evaluate_at!r}"


def _mixture_log_prob(x: torch.Tensor, log_w: torch.Tensor, means: torch.Tensor, scale_trils: torch.Tensor):
    """``log sum_n w_n N(x; mu_n, L_n L_n^T)`` of ``x (B, G', n, d)`` under ``G`` components
    ``(B, G, d)`` (every sample against every component: one batched solve)."""
    B, G2, n, d = x.shape
    flat = x.reshape(B, 1, G2 * n, d)
    lp = linalg.mvn_log_prob(flat, means.unsqueeze(2), scale_trils.unsqueeze(2))  # (B, G, G2 n)
    return torch.logsumexp(log_w.unsqueeze(-1) + lp, 1).reshape(B, G2, n)
