"""Exact Daum-Huang flows: EDH (global linearisation) and LEDH (local, per particle).

For a Gaussian prior ``N(eta_bar_0, P)`` and a measurement linearised at ``eta_bar``
(``H = dh/dx``, ``e = h(eta_bar) - H eta_bar``):

    A(lambda) = -1/2 P H^T (lambda H P H^T + R)^{-1} H
    b(lambda) = (I + 2 lambda A) [(I + lambda A) P H^T R^{-1} (z - e) + A eta_bar_0]

Computed in a square-root information form that needs no inverse of P and never an ``m x m``
system per point: with ``P = L L^T``, ``W = L_R^{-1} H`` and ``S = (W L)^T (W L) = L^T J L``
(``J = H^T R^{-1} H``), ``P H^T (lambda H P H^T + R)^{-1} H = L (I + lambda S)^{-1} L^T J``, and
``I + lambda S`` is symmetric with eigenvalues >= 1 (a well-conditioned Cholesky). The Euler
step's Jacobian determinant follows from the same factors,

    det(I + eps A) = det(I + (lambda - eps/2) S) / det(I + lambda S),

both symmetric positive definite when ``lambda >= eps/2`` (true for any schedule evaluated at the
pseudo-time after the step), so the map is always invertible and ``log|det|`` is exact and finite.
"""

from __future__ import annotations

from typing import Optional

import torch

from torchflow.core import linalg, tuning
from torchflow.flows.base import FlowCoefficients, FlowPrior, ParticleFlow
from torchflow.flows.measurement import Linearisation


def daum_huang_coefficients(
    W,
    y,
    L,
    eta_bar0,
    lam,
    eps,
    *,
    L_support=None,
    support=None,
    P_cols=None,
    operator=None,
    W_diag=None,
    fixed: Optional[dict] = None,
) -> FlowCoefficients:
    """EDH/LEDH drift from the whitened linearisation.

    Args:
        W: ``(..., m, k)`` whitened Jacobian (or ``(m, k)`` shared); y: ``(..., m)`` whitened
            pseudo-measurement.
        L: ``(..., d, k)`` square root of the prior covariance P: its Cholesky factor
            (``k = d``), or the first k columns of :attr:`FlowPrior.root` when the measurement
            reads only the coordinates ``support``.
        eta_bar0: ``(..., d)`` prior mean.
        lam, eps: pseudo-time after the step, step size.
        L_support: rows ``support`` of L, ``(..., k, k)`` (default: L itself, k = d).
        support: ``(k,)`` measured coordinates or ``None``.
        P_cols: ``L L_support^T = P[..., :, support]`` if precomputed (:attr:`FlowPrior.cov_cols`).
        operator: give A as an operator (``apply_A``, with ``form_A`` for uses that need the
            matrix) instead of forming it; ``None`` (default): when ``k`` is at least
            ``torchflow.core.tuning`` ``flow_operator_min_dim``.
        W_diag: ``(..., m)`` the diagonal of W when W is diagonal (:attr:`Linearisation.diag`); the
            operator form then scales rows instead of multiplying by W (``d x d x d`` -> ``d x d``
            per point; the same numbers: the products' other terms are exact zeros).

        fixed: a dict that lives for one integration, given when W and the prior do not change
            over pseudo-time (a linear measurement with a constant R: :attr:`GaussianMeasurement.fixed`)
            and no gradient is recorded: ``S = L_s^T J L_s`` is then the same at every step, so its
            eigendecomposition ``S = V diag(s) V^T`` (and ``W L_s``) is computed at the first step
            and kept there, and every later step solves ``(I + lam S) u = v`` as
            ``V diag(1 / (1 + lam s)) V^T v`` and takes
            ``log det(I + eps A) = sum log((1 + (lam - eps/2) s) / (1 + lam s))``: no ``k x k``
            factorisation per step and point. The same coefficients to round-off.

    A particle's flow applies A to only a few vectors, so for large k the operator form skips the
    ``k``-column solve and ``d x k x k`` product that form A (timings:
    ``python -m experiments.benchmarks.bench_gaussian_sum``); both give the same numbers up to round-off.
    """
    Ls = L if L_support is None else L_support
    k = Ls.shape[-1]
    if operator is None:
        operator = k >= tuning.get().flow_operator_min_dim
    eye = torch.eye(k, dtype=L.dtype, device=L.device)
    diag = operator and W_diag is not None
    if fixed is not None:
        co, A_times = _fixed_coefficients(fixed, W, y, L, Ls, lam, eps, support, P_cols, operator, W_diag)
        Pg = co.b  # b is set below from it
    else:
        if operator:
            W_times = _row_scaling(W_diag) if diag else (lambda M: W @ M)
            WL = W_times(Ls)  # (..., m, k)
            S = linalg.symmetrize(WL.transpose(-1, -2) @ WL)
            Wy = (W_diag * y).contiguous() if diag else _whitened_rhs(W, y)
        else:
            T, S, Wy = _gram_terms(W, y, Ls)
        # I + c S with c >= 0 has eigenvalues >= 1: its Cholesky cannot fail (no jitter retry, no host sync)
        K = torch.linalg.cholesky_ex(eye + lam * S)[0]
        K2 = torch.linalg.cholesky_ex(eye + (lam - 0.5 * eps) * S)[0]
        log_det = linalg.chol_logdet(K2) - linalg.chol_logdet(K)
        # P H^T R^{-1} (z - e) = L L_s^T W^T y
        Pg = _prior_gain(L, Ls, Wy, P_cols)
        if operator:

            def apply_A(V):  # -1/2 L (I + lam S)^{-1} (W L_s)^T W V_s for stacked vectors V (..., d, r)
                Vs = V if support is None else V[..., support, :]
                return -0.5 * (L @ linalg.chol_solve(K, WL.transpose(-1, -2) @ W_times(Vs)))

            def form_A():  # -1/2 L (I + lam S)^{-1} L_s^T J, (..., d, k)
                WLW = (WL.transpose(-1, -2) * W_diag.unsqueeze(-2)).contiguous() if diag else WL.transpose(-1, -2) @ W
                return -0.5 * (L @ linalg.chol_solve(K, WLW))

            co = FlowCoefficients(None, Pg, log_det, apply_A=apply_A, form_A=form_A, support=support)

            def A_times(v):
                return apply_A(v.unsqueeze(-1)).squeeze(-1)
        else:
            A = -0.5 * linalg.matmul(L, linalg.chol_solve(K, T))  # -1/2 L (I + lam S)^{-1} L^T J, (..., d, k)
            co = FlowCoefficients(A, Pg, log_det, support=support)  # b is set below

            def A_times(v):
                return linalg.matvec(A, co.cols(v))

    # b = (I + 2 lam A) u,  u = (I + lam A) Pg + A eta_bar0 = Pg + A (lam Pg + eta_bar0): two
    # single-vector products (a batched d x k @ k x 2 product costs more than two d x k @ k x 1)
    u = Pg + A_times(lam * Pg + eta_bar0)
    co.b = u + 2 * lam * A_times(u)
    return co


