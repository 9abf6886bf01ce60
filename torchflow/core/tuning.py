"""Speed settings, as documented knobs in one place.

Every value here changes only how fast (or in how much memory) a result is computed, never the
result: the same seed gives the same numbers whatever they are set to (up to round-off where a
batch's size changes BLAS blocking; see README "Reproducibility"). The exceptions compute the same
formulas in another order: ``fused_flows``, ``fused_info``, ``fused_measurement``, ``fused_weights``
and ``structured_update`` agree with their torch/Joseph counterparts to round-off per call, which a
chaotic trial (a resampling decision, a diverging EKF) can amplify; their statistics are the same;
``kernel_float32`` computes a float32 run's GPU kernel in float32 instead of float64 (float32
round-off). The defaults were chosen by timing representative runs on a small CPU machine; on
another machine, time a representative run with ``experiments/benchmarks`` and set them here, from
Python or from the
runner (``python experiments/run.py tuning.points_per_call=40000``).

Constants that *define* numbers are not here: the block size of a trial's child random streams
(:data:`torchflow.core.random.BLOCK`) and the fast sampler's thresholds
(:data:`torchflow.core.linalg.FAST_NORMAL_MIN`, ``FAST_NORMAL_BLOCK``) decide which random numbers a
draw gets, so changing them would change results; they are part of the stream definitions.

Usage::

    from torchflow.core import tuning
    tuning.get().points_per_call          # read
    tuning.set(points_per_call=40_000)    # set for the process (returns the previous settings)
    with tuning.tuned(serial_solve_max_dim=0):
        ...                               # set within a block
"""

from __future__ import annotations

import contextlib
from dataclasses import asdict, dataclass, fields, replace

from torchflow.core.errors import ArgumentError

__all__ = ["Tuning", "get", "set", "tuned"]


