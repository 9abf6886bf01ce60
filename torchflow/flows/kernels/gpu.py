"""The Triton kernel of :mod:`torchflow.flows.kernels.steps` (imported only when it is used: Triton is an
optional dependency)."""

import triton
import triton.language as tl

# One particle per thread. Tiles put the particle axis last: ``[BK, BP]`` for a k-vector of BP
# particles and ``[BK, BK, BP]`` for their k x k matrices. Triton's default layout gives each thread
# whole matrices (the threads run along the last axis), so the Cholesky factors, solves and products
# below are sums over axes held in one thread's registers: no shuffles between threads, no shared
# memory. Loads and stores go through flat views (:func:`_ld`) to keep that layout, and selections
# by a constant index fold away in the compiled code (in-thread, each register's index is known).
# Compiled for sm_90 with Triton 3.6, both kernels use no shuffles between threads and spill some
# registers to local memory, ``kernel_info`` more than ``kernel_rows``; ``kernel_info`` is the
# default all the same, since it reads no ``L_s`` per row of W (register and spill counts:
# ``experiments/benchmarks/kernel_registers.py``; timings: ``experiments/benchmarks/bench_gpu.py``). Tiles
# loaded as ``[BK, BP]`` with J and J L_s kept spilled far more and shuffled between threads.


@triton.jit
def _pick(v, rk, i):
    """Entry ``i`` of each particle's k-vector ``v [BK, BP]``: ``[BP]``."""
    return tl.sum(tl.where(rk[:, None] == i, v, 0.0), axis=0)


@triton.jit
def _put(v, rk, i, x):
    """``v`` with entry ``i`` set to ``x [BP]``."""
    return tl.where(rk[:, None] == i, x[None, :], v)


@triton.jit
def _col(M, rk, j):
    """Column ``j`` of each particle's ``M [BK, BK, BP]``: ``[BK, BP]``."""
    return tl.sum(tl.where(rk[None, :, None] == j, M, 0.0), axis=1)


@triton.jit
def _row(M, rk, i):
    """Row ``i`` of each particle's ``M [BK, BK, BP]``: ``[BK, BP]``."""
    return tl.sum(tl.where(rk[:, None, None] == i, M, 0.0), axis=0)


@triton.jit
def _mv(M, v):
    """``M v`` for each particle: ``[BK, BK, BP] x [BK, BP] -> [BK, BP]``."""
    return tl.sum(M * v[None, :, :], axis=1)


@triton.jit
def _chol_t(M, rk, BK: tl.constexpr):
    """Lower Cholesky factors of each particle's ``M [BK, BK, BP]`` (lower triangle read)."""
    K = tl.zeros_like(M)
    for j in tl.static_range(BK):
        v = _col(M, rk, j) - _mv(K, _row(K, rk, j))  # a_r - sum_c K[r, c] K[j, c]
        djj = tl.sqrt(_pick(v, rk, j))
        K = tl.where(rk[None, :, None] == j, tl.where(rk[:, None] >= j, v / djj[None, :], 0.0)[:, None, :], K)
    return K


@triton.jit
def _solve_t(K, t, rk, BK: tl.constexpr):
    """``(K K^T)^{-1} t`` for each particle (``K [BK, BK, BP]`` lower, ``t [BK, BP]``)."""
    z = tl.zeros_like(t)
    for i in tl.static_range(BK):
        krow = _row(K, rk, i)
        z = _put(z, rk, i, (_pick(t, rk, i) - tl.sum(krow * z, axis=0)) / _pick(krow, rk, i))
    x = tl.zeros_like(t)
    for ii in tl.static_range(BK):
        i = BK - 1 - ii
        kcol = _col(K, rk, i)
        x = _put(x, rk, i, (_pick(z, rk, i) - tl.sum(kcol * x, axis=0)) / _pick(kcol, rk, i))
    return x


