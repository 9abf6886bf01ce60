"""Whether Triton's kernels can run here: shared by the fused flow step (:mod:`torchflow.flows.fused`)
and the fused Philox draws (:mod:`torchflow.random`). Triton is an optional dependency (CUDA builds
of PyTorch bring it)."""
from __future__ import annotations

import os

_available = None


def available() -> bool:
    """Triton can be imported (cached)."""
    global _available
    if _available is None:
        try:
            import triton  # noqa: F401  (pyflakes: unused on purpose, an availability test)
            _available = True
        except Exception:  # noqa: BLE001 - any import failure means: not available
            _available = False
    return _available


def interpreted() -> bool:
    """Triton runs its interpreter on the CPU (``TRITON_INTERPRET=1``, set before Triton's import)."""
    return os.environ.get("TRITON_INTERPRET", "0") not in ("", "0")


def runs_on(device) -> bool:
    """A Triton kernel can run on tensors of ``device``: CUDA, or the CPU under the interpreter."""
    import torch
    device = torch.device(device)
    return available() and (device.type == "cuda" or (device.type == "cpu" and interpreted()))
