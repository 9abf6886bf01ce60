"""Batched particle resampling.

All functions operate on a batch of ``B`` independent trials, each carrying
``N`` particles, and take *log* weights of shape ``(B, N)``. Weights never
need to be normalised on input; normalisation is done in log space with
``torch.logsumexp`` (or, for the cumulative weights used by the resamplers,
relative to the per-trial maximum log weight, which is equivalent and
overflow-free). Zero weights are expressed as ``-inf`` log weights and such
particles are never selected.

Randomness comes only from the ``torch.Generator`` (or per-trial
:class:`~torchflow.core.random.TrialStreams`) passed as ``generator`` (``None`` means
torch's default generator). Random numbers are drawn with
``torch.rand`` on the device of ``log_weights``; each resampler consumes a
fixed number of uniforms per call (independent of the weight values), so the
same generator state always yields the same indices.

Every resampler returns ``indices`` of shape ``(B, N)`` and dtype
``torch.int64``: ``indices[b, j]`` is the parent (ancestor) of particle ``j``
in trial ``b`` after resampling. Use :func:`gather_particles` to apply them.

Implementation note: the inverse-CDF resamplers compare positions
``p_j in [0, N)`` with the *scaled* cumulative weights ``S_i = N * c_i``
where ``c`` is the normalised cumulative sum whose last entry (and every
entry after the last positive weight) is exactly ``1``, i.e. ``S`` ends
exactly at ``N``. This is the same as comparing ``u_j = p_j / N`` with ``c``,
but keeps integer positions exact (uniform weights give ``S_i = i + 1``
exactly), and ``p_j`` is kept strictly below its upper bound, so zero-weight
particles (leading, interior or trailing) can never be selected.
"""

from __future__ import annotations

import math
import numbers
from typing import Callable, Dict, Optional, Tuple

import torch
from torch import Tensor, nn

from torchflow.core import linalg, registry
from torchflow.core import random as _random
from torchflow.core import tuning as _tuning
from torchflow.core.checks import check_count, check_float_tensor, shape_str
from torchflow.core.errors import ArgumentError
from torchflow.core.linalg import standard_normal

__all__ = [
    "normalize_log_weights",
    "effective_sample_size",
    "multinomial",
    "systematic",
    "stratified",
    "residual",
    "RESAMPLERS",
    "get_resampler",
    "resample_if_needed",
    "gather_particles",
    "Resampler",
    "RESAMPLING_GRADIENTS",
    "sinkhorn_transport",
    "sort_order",
    "hilbert_index",
    "SORT_ORDERS",
    "reads_host",
]

ResampleFn = Callable[..., Tensor]


# ---------------------------------------------------------------------------
# Validation helpers
# ---------------------------------------------------------------------------
def _check_log_weights(log_weights: object, name: str = "log_weights", values: bool = True) -> Tensor:
    """Validates a ``(B, N)`` floating-point log-weight tensor.

    Checks the type, shape (2-D with ``N >= 1``) and dtype, and that the
    values are usable: no NaN, no ``+inf`` and at least one finite entry per
    trial (otherwise the weights cannot be normalised).

    Args:
        log_weights: Candidate tensor, expected shape ``(B, N)``.
        name: Argument name used in error messages.
        values: also check the values (NaN, +inf, rows of -inf); these checks read the
            tensor back to the host, so filters whose weights are finite by construction skip them.

    Returns:
        The same tensor.

    Raises:
        ValueError: If any of the checks fails.
    """
    check_float_tensor(log_weights, name, "(B, N)", ndim=2)
    if log_weights.shape[1] < 1:
        raise ArgumentError(f"{name}: expected (B, N) with N >= 1 particles, got {shape_str(log_weights.shape)}")
    if values and log_weights.numel() > 0:  # value checks synchronise with the device
        has_nan_or_posinf = torch.isnan(log_weights).any() | torch.isposinf(log_weights).any()
        row_ok = torch.isfinite(log_weights).any(dim=1).all()
        if bool(has_nan_or_posinf):
            raise ArgumentError(f"{name}: expected no NaN or +inf values, got some")
        if not bool(row_ok):
            raise ArgumentError(
                f"{name}: expected at least one finite log weight in every trial (row), got a row that is entirely -inf"
            )
    return log_weights


def _working_dtype(dtype: torch.dtype) -> torch.dtype:
    """Returns the dtype used for internal computations (at least float32)."""
    return torch.promote_types(dtype, torch.float32)


def _unnormalized_weights(log_weights: Tensor) -> Tensor:
    """Returns ``exp(log_weights - max)`` per trial, shape ``(B, N)``.

    The maximum entry of each row is exactly ``1``; ``-inf`` maps to ``0``.
    """
    lw = log_weights.to(_working_dtype(log_weights.dtype))
    return torch.exp(lw - lw.amax(dim=1, keepdim=True))


def _scaled_cdf(weights: Tensor) -> Tensor:
    """Scaled cumulative weights ``N * cumsum(w) / sum(w)``, shape ``(B, N)``.

    Every entry whose cumulative sum already equals the total (in particular
    the last entry) is set to exactly ``N``, so the normalised CDF ends at
    exactly ``1``. Values are clamped to ``<= N`` to keep rows sorted.

    Args:
        weights: Non-negative weights, shape ``(B, N)``, each row with a
            positive sum.

    Returns:
        Tensor of shape ``(B, N)``, non-decreasing along dim 1.
    """
    n = weights.shape[1]
    cs = torch.cumsum(weights, dim=1)
    total = cs[:, -1:]
    scaled = (cs * (n / total)).clamp(max=float(n))
    return torch.where(cs >= total, torch.full_like(scaled, float(n)), scaled)


def _invert_cdf(scaled_cdf: Tensor, positions: Tensor) -> Tensor:
    """Finds, per position, the particle whose CDF interval contains it.

    Args:
        scaled_cdf: Output of :func:`_scaled_cdf`, shape ``(B, N)``.
        positions: Positions in ``[0, N)``, shape ``(B, M)``.

    Returns:
        int64 indices of shape ``(B, M)``, clamped to ``N - 1``.
    """
    n = scaled_cdf.shape[1]
    idx = torch.searchsorted(scaled_cdf.contiguous(), positions.contiguous(), right=True)
    return idx.clamp_(max=n - 1)


