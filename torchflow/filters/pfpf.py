"""Particle flow filters: the PF-PF (Li & Coates 2017) and the unweighted flow filters
(Ding & Coates 2012). Both take any :class:`~torchflow.flows.ParticleFlow` and lambda schedule;
the flow maths lives in :mod:`torchflow.flows`, the weighting/resampling in
:class:`~torchflow.filters.base.ParticleFilterBase`.
"""
from __future__ import annotations

import math
from typing import Optional

import torch

from .. import linalg
from ..flows import (EDHFlow, FlowPrior, GeodesicFlow, GromovFlow, LEDHFlow, OptimalDiffusionFlow, ParticleFlow,
                     integrate_flow, resolve_points)
from ..flows.points import flow_points_per_call
from ..proposals import _tracker, flow_proposal
from ..schedules import ExponentialSchedule, LambdaSchedule
from .._checks import check_count
from ..flows.points import ClusteredPoints
from .base import Filter, GaussianState, ParticleFilterBase, ParticleState


def _flow(flow):
    if flow is None:
        return LEDHFlow()
    if isinstance(flow, str):
        flows = {"edh": EDHFlow, "ledh": LEDHFlow, "geodesic": GeodesicFlow, "gromov": GromovFlow,
                 "osd": OptimalDiffusionFlow}
        if flow not in flows:
            raise ValueError(f"flow: expected a ParticleFlow or one of {sorted(flows)}, got {flow!r}")
        return flows[flow]()
    if not isinstance(flow, ParticleFlow):
        raise TypeError(f"flow: expected a torchflow ParticleFlow, got {type(flow).__name__}")
    return flow


