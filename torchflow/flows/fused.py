"""A fused GPU kernel for one pseudo-time step of the exact Daum-Huang flows at per-particle points
(PF-PF(LEDH)): the coefficients of :func:`~torchflow.flows.daum_huang.daum_huang_coefficients` and
the Euler step of the particle and its point, one Triton program per point, every ``k x k`` matrix
in registers.

Why: on a GPU the unfused pseudo-step is ~85 kernels over ``(B, N, k, k)`` tensors, and the
batched library kernels for tiny matrices are slow (H200, float64, 50,000 matrices of 8 x 8: a
batched product 189 us, a Cholesky 216 us, where an elementwise pass takes ~25 us;
``experiments/benchmarks/micro_small_linalg.py``). PF-PF(LEDH) on acoustic tracking (100 trials x
500 particles) spent ~100 ms of kernel time per time step, 60 % of it in those calls
(``experiments/benchmarks/profile_step.py``). Here a point's ``S = L_s^T W^T W L_s``, the two
Cholesky factors of ``I + lambda S`` and ``I + (lambda - eps/2) S``, the log-determinant, the four
applications of ``A = -1/2 L (I + lambda S)^{-1} L_s^T W^T W`` and the moves of the particle and
its point are one kernel; the measurement's linearisation stays in torch (any model).

Arithmetic: float64 inside (float32 runs load and store their own dtype; the ``k x k`` algebra is
float64 as :attr:`~torchflow.flows.daum_huang.EDHFlow.promote_low_precision` asks). The same
formulas as the unfused path, applied to vectors instead of forming A, so the numbers agree to
round-off (``tests/flows/test_fused.py``), not bit for bit.

Used by :func:`~torchflow.flows.integrate_flow` when Triton is importable, the tensors are on CUDA,
no gradient is recorded, the flow is :class:`~torchflow.flows.EDHFlow` or
:class:`~torchflow.flows.LEDHFlow` itself at per-particle points, ``k <= 32`` measured
coordinates, and ``torchflow.tuning`` ``fused_flows`` is 1 (the default); otherwise the torch path.
Set ``TRITON_INTERPRET=1`` before the first import of Triton to run it on the CPU (tests).
"""
from __future__ import annotations

from typing import Optional

import torch

from .. import _triton

__all__ = ["available", "dh_particle_step"]

available, interpreted = _triton.available, _triton.interpreted  # shared with torchflow.random's fused draws


_kernel = None


def _build():
    from ._fused_kernel import kernel
    return kernel


def _bn_strides(t: torch.Tensor, B: int, N: int, tail: int):
    """``t`` viewed as ``(B, N, *tail dims)`` (broadcast where it has no such dimension) and its
    strides."""
    shape = (B, N) + tuple(t.shape[-tail:])
    t = t.reshape(*((1,) * (2 + tail - t.dim())), *t.shape) if t.dim() < 2 + tail else t
    t = t.expand(shape)
    return t, t.stride()


def tile(x: int) -> int:
    """The kernel's tile size for a dimension of ``x``: the next power of two (at least 2)."""
    return max(2, 1 << (int(x) - 1).bit_length())


def dh_particle_step(W: torch.Tensor, y: torch.Tensor, L: torch.Tensor, Ls: torch.Tensor, Pc: torch.Tensor,
                     mean: torch.Tensor, support: Optional[torch.Tensor], eta: torch.Tensor, aux: torch.Tensor,
                     log_det: torch.Tensor, lams: torch.Tensor, epss: torch.Tensor, j: int):
    """One Euler step of EDH/LEDH at per-particle points, fused (see the module docstring).

    Args:
        W: ``(B, N, m, k)`` whitened Jacobians at the points, or a shared ``(m, k)``; y: ``(B, N, m)``.
        L, Pc: ``(B, N|1, d, k)`` prior root columns and ``P[:, support]``; Ls: ``(B, N|1, k, k)``.
        mean: ``(B, N|1, d)`` prior mean eta_bar_0; support: ``(k,)`` measured coordinates or ``None``.
        eta, aux: ``(B, N, d)`` particles and their points (contiguous).
        log_det: ``(B, N)`` contiguous accumulator, updated in place.
        lams, epss: the schedule's pseudo-times and step sizes (device tensors); j: the step.

    Returns:
        ``(eta, aux)`` after the step (new tensors).
    """
    global _kernel
    if _kernel is None:
        _kernel = _build()
    B, N, d = eta.shape
    m, k = W.shape[-2:]
    if support is None:
        support = torch.arange(d, device=eta.device)
    W, sW = _bn_strides(W, B, N, 2)
    y, sY = _bn_strides(y, B, N, 1)
    L, sL = _bn_strides(L, B, N, 2)
    Ls, sS = _bn_strides(Ls, B, N, 2)
    Pc, sP = _bn_strides(Pc, B, N, 2)
    mean, sM = _bn_strides(mean, B, N, 1)
    eta, aux = eta.contiguous(), aux.contiguous()
    sE = eta.stride()
    eta_out, aux_out = torch.empty_like(eta), torch.empty_like(aux)
    BK, BM, BD = tile(k), tile(m), tile(d)
    _kernel[(B * N,)](W, *sW, y, *sY, L, *sL, Ls, *sS, Pc, *sP, mean, *sM, support, eta, aux, *sE, eta_out, aux_out,
                      log_det, lams, epss, j, N, m, d, k, BM=BM, BK=BK, BD=BD,
                      num_warps=1 if BK * BK * BM <= 4096 else 4)
    return eta_out, aux_out
