"""Particle flows: a flow states the drift ``dx/dlambda = A x + b`` at a linearisation point;
one integrator (:func:`integrate_flow`) steps every flow over a lambda schedule.

Shapes: a *global* flow (EDH-type) linearises once per trial, so its coefficients are
``A (B, d, d)``, ``b (B, d)``; a *local* flow (LEDH-type) once per particle, ``A (B, N, d, d)``,
``b (B, N, d)``. The integrator migrates the particles ``(B, N, d)`` and the auxiliary
linearisation point(s) with the same coefficients and accumulates ``log|det(I + eps A)|``.

A *stochastic* flow also states a diffusion ``Q = G G^T`` (``noise_factor`` G); the integrator
then takes Euler-Maruyama steps ``eta <- eta + eps (A eta + b) + sqrt(eps) G xi`` and, given the
Gaussian law ``N(mu_0, S_0)`` the particles were drawn from, tracks each particle's proposal law
exactly: the coefficients depend only on the deterministic auxiliary point, so ``eta_1`` is
Gaussian with ``mu_j = (I + eps_j A_j) mu_{j-1} + eps_j b_j`` and
``S_j = (I + eps_j A_j) S_{j-1} (I + eps_j A_j)^T + eps_j Q_j``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Optional, Tuple

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
        log_det: ``log|det(I + eps A)|``, ``(B,)``, ``(B, 1)`` or ``(B, N)``; ``None`` for
            stochastic flows (their map is not a bijection of eta_0).
        apply_A: operator form of A (used when ``A`` is ``None``).
        noise_factor: stochastic flows only: ``G`` with ``G G^T = Q``, ``(..., d, r)`` batched like
            ``A`` (``r`` need not equal ``d``: a rank-deficient Q has a thin exact factor).
        noise_cov, noise_apply, noise_dim: the same diffusion in operator form (used instead of
            ``noise_factor`` when given): ``Q (..., d, d)``, ``xi (..., r) -> G xi`` and ``r``;
            cheaper when G is a product of small factors.
        noise_product: ``(U, V)`` with ``G = U V^T`` (``U (..., d, k)``, ``V (..., r, k)`` or a shared
            ``(r, k)``): ``G xi = U (V^T xi)`` without forming the ``d x r`` factor (Gromov's
            ``M^{-1}[:, s] W_s^T``); plain tensors, so it can be gathered to clustered particles.
        noise_cov_pair: ``(Q1, Q2)`` with ``Q = Q1 Q2^T`` (``(..., d, k)`` each), instead of
            ``noise_cov``: lets the integrator fuse the addition into a product.
        support: when the measurement reads only ``k`` of the ``d`` state coordinates
            (:attr:`~torchflow.models.StateSpaceModel.measurement_support`), A's other columns are
            zero and ``A`` holds only the ``(..., d, k)`` nonzero ones: ``A x = A x[..., support]``.
            ``None``: ``A`` is the full ``(..., d, d)``.
    """

    A: Optional[torch.Tensor]
    b: torch.Tensor
    log_det: Optional[torch.Tensor]
    apply_A: Optional[Callable[[torch.Tensor], torch.Tensor]] = None
    noise_factor: Optional[torch.Tensor] = None
    support: Optional[torch.Tensor] = None
    noise_cov: Optional[torch.Tensor] = None
    noise_apply: Optional[Callable[[torch.Tensor], torch.Tensor]] = None
    noise_dim: Optional[int] = None
    noise_cov_pair: Optional[Tuple[torch.Tensor, torch.Tensor]] = None
    noise_product: Optional[Tuple[torch.Tensor, torch.Tensor]] = None

    def diffusion_cov(self) -> torch.Tensor:
        """``Q = G G^T`` (given, or formed from ``noise_factor``)."""
        if self.noise_cov is not None:
            return self.noise_cov
        if self.noise_cov_pair is not None:
            return self.noise_cov_pair[0] @ self.noise_cov_pair[1].transpose(-1, -2)
        return self.noise_factor @ self.noise_factor.transpose(-1, -2)

    def diffuse(self, xi: torch.Tensor) -> torch.Tensor:
        """``G xi`` for standard normal draws ``xi (..., r)`` batched like ``b``."""
        if self.noise_product is not None:
            U, V = self.noise_product
            Vxi = xi @ V if V.dim() == 2 else (V * xi.unsqueeze(-1)).sum(-2)  # V^T xi, (..., k)
            return linalg.matvec(U, Vxi)
        if self.noise_apply is not None:
            return self.noise_apply(xi)
        return linalg.matvec(self.noise_factor, xi)

    @property
    def noise_rank(self) -> int:
        """r, the number of standard normal draws per point the diffusion uses."""
        if self.noise_dim is not None:
            return self.noise_dim
        if self.noise_product is not None:
            return self.noise_product[1].shape[-2]
        return self.noise_factor.shape[-1]

    @property
    def has_noise(self) -> bool:
        return self.noise_factor is not None or self.noise_apply is not None or self.noise_product is not None

    def gather(self, index: torch.Tensor) -> "FlowCoefficients":
        """These coefficients, computed at L points ``(B, L|1, ...)``, for the particles of each
        point's cluster (``index (B, N)``); shared tensors (no point dimension) stay as they are.
        ``log_det`` is not gathered (it belongs to the points)."""
        if self.noise_apply is not None or self.apply_A is not None:
            raise NotImplementedError("coefficients given as closures (apply_A, noise_apply) cannot be gathered "
                                      "to clustered particles: give tensors (A, noise_factor or noise_product)")

        def g(t):
            return None if t is None or t.dim() < 3 else _gather_points(t, index)

        pair = lambda p: None if p is None else (g(p[0]), p[1] if p[1].dim() < 3 else g(p[1]))  # noqa: E731
        return FlowCoefficients(g(self.A), g(self.b), None, noise_factor=g(self.noise_factor), support=self.support,
                                noise_cov=g(self.noise_cov), noise_dim=self.noise_dim,
                                noise_cov_pair=pair(self.noise_cov_pair), noise_product=pair(self.noise_product))

    def cols(self, x: torch.Tensor) -> torch.Tensor:
        """The coordinates of ``x (..., d)`` that A acts on (all, or ``support``)."""
        return x if self.support is None else x.index_select(-1, self.support)

    def dense_A(self) -> torch.Tensor:
        """A as a full ``(..., d, d)`` matrix (zero columns outside ``support`` filled in)."""
        if self.support is None:
            return self.A
        d = self.b.shape[-1]
        return self.A.new_zeros(*self.A.shape[:-1], d).index_copy(-1, self.support, self.A)

    def drift(self, *points: torch.Tensor):
        """``A x + b`` for each ``x`` of ``points`` (each batched like ``b``)."""
        if self.A is not None:
            # one matrix-vector product per point set: with MKL a batched d x k @ k x 2 product
            # costs more than two d x k @ k x 1 ones (16 x 8, 2000 matrices: 0.73 vs 2 x 0.2 ms)
            return [linalg.matvec(self.A, self.cols(x)) + self.b for x in points]
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
    #: filled by :meth:`reduced`: ``support (k,)`` (``None``: all coordinates), ``root (..., d, d)``
    #: a square root of P (``root root^T = P``) whose rows ``support`` vanish beyond column k,
    #: ``cols = root[..., :k]`` and ``cols_support = root[..., support, :k]`` (lower triangular).
    support: Optional[torch.Tensor] = None
    root: Optional[torch.Tensor] = None
    cols: Optional[torch.Tensor] = None
    cols_support: Optional[torch.Tensor] = None
    cov_cols: Optional[torch.Tensor] = None  # P[..., :, support] = cols cols_support^T, (..., d, k)

    def reduced(self, support) -> "FlowPrior":
        """This prior with the factors the flows use, adapted to the model's measurement support.

        If h reads only the coordinates ``s`` (k of d), factor P in the order ``(s, rest)``:
        ``P[perm, perm] = L' L'^T`` and ``root = L'[inv_perm]``. Then ``W root = [W_s L'_ss, 0]``
        for the whitened Jacobian W (zero outside ``s``), so ``S = root^T J root`` is
        ``blockdiag(S_k, 0)`` and every flow quantity follows from ``k x k`` systems: exact, not an
        approximation. Computed once per filter step (P is fixed during the flow); without a
        support ``root = cols = cols_support = scale_tril``.
        """
        if self.cols is not None:
            return self
        L = self.scale_tril
        d = L.shape[-1]
        # ``support``: the measured coordinates (a tuple or None), or a model that declares them
        sup = getattr(support, "measurement_support", support)
        if sup is None or len(sup) == d:
            return replace(self, root=L, cols=L, cols_support=L, cov_cols=L @ L.transpose(-1, -2))
        k, chosen = len(sup), set(sup)
        perm = torch.tensor(list(sup) + [i for i in range(d) if i not in chosen], device=L.device)
        inv = torch.argsort(perm)
        P = L @ L.transpose(-1, -2)
        Lp = linalg.safe_cholesky(P.index_select(-1, perm).index_select(-2, perm))
        root = Lp.index_select(-2, inv)
        cols, cols_s = root[..., :k].contiguous(), Lp[..., :k, :k].contiguous()  # views are slow in bmm
        return replace(self, support=perm[:k], root=root, cols=cols, cols_support=cols_s,
                       cov_cols=cols @ cols_s.transpose(-1, -2))