def _prior_gain(L, Ls, Wy, P_cols):
    """``P H^T R^{-1} (z - e) = L L_s^T W^T y`` ``(..., d)``."""
    return linalg.matvec(L, linalg.matvec(Ls.transpose(-1, -2), Wy)) if P_cols is None else linalg.matvec(P_cols, Wy)


def _fixed_coefficients(fixed, W, y, L, Ls, lam, eps, support, P_cols, operator, W_diag):
    """:func:`daum_huang_coefficients` for an integration whose ``S = L_s^T J L_s`` is the same at every
    pseudo-time (``fixed``, a dict of that integration): at its first step ``S = V diag(s) V^T`` and
    the two factors of ``A = -1/2 (L V) diag(1 / (1 + lam s)) (V^T L_s^T J)`` are computed and kept;
    every step then applies A with two products and takes ``log det(I + eps A)`` from ``s``.
    ``(coefficients with b unset, A_times)``."""
    if "left" not in fixed:
        T, S, _ = _gram_terms(W, y, Ls)  # T = L_s^T J (k, m) @ (m, k) per point, once
        vals, V = torch.linalg.eigh(S)
        fixed.update(left=L @ V, right=V.transpose(-1, -2) @ T, s=vals.clamp_min(0))  # S >= 0: no negative round-off
    left, right, s_ = fixed["left"], fixed["right"], fixed["s"]
    c1 = 1 + lam * s_
    log_det = (torch.log1p((lam - 0.5 * eps) * s_) - torch.log(c1)).sum(-1)
    Wy = (W_diag * y).contiguous() if W_diag is not None else _whitened_rhs(W, y)
    Pg = _prior_gain(L, Ls, Wy, P_cols)
    inv = (-0.5 / c1).unsqueeze(-1)  # (..., k, 1)

    def apply_A(V):  # A V_s for stacked vectors V (..., d, r)
        Vs = V if support is None else V[..., support, :]
        return left @ (inv * (right @ Vs))

    def form_A():  # (..., d, k)
        return left @ (inv * right)

    if operator:
        co = FlowCoefficients(None, Pg, log_det, apply_A=apply_A, form_A=form_A, support=support)
        return co, lambda v: apply_A(v.unsqueeze(-1)).squeeze(-1)
    co = FlowCoefficients(form_A(), Pg, log_det, support=support)
    return co, lambda v: linalg.matvec(co.A, co.cols(v))


