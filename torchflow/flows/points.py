"""Linearisation points: where a flow is linearised, as strategy objects.

A flow's coefficients are computed at L points per trial, ``(B, L, d)``, and each particle moves
with the coefficients of its point (:func:`~torchflow.flows.integrate_flow`):

* :class:`GlobalPoints`: L = 1, the trial's migrating mean (EDH, PF-PF(EDH));
* :class:`ParticlePoints`: L = N, each particle's own auxiliary point (LEDH, PF-PF(LEDH));
* :class:`ClusteredPoints`: L = K medoids of a batched K-medoids on the mixed particle distance,
  with a ``(B, N) -> K`` index (Li & Coates' clustered PF-PF, Algorithms 1-2).

A strategy says three things, and nothing else in the flow layer or the particle filters depends
on which strategy it is:

* :meth:`LinearisationPoints.covariance`: the type of covariance a PF-PF carries for it
  (:mod:`torchflow.core.covariances`: per trial, or per particle);
* :meth:`LinearisationPoints.place`: the flow's Gaussian prior at the points and each particle's
  point, from the tracker's prediction (a filter's view);
* :meth:`LinearisationPoints.arrange`: the prior as ``(B, L, d)`` and the index (the integrator's
  view). ``index = None`` means the points broadcast against the particles (L = 1) or are the
  particles (L = N, :attr:`~LinearisationPoints.per_particle`).

A new kind of points is a subclass here, registered in :data:`POINTS`; it needs no edit of the
integrator or of the particle filters. Everything is batched over trials: the K-medoids loop runs
over a fixed number of sweeps (like pseudo-time steps), with no convergence test and so no host
synchronisation (a converged assignment is a fixed point of the sweep).
"""

from __future__ import annotations

from typing import Optional, Sequence, Tuple, Union

import torch

from torchflow.core import resampling, tuning
from torchflow.core.checks import check_count
from torchflow.core.covariances import Covariance, ParticleCovariance, TrialCovariance
from torchflow.core.errors import ArgumentError
from torchflow.flows.base import FlowPrior
from torchflow.flows.daum_huang import LEDHFlow


def cluster_distance(
    eta_bar: torch.Tensor, zeta: torch.Tensor, alpha: float = 0.25, support: Optional[Sequence[int]] = None
) -> torch.Tensor:
    """Mixed distance ``phi_ij = alpha d~_ij + (1 - alpha) (1 - p_ij)`` between particles.

    Args:
        eta_bar: ``(B, N, d)`` noise-free predictions of the particles.
        zeta: ``(B, N, d)`` their flow velocities at lambda = 0 (``A^i(0) eta_bar^i + b^i(0)``).
        alpha: weight of the Euclidean part (1: Euclidean only, 0: correlation only).
        support: the state coordinates the measurement reads (``None``: all); the Euclidean part
            uses only these, each rescaled to [0, 1] per trial (min-max), since they may carry
            different units.

    Returns:
        ``(B, N, N)``: ``d~ = 2 d / max d`` (Euclidean, in [0, 2]) and ``1 - p`` with ``p`` the
        Pearson correlation of the ``d``-vectors ``zeta^i`` and ``zeta^j`` (each centred by its
        own component mean; the paper does not say which components: all d are used), also in [0, 2].
    """
    if not 0.0 <= float(alpha) <= 1.0:
        raise ArgumentError(f"alpha: expected a weight in [0, 1], got {alpha}")
    x = eta_bar if support is None else eta_bar[..., list(support)]
    lo, hi = x.amin(1, keepdim=True), x.amax(1, keepdim=True)
    tiny = torch.finfo(x.dtype).tiny
    x = (x - lo) / (hi - lo).clamp_min(tiny)
    dist = torch.cdist(x, x, compute_mode="donot_use_mm_for_euclid_dist")  # (B, N, N), exact zeros on the diagonal
    dist = 2 * dist / dist.amax((1, 2), keepdim=True).clamp_min(tiny)
    zc = zeta - zeta.mean(-1, keepdim=True)
    zn = zc / torch.linalg.vector_norm(zc, dim=-1, keepdim=True).clamp_min(tiny)
    corr = (zn @ zn.transpose(-1, -2)).clamp(-1.0, 1.0)
    return alpha * dist + (1 - alpha) * (1 - corr)