@dataclass
class FlowOutput:
    """Result of :func:`integrate_flow`.

    Attributes:
        particles: ``(B, N, d)`` migrated particles (``eta_1``).
        log_det: ``(B, N)`` log|det| of the particle map ``eta_0 -> eta_1`` (deterministic flows;
            ``None`` for stochastic ones).
        aux: final auxiliary point(s), ``(B, d)`` or ``(B, N, d)``.
        log_proposal: stochastic flows given a ``proposal``: ``(B, N)`` log-density of each
            particle under its exact Gaussian law ``N(mu_1, S_1)``; otherwise ``None``.
        proposal_mean, proposal_cov: that law, ``(B, N, d)`` and ``(B, N|1, d, d)`` (or ``None``).
        image_mean, image_cov: with ``gaussian_image=True``, the image of each point's prior
            ``N(prior.mean, P)`` under the linearised flow (stochastic flows: with their diffusion),
            batched like the points: ``(B, d)``/``(B, d, d)`` (global), ``(B, N|K, d)`` and
            ``(B, N|K|1, d, d)`` (per particle, clustered). Gaussian and Gaussian-sum particle
            filters and flow-induced mixture proposals are built from it.
    """

    particles: torch.Tensor
    log_det: Optional[torch.Tensor]
    aux: torch.Tensor
    log_proposal: Optional[torch.Tensor] = None
    proposal_mean: Optional[torch.Tensor] = None
    proposal_cov: Optional[torch.Tensor] = None
    image_mean: Optional[torch.Tensor] = None
    image_cov: Optional[torch.Tensor] = None


