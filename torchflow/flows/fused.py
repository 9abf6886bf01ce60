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

Two forms of the kernel (``tuning.fused_info``): the row form (:func:`~torchflow.flows._fused_kernel.kernel_rows`)
accumulates ``S = V^T V`` over the rows of ``V = W L_s``, reading each particle's ``L_s`` once per
row of W (25 times per pseudo-step for acoustic tracking) in two passes; the information form
(:func:`~torchflow.flows._fused_kernel.kernel_info`, the default) accumulates ``G = W^T W`` in one
pass and works with the prior precision ``P_s^{-1}`` and ``C = L L_s^{-1}``, formed once per
integration (:func:`info_factors`). H200, 100 x 500, float64, one run (``ab_fused --short``):
0.0237 s per time step in row form, 0.0221 in information form (the torch path 0.0821); the
kernel itself 218 us per pseudo-step on the H200 (``results_profile_ledh_gpu_s8.txt``), where the
row form took 420 us on an H100 (seventh session: another card, not a paired comparison).

Arithmetic: float64 inside (float32 runs load and store their own dtype; the ``k x k`` algebra is
float64 as :attr:`~torchflow.flows.daum_huang.EDHFlow.promote_low_precision` asks). The same
formulas as the unfused path, reassociated, so the numbers agree to round-off
(``tests/flows/test_fused.py``: 1e-12 relative in float64), not bit for bit.