class _FlowFilterMixin:
    """Flow, schedule and covariance tracker shared by the flow filters."""

    def _init_flow(self, model, flow, schedule, covariance, points=None):
        self.flow = _flow(flow)
        self.schedule = schedule or ExponentialSchedule()
        self.covariance = covariance
        self.tracker = _tracker(model, covariance)
        #: where the flow is linearised (:mod:`torchflow.flows.points`; default: the flow's own)
        self.points = resolve_points(self.flow, points)

    def preferred_chunk_trials(self, n_particles=None):
        N = int(n_particles or self.n_particles)
        pref = self.points.preferred_chunk_trials(N)
        if pref is not None and self.points.per_particle:  # high dimension: cache-sized calls
            pref = min(pref, max(1, flow_points_per_call(self.model) // N))
        return pref

    def _flow_bytes(self, N: int, cov_mats: int) -> int:
        """Rough per-trial memory: ``cov_mats`` d x d matrices per particle for local flows."""
        d, m = self.model.state_dim, self.model.obs_dim
        per_point = cov_mats * d * d + 4 * m * d + 8 * d + 4 * m
        shared = (self.covariance == "ekf" and self.model.linear_dynamics and self.model.linear_measurement)
        if shared:  # linear models: one prior factor and Jacobian per trial, vectors per particle
            flow = cov_mats * d * d + N * (8 * d + 3 * m)
        else:
            flow = N * per_point if self.points.per_particle else N * (8 * d + 3 * m) + 4 * per_point
        return 8 * flow + N * self.model.bytes_per_point()


class ParticleFlowParticleFilter(_FlowFilterMixin, ParticleFilterBase):
    """Particle flow particle filter (PF-PF; Li & Coates 2017, Algorithms 1-2).

    Each step, for particle i: draw ``eta_0^i ~ p(. | x_{k-1}^i)``, migrate it with the flow from
    lambda = 0 to 1 (linearised at a deterministic auxiliary point started at the noise-free
    prediction), and weight the result ``x_k^i = eta_1^i`` by

        w_k^i ∝ w_{k-1}^i p(x_k^i | x_{k-1}^i) p(z_k | x_k^i) theta^i / p(eta_0^i | x_{k-1}^i),

    ``theta^i = |det d eta_1 / d eta_0|``. The flow's Gaussian prior covariance P comes from an EKF
    (or UKF) prediction: per particle for local flows (LEDH; each particle carries its own
    covariance, updated by an EKF/UKF update at its predicted point and resampled with it), per
    trial for global flows (EDH; predicted from the weighted-mean estimate).

    Args:
        model: state-space model.
        flow: a :class:`~torchflow.flows.ParticleFlow` (or ``"edh"``, ``"ledh"``, ``"geodesic"``,
            ``"gromov"``, ``"osd"``); default LEDH. With a stochastic flow (Gromov, optimised
            diffusion) the weight divides by the particle's exact Gaussian proposal density,
            ``N(x_k; mu_1, S_1)``, tracked through the flow from ``N(f(x_{k-1}), V)``
            (Pal & Coates 2019, Algorithm 1), instead of using ``theta^i``.
        schedule: lambda schedule (default exponential, 29 steps, ratio 1.2).
        n_particles: N.
        covariance: ``"ekf"`` or ``"ukf"`` covariance tracking.
        points: where the flow is linearised (:mod:`torchflow.flows.points`): ``"particle"``
            (each particle's auxiliary point, P per particle), ``"global"`` (the trial's migrating
            mean, one P per trial), ``"clustered"`` (K medoids, one P per trial; see
            :class:`ClusteredParticleFlowParticleFilter`), a
            :class:`~torchflow.flows.points.LinearisationPoints`, or ``None``: the flow's own
            default (LEDH and the per-particle homotopy flows: particle; EDH: global). Any flow
            pairs with any points.
        n_clusters, alpha, sweeps: knobs of clustered points given by name, see
            :class:`ClusteredParticleFlowParticleFilter`.
        jacobian_in_weight: deterministic flows: keep ``log|det|`` in the weight (default True;
            False is seed 004's printed weight, whose evidence is biased).
        resampling, ess_threshold, regularization: see
            :class:`~torchflow.filters.base.ParticleFilterBase`.
        nonfinite: ``"recover"`` (default) repairs and counts non-finite particles, ``"raise"``
            raises.
        particle_chunk: flow (per-particle points) and weigh at most this many particles at a time
            to bound memory; ``None``: all (see :meth:`~torchflow.filters.base.ParticleFilterBase.plan_memory`).
    """

    random_stream = "pfpf"

    def __init__(self, model, *, flow=None, schedule: Optional[LambdaSchedule] = None,
                 n_particles: int = 500, covariance: str = "ekf", points: Optional[str] = None,
                 n_clusters: int = 100, alpha: float = 0.25, sweeps: int = 10, jacobian_in_weight: bool = True,
                 resampling: str = "systematic", ess_threshold: float = 0.5, regularization=None,
                 nonfinite: str = "recover", particle_chunk: Optional[int] = None, validate: bool = True,
                 name: Optional[str] = None):
        super().__init__(model, n_particles=n_particles, resampling=resampling, ess_threshold=ess_threshold,
                         regularization=regularization, nonfinite=nonfinite, particle_chunk=particle_chunk,
                         validate=validate, name=name)
        flow = _flow(flow)
        # the clustered knobs are checked whatever the points (a config sets them for every PF-PF)
        ClusteredPoints(n_clusters, alpha, sweeps)
        if not isinstance(jacobian_in_weight, bool):
            raise TypeError(f"jacobian_in_weight: expected a bool, got {type(jacobian_in_weight).__name__}")
        #: the flow proposal (:mod:`torchflow.proposals`): flow, schedule, points and covariance tracker
        self.proposal = flow_proposal(model, flow, schedule=schedule, covariance=covariance, points=points,
                                      n_clusters=n_clusters, alpha=alpha, sweeps=sweeps,
                                      jacobian_in_weight=jacobian_in_weight)

    # the proposal's settings, read through the filter
    flow = property(lambda self: self.proposal.flow)
    schedule = property(lambda self: self.proposal.schedule)
    tracker = property(lambda self: self.proposal.tracker)
    points = property(lambda self: self.proposal.points)
    covariance = property(lambda self: self.proposal.covariance)
    jacobian_in_weight = property(lambda self: self.proposal.jacobian_in_weight)

    def bytes_per_trial(self, n_particles=None):
        N = n_particles or self.n_particles
        flow = self._flow_bytes(N, cov_mats=18 if self.flow.stochastic else 12)
        return flow + self.points.extra_bytes(N, self.model.state_dim)

    def init(self, mean, cov, n_particles=None, generator=None):
        N = self._resolve_n(n_particles)
        B, d = mean.shape
        particles = linalg.sample_mvn(mean, linalg.safe_cholesky(cov), (N,), generator)
        lw = torch.full((B, N), -math.log(N), dtype=mean.dtype, device=mean.device)
        # the covariance type follows the points; EKF covariances of a linear model evolve
        # identically for every particle (declared, so per-particle points keep one per trial)
        identical = self.covariance == "ekf" and self.model.linear_dynamics and self.model.linear_measurement
        P = self.points.covariance(cov, N, identical=identical)
        zero = torch.zeros(B, dtype=mean.dtype, device=mean.device)
        return ParticleState(particles, lw, mean, torch.full_like(zero, float(N)), zero,
                             torch.zeros(B, dtype=torch.bool, device=mean.device),
                             n_repaired=torch.zeros(B, dtype=torch.long, device=mean.device), cov=P)

    def extra_repr(self) -> str:
        return f"points={self.points!r}, jacobian_in_weight={self.jacobian_in_weight}"


class ClusteredParticleFlowParticleFilter(ParticleFlowParticleFilter):
    """Clustered PF-PF(LEDH) (seed 004, Li & Coates; MODELS.md §11): the flow is linearised at K
    cluster medoids instead of at every particle, and every particle moves with its cluster's
    affine map, so the flow costs O(N_lambda K + N) instead of O(N_lambda N).

    Each step: the shared prior covariance P comes from an EKF (UKF) on the estimate, as for
    PF-PF(EDH); the particles' noise-free predictions ``eta_bar^i = g(x_{k-1}^i)`` are clustered by
    K-medoids on the mixed distance ``alpha d~ + (1 - alpha)(1 - p)``
    (:func:`~torchflow.flows.points.cluster_distance`: Euclidean on the measured coordinates and
    the correlation of the lambda = 0 LEDH velocities ``zeta^i``); cluster k's flow starts at its
    medoid's ``eta_bar`` (also the ``eta_bar_0`` of its drift offset). Labels and maps depend on the
    previous particles and ``z_k`` only, never on the noise ``v_k^i``, so each particle's map
    ``eta_0 -> eta_1`` is affine and invertible and the proposal density is
    ``p(eta_0 | x_{k-1}) / theta^(k)``, ``theta^(k) = prod_j |det(I + eps_j A^(k)_j)|``.

    Args:
        n_clusters: K (default 100); ``K >= N`` makes every particle its own medoid (PF-PF(LEDH)
            with a shared P, which on linear models is PF-PF(LEDH) exactly).
        alpha: weight of the Euclidean part of the distance (default 0.25; seed 004: results
            similar for alpha in {0, .25, .5, .75, 1}).
        sweeps: K-medoids assign/update sweeps (default 10; MODELS.md allows up to 20).
        jacobian_in_weight: include ``theta^(k)`` in the weight (default True: the proposal density
            needs it, since it differs between clusters); False reproduces the seed's printed
            algorithm, which omits it.
        flow: any flow (default LEDH drift). With a stochastic flow (``"gromov"``, ``"osd"``) each
            particle takes its cluster's drift and diffusion and is weighted by its exact Gaussian
            proposal density, as PF-PF(Gromov).
        other arguments: as :class:`ParticleFlowParticleFilter`, which this is with
        ``points="clustered"`` (any PF-PF takes ``points``; this class only changes the default).
    """

    def __init__(self, model, *, points: Optional[str] = "clustered", **kwargs):
        super().__init__(model, points=points, **kwargs)


class ParticleFlowFilter(_FlowFilterMixin, Filter):
    """Particle flow filter without importance weights (Ding & Coates 2012; the "EDH"/"LEDH" rows
    of the seed tables).

    Each step re-draws N particles from ``N(x_hat_{k-1}, P_{k-1})``, propagates them through the
    dynamics, migrates them with the flow, and reports their plain mean; the covariance is
    propagated by an EKF (or UKF) predict/update, which also supplies the flow's prior P. The
    reported log-evidence is that EKF/UKF's Gaussian approximation, not a particle estimate.

    Args:
        model, flow, schedule, n_particles, covariance: as for :class:`ParticleFlowParticleFilter`.
    """

    estimates_evidence = False
    uses_randomness = True
    random_stream = "flow_filter"

    def __init__(self, model, *, flow=None, schedule: Optional[LambdaSchedule] = None,
                 n_particles: int = 500, covariance: str = "ekf", points: Optional[str] = None,
                 validate: bool = True, name: Optional[str] = None):
        super().__init__(model, validate=validate, name=name)
        self.n_particles = check_count("n_particles", n_particles)
        self._init_flow(model, flow, schedule, covariance, points)

    def bytes_per_trial(self, n_particles=None):
        N = n_particles or self.n_particles
        return self._flow_bytes(N, cov_mats=8) + self.points.extra_bytes(N, self.model.state_dim)

    def init(self, mean, cov, n_particles=None, generator=None):
        N = self.n_particles if n_particles is None else check_count("n_particles", n_particles)
        return GaussianState(mean, cov, torch.zeros_like(mean[:, 0]), 0, n_particles=N)

    def step(self, state: GaussianState, z, generator=None):
        model = self.model
        N = state.n_particles or self.n_particles
        B, d = state.mean.shape
        L_prev = linalg.safe_cholesky(state.cov)
        x_prev = linalg.sample_mvn(state.mean, L_prev, (N,), generator)  # re-draw (B, N, d)
        eta0 = model.sample_transition(x_prev, generator)
        m_pred, P_pred = self.tracker.predict(state.mean, state.cov)  # (B, d), (B, d, d)
        L = linalg.safe_cholesky(P_pred)
        if self.points.per_particle:  # each particle's prior: its noise-free prediction, the trial's P
            prior, index = FlowPrior(model.transition_mean(x_prev), L.unsqueeze(1)), None
        else:
            prior, index = self.points.place(model, x_prev, m_pred, L, z)
        out = integrate_flow(self.flow, model, eta0, z, prior, self.schedule, generator=generator,
                             points=self.points, index=index)
        _, P_post, ll = self.tracker.update(m_pred, P_pred, z)
        return GaussianState(out.particles.mean(1), P_post, ll, state.step + 1, n_particles=N)
