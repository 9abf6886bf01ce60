"""Marginal particle weights: mixtures over the previous cloud, O(N^2) per step in blocks.

The standard weight of particle i divides the model's joint density of its own path by the
proposal's, ``p(x_i | x'_i) p(z | x_i) / q(x_i | x'_i)``: any move the proposal makes away from the
transition ``p(. | x'_i)`` of its own parent is paid for in the weight, however good it is for the
filtering law. The marginal weight (Klaas, de Freitas & Doucet 2005, the marginal particle filter)
weighs the particle against the filter's predictive mixture instead, and divides by the proposal's
own mixture over the parents:

    w_i ∝ p(z | x_i) [sum_j W'_j p(x_i | x'_j)] / [(1/N) sum_j q(x_i | x'_j)],

``x'_j, W'_j`` the previous particles and normalised weights (slot j propagates parent ``x'_j``;
each slot is one stratum of the proposal mixture, whence the uniform ``1/N``). The evidence
increment ``(1/N) sum_i w_i`` is unbiased for ``sum_j W'_j ∫ p(z | x) p(x | x'_j) dx``, as the standard
one is, so the filter's evidence stays unbiased.

Gradients: with the proposal held constant (``proposal_gradient="score"``) and
``resampling_gradient="stop_gradient"``, autograd through ``log sum_j exp(lw'_j + log p(x_i | x'_j))``
gives each particle the backward-weighted mean of its parents' scores plus the step's own terms:
the O(N^2) score recursion of Poyiadjis, Doucet & Singh (2011), whose estimate of ``grad log Z``
does not degenerate along the particles' genealogy as the path-based estimators do.

Which proposals have a mixture density: the transition itself (the bootstrap proposal), and any
proposal whose law given a parent is Gaussian and reported as :attr:`Proposed.ancestor_law`: the
deterministic flows (each parent's affine map ``eta -> M eta + c`` pushes ``N(f(x'), Q)`` to
``N(M f(x') + c, M Q M^T)``, for global, per-particle and clustered points alike: their maps depend
on the previous particles and ``z``, not on the particle's own noise) and the stochastic flows (the
exact Gaussian law tracked through the flow).
"""

from __future__ import annotations

import contextlib
import math
from typing import Callable, List, Optional, Sequence

import torch
import torch.utils.checkpoint

from torchflow.core import linalg

#: ``weights=`` choices of :class:`~torchflow.filters.ParticleFilter`
WEIGHTS = ("standard", "marginal")

#: default memory of one block of pair evaluations (bytes); the blocks split the rows i
PAIR_BLOCK_BYTES = 64 * 2**20


