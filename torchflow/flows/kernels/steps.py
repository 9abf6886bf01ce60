"""Fused pseudo-steps of the particle flows at per-particle points, and their set-up.

The wrappers here turn a flow integration's tensors into the kernels' arguments once per
integration and call one kernel per pseudo-step; :mod:`torchflow.flows.select` decides
whether they run, :mod:`torchflow.flows.loops` drives them.

**EDH/LEDH** (:func:`dh_particle_step`, :class:`ParticleSteps`): the exact Daum-Huang coefficients
(Daum & Huang 2010; Ding & Coates 2012) at each particle's point,

    A = -1/2 P H^T (lam H P H^T + R)^{-1} H,
    b = (I + 2 lam A) [(I + lam A) P H^T R^{-1} (z - h(x) + H x) + A eta_bar_0],

and the Euler moves of the particle and its point, with ``log|det(I + eps A)|`` accumulated for
the PF-PF weight (Li & Coates 2017). With ``W = L_R^{-1} H`` restricted to the k measured
coordinates and ``L_s`` the prior factor's rows there, ``A`` is applied by three triangular solves
with ``Q = I + lam S``, ``S = (W L_s)^T (W L_s)`` (the *row form*, two passes over W's rows), or in
*information form* with ``G = W^T W``, ``C = L L_s^{-1}`` and the prior precision ``P_s^{-1}``,
``L (I + lam L_s^T G L_s)^{-1} L_s^T = C (P_s^{-1} + lam G)^{-1}`` (one pass; :func:`info_factors`
once per integration). On CUDA (or Triton's interpreter) one particle per thread with every
``k x k`` matrix in its registers (:mod:`~torchflow.flows.kernels.gpu`); on the CPU 64 particles in
SIMD lanes (:mod:`~torchflow.flows.kernels.cpu`, Numba). A measurement in a named form
(:class:`FusedMeasurement`) is linearised inside the kernel: no ``(B, N, m, k)`` Jacobian per
pseudo-step.

**Gromov** (:class:`GromovSteps`): the Gromov flow's Euler-Maruyama step with its exact diffusion
factor (Dai & Daum), and PF-PF(Gromov)'s tracked Gaussian law ``mu_j = (I + eps A) mu_{j-1} + eps b``,
``S_j = (I + eps A) S_{j-1} (I + eps A)^T + eps Q``, on the CPU; the normals are torch's draws.

**Diagonal** (:class:`DiagonalSteps`): EDH/LEDH when ``D = W^T W`` is diagonal by declaration, in
information form, ``L (I + lam L^T D L)^{-1} L^T = (P^{-1} + lam D)^{-1}``: two ``d x d`` Cholesky
factorisations of ``P^{-1} + h D`` per particle and pseudo-step, no ``d x d x d`` product, ``P^{-1}``
once per integration.

**GPFIS** (:class:`GPFISSteps`): the Gaussian-particle-flow importance sampler's transport with its
Cholesky root (:func:`~torchflow.flows.gpfis.gpfis_flow`) and the ``log|det|`` of each step's
``k x k`` Jacobian, the step's tangents as rank-``2b`` updates.

Arithmetic: float64 inside the kernels (float32 runs load and store their own dtype); the GPU lane
kernel computes a float32 run in float32 with ``tuning.kernel_float32=1`` (not the default). The same
formulas as the reference loop, reassociated: the numbers agree to round-off
(``tests/flows/test_fused.py``), not bit for bit. On the CPU the results do not depend on the
thread count (particles do not interact). Numba compiles a kernel on its first call in a process
and caches it on disk; ``python -m experiments.benchmarks.bench_ops`` times the kernels.
"""

from __future__ import annotations

import functools
import importlib
import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from torchflow.core import _triton

__all__ = [
    "available",
    "dh_particle_step",
    "FusedMeasurement",
    "ParticleSteps",
    "GromovSteps",
    "GPFISSteps",
    "DiagonalSteps",
]

available, interpreted = _triton.available, _triton.interpreted  # shared with torchflow.core.random's fused draws


