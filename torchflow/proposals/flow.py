"""Particle flows as proposals (Li & Coates 2017; Pal & Coates 2019).

* :class:`InvertibleFlowProposal`: a deterministic flow moves ``eta_0 ~ p(. | x_{k-1})``;
  ``log q = log p(eta_0 | x_{k-1}) - log|det d eta_1 / d eta_0|``.
* :class:`StochasticFlowProposal`: a stochastic flow's Euler-Maruyama law, tracked exactly from the
  Gaussian transition (Pal & Coates 2019, Algorithm 1).

Both own the flow, the lambda schedule, the linearisation points (global, per particle, clustered)
and the covariance tracker (EKF/UKF, :mod:`torchflow.core.trackers`) that gives the flow its prior; the
tracked covariance is the state they carry between steps.
"""

from __future__ import annotations

import warnings
from typing import Optional

import torch

from torchflow.core import linalg, registry
from torchflow.core.blocks import blockwise
from torchflow.core.covariances import DiagonalCovariance
from torchflow.core.errors import ArgumentError, ArgumentTypeError
from torchflow.core.trackers import tracker
from torchflow.flows import FlowPrior, LEDHFlow, ParticleFlow, integrate_flow, resolve_points
from torchflow.flows.points import ClusteredPoints, flow_points_per_call
from torchflow.flows.schedules import LambdaSchedule, resolve_schedule
from torchflow.models.structure import bytes_per_point
from torchflow.proposals.base import Proposal, Proposed

#: flows by config name (:data:`torchflow.core.registry.REGISTRY`)
FLOWS = registry.table("flow")


def resolve_flow(flow, default=LEDHFlow) -> ParticleFlow:
    """A :class:`~torchflow.flows.ParticleFlow` from an instance, a name of :data:`FLOWS` or
    ``None`` (``default()``)."""
    if flow is None:
        return default()
    if isinstance(flow, str):
        if flow not in FLOWS:
            raise ArgumentError(f"flow: expected a ParticleFlow or one of {sorted(FLOWS)}, got {flow!r}")
        return FLOWS[flow]()
    if not isinstance(flow, ParticleFlow):
        raise ArgumentTypeError(f"flow: expected a torchflow ParticleFlow, got {type(flow).__name__}")
    return flow


