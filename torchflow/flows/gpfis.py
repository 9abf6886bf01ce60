"""Gaussian particle flow importance sampling (GPFIS; Bunch & Godsill 2016; MODELS.md §6, §13).

Each particle starts from the Gaussian transition, ``x_0 ~ N(m_0, P_0)`` with ``m_0 = f(x_{k-1})``
and ``P_0 = V`` (the transition covariance), and moves over the pseudo-time grid. On a step
``[lambda_0, lambda_1]`` the measurement is linearised at the particle's *current* position
(``H``, ``e = h(x) - H x``), which defines the Gaussian homotopy

    P_lam^{-1} = P_0^{-1} + lam H^T R^{-1} H,   m_lam = P_lam (P_0^{-1} m_0 + lam H^T R^{-1} (z - e)),

and the particle takes its transport step (deterministic, gamma = 0)

    x <- m_lam1 + T (x - m_lam0),   T P_lam0 T^T = P_lam1.

Because the linearisation moves with the particle, the map's Jacobian involves dH/dx: it is
computed by forward-mode autodiff (``torch.func.jvp``, batched over the tangent directions with
``torch.func.vmap``; no loop over trials or particles) and its ``log|det|`` accumulated. The
steps telescope into one importance weight, so GPFIS is a proposal like any other here:
``log q(x) = log p(x_0 | x_{k-1}) - sum_j log|det dx_j/dx_{j-1}|``, weighted by the particle filter
base as ``p(x | x_{k-1}) p(z | x) / q(x)``; its evidence estimate is unbiased.

Computed in whitened prior coordinates with the model's measurement support (k measured
coordinates of d): with ``P_0 = root root^T`` (:meth:`~torchflow.flows.FlowPrior.reduced`), only
the first k whitened coordinates move, and the Jacobian needs only k tangent directions.

The root ``T`` is a choice (UNCONF in the papers; every root gives the exact transport of the
linearised Gaussian and an exact weight): ``root="cholesky"`` (default) is
``T = root K_1^{-T} K_0^T root^{-1}`` with ``K K^T = I + lam G``, ``G = root^T H^T R^{-1} H root``:
triangular algebra whose derivative exists everywhere. ``root="symmetric"`` is the principal
square root ``(P_lam1 P_lam0^{-1})^{1/2}`` of Bunch & Godsill through an eigendecomposition of G,
whose derivative is undefined when G has repeated eigenvalues (e.g. isotropic P_0 and H).
The stochastic variant (gamma > 0) is not implemented.
"""
from __future__ import annotations

from typing import Optional

import torch
from torch.func import jvp, vmap

from .. import linalg
from .._checks import check_choice
from ..schedules import LambdaSchedule, resolve_schedule
from .base import FlowPrior
from .measurement import GaussianMeasurement

ROOTS = ("cholesky", "symmetric")


def _tri(L, b, upper=False):
    return linalg.solve_triangular(L, b, upper=upper)


def gpfis_flow(measurement: GaussianMeasurement, x: torch.Tensor, prior: FlowPrior,
               schedule: Optional[LambdaSchedule] = None, root: str = "cholesky"):
    """Move ``x (B, N, d)`` with the GPFIS transport from ``prior`` (``m_0 (B, N, d)``, factor
    broadcastable to ``(B, N, d, d)``); returns ``(x_1 (B, N, d), log|det dx_1/dx_0| (B, N))``."""
    check_choice("root", root, ROOTS)
    schedule = resolve_schedule(schedule)
    eps_all, lam_all = schedule.steps(dtype=x.dtype, device=x.device)
    prior = prior.reduced(measurement.support)
    sup = prior.support  # (k,) or None
    C, cols = prior.cols_support, prior.cols  # (..., k, k) lower, (..., d, k)
    k = C.shape[-1]
    eye = torch.eye(k, dtype=x.dtype, device=x.device)
    m0s = prior.mean if sup is None else prior.mean[..., sup]
    u0 = _tri(C, m0s.unsqueeze(-1)).squeeze(-1)  # whitened prior mean, (B, N, k)
    log_det_C = torch.log(C.diagonal(dim1=-2, dim2=-1).abs()).sum(-1)
    tangents = eye.reshape(k, *([1] * (x.dim() - 1)), k).expand(k, *x.shape[:-1], k)
    log_det = torch.zeros(x.shape[:-1], dtype=x.dtype, device=x.device)
    for j in range(len(eps_all)):
        lam1 = lam_all[j]
        lam0 = lam1 - eps_all[j]
        x_now = x

        def step(xs):
            """The whitened support coordinates after the step, as a function of ``xs (B, N, k)``."""
            xf = xs if sup is None else x_now.index_copy(-1, sup, xs)
            lin = measurement.at(xf, sup)
            A = lin.W @ C  # whitened Jacobian in prior coordinates, (..., m, k)
            G = A.transpose(-1, -2) @ A
            r = linalg.matvec(A.transpose(-1, -2), lin.y)
            u = _tri(C, xs.unsqueeze(-1)).squeeze(-1)
            if root == "cholesky":
                K0 = torch.linalg.cholesky_ex(eye + lam0 * G)[0]
                K1 = torch.linalg.cholesky_ex(eye + lam1 * G)[0]
                # (I + lam G)^{-1} b = K^{-T} K^{-1} b, and T v = K_1^{-T} K_0^T v: triangular solves only
                w0 = _tri(K0, (u0 + lam0 * r).unsqueeze(-1))  # K_0^{-1} b_0
                m_lam0 = _tri(K0.transpose(-1, -2), w0, upper=True)
                w = _tri(K1, (u0 + lam1 * r).unsqueeze(-1)) + K0.transpose(-1, -2) @ (u.unsqueeze(-1) - m_lam0)
                return _tri(K1.transpose(-1, -2), w, upper=True).squeeze(-1)
            g, U = torch.linalg.eigh(G)
            g = g.clamp_min(0)
            Ut = U.transpose(-1, -2)
            m_lam0 = linalg.matvec(U, linalg.matvec(Ut, u0 + lam0 * r) / (1 + lam0 * g))
            m_lam1 = linalg.matvec(U, linalg.matvec(Ut, u0 + lam1 * r) / (1 + lam1 * g))
            return m_lam1 + linalg.matvec(U, linalg.matvec(Ut, u - m_lam0) * torch.sqrt((1 + lam0 * g) / (1 + lam1 * g)))

        xs = x if sup is None else x[..., sup]
        u_new, jac = vmap(lambda t: jvp(step, (xs,), (t,)), out_dims=(None, -1))(tangents)
        # x'_s = C u'(x_s): det(dx'/dx) = det(C) det(du'/dx_s) (the other coordinates follow
        # triangularly with unit diagonal)
        log_det = log_det + torch.linalg.slogdet(jac)[1] + log_det_C
        u_old = _tri(C, xs.unsqueeze(-1)).squeeze(-1)
        x = x + linalg.matvec(cols, u_new - u_old)
    return x, log_det


__all__ = ["gpfis_flow", "ROOTS"]