def _row_scaling(w):
    """``M -> diag(w) M`` for a diagonal W given by ``w (..., m)``: the rows scaled, made contiguous like
    a product's result, so that the products that use it run the same kernels on the same layout as
    with the dense W (whose other terms are exact zeros): the same numbers."""
    return lambda M: (w.unsqueeze(-1) * M).contiguous()


def _whitened_rhs(W, y):
    """``W^T y`` for ``W (..., m, k)`` (or a shared ``(m, k)``) and ``y (..., m)`` -> ``(..., k)``."""
    return y @ W if W.dim() == 2 else (W * y.unsqueeze(-1)).sum(-2)


def _gram_terms(W, y, Ls):
    """``T = L_s^T J``, ``S = L_s^T J L_s`` and ``W^T y`` with ``J = W^T W``: the Gram matrix is formed
    first (one ``k x m x k`` product per point, then ``k x k`` ones), fewer and smaller batched
    products than going through ``W L_s``."""
    J = linalg.matmul(W.transpose(-1, -2), W)  # (..., k, k), or (k, k) for a shared W
    Wy = _whitened_rhs(W, y)
    T = linalg.matmul(Ls.transpose(-1, -2), J)
    S = linalg.symmetrize(linalg.matmul(T, Ls))
    return T, S, Wy


class EDHFlow(ParticleFlow):
    """Exact Daum-Huang flow: one linearisation per trial at the migrating mean (Daum & Huang
    2010; the PF-PF(EDH) proposal of Li & Coates 2017).

    Attributes:
        promote_low_precision: in float32 (or half) runs, compute the drift's ``k x k`` algebra in
            float64 (default True). Its offset ``b`` cancels terms ``~lam |S|`` times larger than
            itself, and ``S = L^T H^T R^-1 H L`` reaches ~5e11 on acoustic tracking with
            sigma_w = 0.001: in float32 that drift is wrong by metres and PF-PF(EDH/LEDH) lose every
            track (``experiments/benchmarks/results/results_float32.md``). Everything else stays in the
            run's precision.
    """

    points = "global"
    promote_low_precision = True
    kernel = "daum_huang"  # declared per class (torchflow.flows.select)

    def coefficients_at(self, lin: Linearisation, prior: FlowPrior, lam, eps):
        W, y = lin.W, lin.y
        dt = prior.cols.dtype
        if self.promote_low_precision and dt in (torch.float32, torch.float16, torch.bfloat16):
            up = lambda t: t.to(torch.float64)
            # P_cols is not reused: it was rounded independently of L in low precision
            co = daum_huang_coefficients(
                up(W),
                up(y),
                up(prior.cols),
                up(prior.mean),
                up(lam),
                up(eps),
                L_support=up(prior.cols_support),
                support=prior.support,
                W_diag=None if lin.diag is None else up(lin.diag),
            )
            if co.A is None:  # operator form: apply (and form) in float64, hand back the run's dtype
                return FlowCoefficients(
                    None,
                    co.b.to(dt),
                    co.log_det.to(dt),
                    support=co.support,
                    apply_A=lambda V: co.apply_A(V.to(torch.float64)).to(dt),
                    form_A=lambda: co.matrix().to(dt),
                )
            return FlowCoefficients(co.A.to(dt), co.b.to(dt), co.log_det.to(dt), support=co.support)
        return daum_huang_coefficients(
            W,
            y,
            prior.cols,
            prior.mean,
            lam,
            eps,
            L_support=prior.cols_support,
            support=prior.support,
            P_cols=prior.cov_cols,
            W_diag=lin.diag,
            # the kept spectrum: a fast path to round-off, off with a gradient or tuning.fused_flows=0
            fixed=prior.fixed if not torch.is_grad_enabled() and tuning.get().fused_flows else None,
        )


class LEDHFlow(EDHFlow):
    """Localised exact Daum-Huang flow: each particle linearises at its own auxiliary point
    (Ding & Coates 2012; the PF-PF(LEDH) proposal of Li & Coates 2017)."""

    points = "particle"
    kernel = "daum_huang"
