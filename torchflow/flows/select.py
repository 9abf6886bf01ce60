"""Which kernel runs a computation: the one place that decides.

Every fast path of the library is chosen here and nowhere else. The flow integrator
(:func:`~torchflow.flows.integrate_flow`), GPFIS's transport, the Gaussian-sum filters' blocks of
particles and the filters' CUDA-graph step each ask one question of this module; the rest of the
library runs the reference code. This module alone reads the kernels' tuning knobs
(:data:`KNOBS`) and the eligibility rules live in its functions.

What a kernel may exploit is *declared*, never detected from classes or private fields:

* a flow offers a kernel through its class attribute ``kernel`` (:attr:`~torchflow.flows.ParticleFlow.kernel`):
  ``"daum_huang"`` (the exact EDH/LEDH coefficients), ``"gromov"`` (the Gromov flow's exact
  factor). The declaration is read from the flow's own class, not inherited
  (:func:`declared`): a subclass that changes the coefficients runs the reference loop unless it
  declares the kernel again;
* a measurement (:class:`~torchflow.flows.GaussianMeasurement`) states its noise structure, its
  support, whether its Jacobian is diagonal, its second derivatives, the prepared ``1 / sigma`` of
  a scalar R (:attr:`~torchflow.flows.GaussianMeasurement.inv_sigma`) and, where the model declares
  one, a named measurement form that a kernel linearises itself
  (:attr:`~torchflow.flows.GaussianMeasurement.form`);
* a model's and a proposal's ``graph_safe`` (the whole particle-filter step may be replayed from
  a CUDA graph), read from their own classes.

Kernels (:mod:`torchflow.flows.kernels.steps` wraps them):

* ``"lanes"``: the EDH/LEDH pseudo-step at per-particle points, one particle per GPU thread
  (Triton, :mod:`~torchflow.flows.kernels.gpu`) or 64 particles in SIMD lanes on the CPU (Numba,
  :mod:`~torchflow.flows.kernels.cpu`);
* ``"diagonal"``: EDH/LEDH at per-particle points for a diagonal whitened Jacobian too large for
  the lane tiles, in information form on the CPU;
* ``"gromov"``: the Gromov flow's Euler-Maruyama pseudo-step and PF-PF(Gromov)'s tracked law on the CPU;
* GPFIS's transport on the CPU (:func:`gpfis_kernel`);
* a particle filter's weighting, estimate and resampling on the CPU (:func:`weights_kernel`);
* the CUDA graph of a deterministic flow's pseudo-time loop (:func:`flow_graph`) and of a whole
  particle-filter step (:func:`graph_step`).

The run-time answers (:func:`flow_kernel`, :func:`gpfis_kernel`, :func:`flow_graph`) are noted
in :mod:`~torchflow.core.paths` while a recording listens (a filter's ``forward`` does:
:attr:`~torchflow.filters.FilterResult.paths`), so a run says which path it took.
"""

from __future__ import annotations

from typing import Optional

import torch

from torchflow.core import _triton, missing, paths, tuning
from torchflow.core.random import TrialStreams
from torchflow.flows.kernels import steps

#: the tuning knobs (:mod:`torchflow.core.tuning`) read by the kernel selection, and by nothing else
KNOBS = (
    "fused_flows",
    "fused_info",
    "kernel_float32",
    "fused_measurement",
    "fused_weights",
    "cuda_graphs",
    "graph_step_max_elems",
)

#: named measurement forms a kernel linearises itself, and the kernels' code for each
FORMS = {"inverse_distance_sum": 1}

#: the flow kernels :func:`flow_kernel` may return
FLOW_KERNELS = ("lanes", "diagonal", "gromov")


def declared(obj, name: str, default=None):
    """``obj``'s declaration ``name`` as its own class states it (a class attribute, or a property
    evaluated on ``obj``), not inherited from a parent class; ``default`` when the class is silent."""
    value = vars(type(obj)).get(name, default)
    return value.fget(obj) if isinstance(value, property) else value


