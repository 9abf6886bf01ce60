"""Proposals of the particle filters: ``q(x_k | x_{k-1}, z_k)`` as small objects.

A particle filter step is (:meth:`torchflow.filters.base.ParticleFilterBase.step`):
``propose`` -> weigh with ``log p(x | x_prev) + log p(z | x) - log q`` -> resample; the weight
formula lives in one place (the base), the proposals only say how particles are drawn and with
what density:

* :class:`BootstrapProposal`: ``q`` is the transition, so the weight is the likelihood alone.
* :class:`InvertibleFlowProposal`: a deterministic flow moves ``eta_0 ~ p(. | x_{k-1})``;
  ``log q = log p(eta_0 | x_{k-1}) - log|det d eta_1 / d eta_0|`` (Li & Coates 2017).
* :class:`StochasticFlowProposal`: a stochastic flow's Euler-Maruyama law, tracked exactly from
  the Gaussian transition (Pal & Coates 2019, Algorithm 1).

The flow proposals own the flow, the lambda schedule, the linearisation points (global, per
particle, clustered) and the covariance tracker (EKF/UKF) that gives the flow its prior; a
proposal without a tracker (the Gaussian PFs to come) simply has none.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch
from torch import nn

from . import linalg
from .covariances import Covariance
from .flows import FlowPrior, ParticleFlow, integrate_flow, resolve_points
from .schedules import ExponentialSchedule, LambdaSchedule


@dataclass
class Proposed:
    """What a proposal returns for one step.

    Attributes:
        particles: ``(B, N, d)`` the proposed ``x_k``.
        log_q: ``(B, N)`` log proposal density of each particle given its parent, or ``None``
            when ``q`` is the transition itself (the weight is then the likelihood alone).
        cov: the filter state's covariance after the step (flow proposals' tracker: a
            :class:`~torchflow.covariances.Covariance`), or ``None``.
        fallback: ``(B, N, d)`` finite positions for particles repaired by ``nonfinite="recover"``.
    """

    particles: torch.Tensor
    log_q: Optional[torch.Tensor]
    cov: Optional["Covariance"] = None
    fallback: Optional[torch.Tensor] = None


class Proposal(nn.Module):
    """Base class: :meth:`propose` draws the step's particles and states their density."""

    def propose(self, filt, state, z: torch.Tensor, generator) -> Proposed:
        """Particles for observation ``z (B, m)`` from ``state`` (a ``ParticleState``); ``filt`` is
        the particle filter (its model, and :meth:`per_particle` for memory-bounded blocks)."""
        raise NotImplementedError


class BootstrapProposal(Proposal):
    """``q = p(x_k | x_{k-1})``: draw from the transition; the weight is the likelihood."""

    def propose(self, filt, state, z, generator) -> Proposed:
        x = filt.model.sample_transition(state.particles, generator)  # (B, N, d)
        return Proposed(x, None, fallback=state.particles)


def _tracker(model, covariance: str):
    from .filters.kalman import ExtendedKalmanFilter, UnscentedKalmanFilter

    if covariance == "ekf":
        return ExtendedKalmanFilter(model, validate=False)
    if covariance == "ukf":
        return UnscentedKalmanFilter(model, validate=False)
    raise ValueError(f"covariance: expected 'ekf' or 'ukf', got {covariance!r}")


