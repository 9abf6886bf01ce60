"""The CPU kernel of :mod:`torchflow.flows.kernels.steps`, compiled by Numba (imported only when it is used:
Numba is an optional dependency, the ``kernels`` extra).

The same pseudo-step as the Triton kernel (:func:`torchflow.flows.kernels.gpu.kernel_rows`):
``LANES`` particles side by side, the particle the last axis of every scratch array, so that each
line of the per-particle ``k x k`` algebra is a loop over lanes that LLVM vectorises (8 float64 per
AVX-512 instruction); blocks of ``BLOCK`` particles run in parallel (``prange``), each allocating its
scratch once. Particles do not interact, so the numbers do not depend on the thread count or the
blocks, and none are reassociated across lanes: a run gives the same bits with 1 or 2 threads.

Why lanes of 64 and not 8 (one register): with 8 the lane loops are unrolled before the loop
vectoriser sees them and Numba's pipeline does not SLP-vectorise them, so the code stayed scalar
(2,800 scalar against 16 vector arithmetic instructions in its assembly); at 64 the loop vectoriser
runs (with run-time alias checks between the scratch arrays). Timings:
``python -m experiments.benchmarks.bench_ops``.

One pass over the rows of W accumulates ``W^T y``, ``S = V^T V`` (lower triangle) and
``M = V^T W`` (``V_i = L_s^T W_i``); the four products ``t(u) = sum_i V_i (W_i . u)`` of the
Triton kernel are then ``M u``, so no row is computed or stored twice.

:func:`gromov_step` is the same treatment of the Gromov flow's Euler-Maruyama step at per-particle
points, with PF-PF(Gromov)'s tracked Gaussian law (a ``d x d`` covariance per particle).
"""

import math

import numba
import numpy as np

#: particles computed side by side (see the module docstring)
LANES = 64
#: particles per block of the parallel loop (a multiple of LANES; each block allocates its scratch once)
BLOCK = 256