_kernels = {}


#: warps per program (32 particles each); 1, 2 and 4 ran alike (``experiments/benchmarks/ab_fused.py``)
ROWS_WARPS = 1


def _build(form: str):
    if form not in _kernels:
        from torchflow.flows.kernels import gpu

        _kernels[form] = getattr(gpu, "kernel_" + form)
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
    """A measurement the fused kernel linearises itself (``tuning`` ``fused_measurement=1``), so that no
    ``(B, N, m, k)`` Jacobian is written and read per
    pseudo-step. ``kind`` 1: ``h_i(x) = psi sum_c 1 / (|p_c - s_i| + d0)`` over the 2-D positions
    ``p_c`` (support coordinates ``2c, 2c + 1``) and sensors ``s_i`` (``sensors (m, 2)``), with a
    scalar R (acoustic tracking: :attr:`~torchflow.models.Structure.measurement_form`)."""

    kind: int
    sensors: torch.Tensor
    psi: torch.Tensor
    d0: torch.Tensor


def dh_particle_step(
    W: Optional[torch.Tensor],
    y: torch.Tensor,
    L: torch.Tensor,
    Ls: torch.Tensor,
    Pc: torch.Tensor,
    mean: torch.Tensor,
    support: Optional[torch.Tensor],
    eta: torch.Tensor,
    aux: torch.Tensor,
    log_det: torch.Tensor,
    lams: torch.Tensor,
    epss: torch.Tensor,
    j: int,
    measure: Optional[FusedMeasurement] = None,
    inv_sigma: Optional[torch.Tensor] = None,
    info=None,
    form: str = "info",
    float32: bool = False,
):
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
            ``"info"`` or ``"rows"``; float32: the arithmetic in float32 for float32 particles (both
            chosen by :mod:`torchflow.flows.select`: :func:`~torchflow.flows.select.gpu_form`,
            :func:`~torchflow.flows.select.gpu_float32`).

    Returns:
        ``(eta, aux)`` after the step (new tensors).
    """
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
    DT, TINY = _compute_dtype(float32 and eta.dtype == torch.float32)
    kernel[(-(-B * N // bp),)](
        W,
        *sW,
        y,
        *sY,
        L,
        *sL,
        Ls,
        *sS,
        Pc,
        *sP,
        mean,
        *sM,
        support,
        eta,
        aux,
        *sE,
        eta_out,
        aux_out,
        log_det,
        lams,
        epss,
        j,
        sens,
        const,
        B * N,
        N,
        m,
        d,
        k,
        BK=BK,
        BD=BD,
        BP=bp,
        LIN=0 if measure is None else measure.kind,
        DT=DT,
        TINY=TINY,
        num_warps=ROWS_WARPS,
    )
    return eta_out, aux_out


@functools.lru_cache(maxsize=2)
def _compute_dtype(f32: bool):
    from triton import language as tl

    return (
        (tl.float32, float(torch.finfo(torch.float32).tiny))
        if f32
        else (tl.float64, float(torch.finfo(torch.float64).tiny))
    )


class ParticleSteps:
    """The fused pseudo-steps of one flow integration, set up once: the prior's factors, the
    schedule and the measurement do not change between steps. ``steps(j, eta, aux, log_det[, W, y])``
    is :func:`dh_particle_step` for step ``j`` (``W``, ``y`` at the points unless ``measure``).
    On CUDA (or Triton's interpreter) Triton's kernel; on the CPU Numba's
    (:mod:`torchflow.flows.kernels.cpu`), whose inputs are converted to NumPy here once."""

    def __init__(
        self, L, Ls, Pc, mean, support, lams, epss, measure=None, inv_sigma=None, z_scaled=None, *, form, float32
    ):
        self.prior = (L, Ls, Pc, mean, support)
        self.float32 = float32
        self.lams, self.epss, self.measure, self.inv_sigma, self.z_scaled = lams, epss, measure, inv_sigma, z_scaled
        self.cpu = mean.device.type == "cpu" and not _triton.runs_on(mean.device)
        self.form = form
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
            return dh_particle_step(
                W,
                y,
                *self.prior,
                eta,
                aux,
                log_det,
                self.lams,
                self.epss,
                j,
                measure=self.measure,
                inv_sigma=self.inv_sigma,
                info=self.info,
                form=self.form,
                float32=self.float32,
            )
        Wn, yn, lin, sens, const = _cpu_rows(self.lin, W, y)
        e64, a64 = _f64(eta, 3), _f64(aux, 3)
        eta_out, aux_out = np.empty_like(e64), np.empty_like(a64)
        ld = (
            log_det
            if log_det.dtype == torch.float64 and log_det.is_contiguous()
            else log_det.to(torch.float64).contiguous()
        )
        _set_threads()
        _cpu_kernel()(Wn, yn, *self.args, e64, a64, eta_out, aux_out, _np(ld), *self.sched, j, lin, sens, const)
        if ld is not log_det:
            log_det.copy_(ld)
        return tuple(_cpu_back((eta_out, aux_out), eta.dtype))


class GromovSteps:
    """The Gromov flow's Euler-Maruyama pseudo-steps at per-particle points on the CPU, fused
    (:func:`torchflow.flows.kernels.cpu.gromov_step`, Numba): set up once per integration like
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
        _gromov_kernel()(
            Wn, yn, *self.args, e64, a64, m64, S64, _f64(xi, 3), *outs, *self.sched, j, lin, sens, const, int(track)
        )
        res = _cpu_back(outs if track else outs[:2], eta.dtype)
        return tuple(res) if track else (res[0], res[1], None, None)


class DiagonalSteps:
    """EDH/LEDH pseudo-steps at per-particle points for a measurement whose whitened Jacobian is
    diagonal by declaration (:attr:`~torchflow.flows.GaussianMeasurement.diagonal`: ``m = d``, no
    support), on the CPU, fused in information form (:func:`torchflow.flows.kernels.cpu.dh_diag_step`,
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
        _diag_kernel()(
            _f64(Wd, 3),
            _f64(y, 3),
            *self.args,
            e64,
            a64,
            eta_out,
            aux_out,
            _np(log_det),
            *self.sched,
            j,
            _numba_threads(),
        )
        return tuple(_cpu_back((eta_out, aux_out), eta.dtype))


class GPFISSteps:
    """The GPFIS transport's pseudo-steps (Cholesky root) and each step's ``log|det|`` on the CPU,
    fused (:func:`torchflow.flows.kernels.cpu.gpfis_step`, Numba), set up once per integration like
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
    return sched, (
        np.zeros((1, 1, 1, 1)),
        _f64(z_scaled.unsqueeze(-2), 3),
        1,
        _f64(measure.sensors, 2),
        _f64(torch.stack([measure.psi * inv_sigma, measure.d0]), 1),
    )


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
    from torchflow.flows.kernels.cpu import gromov_step

    return gromov_step


_numba = None
_IMPORTABLE = {}


def _importable(module: str) -> bool:
    """``module`` imports (cached per process; any failure to import means: not available)."""
    if module not in _IMPORTABLE:
        try:
            importlib.import_module(module)
            _IMPORTABLE[module] = True
        except Exception:
            _IMPORTABLE[module] = False
    return _IMPORTABLE[module]


def numba_available() -> bool:
    """The CPU kernels (:mod:`torchflow.flows.kernels.cpu`) can be imported (cached): Numba is
    installed, and the module's ``cache=True`` kernels import (Numba caches next to the module or
    in its user cache directory; any failure to import means the torch path runs)."""
    global _numba
    if _numba is None:
        _numba = _importable("torchflow.flows.kernels.cpu")
    return _numba


#: from this many (trial, particle) pairs on, with more than one torch thread, :func:`weigh_resample`
#: runs its trials in parallel (the same numbers: trials are independent)
PARALLEL_WEIGHTS_MIN = 1 << 16


def weigh_resample(
    particles: torch.Tensor,
    prev_log_weights: torch.Tensor,
    log_increment: torch.Tensor,
    uniforms: Optional[torch.Tensor],
    threshold: float,
):
    """A particle filter's clean weighting step in one Numba call per batch
    (:mod:`torchflow.flows.kernels.cpu_weights`): float64 CPU tensors ``particles (B, N, d)``,
    normalised ``prev_log_weights (B, N)``, ``log_increment (B, N)``; ``uniforms`` the resampling
    scheme's draws, ``(B, 1)`` (systematic) or ``(B, N)`` (stratified), ``None`` when
    ``threshold`` is 0 (no trial resamples). Returns ``(particles, log_weights, estimate (B, d),
    ess (B,), log_evidence_increment (B,), resampled (B,), bad (B,) or None)``: the particles the
    same tensor where no trial resampled and none is bad; ``bad`` flags the trials whose increment
    is not finite (``None`` when none is), whose rows are left for the caller's reference path to
    repair (their particle rows are those of ``particles``, the others undefined)."""
    from torchflow.flows.kernels import cpu_weights as k

    B, N, d = particles.shape
    x = particles.detach().contiguous()
    # the small outputs made by NumPy (a tenth of torch.empty's cost) and wrapped once
    est, ess, inc = np.empty((B, d)), np.empty(B), np.empty(B)
    res, bad = np.empty(B, dtype=np.bool_), np.empty(B, dtype=np.bool_)
    lw, out = torch.empty(B, N, dtype=torch.float64), torch.empty_like(x)
    u = np.zeros((B, 1)) if uniforms is None else _np(uniforms.contiguous())
    parallel = B > 1 and B * N >= PARALLEL_WEIGHTS_MIN and torch.get_num_threads() > 1
    if parallel:
        _set_threads()
    fn = k.weigh_resample_parallel if parallel else k.weigh_resample
    count = fn(
        _np(prev_log_weights.contiguous()),
        _np(log_increment.contiguous()),
        x.numpy(),
        u,
        u.shape[1] > 1,
        float(threshold) * N if uniforms is not None else 0.0,
        -math.log(N),
        lw.numpy(),
        est,
        ess,
        inc,
        res,
        out.numpy(),
        bad,
    )
    n_bad = int(bad.sum())
    if n_bad and not count:
        out = x.clone()  # the bad rows are replaced by the caller
    elif n_bad:
        rows = torch.from_numpy(bad)
        out[rows] = x[rows]
    return (
        (out if count or n_bad else particles, lw)
        + tuple(torch.from_numpy(a) for a in (est, ess, inc, res))
        + (torch.from_numpy(bad) if n_bad else None,)
    )


def weights_available() -> bool:
    """The weighting kernel (:mod:`torchflow.flows.kernels.cpu_weights`) can be imported: where the
    CPU kernels can (:func:`numba_available`) and its own module imports."""
    return numba_available() and _importable("torchflow.flows.kernels.cpu_weights")


def _precision_kernel():
    from torchflow.flows.kernels.cpu import precision_from_factor

    return precision_from_factor


def _diag_kernel():
    from torchflow.flows.kernels.cpu import dh_diag_step

    return dh_diag_step


def _gpfis_kernel():
    from torchflow.flows.kernels.cpu import gpfis_step

    return gpfis_step


def _cpu_kernel():
    from torchflow.flows.kernels.cpu import dh_step

    return dh_step


def _numba_threads() -> int:
    import numba

    return int(numba.config.NUMBA_NUM_THREADS)


def _set_threads() -> None:
    """Numba's threads follow torch's (the ``threads`` knob of the runner sets those). Numba's
    threading layer starts at its first parallel launch; with the OpenMP layer that start sets the
    process's OpenMP thread count to ``NUMBA_NUM_THREADS`` (torch's included: measured 1 -> 2), so
    it is started here first and torch's count is put back."""
    import numba

    n = torch.get_num_threads()
    launch = getattr(getattr(numba.np.ufunc, "parallel", None), "_launch_threads", None)
    if launch is not None:
        launch()
    numba.set_num_threads(max(1, min(n, numba.config.NUMBA_NUM_THREADS)))
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)


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