#: from this many (trial, particle) pairs on, :func:`_invert_strata` inverts the CDF of the
#: stratified and systematic schemes (one pass) instead of a binary search per position
_LINEAR_INVERSION_MIN = 2048


def _invert_strata(scaled_cdf: Tensor, positions: Tensor) -> Tensor:
    """:func:`_invert_cdf` for positions with ``positions[:, j]`` in ``[j, j + 1)`` (the stratified
    and systematic schemes), in one pass over the particles instead of a binary search per position:
    the same indices, exactly, at ``O(N)`` rather than ``O(N log N)`` per trial.

    With ``S = scaled_cdf`` and ``p = positions``: ``p`` is increasing, so ``{j : p_j < S_i}`` is
    the prefix ``[0, C_i)``, and ``p_j`` in ``[j, j + 1)`` gives ``C_i = k + [k < N and p_k < S_i]``
    with ``k = floor(S_i)``. The index of position ``j``, ``#{i : S_i <= p_j}``, is then
    ``#{i : C_i <= j}``: a count of the ``C_i`` and its cumulative sum."""
    b, n = scaled_cdf.shape
    if b * n < _LINEAR_INVERSION_MIN:  # below this the binary search's single call is quicker
        return _invert_cdf(scaled_cdf, positions)
    k = scaled_cdf.floor().to(torch.int64)  # in [0, N]
    c = k + ((k < n) & (positions.gather(1, k.clamp(max=n - 1)) < scaled_cdf))
    marks = torch.zeros(b, n + 1, dtype=torch.int64, device=c.device).scatter_add_(1, c, torch.ones_like(c))
    return marks[:, :n].cumsum(1).clamp_(max=n - 1)


def _below(x: Tensor, upper: Tensor) -> Tensor:
    """Clamps ``x`` to be strictly below ``upper`` (elementwise, broadcast)."""
    return torch.minimum(x, torch.nextafter(upper, torch.zeros_like(upper)))


def _rand(shape: Tuple[int, ...], like: Tensor, generator: Optional[torch.Generator]) -> Tensor:
    """Uniform ``[0, 1)`` draws on ``like``'s device in the working dtype (a
    :class:`~torchflow.core.random.TrialStreams` draws each trial's row from its own stream)."""
    return _random.uniform(shape, generator=generator, device=like.device, dtype=_working_dtype(like.dtype))


# ---------------------------------------------------------------------------
# Weight utilities
# ---------------------------------------------------------------------------
def normalize_log_weights(log_weights: Tensor, *, validate: bool = True) -> Tensor:
    """Normalises log weights so that each trial's weights sum to one.

    Args:
        log_weights: Unnormalised log weights, shape ``(B, N)``.

    Returns:
        Log weights of shape ``(B, N)`` (same dtype) with
        ``logsumexp(result, dim=1) == 0``.

    Raises:
        ValueError: If ``log_weights`` is not a 2-D floating-point tensor with
            at least one finite entry per row, or contains NaN / ``+inf``.
    """
    _check_log_weights(log_weights, values=validate)
    # Shift by the row maximum first: exact, and avoids cancellation when the
    # log weights are large in magnitude (e.g. -1000 in float32).
    shifted = log_weights - log_weights.amax(dim=1, keepdim=True)
    return shifted - torch.logsumexp(shifted, dim=1, keepdim=True)


def effective_sample_size(log_weights: Tensor) -> Tensor:
    """Effective sample size ``1 / sum_i w_i^2`` of normalised weights.

    Computed in log space as ``exp(-logsumexp(2 * log_w_normalised))``.
    Ranges from ``1`` (one particle holds all the weight) to ``N`` (uniform).

    Args:
        log_weights: Unnormalised log weights, shape ``(B, N)``.

    Returns:
        ESS per trial, shape ``(B,)``, same dtype as ``log_weights``.

    Raises:
        ValueError: On invalid ``log_weights`` (see :func:`normalize_log_weights`).
    """
    return _ess(normalize_log_weights(log_weights))


def _ess(normalised: Tensor) -> Tensor:
    """``1 / sum_i w_i^2`` of normalised log weights ``(..., N)`` -> ``(...)``, in log space; no
    validation (the filters' weights are valid by construction)."""
    return torch.exp(-torch.logsumexp(2.0 * normalised, dim=-1))


# ---------------------------------------------------------------------------
# Resamplers
# ---------------------------------------------------------------------------
def multinomial(log_weights: Tensor, generator: Optional[torch.Generator] = None, *, validate: bool = True) -> Tensor:
    """Multinomial resampling: ``N`` i.i.d. draws from the weights.

    Uses inverse-CDF sampling with ``N`` independent uniforms per trial. The
    offspring count of particle ``i`` is ``Binomial(N, w_i)``.

    Args:
        log_weights: Unnormalised log weights, shape ``(B, N)``.
        generator: Source of randomness; ``None`` uses torch's default.

    Returns:
        Ancestor indices, shape ``(B, N)``, dtype ``torch.int64``.

    Raises:
        ValueError: On invalid ``log_weights``.
    """
    _check_log_weights(log_weights, values=validate)
    b, n = log_weights.shape
    return _multinomial_indices(log_weights, _rand((b, n), log_weights, generator))


def _multinomial_indices(log_weights: Tensor, u: Tensor) -> Tensor:
    n = log_weights.shape[1]
    cdf = _scaled_cdf(_unnormalized_weights(log_weights))
    return _invert_cdf(cdf, _below(u * n, u.new_full((), float(n))))


def systematic(log_weights: Tensor, generator: Optional[torch.Generator] = None, *, validate: bool = True) -> Tensor:
    """Systematic resampling: one uniform ``U`` per trial, ``u_i = (U + i) / N``.

    Indices are the inverse CDF (``searchsorted`` of the cumulative weights,
    normalised to end at exactly ``1``) at the ``u_i``, clamped to ``N - 1``.
    The returned indices are non-decreasing, and the offspring count of
    particle ``i`` is always ``floor(N w_i)`` or ``ceil(N w_i)``.

    Args:
        log_weights: Unnormalised log weights, shape ``(B, N)``.
        generator: Source of randomness; ``None`` uses torch's default.

    Returns:
        Ancestor indices, shape ``(B, N)``, dtype ``torch.int64``.

    Raises:
        ValueError: On invalid ``log_weights``.
    """
    _check_log_weights(log_weights, values=validate)
    b, n = log_weights.shape
    return _strata_indices(log_weights, _rand((b, 1), log_weights, generator))


