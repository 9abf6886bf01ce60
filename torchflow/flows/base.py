"""Particle flows: a flow states the drift ``dx/dlambda = A x + b`` at a linearisation point;
one integrator (:func:`integrate_flow`) steps every flow over a lambda schedule.

Shapes: a flow's coefficients are computed at L linearisation points per trial
(:mod:`~torchflow.flows.points`: L = 1 global, L = N per particle, L = K clustered), so
``A (B, L, d, d)``, ``b (B, L, d)``; the integrator (:mod:`~torchflow.flows.integrate`) moves the
points with their own drift and each particle ``(B, N, d)`` with its point's coefficients, and
accumulates ``log|det(I + eps A)|`` per point.

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

from torchflow.core import linalg
from torchflow.core.errors import ArgumentTypeError
from torchflow.flows.measurement import GaussianMeasurement


@dataclass
class FlowCoefficients:
    """Drift ``A x + b`` of one pseudo-time step.

    ``A`` is either an explicit tensor, ``(B, d, d)`` (global), ``(B, 1, d, d)`` (shared by a
    trial's particles) or ``(B, N, d, d)`` (local), or, when forming it would cost more than
    applying it, an operator ``apply_A(V)`` acting on stacked vectors ``V (..., d, r)``; then
    ``form_A()``, when given, forms the matrix for the uses that need it (:meth:`matrix`: the
    Gaussian image, clustered particles, composed global maps), once.

    Attributes:
        A: explicit matrix or ``None``.
        b: ``(B, d)`` or ``(B, N, d)``.
        log_det: ``log|det(I + eps A)|``, ``(B,)``, ``(B, 1)`` or ``(B, N)``; ``None`` for
            stochastic flows (their map is not a bijection of eta_0).
        apply_A: operator form of A (used when ``A`` is ``None``).
        form_A: ``() -> A``, the explicit matrix of an operator-form A, formed on first demand.
        noise_factor: stochastic flows only: ``G`` with ``G G^T = Q``, ``(..., d, r)`` batched like
            ``A`` (``r`` need not equal ``d``: a rank-deficient Q has a thin exact factor).
        noise_product: ``(U, V)`` with ``G = U V^T`` (``U (..., d, k)``, ``V (..., r, k)`` or a shared
            ``(r, k)``): ``G xi = U (V^T xi)`` without forming the ``d x r`` factor (Gromov's
            ``M^{-1}[:, s] W_s^T``); plain tensors, so it can be gathered to clustered particles.
        noise_cov_pair: ``(Q1, Q2)`` with ``Q = Q1 Q2^T`` (``(..., d, k)`` each), instead of
            forming Q: lets the integrator fuse the addition into a product.
        support: when the measurement reads only ``k`` of the ``d`` state coordinates
            (:attr:`~torchflow.models.Structure.measurement_support`), A's other columns are
            zero and ``A`` holds only the ``(..., d, k)`` nonzero ones: ``A x = A x[..., support]``.
            ``None``: ``A`` is the full ``(..., d, d)``.
    """

    A: Optional[torch.Tensor]
    b: torch.Tensor
    log_det: Optional[torch.Tensor]
    apply_A: Optional[Callable[[torch.Tensor], torch.Tensor]] = None
    noise_factor: Optional[torch.Tensor] = None
    support: Optional[torch.Tensor] = None
    noise_cov_pair: Optional[Tuple[torch.Tensor, torch.Tensor]] = None
    noise_product: Optional[Tuple[torch.Tensor, torch.Tensor]] = None
    form_A: Optional[Callable[[], torch.Tensor]] = None

    def matrix(self) -> torch.Tensor:
        """A as a tensor (the ``(..., d, k)`` support columns when ``support`` is set): the given
        one, or formed once from ``form_A``."""
        if self.A is None:
            if self.form_A is None:
                raise ArgumentTypeError(
                    "these flow coefficients give A only as an operator (apply_A) and cannot form it: give A or form_A"
                )
            self.A = self.form_A()
        return self.A

    def diffusion_cov(self) -> torch.Tensor:
        """``Q = G G^T`` (from ``noise_cov_pair`` or ``noise_factor``; 0 for a deterministic flow)."""
        if self.noise_cov_pair is not None:
            return self.noise_cov_pair[0] @ self.noise_cov_pair[1].transpose(-1, -2)
        if self.noise_factor is None:
            return self.b.new_zeros(())
        return self.noise_factor @ self.noise_factor.transpose(-1, -2)

    def diffuse(self, xi: torch.Tensor) -> torch.Tensor:
        """``G xi`` for standard normal draws ``xi (..., r)`` batched like ``b``."""
        if self.noise_product is not None:
            U, V = self.noise_product
            Vxi = xi @ V if V.dim() == 2 else (V * xi.unsqueeze(-1)).sum(-2)  # V^T xi, (..., k)
            return linalg.matvec(U, Vxi)
        return linalg.matvec(self.noise_factor, xi)

    @property
    def noise_rank(self) -> int:
        """r, the number of standard normal draws per point the diffusion uses."""
        if self.noise_product is not None:
            return self.noise_product[1].shape[-2]
        return self.noise_factor.shape[-1]

    @property
    def has_noise(self) -> bool:
        return self.noise_factor is not None or self.noise_product is not None

    def gather(self, index: torch.Tensor) -> "FlowCoefficients":
        """These coefficients, computed at L points ``(B, L|1, ...)``, for the particles of each
        point's cluster (``index (B, N)``); shared tensors (no point dimension) stay as they are.
        ``log_det`` is not gathered (it belongs to the points)."""
        if self.apply_A is not None and self.form_A is None:
            raise NotImplementedError(
                "coefficients given as a closure (apply_A without form_A) cannot be gathered "
                "to clustered particles: give tensors (A, noise_factor or noise_product)"
            )
        A = None if self.A is None and self.apply_A is None else self.matrix()

        def g(t):
            return None if t is None or t.dim() < 3 else _gather_points(t, index)

        pair = lambda p: None if p is None else (g(p[0]), p[1] if p[1].dim() < 3 else g(p[1]))
        return FlowCoefficients(
            g(A),
            g(self.b),
            None,
            noise_factor=g(self.noise_factor),
            support=self.support,
            noise_cov_pair=pair(self.noise_cov_pair),
            noise_product=pair(self.noise_product),
        )

    def cols(self, x: torch.Tensor) -> torch.Tensor:
        """The coordinates of ``x (..., d)`` that A acts on (all, or ``support``)."""
        return x if self.support is None else x[..., self.support]  # cheaper than index_select on the CPU

    def dense_A(self) -> torch.Tensor:
        """A as a full ``(..., d, d)`` matrix (zero columns outside ``support`` filled in)."""
        A = self.matrix()
        if self.support is None:
            return A
        d = self.b.shape[-1]
        return A.new_zeros(*A.shape[:-1], d).index_copy(-1, self.support, A)

    def drift(self, *points: torch.Tensor):
        """``A x + b`` for each ``x`` of ``points`` (each batched like ``b``)."""
        if self.A is not None:
            # one matrix-vector product per point set: with MKL a batched d x k @ k x 2 product
            # takes a general matrix-matrix path that costs more than two d x k @ k x 1 ones
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
    #: a dict for one integration whose measurement is fixed over pseudo-time (a linear measurement
    #: with a constant R, :attr:`~torchflow.flows.measurement.GaussianMeasurement.fixed`): a flow keeps
    #: there what it computes once from the prior and W (the Daum-Huang flows: S's eigendecomposition)
    fixed: Optional[dict] = None

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
        order = list(sup) + [i for i in range(d) if i not in chosen]
        perm = linalg.index_tensor(order, L.device)
        inv = linalg.index_tensor(sorted(range(d), key=order.__getitem__), L.device)  # perm's inverse
        P = L @ L.transpose(-1, -2)
        Lp = linalg.safe_cholesky(P.index_select(-1, perm).index_select(-2, perm))
        root = Lp.index_select(-2, inv)
        cols, cols_s = root[..., :k].contiguous(), Lp[..., :k, :k].contiguous()  # views are slow in bmm
        return replace(
            self, support=perm[:k], root=root, cols=cols, cols_support=cols_s, cov_cols=cols @ cols_s.transpose(-1, -2)
        )


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
        map_jacobian: with ``map_jacobian=True`` (deterministic flows), each particle's map matrix
            ``M`` (``eta_1 = M eta_0 + c``): ``(B, 1, d, d)`` (one point per trial) or ``(B, N, d, d)``.
    """

    particles: torch.Tensor
    log_det: Optional[torch.Tensor]
    aux: torch.Tensor
    log_proposal: Optional[torch.Tensor] = None
    proposal_mean: Optional[torch.Tensor] = None
    proposal_cov: Optional[torch.Tensor] = None
    image_mean: Optional[torch.Tensor] = None
    image_cov: Optional[torch.Tensor] = None
    map_jacobian: Optional[torch.Tensor] = None


class ParticleFlow(nn.Module):
    """Base class of flows. Subclasses implement :meth:`coefficients`.

    Attributes:
        points: the flow's default linearisation points, a name of
            :data:`~torchflow.flows.points.POINTS`: ``"global"`` (EDH) or ``"particle"`` (LEDH).
            Filters and :func:`~torchflow.flows.integrate_flow` take ``points`` (a name or a
            :class:`~torchflow.flows.points.LinearisationPoints`) to pair any flow with any points.
        stochastic: the flow has a diffusion term (``noise_factor``) and no log-det.
        kernel: the fused kernel the flow's coefficients admit, declared by the flow's own class
            (not inherited: a subclass that changes the coefficients declares it again, or runs the
            reference loop): ``"daum_huang"`` (the exact Daum-Huang coefficients), ``"gromov"`` (the
            Gromov flow with its exact diffusion factor) or ``None``. The kernel layer
            (:mod:`torchflow.flows.select`) reads it.
    """

    points: str = "global"
    stochastic: bool = False
    kernel: Optional[str] = None

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

    def coefficients(
        self, model, z: torch.Tensor, aux: torch.Tensor, prior: FlowPrior, lam: torch.Tensor, eps: torch.Tensor
    ) -> FlowCoefficients:
        """Convenience: :meth:`coefficients_at` with the model's own measurement term linearised at
        ``aux`` (``(B, d)`` or ``(B, L, d)``); ``z (B, m)``."""
        meas = GaussianMeasurement.from_model(model, z)
        prior = prior.reduced(meas.support)
        return self.coefficients_at(meas.at(aux, prior.support), prior, lam, eps)


def _gather_points(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Rows ``x[b, index[b, n]]`` of per-point values ``x (B, K|1, ...)`` -> ``(B, N, ...)``."""
    if x.shape[1] == 1:
        return x.expand(x.shape[0], index.shape[1], *x.shape[2:])
    flat = index.reshape(*index.shape, *([1] * (x.dim() - 2))).expand(*index.shape, *x.shape[2:])
    return x.gather(1, flat)