POINTS = ("global", "particle", "clustered")


def resolve_points(flow, points: Optional[str]) -> str:
    """The linearisation points to use: ``points`` if given, else the flow's default
    (``"particle"`` for a per-particle flow such as LEDH, ``"global"`` for EDH)."""
    if points is None:
        return "particle" if flow.local else "global"
    if points not in POINTS:
        raise ValueError(f"points: expected one of {POINTS} or None (the flow's default), got {points!r}")
    return points


class ParticleFlow(nn.Module):
    """Base class of flows. Subclasses implement :meth:`coefficients`.

    Attributes:
        local: the flow's default linearisation points: per particle (True) or once per trial at
            the migrating mean (False). Filters and :func:`integrate_flow` take ``points`` to pair
            any flow with any points (global, per particle, clustered).
        stochastic: the flow has a diffusion term (``noise_factor``) and no log-det.
    """

    local: bool = False
    stochastic: bool = False

    def coefficients_at(self, lin, prior: FlowPrior, lam: torch.Tensor, eps: torch.Tensor) -> FlowCoefficients:
        """Drift (and diffusion) at pseudo-time ``lam`` (after the step of size ``eps``), from
        explicit tensors only: a flow never sees the model.

        Args:
            lin: :class:`~torchflow.flows.measurement.Linearisation`, the whitened measurement at
                the linearisation points: ``W (..., m, k)`` (or ``(m, k)`` shared) and ``y (..., m)``.
            prior: the flow's Gaussian prior at the points, reduced to the measured coordinates
                (:meth:`FlowPrior.reduced`), batched like the points.
            lam, eps: 0-d tensors.
        """
        raise NotImplementedError

    def coefficients(self, model, z: torch.Tensor, aux: torch.Tensor, prior: FlowPrior,
                     lam: torch.Tensor, eps: torch.Tensor) -> FlowCoefficients:
        """Convenience: :meth:`coefficients_at` with the model's own measurement term linearised at
        ``aux`` (``(B, d)`` or ``(B, L, d)``); ``z (B, m)``."""
        from .measurement import GaussianMeasurement

        meas = GaussianMeasurement.from_model(model, z)
        prior = prior.reduced(meas.support)
        return self.coefficients_at(meas.at(aux, prior.support), prior, lam, eps)