@triton.jit
def _mv_sym(S, v, rk):
    """``S v`` for each particle's symmetric ``S`` given by its lower triangle ``[BK, BK, BP]``."""
    diag = tl.sum(tl.where(rk[:, None, None] == rk[None, :, None], S, 0.0), axis=1)
    return tl.sum(S * v[None, :, :], axis=1) + tl.sum(S * v[:, None, :], axis=0) - diag * v


@triton.jit
def _ld(ptrs, mask, R: tl.constexpr, BP: tl.constexpr, DT: tl.constexpr):
    """A ``[R, BP]`` tile (in the compute dtype ``DT``) loaded through a flat view: each thread keeps its particle's R
    values. (Loaded as ``[R, BP]``, Triton's coalescing spreads R over the threads, and every
    reduction over R then shuffles between them.)"""
    ptrs = tl.broadcast_to(ptrs, (R, BP))
    mask = tl.broadcast_to(mask, (R, BP))
    v = tl.load(tl.reshape(ptrs, (R * BP,)), mask=tl.reshape(mask, (R * BP,)), other=0.0)
    return tl.reshape(v, (R, BP)).to(DT)


@triton.jit
def _st(ptrs, v, mask, R: tl.constexpr, BP: tl.constexpr):
    """Store a ``[R, BP]`` tile through a flat view (see :func:`_ld`)."""
    ptrs = tl.broadcast_to(ptrs, (R, BP))
    mask = tl.broadcast_to(mask, (R, BP))
    tl.store(
        tl.reshape(ptrs, (R * BP,)),
        tl.reshape(v, (R * BP,)).to(ptrs.dtype.element_ty),
        mask=tl.reshape(mask, (R * BP,)),
    )


