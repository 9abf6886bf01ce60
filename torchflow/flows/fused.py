"""A fused GPU kernel for one pseudo-time step of the exact Daum-Huang flows at per-particle points
(PF-PF(LEDH)): the coefficients of :func:`~torchflow.flows.daum_huang.daum_huang_coefficients` and
the Euler step of the particle and its point, one particle per GPU thread, every ``k x k`` matrix
in that thread's registers.

Why: on a GPU the unfused pseudo-step is ~85 kernels over ``(B, N, k, k)`` tensors, and the
batched library kernels for tiny matrices are slow (H200, float64, 50,000 matrices of 8 x 8: a
batched product 189 us, a Cholesky 216 us, where an elementwise pass takes ~25 us;
``experiments/benchmarks/micro_small_linalg.py``). Here a point's ``S = (W L_s)^T (W L_s)``, the
two Cholesky factors of ``I + lambda S`` and ``I + (lambda - eps/2) S``, the log-determinant, the
four applications of ``A = -1/2 L (I + lambda S)^{-1} L_s^T W^T W`` (three solves: see
:func:`~torchflow.flows._fused_kernel.kernel_rows`) and the moves of the particle and its point are
one kernel. The measurement's linearisation stays in torch (any model), unless the model declares
it in the kernel's terms (:meth:`~torchflow.models.StateSpaceModel.fused_measurement`, acoustic
tracking; ``tuning.fused_measurement``): then the kernel computes each row of W and y at the
points itself and no ``(B, N, m, k)`` Jacobian is written or read.

PF-PF(LEDH), acoustic, 100 trials x 500 particles, float64, H100, seconds per time step
(``experiments/benchmarks/ab_fused.py``, one run): the torch path 0.095, the first fused kernel
(one program per particle, retired) 0.071, this one 0.053, with the measurement inside 0.031.

Arithmetic: float64 inside (float32 runs load and store their own dtype; the ``k x k`` algebra is
float64 as :attr:`~torchflow.flows.daum_huang.EDHFlow.promote_low_precision` asks). The same
formulas as the unfused path, reassociated, so the numbers agree to round-off
(``tests/flows/test_fused.py``: 1e-12 relative in float64), not bit for bit.

Used by :func:`~torchflow.flows.integrate_flow` when Triton is importable, the tensors are on CUDA,
no gradient is recorded, the flow is :class:`~torchflow.flows.EDHFlow` or
:class:`~torchflow.flows.LEDHFlow` itself at per-particle points, ``k <= 32`` measured
coordinates, and ``torchflow.tuning`` ``fused_flows`` is 1 (the default); otherwise the torch path.
Set ``TRITON_INTERPRET=1`` before the first import of Triton to run it on the CPU (tests).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from .. import _triton

__all__ = ["available", "dh_particle_step", "FusedMeasurement"]

available, interpreted = _triton.available, _triton.interpreted  # shared with torchflow.random's fused draws


_kernel = None


#: warps per program (32 particles each); 1, 2 and 4 ran alike on an H100 (``ab_fused``)
ROWS_WARPS = 1


def _build():
    from ._fused_kernel import kernel_rows
    return kernel_rows


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


@dataclass
class FusedMeasurement:
    """A measurement the fused kernel linearises itself (``tuning`` ``fused_measurement=1``), so that no ``(B, N, m, k)`` Jacobian is written and read per
    pseudo-step. ``kind`` 1: ``h_i(x) = psi sum_c 1 / (|p_c - s_i| + d0)`` over the 2-D positions
    ``p_c`` (support coordinates ``2c, 2c + 1``) and sensors ``s_i`` (``sensors (m, 2)``), with a
    scalar R (acoustic tracking, :meth:`~torchflow.models.AcousticTracking.fused_measurement`)."""

    kind: int
    sensors: torch.Tensor
    psi: torch.Tensor
    d0: torch.Tensor


def dh_particle_step(W: Optional[torch.Tensor], y: torch.Tensor, L: torch.Tensor, Ls: torch.Tensor, Pc: torch.Tensor,
                     mean: torch.Tensor, support: Optional[torch.Tensor], eta: torch.Tensor, aux: torch.Tensor,
                     log_det: torch.Tensor, lams: torch.Tensor, epss: torch.Tensor, j: int,
                     measure: Optional[FusedMeasurement] = None, inv_sigma: Optional[torch.Tensor] = None):
    """One Euler step of EDH/LEDH at per-particle points, fused (see the module docstring).

    Args:
        W: ``(B, N, m, k)`` whitened Jacobians at the points, or a shared ``(m, k)``; y: ``(B, N, m)``.
            With ``measure``: ``W`` is ``None`` and ``y`` is the whitened observation ``z / sigma``
            ``(B, m)``; the kernel linearises at the points.
        L, Pc: ``(B, N|1, d, k)`` prior root columns and ``P[:, support]``; Ls: ``(B, N|1, k, k)``.
        mean: ``(B, N|1, d)`` prior mean eta_bar_0; support: ``(k,)`` measured coordinates or ``None``.
        eta, aux: ``(B, N, d)`` particles and their points (contiguous).
        log_det: ``(B, N)`` contiguous accumulator, updated in place.
        lams, epss: the schedule's pseudo-times and step sizes (device tensors); j: the step.
        measure, inv_sigma: a :class:`FusedMeasurement` and the 0-d ``1 / sigma`` of its scalar R.

    Returns:
        ``(eta, aux)`` after the step (new tensors).
    """
    global _kernel
    if _kernel is None:
        _kernel = _build()
    B, N, d = eta.shape
    if support is None:
        support = torch.arange(d, device=eta.device)
    k = len(support)
    if measure is not None:
        m = measure.sensors.shape[0]
        W, sW = y, (0, 0, 0, 0)  # not read
        y, sY = _bn_strides(y.unsqueeze(-2), B, N, 1)
        sens = measure.sensors.contiguous()
        const = torch.stack([measure.psi * inv_sigma, measure.d0]).to(torch.float64)
    else:
        m = W.shape[-2]
        W, sW = _bn_strides(W, B, N, 2)
        y, sY = _bn_strides(y, B, N, 1)
        sens = const = lams  # not read
    L, sL = _bn_strides(L, B, N, 2)
    Ls, sS = _bn_strides(Ls, B, N, 2)
    Pc, sP = _bn_strides(Pc, B, N, 2)
    mean, sM = _bn_strides(mean, B, N, 1)
    eta, aux = eta.contiguous(), aux.contiguous()
    sE = eta.stride()
    eta_out, aux_out = torch.empty_like(eta), torch.empty_like(aux)
    BK, BD = tile(k), tile(d)
    bp = 32 * ROWS_WARPS
    _kernel[(-(-B * N // bp),)](W, *sW, y, *sY, L, *sL, Ls, *sS, Pc, *sP, mean, *sM, support, eta, aux, *sE, eta_out,
                                aux_out, log_det, lams, epss, j, sens, const, B * N, N, m, d, k, BK=BK, BD=BD, BP=bp,
                                LIN=0 if measure is None else measure.kind, num_warps=ROWS_WARPS)
    return eta_out, aux_out
