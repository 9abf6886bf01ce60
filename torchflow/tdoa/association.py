"""Probabilistic data association by loopy belief propagation (Williams & Lau 2014; Meyer et al.
2017/2018; the framework of Zhang, Khojasteh, Atanasov & Meyer 2024), batched over runs with padded objects and
measurements.

For K legacy potential objects (POs) and M measurements of one sensor, the association variable
``a_k in {0 (missed), 1..M}`` of each PO and the exclusion "a measurement has at most one PO"
form a factor graph whose only loops are the object-measurement ones. Inputs are the local terms

    beta_k(0) = 1 - r_k p_d,     beta_k(m) = r_k p_d int f_k l_m dx / (mu_c f_c(z_m)),
    xi(m) = 1 + mu_b int f_b l_m dx / (mu_c f_c(z_m))    (clutter or a new PO),

and the messages iterate a fixed number of times (no convergence test, so no host
synchronisation; a converged message is a fixed point of the iteration):

    zeta_{k->m} = beta_k(m) / (beta_k(0) + sum_{m' != m} beta_k(m') nu_{m'->k}),
    nu_{m->k} = 1 / (xi(m) + sum_{k' != k} zeta_{k'->m}).

Outputs are the approximate marginals ``p(a_k = m)`` and the messages the PO updates need.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from torchflow.core.checks import check_count
from torchflow.core.errors import ArgumentError


@dataclass
class Association:
    """Result of :func:`loopy_association`.

    Attributes:
        probabilities: ``(B, K, M + 1)`` approximate ``p(a_k = m)`` (column 0: missed detection);
            rows of padded POs are 0.
        nu: ``(B, K, M)`` messages ``nu_{m->k}`` (measurement to PO), 0 for padding.
        zeta: ``(B, K, M)`` messages ``zeta_{k->m}``.
        new_existence: ``(B, M)`` existence probability of the new PO of each measurement,
            ``(xi(m) - 1) / (xi(m) + sum_k zeta_{k->m})``.
    """

    probabilities: torch.Tensor
    nu: torch.Tensor
    zeta: torch.Tensor
    new_existence: torch.Tensor


def loopy_association(
    beta: torch.Tensor,
    xi: torch.Tensor,
    object_mask: Optional[torch.Tensor] = None,
    measurement_mask: Optional[torch.Tensor] = None,
    iterations: int = 20,
) -> Association:
    """Loopy BP for data association (see the module docstring).

    Args:
        beta: ``(B, K, M + 1)`` local terms ``beta_k(m)`` (column 0: missed detection), >= 0.
        xi: ``(B, M)`` terms ``xi(m) >= 1`` of clutter or a new PO.
        object_mask, measurement_mask: ``(B, K)`` / ``(B, M)`` bool, the real POs and measurements
            (``None``: all real).
        iterations: message passes (default 20).

    Returns:
        :class:`Association`.
    """
    if beta.dim() != 3:
        raise ArgumentError(f"beta: expected (B, K, M + 1), got {tuple(beta.shape)}")
    B, K, M1 = beta.shape
    M = M1 - 1
    if xi.shape != (B, M):
        raise ArgumentError(
            f"xi: expected (B, M) = ({B}, {M}) to match beta {tuple(beta.shape)}, got {tuple(xi.shape)}"
        )
    iterations = check_count("iterations", iterations)
    om = torch.ones(B, K, dtype=torch.bool, device=beta.device) if object_mask is None else object_mask
    mm = torch.ones(B, M, dtype=torch.bool, device=beta.device) if measurement_mask is None else measurement_mask
    for name, mask, shape in (("object_mask", om, (B, K)), ("measurement_mask", mm, (B, M))):
        if mask.dtype != torch.bool or tuple(mask.shape) != shape:
            raise ArgumentError(f"{name}: expected a bool tensor {shape}, got {tuple(mask.shape)} of {mask.dtype}")
    live = om.unsqueeze(-1) & mm.unsqueeze(-2)  # (B, K, M)
    b0 = beta[..., 0]
    zero = beta.new_zeros(())
    bm = torch.where(live, beta[..., 1:], zero)  # padded pairs contribute nothing (even nan or inf)
    b0 = torch.where(om, b0, torch.ones_like(b0))
    nu = live.to(beta.dtype)  # nu^(0) = 1
    zeta = torch.zeros_like(bm)
    # leave-one-out sums by exclusion, never by subtraction: a certain PO (beta_k(0) = 0) with one
    # dominant measurement makes "total - own term" cancel to round-off (and inf - inf = nan)
    other_m = ~torch.eye(M, dtype=torch.bool, device=beta.device)  # (m, m')
    other_k = ~torch.eye(K, dtype=torch.bool, device=beta.device)  # (k, k')
    for _ in range(iterations):
        bn = (bm * nu).unsqueeze(-2)  # (B, K, 1, M'): beta_k(m') nu_{m'->k}, finite
        loo_m = torch.where(other_m, bn, zero).sum(-1)  # (B, K, M)
        # inf where a certain PO has no other measurement; 0 (not 0/0) where beta_k(m) = 0
        zeta = torch.where(bm > 0, bm / (b0.unsqueeze(-1) + loo_m), zero)
        zk = zeta.unsqueeze(1)  # (B, 1, K', M)
        loo_k = torch.where(other_k.unsqueeze(-1), zk, zero).sum(2)  # (B, K, M), no inf * 0
        nu = torch.where(live, 1 / (xi.unsqueeze(-2) + loo_k), zero)
    un = torch.cat([b0.unsqueeze(-1), bm * nu], -1) * om.unsqueeze(-1)
    prob = un / un.sum(-1, keepdim=True).clamp_min(torch.finfo(beta.dtype).tiny)
    new = torch.where(mm, (xi - 1) / (xi + torch.where(live, zeta, zero).sum(-2)), zero)
    return Association(prob, nu, zeta, new)


__all__ = ["Association", "loopy_association"]
