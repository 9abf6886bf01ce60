"""Gaussian particle flow importance sampling (GPFIS; Bunch & Godsill 2016).

Each particle starts from the Gaussian transition, ``x_0 ~ N(m_0, P_0)`` with ``m_0 = f(x_{k-1})``
and ``P_0 = V`` (the transition covariance), and moves over the pseudo-time grid. On a step
``[lambda_0, lambda_1]`` the measurement is linearised at the particle's *current* position
(``H``, ``e = h(x) - H x``), which defines the Gaussian homotopy

    P_lam^{-1} = P_0^{-1} + lam H^T R^{-1} H,   m_lam = P_lam (P_0^{-1} m_0 + lam H^T R^{-1} (z - e)),

and the particle takes its transport step (deterministic, gamma = 0)

    x <- m_lam1 + T (x - m_lam0),   T P_lam0 T^T = P_lam1.

Because the linearisation moves with the particle, the map's Jacobian involves dH/dx (h's second
derivatives): by default (``jacobian="analytic"``) the step's derivative is written out
(:func:`_cholesky_step_and_jacobian`): the tangents enter only through ``dG`` and ``dr``, taken from
the model's :meth:`~torchflow.models.GaussianStateSpaceModel.measurement_hessian_blocks` in one product, and
the rest is ``k x k`` algebra per tangent; ``jacobian="autodiff"`` traces the whole step by forward
mode (``torch.func.jvp`` batched over the tangent directions with ``torch.func.vmap``). No loop
over trials or particles either way; ``log|det|`` is accumulated. The
steps telescope into one importance weight, so GPFIS is a proposal like any other here:
``log q(x) = log p(x_0 | x_{k-1}) - sum_j log|det dx_j/dx_{j-1}|``, weighted by the particle filter
base as ``p(x | x_{k-1}) p(z | x) / q(x)``; its evidence estimate is unbiased.

Computed in whitened prior coordinates with the model's measurement support (k measured
coordinates of d): with ``P_0 = root root^T`` (:meth:`~torchflow.flows.FlowPrior.reduced`), only
the first k whitened coordinates move, and the Jacobian needs only k tangent directions.

The root ``T`` is a choice (the papers do not fix it; every root gives the exact transport of the
linearised Gaussian and an exact weight): ``root="cholesky"`` (default) is
``T = root K_1^{-T} K_0^T root^{-1}`` with ``K K^T = I + lam G``, ``G = root^T H^T R^{-1} H root``:
triangular algebra whose derivative exists everywhere. ``root="symmetric"`` is the principal
square root ``(P_lam1 P_lam0^{-1})^{1/2}`` of Bunch & Godsill through an eigendecomposition of G,
whose derivative is undefined when G has repeated eigenvalues (e.g. isotropic P_0 and H).
The stochastic variant (gamma > 0) is not implemented.

On the CPU with Numba, with no gradient recorded (``tuning.fused_flows``), the analytic path runs as
one compiled kernel (:class:`~torchflow.flows.kernels.steps.GPFISSteps`): the same formulas, 64 particles in
SIMD lanes, each tangent's ``dG`` applied as a rank-``2b`` update instead of a ``k x k`` matrix, the
``log|det|`` from a QR of the step Jacobian instead of an LU; it agrees with this module's torch path
to round-off.
"""

from __future__ import annotations

from typing import Optional

import torch
from torch.func import jvp, vmap

from torchflow.core import linalg
from torchflow.core.checks import check_choice
from torchflow.flows import select
from torchflow.flows.base import FlowPrior
from torchflow.flows.kernels import steps as kernel_steps
from torchflow.flows.measurement import GaussianMeasurement
from torchflow.flows.schedules import LambdaSchedule, resolve_schedule

ROOTS = ("cholesky", "symmetric")
JACOBIANS = ("analytic", "autodiff")


def _tri(L, b, upper=False):
    return linalg.solve_triangular(L, b, upper=upper)