class FlowProposal(Proposal):
    """A particle flow as proposal (base of the invertible and stochastic flow proposals).

    Each step: the tracker predicts the flow's Gaussian prior where the state's covariance lives
    (at each particle, or at the trial's estimate: :mod:`torchflow.covariances`), the
    linearisation points place it (:meth:`~torchflow.flows.points.LinearisationPoints.place`),
    the flow migrates ``eta_0 ~ p(. | x_{k-1})``, and the tracker updates the covariance. Nothing
    here depends on which points are used, beyond the declared ``per_particle`` (particles that
    flow independently may be flowed in blocks to bound memory).

    Args:
        model: the state-space model (for the covariance tracker).
        flow: a :class:`~torchflow.flows.ParticleFlow`.
        schedule: lambda schedule (default exponential, 29 steps, ratio 1.2).
        covariance: ``"ekf"`` or ``"ukf"``: the tracker that gives the flow its prior P.
        points: a :class:`~torchflow.flows.points.LinearisationPoints`, a name (``"particle"``,
            ``"global"``, ``"clustered"``) or ``None`` (the flow's default).
        n_clusters, alpha, sweeps: knobs of clustered points given by name
            (:class:`~torchflow.flows.points.ClusteredPoints`).
        jacobian_in_weight: invertible flows: include ``log|det|`` in ``log q`` (default True;
            False is seed 004's printed weight, whose evidence is biased: a knob for comparison).
    """

    def __init__(self, model, flow: ParticleFlow, schedule: Optional[LambdaSchedule] = None,
                 covariance: str = "ekf", points=None, n_clusters: int = 100,
                 alpha: float = 0.25, sweeps: int = 10, jacobian_in_weight: bool = True):
        super().__init__()
        self.flow = flow
        self.schedule = schedule or ExponentialSchedule()
        self.covariance = covariance
        self.tracker = _tracker(model, covariance)
        #: the linearisation-point strategy (:mod:`torchflow.flows.points`)
        self.points = resolve_points(flow, points, n_clusters=n_clusters, alpha=alpha, sweeps=sweeps)
        self.jacobian_in_weight = jacobian_in_weight

    def _migrate(self, model, eta0, x_prev, z, prior, generator, log_q0, noise=None, index=None):
        """Flow ``eta0`` from ``prior`` at the points (``index``: each particle's point); returns
        the particles and their log-density ``(B, N)``."""
        raise NotImplementedError

    def propose(self, filt, state, z, generator) -> Proposed:
        model, pts, cov = filt.model, self.points, state.cov
        x_prev = state.particles  # (B, N, d)
        if self.flow.stochastic and not model.gaussian_transition:
            # the tracked proposal law starts from the Gaussian fit, so eta_0 must be drawn from it
            # (MODELS.md §14e); the weight keeps the model's exact transition density
            eta0 = model.sample_transition_gaussian(x_prev, generator)
        else:
            eta0 = model.sample_transition(x_prev, generator)
        log_q0 = None if self.flow.stochastic else model.transition_log_prob(eta0, x_prev)
        at = x_prev if cov.per_particle else state.estimate
        m_pred, P_pred = self.tracker.predict(at, cov.matrix)  # (B, [N,] d), (B, [N|1,] d, d)
        L_pred = linalg.safe_cholesky(P_pred)
        prior, index = pts.place(model, x_prev, m_pred, L_pred, z)
        if pts.per_particle:
            # every particle flows with its own prior: blocks of particles are independent
            B, N = eta0.shape[:2]
            chunk = filt.flow_chunk(N)  # particle_chunk, or cache-sized blocks in high dimension
            blocked = bool(chunk) and N > chunk
            tape = {}

            def draw(sl):
                """A block's diffusion noise: slices of whole-cloud draws (one per pseudo-time step,
                drawn when the first block needs it), so blocking does not change the numbers."""
                def noise(j, shape):
                    if j not in tape:
                        tape[j] = linalg.standard_normal((B, N, shape[-1]), dtype=eta0.dtype, device=eta0.device,
                                                         generator=generator)
                    return tape[j][:, sl]
                return noise

            def block(eta0, x_prev, m, L, log_q0, particles):
                kw = {"noise": draw(particles)} if blocked and self.flow.stochastic else {}
                return self._migrate(model, eta0, x_prev, z, FlowPrior(m, L), generator, log_q0, **kw)

            x, log_q = filt.per_particle(block, eta0, x_prev, prior.mean, prior.scale_tril, log_q0, pass_slice=True,
                                         chunk=chunk)
        else:
            x, log_q = self._migrate(model, eta0, x_prev, z, prior, generator, log_q0, index=index)
        _, P_post, _ = self.tracker.update(m_pred, P_pred, z.unsqueeze(1) if cov.per_particle else z)
        return Proposed(x, log_q, cov=cov.like(P_post), fallback=eta0)