def _strata_indices(log_weights: Tensor, u: Tensor) -> Tensor:
    """The systematic (``u (B, 1)``) or stratified (``u (B, N)``) indices of ``log_weights (B, N)``."""
    n = log_weights.shape[1]
    cdf = _scaled_cdf(_unnormalized_weights(log_weights))
    i = torch.arange(n, device=cdf.device, dtype=cdf.dtype)
    positions = _below(i + u, i + 1.0)  # N * u_i, kept in [i, i + 1)
    return _invert_strata(cdf, positions)


def stratified(log_weights: Tensor, generator: Optional[torch.Generator] = None, *, validate: bool = True) -> Tensor:
    """Stratified resampling: ``u_i = (i + U_i) / N`` with independent ``U_i``.

    Args:
        log_weights: Unnormalised log weights, shape ``(B, N)``.
        generator: Source of randomness; ``None`` uses torch's default.

    Returns:
        Ancestor indices (non-decreasing per trial), shape ``(B, N)``,
        dtype ``torch.int64``.

    Raises:
        ValueError: On invalid ``log_weights``.
    """
    _check_log_weights(log_weights, values=validate)
    b, n = log_weights.shape
    return _strata_indices(log_weights, _rand((b, n), log_weights, generator))


def residual(log_weights: Tensor, generator: Optional[torch.Generator] = None, *, validate: bool = True) -> Tensor:
    """Residual resampling.

    Particle ``i`` first receives ``floor(N w_i)`` deterministic copies: output
    position ``j`` below the total deterministic count ``K`` gets index
    ``searchsorted(cumsum(counts), j, right=True)``. The remaining ``N - K``
    positions are filled with multinomial draws from the residual weights
    ``N w_i - floor(N w_i)`` (renormalised). Rows whose residual is all zero
    (then ``K == N``) fall back to the weights themselves, which keeps the
    computation NaN-free; the fallback draws are never used. ``N`` uniforms
    are drawn per trial regardless of ``K``.

    Args:
        log_weights: Unnormalised log weights, shape ``(B, N)``.
        generator: Source of randomness; ``None`` uses torch's default.

    Returns:
        Ancestor indices, shape ``(B, N)``, dtype ``torch.int64``.

    Raises:
        ValueError: On invalid ``log_weights``.
    """
    _check_log_weights(log_weights, values=validate)
    b, n = log_weights.shape
    return _residual_indices(log_weights, _rand((b, n), log_weights, generator))


def _residual_indices(log_weights: Tensor, u: Tensor) -> Tensor:
    b, n = log_weights.shape
    w = _unnormalized_weights(log_weights)
    # N * w_i, computed so that uniform weights give exactly 1.
    nw = w * (n / w.sum(dim=1, keepdim=True))
    floors = torch.floor(nw)
    counts = floors.to(torch.int64)
    ccounts = torch.cumsum(counts, dim=1)  # (B, N)
    n_det = ccounts[:, -1:].clamp(max=n)  # (B, 1)

    j = torch.arange(n, device=w.device, dtype=torch.int64).expand(b, n)
    det_idx = torch.searchsorted(ccounts, j.contiguous(), right=True).clamp_(max=n - 1)

    res = (nw - floors).clamp(min=0.0)
    res_ok = res.sum(dim=1, keepdim=True) > 0
    res = torch.where(res_ok, res, w)  # guard: all-zero residual rows
    cdf = _scaled_cdf(res)
    rand_idx = _invert_cdf(cdf, _below(u * n, u.new_full((), float(n))))

    return torch.where(j < n_det, det_idx, rand_idx)


RESAMPLERS: Dict[str, ResampleFn] = registry.table("resampling")
"""The resampling schemes of :data:`torchflow.core.registry.REGISTRY`, name -> ``fn(log_weights, generator=None)``."""


def _get_resampler(name: object, arg_name: str) -> ResampleFn:
    return registry.lookup("resampling", name, arg_name)


def get_resampler(name: str) -> ResampleFn:
    """Looks up a resampling scheme by name.

    Args:
        name: One of ``"multinomial"``, ``"systematic"``, ``"stratified"``,
            ``"residual"``.

    Returns:
        The resampler ``fn(log_weights, generator=None) -> (B, N) int64``.

    Raises:
        ValueError: If ``name`` is not a known scheme (message lists the valid
            names).
    """
    return _get_resampler(name, "name")


