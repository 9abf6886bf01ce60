"""Batched linear algebra used by every filter: Cholesky with jitter, solves, log-dets, MVN log-pdf.

All functions take arbitrary leading batch dimensions ``(..., d, d)``. No matrix inverse is ever
formed: solves go through Cholesky factors.
"""

from __future__ import annotations

import math
from typing import Optional, Tuple

import numpy as np
import torch

from torchflow.core import tuning
from torchflow.core.random import TrialStreams, fill_numpy, thread_pool

_LOG_2PI = math.log(2.0 * math.pi)


def symmetrize(A: torch.Tensor) -> torch.Tensor:
    """Return ``(A + A^T) / 2`` for ``A (..., d, d)``."""
    return 0.5 * (A + A.transpose(-1, -2))


#: the batched jitter ladder's slots are at least this many (every matrix of a smaller batch has one)
LADDER_MIN_SLOTS = 4096


def cholesky_or_nan(A: torch.Tensor) -> torch.Tensor:
    """The lower Cholesky factor of ``A (..., n, n)``, NaN where it fails, with no host read and
    no jitter: for matrices definite by construction (``c I + Y Y^T``) that fail only when their
    inputs are not finite. The NaN then reaches a filter's estimates and its non-finite check names
    the filter, step and trials, instead of a raw ``LinAlgError``. (:func:`safe_cholesky`: for
    matrices that may be singular.)"""
    L, info = torch.linalg.cholesky_ex(A)
    return torch.where((info > 0)[..., None, None], torch.full_like(L, math.nan), L)