class InvertibleFlowProposal(FlowProposal):
    """Deterministic flow: ``log q(x) = log p(eta_0 | x_prev) - log|det d x / d eta_0|``."""

    def _migrate(self, model, eta0, x_prev, z, prior, generator, log_q0, noise=None, index=None):
        out = integrate_flow(self.flow, model, eta0, z, prior, self.schedule, points=self.points, index=index)
        # jacobian_in_weight=False: seed 004's printed weight (biased evidence; a knob for comparison)
        return out.particles, (log_q0 - out.log_det if self.jacobian_in_weight else log_q0)


class StochasticFlowProposal(FlowProposal):
    """Stochastic flow: the exact Gaussian law of the Euler-Maruyama map started from the Gaussian
    transition ``N(f(x_prev), V)`` (Pal & Coates 2019, Algorithm 1)."""

    def _migrate(self, model, eta0, x_prev, z, prior, generator, log_q0, noise=None, index=None):
        start = FlowPrior(model.transition_mean(x_prev), model.transition_scale_tril(x_prev))
        out = integrate_flow(self.flow, model, eta0, z, prior, self.schedule, generator=generator, proposal=start,
                             noise=noise, points=self.points, index=index)
        return out.particles, out.log_proposal


RATIOS = ("mixture", "component")


class FlowedMixtureProposal(nn.Module):
    """Flow-induced Gaussian-mixture importance sampling (seed 002; MODELS.md §12.2).

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
        schedule: lambda schedule (default exponential, 29 steps, ratio 1.2; seed 002 uses
            :class:`~torchflow.schedules.GeometricSchedule` grids).
        ratio: ``"mixture"`` or ``"component"``.
        evaluate_at: ``"end"`` (default) or ``"start"``: the pseudo-time of each step's flow
            coefficients (:func:`~torchflow.flows.flow_gaussian`).
    """

    def __init__(self, flow: ParticleFlow, schedule: Optional[LambdaSchedule] = None, ratio: str = "mixture",
                 evaluate_at: str = "end"):
        super().__init__()
        if not isinstance(flow, ParticleFlow):
            raise TypeError(f"flow: expected a torchflow ParticleFlow, got {type(flow).__name__}")
        if ratio not in RATIOS:
            raise ValueError(f"ratio: expected one of {RATIOS}, got {ratio!r}")
        from .flows.integrate import EVALUATE_AT

        if evaluate_at not in EVALUATE_AT:
            raise ValueError(f"evaluate_at: expected one of {EVALUATE_AT}, got {evaluate_at!r}")
        self.flow, self.schedule, self.ratio, self.evaluate_at = flow, schedule or ExponentialSchedule(), ratio, evaluate_at

    def flowed(self, means: torch.Tensor, scale_trils: torch.Tensor, measurement):
        """``(means', covs')`` of every component ``(..., G, d)``, ``(..., G, d, d)`` flowed by the
        measurement term, whose ``z`` has one row per component (``prod(...) * G`` rows, in the
        order of ``means.reshape(-1, d)``)."""
        from .flows import flow_gaussian

        *batch, G, d = means.shape
        mu = means.reshape(-1, d)
        L = scale_trils.expand(*batch, G, d, d).reshape(-1, d, d)
        mu1, P1 = flow_gaussian(self.flow, measurement, FlowPrior(mu, L), self.schedule, self.evaluate_at)
        return mu1.reshape(*batch, G, d), P1.reshape(*batch, G, d, d)

    def sample(self, log_w: torch.Tensor, means: torch.Tensor, scale_trils: torch.Tensor, flowed_means: torch.Tensor,
               flowed_scale_trils: torch.Tensor, log_likelihood, n_samples: int, generator):
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


def flow_proposal(model, flow: ParticleFlow, **kwargs) -> FlowProposal:
    """The flow proposal for ``flow``: invertible (deterministic flows) or stochastic."""
    cls = StochasticFlowProposal if flow.stochastic else InvertibleFlowProposal
    return cls(model, flow, **kwargs)


__all__ = ["Proposed", "Proposal", "BootstrapProposal", "FlowProposal", "InvertibleFlowProposal",
           "StochasticFlowProposal", "flow_proposal", "FlowedMixtureProposal"]
