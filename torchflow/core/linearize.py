"""Jacobians by ``torch.func``: ``jacrev`` vmapped over any leading batch shape."""

from __future__ import annotations

from typing import Callable

import torch
from torch.func import jacrev, vmap


def jacobian(fn: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """Jacobian of a pointwise map ``fn: (d,) -> (m,)`` at every point of ``x (..., d)``.

    ``fn`` must act on one point at a time (or broadcast over leading dims; it is called on single
    points under ``vmap``). Returns ``(..., m, d)``.
    """
    lead = x.shape[:-1]
    flat = x.reshape(-1, x.shape[-1])
    J = vmap(jacrev(fn))(flat)
    return J.reshape(*lead, *J.shape[-2:])
