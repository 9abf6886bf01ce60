"""Clustered linearisation points (seed 004, Li & Coates; MODELS.md §11): the mixed particle
distance and a batched K-medoids.

A clustered flow linearises at K medoids instead of at every particle and moves each particle with
its cluster's affine map (:func:`~torchflow.flows.integrate_flow` with ``index``). Everything here
is batched over trials: no Python loop over trials, particles or clusters (the K-medoids loop runs
over a fixed number of sweeps, like pseudo-time steps), and no host synchronisation (no
convergence test: a converged assignment is a fixed point of the sweep).
"""
from __future__ import annotations

from typing import Optional, Sequence, Tuple

import torch


def cluster_distance(eta_bar: torch.Tensor, zeta: torch.Tensor, alpha: float = 0.25,
                     support: Optional[Sequence[int]] = None) -> torch.Tensor:
    """Mixed distance ``phi_ij = alpha d~_ij + (1 - alpha) (1 - p_ij)`` between particles.

    Args:
        eta_bar: ``(B, N, d)`` noise-free predictions of the particles.
        zeta: ``(B, N, d)`` their flow velocities at lambda = 0 (``A^i(0) eta_bar^i + b^i(0)``).
        alpha: weight of the Euclidean part (1: Euclidean only, 0: correlation only).
        support: the state coordinates the measurement reads (``None``: all); the Euclidean part
            uses only these, each rescaled to [0, 1] per trial (min-max), since they may carry
            different units.

    Returns:
        ``(B, N, N)``: ``d~ = 2 d / max d`` (Euclidean, in [0, 2]) and ``1 - p`` with ``p`` the
        Pearson correlation of the ``d``-vectors ``zeta^i`` and ``zeta^j`` (each centred by its
        own component mean; UNCONF in the seed: all d components are used), also in [0, 2].
    """
    if not 0.0 <= float(alpha) <= 1.0:
        raise ValueError(f"alpha: expected a weight in [0, 1], got {alpha}")
    x = eta_bar if support is None else eta_bar[..., list(support)]
    lo, hi = x.amin(1, keepdim=True), x.amax(1, keepdim=True)
    tiny = torch.finfo(x.dtype).tiny
    x = (x - lo) / (hi - lo).clamp_min(tiny)
    dist = torch.cdist(x, x, compute_mode="donot_use_mm_for_euclid_dist")  # (B, N, N), exact zeros on the diagonal
    dist = 2 * dist / dist.amax((1, 2), keepdim=True).clamp_min(tiny)
    zc = zeta - zeta.mean(-1, keepdim=True)
    zn = zc / torch.linalg.vector_norm(zc, dim=-1, keepdim=True).clamp_min(tiny)
    corr = (zn @ zn.transpose(-1, -2)).clamp(-1.0, 1.0)
    return alpha * dist + (1 - alpha) * (1 - corr)


def kmedoids(dist: torch.Tensor, n_clusters: int, sweeps: int = 20) -> Tuple[torch.Tensor, torch.Tensor]:
    """Batched alternating K-medoids on distance matrices ``dist (B, N, N)``.

    Initialisation (deterministic, no random draws): sort the points of each trial by their
    distance to the trial's most central point (smallest row sum) and take K evenly spaced ranks.
    Then ``sweeps`` times: assign every point to its nearest medoid, and make each cluster's
    medoid the member with the smallest total distance to the other members (an empty cluster
    keeps its medoid). MODELS.md §11 allows this alternating variant in place of PAM
    (UNCONF: variant and iterations).

    Returns:
        ``index (B, N)`` cluster of each point and ``medoids (B, K)`` the medoids' point indices.
    """
    B, N, _ = dist.shape
    K = int(n_clusters)
    if K < 1:
        raise ValueError(f"n_clusters: expected a positive integer, got {n_clusters}")
    if K >= N:  # every point its own medoid
        ar = torch.arange(N, device=dist.device).expand(B, N)
        return ar.clone(), ar.clone()
    rows = torch.arange(B, device=dist.device)[:, None]
    centre = dist.sum(-1).argmin(-1)  # (B,)
    order = dist[rows[:, 0], centre].argsort(-1)  # (B, N): points by distance to the centre
    ranks = torch.div(torch.arange(K, device=dist.device) * N, K, rounding_mode="floor")
    medoids = order[:, ranks]  # (B, K)
    big = torch.finfo(dist.dtype).max
    kk = torch.arange(K, device=dist.device)
    for _ in range(int(sweeps)):
        index = dist.gather(2, medoids[:, None, :].expand(B, N, K)).argmin(-1)  # (B, N)
        same = index.unsqueeze(-1) == index.unsqueeze(-2)  # (B, N, N)
        cost = (dist * same).sum(-1)  # each point's total distance to its cluster
        member = index.unsqueeze(1) == kk[None, :, None]  # (B, K, N)
        best = torch.where(member, cost.unsqueeze(1), big).argmin(-1)  # (B, K)
        medoids = torch.where(member.any(-1), best, medoids)
    index = dist.gather(2, medoids[:, None, :].expand(B, N, K)).argmin(-1)
    return index, medoids
