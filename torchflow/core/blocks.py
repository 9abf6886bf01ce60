"""Memory-bounded evaluation of per-particle work in blocks of particles."""

from __future__ import annotations

from typing import Callable, Optional

import torch


def blockwise(fn: Callable, *tensors, chunk: Optional[int] = None, pass_slice: bool = False):
    """``fn(*tensors)`` evaluated on blocks of at most ``chunk`` particles (``None``: all at once).

    Tensors whose dim 1 has the particle count N (taken from the first one) are sliced along it;
    others (``None``, per-trial or ``(B, 1, ...)`` shared ones) are passed whole. Outputs (a tensor
    or a tuple of tensors or ``None``, particles on dim 1) are concatenated. Bounds the memory of per-particle
    evaluations (e.g. the acoustic likelihood's ``(B, N, C, m)`` intermediates) without changing
    the result beyond round-off. ``pass_slice=True`` also passes the block's particle ``slice`` as
    the keyword ``particles``."""
    N = tensors[0].shape[1]
    kw = (lambda sl: {"particles": sl}) if pass_slice else (lambda sl: {})
    if not chunk or N <= chunk:
        return fn(*tensors, **kw(slice(0, N)))
    blocks = []
    for s in range(0, N, chunk):
        args = [
            t[:, s : s + chunk] if isinstance(t, torch.Tensor) and t.dim() > 1 and t.shape[1] == N else t
            for t in tensors
        ]
        blocks.append(fn(*args, **kw(slice(s, s + chunk))))
    if isinstance(blocks[0], tuple):
        return tuple(None if parts[0] is None else torch.cat(parts, 1) for parts in zip(*blocks))
    return torch.cat(blocks, 1)
