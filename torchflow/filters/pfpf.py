"""Particle flow filters: the PF-PF (Li & Coates 2017) and the unweighted flow filters
(Ding & Coates 2012). Both take any :class:`~torchflow.flows.ParticleFlow` and lambda schedule
through the same flow proposal (:mod:`torchflow.proposals.flow`); the weighting and resampling are
:class:`~torchflow.filters.ParticleFilter`'s.
"""

from __future__ import annotations

from typing import Optional

from torchflow.core import linalg
from torchflow.core.checks import check_count
from torchflow.core.covariances import TrialCovariance
from torchflow.filters.base import Filter, GaussianState, ParticleFilter
from torchflow.flows.schedules import LambdaSchedule
from torchflow.proposals import flow_proposal


class _FlowSettings:
    """The flow proposal's settings, read through the filter."""

    flow = property(lambda self: self.proposal.flow)
    schedule = property(lambda self: self.proposal.schedule)
    tracker = property(lambda self: self.proposal.tracker)
    points = property(lambda self: self.proposal.points)
    covariance = property(lambda self: self.proposal.covariance)
    jacobian_in_weight = property(lambda self: self.proposal.jacobian_in_weight)


class ParticleFlowParticleFilter(_FlowSettings, ParticleFilter):
    """Particle flow particle filter (PF-PF; Li & Coates 2017, Algorithms 1-2).

    Each step, for particle i: draw ``eta_0^i ~ p(. | x_{k-1}^i)``, migrate it with the flow from
    lambda = 0 to 1 (linearised at a deterministic auxiliary point started at the noise-free
    prediction), and weight the result ``x_k^i = eta_1^i`` by

        w_k^i ∝ w_{k-1}^i p(x_k^i | x_{k-1}^i) p(z_k | x_k^i) theta^i / p(eta_0^i | x_{k-1}^i),

    ``theta^i = |det d eta_1 / d eta_0|``. The flow's Gaussian prior covariance P comes from an EKF
    (or UKF) prediction: per particle for local flows (LEDH; each particle carries its own
    covariance, updated by an EKF/UKF update at its predicted point and resampled with it), per
    trial for global flows (EDH; predicted from the weighted-mean estimate).
    :class:`~torchflow.filters.ParticleFilter` with a flow proposal
    (:func:`~torchflow.proposals.flow_proposal`).

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
            False is the weight printed in Li & Coates' clustered PF-PF paper, whose evidence is biased).
        other arguments: see :class:`~torchflow.filters.ParticleFilter`.
    """

    random_stream = "pfpf"

    def __init__(
        self,
        model,
        *,
        flow=None,
        schedule: Optional[LambdaSchedule] = None,
        covariance: str = "ekf",
        points: Optional[str] = None,
        n_clusters: int = 100,
        alpha: float = 0.25,
        sweeps: int = 10,
        jacobian_in_weight: bool = True,
        **kwargs,
    ):
        proposal = flow_proposal(
            model,
            flow,
            schedule=schedule,
            covariance=covariance,
            points=points,
            n_clusters=n_clusters,
            alpha=alpha,
            sweeps=sweeps,
            jacobian_in_weight=jacobian_in_weight,
        )
        super().__init__(model, proposal, **kwargs)

    def flow_chunk(self, n_particles: Optional[int] = None) -> Optional[int]:
        """Particles of one trial per pass of a per-particle flow (see
        :meth:`~torchflow.proposals.FlowProposal.flow_chunk`)."""
        return self.proposal.flow_chunk(self._resolve_n(n_particles), self.particle_chunk)


class ClusteredParticleFlowParticleFilter(ParticleFlowParticleFilter):
    """Clustered PF-PF(LEDH) (Li & Coates' clustered PF-PF, Algorithms 1-2): the flow is linearised at K
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
        alpha: weight of the Euclidean part of the distance (default 0.25; the paper: results
            similar for alpha in {0, .25, .5, .75, 1}).
        sweeps: K-medoids assign/update sweeps (default 10; the paper does not fix a number).
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


class ParticleFlowFilter(_FlowSettings, Filter):
    """Particle flow filter without importance weights (Ding & Coates 2012; the "EDH"/"LEDH" rows
    of the seed tables): the PF-PF's flow proposal with weighting off.

    Each step re-draws N particles from ``N(x_hat_{k-1}, P_{k-1})``, propagates them through the
    dynamics and migrates them with the flow (the proposal, fed a per-trial covariance: global
    points at the trial's mean, per-particle points at each particle's noise-free prediction with
    the trial's P), and reports their plain mean; the covariance is propagated by the proposal's
    EKF (or UKF) predict/update, which also supplies the flow's prior P. The reported log-evidence
    is that EKF/UKF's Gaussian approximation, not a particle estimate.

    Args:
        model, flow, schedule, n_particles, covariance, points: as for
            :class:`ParticleFlowParticleFilter`.
    """

    estimates_evidence = False
    uses_randomness = True
    random_stream = "flow_filter"

    def __init__(
        self,
        model,
        *,
        flow=None,
        schedule: Optional[LambdaSchedule] = None,
        n_particles: int = 500,
        covariance: str = "ekf",
        points: Optional[str] = None,
        validate: bool = True,
        name: Optional[str] = None,
    ):
        super().__init__(model, validate=validate, name=name)
        self.n_particles = check_count("n_particles", n_particles)
        self.proposal = flow_proposal(
            model, flow, schedule=schedule, covariance=covariance, points=points, weighted=False
        )

    def bytes_per_trial(self, n_particles=None):
        return self.proposal.flow_bytes(n_particles or self.n_particles, cov_mats=8)

    def preferred_chunk_trials(self, n_particles=None):
        return self.proposal.preferred_chunk_trials(n_particles or self.n_particles)

    def init(self, mean, cov, n_particles=None, generator=None):
        N = self.n_particles if n_particles is None else check_count("n_particles", n_particles)
        return GaussianState(mean, cov, mean.new_zeros(mean.shape[0]), 0, n_particles=N)

    def step(self, state: GaussianState, z, generator=None):
        N = state.n_particles or self.n_particles
        x_prev = linalg.sample_mvn(state.mean, linalg.safe_cholesky(state.cov), (N,), generator)  # re-draw (B, N, d)
        prop = self.proposal.propose(x_prev, None, state.mean, z, TrialCovariance(state.cov), generator)
        return GaussianState(prop.particles.mean(1), prop.cov.matrix, prop.log_evidence, state.step + 1, n_particles=N)
