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

import torch

from .. import linalg
from .base import FlowCoefficients, FlowPrior, ParticleFlow, _bcast_obs


def _whiten(model, aux: torch.Tensor, z: torch.Tensor):
    """Whitened linearisation at ``aux (..., d)``: ``W = L_R^{-1} H (..., m, d)`` and the whitened
    pseudo-measurement ``y = L_R^{-1} (z - e) (..., m)`` with ``e = h(aux) - H aux``."""
    # a linear measurement has one H for every point: keep it unbatched (m, d)
    H = model.measurement_matrix() if model.linear_measurement else model.measurement_jacobian(aux)
    e = model.measure(aux) - linalg.matvec(H, aux)
    LR = model.measurement_scale_tril(aux)
    resid = _bcast_obs(z, aux) - e
    if LR.dim() == 2 and bool((LR == torch.diag(LR.diagonal())).all()):
        dr = LR.diagonal()
        return H / dr.unsqueeze(-1), resid / dr
    W = torch.linalg.solve_triangular(LR, H, upper=False)
    y = torch.linalg.solve_triangular(LR, resid.unsqueeze(-1), upper=False).squeeze(-1)
    return W, y


def daum_huang_coefficients(W, y, L, eta_bar0, lam, eps) -> FlowCoefficients:
    """EDH/LEDH drift from the whitened linearisation.

    Args:
        W: ``(..., m, d)`` whitened Jacobian (or ``(m, d)`` shared); y: ``(..., m)`` whitened
            pseudo-measurement.
        L: ``(..., d, d)`` Cholesky factor of the prior covariance P.
        eta_bar0: ``(..., d)`` prior mean.
        lam, eps: pseudo-time after the step, step size.

    A is formed explicitly (one Cholesky solve with d right-hand sides) and then applied to
    stacked vectors: on CPU the number of batched small products, not their size, sets the cost.
    """
    d = L.shape[-1]
    eye = torch.eye(d, dtype=L.dtype, device=L.device)
    WL = W @ L  # (..., m, d)
    WLt = WL.transpose(-1, -2)
    S = WLt @ WL  # L^T J L, (..., d, d)
    K = linalg.safe_cholesky(eye + lam * S)
    K2 = linalg.safe_cholesky(eye + (lam - 0.5 * eps) * S)
    log_det = linalg.chol_logdet(K2) - linalg.chol_logdet(K)
    A = -0.5 * (L @ linalg.chol_solve(K, WLt @ W))  # -1/2 L (I + lam S)^{-1} L^T J
    Pg = linalg.matvec(L, linalg.matvec(WLt, y))  # P H^T R^{-1} (z - e) = L (W L)^T y
    if A.dim() >= 4 and A.shape[-3] > 1:  # per-point A: one product for both vectors
        AV = A @ torch.stack([Pg, eta_bar0.expand_as(Pg)], -1)
        APg, Aeta0 = AV[..., 0], AV[..., 1]
    else:
        APg, Aeta0 = linalg.matvec(A, Pg), linalg.matvec(A, eta_bar0)
    u = Pg + lam * APg + Aeta0
    b = u + 2 * lam * linalg.matvec(A, u)
    return FlowCoefficients(A, b, log_det)


class EDHFlow(ParticleFlow):
    """Exact Daum-Huang flow: one linearisation per trial at the migrating mean (Daum & Huang
    2010; the PF-PF(EDH) proposal of Li & Coates 2017)."""

    local = False

    def coefficients(self, model, z, aux, prior: FlowPrior, lam, eps):
        W, y = _whiten(model, aux, z)
        return daum_huang_coefficients(W, y, prior.scale_tril, prior.mean, lam, eps)


class LEDHFlow(EDHFlow):
    """Localised exact Daum-Huang flow: each particle linearises at its own auxiliary point
    (Ding & Coates 2012; the PF-PF(LEDH) proposal of Li & Coates 2017)."""

    local = True