def pair_rows(B: int, N: int, J: int, d: int, itemsize: int, chunk: Optional[int] = None) -> int:
    """Rows i per block of a ``(B, rows, J, d)`` pair evaluation: ``chunk`` when given, else what
    fits :data:`PAIR_BLOCK_BYTES` (at least one)."""
    if chunk:
        return max(1, min(int(chunk), N))
    return max(1, min(N, PAIR_BLOCK_BYTES // max(1, B * J * d * itemsize)))


class Pairs:
    """Pair log-densities ``log k(x_i, j)`` of a block of rows against J components, reduced by a
    weighted log-sum-exp over the components (:meth:`logsumexp`). Subclasses give :meth:`block`;
    :class:`SharedGaussianPairs` reduces without forming the pair matrix's distances."""

    def block(self, sl: slice) -> torch.Tensor:
        """``(B, n, J)`` pair log-densities of rows ``sl``."""
        raise NotImplementedError

    def logsumexp(self, sl: slice, log_weights: torch.Tensor) -> torch.Tensor:
        """``(B, n)``: ``log sum_j exp(log_weights[:, j] + log k(x_i, j))`` for the rows ``sl``."""
        return torch.logsumexp(self.block(sl) + log_weights.unsqueeze(1), dim=-1)


class FunctionPairs(Pairs):
    """Pairs from a function of the row slice."""

    def __init__(self, fn: Callable[[slice], torch.Tensor]):
        self.block = fn


class SharedGaussianPairs(Pairs):
    """``log N(x_i; mean_j, L L^T)`` with one factor per trial: with ``a = L^{-1} x``,
    ``m = L^{-1} mean``, the exponent is ``a_i.m_j - |m_j|^2/2 - |a_i|^2/2``, so a weighted
    log-sum-exp over j is one batched matrix product (``baddbmm``) and one reduction per block."""

    def __init__(self, x: torch.Tensor, mean: torch.Tensor, L: torch.Tensor):
        B, N, d = x.shape
        centre = x.mean(1, keepdim=True)  # centred: the expanded square's terms stay small
        x, mean = x - centre, mean - centre
        Lb = L.expand(B, d, d) if L.dim() == 2 else L
        self.a = linalg.solve_triangular(Lb, x.transpose(-1, -2), upper=False).transpose(-1, -2)  # (B, N, d)
        m = linalg.solve_triangular(Lb, mean.transpose(-1, -2), upper=False).transpose(-1, -2)  # (B, J, d)
        self.mT, self.half_mm = m.transpose(-1, -2), 0.5 * m.pow(2).sum(-1)  # (B, d, J), (B, J)
        logdet = torch.log(Lb.diagonal(dim1=-2, dim2=-1)).sum(-1)  # (B,)
        self.row = (-0.5 * d * math.log(2 * math.pi) - logdet).unsqueeze(-1) - 0.5 * self.a.pow(2).sum(-1)  # (B, N)

    def logsumexp(self, sl, log_weights):
        S = torch.baddbmm((log_weights - self.half_mm).unsqueeze(1), self.a[:, sl], self.mT)  # (B, n, J)
        return self.row[:, sl] + torch.logsumexp(S, dim=-1)

    def block(self, sl):
        S = torch.baddbmm((-self.half_mm).unsqueeze(1), self.a[:, sl], self.mT)
        return self.row[:, sl].unsqueeze(-1) + S


def mixture_logsumexp(pairs: Pairs, log_weights: Sequence[torch.Tensor], N: int, rows: int) -> List[torch.Tensor]:
    """``log sum_j exp(log_w[b, j] + log k(x_i, j))`` for each weight vector ``log_w (B, J)``, i < N,
    in blocks of ``rows`` rows. Returns ``(B, N)`` per weight vector."""

    def block(sl: slice, *lws):
        return tuple(pairs.logsumexp(sl, lw) for lw in lws)

    # with autograd on, each block is recomputed in the backward pass rather than kept: the pair
    # matrices are O(B N^2) per step, the saved inputs O(B N d)
    run = (
        (lambda sl: torch.utils.checkpoint.checkpoint(block, sl, *log_weights, use_reentrant=False))
        if torch.is_grad_enabled()
        else (lambda sl: block(sl, *log_weights))
    )
    outs = [run(slice(s, min(N, s + rows))) for s in range(0, N, rows)]
    return [torch.cat(parts, 1) for parts in zip(*outs)]


class ComponentGaussianPairs(Pairs):
    """``log N(x_i; mean_j, L_j L_j^T)`` with one factor per component: with the precision
    ``P_j = L_j^{-T} L_j^{-1}`` the exponent is the inner product of the row features
    ``[vec(x_i x_i^T), x_i]`` with the component features ``[-vec(P_j)/2, P_j mean_j]`` plus a
    constant of j, so a weighted log-sum-exp over j is again one ``baddbmm`` (inner size
    ``d^2 + d``) and one reduction per block. Points and means are centred on the trial's mean
    point first, to keep the expanded quadratic's terms small."""

    def __init__(self, x: torch.Tensor, mean: torch.Tensor, L: torch.Tensor):
        B, N, d = x.shape
        centre = x.mean(1, keepdim=True)
        x, mean = x - centre, mean - centre
        eye = torch.eye(d, dtype=L.dtype, device=L.device).expand_as(L)
        W = linalg.solve_triangular(L, eye, upper=False)  # L_j^{-1}, (B, J, d, d)
        P = W.transpose(-1, -2) @ W  # (B, J, d, d)
        Pm = linalg.matvec(P, mean)  # (B, J, d)
        J = mean.shape[1]
        self.psi = torch.cat([-0.5 * P.reshape(B, J, d * d), Pm], -1).transpose(-1, -2)  # (B, d^2 + d, J)
        self.phi = torch.cat([(x.unsqueeze(-1) * x.unsqueeze(-2)).reshape(B, N, d * d), x], -1)  # (B, N, d^2 + d)
        logdet = torch.log(L.diagonal(dim1=-2, dim2=-1)).sum(-1)  # (B, J)
        self.col = -0.5 * (Pm * mean).sum(-1) - logdet - 0.5 * d * math.log(2 * math.pi)  # (B, J)

    def logsumexp(self, sl, log_weights):
        return torch.logsumexp(torch.baddbmm((log_weights + self.col).unsqueeze(1), self.phi[:, sl], self.psi), dim=-1)

    def block(self, sl):
        return torch.baddbmm(self.col.unsqueeze(1), self.phi[:, sl], self.psi)


def gaussian_pairs(x: torch.Tensor, mean: torch.Tensor, scale_tril: torch.Tensor) -> Pairs:
    """Pair log-densities ``log N(x_i; mean_j, L_j L_j^T)``.

    Args:
        x: ``(B, N, d)`` points.
        mean: ``(B, J, d)`` component means.
        scale_tril: lower factors ``(d, d)``, ``(B, d, d)``, ``(B, 1, d, d)`` (one per trial:
            :class:`SharedGaussianPairs`) or ``(B, J, d, d)`` (one per component:
            :class:`ComponentGaussianPairs`).
    """
    L = scale_tril
    if L.dim() == 4 and L.shape[1] == 1:
        L = L.squeeze(1)
    return SharedGaussianPairs(x, mean, L) if L.dim() <= 3 else ComponentGaussianPairs(x, mean, L)


def transition_pairs(model, x: torch.Tensor, x_prev: torch.Tensor) -> Pairs:
    """Pair log-densities ``log p(x_i | x'_j)`` of the model's transition by blocks of rows.

    A declared Gaussian transition is :func:`gaussian_pairs` at the transition means (one matrix
    product per block when Q does not depend on the state); any other goes through the model's
    ``transition_log_prob`` on ``(B, n J, d)`` pairs laid out like particles."""
    if model.structure.gaussian_transition:
        return gaussian_pairs(x, model.transition_mean(x_prev), model.transition_scale_tril(x_prev))
    B, J, d = x_prev.shape

    def pair(sl: slice) -> torch.Tensor:
        xi = x[:, sl]
        n = xi.shape[1]
        nxt = xi.unsqueeze(2).expand(B, n, J, d).reshape(B, n * J, d)
        prev = x_prev.unsqueeze(1).expand(B, n, J, d).reshape(B, n * J, d)
        return model.transition_log_prob(nxt, prev).reshape(B, n, J)

    return FunctionPairs(pair)


def marginal_log_increment(
    model,
    prop,
    x_prev: torch.Tensor,
    log_weights: torch.Tensor,
    log_lik: torch.Tensor,
    *,
    hold_proposal: bool,
    chunk: Optional[int] = None,
) -> torch.Tensor:
    """``(B, N)`` marginal log-weights (module docstring) before normalisation, to be added to the
    uniform ``-log N`` of the slots.

    Args:
        model: the state-space model.
        prop: the step's :class:`~torchflow.proposals.Proposed`: ``log_q is None`` (the proposal is
            the transition) or an ``ancestor_law`` ``(mean (B, N, d), scale_tril (B, N|1, d, d))``.
        x_prev: ``(B, N, d)`` the previous particles (each slot's parent).
        log_weights: ``(B, N)`` their normalised log-weights ``lw'``.
        log_lik: ``(B, N)`` ``log p(z | x_i)``.
        hold_proposal: evaluate the proposal mixture without a graph (the proposal held constant).
        chunk: rows per block (``None``: :data:`PAIR_BLOCK_BYTES`).
    """
    x = prop.particles
    B, N, d = x.shape
    rows = pair_rows(B, N, x_prev.shape[1], d, x.element_size(), chunk)
    uniform = torch.full_like(log_weights, -math.log(N))
    trans = transition_pairs(model, x, x_prev)
    if prop.log_q is None:  # q is the transition: one pair matrix, two mixtures
        log_rho, log_qbar = mixture_logsumexp(trans, (log_weights, uniform), N, rows)
        return log_lik + log_rho - (log_qbar.detach() if hold_proposal else log_qbar)
    (log_rho,) = mixture_logsumexp(trans, (log_weights,), N, rows)
    mean, scale_tril = prop.ancestor_law
    with torch.no_grad() if hold_proposal else contextlib.nullcontext():
        (log_qbar,) = mixture_logsumexp(gaussian_pairs(x, mean, scale_tril), (uniform,), N, rows)
    return log_lik + log_rho - log_qbar