# ---------------------------------------------------------------------------
# Adaptive resampling and gathering
# ---------------------------------------------------------------------------
def resample_if_needed(
    log_weights: Tensor,
    generator: Optional[torch.Generator] = None,
    *,
    scheme: str = "systematic",
    ess_threshold: float = 0.5,
    validate: bool = True,
) -> Tuple[Tensor, Tensor, Tensor]:
    """Resamples only the trials whose effective sample size is too low.

    Trial ``b`` is resampled iff ``ESS_b < ess_threshold * N`` (strict).
    Hence ``ess_threshold = 0`` never resamples, and ``ess_threshold = 1``
    resamples every trial whose weights are not (numerically) uniform; since
    the ESS of uniform weights is ``N`` only up to rounding, uniform trials may
    also be resampled at ``1`` (harmless: they get uniform weights again).

    The uniforms are drawn for every trial whatever the weights, so the
    generator advances identically whichever trials resample; the exception
    is ``ess_threshold == 0``, where nothing is drawn. On the CPU only the
    trials that resample are computed (:func:`reads_host`); elsewhere all are,
    with no host synchronisation. Both give the same indices.

    Args:
        log_weights: Unnormalised log weights, shape ``(B, N)``.
        generator: Source of randomness; ``None`` uses torch's default.
        scheme: Name of the resampling scheme (a key of :data:`RESAMPLERS`).
        ess_threshold: Fraction of ``N`` in ``[0, 1]``.
        validate: check the weights' values (NaN, +inf, all -inf rows); a filter whose weights
            are valid by construction passes ``False`` to avoid the host synchronisation.

    Returns:
        A tuple ``(indices, resampled, new_log_weights)``:

        * ``indices``: ``(B, N)`` int64 ancestor indices; ``arange(N)`` for
          trials that were not resampled.
        * ``resampled``: ``(B,)`` bool, which trials were resampled.
        * ``new_log_weights``: ``(B, N)`` normalised log weights (dtype of the
          input): ``-log N`` for resampled trials, the normalised input
          otherwise.

    Raises:
        ValueError: On invalid ``log_weights``, unknown ``scheme`` or
            ``ess_threshold`` outside ``[0, 1]``.
    """
    _check_log_weights(log_weights, values=validate)
    resampler = _get_resampler(scheme, "scheme")
    if (
        isinstance(ess_threshold, bool)
        or not isinstance(ess_threshold, numbers.Real)
        or not (0.0 <= float(ess_threshold) <= 1.0)
    ):
        raise ArgumentError(f"ess_threshold: expected a real number in [0, 1], got {ess_threshold!r}")
    threshold = float(ess_threshold)
    b, n = log_weights.shape

    lw = normalize_log_weights(log_weights, validate=False)
    indices, resampled, new_log_weights = _resample_rows(log_weights, lw, generator, resampler, threshold)
    if indices is None:  # no trial resampled: the identity
        indices = torch.arange(n, device=lw.device, dtype=torch.int64).repeat(b, 1)
    return indices, resampled, new_log_weights


#: the built-in schemes as their uniforms' shape per trial ``(1: one, None: N)`` and the indices
#: those uniforms give (``fn(log_weights (B, N), u) -> (B, N)``): what lets :func:`_resample_rows`
#: draw for every trial and compute only the trials that resample
_SPLIT: Dict[Callable, Tuple[Optional[int], Callable]] = {
    multinomial: (None, _multinomial_indices),
    systematic: (1, _strata_indices),
    stratified: (None, _strata_indices),
    residual: (None, _residual_indices),
}


def reads_host(t: Tensor) -> bool:
    """Whether a filter step may read ``t`` back to decide what to compute: on the CPU a host read
    costs nothing, so work that no trial needs (a resampling no trial triggers) is skipped; never on
    a GPU (the read would stall the device and break a CUDA graph), under ``torch.func`` transforms
    or while ``torch.compile`` traces; ``tuning`` ``host_reads_cpu=0`` turns it off."""
    return (
        t.device.type == "cpu"
        and _tuning.get().host_reads_cpu
        and not linalg.under_func_transform(t)
        and not torch.compiler.is_compiling()
    )


def _resample_rows(
    log_weights: Tensor,
    lw: Tensor,
    generator,
    resampler: Callable,
    threshold: float,
    ess: Optional[Tensor] = None,
    u: Optional[Tensor] = None,
):
    """``(indices or None, resampled (B,), new_log_weights)`` with ``lw`` the normalised
    ``log_weights`` and ``ess`` their effective sample size (computed when ``None``); ``None`` stands
    for identity indices in every trial.

    The uniforms of a built-in scheme are drawn for every trial whatever the weights (each trial's
    stream advances the same way, so the numbers do not depend on which trials resample). Where
    :func:`reads_host` allows, only the trials that resample are computed and a step in which none
    does computes nothing else; elsewhere every trial is computed and the identity kept where the
    ESS did not trigger (no host synchronisation). Both give the same indices. ``u``: the uniforms,
    already drawn by the caller (:meth:`Resampler.draw_uniforms`; a built-in scheme where
    :func:`reads_host` allows)."""
    b, n = lw.shape
    if threshold == 0.0:  # never resamples: nothing drawn
        return None, torch.zeros(b, dtype=torch.bool, device=lw.device), lw
    resampled = (_ess(lw) if ess is None else ess) < threshold * n
    split = _SPLIT.get(resampler)
    if split is None or not reads_host(lw):
        indices = resampler(log_weights, generator, validate=False)
        identity = torch.arange(n, device=lw.device, dtype=torch.int64)
        return (
            torch.where(resampled[:, None], indices, identity),
            resampled,
            torch.where(resampled[:, None], torch.full_like(lw, -math.log(n)), lw),
        )
    per_trial, invert = split
    if u is None:
        u = _rand((b, n if per_trial is None else per_trial), log_weights, generator)
    m = int(resampled.sum())
    if m == 0:
        return None, resampled, lw
    uniform = torch.full_like(lw, -math.log(n))
    if m == b:
        return invert(log_weights, u), resampled, uniform
    rows = resampled.nonzero().squeeze(1)
    indices = torch.arange(n, dtype=torch.int64, device=lw.device).repeat(b, 1)
    indices[rows] = invert(log_weights[rows], u[rows])
    return indices, resampled, torch.where(resampled[:, None], uniform, lw)


#: the schemes the CPU weighting kernel implements (:attr:`Resampler.kernel_scheme`)
_KERNEL_SCHEMES: Dict[Callable, str] = {systematic: "systematic", stratified: "stratified"}


def gather_particles(x: Tensor, indices: Tensor) -> Tensor:
    """Selects particles per trial according to ancestor indices.

    ``out[b, j, ...] = x[b, indices[b, j], ...]``. Works for any trailing
    shape, e.g. states ``(B, N, d)`` and covariances ``(B, N, d, d)``, and is
    differentiable with respect to ``x``.

    Args:
        x: Per-particle quantities, shape ``(B, N, *rest)``.
        indices: Integer ancestor indices, shape ``(B, M)`` (usually
            ``M == N``), values in ``[0, N)``.

    Returns:
        Tensor of shape ``(B, M, *rest)``.

    Raises:
        ValueError: If ``x`` has fewer than 2 dims, ``indices`` is not a 2-D
            integer tensor, or the batch sizes differ.
    """
    if not isinstance(x, Tensor) or x.dim() < 2:
        shape = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
        raise ArgumentError(f"x: expected a tensor of shape (B, N, *rest), got {shape}")
    if not isinstance(indices, Tensor) or indices.dim() != 2:
        shape = tuple(indices.shape) if isinstance(indices, Tensor) else type(indices).__name__
        raise ArgumentError(f"indices: expected a tensor of shape (B, N), got {shape}")
    if indices.dtype.is_floating_point or indices.dtype.is_complex or indices.dtype == torch.bool:
        raise ArgumentError(f"indices: expected an integer dtype, got {indices.dtype}")
    if indices.shape[0] != x.shape[0]:
        raise ArgumentError(
            f"indices: expected shape (B, N) with B = x.shape[0] = {x.shape[0]}, got shape {tuple(indices.shape)}"
        )
    batch = torch.arange(x.shape[0], device=x.device)[:, None]
    return x[batch, indices.to(device=x.device, dtype=torch.int64)]