def kmedoids(dist: torch.Tensor, n_clusters: int, sweeps: int = 20) -> Tuple[torch.Tensor, torch.Tensor]:
    """Batched alternating K-medoids on distance matrices ``dist (B, N, N)``.

    Initialisation (deterministic, no random draws): sort the points of each trial by their
    distance to the trial's most central point (smallest row sum) and take K evenly spaced ranks.
    Then ``sweeps`` times: assign every point to its nearest medoid, and make each cluster's
    medoid the member with the smallest total distance to the other members (an empty cluster
    keeps its medoid). This alternating variant stands in for the PAM algorithm (Kaufman &
    Rousseeuw 1990) that Li & Coates' clustered PF-PF names; the paper gives neither the variant
    nor the number of iterations.

    Returns:
        ``index (B, N)`` cluster of each point and ``medoids (B, K)`` the medoids' point indices.
    """
    B, N, _ = dist.shape
    K = int(n_clusters)
    if K < 1:
        raise ArgumentError(f"n_clusters: expected a positive integer, got {n_clusters}")
    if K >= N:  # every point its own medoid
        ar = torch.arange(N, device=dist.device).expand(B, N)
        return ar.clone(), ar.clone()
    rows = torch.arange(B, device=dist.device)[:, None]
    centre = dist.sum(-1).argmin(-1)  # (B,)
    order = dist[rows[:, 0], centre].argsort(-1)  # (B, N): points by distance to the centre
    ranks = torch.div(torch.arange(K, device=dist.device) * N, K, rounding_mode="floor")
    medoids = order[:, ranks]  # (B, K)
    big = torch.finfo(dist.dtype).max
    kk = torch.arange(K, device=dist.device)
    for _ in range(int(sweeps)):
        index = dist.gather(2, medoids[:, None, :].expand(B, N, K)).argmin(-1)  # (B, N)
        same = index.unsqueeze(-1) == index.unsqueeze(-2)  # (B, N, N)
        cost = (dist * same).sum(-1)  # each point's total distance to its cluster
        member = index.unsqueeze(1) == kk[None, :, None]  # (B, K, N)
        best = torch.where(member, cost.unsqueeze(1), big).argmin(-1)  # (B, K)
        medoids = torch.where(member.any(-1), best, medoids)
    index = dist.gather(2, medoids[:, None, :].expand(B, N, K)).argmin(-1)
    return index, medoids


def flow_points_per_call(model) -> int:
    """Points (trials x particles) per call of a per-particle flow on ``model``: ``torchflow.core.tuning``
    ``points_per_call``, capped so that one batch of the points' ``k x k`` matrices (k = the
    measured state coordinates) stays within ``flow_bytes_per_call`` (0: no cap)."""
    sup = model.structure.measurement_support
    k = model.state_dim if sup is None else len(sup)
    t = tuning.get()
    cap = t.flow_bytes_per_call // (8 * k * k) if t.flow_bytes_per_call else t.points_per_call  # 0: no cap
    return max(1, min(t.points_per_call, cap))