def gpfis_flow(
    measurement: GaussianMeasurement,
    x: torch.Tensor,
    prior: FlowPrior,
    schedule: Optional[LambdaSchedule] = None,
    root: str = "cholesky",
    jacobian: str = "analytic",
):
    """Move ``x (B, N, d)`` with the GPFIS transport from ``prior`` (``m_0 (B, N, d)``, factor
    broadcastable to ``(B, N, d, d)``); returns ``(x_1 (B, N, d), log|det dx_1/dx_0| (B, N))``.

    ``jacobian``: how each step's Jacobian is formed. ``"analytic"`` (default; the Cholesky root):
    the step's derivative in closed form, the measurement's ``dW/dx`` from the declared second
    derivatives (:meth:`GaussianMeasurement.derivative`; forward mode through the whitened
    linearisation alone when there are none), every tangent a column of a few batched products and
    solves (:func:`_cholesky_step_and_jacobian`); ``"autodiff"``: forward mode through the whole step
    (the reference; the symmetric root always uses it). Both are exact; they differ by round-off.
    """
    check_choice("root", root, ROOTS)
    check_choice("jacobian", jacobian, JACOBIANS)
    analytic = jacobian == "analytic" and root == "cholesky"
    schedule = resolve_schedule(schedule)
    eps_all, lam_all = schedule.steps(dtype=x.dtype, device=x.device)
    measurement.prepare(x)  # constants of R once, outside the transforms
    prior = prior.reduced(measurement.support)
    sup = prior.support  # (k,) or None
    C, cols = prior.cols_support, prior.cols  # (..., k, k) lower, (..., d, k)
    k = C.shape[-1]
    if analytic and select.gpfis_kernel(measurement, x, k):
        return _fused_flow(measurement, x, prior, sup, k, eps_all, lam_all)
    eye = torch.eye(k, dtype=x.dtype, device=x.device)
    m0s = prior.mean if sup is None else prior.mean[..., sup]
    u0 = _tri(C, m0s.unsqueeze(-1)).squeeze(-1)  # whitened prior mean, (B, N, k)
    log_det_C = torch.log(C.diagonal(dim1=-2, dim2=-1).abs()).sum(-1)
    tangents = eye.reshape(k, *([1] * (x.dim() - 1)), k).expand(k, *x.shape[:-1], k)
    log_det = torch.zeros(x.shape[:-1], dtype=x.dtype, device=x.device)
    C_inv = _tri(C, eye.expand_as(C)) if analytic else None  # dx_s -> du: (..., k, k)
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
            g, U = linalg.eigh(G)  # threaded over a large CPU batch, the same numbers
            g = g.clamp_min(0)
            Ut = U.transpose(-1, -2)
            m_lam0 = linalg.matvec(U, linalg.matvec(Ut, u0 + lam0 * r) / (1 + lam0 * g))
            m_lam1 = linalg.matvec(U, linalg.matvec(Ut, u0 + lam1 * r) / (1 + lam1 * g))
            return m_lam1 + linalg.matvec(
                U, linalg.matvec(Ut, u - m_lam0) * torch.sqrt((1 + lam0 * g) / (1 + lam1 * g))
            )

        xs = x if sup is None else x[..., sup]
        if analytic:
            u_new, jac = _cholesky_step_and_jacobian(
                measurement, x_now, xs, sup, C, C_inv, u0, lam0, lam1, eye, tangents
            )
        else:
            u_new, jac = vmap(lambda t: jvp(step, (xs,), (t,)), out_dims=(None, -1))(tangents)
        # x'_s = C u'(x_s): det(dx'/dx) = det(C) det(du'/dx_s) (the other coordinates follow
        # triangularly with unit diagonal)
        log_det = log_det + torch.linalg.slogdet(jac)[1] + log_det_C
        u_old = _tri(C, xs.unsqueeze(-1)).squeeze(-1)
        x = x + linalg.matvec(cols, u_new - u_old)
    return x, log_det


def _fused_flow(measurement, x, prior, sup, k, eps_all, lam_all):
    """:func:`gpfis_flow` by the fused CPU kernel: every step in one call when the kernel linearises
    the model itself (acoustic), else one call per step with the whitened linearisation and the
    second-derivative blocks from torch."""
    inside = select.measured_inside(measurement, sup, k)
    steps = kernel_steps.GPFISSteps(
        prior.cols_support,
        prior.cols,
        prior.mean,
        sup,
        lam_all.to(torch.float64),
        eps_all.to(torch.float64),
        inside,
        measurement.inv_sigma,
        measurement.z_scaled if inside is not None else None,
    )
    log_det = torch.zeros(x.shape[:-1], dtype=torch.float64)
    x = x.contiguous()
    if inside is not None:
        x = steps(0, len(eps_all), x, log_det)
    else:
        for j in range(len(eps_all)):
            lin = measurement.at(x, sup)
            x = steps(j, j + 1, x, log_det, lin.W, lin.y, measurement.derivative(x, sup))
    return x, log_det.to(x.dtype)