def cpu_kernels_on(device) -> bool:
    """The Numba CPU kernels may run on ``device``: the CPU (not under Triton's interpreter),
    ``tuning.fused_flows`` on and the kernels' module importable."""
    device = torch.device(device)
    return (
        bool(tuning.get().fused_flows)
        and device.type == "cpu"
        and not _triton.runs_on(device)
        and steps.numba_available()
    )


def tiles_fit(m: int, k: int, d: int, device="cpu") -> bool:
    """The per-particle tiles for ``m`` measurements, ``k`` measured and ``d`` state coordinates
    are small enough: in cache on the CPU; on a GPU, where a thread holds its particle's ``k x k``
    matrices in registers, no larger than acoustic tracking's (``k = 8``, ``m = 25``, ``d = 16``;
    larger tiles spill to local memory: ``experiments/benchmarks/kernel_registers.py``)."""
    bm, bk, bd = (steps.tile(x) for x in (m, k, d))
    if torch.device(device).type == "cuda":
        return bk <= 8 and bm * bk * bk <= 2048 and bd * bk <= 128
    return bm * bk * bk <= 16384 and bd * bk <= 4096


def _tiles_fit(measurement, particles, k) -> bool:
    return tiles_fit(measurement.z.shape[-1], k, particles.shape[-1], particles.device) and particles.dtype in (
        torch.float32,
        torch.float64,
    )


def flow_kernel(
    flow, measurement, particles: torch.Tensor, k: int, *, per_particle: bool, track: bool, gaussian_image: bool
) -> Optional[str]:
    """The kernel that integrates ``flow`` (one of :data:`FLOW_KERNELS`), or ``None``: the reference loop.

    Kernels run at per-particle points, with no gradient recorded and no Gaussian image asked for:

    * ``"lanes"``: a flow offering ``"daum_huang"``, no tracked proposal law, ``tuning.fused_flows``,
      on CUDA with Triton (or its CPU interpreter) or on the CPU with Numba, tiles that fit;
    * ``"diagonal"``: otherwise, a ``"daum_huang"`` flow whose measurement is diagonal by
      declaration, on the CPU kernels;
    * ``"gromov"``: a flow offering ``"gromov"``, on the CPU kernels, tiles that fit.

    The integrator asks once per integration; the answer is noted (:mod:`.paths`:
    ``"kernel:<name>"``, or ``"torch"`` for the reference loop).
    """
    kernel = _flow_kernel(flow, measurement, particles, k, per_particle, track, gaussian_image)
    paths.note("torch" if kernel is None else "kernel:" + kernel)
    return kernel


def _flow_kernel(flow, measurement, particles, k, per_particle, track, gaussian_image) -> Optional[str]:
    if not per_particle or gaussian_image or torch.is_grad_enabled() or measurement.observed is not None:
        return None  # (a kernel takes no mask of unobserved coordinates)
    offer = declared(flow, "kernel")
    if offer == "daum_huang" and not track:
        if tuning.get().fused_flows and steps.runs_on(particles.device) and _tiles_fit(measurement, particles, k):
            return "lanes"
        if (
            measurement.diagonal
            and particles.dtype in (torch.float32, torch.float64)
            and cpu_kernels_on(particles.device)
        ):
            return "diagonal"
        return None
    if offer == "gromov" and cpu_kernels_on(particles.device) and _tiles_fit(measurement, particles, k):
        return "gromov"
    return None


def per_particle_kernel(flow, model, device) -> Optional[str]:
    """The kernel a no-gradient integration of ``flow`` at per-particle points on ``model`` takes
    on ``device``, as far as it can be told before the measurement is built: ``"diagonal"`` (a
    nonlinear measurement diagonal by declaration with a diagonal R, too large for the lane tiles:
    no ``d x d`` matrix per particle is built) or ``None``. A filter uses it to choose its blocks
    of particles."""
    noise_ok = model.structure.measurement_noise in ("diagonal", "state_dependent_diagonal")
    if not (model.structure.measurement_jacobian_diagonal and noise_ok) or model.structure.linear_measurement:
        return None
    d = model.state_dim
    if declared(flow, "kernel") == "daum_huang" and not tiles_fit(model.obs_dim, d, d) and cpu_kernels_on(device):
        return "diagonal"
    return None