class FlowProposal(Proposal):
    """A particle flow as proposal (base of the invertible and stochastic flow proposals).

    Each step: the tracker predicts the flow's Gaussian prior where the carried covariance lives
    (at each particle, or at the trial's estimate: :mod:`torchflow.core.covariances`), the
    linearisation points place it (:meth:`~torchflow.flows.points.LinearisationPoints.place`),
    the flow migrates ``eta_0 ~ p(. | x_{k-1})``, and the tracker updates the covariance.
    Particles that flow independently (per-particle points) are flowed in blocks to bound memory.

    Args:
        model: the state-space model.
        flow: a :class:`~torchflow.flows.ParticleFlow` or a name of :data:`FLOWS` (default LEDH).
        schedule: lambda schedule (default exponential, 29 steps, ratio 1.2).
        covariance: ``"ekf"`` or ``"ukf"``: the tracker that gives the flow its prior P.
        points: a :class:`~torchflow.flows.points.LinearisationPoints`, a name (``"particle"``,
            ``"global"``, ``"clustered"``) or ``None`` (the flow's default).
        n_clusters, alpha, sweeps: knobs of clustered points given by name
            (:class:`~torchflow.flows.points.ClusteredPoints`; checked whatever the points).
        jacobian_in_weight: invertible flows: include ``log|det|`` in ``log q`` (default True;
            False is the weight printed in Li & Coates' clustered PF-PF paper, whose evidence is biased:
            a knob for comparison).
        weighted: compute ``log q`` (default); ``False`` moves the particles only (the unweighted
            flow filters: no transition density, no tracked proposal law), ``log_q`` is ``None``.
    """

    def __init__(
        self,
        model,
        flow=None,
        schedule: Optional[LambdaSchedule] = None,
        covariance: str = "ekf",
        points=None,
        n_clusters: int = 100,
        alpha: float = 0.25,
        sweeps: int = 10,
        jacobian_in_weight: bool = True,
        weighted: bool = True,
    ):
        super().__init__(model)
        self.flow = resolve_flow(flow)
        self.schedule = resolve_schedule(schedule)
        self.covariance = covariance
        self.tracker = tracker(model, covariance)
        ClusteredPoints(n_clusters, alpha, sweeps)  # the knobs are checked whatever the points
        if not isinstance(jacobian_in_weight, bool):
            raise ArgumentTypeError(f"jacobian_in_weight: expected a bool, got {type(jacobian_in_weight).__name__}")
        #: the linearisation-point strategy (:mod:`torchflow.flows.points`)
        self.points = resolve_points(self.flow, points, n_clusters=n_clusters, alpha=alpha, sweeps=sweeps)
        self.jacobian_in_weight = jacobian_in_weight
        self.weighted = bool(weighted)
        self.uses_transition_density = self.weighted
        self._informative_checked = False  # check_informative: warned (or found informative) already

    @property
    def identical_covariances(self) -> bool:
        """EKF covariances of a linear model evolve identically for every particle (declared by the
        model), so per-particle points keep one per trial."""
        return (
            self.covariance == "ekf"
            and self.model.structure.linear_dynamics
            and self.model.structure.linear_measurement
        )

    @property
    def has_ancestor_law(self) -> bool:
        """Weighted flows: every parent's map is affine (deterministic flows: the pushforward of a
        Gaussian transition) or its law is tracked exactly (stochastic flows)."""
        return self.weighted and (self.flow.stochastic or self.model.structure.gaussian_transition)

    def init_carry(self, cov, n_particles):
        return self.points.covariance(cov, n_particles, identical=self.identical_covariances)

    def flow_chunk(self, n_particles: int, chunk: Optional[int] = None) -> Optional[int]:
        """Particles of one trial per pass of a per-particle flow: ``chunk`` when given, else
        :func:`~torchflow.flows.points.flow_points_per_call` when the cloud exceeds it, else ``None``
        (one pass). Changes speed, not numbers (the blocks are independent; round-off aside)."""
        if chunk:
            return chunk
        N, c = int(n_particles), flow_points_per_call(self.model)
        return c if N > c else None

    def bytes_per_trial(self, n_particles):
        return self.flow_bytes(n_particles, cov_mats=18 if self.flow.stochastic else 12)

    def flow_bytes(self, n_particles: int, cov_mats: int) -> int:
        """Rough per-trial memory: ``cov_mats`` d x d matrices per particle for local flows."""
        N = int(n_particles)
        d, m = self.model.state_dim, self.model.obs_dim
        per_point = cov_mats * d * d + 4 * m * d + 8 * d + 4 * m
        if self.identical_covariances:  # one prior factor and Jacobian per trial, vectors per particle
            flow = cov_mats * d * d + N * (8 * d + 3 * m)
        else:
            flow = N * per_point if self.points.per_particle else N * (8 * d + 3 * m) + 4 * per_point
        return 8 * flow + N * bytes_per_point(self.model) + self.points.extra_bytes(N, d)

    def preferred_chunk_trials(self, n_particles):
        N = int(n_particles)
        pref = self.points.preferred_chunk_trials(N)
        if pref is not None and self.points.per_particle:  # high dimension: cache-sized calls
            pref = min(pref, max(1, flow_points_per_call(self.model) // N))
        return pref

    def _migrate(self, eta0, x_prev, z, prior, generator, log_q0, noise=None, index=None):
        """Flow ``eta0`` from ``prior`` at the points (``index``: each particle's point); returns
        the particles, their log-density ``(B, N)`` and, with :attr:`report_ancestor_law`, the
        Gaussian law given each parent ``(mean (B, N, d), scale_tril (B, N|1, d, d))`` (else two
        ``None``)."""
        raise NotImplementedError

    def _draw_eta0(self, x_prev, generator):
        if self.flow.stochastic and not self.model.structure.gaussian_transition:
            # the tracked proposal law starts from the Gaussian fit, so eta_0 must be drawn from it
            # (Pal & Coates 2019, non-Gaussian transitions); the weight keeps the model's exact transition density
            return self.model.sample_transition_gaussian(x_prev, generator)
        return self.model.sample_transition(x_prev, generator)

    def propose(self, particles, log_weights, estimate, z, carry, generator, *, chunk=None) -> Proposed:
        model, pts, cov = self.model, self.points, carry
        x_prev = particles  # (B, N, d)
        eta0 = self._draw_eta0(x_prev, generator)
        log_q0 = model.transition_log_prob(eta0, x_prev) if self.weighted and not self.flow.stochastic else None
        at = x_prev if cov.per_particle else estimate
        m_pred, P_pred = self.tracker.predict(at, cov.matrix)  # (B, [N,] d), (B, [N|1,] d, d)
        L_pred = linalg.safe_cholesky(P_pred)
        prior, index = pts.place(model, x_prev, m_pred, L_pred, z)
        if pts.per_particle:
            x, log_q, law_mean, law_tril = self._flow_blocks(
                eta0, x_prev, z, prior, generator, log_q0, self.flow_chunk(eta0.shape[1], chunk)
            )
        else:
            x, log_q, law_mean, law_tril = self._migrate(eta0, x_prev, z, prior, generator, log_q0, index=index)
        _, P_post, ll = self.tracker.update(m_pred, P_pred, z.unsqueeze(1) if cov.per_particle else z)
        return Proposed(
            x,
            log_q,
            cov=cov.like(P_post),
            fallback=eta0,
            log_evidence=ll,
            ancestor_law=(law_mean, law_tril) if self.report_ancestor_law else None,
        )

    def _flow_blocks(self, eta0, x_prev, z, prior, generator, log_q0, chunk):
        """Every particle flows with its own prior: blocks of particles are independent."""
        B, N = eta0.shape[:2]
        blocked = bool(chunk) and N > chunk
        tape = {}

        def draw(sl):
            """A block's diffusion noise: slices of whole-cloud draws (one per pseudo-time step, drawn
            when the first block needs it), so blocking does not change the numbers."""

            def noise(j, shape):
                if j not in tape:
                    tape[j] = linalg.standard_normal(
                        (B, N, shape[-1]), dtype=eta0.dtype, device=eta0.device, generator=generator
                    )
                return tape[j][:, sl]

            return noise

        def block(eta0, x_prev, m, L, log_q0, particles):
            kw = {"noise": draw(particles)} if blocked and self.flow.stochastic else {}
            x, log_q, law_mean, law_tril = self._migrate(eta0, x_prev, z, FlowPrior(m, L), generator, log_q0, **kw)
            if law_tril is not None and blocked:  # a factor shared by the block: one per particle, to concatenate
                law_tril = law_tril.expand(*x.shape, x.shape[-1])
            return x, log_q, law_mean, law_tril

        return blockwise(block, eta0, x_prev, prior.mean, prior.scale_tril, log_q0, pass_slice=True, chunk=chunk)

    def extra_repr(self) -> str:
        return f"points={self.points!r}, jacobian_in_weight={self.jacobian_in_weight}"


class InvertibleFlowProposal(FlowProposal):
    """Deterministic flow: ``log q(x) = log p(eta_0 | x_prev) - log|det d x / d eta_0|``.

    Graph-safe (:attr:`~torchflow.proposals.Proposal.graph_safe`) where its linearisation points
    are (:attr:`~torchflow.flows.points.LinearisationPoints.graph_safe`): each step draws ``eta_0``
    (one normal draw of the cloud's shape) and runs the same kernels, so a PF-PF step with a
    deterministic flow is replayed from a CUDA graph whole, the flow loop inside it."""

    graph_safe = True

    def _migrate(self, eta0, x_prev, z, prior, generator, log_q0, noise=None, index=None):
        law = self.report_ancestor_law
        out = integrate_flow(
            self.flow, self.model, eta0, z, prior, self.schedule, points=self.points, index=index, map_jacobian=law
        )
        if log_q0 is None:  # weighted=False
            return out.particles, None, None, None
        # jacobian_in_weight=False: the clustered PF-PF paper's printed weight (biased evidence; a knob for comparison)
        log_q = log_q0 - out.log_det if self.jacobian_in_weight else log_q0
        if not law:
            return out.particles, log_q, None, None
        # the parent's affine map x = M eta + c pushes N(f(x_prev), Q) to N(x - M (eta_0 - f(x_prev)), M Q M^T)
        model, M = self.model, out.map_jacobian
        Lq = model.transition_scale_tril(x_prev)
        return (out.particles, log_q) + affine_law(
            out.particles, eta0, model.transition_mean(x_prev), M, Lq.unsqueeze(-3) if Lq.dim() == 3 else Lq
        )


class StochasticFlowProposal(FlowProposal):
    """Stochastic flow: the exact Gaussian law of the Euler-Maruyama map started from the Gaussian
    transition ``N(f(x_prev), V)`` (Pal & Coates 2019, Algorithm 1)."""

    def _migrate(self, eta0, x_prev, z, prior, generator, log_q0, noise=None, index=None):
        model = self.model
        start = FlowPrior(model.transition_mean(x_prev), model.transition_scale_tril(x_prev)) if self.weighted else None
        out = integrate_flow(
            self.flow,
            model,
            eta0,
            z,
            prior,
            self.schedule,
            generator=generator,
            proposal=start,
            noise=noise,
            points=self.points,
            index=index,
        )
        if not (self.report_ancestor_law and self.weighted):
            return out.particles, out.log_proposal, None, None
        return out.particles, out.log_proposal, out.proposal_mean, linalg.safe_cholesky(out.proposal_cov)


def affine_law(
    x: torch.Tensor,
    eta0: torch.Tensor,
    transition_mean: torch.Tensor,
    maps: torch.Tensor,
    transition_tril: torch.Tensor,
):
    """The Gaussian law of a deterministic flow's particle given its parent: the affine map
    ``x = M eta_0 + c`` pushes ``N(f(x_prev), L L^T)`` to ``N(x - M (eta_0 - f(x_prev)), M L L^T M^T)``.
    ``x``, ``eta0``, ``transition_mean`` ``(B, N, d)``; maps ``M (B, N|1, d, d)``; ``L`` broadcastable
    against them. Returns ``(mean (B, N, d), scale_tril (B, N|1, d, d))``."""
    G = maps @ transition_tril
    return (
        x - linalg.matvec(maps, eta0 - transition_mean),
        linalg.safe_cholesky(linalg.symmetrize(G @ G.transpose(-1, -2))),
    )


def check_informative(proposal, mean: torch.Tensor, who: str, cov=None) -> None:
    """Warn, once per proposal, when a flow proposal's model has a Gaussian measurement form whose
    Jacobian ``dh/dx`` is zero at every trial's prior ``mean (B, d)`` and one prior standard
    deviation either side of it (``cov``: ``(B, d, d)``, a
    :class:`~torchflow.core.covariances.DiagonalCovariance`, or ``None``: a unit step). The flow's
    drift is then zero near the prior, so it does not move the particles and the filter is the
    bootstrap PF at a flow's cost. Stochastic volatility's ``h(x) = 0``, ``R(x) = exp(x)`` is such a
    model: its information sits in a state-dependent R. A Jacobian that vanishes only at the mean,
    such as that of ``h(x) = x^3`` at 0, is not flat: particles linearised where they are still move.
    ``who`` names the filter. Anything but a :class:`FlowProposal` (or ``None``) is left alone.
    One batched linearisation at ``3 B`` points and one host read: call it before the first step."""
    if not isinstance(proposal, FlowProposal) or proposal._informative_checked:
        return
    proposal._informative_checked = True
    with torch.no_grad():
        mean = mean.detach()
        if cov is None:
            sd = torch.ones_like(mean)
        else:
            var = cov.variance if isinstance(cov, DiagonalCovariance) else cov.detach().diagonal(dim1=-2, dim2=-1)
            sd = var.expand_as(mean).clamp_min(0).sqrt()
        points = torch.cat([mean, mean + sd, mean - sd], 0)  # (3 B, d)
        _, H = proposal.model.linearize_measurement(points)  # (3 B, m, d)
        flat = not bool(H.ne(0).any())
    if flat:
        warnings.warn(
            f"{who}: the Gaussian measurement form of {type(proposal.model).__name__} has a zero Jacobian "
            "dh/dx at the prior mean and one prior standard deviation either side of it, so it carries no "
            "information about the state: the flow will not move the particles (the filter is the bootstrap "
            "PF at a flow's cost). Use the bootstrap particle filter, or a Gaussian form whose measurement "
            "depends on the state (stochastic volatility: gaussian_form='log_squared')",
            UserWarning,
            stacklevel=2,
        )


def flow_proposal(model, flow=None, **kwargs) -> FlowProposal:
    """The flow proposal for ``flow`` (an instance or a name): invertible (deterministic flows) or
    stochastic."""
    flow = resolve_flow(flow)
    cls = StochasticFlowProposal if flow.stochastic else InvertibleFlowProposal
    return cls(model, flow, **kwargs)