@numba.njit(cache=True, inline="always")
def _row(i, lin, Wr, yr, aux_s, sens, psi, d0, w, s1, k, P):
    """Row ``i`` of W into ``w (k, P)`` and entry ``i`` of y into ``s1 (P,)`` for each lane: read
    (``lin`` 0) or computed at the points ``aux_s`` (``lin`` 1, the acoustic form)."""
    if lin == 1:
        sx, sy = sens[i, 0], sens[i, 1]
        for q in range(P):
            s1[q] = yr[i, q]
        for c in range(k // 2):
            for q in range(P):
                dx = aux_s[2 * c, q] - sx
                dy = aux_s[2 * c + 1, q] - sy
                r = math.sqrt(dx * dx + dy * dy)
                inv = 1.0 / (r + d0)
                g = -psi * inv * inv / max(r, 2.2250738585072014e-308)
                w[2 * c, q] = g * dx
                w[2 * c + 1, q] = g * dy
                s1[q] += g * dx * aux_s[2 * c, q] + g * dy * aux_s[2 * c + 1, q] - psi * inv
    else:
        for a in range(k):
            for q in range(P):
                w[a, q] = Wr[i, a, q]
        for q in range(P):
            s1[q] = yr[i, q]


@numba.njit(cache=True, inline="always")
def _accumulate(w, s1, LsP, Wy, v, S, M, k, P):
    """``Wy += w s1``, ``v = L_s^T w``, ``S += v v^T`` (lower triangle), ``M += v w^T``, per lane."""
    for a in range(k):
        for q in range(P):
            Wy[a, q] += w[a, q] * s1[q]
        for q in range(P):
            v[a, q] = 0.0
        for e in range(a, k):
            for q in range(P):
                v[a, q] += LsP[e, a, q] * w[e, q]
    for a in range(k):
        for c in range(a + 1):
            for q in range(P):
                S[a, c, q] += v[a, q] * v[c, q]
        for c in range(k):
            for q in range(P):
                M[a, c, q] += v[a, q] * w[c, q]


@numba.njit(cache=True, inline="always")
def _grid(eta, sup, sens, y, lin, lams, epss, const, j):
    """Sizes, the step's constants and the blocks of lanes of a kernel call (see :func:`dh_step`)."""
    B, N, d = eta.shape
    k = sup.shape[0]
    m = sens.shape[0] if lin == 1 else y.shape[2]
    P = LANES
    total = B * N
    groups = (total + P - 1) // P
    per = BLOCK // P
    return B, N, d, k, m, lams[j], epss[j], const[0], const[1], P, total, per, groups, (groups + per - 1) // per


@numba.njit(cache=True, inline="always")
def _gather_rows(q, b, n, lin, W, y, Wr, yr, m, k):
    """Lane ``q`` of ``yr (m, P)`` and (``lin`` 0) ``Wr (m, k, P)`` from particle ``(b, n)``."""
    by, ny = (b if y.shape[0] > 1 else 0), (n if y.shape[1] > 1 else 0)
    for i in range(m):
        yr[i, q] = y[by, ny, i]
    if lin == 0:  # the rows of W, read
        bw, nw = (b if W.shape[0] > 1 else 0), (n if W.shape[1] > 1 else 0)
        for i in range(m):
            for a in range(k):
                Wr[i, a, q] = W[bw, nw, i, a]


@numba.njit(cache=True, inline="always")
def _zero(Wy, S, M, k, P):
    """The accumulators of the pass over the rows set to 0 (S's lower triangle)."""
    for a in range(k):
        for q in range(P):
            Wy[a, q] = 0.0
        for c in range(k):
            for q in range(P):
                M[a, c, q] = 0.0
        for c in range(a + 1):
            for q in range(P):
                S[a, c, q] = 0.0


@numba.njit(cache=True, parallel=True, error_model="numpy")
def dh_step(W, y, L, Ls, Pc, mean, sup, eta, aux, eta_out, aux_out, log_det, lams, epss, j, lin, sens, const):
    """One Euler pseudo-step of EDH/LEDH at per-particle points for every particle of ``eta
    (B, N, d)`` (float64 arrays; ``L, Pc (B|1, N|1, d, k)``, ``Ls (B|1, N|1, k, k)``,
    ``mean (B|1, N|1, d)``, ``W (B|1, N|1, m, k)`` and ``y (B|1, N|1, m)``). Writes ``eta_out``,
    ``aux_out`` and adds ``log|det|`` of the step's map to ``log_det (B, N)``; ``lams``, ``epss``:
    the schedule, ``j`` the step; ``lin`` 1: the rows of W and y are computed at the points in the
    acoustic form of :class:`~torchflow.flows.kernels.steps.FusedMeasurement` (``y`` holds ``z / sigma``
    ``(B, 1, m)``, ``const = [Psi / sigma, d0]``, ``sens (m, 2)``; ``W`` not read). The algebra of
    :func:`torchflow.flows.kernels.gpu.kernel_rows`: three solves with ``Q = I + lam S``."""
    B, N, d, k, m, lam, eps, psi, d0, P, total, per, groups, nblocks = _grid(
        eta, sup, sens, y, lin, lams, epss, const, j
    )
    for blk in numba.prange(nblocks):
        bb = np.empty(P, np.int64)
        nn = np.empty(P, np.int64)
        Wr = np.empty((m if lin == 0 else 0, k, P))
        yr = np.empty((m, P))
        M = np.empty((k, k, P))
        w = np.empty((k, P))
        LsP = np.empty((k, k, P))
        PcP = np.empty((d, k, P))
        LP = np.empty((d, k, P))
        S = np.empty((k, k, P))
        K1 = np.empty((k, k, P))
        K2 = np.empty((k, k, P))
        vec = np.empty((14, k, P))
        sc = np.empty((4, P))
        for grp in range(blk * per, min(groups, (blk + 1) * per)):
            for q in range(P):
                p = min(grp * P + q, total - 1)
                bb[q], nn[q] = p // N, p % N
            aux_s, eta_s, Wy, Pg_s, x1_s = vec[0], vec[1], vec[2], vec[3], vec[4]
            v, t1, tp, te, ta = vec[5], vec[6], vec[7], vec[8], vec[9]
            q1, q2, tmp, dg = vec[10], vec[11], vec[12], vec[13]
            ld, s1, s2, s3 = sc[0], sc[1], sc[2], sc[3]
            for q in range(P):  # gather the lanes' inputs
                b, n = bb[q], nn[q]
                bl, nl = (b if L.shape[0] > 1 else 0), (n if L.shape[1] > 1 else 0)
                bs, ns = (b if Ls.shape[0] > 1 else 0), (n if Ls.shape[1] > 1 else 0)
                bp, np_ = (b if Pc.shape[0] > 1 else 0), (n if Pc.shape[1] > 1 else 0)
                bm, nm = (b if mean.shape[0] > 1 else 0), (n if mean.shape[1] > 1 else 0)
                for a in range(k):
                    aux_s[a, q] = aux[b, n, sup[a]]
                    eta_s[a, q] = eta[b, n, sup[a]]
                    dg[a, q] = mean[bm, nm, sup[a]]
                    for c in range(k):
                        LsP[a, c, q] = Ls[bs, ns, a, c]
                for r in range(d):
                    for c in range(k):
                        PcP[r, c, q] = Pc[bp, np_, r, c]
                        LP[r, c, q] = L[bl, nl, r, c]
                _gather_rows(q, b, n, lin, W, y, Wr, yr, m, k)
            _zero(Wy, S, M, k, P)
            # one pass over the rows i of W: W^T y, S = V^T V (lower triangle) and M = V^T W, V_i = L_s^T W_i
            for i in range(m):
                _row(i, lin, Wr, yr, aux_s, sens, psi, d0, w, s1, k, P)
                _accumulate(w, s1, LsP, Wy, v, S, M, k, P)
            # Pg = P_cols W^T y and lam Pg + mean at the measured coordinates; t(u) = M u
            for a in range(k):
                for q in range(P):
                    Pg_s[a, q] = 0.0
                for c in range(k):
                    for q in range(P):
                        Pg_s[a, q] += PcP[sup[a], c, q] * Wy[c, q]
                for q in range(P):
                    x1_s[a, q] = lam * Pg_s[a, q] + dg[a, q]
            for a in range(k):
                for q in range(P):
                    t1[a, q] = 0.0
                    tp[a, q] = 0.0
                    te[a, q] = 0.0
                    ta[a, q] = 0.0
                for c in range(k):
                    for q in range(P):
                        mac = M[a, c, q]
                        t1[a, q] += mac * x1_s[c, q]
                        tp[a, q] += mac * Pg_s[c, q]
                        te[a, q] += mac * eta_s[c, q]
                        ta[a, q] += mac * aux_s[c, q]
            h = lam - 0.5 * eps
            _chol_lanes(S, h, K2, k, P)
            _chol_lanes(S, lam, K1, k, P)
            for q in range(P):
                ld[q] = 0.0
            for a in range(k):
                for q in range(P):
                    ld[q] += math.log(K2[a, a, q]) - math.log(K1[a, a, q])
            _solve_lanes(K1, t1, q1, k, P)
            for a in range(k):
                for q in range(P):
                    tmp[a, q] = 0.0
                for c in range(k):
                    if c <= a:
                        for q in range(P):
                            tmp[a, q] += S[a, c, q] * q1[c, q]
                    else:
                        for q in range(P):
                            tmp[a, q] += S[c, a, q] * q1[c, q]
                for q in range(P):
                    tmp[a, q] = tp[a, q] - 0.5 * tmp[a, q]
            _solve_lanes(K1, tmp, q2, k, P)
            _solve_lanes(K1, te, te, k, P)
            _solve_lanes(K1, ta, ta, k, P)
            for a in range(k):
                for q in range(P):
                    base = 0.5 * q1[a, q] + lam * q2[a, q]
                    te[a, q] = 0.5 * te[a, q] + base
                    ta[a, q] = 0.5 * ta[a, q] + base
            for r in range(d):
                for q in range(P):
                    s1[q] = 0.0
                    s2[q] = 0.0
                    s3[q] = 0.0
                for c in range(k):
                    for q in range(P):
                        s1[q] += PcP[r, c, q] * Wy[c, q]
                        s2[q] += LP[r, c, q] * te[c, q]
                        s3[q] += LP[r, c, q] * ta[c, q]
                for q in range(P):
                    if grp * P + q < total:
                        b, n = bb[q], nn[q]
                        eta_out[b, n, r] = eta[b, n, r] + eps * (s1[q] - s2[q])
                        aux_out[b, n, r] = aux[b, n, r] + eps * (s1[q] - s3[q])
            for q in range(P):
                if grp * P + q < total:
                    log_det[bb[q], nn[q]] += 2.0 * ld[q]


@numba.njit(cache=True, inline="always")
def _chol_lanes(S, h, K, k, P):
    """Lower Cholesky factors ``K`` of ``I + h S`` for each lane (``S``'s lower triangle read)."""
    for j in range(k):
        for r in range(j, k):
            for q in range(P):
                K[r, j, q] = h * S[r, j, q] + (1.0 if r == j else 0.0)
            for c in range(j):
                for q in range(P):
                    K[r, j, q] -= K[r, c, q] * K[j, c, q]
        for q in range(P):
            K[j, j, q] = math.sqrt(K[j, j, q])
        for r in range(j + 1, k):
            for q in range(P):
                K[r, j, q] /= K[j, j, q]


@numba.njit(cache=True, inline="always")
def _forward_lanes(K, t, x, k, P):
    """``x = K^{-1} t`` for each lane (``K`` lower); ``x`` may be ``t``."""
    for i in range(k):
        for q in range(P):
            x[i, q] = t[i, q]
        for c in range(i):
            for q in range(P):
                x[i, q] -= K[i, c, q] * x[c, q]
        for q in range(P):
            x[i, q] /= K[i, i, q]


@numba.njit(cache=True, inline="always")
def _backward_lanes(K, t, x, k, P):
    """``x = K^{-T} t`` for each lane (``K`` lower); ``x`` may be ``t``."""
    for i in range(k - 1, -1, -1):
        for q in range(P):
            x[i, q] = t[i, q]
        for r in range(i + 1, k):
            for q in range(P):
                x[i, q] -= K[r, i, q] * x[r, q]
        for q in range(P):
            x[i, q] /= K[i, i, q]


@numba.njit(cache=True, inline="always")
def _solve_lanes(K, t, x, k, P):
    """``x = (K K^T)^{-1} t`` for each lane (``K`` lower); ``x`` may be ``t``."""
    _forward_lanes(K, t, x, k, P)
    _backward_lanes(K, x, x, k, P)


@numba.njit(cache=True, parallel=True, error_model="numpy")
def gromov_step(
    W, y, L, Ls, sup, eta, aux, mu, Sig, xi, eta_out, aux_out, mu_out, Sig_out, lams, epss, j, lin, sens, const, track
):
    """One Euler-Maruyama pseudo-step of the Gromov flow at per-particle points (the operator form
    of :class:`~torchflow.flows.GromovFlow`, ``noise_root="factor"``) for every particle of ``eta
    (B, N, d)``, with ``LANES`` particles side by side as :func:`dh_step`.

    With ``Q = I + lam S``, ``S = V^T V``, ``M = V^T W`` (``V_i = L_s^T W_i``): ``C = L Q^{-1} M``,
    ``N = L Q^{-1} L_s^T``, ``g = L Q^{-1} L_s^T W^T y``; the drift of ``x`` is ``-C x_s + g`` and
    the diffusion ``N (W^T xi)`` with ``xi (B, N, m)`` the step's standard normals. The particle, its
    point and (``track`` 1) the mean ``mu`` of its Gaussian law move; the law's covariance
    ``Sig (B|1, N|1, d, d)`` becomes ``(I - eps C_s) Sig (I - eps C_s)^T + eps C N^T`` in
    ``Sig_out (B, N, d, d)`` (``C_s``: C in the support columns). Inputs as :func:`dh_step`."""
    B, N, d, k, m, lam, eps, psi, d0, P, total, per, groups, nblocks = _grid(
        eta, sup, sens, y, lin, lams, epss, const, j
    )
    root = math.sqrt(eps)
    for blk in numba.prange(nblocks):
        bb = np.empty(P, np.int64)
        nn = np.empty(P, np.int64)
        Wr = np.empty((m if lin == 0 else 0, k, P))
        yr = np.empty((m, P))
        xr = np.empty((m, P))
        M = np.empty((k, k, P))
        w = np.empty((k, P))
        LsP = np.empty((k, k, P))
        LP = np.empty((d, k, P))
        S = np.empty((k, k, P))
        K1 = np.empty((k, k, P))
        Z = np.empty((2 * k + 1, k, P))  # Q^{-1} [M | L_s^T | L_s^T W^T y], a column per row
        Cm = np.empty((d, k, P))
        Nm = np.empty((d, k, P))
        SigP = np.empty((d, d, P))
        V = np.empty((d, d, P))
        vec = np.zeros((6, k, P))
        dvec = np.empty((5, d, P))
        sc = np.empty((1, P))
        for grp in range(blk * per, min(groups, (blk + 1) * per)):
            for q in range(P):
                p = min(grp * P + q, total - 1)
                bb[q], nn[q] = p // N, p % N
            aux_s, eta_s, mu_s, Wy, Wx, v = vec[0], vec[1], vec[2], vec[3], vec[4], vec[5]
            g, de, da, dm, dn = dvec[0], dvec[1], dvec[2], dvec[3], dvec[4]
            s1 = sc[0]
            for q in range(P):  # gather the lanes' inputs
                b, n = bb[q], nn[q]
                bl, nl = (b if L.shape[0] > 1 else 0), (n if L.shape[1] > 1 else 0)
                bs, ns = (b if Ls.shape[0] > 1 else 0), (n if Ls.shape[1] > 1 else 0)
                for a in range(k):
                    aux_s[a, q] = aux[b, n, sup[a]]
                    eta_s[a, q] = eta[b, n, sup[a]]
                    for c in range(k):
                        LsP[a, c, q] = Ls[bs, ns, a, c]
                for r in range(d):
                    for c in range(k):
                        LP[r, c, q] = L[bl, nl, r, c]
                if track == 1:
                    bg, ng = (b if Sig.shape[0] > 1 else 0), (n if Sig.shape[1] > 1 else 0)
                    for a in range(k):
                        mu_s[a, q] = mu[b, n, sup[a]]
                    for r in range(d):
                        for c in range(d):
                            SigP[r, c, q] = Sig[bg, ng, r, c]
                _gather_rows(q, b, n, lin, W, y, Wr, yr, m, k)
                for i in range(m):
                    xr[i, q] = xi[b, n, i]
            _zero(Wy, S, M, k, P)
            for a in range(k):
                for q in range(P):
                    Wx[a, q] = 0.0
            for i in range(m):  # one pass over the rows: W^T y, W^T xi, S (lower) and M
                _row(i, lin, Wr, yr, aux_s, sens, psi, d0, w, s1, k, P)
                for a in range(k):
                    for q in range(P):
                        Wx[a, q] += w[a, q] * xr[i, q]
                _accumulate(w, s1, LsP, Wy, v, S, M, k, P)
            _chol_lanes(S, lam, K1, k, P)
            for c in range(k):  # right-hand sides: the columns of M and of L_s^T, and L_s^T W^T y
                for a in range(k):
                    for q in range(P):
                        Z[c, a, q] = M[a, c, q]
                        Z[k + c, a, q] = LsP[c, a, q]
            for a in range(k):
                for q in range(P):
                    Z[2 * k, a, q] = 0.0
                for e in range(a, k):
                    for q in range(P):
                        Z[2 * k, a, q] += LsP[e, a, q] * Wy[e, q]
            for c in range(2 * k + 1):
                _solve_lanes(K1, Z[c], Z[c], k, P)
            for r in range(d):  # C = L Z_M, N = L Z_L, g = L z_y
                for c in range(k):
                    for q in range(P):
                        Cm[r, c, q] = 0.0
                        Nm[r, c, q] = 0.0
                for q in range(P):
                    g[r, q] = 0.0
                for a in range(k):
                    for q in range(P):
                        g[r, q] += LP[r, a, q] * Z[2 * k, a, q]
                    for c in range(k):
                        for q in range(P):
                            Cm[r, c, q] += LP[r, a, q] * Z[c, a, q]
                            Nm[r, c, q] += LP[r, a, q] * Z[k + c, a, q]
            for r in range(d):  # drifts -C x_s + g, the diffusion N (W^T xi)
                for q in range(P):
                    de[r, q] = g[r, q]
                    da[r, q] = g[r, q]
                    dm[r, q] = g[r, q]
                    dn[r, q] = 0.0
                for c in range(k):
                    for q in range(P):
                        cc = Cm[r, c, q]
                        de[r, q] -= cc * eta_s[c, q]
                        da[r, q] -= cc * aux_s[c, q]
                        dm[r, q] -= cc * mu_s[c, q]
                        dn[r, q] += Nm[r, c, q] * Wx[c, q]
            if track == 1:  # V = Sig - eps C Sig[s, :]; Sig' = V - eps V[:, s] C^T + eps C N^T
                for r in range(d):
                    for c in range(d):
                        for q in range(P):
                            V[r, c, q] = SigP[r, c, q]
                        for a in range(k):
                            for q in range(P):
                                V[r, c, q] -= eps * (Cm[r, a, q] * SigP[sup[a], c, q])
                for r in range(d):
                    for c in range(d):
                        for q in range(P):
                            SigP[r, c, q] = V[r, c, q]
                        for a in range(k):
                            for q in range(P):
                                SigP[r, c, q] += eps * (Cm[r, a, q] * Nm[c, a, q] - V[r, sup[a], q] * Cm[c, a, q])
            for q in range(P):
                if grp * P + q < total:
                    b, n = bb[q], nn[q]
                    for r in range(d):
                        eta_out[b, n, r] = eta[b, n, r] + eps * de[r, q] + root * dn[r, q]
                        aux_out[b, n, r] = aux[b, n, r] + eps * da[r, q]
                    if track == 1:
                        for r in range(d):
                            mu_out[b, n, r] = mu[b, n, r] + eps * dm[r, q]
                            for c in range(d):
                                Sig_out[b, n, r, c] = SigP[r, c, q]


@numba.njit(cache=True, inline="always")
def _row_hessian(i, lin, Wr, yr, Dg, xs, sens, psi, d0, w, s1, Dr, k, nb, bs, P):
    """:func:`_row` at the points ``xs`` and the row's second-derivative blocks ``Dr (nb, bs, bs, P)``
    (``dW_t[i, (c, j)] = Dr[c, t_i, j]`` for ``t = (c, t_i)``): read (``lin`` 0) or computed in the
    acoustic form (``lin`` 1; the blocks of
    :meth:`~torchflow.models.AcousticTracking.measurement_hessian_blocks`)."""
    _row(i, lin, Wr, yr, xs, sens, psi, d0, w, s1, k, P)
    if lin == 1:
        sx, sy = sens[i, 0], sens[i, 1]
        for c in range(nb):
            for q in range(P):
                dx = xs[2 * c, q] - sx
                dy = xs[2 * c + 1, q] - sy
                r = math.sqrt(dx * dx + dy * dy)
                inv = 1.0 / (r + d0)
                ir = 1.0 / max(r, 2.2250738585072014e-308)
                bb = psi * inv * inv * ir
                cc = (2.0 * psi * inv * inv * inv + bb) * ir * ir
                Dr[c, 0, 0, q] = cc * dx * dx - bb
                Dr[c, 0, 1, q] = cc * dx * dy
                Dr[c, 1, 0, q] = cc * dx * dy
                Dr[c, 1, 1, q] = cc * dy * dy - bb
    else:
        for c in range(nb):
            for e in range(bs):
                for f in range(bs):
                    for q in range(P):
                        Dr[c, e, f, q] = Dg[i, c, e, f, q]


@numba.njit(cache=True, inline="always")
def _upper_times(K, t, x, k, P):
    """``x = K^T t`` for each lane (``K`` lower); ``x`` is not ``t``."""
    for a in range(k):
        for q in range(P):
            x[a, q] = 0.0
        for p in range(a, k):
            for q in range(P):
                x[a, q] += K[p, a, q] * t[p, q]


@numba.njit(cache=True)
def _tangent_side(K, Nm, Cm, lam, Cl, et, drx, v, c, bs, k, P, qv, rhs, dm, ph, At, Bt, sb):
    """GPFIS's tangent ``t = (c, .)`` at pseudo-time ``lam`` (factor ``K``, ``N = K^{-1} C^T``,
    ``C m``): ``dm = lam M^{-1} C^T (drx - F_t C m)`` and ``phi = Psi^T v`` into ``dm``, ``ph``
    (``(k, P)``) -- see :func:`gpfis_step`. Not inlined: it keeps the kernel's compilation short."""
    for a in range(k):
        for q in range(P):
            qv[a, q] = drx[a, q]
        for f in range(bs):
            for q in range(P):
                qv[a, q] -= et[a, f, q] * Cm[c * bs + f, q]
    for f in range(bs):
        for a in range(k):
            for q in range(P):
                qv[c * bs + f, q] -= et[a, f, q] * Cm[a, q]
    _upper_times(Cl, qv, rhs, k, P)
    _solve_lanes(K, rhs, dm, k, P)
    for a in range(k):
        for q in range(P):
            dm[a, q] *= lam
    # a = N e_t, b = N's block-c columns; phi = Psi^T v by suffix sums over the rows
    for a in range(k):
        for f in range(bs):
            for q in range(P):
                At[a, f, q] = 0.0
                Bt[a, f, q] = Nm[a, c * bs + f, q]
            for p in range(k):
                for q in range(P):
                    At[a, f, q] += Nm[a, p, q] * et[p, f, q]
    for f in range(bs):
        for q in range(P):
            sb[0, f, q] = 0.0
            sb[1, f, q] = 0.0
    for a in range(k - 1, -1, -1):
        for q in range(P):
            ph[a, q] = 0.0
        for f in range(bs):
            for q in range(P):
                ph[a, q] += Bt[a, f, q] * sb[0, f, q] + At[a, f, q] * sb[1, f, q] + At[a, f, q] * Bt[a, f, q] * v[a, q]
        for f in range(bs):
            for q in range(P):
                sb[0, f, q] += At[a, f, q] * v[a, q]
                sb[1, f, q] += Bt[a, f, q] * v[a, q]
        for q in range(P):
            ph[a, q] *= lam


@numba.njit(cache=True)
def _gpfis_rows(lin, Wr, yr, Dg, xs, sens, psi, d0, w, s1, Dr, Wy, Sw, Zb, k, m, nb, bs, P):
    """:func:`gpfis_step`'s pass over the rows of W at the points ``xs``: ``Wy = W^T y``,
    ``Sw = W^T W`` (lower triangle) and ``Zb = [W y]^T D`` (its second-derivative blocks)."""
    for a in range(k):
        for q in range(P):
            Wy[a, q] = 0.0
        for c in range(a + 1):
            for q in range(P):
                Sw[a, c, q] = 0.0
    for a in range(k + 1):
        for c in range(nb):
            for e in range(bs):
                for f in range(bs):
                    for q in range(P):
                        Zb[a, c, e, f, q] = 0.0
    for i in range(m):
        _row_hessian(i, lin, Wr, yr, Dg, xs, sens, psi, d0, w, s1, Dr, k, nb, bs, P)
        for a in range(k):
            for q in range(P):
                Wy[a, q] += w[a, q] * s1[q]
            for c in range(a + 1):
                for q in range(P):
                    Sw[a, c, q] += w[a, q] * w[c, q]
            for c in range(nb):
                for e in range(bs):
                    for f in range(bs):
                        for q in range(P):
                            Zb[a, c, e, f, q] += w[a, q] * Dr[c, e, f, q]
        for c in range(nb):
            for e in range(bs):
                for f in range(bs):
                    for q in range(P):
                        Zb[k, c, e, f, q] += s1[q] * Dr[c, e, f, q]


@numba.njit(cache=True)
def _qr_logdet(J, ldc, ld, s1, k, P):
    """``ld = ldc + log|det J|`` for each lane's ``J (k, k)`` by modified Gram-Schmidt (the product of
    R's diagonal); J is overwritten."""
    for q in range(P):
        ld[q] = ldc[q]
    for t in range(k):
        for s in range(t):
            for q in range(P):
                s1[q] = 0.0
            for a in range(k):
                for q in range(P):
                    s1[q] += J[a, s, q] * J[a, t, q]
            for a in range(k):
                for q in range(P):
                    J[a, t, q] -= s1[q] * J[a, s, q]
        for q in range(P):
            s1[q] = 0.0
        for a in range(k):
            for q in range(P):
                s1[q] += J[a, t, q] * J[a, t, q]
        for q in range(P):
            s1[q] = math.sqrt(s1[q])
            ld[q] += math.log(s1[q])
        for a in range(k):
            for q in range(P):
                J[a, t, q] /= s1[q]


@numba.njit(cache=True, parallel=True, error_model="numpy")
def gpfis_step(W, y, D, C, cols, mean, sup, x, x_out, log_det, lams, epss, j0, j1, lin, sens, const, nb, bs):
    """Pseudo-steps ``j0 .. j1 - 1`` of the GPFIS transport (Cholesky root) and the log-determinant
    of each step's map (:func:`torchflow.flows.gpfis._cholesky_step_and_jacobian`'s formulas) for
    every particle of ``x (B, N, d)``, ``LANES`` particles side by side as :func:`dh_step`. Writes
    ``x_out`` and adds to ``log_det (B, N)``.

    ``C (B|1, N|1, k, k)``: the prior's lower factor at the support, ``cols (B|1, N|1, d, k)``
    its columns, ``mean (B|1, N|1, d)`` the prior mean; ``lin`` 0: ``W (B|1, N|1, m, k)``,
    ``y (B|1, N|1, m)`` and the second-derivative blocks ``D (B|1, N|1, m, nb, bs, bs)`` at ``x``
    are read (one step: ``j1 = j0 + 1``); ``lin`` 1: computed at the particles in the acoustic
    form (``y`` holds ``z / sigma``, ``const = [Psi / sigma, d0]``, ``bs`` 2), every step in one call.

    Per step, in whitened coordinates ``u = C^{-1} x_s`` with ``G = C^T (W^T W) C``, ``r = C^T W^T y``,
    ``M_i = I + lam_i G = K_i K_i^T``, ``m_i = M_i^{-1} (u_0 + lam_i r)``, ``v = K_0^T (u - m_0)``:
    ``u' = K_1^{-T} (K_1^{-1} (u_0 + lam_1 r) + v)``. Along tangent ``t = (c, t_i)`` of ``x_s`` only
    ``dW_t`` (block c of the row blocks) moves, so ``F_t = W^T dW_t + dW_t^T W = e_t P_c^T + P_c e_t^T``
    with ``e_t = W^T D[:, c, t_i, :] (k, bs)`` is of rank ``2 bs``: ``K_i^{-1} C^T F_t C K_i^{-T}
    = a b^T + b a^T`` (``a = N_i e_t``, ``b = N_i[:, block c]``, ``N_i = K_i^{-1} C^T``) and the
    Cholesky factor's derivative applied to ``v`` is a suffix sum over rows, ``O(k bs)`` per tangent.
    ``log|det du'/dx_s|`` from a modified Gram-Schmidt QR of the ``k x k`` Jacobian, plus
    ``log|det C|`` (the map of the other coordinates is triangular with unit diagonal)."""
    B, N, d, k, m, _, _, psi, d0, P, total, per, groups, nblocks = _grid(x, sup, sens, y, lin, lams, epss, const, j0)
    for blk in numba.prange(nblocks):
        _gpfis_block(
            blk,
            per,
            groups,
            total,
            W,
            y,
            D,
            C,
            cols,
            mean,
            sup,
            x,
            x_out,
            log_det,
            lams,
            epss,
            j0,
            j1,
            lin,
            sens,
            const,
            nb,
            bs,
            B,
            N,
            d,
            k,
            m,
            psi,
            d0,
            P,
        )


@numba.njit(cache=True, error_model="numpy")
def _gpfis_block(
    blk,
    per,
    groups,
    total,
    W,
    y,
    D,
    C,
    cols,
    mean,
    sup,
    x,
    x_out,
    log_det,
    lams,
    epss,
    j0,
    j1,
    lin,
    sens,
    const,
    nb,
    bs,
    B,
    N,
    d,
    k,
    m,
    psi,
    d0,
    P,
):
    """Block ``blk`` of :func:`gpfis_step`'s parallel loop (a function of its own: Numba compiles
    a parallel loop's body slowly)."""
    bbi = np.empty(P, np.int64)
    nni = np.empty(P, np.int64)
    Wr = np.empty((m if lin == 0 else 0, k, P))
    yr = np.empty((m, P))
    Dg = np.empty((m if lin == 0 else 0, nb, bs, bs, P))
    Dr = np.empty((nb, bs, bs, P))
    Zb = np.empty((k + 1, nb, bs, bs, P))
    X = np.empty((d, P))
    Co = np.empty((d, k, P))
    mat = np.empty((10, k, k, P))
    vec = np.empty((24, k, P))
    tb = np.empty((6, k, bs, P))
    sb = np.empty((2, bs, P))
    sc = np.empty((3, P))
    for grp in range(blk * per, min(groups, (blk + 1) * per)):
        for q in range(P):
            p = min(grp * P + q, total - 1)
            bbi[q], nni[q] = p // N, p % N
        Cl, Ci, Sw, T, G, K0, K1, N0, N1, J = (
            mat[0],
            mat[1],
            mat[2],
            mat[3],
            mat[4],
            mat[5],
            mat[6],
            mat[7],
            mat[8],
            mat[9],
        )
        xs, u0, w, Wy, r, u, b0, m0, v, b1 = (
            vec[0],
            vec[1],
            vec[2],
            vec[3],
            vec[4],
            vec[5],
            vec[6],
            vec[7],
            vec[8],
            vec[9],
        )
        un, m1, Cm0, Cm1, drx, qv, rhs, dm0, dm1, col = (
            vec[10],
            vec[11],
            vec[12],
            vec[13],
            vec[14],
            vec[15],
            vec[16],
            vec[17],
            vec[18],
            vec[19],
        )
        ph0, ph1, tmp, ms = vec[20], vec[21], vec[22], vec[23]
        et, A0, B0, A1, B1 = tb[0], tb[1], tb[2], tb[3], tb[4]
        s1, ldc, ld = sc[0], sc[1], sc[2]
        for q in range(P):  # gather the lanes' inputs
            b, n = bbi[q], nni[q]
            bc, nc = (b if C.shape[0] > 1 else 0), (n if C.shape[1] > 1 else 0)
            bo, no = (b if cols.shape[0] > 1 else 0), (n if cols.shape[1] > 1 else 0)
            bm, nm = (b if mean.shape[0] > 1 else 0), (n if mean.shape[1] > 1 else 0)
            for r_ in range(d):
                X[r_, q] = x[b, n, r_]
                for c in range(k):
                    Co[r_, c, q] = cols[bo, no, r_, c]
            for a in range(k):
                ms[a, q] = mean[bm, nm, sup[a]]
                for c in range(k):
                    Cl[a, c, q] = C[bc, nc, a, c]
            if lin == 0:
                _gather_rows(q, b, n, lin, W, y, Wr, yr, m, k)
                bd, nd = (b if D.shape[0] > 1 else 0), (n if D.shape[1] > 1 else 0)
                for i in range(m):
                    for c in range(nb):
                        for e in range(bs):
                            for f in range(bs):
                                Dg[i, c, e, f, q] = D[bd, nd, i, c, e, f]
            else:
                _gather_rows(q, b, n, 1, W, y, Wr, yr, m, k)
        # constants of the integration: C^{-1} (its columns are the tangents' du), log|det C|, u_0
        for c in range(k):
            for a in range(k):
                for q in range(P):
                    tmp[a, q] = 1.0 if a == c else 0.0
            _forward_lanes(Cl, tmp, tmp, k, P)
            for a in range(k):
                for q in range(P):
                    Ci[a, c, q] = tmp[a, q]
        for q in range(P):
            ldc[q] = 0.0
        for a in range(k):
            for q in range(P):
                ldc[q] += math.log(abs(Cl[a, a, q]))
        _forward_lanes(Cl, ms, u0, k, P)
        for j in range(j0, j1):
            lam1 = lams[j]
            lam0 = lam1 - epss[j]
            for a in range(k):
                for q in range(P):
                    xs[a, q] = X[sup[a], q]
            _gpfis_rows(lin, Wr, yr, Dg, xs, sens, psi, d0, w, s1, Dr, Wy, Sw, Zb, k, m, nb, bs, P)
            # G = C^T S_w C (T = S_w C), r = C^T W^T y, u = C^{-1} x_s
            for a in range(k):
                for c in range(k):
                    for q in range(P):
                        T[a, c, q] = 0.0
                    for p in range(c, k):
                        if p <= a:
                            for q in range(P):
                                T[a, c, q] += Sw[a, p, q] * Cl[p, c, q]
                        else:
                            for q in range(P):
                                T[a, c, q] += Sw[p, a, q] * Cl[p, c, q]
            for a in range(k):
                for c in range(a + 1):
                    for q in range(P):
                        G[a, c, q] = 0.0
                    for p in range(a, k):
                        for q in range(P):
                            G[a, c, q] += Cl[p, a, q] * T[p, c, q]
            _upper_times(Cl, Wy, r, k, P)
            _forward_lanes(Cl, xs, u, k, P)
            _chol_lanes(G, lam0, K0, k, P)
            _chol_lanes(G, lam1, K1, k, P)
            for a in range(k):
                for q in range(P):
                    b0[a, q] = u0[a, q] + lam0 * r[a, q]
                    b1[a, q] = u0[a, q] + lam1 * r[a, q]
            _solve_lanes(K0, b0, m0, k, P)
            for a in range(k):
                for q in range(P):
                    tmp[a, q] = u[a, q] - m0[a, q]
            _upper_times(K0, tmp, v, k, P)
            _forward_lanes(K1, b1, b1, k, P)
            for a in range(k):
                for q in range(P):
                    tmp[a, q] = b1[a, q] + v[a, q]
            _backward_lanes(K1, tmp, un, k, P)
            _backward_lanes(K1, b1, m1, k, P)
            # N_i = K_i^{-1} C^T, column by column; C m_i
            for c in range(k):
                for a in range(k):
                    for q in range(P):
                        tmp[a, q] = Cl[c, a, q]
                _forward_lanes(K0, tmp, rhs, k, P)
                _forward_lanes(K1, tmp, qv, k, P)
                for a in range(k):
                    for q in range(P):
                        N0[a, c, q] = rhs[a, q]
                        N1[a, c, q] = qv[a, q]
            for a in range(k):
                for q in range(P):
                    Cm0[a, q] = 0.0
                    Cm1[a, q] = 0.0
                for p in range(a + 1):
                    for q in range(P):
                        Cm0[a, q] += Cl[a, p, q] * m0[p, q]
                        Cm1[a, q] += Cl[a, p, q] * m1[p, q]
            # the Jacobian, a column per tangent t = (c, ti)
            for c in range(nb):
                for ti in range(bs):
                    t = c * bs + ti
                    for a in range(k):  # e_t = W^T dW_t's block, W^T dy_t = e_t x_c, dW_t^T y
                        for f in range(bs):
                            for q in range(P):
                                et[a, f, q] = Zb[a, c, ti, f, q]
                        for q in range(P):
                            drx[a, q] = 0.0
                        for f in range(bs):
                            for q in range(P):
                                drx[a, q] += et[a, f, q] * xs[c * bs + f, q]
                    for f in range(bs):
                        for q in range(P):
                            drx[c * bs + f, q] += Zb[k, c, ti, f, q]
                    _tangent_side(K0, N0, Cm0, lam0, Cl, et, drx, v, c, bs, k, P, qv, rhs, dm0, ph0, A0, B0, sb)
                    _tangent_side(K1, N1, Cm1, lam1, Cl, et, drx, v, c, bs, k, P, qv, rhs, dm1, ph1, A1, B1, sb)
                    # J[:, t] = dm_1 + K_1^{-T} (K_0^T (C^{-1} e_t - dm_0) + phi_0 - phi_1)
                    for a in range(k):
                        for q in range(P):
                            tmp[a, q] = Ci[a, t, q] - dm0[a, q]
                    _upper_times(K0, tmp, col, k, P)
                    for a in range(k):
                        for q in range(P):
                            col[a, q] += ph0[a, q] - ph1[a, q]
                    _backward_lanes(K1, col, col, k, P)
                    for a in range(k):
                        for q in range(P):
                            J[a, t, q] = dm1[a, q] + col[a, q]
            _qr_logdet(J, ldc, ld, s1, k, P)
            # x += cols (u' - u)
            for a in range(k):
                for q in range(P):
                    tmp[a, q] = un[a, q] - u[a, q]
            for r_ in range(d):
                for c in range(k):
                    for q in range(P):
                        X[r_, q] += Co[r_, c, q] * tmp[c, q]
            for q in range(P):
                if grp * P + q < total:
                    log_det[bbi[q], nni[q]] += ld[q]
        for q in range(P):
            if grp * P + q < total:
                b, n = bbi[q], nni[q]
                for r_ in range(d):
                    x_out[b, n, r_] = X[r_, q]


@numba.njit(cache=True, fastmath={"reassoc", "contract"})
def _chol_into(Pinv, dgn, h, K, d):
    """Lower Cholesky factor ``K`` of ``Pinv + h diag(dgn)`` (``Pinv`` read in full, symmetric), row
    by row (Cholesky-Banachiewicz), four rows at a time: each entry is a contiguous dot product of two
    rows, vectorised by reassociating it, and each load of an earlier row serves four (fewer loads
    per flop than one or two rows at a time; its rate against torch's batched ``cholesky_ex``:
    ``python -m experiments.benchmarks.micro_small_linalg``)."""
    r0 = 0
    while r0 < d:
        nr = min(4, d - r0)
        if nr == 4:
            for j in range(r0):
                a0, a1, a2, a3 = Pinv[r0, j], Pinv[r0 + 1, j], Pinv[r0 + 2, j], Pinv[r0 + 3, j]
                for c in range(j):
                    kc = K[j, c]
                    a0 -= K[r0, c] * kc
                    a1 -= K[r0 + 1, c] * kc
                    a2 -= K[r0 + 2, c] * kc
                    a3 -= K[r0 + 3, c] * kc
                inv = 1.0 / K[j, j]
                K[r0, j], K[r0 + 1, j], K[r0 + 2, j], K[r0 + 3, j] = a0 * inv, a1 * inv, a2 * inv, a3 * inv
        else:
            for r in range(r0, d):
                for j in range(r0):
                    a = Pinv[r, j]
                    for c in range(j):
                        a -= K[r, c] * K[j, c]
                    K[r, j] = a / K[j, j]
        for r in range(r0, r0 + nr):  # the diagonal block
            for j in range(r0, r + 1):
                a = Pinv[r, j] + (h * dgn[r] if j == r else 0.0)
                for c in range(j):
                    a -= K[r, c] * K[j, c]
                K[r, j] = math.sqrt(a) if j == r else a / K[j, j]
        r0 += nr


@numba.njit(cache=True, fastmath={"reassoc", "contract"})
def _chol_solve_into(K, X, n, d):
    """``X[:n] <- (K K^T)^{-1} X[:n]`` for ``n`` right-hand sides as rows of ``X (r, d)``: forward
    by contiguous dot products, backward by contiguous row updates."""
    for v in range(n):
        x = X[v]
        for i in range(d):
            s = x[i]
            for c in range(i):
                s -= K[i, c] * x[c]
            x[i] = s / K[i, i]
        for i in range(d - 1, -1, -1):
            x[i] /= K[i, i]
            xi = x[i]
            for r in range(i):
                x[r] -= K[i, r] * xi


@numba.njit(cache=True, parallel=True, fastmath={"reassoc", "contract"})
def dh_diag_step(Wd, y, Pinv, Pc, mean, eta, aux, eta_out, aux_out, log_det, lams, epss, j, nslots):
    """One Euler pseudo-step of EDH/LEDH at per-particle points for a diagonal whitened Jacobian
    (``W = diag(Wd)``, ``Wd, y (B|1, N|1, d)``), in information form, one particle per iteration of
    the parallel loop: with ``D = diag(Wd^2)`` and ``M_l = P^{-1} + l D = K_l K_l^T``
    (``Pinv (B|1, N|1, d, d)``), ``A = -1/2 M_lam^{-1} D``, ``P H^T R^{-1} (z - e) = P (Wd y)``
    (``Pc``: P), ``log|det(I + eps A)| = log det K_{lam - eps/2} - log det K_lam``; the same maps as
    :func:`~torchflow.flows.daum_huang.daum_huang_coefficients` (``L (I + lam L^T D L)^{-1} L^T =
    M_lam^{-1}``), two ``d x d`` Cholesky factorisations per particle and no ``d x d x d`` product.
    ``nslots``: scratch slots, at least the threads (``numba.config.NUMBA_NUM_THREADS``)."""
    B, N, d = eta.shape
    lam = lams[j]
    eps = epss[j]
    total = B * N
    slots = nslots
    # scratch per thread, allocated once per call (a d x d array per particle costs a page fault each)
    K_, X_, v_ = np.empty((slots, d, d)), np.empty((slots, 3, d)), np.empty((slots, 3, d))
    for p in numba.prange(total):  # one particle per iteration: even shares of the particles
        t = numba.get_thread_id()
        _diag_particle(
            p,
            N,
            d,
            Wd,
            y,
            Pinv,
            Pc,
            mean,
            eta,
            aux,
            eta_out,
            aux_out,
            log_det,
            lam,
            eps,
            K_[t],
            X_[t],
            v_[t, 0],
            v_[t, 1],
            v_[t, 2],
        )


@numba.njit(cache=True, fastmath={"reassoc", "contract"})
def _diag_particle(p, N, d, Wd, y, Pinv, Pc, mean, eta, aux, eta_out, aux_out, log_det, lam, eps, K, X, dg, wy, pg):
    """Particle ``p`` of :func:`dh_diag_step` (scratch ``K (d, d)``, ``X (3, d)``, ``dg``, ``wy``, ``pg``)."""
    b, n = p // N, p % N
    bw, nw = (b if Wd.shape[0] > 1 else 0), (n if Wd.shape[1] > 1 else 0)
    by, ny = (b if y.shape[0] > 1 else 0), (n if y.shape[1] > 1 else 0)
    bi, ni = (b if Pinv.shape[0] > 1 else 0), (n if Pinv.shape[1] > 1 else 0)
    bp, np_ = (b if Pc.shape[0] > 1 else 0), (n if Pc.shape[1] > 1 else 0)
    bm, nm = (b if mean.shape[0] > 1 else 0), (n if mean.shape[1] > 1 else 0)
    Pi = Pinv[bi, ni]
    for i in range(d):
        w = Wd[bw, nw, i]
        dg[i] = w * w
        wy[i] = w * y[by, ny, i]
    P = Pc[bp, np_]
    for i in range(d):
        s = 0.0
        for c in range(d):
            s += P[i, c] * wy[c]
        pg[i] = s
    _chol_into(Pi, dg, lam - 0.5 * eps, K, d)
    ld = 0.0
    for i in range(d):
        ld += math.log(K[i, i])
    _chol_into(Pi, dg, lam, K, d)
    for i in range(d):
        ld -= math.log(K[i, i])
    # A v = -1/2 M^{-1} (D v) for v = lam Pg + mean, eta, aux; then u = Pg + A(lam Pg + mean), b = u + 2 lam A u
    for i in range(d):
        X[0, i] = dg[i] * (lam * pg[i] + mean[bm, nm, i])
        X[1, i] = dg[i] * eta[b, n, i]
        X[2, i] = dg[i] * aux[b, n, i]
    _chol_solve_into(K, X, 3, d)
    for i in range(d):
        X[0, i] = pg[i] - 0.5 * X[0, i]  # u
    for i in range(d):
        wy[i] = dg[i] * X[0, i]  # D u, solved in place below
    U = wy.reshape((1, d))
    _chol_solve_into(K, U, 1, d)
    for i in range(d):
        bb = X[0, i] - lam * U[0, i]  # b = u + 2 lam (-1/2 M^{-1} D u)
        eta_out[b, n, i] = eta[b, n, i] + eps * (bb - 0.5 * X[1, i])
        aux_out[b, n, i] = aux[b, n, i] + eps * (bb - 0.5 * X[2, i])
    log_det[b, n] += 2.0 * ld


@numba.njit(cache=True, parallel=True, fastmath={"reassoc", "contract"})
def precision_from_factor(L, out):
    """``out[b, n] = (L L^T)^{-1}`` for lower factors ``L (B, N, d, d)``: ``X = L^{-1}`` by forward
    substitution, then ``X^T X``, both as updates of contiguous rows. One matrix per iteration of
    the parallel loop, so the bits do not depend on the thread count (torch's batched
    ``cholesky_inverse`` does)."""
    B, N, d = L.shape[0], L.shape[1], L.shape[2]
    for p in numba.prange(B * N):
        b, n = p // N, p % N
        Lm = L[b, n]
        X = np.zeros((d, d))  # L^{-1}, lower: row i = -(L[i, :i] X[:i, :]) / L[i, i], and 1 / L[i, i]
        for i in range(d):
            for k in range(i):
                f = Lm[i, k]
                for c in range(k + 1):
                    X[i, c] -= f * X[k, c]
            inv = 1.0 / Lm[i, i]
            for c in range(i):
                X[i, c] *= inv
            X[i, i] = inv
        O = out[b, n]
        O[:, :] = 0.0
        for k in range(d):  # X^T X = sum_k (row k of X)^T (row k of X): the lower triangle
            for r in range(k + 1):
                f = X[k, r]
                for c in range(r + 1):
                    O[r, c] += f * X[k, c]
        for r in range(d):
            for c in range(r):
                O[c, r] = O[r, c]