#: how gradients pass through resampling (the slot :class:`Resampler` keeps for estimators)
RESAMPLING_GRADIENTS = ("none", "stop_gradient", "soft", "ot")


def sinkhorn_transport(
    particles: Tensor, log_weights: Tensor, *, epsilon: float = 0.1, iterations: int = 100
) -> Tensor:
    """Entropy-regularised optimal transport from the weighted particles to uniform weights
    (Corenflos, Thornton, Deligiannidis & Doucet 2021), batched over trials, in log space.

    Solves ``min_P <P, C> - epsilon H(P)`` with row sums ``W`` (the normalised weights) and column
    sums ``1/N``, ``C_ij = |x_i - x_j|^2 / s^2`` on positions scaled by ``s``, the trial's largest
    weighted standard deviation (so ``epsilon`` is relative to the cloud's spread; ``s`` is held
    constant for the gradient). The Sinkhorn potentials are iterated ``iterations`` times without
    autograd, then once more with it: the gradient is that of the last iteration at the converged
    potentials (the implicit-function approximation used by geomloss), so the backward pass keeps
    one ``(B, N, N)`` plan, not ``iterations`` of them. The regularisation is annealed from 10 to
    ``epsilon`` over the first half of the iterations (epsilon-scaling, which converges in far fewer
    iterations than a fixed small epsilon). A fixed number of iterations: no
    convergence test, hence no host synchronisation.

    Args:
        particles: ``(B, N, d)``.
        log_weights: ``(B, N)`` normalised log-weights (``-inf`` allowed).
        epsilon: entropic regularisation (> 0; smaller is closer to exact transport and needs more
            iterations).
        iterations: Sinkhorn iterations (>= 1).

    Returns:
        ``T (B, N, N)`` with ``T[b, i, j] = N P_ij``: each column sums to one, and the transported
        particles are ``x_new[b, j] = sum_i T[b, i, j] x[b, i]`` (every new particle is a convex
        combination of the old ones, with weight ``1/N``). Memory: a few ``(B, N, N)`` tensors.
    """
    B, N, d = particles.shape
    w = log_weights.exp()
    with torch.no_grad():
        mean = torch.einsum("bn,bnd->bd", w, particles)
        var = torch.einsum("bn,bnd->bd", w, (particles - mean[:, None]).pow(2))
        scale = var.amax(-1).sqrt().clamp_min(torch.finfo(particles.dtype).tiny)
    xs = particles / scale[:, None, None]
    sq = xs.pow(2).sum(-1)
    C = (sq[:, :, None] + sq[:, None, :] - 2 * xs @ xs.transpose(-1, -2)).clamp_min(0.0)
    log_a, log_b = log_weights, -math.log(N)
    eps = float(epsilon)

    def f_of(g, C, eps=eps):  # row potentials given the column potentials
        return -eps * torch.logsumexp((g[:, None, :] - C) / eps + log_b, dim=2)

    def g_of(f, C, eps=eps):
        return -eps * torch.logsumexp((f[:, :, None] - C) / eps + log_a[:, :, None], dim=1)

    # epsilon-scaling: the regularisation falls geometrically from 10 (a blur wider than the cloud,
    # whose scaled spread is 1) to epsilon over the first half of the iterations, then stays
    n_iter = int(iterations)
    anneal = max(1, n_iter // 2)
    g = torch.zeros_like(log_a)
    with torch.no_grad():
        Cd = C.detach()
        for k in range(n_iter - 1):
            e = max(eps, 10.0 * (eps / 10.0) ** (k / anneal)) if eps < 10.0 else eps
            g = g_of(f_of(g, Cd, e), Cd, e)
    f = f_of(g, C)  # the last iteration with autograd; g's update makes every column sum exact
    g = g_of(f, C)
    return torch.exp(log_a[:, :, None] + (f[:, :, None] + g[:, None, :] - C) / eps + (log_b + math.log(N)))


#: orders :class:`Resampler` can sort the particles in before resampling (``sort=``)
SORT_ORDERS = ("first", "principal", "hilbert")


def hilbert_index(cells: Tensor, bits: int) -> Tensor:
    """Position along the d-dimensional Hilbert curve of integer cells ``(..., d)`` in
    ``[0, 2**bits)`` -> ``(...)`` int64 (``d * bits <= 63``). Consecutive positions are adjacent
    cells. Skilling's method (AIP Conf. Proc. 707, 2004): the cell's coordinates are turned into
    the curve's transposed index by one pass of bit exchanges and inversions from the top bit
    down, Gray-decoded, and the transposed bits interleaved (loops over bits and coordinates, each
    an elementwise op over all cells)."""
    x = list(cells.to(torch.int64).unbind(-1))
    d, top = len(x), 1 << (bits - 1)
    q = top
    while q > 1:  # undo the excess work of the curve's construction, top bit first
        low = q - 1
        for i in range(d):
            hit = (x[i] & q) != 0
            t = (x[0] ^ x[i]) & low
            x0 = torch.where(hit, x[0] ^ low, x[0] ^ t)
            if i:
                x[i] = torch.where(hit, x[i], x[i] ^ t)
            x[0] = x0
        q >>= 1
    for i in range(1, d):  # Gray encode
        x[i] = x[i] ^ x[i - 1]
    t, q = torch.zeros_like(x[0]), top
    while q > 1:
        t = torch.where((x[d - 1] & q) != 0, t ^ (q - 1), t)
        q >>= 1
    x = [xi ^ t for xi in x]
    index = torch.zeros_like(x[0])
    for b in range(bits - 1, -1, -1):  # interleave: bit b of every coordinate, most significant first
        for i in range(d):
            index = (index << 1) | ((x[i] >> b) & 1)
    return index


def sort_order(particles: Tensor, log_weights: Tensor, by: str) -> Tensor:
    """``(B, N)`` int64 permutation sorting each trial's ``particles (B, N, d)`` by a scalar key
    (stable: ties keep their order). In d = 1 the key is the value whatever ``by`` says; else:

    * ``"first"``: the first coordinate;
    * ``"principal"``: the projection on the leading eigenvector of the cloud's covariance
      weighted by ``log_weights (B, N)`` (signed so that its largest component is positive);
    * ``"hilbert"``: the position along the Hilbert curve of the unit cube (``floor(62 / d)`` bits
      per coordinate, at most 31; ``d <= 62``) of ``Phi((x - m) / s)`` per coordinate, ``m`` and
      ``s`` the weighted mean and standard deviation and ``Phi`` the normal CDF: nearby particles
      get nearby keys, so the order moves little when the particles do.
    """
    x = particles.detach()
    d = x.shape[-1]
    if d == 1 or by == "first":
        key = x[..., 0]
    elif by == "principal":
        _, cov = linalg.weighted_mean_cov(x, log_weights.detach())
        axis = torch.linalg.eigh(cov)[1][..., -1]  # (B, d)
        sign = torch.where(axis.gather(-1, axis.abs().argmax(-1, keepdim=True)) < 0, -1.0, 1.0)
        key = torch.einsum("bnd,bd->bn", x, axis * sign)
    else:
        if d > 62:
            raise ArgumentError(f"sort: 'hilbert' keys hold at most 62 dimensions, got d = {d} (use 'principal')")
        bits = min(31, 62 // d)
        mean, cov = linalg.weighted_mean_cov(x, log_weights.detach())
        sd = cov.diagonal(dim1=-2, dim2=-1).clamp_min(torch.finfo(x.dtype).tiny).sqrt()
        unit = torch.special.ndtr((x - mean[:, None]) / sd[:, None]).double()  # (B, N, d) in [0, 1]
        cells = (unit * 2.0**bits).floor().clamp(0, 2**bits - 1).to(torch.int64)
        key = hilbert_index(cells, bits)
    return torch.sort(key, dim=1, stable=True)[1]


class Resampler(nn.Module):
    """The resampling part of a particle filter: scheme, ESS trigger, regularisation and how
    gradients pass through it.

    Args:
        state_dim: d (for per-coordinate regularisation variances).
        scheme: ``multinomial``, ``systematic`` (default), ``stratified`` or ``residual``.
        ess_threshold: resample a trial when ESS < ess_threshold * N (0 never, 1 nearly always).
        regularization: ``None`` (off), a float variance, or a list of d per-coordinate variances
            of Gaussian jitter added to the particles of resampled trials (absolute: the same
            whatever the cloud's spread).
        regularization_relative: ``None`` (off) or a number ``h >= 0``: Gaussian jitter of standard
            deviation ``h`` times each coordinate's weighted spread before resampling, added to the
            particles of resampled trials (relative to the cloud, as DAPPER's ``PartFilt(reg=...)``
            scales its jitter by the weighted covariance; here per coordinate). With both given the
            variances add.
        gradient: how gradients pass through the ancestor choice.

            * ``"none"``: the index gather drops how the ancestors depend on the parameters, so
              the gradient of the log-evidence is a biased estimate of the score wherever
              resampling happens (the bias does not vanish as N grows).
            * ``"stop_gradient"`` (Scibior & Wood 2021): a resampled particle's log-weight
              becomes ``-log N + log W_a - stop_gradient(log W_a)`` (``W_a`` its ancestor's
              normalised weight). Its value is exactly ``-log N`` (the forward pass is bit for bit
              that of ``"none"``), and its gradient adds the score-function term of the ancestor
              draw, so the gradient of ``log Z_hat`` estimates the score consistently.
            * ``"soft"`` (Karkus, Hsu & Lee 2018): ancestors are drawn from
              ``q = soft_alpha W + (1 - soft_alpha) / N`` and weighted ``W_a / q_a`` (normalised),
              so the evidence estimate stays unbiased and gradients flow through the new weights;
              the ancestor draw itself has no gradient term (biased, less so as ``soft_alpha``
              falls, at the cost of a lower ESS after resampling). The forward pass differs from
              ``"none"`` unless ``soft_alpha = 1``.
            * ``"ot"`` (Corenflos et al. 2021): the particles of a resampled trial are moved by
              entropy-regularised optimal transport to equally weighted ones
              (:func:`sinkhorn_transport`); a differentiable map, so gradients flow through the
              new positions. Biased (the transported cloud matches the weighted one only in the
              mean; its spread shrinks as ``ot_epsilon`` grows) and O(N^2) in time and memory; no
              random numbers are drawn.
        soft_alpha: the mixture weight of ``"soft"``, in (0, 1].
        ot_epsilon, ot_iterations: the regularisation and the Sinkhorn iterations of ``"ot"``.
        dtype: of the regularisation scale (the model's).
        sort: ``None`` (default): resample the particles in their order. Else sort each trial's
            particles by a scalar key before inverting the resampling CDF (:func:`sort_order`):
            ``"first"`` (the first coordinate), ``"principal"`` (the projection on the weighted
            cloud's first principal axis) or ``"hilbert"`` (the position along a Hilbert curve);
            in d = 1 all three sort by the value. Sorted, the ancestors chosen move continuously
            with the uniforms and the particles (exactly so in d = 1, approximately along the
            Hilbert curve in higher dimensions), which correlated pseudo-marginal MCMC needs
            (:func:`torchflow.inference.pmmh` with ``correlation`` turns on ``"hilbert"``). The
            particles of every trial leave in sorted order, with their weights where the trial is
            not resampled (a reordering: the same weighted cloud). Not used by ``"ot"``.
    """

    def __init__(
        self,
        state_dim: int,
        *,
        scheme: str = "systematic",
        ess_threshold: float = 0.5,
        regularization=None,
        gradient: str = "none",
        soft_alpha: float = 0.5,
        ot_epsilon: float = 0.1,
        ot_iterations: int = 100,
        dtype: torch.dtype = torch.float64,
        sort: Optional[str] = None,
        regularization_relative: Optional[float] = None,
    ):
        super().__init__()
        self.sort = sort
        if regularization_relative is not None and (
            isinstance(regularization_relative, bool)
            or not isinstance(regularization_relative, numbers.Real)
            or not 0 <= float(regularization_relative) < math.inf
        ):
            raise ArgumentError(
                f"regularization_relative: expected None or a number >= 0 (jitter in units of the "
                f"cloud's spread), got {regularization_relative!r}"
            )
        #: jitter relative to each coordinate's weighted spread (``None``: off)
        self.regularization_relative = None if regularization_relative is None else float(regularization_relative)
        if (
            isinstance(ess_threshold, bool)
            or not isinstance(ess_threshold, numbers.Real)
            or not 0.0 <= float(ess_threshold) <= 1.0
        ):
            raise ArgumentError(f"ess_threshold: expected a fraction in [0, 1], got {ess_threshold!r}")
        if gradient not in RESAMPLING_GRADIENTS:
            raise ArgumentError(f"resampling_gradient: expected one of {RESAMPLING_GRADIENTS}, got {gradient!r}")
        if isinstance(soft_alpha, bool) or not isinstance(soft_alpha, numbers.Real) or not 0 < soft_alpha <= 1:
            raise ArgumentError(f"soft_alpha: expected a mixture weight in (0, 1], got {soft_alpha!r}")
        self.scheme, self.ess_threshold, self.gradient = scheme, float(ess_threshold), gradient
        self.soft_alpha = float(soft_alpha)
        if isinstance(ot_epsilon, bool) or not isinstance(ot_epsilon, numbers.Real) or not ot_epsilon > 0:
            raise ArgumentError(f"ot_epsilon: expected a regularisation > 0, got {ot_epsilon!r}")
        self.ot_epsilon = float(ot_epsilon)
        self.ot_iterations = check_count("ot_iterations", ot_iterations)
        d = int(state_dim)
        if regularization is None:
            self.register_buffer("regularization_std", None)
        else:
            var = torch.as_tensor(regularization, dtype=torch.float64)
            if var.dim() == 0:
                var = var.expand(d)
            if var.shape != (d,) or bool((var < 0).any()):
                raise ArgumentError(
                    f"regularization: expected a non-negative variance or {d} of them, got {regularization!r}"
                )
            self.register_buffer("regularization_std", var.sqrt().to(dtype))

    @property
    def scheme(self) -> str:
        """The resampling scheme's name (a key of :data:`RESAMPLERS`)."""
        return self._scheme

    @scheme.setter
    def scheme(self, value: str) -> None:
        self._scheme_fn = _get_resampler(value, "resampling")  # resolved once, not per step
        self._scheme = value

    @property
    def kernel_scheme(self) -> Optional[str]:
        """``"systematic"`` or ``"stratified"`` where a step's resampling may run in the CPU weighting
        kernel (:func:`torchflow.flows.select.weights_kernel`): that built-in scheme, no
        sorting, no regularisation, and a gradient rule that changes nothing without autograd
        (``"none"``, ``"stop_gradient"``), and this class's own :meth:`forward` (a subclass that
        overrides it is always called); ``None`` otherwise."""
        if (
            self.sort is not None
            or self.regularization_std is not None
            or self.regularization_relative is not None
            or self.gradient not in ("none", "stop_gradient")
            or type(self).forward is not Resampler.forward
        ):
            return None
        return _KERNEL_SCHEMES.get(self._scheme_fn)

    def draw_uniforms(self, log_weights: Tensor, generator) -> Optional[Tensor]:
        """The uniforms this resampler's built-in scheme draws for ``log_weights (B, N)``: ``(B, 1)``
        (systematic) or ``(B, N)`` (stratified, multinomial, residual), from ``generator``, as
        :meth:`forward` would draw them; ``None`` when ``ess_threshold`` is 0 (nothing is drawn).
        Passed back as :meth:`forward`'s ``uniforms``, they stand for its own draw."""
        if self._scheme_fn not in _SPLIT:
            raise ArgumentError(
                f"draw_uniforms: the scheme {self.scheme!r} is not a built-in one; its draws are its own"
            )
        if self.ess_threshold == 0.0:
            return None
        b, n = log_weights.shape
        per_trial = _SPLIT[self._scheme_fn][0]
        return _rand((b, n if per_trial is None else per_trial), log_weights, generator)

    @property
    def sort(self) -> Optional[str]:
        """The order particles are sorted in before resampling (``None`` or one of :data:`SORT_ORDERS`)."""
        return self._sort

    @sort.setter
    def sort(self, value: Optional[str]) -> None:
        if value is not None and value not in SORT_ORDERS:
            raise ArgumentError(f"sort: expected None or one of {SORT_ORDERS}, got {value!r}")
        self._sort = value

    def forward(
        self,
        particles: Tensor,
        log_weights: Tensor,
        generator,
        *,
        cov=None,
        extras: Optional[Dict[str, Tensor]] = None,
        ess: Optional[Tensor] = None,
        uniforms: Optional[Tensor] = None,
    ):
        """Resample the low-ESS trials of ``particles (B, N, d)`` with normalised ``log_weights
        (B, N)``; a per-particle ``cov`` (a :class:`~torchflow.core.covariances.Covariance`) and
        ``extras`` (tensors with a leading ``(B, N)``) follow the particles. ``ess (B,)``: the
        weights' effective sample size where the caller has it (computed here otherwise); the
        weights are then taken as they are, already normalised.

        Returns ``(particles, log_weights, cov, extras, resampled (B,))``. On a GPU there is no host
        synchronisation: every trial is gathered (identity indices where not resampled). On the CPU
        (:func:`reads_host`) only the trials that resample are computed, and a step in which none
        does gathers nothing; the random draws, hence the numbers, are the same either way. ``uniforms``:
        this step's draws, made beforehand by :meth:`draw_uniforms` (a built-in scheme on the CPU)."""
        spread = self._spread(particles, log_weights)
        if self.gradient == "ot":
            return self._ot(particles, log_weights, generator, cov, extras, spread)
        order = None if self.sort is None else sort_order(particles, log_weights, self.sort)
        lw_in = log_weights if order is None else log_weights.gather(1, order)
        if self.gradient == "soft":
            idx, resampled, lw_new = self._soft(lw_in, generator)
        else:
            idx, resampled, lw_new = _resample_rows(
                lw_in,
                lw_in if ess is not None else normalize_log_weights(lw_in, validate=False),
                generator,
                self._scheme_fn,
                self.ess_threshold,
                ess=ess,
                u=uniforms,
            )
            if idx is None:  # no trial resampled
                if order is None:  # the particles stay where they are: nothing to gather
                    return (
                        self._regularise(particles, resampled, generator, spread),
                        lw_new,
                        cov,
                        extras or {},
                        resampled,
                    )
                idx = torch.arange(lw_in.shape[1], device=lw_in.device).expand_as(lw_in)
        if order is not None:  # positions in the sorted cloud -> the particles' own indices
            idx = order.gather(1, idx)
        particles = gather_particles(particles, idx)
        if self.gradient == "stop_gradient" and torch.is_grad_enabled():  # adds exactly 0: skipped without autograd
            lw_anc = gather_particles(log_weights, idx)
            # exactly 0 in value (an ancestor has a finite weight: zero-weight particles are never
            # drawn); its gradient is that of log W_a
            score = torch.where(torch.isfinite(lw_anc), lw_anc - lw_anc.detach(), torch.zeros_like(lw_anc))
            lw_new = torch.where(resampled[:, None], lw_new + score, lw_new)
        if cov is not None:  # its type says whether it follows the particles
            cov = cov.resampled(idx)
        if extras:
            extras = {k: gather_particles(v, idx) for k, v in extras.items()}
        return self._regularise(particles, resampled, generator, spread), lw_new, cov, extras or {}, resampled

    def _spread(self, particles: Tensor, log_weights: Tensor) -> Optional[Tensor]:
        """``(B, 1, d)`` each coordinate's weighted standard deviation, for the relative jitter (else ``None``)."""
        if self.regularization_relative is None:
            return None
        W = torch.softmax(log_weights.detach(), 1).unsqueeze(-1)  # (B, N, 1)
        x = particles.detach()
        mean = (W * x).sum(1, keepdim=True)
        return ((W * (x - mean).square()).sum(1, keepdim=True)).sqrt()

    def _regularise(self, particles: Tensor, resampled: Tensor, generator, spread: Optional[Tensor] = None) -> Tensor:
        if self.regularization_std is None and spread is None:
            return particles
        std = 0.0 if self.regularization_std is None else self.regularization_std.to(particles.dtype).square()
        if spread is not None:
            std = std + (self.regularization_relative * spread).square()
        # drawn whether or not any trial resampled, so that each trial's stream advances the
        # same way whatever the other trials in its batch do
        noise = (
            standard_normal(particles.shape, dtype=particles.dtype, device=particles.device, generator=generator)
            * torch.as_tensor(std, dtype=particles.dtype).sqrt()
        )
        return particles + noise * resampled[:, None, None].to(particles.dtype)

    def _ot(self, particles, log_weights, generator, cov, extras, spread=None):
        """Transport resampling: every trial's plan is computed (no host synchronisation), the
        identity kept where the ESS did not trigger; per-particle covariances and extras are moved
        by the same convex combinations."""
        B, n = log_weights.shape
        ess = _ess(log_weights)
        resampled = ess < self.ess_threshold * n
        if self.ess_threshold == 0.0:
            return particles, log_weights, cov, extras or {}, resampled
        T = sinkhorn_transport(particles, log_weights, epsilon=self.ot_epsilon, iterations=self.ot_iterations)
        eye = torch.eye(n, dtype=T.dtype, device=T.device)
        T = torch.where(resampled[:, None, None], T, eye)
        particles = torch.einsum("bij,bi...->bj...", T, particles)
        if cov is not None:
            cov = cov.transported(T)
        if extras:
            extras = {
                k: torch.einsum("bij,bi...->bj...", T.to(v.dtype), v)
                if v.is_floating_point()
                else gather_particles(v, T.argmax(1))
                for k, v in extras.items()
            }
        lw = torch.where(resampled[:, None], torch.full_like(log_weights, -math.log(n)), log_weights)
        return self._regularise(particles, resampled, generator, spread), lw, cov, extras or {}, resampled

    def _soft(self, log_weights: Tensor, generator):
        """Soft resampling: trigger on the ESS of ``W``, draw from ``q`` (no gradient through the
        draw), weigh ``W_a / q_a``."""
        B, n = log_weights.shape
        identity = torch.arange(n, device=log_weights.device).expand(B, n)
        ess = _ess(log_weights)
        resampled = ess < self.ess_threshold * n
        if self.ess_threshold == 0.0:
            return identity, resampled, log_weights
        a = self.soft_alpha
        log_q = (
            log_weights
            if a == 1.0
            else torch.logaddexp(log_weights + math.log(a), torch.full_like(log_weights, math.log1p(-a) - math.log(n)))
        )
        drawn = self._scheme_fn(log_q.detach(), generator, validate=False)
        idx = torch.where(resampled[:, None], drawn, identity)
        lw = gather_particles(log_weights, idx) - gather_particles(log_q, idx)
        lw = lw - torch.logsumexp(lw, dim=-1, keepdim=True)
        return idx, resampled, torch.where(resampled[:, None], lw, log_weights)

    def extra_repr(self) -> str:
        extra = (
            f", soft_alpha={self.soft_alpha}"
            if self.gradient == "soft"
            else f", ot_epsilon={self.ot_epsilon}, ot_iterations={self.ot_iterations}"
            if self.gradient == "ot"
            else ""
        )
        extra += f", sort={self.sort!r}" if self.sort is not None else ""
        return f"scheme={self.scheme!r}, ess_threshold={self.ess_threshold}, gradient={self.gradient!r}{extra}"