@dataclass(frozen=True)
class Tuning:
    """The speed knobs (defaults chosen for a small CPU machine).

    Attributes:
        points_per_call: per-particle flows (LEDH-type points) batch ``d x d`` products over
            trials x particles; the runner's default chunk is this many particles per call. The
            per-point cost is flat while a call's per-particle matrices stay in the CPU's cache
            and rises once they spill (``python -m experiments.benchmarks.bench_scaling``, against B).
            GPUs want more.
        cache_bytes_per_call: bytes of one ``(B, N, d)`` state tensor per call at which the
            whole-cloud passes of the other particle filters (sampling, likelihood, resampling)
            stay cache-resident (larger calls are memory-bound: each pass streams the whole cloud
            from main memory).
        serial_solve_max_dim: CPU batches of triangular matrices up to this size are solved with
            one intra-op thread (with several threads MKL pays a parallel-region start per tiny
            matrix, which costs more than the solve itself); 0 turns this off.
        flow_operator_min_dim: EDH/LEDH coefficients with at least this many measured state
            coordinates k give A as an operator on vectors instead of forming the ``d x k`` matrix
            (:func:`torchflow.flows.daum_huang_coefficients`); below it, forming A and applying
            it by batched products is faster. A particle's flow applies A to only a few vectors,
            so for large k the ``k``-column solve and ``d x k x k`` product that form A dominate
            (PFGSPF at d = 144; ``python -m experiments.benchmarks.bench_gaussian_sum``); both give
            the same numbers to round-off. 0: always an operator.
        parallel_draw_min: numbers per call from which the numpy random back end fills trials on
            several threads (the numbers do not depend on the thread count).
        assignment_brute_force_max: OMAT/OSPA assignments with at most this many items are solved
            by enumerating permutations (batched), larger ones by the Hungarian algorithm; both
            are exact.
        assignment_chunk_elems: memory guard of the brute-force assignment: elements of the
            gathered cost tensor built at once.
        batched_jitter_cpu: :func:`torchflow.core.linalg.safe_cholesky` on a CUDA tensor always
            factors its whole jitter ladder in one batched call, so that no host read decides
            whether a factorisation failed (a read stalls the GPU's queue). On the CPU a host read
            costs nothing and the ladder costs ``max_tries`` extra factorisations of every batch:
            with 0 (default) the CPU reads the failure flags and tries the ladder only when one
            failed; 1 batches it there too (slower on the CPU:
            ``python -m experiments.benchmarks.bench_ops``). The same factor either way.
        host_reads_cpu: on the CPU, where a host read costs nothing, a particle filter's step reads
            back what work it needs (:func:`torchflow.core.resampling.reads_host`): the resampling
            computes (CDF, inversion, gathers) only the trials whose ESS triggered it, and nothing
            in a step where none did (the uniforms are still drawn for every trial), and the
            repair of non-finite particles and dead trials is skipped in a step that has none.
            The same numbers either way, except that the weighting kernel (``fused_weights``)
            needs these reads: with it on, 0 also turns it off (round-off). On a GPU every trial is
            computed with masks (no host read). 0: the GPU's way on the CPU too (what the
            host-synchronisation tests count).
        jitter_ladder_divisor: the batched jitter ladder of :func:`torchflow.core.linalg.safe_cholesky`
            (CUDA, or ``batched_jitter_cpu=1``) gathers the failed matrices of a batch of n into
            ``max(min(n, 4096), ceil(n / divisor))`` slots and factors the ladder for those only;
            failed matrices beyond the slots take the ladder's largest jitter. 1: a slot per
            matrix. Failures are rare, so factoring the ladder for every matrix mostly repeats
            work.
        cuda_graphs: on CUDA, a deterministic flow's pseudo-time loop (EDH, LEDH, geodesic,
            clustered; no gradient recorded) is captured once per shape as a CUDA graph and
            replayed (:mod:`torchflow.core.cudagraphs`): one launch instead of thousands of small ones.
            The same kernels, so the same numbers. Also a graph-safe particle filter's whole step
            (the bootstrap PF's; ``graph_step_max_elems``). 0 runs both eagerly. No effect on the CPU.
        fused_flows: EDH/LEDH at per-particle points take each pseudo-step as one fused kernel
            (:mod:`torchflow.flows.kernels.steps`) instead of ~85 batched small-matrix ops: on CUDA with
            Triton installed a particle per GPU thread, on the CPU with Numba installed 64
            particles side by side in SIMD lanes. The numbers agree with the torch path to
            round-off (1e-12 relative per flow in float64), not bit for bit. 0: the torch path.
            On the CPU the Gromov flow at per-particle points (PF-PF(Gromov)) and GPFIS's transport
            (its analytic Jacobian) have one too, and EDH/LEDH with a diagonal W too large for the
            lane kernel run in information form (PFGSPF, d = 144). One kernel keeps each
            particle's small matrices in registers or cache and replaces many small launches and
            passes over memory; timed by ``experiments/benchmarks/bench_ops.py`` and ``bench_gpu.py``.
            Also, in the torch path with no gradient recorded, a Daum-Huang flow whose measurement
            is fixed over pseudo-time (linear, constant R) keeps ``S``'s eigendecomposition for the
            whole integration (:func:`torchflow.flows.daum_huang_coefficients`, ``fixed``): the same
            flow to round-off. 0 turns that off too.
        fused_weights: on the CPU with Numba installed, a particle filter's step with at most
            4096 particles per trial (the bootstrap PF's, and any whose particles carry no
            covariance or extras; ``select.WEIGHTS_KERNEL_MAX_PARTICLES``) weighs, normalises,
            estimates and resamples (systematic or stratified, no sorting or jitter) in one
            compiled call per batch (:mod:`torchflow.flows.kernels.cpu_weights`) instead of ~20
            eager ops of 1-3 us each: what one trial per call at N = 10^3 spends most of its
            step on. The same formulas; two sums accumulate in another order, so the numbers
            agree to round-off (a few ulp), and the ancestors are the same unless a position
            falls within round-off of a CDF step. Runs with gradients recorded take the torch
            path. 0: the torch path.
        fused_info: the GPU kernel of ``fused_flows`` in information form (1,
            :func:`~torchflow.flows.kernels.gpu.kernel_info`: ``G = W^T W`` and the prior precision,
            one pass over W's rows, no ``L_s`` read per row) or the row form (0,
            :func:`~torchflow.flows.kernels.gpu.kernel_rows`: ``S = (W L_s)^T (W L_s)``, two
            passes). The same formulas rearranged (round-off); the information form reads W once
            and never re-reads ``L_s`` per row. No effect on the
            Numba CPU kernel (it does select the form Triton's interpreter runs on the CPU, in tests).
        kernel_float32: the GPU lane kernel of ``fused_flows`` computes a float32 run's pseudo-steps
            in float32 (1), or in float64 as the CPU kernels do, loading and storing float32 (0,
            the default). In float32 the information form's ``Pi + lam G`` is poorly conditioned
            where the measurement is sharp: on acoustic tracking (Triton's interpreter, 3
            pseudo-steps) the particles move 1.5e-4 relative from the float64 flow, against 1e-6
            for the float64 arithmetic and 1.3e-7 for the torch path in float32. Whether that
            changes a run's statistics, and what it gains in speed, is for the GPU check to
            measure (``experiments/benchmarks/gpu_check.sh``); no effect on float64 runs or the CPU.
        fused_measurement: the fused kernel linearises a model that declares its measurement in
            the kernel's terms (:attr:`~torchflow.models.Structure.measurement_form`:
            acoustic tracking) itself, at the points, instead of torch ops writing a
            ``(B, N, m, k)`` Jacobian each pseudo-step. 0: the model's linearisation.
        structured_update: the EKF update of a nonlinear model that declares a scalar R and a
            measurement support of ``k <= m`` coordinates (acoustic tracking: k = 8, m = 25) is
            done in ``k x k`` algebra (:func:`torchflow.core.trackers.kalman_update_scalar_support`,
            Woodbury) instead of the ``m x m`` Joseph form: the same posterior to round-off
            (1e-14 relative), with ``k x k`` instead of ``m x m`` factorisations and about ten
            times fewer flops per particle; it is the per-particle EKF of PF-PF. 0: the Joseph form.
        graph_step_max_elems: on CUDA, a particle filter step declared graph-safe (the bootstrap
            PF's; :mod:`torchflow.filters.graph_step`) with at most this many state elements
            ``B x N x d`` is replayed from a CUDA graph (under ``cuda_graphs``): one launch instead
            of ~130, with its random words drawn outside the graph; the same numbers. Larger steps
            are bound by the GPU's arithmetic (a graph saves nothing there and keeps a memory pool
            as large as the step's intermediates). 0: never.
        fused_philox: on CUDA with Triton installed, the Philox4x32 rounds of per-trial random
            streams (:class:`torchflow.core.random.TrialStreams` off the CPU) run as one kernel
            (:func:`torchflow.core.random.philox4x32_fused`) instead of ~165 integer ops per draw; the
            same bits. 0: the torch ops. No effect on the CPU.
    """

    points_per_call: int = 10_000
    cache_bytes_per_call: int = 16 * 2**20
    serial_solve_max_dim: int = 64
    flow_operator_min_dim: int = 32
    flow_bytes_per_call: int = 8 << 20
    parallel_draw_min: int = 1 << 19
    assignment_brute_force_max: int = 7
    assignment_chunk_elems: int = 1 << 24
    batched_jitter_cpu: int = 0
    host_reads_cpu: int = 1
    jitter_ladder_divisor: int = 16
    cuda_graphs: int = 1
    fused_flows: int = 1
    fused_info: int = 1
    fused_weights: int = 1
    kernel_float32: int = 0
    fused_measurement: int = 1
    fused_philox: int = 1
    graph_step_max_elems: int = 1 << 23
    structured_update: int = 1

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ArgumentError(f"tuning.{f.name}: expected an integer >= 0, got {v!r}")


_current = Tuning()


def get() -> Tuning:
    """The settings in force."""
    return _current


def set(**knobs) -> Tuning:
    """Change some knobs for the process; returns the previous settings. Unknown names raise."""
    global _current
    known = {f.name for f in fields(Tuning)}
    unknown = sorted(k for k in knobs if k not in known)
    if unknown:
        raise ArgumentError(f"tuning: unknown knob(s) {unknown}; expected some of {sorted(known)}")
    previous = _current
    _current = replace(
        _current, **{k: int(v) if isinstance(v, float) and v.is_integer() else v for k, v in knobs.items()}
    )
    return previous


@contextlib.contextmanager
def tuned(**knobs):
    """Within the block, the given knobs (restored afterwards, also on error)."""
    global _current
    previous = set(**knobs)
    try:
        yield _current
    finally:
        _current = previous


def as_dict() -> dict:
    """The settings in force as a plain dict (recorded with a run's results)."""
    return asdict(_current)