def measured_inside(measurement, support, k) -> Optional["steps.FusedMeasurement"]:
    """The measurement a kernel linearises itself (no ``(B, N, m, k)`` Jacobian written and read per
    pseudo-step), or ``None``: ``tuning.fused_measurement``, a named form (:data:`FORMS`) declared
    by the model, a prepared scalar R, pairs of position coordinates as the support."""
    form = measurement.form
    if form is None or not tuning.get().fused_measurement or measurement.inv_sigma is None or support is None or k % 2:
        return None
    name, (sensors, psi, d0) = form
    if name not in FORMS or measurement.z.shape[-1] != sensors.shape[0]:
        return None
    return steps.FusedMeasurement(FORMS[name], sensors, psi, d0)


def gpfis_kernel(measurement, x: torch.Tensor, k: int) -> bool:
    """GPFIS's transport runs as the CPU kernel (:class:`~torchflow.flows.kernels.steps.GPFISSteps`):
    ``(B, N, d)`` particles on the CPU kernels, no gradient recorded, the measurement's second
    derivatives declared (or a linear measurement), tiles that fit and ``k <= 16`` (the kernel keeps
    ``[W y]^T D``, up to ``(k + 1) k^2`` numbers, per lane). Noted (:mod:`.paths`): ``"kernel:gpfis"``
    or ``"torch"``."""
    fused = (
        not torch.is_grad_enabled()
        and x.dim() == 3
        and k <= 16
        and measurement.observed is None
        and (measurement.hessian is not None or measurement.matrix is not None)
        and cpu_kernels_on(x.device)
        and _tiles_fit(measurement, x, k)
    )
    paths.note("kernel:gpfis" if fused else "torch")
    return fused


#: the weighting kernel runs for at most this many particles per trial: its one exponential per
#: particle is a scalar call (about 4 ns), where torch's are vectorised, so from about 4,000
#: particles on the torch path's few passes cost less than the calls the kernel saves (the
#: stochastic-volatility series, one thread: ``python -m experiments.benchmarks.bench_sv``)
WEIGHTS_KERNEL_MAX_PARTICLES = 4096


def weights_kernel(particles: torch.Tensor, *tensors: torch.Tensor, resampler, cov, extras) -> Optional[str]:
    """A particle filter's step weighs, estimates and resamples in one CPU kernel call
    (:func:`~torchflow.flows.kernels.steps.weigh_resample`): ``tuning.fused_weights``, float64
    ``(B, N, d)`` particles on the CPU with Numba, ``N <=`` :data:`WEIGHTS_KERNEL_MAX_PARTICLES`,
    ``tensors`` (the weights) float64 ``(B, N)``, no gradient recorded through them or
    ``tensors`` (the weights), nothing carried per particle (no tracked covariance, no extras), and
    a resampler that declares a kernel scheme
    (:attr:`~torchflow.core.resampling.Resampler.kernel_scheme`). Returns that scheme
    (``"systematic"`` or ``"stratified"``) or ``None``. The caller, which has read the host
    (:func:`torchflow.core.resampling.reads_host`), notes ``"kernel:weights"`` when the call succeeds."""
    if (
        cov is not None
        or extras
        or particles.dtype != torch.float64
        or particles.dim() != 3
        or not particles.is_cpu
        or particles.shape[1] > WEIGHTS_KERNEL_MAX_PARTICLES
        or not tuning.get().fused_weights
    ):
        return None
    if any(t.shape != particles.shape[:2] or t.dtype != torch.float64 or not t.is_cpu for t in tensors):
        return None  # (the torch path broadcasts a weight of another shape; the kernel reads (B, N))
    if torch.is_grad_enabled() and any(t.requires_grad for t in (particles,) + tensors):
        return None
    scheme = getattr(resampler, "kernel_scheme", None)  # a Resampler's declaration
    return scheme if scheme is not None and steps.weights_available() else None