def _cholesky_step_and_jacobian(measurement, x_now, xs, sup, C, C_inv, u0, lam0, lam1, eye, tangents):
    """One step of the Cholesky-root transport and its Jacobian ``du'/dx_s (..., k, k)``, the
    derivative written out instead of traced (the same map as the ``"autodiff"`` path's ``step``).

    In whitened prior coordinates ``u = C^{-1} x_s`` with ``A = W C``, ``G = A^T A``, ``r = A^T y``,
    ``M_i = I + lam_i G = K_i K_i^T`` and ``m_i = M_i^{-1} (u0 + lam_i r)``, the step is
    ``u' = m_1 + T (u - m_0)`` with ``T = K_1^{-T} K_0^T``. Along coordinate t of ``x_s``
    (``dW_t``, ``dy_t``: the measurement's derivatives) only ``dG_t = C^T F_t C`` with
    ``F_t = dW_t^T W + W^T dW_t`` and ``dr_t = C^T (dW_t^T y + W^T dy_t)`` enter:

    * ``dm_i = lam_i M_i^{-1} (dr_t - dG_t m_i)``;
    * ``dK_i = K_i Psi_i`` with ``Psi_i`` the lower triangle of ``X_i = K_i^{-1} dM_i K_i^{-T}
      = lam_i N_i F_t N_i^T`` (``N_i = K_i^{-1} C^T``) with half its diagonal, so
      ``dT v = K_1^{-T} (Psi_0 - Psi_1)^T w`` with ``w = K_0^T (u - m_0)``; ``(Psi^T w)_a`` is row a
      of X times w's entries on and after a (halved at a), i.e. ``lam_i sum_p N_i[a, p] (F_t V_i^T)[p, a]``
      with ``V_i = U_w N_i`` (``U_w``: w on and above the diagonal, halved on it), so no ``k x k``
      matrix per tangent is solved for.

    Then ``J = dm_1 + K_1^{-T} (K_0^T (C^{-1} - dm_0) + phi_0 - phi_1)``, ``phi_i = Psi_i^T w``, every
    tangent a column. The measurement's second derivatives enter once, through one product
    ``[W y]^T dW`` (``(k + 1) x m x k^2`` per point); the rest is ``k x k`` algebra per tangent.
    """
    D = measurement.derivative(
        x_now, sup
    )  # (..., m, n_b, b, b): dW_t[a, (c', j)] = [c == c'] D[a, c, i, j], t = (c, i)
    if D is not None:  # the model's second derivatives, R constant: dy_t = dW_t x_s
        lin = measurement.at(x_now, sup)
        W, y, Wdy = lin.W, lin.y, None
    else:  # forward mode through the whitened linearisation, one dense block

        def lin_at(v):
            lin = measurement.at(v if sup is None else x_now.index_copy(-1, sup, v), sup)
            return lin.W, lin.y

        (W, y), (dW, dy) = vmap(lambda t: jvp(lin_at, (xs,), (t,)), out_dims=((None, None), (-3, -2)))(tangents)
        D = dW.movedim(-3, -2).unsqueeze(-3)
        Wdy = linalg.matmul(W.transpose(-1, -2), dy.transpose(-1, -2)).transpose(-1, -2)  # (..., k_t, k): W^T dy_t
    m, nb, bs = D.shape[-4], D.shape[-3], D.shape[-1]
    A = W @ C  # (..., m, k)
    k = A.shape[-1]
    G = A.transpose(-1, -2) @ A
    r = linalg.matvec(A.transpose(-1, -2), y)
    u = _tri(C, xs.unsqueeze(-1)).squeeze(-1)
    K0 = torch.linalg.cholesky_ex(eye + lam0 * G)[0]
    K1 = torch.linalg.cholesky_ex(eye + lam1 * G)[0]
    # the primal exactly as the autodiff path's step (the same ops: the same bits)
    w0 = _tri(K0, (u0 + lam0 * r).unsqueeze(-1))
    m0 = _tri(K0.transpose(-1, -2), w0, upper=True)
    v = K0.transpose(-1, -2) @ (u.unsqueeze(-1) - m0)  # w = K_0^T (u - m_0), (..., k, 1)
    b1 = _tri(K1, (u0 + lam1 * r).unsqueeze(-1))
    u_new = _tri(K1.transpose(-1, -2), b1 + v, upper=True).squeeze(-1)
    m1 = _tri(K1.transpose(-1, -2), b1, upper=True)
    # tangents: one pass over the second derivatives, Zb = [W y]^T dW's blocks, (..., k + 1, n_b b b)
    batch = torch.broadcast_shapes(D.shape[:-4], W.shape[:-2], y.shape[:-1])
    Wy = torch.cat([W.expand(*batch, m, k), y.expand(*batch, m).unsqueeze(-1)], -1)
    Zb = linalg.matmul(Wy.transpose(-1, -2), D.expand(*batch, *D.shape[-4:]).reshape(*batch, m, nb * bs * bs))
    # E_t = W^T dW_t (..., k_t, k, k): E[(c, i), i', (c, j)] = Zb[i', (c, i, j)], zero off the blocks
    E = Zb.new_zeros(*batch, nb, bs, k, nb, bs)
    E.diagonal(dim1=-5, dim2=-2).copy_(
        Zb[..., :k, :].view(*batch, k, nb, bs, bs).permute(*range(len(batch)), -2, -4, -1, -3)
    )  # (..., i, i', j, c)
    E = E.view(*batch, k, k, k)
    F = E + E.transpose(-1, -2)  # dW_t^T W + W^T dW_t (..., k_t, k, k)
    F_rows = F.view(*batch, k * k, k)
    g = linalg.block_diagonal(Zb[..., k, :].view(*batch, nb, bs, bs))  # dW_t^T y as rows, (..., k_t, k)
    if Wdy is None:  # W^T dy_t = W^T dW_t x_s = E_t x_s
        Wdy = linalg.matmul(E.view(*batch, k * k, k), xs.expand(*batch, k).unsqueeze(-1)).view(*batch, k, k)
    drx = g + Wdy  # C^{-T} dr_t as rows, (..., k_t, k)
    Ct = C.transpose(-1, -2).expand(*batch, k, k)
    wv = v.squeeze(-1)
    Uw = torch.triu(wv.unsqueeze(-2).expand(*wv.shape, k), 1) + torch.diag_embed(0.5 * wv)  # (..., k, k)
    N0, N1 = _tri(K0, Ct), _tri(K1, Ct)  # N_i = K_i^{-1} C^T
    # (Psi_i^T w)_a / lam_i = sum_{p,q} N_i[a, p] F_t[p, q] V_i[a, q] with V_i = U_w N_i: both factors in one product
    VV = torch.cat([linalg.matmul(Uw, N0), linalg.matmul(Uw, N1)], -2)  # (..., 2k, k)
    P = linalg.matmul(F_rows, VV.transpose(-1, -2)).view(*batch, k, k, 2, k)  # [t, p, i, a]
    Cm = torch.cat([m0, m1], -1)  # (..., k, 2)
    Fm = linalg.matmul(F_rows, linalg.matmul(C.expand(*batch, k, k), Cm)).view(*batch, k, k, 2)  # F_t C m_i

    def terms(K, Nm, i, lam):
        """``(dm_i, phi_i)``, each ``(..., k, k_t)``: the tangents as columns."""
        rhs = drx - Fm[..., i]  # C^{-T} (dr_t - dG_t m_i) as rows
        dm = lam * _tri(K.transpose(-1, -2), linalg.matmul(Nm, rhs.transpose(-1, -2)), upper=True)  # M^{-1} C^T q
        psi = (P[..., i, :] * Nm.transpose(-1, -2).unsqueeze(-3)).sum(-2)  # (..., k_t, k)
        return dm, lam * psi.transpose(-1, -2)

    dm0, phi0 = terms(K0, N0, 0, lam0)
    dm1, phi1 = terms(K1, N1, 1, lam1)
    jac = dm1 + _tri(K1.transpose(-1, -2), K0.transpose(-1, -2) @ (C_inv - dm0) + phi0 - phi1, upper=True)
    return u_new, jac


__all__ = ["gpfis_flow", "ROOTS", "JACOBIANS"]