def safe_cholesky(A: torch.Tensor, *, max_tries: int = 6) -> torch.Tensor:
    """Lower Cholesky factor of ``A (..., d, d)``, adding diagonal jitter where it fails.

    Matrices that factor cleanly are untouched. A matrix that does not gets the smallest jitter
    ``eps * 10^k * mean(diag)`` (k = 0 .. ``max_tries`` - 1, ``eps`` the dtype's machine epsilon
    times 10) under which it factors; the ladder is factored in one batched call
    ``(max_tries, c, d, d)`` for the failed matrices gathered into ``c`` slots.

    On a CUDA tensor that call is always made, so that no host read asks whether anything failed
    (a read would stall the queue). A batch of ``n`` matrices then has
    ``c = max(min(n, LADDER_MIN_SLOTS), ceil(n / divisor))`` slots (``torchflow.core.tuning``
    ``jitter_ladder_divisor``, default 16; 1: a slot per matrix), so a large batch pays
    ``max_tries / divisor`` factorisations for the ladder instead of ``max_tries``. Failed matrices
    beyond the slots (more than ``c`` in one call: a structurally singular covariance, say) take the
    ladder's largest jitter in one more factorisation of the batch, which a large batch always makes.
    On the CPU the failure flags are read first and the ladder runs only when one failed, with a
    slot per failed matrix (``batched_jitter_cpu=1``: as on CUDA). The factor is the same either
    way, but for the failed matrices beyond the slots.

    A matrix that fails every jitter gets a NaN factor: a filter's non-finite path then names the
    filter, step and trial (outside a filter, check the result with ``torch.isfinite``).
    """
    L, info = torch.linalg.cholesky_ex(A)
    failed = info > 0
    d = A.shape[-1]
    n = failed.numel()
    if A.device.type != "cuda" and not tuning.get().batched_jitter_cpu:
        n_failed = int(failed.sum())  # the CPU: a host read costs nothing, the ladder max_tries factorisations
        if not n_failed:
            return L
        slots = n_failed
    else:
        slots = max(min(n, LADDER_MIN_SLOTS), -(-n // max(1, tuning.get().jitter_ladder_divisor)))
    flat, A_f = failed.reshape(-1), A.reshape(n, d, d)
    base = 10.0 * torch.finfo(A.dtype).eps
    # a zero matrix (a known state) gets jitters from the smallest normal number up: a subnormal
    # jitter does not factor (float32: NaN factor of a valid zero prior)
    scale = A_f.diagonal(dim1=-2, dim2=-1).abs().mean(-1).clamp_min(torch.finfo(A.dtype).tiny / base)  # (n,)
    eye = torch.eye(d, dtype=A.dtype, device=A.device)
    ladder = _jitter_ladder(base, max_tries, A.dtype, A.device)
    if slots < n:  # gather the failed matrices (in batch order) into the slots; empty slots point at n
        pos = torch.cumsum(flat, 0) - 1
        target = torch.where(flat & (pos < slots), pos, slots)
        idx = torch.full((slots + 1,), n, dtype=torch.long, device=A.device)
        idx.scatter_(0, target, torch.arange(n, device=A.device))
        idx = idx[:slots]
        used, at = idx < n, idx.clamp_max(n - 1)
        A_s, scale_s = A_f.index_select(0, at), scale.index_select(0, at)
    else:
        idx, used, A_s, scale_s = None, flat, A_f, scale
    add = ladder[:, None] * torch.where(used, scale_s, torch.zeros_like(scale_s))
    L_j, info_j = torch.linalg.cholesky_ex(A_s.unsqueeze(0) + add[..., None, None] * eye)
    ok = info_j == 0  # (max_tries, slots)
    first = torch.argmax(ok.to(torch.uint8), dim=0)  # the first jitter that factors (0 when none does)
    L_first = torch.take_along_dim(L_j, first[None, :, None, None], dim=0)[0]
    L_first = torch.where(ok.any(0)[:, None, None], L_first, torch.full_like(L_first, float("nan")))
    if idx is None:
        return torch.where(failed[..., None, None], L_first.reshape(L.shape), L)
    # beyond the slots: the largest jitter (the others get none: their factor is discarded)
    over = flat & (pos >= slots)
    top = ladder[-1] * torch.where(over, scale, torch.zeros_like(scale))
    L_top, info_top = torch.linalg.cholesky_ex(A_f + top[:, None, None] * eye)
    nan = torch.full((), float("nan"), dtype=L.dtype, device=L.device)
    out = torch.where(over[:, None, None], torch.where((info_top > 0)[:, None, None], nan, L_top), L.reshape(n, d, d))
    out = torch.cat([out, L.new_zeros(1, d, d)])
    out.index_copy_(0, torch.where(used, idx, n), L_first)  # empty slots write the spare last row
    return out[:n].reshape(L.shape)


def small_cholesky(A: torch.Tensor) -> torch.Tensor:
    """Lower Cholesky factor of symmetric positive definite ``A (..., k, k)`` by the column formulas
    in plain tensor ops (k columns, a few elementwise ops and one batched product each), for tiny k
    on a GPU, where batched LAPACK-style kernels can be slow (``micro_small_linalg``). Reads the lower
    triangle. No test of definiteness: a matrix that is not positive definite gives NaN."""
    k = A.shape[-1]
    L = torch.zeros_like(A)
    for j in range(k):
        v = A[..., j:, j]  # (..., k - j): the column on and below the diagonal
        if j:
            v = v - (L[..., j:, :j] @ L[..., j, :j].unsqueeze(-1)).squeeze(-1)
        diag = v[..., :1].sqrt()
        L[..., j:, j] = v / diag
    return L


def small_solve_lower(L: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """``L^{-1} B`` for lower triangular ``L (..., k, k)`` and ``B (..., k, r)`` by forward
    substitution in plain tensor ops (k rows); the GPU counterpart of :func:`small_cholesky`."""
    k = L.shape[-1]
    X = torch.zeros(torch.broadcast_shapes(L.shape[:-2], B.shape[:-2]) + B.shape[-2:], dtype=B.dtype, device=B.device)
    for i in range(k):
        r = B[..., i, :]
        if i:
            r = r - (L[..., i : i + 1, :i] @ X[..., :i, :]).squeeze(-2)
        X[..., i, :] = r / L[..., i, i : i + 1]
    return X


_LADDERS = {}
_INDICES = {}


def index_tensor(values, device) -> torch.Tensor:
    """The int64 tensor of the integers ``values`` on ``device``, made once per values and device:
    an index that a filter step uses (a model's measurement support) without copying it from the
    host at every step (on a GPU each such copy waits for the host, and a CUDA graph cannot capture
    one). Read-only: shared by every caller."""
    key = (tuple(int(v) for v in values), str(device))
    out = _INDICES.get(key)
    if out is None:
        out = _INDICES[key] = torch.tensor(key[0], dtype=torch.int64, device=device)
    return out


def _jitter_ladder(base: float, max_tries: int, dtype, device) -> torch.Tensor:
    """``base * 10^k``, k < ``max_tries``, from host values, made once per dtype and device (no copy
    to the device in a filter step: a CUDA graph cannot capture one)."""
    key = (base, max_tries, dtype, str(device))
    if key not in _LADDERS:
        _LADDERS[key] = torch.tensor([base * 10.0**k for k in range(max_tries)], dtype=dtype, device=device)
    return _LADDERS[key]


def solve_triangular(A: torch.Tensor, B: torch.Tensor, *, upper: bool, left: bool = True) -> torch.Tensor:
    """``torch.linalg.solve_triangular``, run with one intra-op thread for a CPU batch of small
    matrices (up to ``torchflow.core.tuning`` ``serial_solve_max_dim``: batched CPU solves loop over
    the batch calling MKL's trsm, which with several threads pays a parallel-region start per tiny
    matrix); otherwise unchanged."""
    if (
        A.device.type == "cpu"
        and A.dim() > 2
        and A.shape[-1] <= tuning.get().serial_solve_max_dim
        and A.shape[:-2].numel() > 1
    ):
        n = torch.get_num_threads()
        if n > 1:
            torch.set_num_threads(1)
            try:
                return torch.linalg.solve_triangular(A, B, upper=upper, left=left)
            finally:
                torch.set_num_threads(n)
    return torch.linalg.solve_triangular(A, B, upper=upper, left=left)


#: CPU float64 draws of at least this many numbers come from numpy's ziggurat sampler (SFC64
#: bit generator) seeded from the caller's torch.Generator; torch's own CPU float64 normal
#: sampler costs several times more per draw, which made the bootstrap PF RNG-bound. It decides
#: which numbers a torch.Generator draw gets, so it is part of the draw's definition, not a speed
#: knob (torchflow.core.tuning).
FAST_NORMAL_MIN = 1 << 12
#: numbers per independent stream of the fast sampler (large draws are filled block-parallel)
FAST_NORMAL_BLOCK = 1 << 19


def standard_normal(shape, *, dtype: torch.dtype, device, generator: Optional[torch.Generator] = None) -> torch.Tensor:
    """``N(0, 1)`` draws of ``shape``, all randomness from ``generator`` (torch's default if None).

    A :class:`~torchflow.core.random.TrialStreams` generator draws each trial's share (``shape[0]`` is
    trials, or a trial-major multiple of them) from that trial's own stream.

    Large float64 CPU draws (``>= FAST_NORMAL_MIN`` numbers) take one 62-bit seed
    from ``generator`` and fill the tensor with numpy's ziggurat normals (``np.random.SFC64``):
    exact float64 normals, cheaper per thread than ``torch.randn`` on the CPU, and the same seed
    gives the same numbers. Draws of more than ``FAST_NORMAL_BLOCK`` numbers use one stream per
    block (children of the seed's ``SeedSequence``), filled on up to ``torch.get_num_threads()``
    threads; the numbers do not depend on the thread count. Everything else (GPU, float32, small
    draws) is ``torch.randn``.
    """
    device = torch.device(device) if device is not None else torch.device("cpu")
    if isinstance(generator, TrialStreams):  # per-trial streams (leading dim: trials)
        return generator.normal(shape, dtype=dtype, device=device)
    n = math.prod(shape)
    if device.type == "cpu" and dtype == torch.float64 and n >= FAST_NORMAL_MIN:
        seed = int(torch.randint(0, 2**62, (), generator=generator))
        out = torch.empty(shape, dtype=dtype)
        flat = out.numpy().reshape(-1)
        blk = FAST_NORMAL_BLOCK
        seeds = [seed] if n <= blk else np.random.SeedSequence(seed).spawn(-(-n // blk))
        fill_numpy(
            "normal",
            [(np.random.Generator(np.random.SFC64(s)), flat[i * blk : (i + 1) * blk]) for i, s in enumerate(seeds)],
            np.float64,
        )
        return out
    return torch.randn(shape, dtype=dtype, device=device, generator=generator)


#: :func:`eigh` splits a CPU batch over threads from this many matrices on
THREADED_EIGH_MIN = 512


def eigh(A: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """``torch.linalg.eigh`` of a batch of symmetric matrices ``A (..., n, n)``: ``(eigenvalues
    (..., n), eigenvectors (..., n, n))``.

    torch solves a CPU batch one matrix after another on one thread. From
    :data:`THREADED_EIGH_MIN` matrices on, with ``torch.get_num_threads() > 1``, the batch is split
    into one contiguous part per thread (LAPACK releases the GIL): each matrix is solved by the same
    routine on its own, so the numbers are those of one call, whatever the thread count. GPU
    batches, small ones, tensors that record gradients and tensors under a ``torch.func`` transform
    take one call."""
    batch = math.prod(A.shape[:-2])
    workers = min(torch.get_num_threads(), batch // max(1, THREADED_EIGH_MIN // 2))
    if A.device.type != "cpu" or batch < THREADED_EIGH_MIN or workers < 2 or A.requires_grad or under_func_transform(A):
        return torch.linalg.eigh(A)
    flat = A.reshape(batch, *A.shape[-2:])
    parts = list(thread_pool(workers).map(torch.linalg.eigh, flat.tensor_split(workers)))
    lam = torch.cat([p[0] for p in parts]).reshape(*A.shape[:-1])
    vec = torch.cat([p[1] for p in parts]).reshape(A.shape)
    return lam, vec


def under_func_transform(x: torch.Tensor) -> bool:
    """Whether ``x`` is wrapped by a ``torch.func`` transform (vmap, grad, jvp): what may not be
    read back or split over threads (where torch cannot say, ``True``)."""
    check = getattr(torch._C._functorch, "is_functorch_wrapped_tensor", None)
    return bool(check(x)) if check is not None else True


def chol_solve(L: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """Solve ``(L L^T) X = B`` for ``X`` given lower ``L (..., d, d)`` and ``B (..., d, k)``.

    Two batched triangular solves, which on the CPU cost less than ``torch.cholesky_solve`` for
    large batches of small matrices. They are posed on the transposed system
    (``X^T (L L^T) = B^T``, right-hand solves) for a batch of matrices, whose result comes back in
    row-major layout, the layout later batched products read without a copy (left-hand solves
    return it column-major)."""
    if L.dim() == 2:  # one matrix: left-hand solves, the faster of the two here
        Y = torch.linalg.solve_triangular(L, B, upper=False)
        return torch.linalg.solve_triangular(L.transpose(-1, -2), Y, upper=True)
    Zt = solve_triangular(L.transpose(-1, -2), B.transpose(-1, -2), upper=True, left=False)
    return solve_triangular(L, Zt, upper=False, left=False).transpose(-1, -2)


def chol_logdet(L: torch.Tensor) -> torch.Tensor:
    """``log det(L L^T)`` for lower Cholesky factor ``L (..., d, d)`` -> ``(...)``."""
    return 2.0 * torch.log(L.diagonal(dim1=-2, dim2=-1)).sum(-1)


def mvn_log_prob(x: torch.Tensor, mean: torch.Tensor, scale_tril: torch.Tensor) -> torch.Tensor:
    """Log-density of ``N(mean, L L^T)`` at ``x``.

    Args:
        x: ``(..., d)`` points.
        mean: ``(..., d)`` broadcastable to ``x``.
        scale_tril: ``(..., d, d)`` lower Cholesky factor, broadcastable.

    Returns:
        ``(...)`` log-densities.
    """
    diff = x - mean
    d = diff.shape[-1]
    if scale_tril.dim() > 2 and scale_tril.shape[:-2].numel() == 1:
        scale_tril = scale_tril.reshape(d, d)
    if scale_tril.dim() == 2:
        # one shared factor: a single triangular solve with all points as right-hand sides
        flat = diff.reshape(-1, d)
        sol = torch.linalg.solve_triangular(scale_tril, flat.transpose(0, 1), upper=False).transpose(0, 1)
        sol = sol.reshape(diff.shape)
    elif scale_tril.dim() == diff.dim() + 1 and scale_tril.dim() >= 4 and scale_tril.shape[-3] == 1:
        # one factor per (...) shared by the N points diff (..., N, d): N right-hand sides
        shape = torch.broadcast_shapes(diff.shape[:-2], scale_tril.shape[:-3])
        L = scale_tril.squeeze(-3).expand(*shape, d, d)
        rhs = diff.expand(*shape, *diff.shape[-2:]).transpose(-1, -2)
        sol = solve_triangular(L, rhs, upper=False).transpose(-1, -2)
    else:
        shape = torch.broadcast_shapes(diff.shape[:-1], scale_tril.shape[:-2])
        diff = diff.expand(*shape, d)
        L = scale_tril.expand(*shape, d, d)
        sol = solve_triangular(L, diff.unsqueeze(-1), upper=False).squeeze(-1)
    return -0.5 * (sol.pow(2).sum(-1) + d * _LOG_2PI) - torch.log(scale_tril.diagonal(dim1=-2, dim2=-1)).sum(-1)


def matmul(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """``A @ B``; when both have the same batch dimensions (``(..., m, k) @ (..., k, p)``), one
    ``bmm`` over the flattened batch: the same kernel on the same memory as ``torch.matmul`` (so the
    same numbers), without its broadcasting ops (4 aten ops instead of 6-7; on a GPU each is a
    dispatch, and a flow calls this a few times per pseudo-time step)."""
    if A.dim() == B.dim() and A.dim() >= 4 and A.shape[:-2] == B.shape[:-2]:
        out = torch.bmm(A.reshape(-1, *A.shape[-2:]), B.reshape(-1, *B.shape[-2:]))
        return out.view(*A.shape[:-2], *out.shape[-2:])
    return A @ B


def matvec(A: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``A x`` for matrices ``A (m, d)`` or ``(..., m, d)`` and vectors ``x (..., d)`` -> ``(..., m)``.

    A single shared matrix (2-D, or batch of size one) is applied as one matrix product
    ``x @ A^T``, much faster than a batch of matrix-vector products. One matrix per vector (the same
    batch dimensions) is one ``bmm`` over the flattened batch (:func:`matmul`)."""
    if A.dim() > 2 and A.shape[:-2].numel() == 1:
        A = A.reshape(A.shape[-2:])
    if A.dim() == 2:
        return x @ A.transpose(0, 1)
    if A.dim() == x.dim() + 1 and A.dim() >= 4 and A.shape[-3] == 1 and x.shape[-2] > 1:
        # one matrix per (...) shared by the N vectors x (..., N, d): a batched matrix product
        return x @ A.squeeze(-3).transpose(-1, -2)
    if A.dim() == x.dim() + 1 and A.dim() >= 3 and A.shape[:-2] == x.shape[:-1]:
        out = torch.bmm(A.reshape(-1, *A.shape[-2:]), x.reshape(-1, x.shape[-1], 1))
        return out.view(*A.shape[:-1])
    return (A @ x.unsqueeze(-1)).squeeze(-1)


def sample_mvn(
    mean: torch.Tensor, scale_tril: torch.Tensor, sample_shape: Tuple[int, ...], generator=None
) -> torch.Tensor:
    """Draw ``mean + L xi`` with ``xi ~ N(0, I)``.

    Args:
        mean: ``(..., d)``.
        scale_tril: ``(..., d, d)`` broadcastable with ``mean``.
        sample_shape: extra dims inserted right after the leading batch dims of ``mean``'s first
            dim. Samples have shape ``(mean.shape[0], *sample_shape, d)`` when ``mean`` is ``(B, d)``.
        generator: ``torch.Generator`` or ``None``.
    """
    d = mean.shape[-1]
    B = mean.shape[:-1]
    xi = standard_normal((*B, *sample_shape, d), dtype=mean.dtype, device=mean.device, generator=generator)
    k = len(sample_shape)
    m = mean.reshape(*B, *([1] * k), d)
    if scale_tril.dim() > 2 and k == 1 and mean.dim() == 2:
        # (B, N, d) @ (B, d, d)^T: one batched matrix product instead of B*N matrix-vector products
        return torch.baddbmm(m, xi, scale_tril.expand(*B, d, d).transpose(-1, -2))
    L = scale_tril.reshape(*scale_tril.shape[:-2], *([1] * k), d, d) if scale_tril.dim() > 2 else scale_tril
    return m + matvec(L, xi)


def weighted_mean_cov(x: torch.Tensor, log_weights: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Weighted mean ``(B, d)`` and covariance ``(B, d, d)`` of particles ``x (B, N, d)``.

    ``log_weights (B, N)`` need not be normalised.
    """
    w = torch.softmax(log_weights, dim=-1)
    mean = torch.einsum("bn,bnd->bd", w, x)
    diff = x - mean.unsqueeze(1)
    cov = torch.einsum("bn,bni,bnj->bij", w, diff, diff)
    return mean, symmetrize(cov)


def block_diagonal(blocks: torch.Tensor) -> torch.Tensor:
    """``(..., n_b, b, b)`` diagonal blocks -> the ``(..., n_b b, n_b b)`` block-diagonal matrix."""
    nb, b = blocks.shape[-3], blocks.shape[-1]
    out = blocks.new_zeros(*blocks.shape[:-3], nb, b, nb, b)
    out.diagonal(dim1=-4, dim2=-2).copy_(blocks.movedim(-3, -1))  # (..., b, b, n_b)
    return out.view(*blocks.shape[:-3], nb * b, nb * b)