@triton.jit
def _w_row(
    wrow,
    yrow,
    SENS,
    i,
    sWm,
    sYm,
    m2,
    pm,
    rk,
    aux_s,
    psi,
    d0,
    LIN: tl.constexpr,
    BK: tl.constexpr,
    BP: tl.constexpr,
    DT: tl.constexpr,
    TINY: tl.constexpr,
):
    """Row ``i`` of W ``[BK, BP]`` and entry ``i`` of y ``[BP]``: read from memory (``LIN = 0``), or
    computed at the points ``aux_s`` (``LIN = 1``, see :func:`kernel_rows`)."""
    yi = tl.load(yrow + i * sYm, mask=pm, other=0.0).to(DT)
    if LIN == 1:
        s_i = tl.load(SENS + 2 * i + (rk % 2)).to(DT)  # [BK]: the sensor's x, y per coordinate
        D = aux_s - s_i[:, None]
        pair = (rk[:, None] // 2) == (rk[None, :] // 2)  # coordinates of the same target
        r = tl.sqrt(tl.sum(tl.where(pair[:, :, None], (D * D)[None, :, :], 0.0), axis=1))  # the target's range
        inv = 1.0 / (r + d0)
        w = tl.where(m2, (-psi) * inv * inv / tl.maximum(r, TINY) * D, 0.0)
        first = (rk % 2) == 0
        yi = yi - psi * tl.sum(tl.where(first[:, None] & m2, inv, 0.0), axis=0) + tl.sum(w * aux_s, axis=0)
    else:
        w = _ld(wrow + i * sWm, m2, BK, BP, DT)
    return w, yi


@triton.jit
def _setup(
    W,
    sWb,
    sWn,
    sWk,
    Y,
    sYb,
    sYn,
    SUP,
    AUX,
    sEb,
    sEn,
    sEd,
    LAMS,
    EPSS,
    j,
    CONST,
    BN,
    N,
    d,
    k,
    BK: tl.constexpr,
    BD: tl.constexpr,
    BP: tl.constexpr,
    DT: tl.constexpr,
):
    """What both kernels' pseudo-steps start from: the program's particles ``p [BP]`` (trial ``b``,
    particle ``n``, mask ``pm``), the ranges and masks of the k- and d-axes, the step's ``lam`` and
    ``eps``, the support, the lower-triangle mask, the particles' points at the support ``aux_s
    [BK, BP]`` (and their offsets ``es``), the rows' base pointers of W and y and the measurement's
    constants."""
    p = tl.program_id(0) * BP + tl.arange(0, BP)
    pm = p < BN
    b = p // N
    n = p % N
    rk, rd = tl.arange(0, BK), tl.arange(0, BD)
    mk, md = rk < k, rd < d
    lam = tl.load(LAMS + j).to(DT)
    eps = tl.load(EPSS + j).to(DT)
    m2 = mk[:, None] & pm[None, :]
    md2 = md[:, None] & pm[None, :]
    sup = tl.load(SUP + rk, mask=mk, other=0)
    tri = (rk[:, None] >= rk[None, :])[:, :, None]  # lower triangles
    es = b[None, :] * sEb + n[None, :] * sEn + sup[:, None] * sEd
    aux_s = _ld(AUX + es, m2, BK, BP, DT)
    wrow = W + b[None, :] * sWb + n[None, :] * sWn + rk[:, None] * sWk
    yrow = Y + b * sYb + n * sYn
    psi = tl.load(CONST).to(DT)
    d0 = tl.load(CONST + 1).to(DT)
    return p, pm, b, n, rk, rd, lam, eps, m2, md2, sup, tri, es, aux_s, wrow, yrow, psi, d0


@triton.jit(do_not_specialize=["j"])
def kernel_rows(
    W,
    sWb,
    sWn,
    sWm,
    sWk,
    Y,
    sYb,
    sYn,
    sYm,
    Lp,
    sLb,
    sLn,
    sLd,
    sLk,
    LS,
    sSb,
    sSn,
    sSi,
    sSj,
    PC,
    sPb,
    sPn,
    sPd,
    sPk,
    MEAN,
    sMb,
    sMn,
    sMd,
    SUP,
    ETA,
    AUX,
    sEb,
    sEn,
    sEd,
    ETA_OUT,
    AUX_OUT,
    LOGDET,
    LAMS,
    EPSS,
    j,
    SENS,
    CONST,
    BN,
    N,
    m,
    d,
    k,
    BK: tl.constexpr,
    BD: tl.constexpr,
    BP: tl.constexpr,
    LIN: tl.constexpr,
    DT: tl.constexpr,
    TINY: tl.constexpr,
):
    """One pseudo-step for BP particles, one per thread. With ``Q = I + lam S``, ``V = W L_s``,
    ``S = V^T V`` and ``t(v) = L_s^T W^T W v_s = sum_i V_i (W_i . v_s)`` over the rows i,
    ``A v = -1/2 L Q^{-1} t(v)``; since the rows ``support`` of L are ``L_s``,
    ``t(A v) = -1/2 S Q^{-1} t(v)``, so the four applications of A of the unfused step need three
    solves with Q: ``q1 = Q^{-1} t(lam Pg + mean)``, ``q2 = Q^{-1} (t(Pg) - S q1 / 2)``,
    ``q_x = Q^{-1} t(x)``, and ``x <- x + eps (Pg - L (q_x / 2 + q1 / 2 + lam q2))`` for x the
    particle and its point. Two passes over the rows of W (``W^T y`` first, since ``Pg = P_s W^T y``
    enters ``t``); only lower triangles of S and of the factors are kept (registers).

    ``LIN = 0``: the rows of W and y are read from memory. ``LIN = 1``: they are computed here, at
    the points, for a measurement ``h_i = Psi sum_c 1 / (|p_c - s_i| + d0)`` over 2-D positions
    ``p_c`` (support coordinates ``2c, 2c + 1``) and sensors ``s_i`` (``SENS (m, 2)``), whitened
    by a scalar ``1 / sigma``: ``CONST = [Psi / sigma, d0]`` and ``Y`` holds ``z / sigma``
    (acoustic tracking; :func:`torchflow.flows.kernels.steps.dh_particle_step`)."""
    p, pm, b, n, rk, rd, lam, eps, m2, md2, sup, tri, es, aux_s, wrow, yrow, psi, d0 = _setup(
        W, sWb, sWn, sWk, Y, sYb, sYn, SUP, AUX, sEb, sEn, sEd, LAMS, EPSS, j, CONST, BN, N, d, k, BK, BD, BP, DT
    )
    # pass 1: W^T y, then Pg at the measured coordinates
    Wy = tl.zeros((BK, BP), dtype=DT)
    for i in range(m):
        w, yi = _w_row(wrow, yrow, SENS, i, sWm, sYm, m2, pm, rk, aux_s, psi, d0, LIN, BK, BP, DT, TINY)
        Wy += w * yi[None, :]
    pbase = PC + b[None, :] * sPb + n[None, :] * sPn
    Pg_s = tl.zeros((BK, BP), dtype=DT)
    for c in tl.static_range(BK):
        Pg_s += _ld(pbase + sup[:, None] * sPd + c * sPk, m2 & (c < k), BK, BP, DT) * _pick(Wy, rk, c)[None, :]
    mean_s = _ld(MEAN + b[None, :] * sMb + n[None, :] * sMn + sup[:, None] * sMd, m2, BK, BP, DT)
    x1_s = lam * Pg_s + mean_s
    eta_s = _ld(ETA + es, m2, BK, BP, DT)
    # pass 2: S = V^T V (lower triangle) and t(v) for v = lam Pg + mean, Pg, the particle, its point
    lsrow = LS + b[None, :] * sSb + n[None, :] * sSn + rk[:, None] * sSj
    S = tl.zeros((BK, BK, BP), dtype=DT)
    t1 = tl.zeros((BK, BP), dtype=DT)
    tp = tl.zeros((BK, BP), dtype=DT)
    te = tl.zeros((BK, BP), dtype=DT)
    ta = tl.zeros((BK, BP), dtype=DT)
    for i in range(m):
        w, yi = _w_row(wrow, yrow, SENS, i, sWm, sYm, m2, pm, rk, aux_s, psi, d0, LIN, BK, BP, DT, TINY)
        v = tl.zeros((BK, BP), dtype=DT)
        for e in tl.static_range(BK):  # v = L_s^T w, a row of the lower triangular L_s at a time
            ls = _ld(lsrow + e * sSi, m2 & (e < k), BK, BP, DT)
            v += tl.where(rk[:, None] <= e, ls, 0.0) * _pick(w, rk, e)[None, :]
        S += tl.where(tri, v[:, None, :] * v[None, :, :], 0.0)
        t1 += v * tl.sum(w * x1_s, axis=0)[None, :]
        tp += v * tl.sum(w * Pg_s, axis=0)[None, :]
        te += v * tl.sum(w * eta_s, axis=0)[None, :]
        ta += v * tl.sum(w * aux_s, axis=0)[None, :]
    eye = tl.where(rk[:, None, None] == rk[None, :, None], 1.0, 0.0).to(DT)
    K2 = _chol_t(eye + (lam - 0.5 * eps) * S, rk, BK)
    logdet = tl.zeros((BP,), dtype=DT)
    for c in tl.static_range(BK):
        logdet += tl.log(_pick(_row(K2, rk, c), rk, c))  # padded diagonal entries are 1
    K1 = _chol_t(eye + lam * S, rk, BK)
    for c in tl.static_range(BK):
        logdet -= tl.log(_pick(_row(K1, rk, c), rk, c))
    q1 = _solve_t(K1, t1, rk, BK)
    q2 = _solve_t(K1, tp - 0.5 * _mv_sym(S, q1, rk), rk, BK)
    qe = _solve_t(K1, te, rk, BK)
    qa = _solve_t(K1, ta, rk, BK)
    re = 0.5 * (qe + q1) + lam * q2
    ra = 0.5 * (qa + q1) + lam * q2
    lcol = Lp + b[None, :] * sLb + n[None, :] * sLn + rd[:, None] * sLd
    Pg = tl.zeros((BD, BP), dtype=DT)  # P H^T R^{-1} (z - e) = P_cols W^T y
    Le = tl.zeros((BD, BP), dtype=DT)
    La = tl.zeros((BD, BP), dtype=DT)
    for c in tl.static_range(BK):
        Pg += _ld(pbase + rd[:, None] * sPd + c * sPk, md2 & (c < k), BD, BP, DT) * _pick(Wy, rk, c)[None, :]
        lc = _ld(lcol + c * sLk, md2 & (c < k), BD, BP, DT)
        Le += lc * _pick(re, rk, c)[None, :]
        La += lc * _pick(ra, rk, c)[None, :]
    ed = b[None, :] * sEb + n[None, :] * sEn + rd[:, None] * sEd
    eta = _ld(ETA + ed, md2, BD, BP, DT)
    aux = _ld(AUX + ed, md2, BD, BP, DT)
    out = p[None, :] * d + rd[:, None]
    _st(ETA_OUT + out, eta + eps * (Pg - Le), md2, BD, BP)
    _st(AUX_OUT + out, aux + eps * (Pg - La), md2, BD, BP)
    old = tl.load(LOGDET + p, mask=pm, other=0.0)
    tl.store(LOGDET + p, (old.to(DT) + 2.0 * logdet).to(LOGDET.dtype.element_ty), mask=pm)


@triton.jit
def _sym_tile(base, sI, sJ, m2, k, rk, tri, BK: tl.constexpr, BP: tl.constexpr, DT: tl.constexpr):
    """The lower triangle of each particle's symmetric ``k x k`` matrix at ``base [1, BP]``
    (row stride ``sI``, column stride ``sJ``), as ``[BK, BK, BP]``; zero elsewhere."""
    M = tl.zeros((BK, BK, BP), dtype=DT)
    for c in tl.static_range(BK):
        col = _ld(base + rk[:, None] * sI + c * sJ, m2 & (c < k), BK, BP, DT)
        M = tl.where((rk[None, :, None] == c) & tri, col[:, None, :], M)
    return M


@triton.jit(do_not_specialize=["j"])
def kernel_info(
    W,
    sWb,
    sWn,
    sWm,
    sWk,
    Y,
    sYb,
    sYn,
    sYm,
    C,
    sCb,
    sCn,
    sCd,
    sCk,
    PI,
    sIb,
    sIn,
    sIi,
    sIj,
    PC,
    sPb,
    sPn,
    sPd,
    sPk,
    MEAN,
    sMb,
    sMn,
    sMd,
    SUP,
    ETA,
    AUX,
    sEb,
    sEn,
    sEd,
    ETA_OUT,
    AUX_OUT,
    LOGDET,
    LAMS,
    EPSS,
    j,
    SENS,
    CONST,
    BN,
    N,
    m,
    d,
    k,
    BK: tl.constexpr,
    BD: tl.constexpr,
    BP: tl.constexpr,
    LIN: tl.constexpr,
    DT: tl.constexpr,
    TINY: tl.constexpr,
):
    """The pseudo-step of :func:`kernel_rows` in information form, one pass over the rows of W.
    With ``G = W^T W`` (the point's whitened information, accumulated row by row: no ``L_s`` read
    per row), ``P_s = L_s L_s^T``, the prior precision ``Pi = P_s^{-1}`` and ``C = L L_s^{-1}``
    (``C``, ``Pi`` formed once per integration, :func:`torchflow.flows.kernels.steps.info_factors`):
    ``L (I + lam S)^{-1} L_s^T = C M^{-1}`` with ``M = Pi + lam G`` (push-through), so
    ``A v = -1/2 C M^{-1} G v_s`` and, with ``g = P_s W^T y`` (so ``P H^T R^{-1} (z - e) = C g``),
    ``x <- x + eps C (g - s_x)``, ``s_x = M^{-1} (G x_s / 2 + a)``, ``a = r_1 / 2 + lam (G g -
    G q_1 / 2)``, ``q_1 = M^{-1} r_1``, ``r_1 = G (lam g + mean_s)``: three solves with M's factor.
    ``log det (I + eps A) = log det (Pi + (lam - eps/2) G) - log det M`` (the ``log det P_s`` of
    each cancels). Registers hold G, not S and four k-vectors of sums, and ``L_s`` is not read."""
    p, pm, b, n, rk, rd, lam, eps, m2, md2, sup, tri, es, aux_s, wrow, yrow, psi, d0 = _setup(
        W, sWb, sWn, sWk, Y, sYb, sYn, SUP, AUX, sEb, sEn, sEd, LAMS, EPSS, j, CONST, BN, N, d, k, BK, BD, BP, DT
    )
    G = tl.zeros((BK, BK, BP), dtype=DT)
    Wy = tl.zeros((BK, BP), dtype=DT)
    for i in range(m):
        w, yi = _w_row(wrow, yrow, SENS, i, sWm, sYm, m2, pm, rk, aux_s, psi, d0, LIN, BK, BP, DT, TINY)
        Wy += w * yi[None, :]
        G += tl.where(tri, w[:, None, :] * w[None, :, :], 0.0)
    pbase = PC + b[None, :] * sPb + n[None, :] * sPn
    g = tl.zeros((BK, BP), dtype=DT)  # P_s W^T y
    for c in tl.static_range(BK):
        g += _ld(pbase + sup[:, None] * sPd + c * sPk, m2 & (c < k), BK, BP, DT) * _pick(Wy, rk, c)[None, :]
    Pi = _sym_tile(PI + b[None, :] * sIb + n[None, :] * sIn, sIi, sIj, m2, k, rk, tri, BK, BP, DT)
    pad = tl.where((rk[:, None, None] == rk[None, :, None]) & (rk[:, None, None] >= k), 1.0, 0.0).to(DT)
    K = _chol_t(Pi + (lam - 0.5 * eps) * G + pad, rk, BK)
    logdet = tl.zeros((BP,), dtype=DT)
    for c in tl.static_range(BK):
        logdet += tl.log(_pick(_row(K, rk, c), rk, c))  # padded diagonal entries are 1
    K = _chol_t(Pi + lam * G + pad, rk, BK)
    for c in tl.static_range(BK):
        logdet -= tl.log(_pick(_row(K, rk, c), rk, c))
    mean_s = _ld(MEAN + b[None, :] * sMb + n[None, :] * sMn + sup[:, None] * sMd, m2, BK, BP, DT)
    Gg = _mv_sym(G, g, rk)
    r1 = lam * Gg + _mv_sym(G, mean_s, rk)
    q1 = _solve_t(K, r1, rk, BK)
    a = 0.5 * r1 + lam * (Gg - 0.5 * _mv_sym(G, q1, rk))
    eta_s = _ld(ETA + es, m2, BK, BP, DT)
    ue = g - _solve_t(K, 0.5 * _mv_sym(G, eta_s, rk) + a, rk, BK)
    ua = g - _solve_t(K, 0.5 * _mv_sym(G, aux_s, rk) + a, rk, BK)
    ccol = C + b[None, :] * sCb + n[None, :] * sCn + rd[:, None] * sCd
    Ce = tl.zeros((BD, BP), dtype=DT)
    Ca = tl.zeros((BD, BP), dtype=DT)
    for c in tl.static_range(BK):
        cc = _ld(ccol + c * sCk, md2 & (c < k), BD, BP, DT)
        Ce += cc * _pick(ue, rk, c)[None, :]
        Ca += cc * _pick(ua, rk, c)[None, :]
    ed = b[None, :] * sEb + n[None, :] * sEn + rd[:, None] * sEd
    eta = _ld(ETA + ed, md2, BD, BP, DT)
    aux = _ld(AUX + ed, md2, BD, BP, DT)
    out = p[None, :] * d + rd[:, None]
    _st(ETA_OUT + out, eta + eps * Ce, md2, BD, BP)
    _st(AUX_OUT + out, aux + eps * Ca, md2, BD, BP)
    old = tl.load(LOGDET + p, mask=pm, other=0.0)
    tl.store(LOGDET + p, (old.to(DT) + 2.0 * logdet).to(LOGDET.dtype.element_ty), mask=pm)
