"""Whether Triton's kernels can run here: shared by the fused flow step (:mod:`torchflow.flows.kernels.steps`)
and the fused Philox draws (:mod:`torchflow.core.random`). Triton is an optional dependency (CUDA builds
of PyTorch bring it)."""

from __future__ import annotations

import importlib
import os

_available = None


def available() -> bool:
    """Triton can be imported (cached)."""
    global _available
    if _available is None:
        try:
            importlib.import_module("triton")  # an availability test
            _available = True
        except Exception:
            _available = False
        if _available and interpreted():
            _interpreter_loop_bounds()
    return _available


def _interpreter_loop_bounds() -> None:
    """Triton 3.6's CPU interpreter turns a kernel's integer argument used as a loop bound
    (``for i in range(m)``) into a Python int with ``int()`` of a one-element 1-D array, which
    NumPy 2.x refuses ("only 0-dimensional arrays can be converted to Python scalars"); NumPy 1.x
    only warned. Read the element instead. Interpreter only: compiled kernels are untouched."""
    try:
        from triton.runtime import interpreter
    except Exception:
        return
    patch = getattr(interpreter, "_patch_lang_tensor", None)
    if patch is None or getattr(patch, "_torchflow", False):
        return

    def patched(tensor, scope):
        patch(tensor, scope)
        scope.set_attr(tensor, "__index__", lambda self: int(self.handle.data.reshape(-1)[0]))

    patched._torchflow = True
    interpreter._patch_lang_tensor = patched


def interpreted() -> bool:
    """Triton runs its interpreter on the CPU (``TRITON_INTERPRET=1``, set before Triton's import)."""
    return os.environ.get("TRITON_INTERPRET", "0") not in ("", "0")


def runs_on(device) -> bool:
    """A Triton kernel can run on tensors of ``device``: CUDA, or the CPU under the interpreter."""
    import torch

    device = torch.device(device)
    return available() and (device.type == "cuda" or (device.type == "cpu" and interpreted()))
