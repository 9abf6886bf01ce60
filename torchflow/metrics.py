"""Evaluation metrics for batched Bayesian filters.

Conventions: ``B`` trials, ``T`` time steps, ``d`` state dimension, ``C``
targets, ``k`` position dimension (2 or 3), ``N`` particles. All functions are
batched over trials and time (no Python loops over either), work for float32
and float64 on any device, and return tensors on the input device.

Assignment problems (OMAT, OSPA) are solved exactly. For up to
``tuning.get().assignment_brute_force_max`` (7) items on the larger side this is done by brute force
over all injective maps expressed as tensor ops: a ``(P, m)`` index tensor
built with :func:`itertools.permutations` is used to gather the costs of every
assignment at once. For larger problems the code falls back to
:func:`scipy.optimize.linear_sum_assignment`, which loops in Python over the
``B * T`` problems (on CPU); the resulting assignment is then gathered from the
torch cost tensor, so the returned value keeps autograd information.
"""

from __future__ import annotations

import functools
import itertools
import math
from typing import Optional

import torch

from . import tuning
from ._checks import check_float_tensor, check_same_device, shape_str

__all__ = ["mse", "omat", "ospa", "ess", "log_evidence_relative_error", "lost_tracks"]


def _check_pair(x, ref, name: str, ref_name: str, letters: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Raise unless ``x`` is a floating-point tensor shaped like ``ref`` on its device; both in their common dtype."""
    expected = f"{letters} matching {ref_name} {shape_str(ref.shape)}"
    check_float_tensor(x, name, expected)
    if x.shape != ref.shape:
        raise ValueError(f"{name}: expected {expected}, got {shape_str(x.shape)}")
    check_same_device(x, ref, name, ref_name)
    return _promote(x, ref)


def _promote(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    dtype = torch.promote_types(a.dtype, b.dtype)
    return a.to(dtype), b.to(dtype)


@functools.lru_cache(maxsize=64)
def _injective_maps(n: int, m: int, device: torch.device) -> torch.Tensor:
    """All injective maps {0..m-1} -> {0..n-1} as a ``(P, m)`` long tensor."""
    perms = list(itertools.permutations(range(n), m))
    return torch.tensor(perms, dtype=torch.long, device=device).reshape(len(perms), m)


def _min_assignment_cost(cost: torch.Tensor) -> torch.Tensor:
    """Minimal total cost over injective assignments of rows to columns.

    Args:
        cost: ``(..., m, n)`` cost matrices with ``m <= n``.

    Returns:
        ``(...)`` tensor: ``min_pi sum_i cost[..., i, pi(i)]`` over injective
        ``pi: {0..m-1} -> {0..n-1}``.
    """
    *batch, m, n = cost.shape
    if m == 0:
        return cost.new_zeros(batch)
    flat = cost.reshape(-1, m, n)
    rows = torch.arange(m, device=cost.device)
    knobs = tuning.get()
    if n <= knobs.assignment_brute_force_max:
        maps = _injective_maps(n, m, cost.device)  # (P, m)
        chunk = max(1, knobs.assignment_chunk_elems // (maps.shape[0] * m))
        # Chunking only bounds memory; each chunk is one batched tensor op.
        out = [
            flat[s : s + chunk][:, rows, maps].sum(-1).amin(-1)  # (chunk, P, m) -> (chunk,)
            for s in range(0, flat.shape[0], chunk)
        ]
        result = torch.cat(out) if out else flat.new_zeros(0)
        return result.reshape(batch)

    # Fallback: Python loop over the B*T problems with scipy (CPU).
    from scipy.optimize import linear_sum_assignment

    cost_np = torch.nan_to_num(flat.detach().to("cpu", torch.float64), nan=1e300, posinf=1e300, neginf=-1e300).numpy()
    cols = torch.empty(flat.shape[0], m, dtype=torch.long)
    for i in range(flat.shape[0]):
        r, c = linear_sum_assignment(cost_np[i])
        cols[i, torch.as_tensor(r)] = torch.as_tensor(c)
    cols = cols.to(cost.device)
    picked = flat.gather(-1, cols.unsqueeze(-1)).squeeze(-1)  # (BT, m)
    return picked.sum(-1).reshape(batch)


def _pairwise_dist(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Euclidean distances ``(..., m, k), (..., n, k) -> (..., m, n)``."""
    return torch.linalg.vector_norm(a.unsqueeze(-2) - b.unsqueeze(-3), dim=-1)


def mse(estimates: torch.Tensor, states: torch.Tensor) -> torch.Tensor:
    """Squared estimation error averaged over the state dimension.

    Args:
        estimates: ``(B, T, d)`` state estimates.
        states: ``(B, T, d)`` true states.

    Returns:
        ``(B, T)`` tensor ``mean_j (estimates[..., j] - states[..., j])**2``.
    """
    check_float_tensor(states, "states", "(B, T, d)", ndim=3)
    estimates, states = _check_pair(estimates, states, "estimates", "states", "(B, T, d)")
    if states.shape[-1] == 0:
        raise ValueError("states: expected (B, T, d) with d >= 1, got d = 0")
    return (estimates - states).square().mean(dim=-1)


def omat(est_positions: torch.Tensor, true_positions: torch.Tensor) -> torch.Tensor:
    """Optimal mass transfer (OMAT) error with ``p = 1`` (Li & Coates, omat.m).

    For each trial and step computes
    ``min_pi (1/C) sum_c ||true[c] - est[pi(c)]||_2`` over permutations ``pi``
    of the ``C`` targets (solved as in the module docstring; gradients flow).

    Args:
        est_positions: ``(B, T, C, k)`` estimated target positions, ``k`` in
            ``{2, 3}``.
        true_positions: ``(B, T, C, k)`` true target positions.

    Returns:
        ``(B, T)`` OMAT error (same units as the positions).
    """
    check_float_tensor(true_positions, "true_positions", "(B, T, C, k)", ndim=4)
    ref = shape_str(true_positions.shape)
    if true_positions.shape[-1] not in (2, 3):
        raise ValueError(f"true_positions: expected (B, T, C, k) with k in {{2, 3}}, got {ref}")
    if true_positions.shape[-2] == 0:
        raise ValueError(f"true_positions: expected (B, T, C, k) with C >= 1, got {ref}")
    est_positions, true_positions = _check_pair(est_positions, true_positions, "est_positions", "true_positions",
                                                "(B, T, C, k)")
    dist = _pairwise_dist(true_positions, est_positions)  # (B, T, C, C)
    return _min_assignment_cost(dist) / true_positions.shape[-2]


def ospa(X: torch.Tensor, Y: torch.Tensor, cutoff: float = 40.0, order: float = 1.0,
         X_mask: Optional[torch.Tensor] = None, Y_mask: Optional[torch.Tensor] = None) -> torch.Tensor:
    """OSPA distance between point sets (Schuhmacher et al. 2008), of fixed or varying cardinality.

    With ``m = |X| <= n = |Y|`` (the sets are swapped otherwise),

    ``d = ((1/n) * (min_pi sum_{i<m} min(c, ||x_i - y_pi(i)||)**p + c**p * (n - m)))**(1/p)``

    where ``pi`` ranges over injective maps of the ``m`` items into the ``n``
    items (solved as in the module docstring). ``d = 0`` when ``m = n = 0``.

    Args:
        X: ``(B, T, m, k)`` first point set per trial and step.
        Y: ``(B, T, n, k)`` second point set per trial and step.
        cutoff: Cut-off ``c > 0``.
        order: Order ``p >= 1``.
        X_mask, Y_mask: optional ``(B, T, m)`` / ``(B, T, n)`` bool masks of the real items: sets
            whose cardinality varies over trials and steps (an unknown number of sources) are
            padded to ``m``/``n`` items. Padded items are matched as "absent": a real item paired
            with an absent one costs ``c^p``, two absent ones cost 0, so the minimal perfect
            matching of the padded ``K x K`` problem (``K = max(m, n)``) is the OSPA numerator of
            each problem, divided by its own ``max(|X|, |Y|)``, all in one batched call.
    """
    check_float_tensor(X, "X", "(B, T, m, k)", ndim=4)
    check_float_tensor(Y, "Y", f"(B, T, n, k) matching X {shape_str(X.shape)} in B, T, k", ndim=4)
    if Y.shape[:2] != X.shape[:2] or Y.shape[-1] != X.shape[-1]:
        raise ValueError(f"Y: expected (B, T, n, k) matching X {shape_str(X.shape)} in B, T, k, "
                         f"got {shape_str(Y.shape)}")
    if X.shape[-1] == 0:
        raise ValueError(f"X: expected (B, T, m, k) with k >= 1, got {shape_str(X.shape)}")
    check_same_device(Y, X, "Y", "X")
    cutoff, order = float(cutoff), float(order)
    if not (math.isfinite(cutoff) and cutoff > 0):
        raise ValueError(f"cutoff: expected a finite float > 0, got {cutoff}")
    if not (math.isfinite(order) and order >= 1):
        raise ValueError(f"order: expected a finite float >= 1, got {order}")
    X, Y = _promote(X, Y)
    if X_mask is not None or Y_mask is not None:
        return _ospa_masked(X, Y, cutoff, order, X_mask, Y_mask)
    if X.shape[-2] > Y.shape[-2]:
        X, Y = Y, X
    m, n = X.shape[-2], Y.shape[-2]
    if n == 0:
        return X.new_zeros(X.shape[:2])
    cost = _pairwise_dist(X, Y).clamp(max=cutoff).pow(order)  # (B, T, m, n)
    total = _min_assignment_cost(cost) + cutoff**order * (n - m)
    return (total / n).pow(1.0 / order)


def _ospa_masked(X, Y, cutoff, order, X_mask, Y_mask) -> torch.Tensor:
    """OSPA of padded sets with masks of their real items (see :func:`ospa`)."""
    B, T, m = X.shape[:3]
    n = Y.shape[2]
    for name, mask, size, what in (("X_mask", X_mask, m, "m"), ("Y_mask", Y_mask, n, "n")):
        if mask is not None and (not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool
                                 or tuple(mask.shape) != (B, T, size)):
            got = shape_str(mask.shape) if isinstance(mask, torch.Tensor) else type(mask).__name__
            raise ValueError(f"{name}: expected a bool tensor (B, T, {what}) = ({B}, {T}, {size}), got {got}"
                             + (f" of {mask.dtype}" if isinstance(mask, torch.Tensor) else ""))
    xm = torch.ones(B, T, m, dtype=torch.bool, device=X.device) if X_mask is None else X_mask.to(X.device)
    ym = torch.ones(B, T, n, dtype=torch.bool, device=X.device) if Y_mask is None else Y_mask.to(X.device)
    K = max(m, n)
    if K == 0:
        return X.new_zeros(B, T)
    pad = lambda P, M, k: (torch.cat([P, P.new_zeros(B, T, K - k, P.shape[-1])], 2),  # noqa: E731
                           torch.cat([M, M.new_zeros(B, T, K - k)], 2))
    X, xm = pad(X, xm, m)
    Y, ym = pad(Y, ym, n)
    cp = cutoff**order
    real = _pairwise_dist(X, Y).clamp(max=cutoff).pow(order)  # (B, T, K, K)
    both = xm.unsqueeze(-1) & ym.unsqueeze(-2)
    one = xm.unsqueeze(-1) ^ ym.unsqueeze(-2)
    cost = torch.where(both, real, torch.where(one, torch.full_like(real, cp), torch.zeros_like(real)))
    total = _min_assignment_cost(cost)
    size = torch.maximum(xm.sum(-1), ym.sum(-1)).to(X.dtype)
    return torch.where(size > 0, (total / size.clamp_min(1)).pow(1.0 / order), torch.zeros_like(total))


def ess(log_weights: torch.Tensor) -> torch.Tensor:
    """Effective sample size ``1 / sum_i w_i**2`` of normalised weights.

    Computed in log space from unnormalised log-weights as
    ``exp(2 * logsumexp(lw) - logsumexp(2 * lw))``, so it is invariant to
    adding a constant to ``log_weights`` and does not overflow.

    Args:
        log_weights: ``(..., N)`` unnormalised log-weights (``-inf`` allowed
            for zero weights), ``N >= 1``.

    Returns:
        ``(...)`` effective sample size in ``[1, N]``.
    """
    check_float_tensor(log_weights, "log_weights", "(..., N)")
    if log_weights.dim() == 0 or log_weights.shape[-1] == 0:
        raise ValueError(f"log_weights: expected (..., N) with N >= 1, got {shape_str(log_weights.shape)}")
    lse = torch.logsumexp(log_weights, dim=-1)
    lse2 = torch.logsumexp(2.0 * log_weights, dim=-1)
    return torch.exp(2.0 * lse - lse2)


def log_evidence_relative_error(log_evidence: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """Relative squared error of log-evidence estimates per trial.

    Computes ``((log_evidence - reference) / reference)**2``. Its mean over
    trials is the "relative MSE of log Z" of Pal & Coates (2019), Table I.

    Args:
        log_evidence: ``(B,)`` estimated log marginal likelihoods ``log Zhat``.
        reference: ``(B,)`` reference (true) log marginal likelihoods ``log Z``.

    Returns:
        ``(B,)`` relative squared error.
    """
    check_float_tensor(reference, "reference", "(B,)", ndim=1)
    log_evidence, reference = _check_pair(log_evidence, reference, "log_evidence", "reference", "(B,)")
    return ((log_evidence - reference) / reference).square()


def lost_tracks(omat_per_step: torch.Tensor, threshold: float = 2.0) -> torch.Tensor:
    """Flags trials whose time-averaged OMAT error exceeds a threshold.

    Args:
        omat_per_step: ``(B, T)`` OMAT error per trial and step (e.g. from
            :func:`omat`), ``T >= 1``.
        threshold: Loss threshold (meters); a trial is lost when
            ``mean_t omat_per_step[b, t] > threshold`` (strict).

    Returns:
        ``(B,)`` boolean tensor, ``True`` for lost trials.
    """
    check_float_tensor(omat_per_step, "omat_per_step", "(B, T)", ndim=2)
    if omat_per_step.shape[1] == 0:
        raise ValueError(f"omat_per_step: expected (B, T) with T >= 1, got {shape_str(omat_per_step.shape)}")
    threshold = float(threshold)
    if not math.isfinite(threshold):
        raise ValueError(f"threshold: expected a finite float, got {threshold}")
    return omat_per_step.mean(dim=1) > threshold