class LinearisationPoints:
    """Base of the linearisation-point strategies (see the module docstring).

    Attributes:
        name: the config name (``points=<name>``).
        per_particle: the points are the particles themselves (L = N): a per-particle flow prior,
            covariance tracked per particle, and particles that flow independently (so a filter
            may flow them in blocks to bound memory).
        graph_safe: :meth:`place` and :meth:`arrange` make the same kernels at every step of one
            layout, with no host read, so a flow filter's whole step may be replayed from a CUDA
            graph. Declared by each class itself, not inherited (the global and per-particle
            points; not the clustered ones).
    """

    name = ""
    per_particle = False
    graph_safe = False

    def covariance(self, cov: torch.Tensor, n_particles: int, identical: bool = False) -> Covariance:
        """The covariance a PF-PF carries from the prior ``cov (B, d, d)``: per trial by default.
        ``identical`` declares that per-particle covariances would all be equal (ignored here)."""
        return TrialCovariance(cov)

    def place(
        self, model, x_prev: torch.Tensor, mean: torch.Tensor, scale_tril: torch.Tensor, z: torch.Tensor
    ) -> Tuple[FlowPrior, Optional[torch.Tensor]]:
        """The flow's Gaussian prior at the points and each particle's point.

        Args:
            model: the state-space model.
            x_prev: ``(B, N, d)`` the previous particles.
            mean, scale_tril: the tracker's prediction where the covariance lives (per trial:
                ``(B, d)``, ``(B, d, d)``; per particle: ``(B, N, d)``, ``(B, N|1, d, d)``).
            z: ``(B, m)`` the observation.

        Returns:
            ``(prior, index)``: the prior as :meth:`arrange` takes it, and ``(B, N)`` or ``None``.
        """
        return FlowPrior(mean, scale_tril), None

    def extra_bytes(self, n_particles: int, state_dim: int) -> int:
        """Memory per trial beyond the flow's own (a filter's memory plan adds it)."""
        return 0

    def preferred_chunk_trials(self, n_particles: int) -> Optional[int]:
        """Trials per call that keep this strategy's per-point work fast (``None``: no preference,
        the memory plan decides). Per-particle and clustered points batch small per-point algebra
        (and the clustered N x N distances), which slows down past ``torchflow.core.tuning``
        ``points_per_call`` particles per call; one point per trial does not."""
        return None

    def arrange(
        self, prior: FlowPrior, particles: torch.Tensor, index: Optional[torch.Tensor]
    ) -> Tuple[FlowPrior, Optional[torch.Tensor], bool]:
        """The integrator's view: ``(prior at (B, L, d) points, index (B, N) or None, squeeze)``;
        ``squeeze``: the caller gave per-trial tensors ``(B, d)``, so outputs at the points drop L."""
        raise NotImplementedError

    def extra_repr(self) -> str:
        return ""

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.extra_repr()})"


class GlobalPoints(LinearisationPoints):
    """One point per trial (L = 1): the migrating mean of the trial's prior."""

    name = "global"
    graph_safe = True

    def arrange(self, prior, particles, index):
        if index is not None:
            raise ArgumentError("index: global points take no cluster index (use points='clustered')")
        if prior.mean.dim() == 3:
            _check_points("prior.mean", prior.mean, particles, 1)
            return prior, None, False
        L = prior.scale_tril
        L = L.unsqueeze(-3) if L.dim() == 3 else L  # (d, d) shared by all trials stays as it is
        return FlowPrior(prior.mean.unsqueeze(-2), L), None, True


