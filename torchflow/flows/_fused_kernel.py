"""The Triton kernel of :mod:`torchflow.flows.fused` (imported only when it is used: Triton is an
optional dependency)."""
import triton
import triton.language as tl


@triton.jit
def _chol(M, rk, BK: tl.constexpr):
    """Lower Cholesky factor of the ``[BK, BK]`` tile M (left-looking, column by column)."""
    K = tl.zeros_like(M)
    for j in tl.static_range(BK):
        a = tl.sum(tl.where(rk[None, :] == j, M, 0.0), axis=1)  # column j of M
        krow = tl.sum(tl.where(rk[:, None] == j, K, 0.0), axis=0)  # row j of K (columns < j set)
        v = a - tl.sum(K * krow[None, :], axis=1)
        djj = tl.sqrt(tl.sum(tl.where(rk == j, v, 0.0), axis=0))
        K = tl.where(rk[None, :] == j, tl.where(rk >= j, v / djj, 0.0)[:, None], K)
    return K


@triton.jit
def _solve_llt(K, t, rk, BK: tl.constexpr):
    """``(K K^T)^{-1} t``: forward then backward substitution."""
    z = tl.zeros_like(t)
    for i in tl.static_range(BK):
        krow = tl.sum(tl.where(rk[:, None] == i, K, 0.0), axis=0)
        kii = tl.sum(tl.where(rk == i, krow, 0.0), axis=0)
        ti = tl.sum(tl.where(rk == i, t, 0.0), axis=0)
        z = tl.where(rk == i, (ti - tl.sum(krow * z, axis=0)) / kii, z)
    x = tl.zeros_like(t)
    for ii in tl.static_range(BK):
        i = BK - 1 - ii
        kcol = tl.sum(tl.where(rk[None, :] == i, K, 0.0), axis=1)
        kii = tl.sum(tl.where(rk == i, kcol, 0.0), axis=0)
        zi = tl.sum(tl.where(rk == i, z, 0.0), axis=0)
        x = tl.where(rk == i, (zi - tl.sum(kcol * x, axis=0)) / kii, x)
    return x


@triton.jit
def _apply_a(T, K, L, v, sup, rd, rk, BK: tl.constexpr):
    """``A v = -1/2 L (K K^T)^{-1} T v_s`` for a state vector v ``[BD]``."""
    vs = tl.sum(tl.where(rd[None, :] == sup[:, None], v[None, :], 0.0), axis=1)  # v at the support
    x = _solve_llt(K, tl.sum(T * vs[None, :], axis=1), rk, BK)
    return -0.5 * tl.sum(L * x[None, :], axis=1)


@triton.jit(do_not_specialize=["j"])
def kernel(W, sWb, sWn, sWm, sWk, Y, sYb, sYn, sYm, Lp, sLb, sLn, sLd, sLk, LS, sSb, sSn, sSi, sSj,
           PC, sPb, sPn, sPd, sPk, MEAN, sMb, sMn, sMd, SUP, ETA, AUX, sEb, sEn, sEd, ETA_OUT, AUX_OUT,
           LOGDET, LAMS, EPSS, j, N, m, d, k, BM: tl.constexpr, BK: tl.constexpr, BD: tl.constexpr):
    p = tl.program_id(0)
    b = p // N
    n = p % N
    rm, rk, rd = tl.arange(0, BM), tl.arange(0, BK), tl.arange(0, BD)
    mm, mk, md = rm < m, rk < k, rd < d
    lam = tl.load(LAMS + j).to(tl.float64)
    eps = tl.load(EPSS + j).to(tl.float64)
    Wt = tl.load(W + b * sWb + n * sWn + rm[:, None] * sWm + rk[None, :] * sWk, mask=mm[:, None] & mk[None, :],
                 other=0.0).to(tl.float64)
    y = tl.load(Y + b * sYb + n * sYn + rm * sYm, mask=mm, other=0.0).to(tl.float64)
    L = tl.load(Lp + b * sLb + n * sLn + rd[:, None] * sLd + rk[None, :] * sLk, mask=md[:, None] & mk[None, :],
                other=0.0).to(tl.float64)
    Ls = tl.load(LS + b * sSb + n * sSn + rk[:, None] * sSi + rk[None, :] * sSj, mask=mk[:, None] & mk[None, :],
                 other=0.0).to(tl.float64)
    Pc = tl.load(PC + b * sPb + n * sPn + rd[:, None] * sPd + rk[None, :] * sPk, mask=md[:, None] & mk[None, :],
                 other=0.0).to(tl.float64)
    mean = tl.load(MEAN + b * sMb + n * sMn + rd * sMd, mask=md, other=0.0).to(tl.float64)
    sup = tl.load(SUP + rk, mask=mk, other=-1)
    base = b * sEb + n * sEn
    eta = tl.load(ETA + base + rd * sEd, mask=md, other=0.0).to(tl.float64)
    aux = tl.load(AUX + base + rd * sEd, mask=md, other=0.0).to(tl.float64)
    # S = L_s^T J L_s, J = W^T W; T = L_s^T J; W^T y
    J = tl.sum(Wt[:, :, None] * Wt[:, None, :], axis=0)
    Wy = tl.sum(Wt * y[:, None], axis=0)
    T = tl.sum(Ls[:, :, None] * J[:, None, :], axis=0)
    S = tl.sum(T[:, :, None] * Ls[None, :, :], axis=1)
    S = 0.5 * (S + tl.trans(S))
    eye = tl.where(rk[:, None] == rk[None, :], 1.0, 0.0).to(tl.float64)
    K1 = _chol(eye + lam * S, rk, BK)
    K2 = _chol(eye + (lam - 0.5 * eps) * S, rk, BK)
    d1 = tl.sum(tl.where(rk[:, None] == rk[None, :], K1, 0.0), axis=1)
    d2 = tl.sum(tl.where(rk[:, None] == rk[None, :], K2, 0.0), axis=1)
    logdet = 2.0 * tl.sum(tl.log(d2) - tl.log(d1), axis=0)  # padded diagonal entries are 1
    Pg = tl.sum(Pc * Wy[None, :], axis=1)  # P H^T R^{-1} (z - e)
    u = Pg + _apply_a(T, K1, L, lam * Pg + mean, sup, rd, rk, BK)
    bvec = u + 2.0 * lam * _apply_a(T, K1, L, u, sup, rd, rk, BK)
    eta_new = eta + eps * (_apply_a(T, K1, L, eta, sup, rd, rk, BK) + bvec)
    aux_new = aux + eps * (_apply_a(T, K1, L, aux, sup, rd, rk, BK) + bvec)
    tl.store(ETA_OUT + p * d + rd, eta_new.to(ETA_OUT.dtype.element_ty), mask=md)
    tl.store(AUX_OUT + p * d + rd, aux_new.to(AUX_OUT.dtype.element_ty), mask=md)
    old = tl.load(LOGDET + p)
    tl.store(LOGDET + p, (old.to(tl.float64) + logdet).to(LOGDET.dtype.element_ty))