**On the CPU** the same pseudo-step is a Numba kernel (:mod:`torchflow.flows._fused_cpu`, Numba an
optional dependency, the ``kernels`` extra): 64 particles side by side in SIMD lanes, blocks of
particles on the threads (``torch.get_num_threads()`` of them). PF-PF(LEDH), acoustic, 20 trials x
500 particles, float64, this project's 2-core CPU: 1.47 s per time step on the torch path, 0.59 s
with the kernel (0.21 s of it the kernel, 7 ms per pseudo-step), aten ops per time step 3,820 ->
527. Its first call in a process compiles it (~20 s; then cached on disk by Numba next to this
module, or in Numba's user cache directory where that is not writable).

The Gromov flow (:class:`~torchflow.flows.GromovFlow`, ``noise_root="factor"``) at per-particle
points has a CPU kernel too (:class:`GromovSteps`, :func:`torchflow.flows._fused_cpu.gromov_step`):
its coefficients, the Euler-Maruyama move of each particle and its point, and the tracked Gaussian
law (mean and ``d x d`` covariance) of PF-PF(Gromov)'s proposal in one kernel per pseudo-step, the
step's normals drawn by torch as before (the same draws). PF-PF(Gromov), acoustic, 8 trials x 500,
1 thread: 0.37 s per trial-step on the torch path, 0.14 s fused; aten ops per time step 4,157 ->
717. No GPU kernel for it yet.

GPFIS's transport (:func:`~torchflow.flows.gpfis.gpfis_flow`, Cholesky root, analytic Jacobian)
has a CPU kernel too (:class:`GPFISSteps`, :func:`torchflow.flows._fused_cpu.gpfis_step`): each
step's move and the ``log|det|`` of its ``k x k`` Jacobian, with the step's tangents as rank-``2b``
updates (``b``: the measurement's second-derivative block size), every step in one call when the
kernel linearises the acoustic measurement itself. GPFIS, acoustic, N = 500, this 2-core CPU: 0.181
-> 0.028 s per trial-step; aten ops per time step 7,696 -> 229. No GPU kernel for it yet.

EDH/LEDH at per-particle points whose whitened Jacobian is diagonal by declaration and too large for
the lane kernel's tiles (the skewed-t / Poisson model, d = 64 and 144) have a CPU kernel in
information form (:class:`DiagonalSteps`, :func:`torchflow.flows._fused_cpu.dh_diag_step`): with
``D = W^T W`` diagonal, ``L (I + lam L^T D L)^{-1} L^T = (P^{-1} + lam D)^{-1}``, so a pseudo-step is
two ``d x d`` Cholesky factorisations of ``P^{-1} + h D`` per particle (its own, at 15 GFLOP/s per
core, where torch's batched one runs at 5) and a few solves, with no ``d x d x d`` product; ``P^{-1}``
once per integration. PFGSPF (G = 5 x 200), d = 144, this 2-core CPU: 25.4 -> 1.6-2.0 s per
trial-step; PF-PF(LEDH) with 1000 particles 24.6 -> 5.4 s.

Used by :func:`~torchflow.flows.integrate_flow` when no gradient is recorded, the flow is
:class:`~torchflow.flows.EDHFlow` or :class:`~torchflow.flows.LEDHFlow` itself at per-particle
points, the tiles are small enough (``k`` measured coordinates: ``tile(m) tile(k)^2 <= 16384``,
``tile(d) tile(k) <= 4096``) and ``torchflow.tuning`` ``fused_flows`` is 1 (the default), on CUDA
with Triton importable or on the CPU with Numba importable; otherwise the torch path. Set
``TRITON_INTERPRET=1`` before the first import of Triton to run Triton's kernel on the CPU instead
(tests).
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from .. import _triton

__all__ = ["available", "dh_particle_step", "FusedMeasurement", "ParticleSteps", "GromovSteps", "GPFISSteps", "DiagonalSteps"]

available, interpreted = _triton.available, _triton.interpreted  # shared with torchflow.random's fused draws


_kernels = {}


#: warps per program (32 particles each); 1, 2 and 4 ran alike on an H100 (``ab_fused``)
ROWS_WARPS = 1



def kernel_form() -> str:
    """The GPU kernel's form (``tuning.fused_info``): ``"info"``
    (:func:`~torchflow.flows._fused_kernel.kernel_info`: ``G = W^T W`` and the prior precision, one
    pass over the rows of W) or ``"rows"`` (:func:`~torchflow.flows._fused_kernel.kernel_rows`:
    ``S = (W L_s)^T (W L_s)``, two passes)."""
    from .. import tuning
    return "info" if tuning.get().fused_info else "rows"


def _build(form: str):
    if form not in _kernels:
        from . import _fused_kernel
        _kernels[form] = getattr(_fused_kernel, "kernel_" + form)
    return _kernels[form]


def info_factors(L: torch.Tensor, Ls: torch.Tensor):
    """The prior's factors of the information-form kernel, once per integration: ``C = L L_s^{-1}``
    ``(..., d, k)`` and the precision ``P_s^{-1} = L_s^{-T} L_s^{-1}`` ``(..., k, k)`` of the
    measured coordinates (float64, triangular solves), from the root columns ``L (..., d, k)`` and
    their rows at the support ``L_s (..., k, k)`` (lower triangular)."""
    L, Ls = L.to(torch.float64), Ls.to(torch.float64)
    C = torch.linalg.solve_triangular(Ls, L, upper=False, left=False)
    eye = torch.eye(Ls.shape[-1], dtype=torch.float64, device=Ls.device)
    inv = torch.linalg.solve_triangular(Ls, eye.expand(Ls.shape), upper=False)
    return C, inv.transpose(-1, -2) @ inv


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
                     measure: Optional[FusedMeasurement] = None, inv_sigma: Optional[torch.Tensor] = None,
                     info=None, form: Optional[str] = None):
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
        info: :func:`info_factors` ``(L, Ls)`` if computed already; form: the kernel's form,
            ``"info"`` or ``"rows"`` (default :func:`kernel_form`).

    Returns:
        ``(eta, aux)`` after the step (new tensors).
    """
    form = kernel_form() if form is None else form
    kernel = _build(form)
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
    if form == "info":  # the kernel reads C = L L_s^{-1} and P_s^{-1} in place of L and L_s
        L, Ls = info_factors(L, Ls) if info is None else info
    L, sL = _bn_strides(L, B, N, 2)
    Ls, sS = _bn_strides(Ls, B, N, 2)
    Pc, sP = _bn_strides(Pc, B, N, 2)
    mean, sM = _bn_strides(mean, B, N, 1)
    eta, aux = eta.contiguous(), aux.contiguous()
    sE = eta.stride()
    eta_out, aux_out = torch.empty_like(eta), torch.empty_like(aux)
    BK, BD = tile(k), tile(d)
    bp = 32 * ROWS_WARPS
    kernel[(-(-B * N // bp),)](W, *sW, y, *sY, L, *sL, Ls, *sS, Pc, *sP, mean, *sM, support, eta, aux, *sE, eta_out,
                                aux_out, log_det, lams, epss, j, sens, const, B * N, N, m, d, k, BK=BK, BD=BD, BP=bp,
                                LIN=0 if measure is None else measure.kind, num_warps=ROWS_WARPS)
    return eta_out, aux_out


class ParticleSteps:
    """The fused pseudo-steps of one flow integration, set up once: the prior's factors, the
    schedule and the measurement do not change between steps. ``steps(j, eta, aux, log_det[, W, y])``
    is :func:`dh_particle_step` for step ``j`` (``W``, ``y`` at the points unless ``measure``).
    On CUDA (or Triton's interpreter) Triton's kernel; on the CPU Numba's
    (:mod:`torchflow.flows._fused_cpu`), whose inputs are converted to NumPy here once."""

    def __init__(self, L, Ls, Pc, mean, support, lams, epss, measure=None, inv_sigma=None, z_scaled=None):
        self.prior = (L, Ls, Pc, mean, support)
        self.lams, self.epss, self.measure, self.inv_sigma, self.z_scaled = lams, epss, measure, inv_sigma, z_scaled
        self.cpu = mean.device.type == "cpu" and not _triton.runs_on(mean.device)
        self.form = kernel_form()
        self.info = info_factors(L, Ls) if not self.cpu and self.form == "info" else None
        if self.cpu:
            d = mean.shape[-1]
            sup = torch.arange(d, device=mean.device) if support is None else support
            self.args = (_f64(L, 4), _f64(Ls, 4), _f64(Pc, 4), _f64(mean, 3), _np(sup.to(torch.int64)))
            self.sched, self.lin = _cpu_constants(lams, epss, measure, inv_sigma, z_scaled)

    def __call__(self, j: int, eta, aux, log_det, W=None, y=None):
        if not self.cpu:
            if self.measure is not None:
                W, y = None, self.z_scaled
            return dh_particle_step(W, y, *self.prior, eta, aux, log_det, self.lams, self.epss, j,
                                    measure=self.measure, inv_sigma=self.inv_sigma, info=self.info,
                                    form=self.form)
        Wn, yn, lin, sens, const = _cpu_rows(self.lin, W, y)
        e64, a64 = _f64(eta, 3), _f64(aux, 3)
        eta_out, aux_out = np.empty_like(e64), np.empty_like(a64)
        ld = log_det if log_det.dtype == torch.float64 and log_det.is_contiguous() else log_det.to(torch.float64).contiguous()
        _set_threads()
        _cpu_kernel()(Wn, yn, *self.args, e64, a64, eta_out, aux_out, _np(ld), *self.sched, j, lin, sens, const)
        if ld is not log_det:
            log_det.copy_(ld)
        return tuple(_cpu_back((eta_out, aux_out), eta.dtype))


class GromovSteps:
    """The Gromov flow's Euler-Maruyama pseudo-steps at per-particle points on the CPU, fused
    (:func:`torchflow.flows._fused_cpu.gromov_step`, Numba): set up once per integration like
    :class:`ParticleSteps`. ``steps(j, eta, aux, mu, Sig, xi[, W, y])`` returns the moved particle,
    point and (when ``mu``, ``Sig`` are given: the tracked Gaussian law) ``mu`` and ``Sig
    (B, N, d, d)``; ``xi (B, N, m)`` are the step's standard normals."""

    def __init__(self, L, Ls, support, lams, epss, measure=None, inv_sigma=None, z_scaled=None):
        d = L.shape[-2]
        sup = torch.arange(d, device=L.device) if support is None else support
        self.args = (_f64(L, 4), _f64(Ls, 4), _np(sup.to(torch.int64)))
        self.sched, self.lin = _cpu_constants(lams, epss, measure, inv_sigma, z_scaled)

    def __call__(self, j: int, eta, aux, mu, Sig, xi, W=None, y=None):
        Wn, yn, lin, sens, const = _cpu_rows(self.lin, W, y)
        track = mu is not None
        e64, a64 = _f64(eta, 3), _f64(aux, 3)
        B, N, d = e64.shape
        outs = [np.empty_like(e64), np.empty_like(a64)]
        if track:
            m64, S64 = _f64(mu, 3), _f64(Sig, 4)
            outs += [np.empty_like(m64), np.empty((B, N, d, d))]
        else:
            m64, S64 = np.zeros((1, 1, 1)), np.zeros((1, 1, 1, 1))
            outs += [m64, S64]
        _set_threads()
        _gromov_kernel()(Wn, yn, *self.args, e64, a64, m64, S64, _f64(xi, 3), *outs, *self.sched, j, lin, sens, const,
                         int(track))
        res = _cpu_back(outs if track else outs[:2], eta.dtype)
        return tuple(res) if track else (res[0], res[1], None, None)


class DiagonalSteps:
    """EDH/LEDH pseudo-steps at per-particle points for a measurement whose whitened Jacobian is
    diagonal by declaration (:attr:`~torchflow.flows.GaussianMeasurement.diagonal`: ``m = d``, no
    support), on the CPU, fused in information form (:func:`torchflow.flows._fused_cpu.dh_diag_step`,
    Numba; one particle per iteration, two ``d x d`` Cholesky factorisations per pseudo-step and no
    ``d x d x d`` product). For the large d the lane kernel's tiles do not fit (the skewed-t /
    Poisson model, d = 64 and 144). ``steps(j, eta, aux, log_det, Wd, y)``: ``Wd``, ``y (B, N, d)``
    the whitened diagonal Jacobian and pseudo-measurement at the points; ``log_det (B, N)`` float64,
    updated in place. The prior precision ``P^{-1}`` is formed once per integration."""

    def __init__(self, scale_tril, cov, mean, lams, epss):
        L = _f64(scale_tril, 4)
        Pinv = np.empty_like(L)
        _set_threads()
        _precision_kernel()(L, Pinv)
        self.args = (Pinv, _f64(cov, 4), _f64(mean, 3))
        self.sched = (_f64(lams, 1), _f64(epss, 1))

    def __call__(self, j: int, eta, aux, log_det, Wd, y):
        e64, a64 = _f64(eta, 3), _f64(aux, 3)
        eta_out, aux_out = np.empty_like(e64), np.empty_like(a64)
        _set_threads()
        _diag_kernel()(_f64(Wd, 3), _f64(y, 3), *self.args, e64, a64, eta_out, aux_out, _np(log_det), *self.sched, j,
                       _numba_threads())
        return tuple(_cpu_back((eta_out, aux_out), eta.dtype))


class GPFISSteps:
    """The GPFIS transport's pseudo-steps (Cholesky root) and each step's ``log|det|`` on the CPU,
    fused (:func:`torchflow.flows._fused_cpu.gpfis_step`, Numba), set up once per integration like
    :class:`ParticleSteps`: ``steps(j0, j1, x, log_det[, W, y, D])`` moves ``x (B, N, d)`` over steps
    ``j0 .. j1 - 1`` and adds to ``log_det (B, N)`` (float64, contiguous) in place. With a
    measurement the kernel linearises itself, every step is one call; otherwise one step per call
    with ``W``, ``y`` and the second-derivative blocks ``D (B|1, N|1, m, n_b, b, b)`` at ``x``."""

    def __init__(self, C, cols, mean, support, lams, epss, measure=None, inv_sigma=None, z_scaled=None):
        d = cols.shape[-2]
        sup = torch.arange(d, device=cols.device) if support is None else support
        self.args = (_f64(C, 4), _f64(cols, 4), _f64(mean, 3), _np(sup.to(torch.int64)))
        self.sched, self.lin = _cpu_constants(lams, epss, measure, inv_sigma, z_scaled)

    def __call__(self, j0: int, j1: int, x, log_det, W=None, y=None, D=None):
        Wn, yn, lin, sens, const = _cpu_rows(self.lin, W, y)
        if lin == 1:
            nb, bs, Dn = self.args[0].shape[-1] // 2, 2, np.zeros((1, 1, 1, 1, 1, 1))  # a block per target
        else:
            D = D.reshape(*((1,) * (6 - D.dim())), *D.shape)
            nb, bs, Dn = D.shape[-3], D.shape[-1], _f64(D, 6)
        x64 = _f64(x, 3)
        out = np.empty_like(x64)
        _set_threads()
        _gpfis_kernel()(Wn, yn, Dn, *self.args, x64, out, _np(log_det), *self.sched, j0, j1, lin, sens, const, nb, bs)
        return _cpu_back((out,), x.dtype)[0]


def _cpu_constants(lams, epss, measure, inv_sigma, z_scaled):
    """The CPU kernels' schedule ``(lams, epss)`` and, for a measurement the kernel linearises
    itself, its arguments ``(W placeholder, z / sigma (B, 1, m), 1, sensors, [Psi / sigma, d0])``
    (``None`` otherwise), as float64 NumPy arrays, once per integration."""
    sched = (_f64(lams, 1), _f64(epss, 1))
    if measure is None:
        return sched, None
    return sched, (np.zeros((1, 1, 1, 1)), _f64(z_scaled.unsqueeze(-2), 3), 1, _f64(measure.sensors, 2),
                   _f64(torch.stack([measure.psi * inv_sigma, measure.d0]), 1))


def _cpu_rows(lin, W, y):
    """The kernels' measurement arguments of one pseudo-step: the prepared ones, or W and y at the
    points (``W (B|1, N|1, m, k)`` or a shared ``(m, k)``)."""
    if lin is not None:
        return lin
    return _f64(W if W.dim() > 2 else W.expand(1, 1, *W.shape), 4), _f64(y, 3), 0, np.zeros((1, 2)), np.zeros(2)


def _cpu_back(arrays, dtype):
    """The kernels' float64 outputs as tensors of the run's dtype (no copy for float64)."""
    out = [torch.from_numpy(a) for a in arrays]
    return out if dtype == torch.float64 else [t.to(dtype) for t in out]


def _gromov_kernel():
    from ._fused_cpu import gromov_step
    return gromov_step


_numba = None


def numba_available() -> bool:
    """The CPU kernels (:mod:`torchflow.flows._fused_cpu`) can be imported (cached): Numba is
    installed, and the module's ``cache=True`` kernels import (Numba caches next to the module or
    in its user cache directory; any failure to import means the torch path runs)."""
    global _numba
    if _numba is None:
        try:
            importlib.import_module("torchflow.flows._fused_cpu")  # an availability test
            _numba = True
        except Exception:  # noqa: BLE001 - any import failure means: not available
            _numba = False
    return _numba


def _precision_kernel():
    from ._fused_cpu import precision_from_factor
    return precision_from_factor


def _diag_kernel():
    from ._fused_cpu import dh_diag_step
    return dh_diag_step


def _gpfis_kernel():
    from ._fused_cpu import gpfis_step
    return gpfis_step


def _cpu_kernel():
    from ._fused_cpu import dh_step
    return dh_step


def _numba_threads() -> int:
    import numba
    return int(numba.config.NUMBA_NUM_THREADS)


def _set_threads() -> None:
    """Numba's threads follow torch's (the ``threads`` knob of the runner sets those)."""
    import numba
    numba.set_num_threads(max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)))


def runs_on(device) -> bool:
    """A fused pseudo-step can run on tensors of ``device``: Triton's kernel on CUDA (or the CPU
    under its interpreter), Numba's on the CPU."""
    device = torch.device(device)
    return _triton.runs_on(device) or (device.type == "cpu" and numba_available())


def _np(t: torch.Tensor):
    """A NumPy view of the CPU tensor ``t`` (detached only where it records a gradient)."""
    return (t.detach() if t.requires_grad else t).numpy()


def _f64(t: torch.Tensor, lead: int):
    """``t`` as a C-contiguous float64 NumPy array with ``lead`` dimensions at least (leading ones
    added as size 1; broadcast dimensions are kept at size 1, not copied)."""
    while t.dim() < lead:
        t = t.unsqueeze(0)
    if t.dtype != torch.float64:
        t = t.to(torch.float64)
    return _np(t if t.is_contiguous() else t.contiguous())