class ParticlePoints(LinearisationPoints):
    """One point per particle (L = N): each particle's auxiliary point, its own prior and
    (in a PF-PF) its own tracked covariance."""

    name = "particle"
    graph_safe = True
    per_particle = True

    def preferred_chunk_trials(self, n_particles):
        return max(1, tuning.get().points_per_call // int(n_particles))

    def covariance(self, cov, n_particles, identical=False):
        B, d = cov.shape[0], cov.shape[-1]
        P = cov.unsqueeze(1)
        return ParticleCovariance(P if identical else P.expand(B, n_particles, d, d), identical=identical)

    def place(self, model, x_prev, mean, scale_tril, z):
        if mean.dim() == x_prev.dim() - 1:
            # a covariance tracked per trial (the unweighted flow filters): each particle's prior mean
            # is its own noise-free prediction, its covariance the trial's
            return FlowPrior(model.transition_mean(x_prev), scale_tril.unsqueeze(-3)), None
        return FlowPrior(mean, scale_tril), None

    def arrange(self, prior, particles, index):
        if index is not None:
            raise ArgumentError("index: per-particle points take no cluster index (use points='clustered')")
        _check_points("prior.mean", prior.mean, particles, particles.shape[1])
        return prior, None, False


class ClusteredPoints(LinearisationPoints):
    """K medoids (Li & Coates' clustered PF-PF, Algorithms 1-2): the particles' noise-free predictions
    ``eta_bar^i = g(x_{k-1}^i)`` are clustered by :func:`kmedoids` on :func:`cluster_distance`
    (Euclidean on the measured coordinates and the correlation of the lambda = 0 LEDH velocities);
    cluster k's flow starts at its medoid's ``eta_bar`` with the trial's covariance.

    The labels depend on the previous particles and ``z_k`` only, never on the transition noise,
    so each particle's map ``eta_0 -> eta_1`` is affine and invertible.

    Args:
        n_clusters: K (default 100); ``K >= N`` makes every particle its own medoid.
        alpha: weight of the Euclidean part of the distance, in [0, 1] (default 0.25).
        sweeps: K-medoids assign/update sweeps (default 10).
    """

    name = "clustered"

    def __init__(self, n_clusters: int = 100, alpha: float = 0.25, sweeps: int = 10):
        self.n_clusters = check_count("n_clusters", n_clusters)
        self.sweeps = check_count("sweeps", sweeps)
        if isinstance(alpha, bool) or not isinstance(alpha, (int, float)) or not 0.0 <= float(alpha) <= 1.0:
            raise ArgumentError(f"alpha: expected a weight in [0, 1], got {alpha!r}")
        self.alpha = float(alpha)

    def place(self, model, x_prev, mean, scale_tril, z):
        eta_bar = model.transition_mean(x_prev)  # (B, N, d)
        index, medoids = self.cluster(model, eta_bar, z, scale_tril)
        return FlowPrior(resampling.gather_particles(eta_bar, medoids), scale_tril.unsqueeze(-3)), index

    def cluster(self, model, eta_bar: torch.Tensor, z: torch.Tensor, scale_tril: torch.Tensor):
        """``(index (B, N), medoids (B, K))`` of the predictions ``eta_bar (B, N, d)``, with the
        trial's prior factor ``scale_tril (B, d, d)`` for the lambda = 0 velocities."""
        B, N, _ = eta_bar.shape
        if self.n_clusters >= N:
            ar = torch.arange(N, device=eta_bar.device).expand(B, N)
            return ar, ar
        prior = FlowPrior(eta_bar, scale_tril.unsqueeze(-3))
        zero = torch.zeros((), dtype=eta_bar.dtype, device=eta_bar.device)
        zeta = _VELOCITY.coefficients(model, z, eta_bar, prior, zero, zero).drift(eta_bar)[0]
        dist = cluster_distance(eta_bar, zeta, self.alpha, model.structure.measurement_support)
        return kmedoids(dist, self.n_clusters, self.sweeps)

    # the (B, N, N) distance sweeps of K-medoids fall out of cache like per-particle flows, so
    # clustered points take as many trials per call as per-particle points
    preferred_chunk_trials = ParticlePoints.preferred_chunk_trials

    def extra_bytes(self, n_particles, state_dim):
        N, K, d = n_particles, min(self.n_clusters, n_particles), state_dim
        return 8 * (4 * N * N + 6 * K * d * d + 2 * N * d * d)  # N x N distances, K maps, gathers

    def arrange(self, prior, particles, index):
        B, N = particles.shape[:2]
        if index is None:
            raise ArgumentError("index: clustered linearisation points need the (B, N) cluster index")
        if index.shape != (B, N):
            raise ArgumentError(f"index: expected (B, N) = ({B}, {N}) cluster indices, got {tuple(index.shape)}")
        return prior, index, False

    def extra_repr(self) -> str:
        return f"n_clusters={self.n_clusters}, alpha={self.alpha}, sweeps={self.sweeps}"


#: the LEDH drift whose lambda = 0 velocities the clustered distance correlates
_VELOCITY = LEDHFlow()


def _check_points(name: str, mean: torch.Tensor, particles: torch.Tensor, L: int) -> None:
    B, _, d = particles.shape
    if mean.shape != (B, L, d):
        raise ArgumentError(f"{name}: expected ({B}, {L}, {d}) for these points, got {tuple(mean.shape)}")


#: the strategies by config name
POINTS = {"global": GlobalPoints, "particle": ParticlePoints, "clustered": ClusteredPoints}


def resolve_points(flow, points: Union[None, str, LinearisationPoints] = None, **knobs) -> LinearisationPoints:
    """The strategy for ``points``: a :class:`LinearisationPoints`, a name of :data:`POINTS`
    (built with ``knobs``, e.g. ``n_clusters`` for clustered points), or ``None`` for the flow's
    own default (:attr:`~torchflow.flows.ParticleFlow.points`)."""
    if isinstance(points, LinearisationPoints):
        return points
    if points is None:
        points = flow.points
    if points not in POINTS:
        raise ArgumentError(
            f"points: expected one of {tuple(POINTS)}, a LinearisationPoints or None "
            f"(the flow's default), got {points!r}"
        )
    cls = POINTS[points]
    return cls(**knobs) if cls is ClusteredPoints else cls()