def integrate_flow(
    flow: ParticleFlow,
    model,
    particles: torch.Tensor,
    z: torch.Tensor,
    prior: FlowPrior,
    schedule: Optional[LambdaSchedule] = None,
    *,
    generator: Optional[torch.Generator] = None,
    proposal: Optional[FlowPrior] = None,
    noise=None,
    index: Optional[torch.Tensor] = None,
    points: Optional[str] = None,
    gaussian_image: bool = False,
    measurement=None,
) -> FlowOutput:
    """Integrate ``d eta = (A eta + b) d lambda [+ Q^{1/2} dW]`` from lambda = 0 to 1.

    The auxiliary point starts at ``prior.mean`` and migrates deterministically with the same
    drift; for a local flow each particle has its own. A deterministic flow (Euler) accumulates
    ``log|det(I + eps_j A_j)|``, the log-Jacobian of the particle map, which the PF-PF weight
    needs. A stochastic flow (Euler-Maruyama, noise from ``generator``) instead propagates the
    particles' Gaussian law from ``proposal`` and returns each particle's log-density under it.

    Args:
        flow: the flow (states A, b and, if stochastic, the diffusion factor).
        model: state-space model.
        particles: ``(B, N, d)`` samples eta_0.
        z: ``(B, m)``.
        prior: :class:`FlowPrior`, ``(B, d)`` (global) or ``(B, N, d)`` (local): the Gaussian the
            flow is built for (the homotopy starts from it).
        schedule: lambda schedule (default: exponential, 29 steps, ratio 1.2).
        generator: ``torch.Generator`` for the diffusion noise (stochastic flows).
        proposal: stochastic flows: the law ``eta_0 ~ N(mean, scale_tril scale_tril^T)`` the
            particles were drawn from, mean ``(B, N, d)``, factor broadcastable to
            ``(B, N, d, d)``. When given, the output carries ``log_proposal``.
        points: where the flow is linearised: ``"global"`` (once per trial, at the migrating mean:
            ``prior`` is per trial), ``"particle"`` (at every particle's auxiliary point: ``prior``
            per particle) or ``"clustered"`` (at K points, with ``index``); default: the flow's
            own (:attr:`ParticleFlow.local`), or ``"clustered"`` when ``index`` is given.
        measurement: the :class:`~torchflow.flows.measurement.GaussianMeasurement` to linearise
            at the points (default: the model's own, ``GaussianMeasurement.from_model(model, z)``);
            a filter passes its own for state-dependent noise, mixture components or data
            association. The flow itself only sees the whitened tensors at the points.
        gaussian_image: also return the image ``(image_mean, image_cov)`` of each point's prior
            Gaussian (costs a ``d x d`` covariance recursion per point).
        index: clustered linearisation points: ``(B, N)`` cluster of each particle; ``prior`` then
            holds one point per cluster (mean ``(B, K, d)``, factor broadcastable to
            ``(B, K, d, d)``), the flow is linearised at the K points and each particle moves with
            its cluster's drift (and diffusion, for stochastic flows; seed 004).
        noise: stochastic flows: optional ``noise(j, shape) -> (B, N, r)`` standard normals of
            pseudo-time step ``j`` (instead of drawing them from ``generator``); a filter that
            flows particles in blocks uses it to keep the draws those of the whole cloud.

    Returns:
        :class:`FlowOutput`.
    """
    schedule = schedule or ExponentialSchedule()
    eps_all, lam_all = schedule.steps(dtype=particles.dtype, device=particles.device)
    points = resolve_points(flow, points if index is None or points is not None else "clustered")
    if measurement is None:
        from .measurement import GaussianMeasurement

        measurement = GaussianMeasurement.from_model(model, z)
    if points == "clustered":
        if index is None:
            raise ValueError("index: clustered linearisation points need the (B, N) cluster index")
        return _integrate_clustered(flow, measurement, particles, prior, eps_all, lam_all, index, gaussian_image,
                                    generator, proposal)
    local = points == "particle"
    if flow.stochastic:
        return _integrate_stochastic(flow, measurement, particles, prior, eps_all, lam_all, generator, proposal,
                                     noise, local, gaussian_image)
    B, N, d = particles.shape
    prior = prior.reduced(measurement.support)
    image = _Image(prior, gaussian_image)
    aux = prior.mean
    log_det = torch.zeros(B, N, dtype=particles.dtype, device=particles.device)
    eta = particles
    if not local:
        # A global flow moves every particle of a trial by the same affine map: compose it on
        # (d, d) matrices, M <- (I + eps A) M, c <- (I + eps A) c + eps b, and apply it once.
        eye = torch.eye(d, dtype=particles.dtype, device=particles.device)
        M = eye.expand(B, d, d)
        c = torch.zeros(B, d, dtype=particles.dtype, device=particles.device)
        for j in range(len(eps_all)):
            eps, lam = eps_all[j], lam_all[j]
            co = flow.coefficients_at(measurement.at(aux, prior.support), prior, lam, eps)
            step = eye + eps * co.dense_A()  # (B, d, d)
            M = step @ M
            c = linalg.matvec(step, c) + eps * co.b
            aux = linalg.matvec(step, aux) + eps * co.b
            log_det = log_det + co.log_det.unsqueeze(-1)
        eta = torch.baddbmm(c.unsqueeze(1), particles, M.transpose(-1, -2))
        if image.on:  # the composed map applied to the prior: M P M^T
            image.cov = linalg.symmetrize(M @ image.cov @ M.transpose(-1, -2))
        return image.output(FlowOutput(eta, log_det, aux))
    for j in range(len(eps_all)):
        eps, lam = eps_all[j], lam_all[j]
        c = flow.coefficients_at(measurement.at(aux, prior.support), prior, lam, eps)
        d_eta, d_aux = c.drift(eta, aux)
        eta = eta + eps * d_eta
        aux = aux + eps * d_aux
        log_det = log_det + c.log_det
        image.step(c, eps)
    return image.output(FlowOutput(eta, log_det, aux))