def gpu_form() -> str:
    """The GPU lane kernel's form (``tuning.fused_info``): ``"info"`` (``G = W^T W`` and the prior
    precision, one pass over the rows of W) or ``"rows"`` (``S = (W L_s)^T (W L_s)``, two passes)."""
    return "info" if tuning.get().fused_info else "rows"


def gpu_float32() -> bool:
    """The GPU lane kernel computes float32 particles in float32 (``tuning.kernel_float32``; an H100
    has twice as many FP32 units as FP64 ones, and a ``k x k`` tile takes half the registers); else
    its arithmetic is float64 whatever the particles' precision."""
    return bool(tuning.get().kernel_float32)


def weigh_resample(particles, prev_log_weights, log_increment, uniforms, ess_threshold):
    """The weighting kernel's call (:func:`torchflow.flows.kernels.steps.weigh_resample`), for a step
    that :func:`weights_kernel` let through: the filters reach the kernel here, not by importing it."""
    return steps.weigh_resample(particles, prev_log_weights, log_increment, uniforms, ess_threshold)


def cpu_kernels_installed() -> bool:
    """The CPU kernels (Numba, the ``kernels`` extra) import."""
    return steps.numba_available()


def offers_flow_kernel(filt) -> bool:
    """Filter ``filt``'s proposal has a flow that declares a fused kernel (:func:`declared`)."""
    return declared(getattr(getattr(filt, "proposal", None), "flow", None), "kernel") is not None


def has_kernel(filt) -> bool:
    """Filter ``filt`` would take a fused kernel somewhere without a gradient: a flow that declares
    one (:func:`offers_flow_kernel`) or the CPU weighting kernel (:func:`may_weigh_in_kernel`)."""
    return offers_flow_kernel(filt) or may_weigh_in_kernel(filt)


def may_weigh_in_kernel(filt) -> bool:
    """Particle filter ``filt``'s steps may take the CPU weighting kernel: its resampler declares a
    kernel scheme, it has at most :data:`WEIGHTS_KERNEL_MAX_PARTICLES` particles per trial and the
    kernel imports (:func:`weights_kernel` decides per step)."""
    return (
        getattr(getattr(filt, "resampler", None), "kernel_scheme", None) is not None
        and int(getattr(filt, "n_particles", 0) or 0) <= WEIGHTS_KERNEL_MAX_PARTICLES
        and steps.weights_available()
    )


def flow_graph(flow, particles: torch.Tensor) -> bool:
    """A deterministic flow's pseudo-time loop is replayed from a CUDA graph
    (:mod:`torchflow.core.cudagraphs`): CUDA, ``tuning.cuda_graphs``, no gradient recorded, not inside
    another capture. A yes is noted (:mod:`.paths`: ``"graph:flow"``)."""
    graphed = (
        particles.is_cuda
        and bool(tuning.get().cuda_graphs)
        and not flow.stochastic
        and not missing.active()
        and not torch.is_grad_enabled()
        and not torch.cuda.is_current_stream_capturing()
    )
    if graphed:
        paths.note("graph:flow")
    return graphed


def graph_step(filt, x: torch.Tensor, generator, *, emulated: bool = False) -> bool:
    """A particle filter's whole step on particles ``x`` is replayed from a CUDA graph
    (:mod:`torchflow.filters.graph_step`): the filter declares its step graph-safe
    (:attr:`~torchflow.filters.ParticleFilter.graph_step`), ``tuning.cuda_graphs``, no gradient
    recorded, per-trial Philox streams (a plain :class:`~torchflow.core.random.TrialStreams`: its draws
    can be split into words made outside the graph), at most ``tuning.graph_step_max_elems`` state
    elements, and CUDA outside another capture (``emulated``: the capture is emulated on any
    device, for tests)."""
    t = tuning.get()
    return (
        (emulated or (x.is_cuda and not torch.cuda.is_current_stream_capturing()))
        and not missing.active()
        and bool(getattr(filt, "graph_step", False))
        and bool(t.cuda_graphs)
        and not torch.is_grad_enabled()
        and type(generator) is TrialStreams
        and generator.backend in ("auto", "philox")
        and x.numel() <= t.graph_step_max_elems
    )