class _Image:
    """The Gaussian image of the points' prior ``N(mean, P)``: the mean is the auxiliary point
    itself; the covariance follows ``S <- (I + eps A) S (I + eps A)^T (+ eps Q)``."""

    def __init__(self, prior: "FlowPrior", on: bool):
        self.on = on
        if on:
            L = prior.scale_tril
            self.cov = L @ L.transpose(-1, -2)
            d = L.shape[-1]
            self.eye = torch.eye(d, dtype=L.dtype, device=L.device)

    def step(self, co: "FlowCoefficients", eps) -> None:
        if not self.on:
            return
        if co.noise_factor is None and co.noise_cov is None and co.noise_cov_pair is None:
            co = replace(co, noise_cov=co.b.new_zeros(()))  # deterministic: no diffusion term
        self.cov = _propagate_cov(self.cov, co, eps, self.eye)

    def output(self, out: "FlowOutput") -> "FlowOutput":
        if self.on:
            out.image_mean, out.image_cov = out.aux, linalg.symmetrize(self.cov)
        return out


def _gather_points(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Rows ``x[b, index[b, n]]`` of per-point values ``x (B, K|1, ...)`` -> ``(B, N, ...)``."""
    if x.shape[1] == 1:
        return x.expand(x.shape[0], index.shape[1], *x.shape[2:])
    flat = index.reshape(*index.shape, *([1] * (x.dim() - 2))).expand(*index.shape, *x.shape[2:])
    return x.gather(1, flat)


def _integrate_clustered(flow, measurement, particles, prior, eps_all, lam_all, index, gaussian_image=False,
                         generator=None, proposal=None):
    """Flow linearised at K points, ``prior.mean (B, K, d)``: at every pseudo-time step the
    coefficients are computed at the K points (which migrate with their own drift) and gathered to
    the particles of each cluster (:meth:`FlowCoefficients.gather`). Deterministic flows: a
    cluster's ``log|det|`` is the sum of its steps' exact log-dets. Stochastic flows: the
    particles take Euler-Maruyama steps with their cluster's drift and diffusion, and given
    ``proposal`` each particle's Gaussian law is tracked exactly, as for per-particle points.
    Cheaper than composing d x d maps per cluster whenever ``K d > N k / d``."""
    B, N, d = particles.shape
    if index.shape != (B, N):
        raise ValueError(f"index: expected (B, N) = ({B}, {N}) cluster indices, got {tuple(index.shape)}")
    prior = prior.reduced(measurement.support)
    image = _Image(prior, gaussian_image)
    aux = prior.mean  # (B, K, d)
    eta = particles
    log_det = torch.zeros(B, aux.shape[1], dtype=particles.dtype, device=particles.device)
    track = flow.stochastic and proposal is not None
    if track:
        eye = torch.eye(d, dtype=particles.dtype, device=particles.device)
        mu, Sig = _initial_law(proposal, B, N, d)
    for j in range(len(eps_all)):
        eps, lam = eps_all[j], lam_all[j]
        co = flow.coefficients_at(measurement.at(aux, prior.support), prior, lam, eps)
        aux = aux + eps * co.drift(aux)[0]
        image.step(co, eps)
        at_particles = co.gather(index)
        if not flow.stochastic:
            eta = eta + eps * at_particles.drift(eta)[0]
            log_det = log_det + co.log_det
            continue
        drifts = at_particles.drift(eta, *([mu] if track else []))
        xi = linalg.standard_normal((B, N, at_particles.noise_rank), dtype=eta.dtype, device=eta.device,
                                    generator=generator)
        eta = eta + eps * drifts[0] + eps.sqrt() * at_particles.diffuse(xi)
        if track:
            mu = mu + eps * drifts[-1]
            Sig = _propagate_cov(Sig, at_particles, eps, eye)
    if not flow.stochastic:
        return image.output(FlowOutput(eta, _gather_points(log_det.unsqueeze(-1), index).squeeze(-1), aux))
    return _stochastic_output(eta, aux, image, *((mu, Sig) if track else ()))


def _flat3(x: torch.Tensor, batch) -> torch.Tensor:
    return x.expand(*batch, *x.shape[-2:]).reshape(-1, *x.shape[-2:])


def _propagate_cov(Sig, co: "FlowCoefficients", eps, eye):
    """``(I + eps A) Sig (I + eps A)^T + eps Q``, ``Sig (..., d, d)``.

    With a measurement support A has only k nonzero columns ``A_s (..., d, k)``:
    ``V = (I + eps A) Sig = Sig + eps A_s Sig[s, :]`` and ``V (I + eps A)^T = V + eps V[:, s] A_s^T``,
    two ``d x k x d`` products fused with their additions (``baddbmm``), and ``Q`` given as a pair
    ``Q = Q1 Q2^T`` is added by a third; no separate passes over the ``d x d`` matrices."""
    if co.support is None:
        T = eye + eps * co.dense_A()
        return T @ Sig @ T.transpose(-1, -2) + eps * co.diffusion_cov()
    A, sup, e = co.A, co.support, float(eps)
    pair = co.noise_cov_pair
    shapes = [Sig.shape[:-2], A.shape[:-2]] + ([p.shape[:-2] for p in pair] if pair is not None else [])
    batch = torch.broadcast_shapes(*shapes)
    S3, A3 = _flat3(Sig, batch), _flat3(A, batch)
    V = torch.baddbmm(S3, A3, S3.index_select(-2, sup), alpha=e)
    out = torch.baddbmm(V, V.index_select(-1, sup), A3.transpose(-1, -2), alpha=e)
    if pair is not None:
        out = torch.baddbmm(out, _flat3(pair[0], batch), _flat3(pair[1], batch).transpose(-1, -2), alpha=e)
        return out.reshape(*batch, *Sig.shape[-2:])
    return out.reshape(*batch, *Sig.shape[-2:]) + eps * co.diffusion_cov()


def _integrate_stochastic(flow, measurement, particles, prior, eps_all, lam_all, generator, proposal, noise=None,
                          local=True, gaussian_image=False):
    """Euler-Maruyama for stochastic flows, with the exact Gaussian proposal recursion."""
    B, N, d = particles.shape
    eye = torch.eye(d, dtype=particles.dtype, device=particles.device)
    prior = prior.reduced(measurement.support)
    image = _Image(prior, gaussian_image)
    aux, eta = prior.mean, particles
    track = proposal is not None
    if track:
        mu, Sig = _initial_law(proposal, B, N, d)
    for j in range(len(eps_all)):
        eps, lam = eps_all[j], lam_all[j]
        co = flow.coefficients_at(measurement.at(aux, prior.support), prior, lam, eps)
        A, b, G = co.A, co.b, co.noise_factor
        if A is None or not co.has_noise:
            raise TypeError(f"{type(flow).__name__}: a stochastic flow must give an explicit A and a noise_factor")
        image.step(co, eps)  # at the points, before the particles' view of the coefficients
        if local:  # aux is per particle: one stacked product for every vector
            drifts = co.drift(eta, aux, *([mu] if track else []))
            aux = aux + eps * drifts[1]
            d_eta, d_mu = drifts[0], drifts[-1]
        else:  # one (B, d, .) matrix per trial: move the trial's aux, view the rest per particle
            aux = aux + eps * co.drift(aux)[0]
            if co.noise_factor is None:
                raise TypeError(f"{type(flow).__name__}: a global stochastic flow must give a noise_factor")
            A, b, G = A.unsqueeze(-3), b.unsqueeze(-2), co.noise_factor.unsqueeze(-3)
            drifts = FlowCoefficients(A, b, None, support=co.support).drift(eta, *([mu] if track else []))
            d_eta, d_mu = drifts[0], drifts[-1]
            co = FlowCoefficients(A, b, None, noise_factor=G, support=co.support)
        if noise is not None:
            xi = noise(j, (B, N, co.noise_rank))
        else:
            xi = linalg.standard_normal((B, N, co.noise_rank), dtype=eta.dtype, device=eta.device,
                                        generator=generator)
        eta = eta + eps * d_eta + eps.sqrt() * co.diffuse(xi)
        if track:
            mu = mu + eps * d_mu
            Sig = _propagate_cov(Sig, co, eps, eye)
    return _stochastic_output(eta, aux, image, *((mu, Sig) if track else ()))


def _initial_law(proposal: FlowPrior, B: int, N: int, d: int):
    """``(mu (B, N, d), Sig (B, N|1, d, d))`` of the law the particles were drawn from."""
    L0 = proposal.scale_tril
    Sig = L0 @ L0.transpose(-1, -2)
    return proposal.mean.expand(B, N, d), (Sig.expand(B, 1, d, d) if Sig.dim() == 2 else Sig)


def _stochastic_output(eta, aux, image, mu=None, Sig=None) -> FlowOutput:
    """Result of a stochastic flow; with the tracked law ``N(mu, Sig)`` each particle's
    log-density under it (the proposal density of Pal & Coates' Algorithm 1)."""
    if mu is None:
        return image.output(FlowOutput(eta, None, aux))
    Sig = linalg.symmetrize(Sig)
    log_q = linalg.mvn_log_prob(eta, mu, linalg.safe_cholesky(Sig))
    return image.output(FlowOutput(eta, None, aux, log_proposal=log_q, proposal_mean=mu, proposal_cov=Sig))
