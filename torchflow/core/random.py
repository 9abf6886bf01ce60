"""Per-trial random streams: a trial's numbers do not depend on how the trials were batched.

A :class:`TrialStreams` is a generator for a batch of ``B`` Monte Carlo trials in which trial
``b`` draws from its own stream, keyed by ``(seed, key, trial_index[b])``. Every draw has a
leading trial dimension (``(B, ...)``, or ``(B*k, ...)`` laid out trial-major); trial ``b`` gets
the next numbers of stream ``b``. So a trial's particles, resampling and flow noise are the same
whether it runs alone, in a chunk of 10 or in one call of 400, on 1 or 2 threads, first or
last, in one process or in several: chunking only selects which streams run together
(:meth:`TrialStreams.select`).

Filters accept a ``TrialStreams`` wherever they accept a ``torch.Generator`` (argument
``generator``); :func:`torchflow.app.runner.run_experiment` always passes one. With a plain
``torch.Generator`` the batch shares one stream (fine for a single call, but then trial ``b``'s
numbers depend on the batch it ran in).

Back ends (``backend=``):

* ``"numpy"`` (default on CPU): one ``numpy.random.Generator(SFC64)`` per trial, seeded by a
  ``SeedSequence([seed, key, trial])``; normals by numpy's ziggurat (exact float64 / float32
  normals; their cost: ``python -m experiments.benchmarks.bench_streams``). Large draws are filled on parallel
  threads (numpy releases the
  GIL), one task per trial or, for more than :data:`BLOCK` numbers per trial, per block of the
  trial's draw from child streams the trial spawns; the numbers do not depend on the thread count.
* ``"philox"`` (default on CUDA, available on every device): counter-based Philox4x32-10
  (Salmon et al. 2011) evaluated with tensor operations on the draw's device: key = 64 bits of
  the trial's ``SeedSequence``, counter = (number of draws so far, element index). Uniforms take
  53 (float64) or 24 (float32) bits; normals use Box-Muller. No loop over trials; the integer
  bits are identical on CPU and CUDA, the transcendental functions of Box-Muller may differ in
  the last ulp between devices.

Determinism contract: same seed, key, trial index, back end and device -> the same numbers,
whatever the chunking. The two back ends give different (equally valid) numbers, so CPU
(numpy) and CUDA (philox) runs agree only statistically; pass ``backend="philox"`` on CPU to get
the CUDA run's integer stream.
"""

from __future__ import annotations

import copy
import math
import warnings
import zlib
from concurrent.futures import ThreadPoolExecutor
from typing import Optional, Sequence, Union

import numpy as np
import torch

from torchflow.core import _triton, tuning
from torchflow.core.checks import check_choice
from torchflow.core.errors import ArgumentError, ArgumentTypeError

__all__ = ["TrialStreams", "CorrelatedStreams", "uniform", "check_generator", "stream_key", "get_state", "set_state"]

#: numbers per block of a trial's large draw (numpy back end): a draw of more than this many numbers
#: per trial is filled from child streams, one per block, on several threads. Part of the stream
#: definition (it decides which numbers a draw gets), so not a speed knob of torchflow.core.tuning
BLOCK = 1 << 18
_POOLS: dict = {}


def stream_key(name: Union[str, int]) -> int:
    """32-bit key of a stream name (CRC32 of its UTF-8 bytes; ints pass through, mod 2**32)."""
    if isinstance(name, (int, np.integer)) and not isinstance(name, bool):
        return int(name) % 2**32
    if isinstance(name, str):
        return zlib.crc32(name.encode())
    raise ArgumentTypeError(f"key: expected a str or int stream name, got {type(name).__name__}")


def thread_pool(workers: int) -> ThreadPoolExecutor:
    """The process's pool of ``workers`` threads (made once) for work that releases the GIL (numpy's
    generators, LAPACK): :func:`fill_numpy`, :func:`torchflow.core.linalg.eigh`."""
    if workers not in _POOLS:
        _POOLS[workers] = ThreadPoolExecutor(max_workers=workers)
    return _POOLS[workers]


def fill_numpy(kind: str, tasks, np_dtype, parallel: bool = True) -> None:
    """Fill each ``(numpy Generator, out array)`` task with standard normals (``kind="normal"``) or
    uniforms, on up to ``torch.get_num_threads()`` threads when ``parallel`` (numpy releases the GIL;
    the numbers do not depend on the thread count)."""

    def fill(task):
        if kind == "normal":
            task[0].standard_normal(out=task[1], dtype=np_dtype)
        else:
            task[0].random(out=task[1], dtype=np_dtype)

    workers = min(torch.get_num_threads(), len(tasks))
    if parallel and workers > 1:
        list(thread_pool(workers).map(fill, tasks))
    else:
        for task in tasks:
            fill(task)


class TrialStreams:
    """Independent random streams, one per Monte Carlo trial.

    Args:
        seed: the run's seed (a non-negative int).
        trials: the trials' global indices ``(B,)`` (an int ``B`` means ``range(B)``). Trial
            ``i`` draws the same numbers whichever batch it is in.
        key: a name (or int) separating uses of one seed, e.g. the filter family
            (:attr:`torchflow.filters.base.Filter.random_stream`), so that a filter's numbers do
            not change when its config is renamed or other filters join the run.
        backend: ``"numpy"``, ``"philox"`` or ``"auto"`` (numpy on CPU, philox elsewhere; decided
            at the first draw from that draw's device).

    Draws advance every stream by the same count, so streams stay aligned; :meth:`select`
    returns a ``TrialStreams`` over a subset that continues those streams' states.
    """

    def __init__(
        self,
        seed: int,
        trials: Union[int, Sequence[int], torch.Tensor],
        key: Union[str, int] = 0,
        *,
        backend: str = "auto",
    ):
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or int(seed) < 0:
            raise ArgumentError(f"seed: expected a non-negative int, got {seed!r}")
        check_choice("backend", backend, ("auto", "numpy", "philox"))
        if isinstance(trials, (int, np.integer)) and not isinstance(trials, bool):
            if int(trials) < 1:
                raise ArgumentError(f"trials: expected a positive number of trials, got {trials}")
            idx = list(range(int(trials)))
        else:
            idx = [int(t) for t in (trials.tolist() if isinstance(trials, torch.Tensor) else trials)]
            if not idx or min(idx) < 0:
                raise ArgumentError(f"trials: expected non-empty non-negative trial indices, got {idx[:10]}")
        self.seed, self.key, self.trials, self.backend = int(seed), stream_key(key), idx, backend
        self._np = None  # list of numpy Generators (numpy back end), created lazily
        self._counter = 0  # philox: 128-bit blocks consumed per trial so far
        self._keys = None  # philox: (B, 2) int64 key words

    def get_state(self):
        """A snapshot of every trial's stream position (restored by :meth:`set_state`)."""
        return copy.deepcopy((self._np, self._counter, self.backend, self._keys))

    def set_state(self, state) -> None:
        """Restore a snapshot of :meth:`get_state` (the snapshot stays reusable)."""
        self._np, self._counter, self.backend, self._keys = copy.deepcopy(state)

    def __len__(self) -> int:
        return len(self.trials)

    def __repr__(self) -> str:
        shown = self.trials if len(self.trials) <= 6 else self.trials[:3] + ["..."] + self.trials[-2:]
        return f"TrialStreams(seed={self.seed}, key={self.key}, trials={shown}, backend={self.backend!r})"

    def _seed_sequence(self, trial: int) -> np.random.SeedSequence:
        return np.random.SeedSequence([self.seed, self.key, trial])

    def select(self, index: Union[slice, Sequence[int]]) -> "TrialStreams":
        """Streams of a subset of this batch's trials (positions ``index``), continuing their
        current states; the subset draws what those trials would have drawn in the full batch."""
        pos = list(range(len(self.trials)))[index] if isinstance(index, slice) else [int(i) for i in index]
        out = TrialStreams.__new__(TrialStreams)
        out.seed, out.key, out.backend = self.seed, self.key, self.backend
        out.trials = [self.trials[i] for i in pos]
        out._counter = self._counter
        out._np = None if self._np is None else [self._np[i] for i in pos]
        out._keys = None if self._keys is None else self._keys[pos]
        return out

    def normal(self, shape, *, dtype: torch.dtype = torch.float64, device=None) -> torch.Tensor:
        """Standard normal draws of ``shape`` (leading dim a multiple of B, trial-major)."""
        return self._draw("normal", shape, dtype, device)

    def uniform(self, shape, *, dtype: torch.dtype = torch.float64, device=None) -> torch.Tensor:
        """Uniform ``[0, 1)`` draws of ``shape`` (leading dim a multiple of B, trial-major)."""
        return self._draw("uniform", shape, dtype, device)

    def _per_trial(self, shape, dtype):
        """``(shape, n)``: a draw's shape as ints and its numbers per trial, after checking both."""
        name = type(self).__name__
        if dtype not in (torch.float64, torch.float32):
            raise ArgumentTypeError(f"dtype: {name} draws float64 or float32, got {dtype}")
        shape, B = tuple(int(s) for s in shape), len(self.trials)
        if not shape or shape[0] % B:
            raise ArgumentError(
                f"shape: draws from {name} need a leading trial dimension that is a "
                f"multiple of B = {B} (trial-major), got {shape}"
            )
        return shape, math.prod(shape) // B

    def _draw(self, kind, shape, dtype, device) -> torch.Tensor:
        device = torch.device("cpu") if device is None else torch.device(device)
        shape, n = self._per_trial(shape, dtype)
        if self.backend == "auto":
            self.backend = "numpy" if device.type == "cpu" else "philox"
        if self.backend == "numpy":
            return self._numpy_draw(kind, n, dtype).reshape(shape).to(device)
        return self._philox_draw(kind, n, dtype, device).reshape(shape)

    def _numpy_draw(self, kind, n, dtype) -> torch.Tensor:
        if self._np is None:
            self._np = [np.random.Generator(np.random.SFC64(self._seed_sequence(t))) for t in self.trials]
        B = len(self.trials)
        out = torch.empty((B, n), dtype=dtype)
        arr = out.numpy()
        np_dtype = np.float64 if dtype == torch.float64 else np.float32
        if n == 0:
            return out
        # one task per trial; a trial drawing more than BLOCK numbers fills its draw in blocks from
        # child generators it spawns (deterministic, and independent of B), so large draws of a
        # few trials still use every thread
        tasks = []
        for b, gen in enumerate(self._np):
            if n <= BLOCK:
                tasks.append((gen, arr[b]))
            else:
                kids = gen.spawn(-(-n // BLOCK))
                tasks += [(kid, arr[b, i * BLOCK : (i + 1) * BLOCK]) for i, kid in enumerate(kids)]
        fill_numpy(kind, tasks, np_dtype, parallel=B * n >= tuning.get().parallel_draw_min)  # speed only
        return out

    def _philox_draw(self, kind, n, dtype, device) -> torch.Tensor:
        return self._philox_numbers(kind, self._philox_bits(kind, n, dtype, device), n, dtype)

    def _philox_bits(self, kind, n, dtype, device) -> torch.Tensor:
        """The raw 32-bit words (int64 ``(B, words)``) of a draw of ``n`` numbers per trial; advances
        the counter. :meth:`_philox_numbers` turns them into the draw (split so that a CUDA graph can
        replay the second half: :mod:`torchflow.filters.graph_step`)."""
        B = len(self.trials)
        # words per number: float64 uniforms use two 32-bit words (53 bits), float32 one (24 bits);
        # Box-Muller turns two uniforms into two normals
        per = 2 if dtype == torch.float64 else 1
        n_even = n + (n % 2) if kind == "normal" else n
        words = n_even * per
        blocks = -(-words // 4)
        if self._keys is None:  # (B, 2) int64 key words
            kw = [self._seed_sequence(t).generate_state(2, np.uint32) for t in self.trials]
            self._keys = torch.tensor(np.stack(kw).astype(np.int64))
        self._keys = keys = self._keys.to(device)  # kept there: no copy to the device per draw
        bits = None
        if _philox_fusable(device):  # one kernel for the rounds, the same bits
            try:
                bits = philox4x32_fused(keys, self._counter, blocks).reshape(B, -1)[:, :words]
            except Exception as exc:
                _philox_failed(exc)
        if bits is None:
            ctr = self._counter + torch.arange(blocks, device=device, dtype=torch.int64)  # (blocks,)
            zero = torch.zeros(B, blocks, dtype=torch.int64, device=device)
            c = [(ctr & 0xFFFFFFFF).expand(B, blocks), (ctr >> 32).expand(B, blocks), zero, zero]
            key = (keys[:, :1].expand(B, blocks), keys[:, 1:].expand(B, blocks))
            bits = philox4x32(c, key).reshape(B, -1)[:, :words]  # (B, words)
        self._counter += blocks
        return bits

    @staticmethod
    def _philox_numbers(kind, bits, n, dtype) -> torch.Tensor:
        """Uniforms or normals ``(B, n)`` of ``dtype`` from the words of :meth:`_philox_bits`."""
        B = bits.shape[0]
        if dtype == torch.float64:
            k = (bits[:, 0::2] >> 5) * 67108864 + (bits[:, 1::2] >> 6)  # 27 + 26 = 53 bits
            scale, wdt = 1.0 / 9007199254740992.0, torch.float64
        else:
            k = bits >> 8  # 24 bits
            scale, wdt = 1.0 / 16777216.0, torch.float32
        if kind == "uniform":  # k / 2**bits: exact, in [0, 1)
            return (k.to(wdt) * scale).to(dtype)
        u = (k.to(wdt) + 0.5) * scale  # (0, 1]: log(u) is finite
        u1, u2 = u[:, 0::2], u[:, 1::2]
        r = torch.sqrt(-2.0 * torch.log(u1))
        theta = (2.0 * math.pi) * u2
        z = torch.stack((r * torch.cos(theta), r * torch.sin(theta)), -1).reshape(B, -1)[:, :n]
        return z.to(dtype)


class CorrelatedStreams(TrialStreams):
    """Per-trial streams that replay a stored tape of standard normals: the auxiliary variables
    ``u`` of a correlated pseudo-marginal sampler (:func:`torchflow.inference.pmmh` with
    ``correlation``; Deligiannidis, Doucet & Pitt 2018).

    Draw ``i`` of a run (the i-th ``normal`` or ``uniform`` call since construction or
    :meth:`rewind`) takes entry ``i`` of :attr:`tape`, a ``(B, n_i)`` float64 tensor of standard
    normals; a draw beyond the tape takes fresh normals from the underlying :class:`TrialStreams`
    (``seed``, ``trials``, ``key``, ``backend``) and appends them (recorded on first use). Uniforms
    are ``Phi(normal)`` (the standard normal CDF, kept below 1), so every number a filter draws
    moves continuously with ``u``. :meth:`crank_nicolson` makes the proposal
    ``u' = rho u + sqrt(1 - rho^2) eps``, which leaves the law ``N(0, I)`` of ``u`` invariant.

    Every filter that draws through :func:`torchflow.core.linalg.standard_normal` and :func:`uniform`
    accepts it (it is a :class:`TrialStreams`). A run must ask for the same sizes as the tape
    holds, draw by draw; otherwise the draw raises (a filter whose number of draws depends on
    the data cannot replay a tape).

    Args:
        seed, trials, key, backend: the fresh numbers' streams (:class:`TrialStreams`).
        tape: the stored normals, a list of ``(B, n_i)`` float64 tensors (default: empty).
    """

    def __init__(
        self,
        seed: int,
        trials: Union[int, Sequence[int], torch.Tensor],
        key: Union[str, int] = 0,
        *,
        tape: Optional[Sequence[torch.Tensor]] = None,
        backend: str = "auto",
    ):
        super().__init__(seed, trials, key, backend=backend)
        B = len(self.trials)
        self.tape = [] if tape is None else list(tape)
        for i, t in enumerate(self.tape):
            if not isinstance(t, torch.Tensor) or t.dim() != 2 or t.shape[0] != B:
                got = tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
                raise ArgumentError(f"tape[{i}]: expected a (B, n) tensor with B = {B} trials, got {got}")
        self.position = 0  # the next draw's tape entry

    def rewind(self) -> "CorrelatedStreams":
        """Start replaying the tape from its first entry again (returns self)."""
        self.position = 0
        return self

    def crank_nicolson(self, rho: float, seed: int) -> "CorrelatedStreams":
        """The proposal ``u' = rho u + sqrt(1 - rho^2) eps`` as new streams (positioned at the start),
        ``eps`` standard normals from ``TrialStreams(seed, trials, (key, "crank_nicolson"))``; draws
        beyond the tape come from ``TrialStreams(seed, trials, key)``."""
        rho = float(rho)
        noise = TrialStreams(seed, self.trials, f"{self.key}:crank_nicolson", backend=self.backend)
        scale = math.sqrt(max(0.0, 1.0 - rho * rho))
        tape = [rho * u + scale * noise.normal(u.shape, dtype=u.dtype, device=u.device) for u in self.tape]
        return CorrelatedStreams(seed, self.trials, self.key, tape=tape, backend=self.backend)

    def where(self, keep: torch.Tensor, other: "CorrelatedStreams") -> "CorrelatedStreams":
        """Streams whose tape is this one's in trials where ``keep (B,)`` is true and ``other``'s
        elsewhere (an accept/reject of ``u``); entries only one of them holds are taken from it."""
        tape = []
        for i in range(max(len(self.tape), len(other.tape))):
            if i >= len(other.tape):
                tape.append(self.tape[i])
            elif i >= len(self.tape):
                tape.append(other.tape[i])
            else:
                mine, theirs = self.tape[i], other.tape[i]
                tape.append(torch.where(keep.to(mine.device).reshape(-1, 1), mine, theirs))
        out = CorrelatedStreams.__new__(CorrelatedStreams)
        out.__dict__.update(self.__dict__)
        out.tape, out.position = tape, 0
        return out

    def get_state(self):
        return super().get_state(), self.position

    def set_state(self, state) -> None:
        super().set_state(state[0])
        self.position = state[1]

    def select(self, index: Union[slice, Sequence[int]]) -> "CorrelatedStreams":
        pos = list(range(len(self.trials)))[index] if isinstance(index, slice) else [int(i) for i in index]
        base = TrialStreams.select(self, pos)
        out = CorrelatedStreams.__new__(CorrelatedStreams)
        out.__dict__.update(base.__dict__)
        out.tape = [u[torch.as_tensor(pos, device=u.device)] for u in self.tape]
        out.position = self.position
        return out

    def _draw(self, kind, shape, dtype, device) -> torch.Tensor:
        device = torch.device("cpu") if device is None else torch.device(device)
        shape, n = self._per_trial(shape, dtype)
        B, i = len(self.trials), self.position
        if i < len(self.tape):
            z = self.tape[i]
            if z.shape[1] != n:
                raise ArgumentError(
                    f"CorrelatedStreams: draw {i} asks for {n} numbers per trial, but the tape holds "
                    f"{z.shape[1]} there: the filter's draws differ from the run that recorded the "
                    "tape (a filter whose number of draws depends on the data cannot replay one)"
                )
            z = z.to(device)
        else:
            z = super()._draw("normal", (B, n), torch.float64, device)
            self.tape.append(z)
        self.position = i + 1
        if kind == "normal":
            return z.to(dtype).reshape(shape)
        u = torch.special.ndtr(z).to(dtype)  # Phi(z), in [0, 1]
        below_one = torch.nextafter(
            torch.ones((), dtype=dtype, device=device), torch.zeros((), dtype=dtype, device=device)
        )
        return torch.minimum(u, below_one).reshape(shape)


def get_state(generator: Optional[Generatorish]):
    """A snapshot of ``generator`` (a ``torch.Generator``, :class:`TrialStreams` or ``None``: torch's
    default CPU generator) that :func:`set_state` restores, so that a computation can draw the same
    numbers twice (gradient checkpointing recomputes a filter step in the backward pass)."""
    return torch.get_rng_state() if generator is None else generator.get_state()


def set_state(generator: Optional[Generatorish], state) -> None:
    """Restore a snapshot of :func:`get_state` (the snapshot stays reusable)."""
    if generator is None:
        torch.set_rng_state(state)
    else:
        generator.set_state(state)


_M0, _M1 = 0xD2511F53, 0xCD9E8D57
_W0, _W1 = 0x9E3779B9, 0xBB67AE85
_MASK = 0xFFFFFFFF


def philox4x32(counter, key, rounds: int = 10):
    """Philox4x32 (Salmon et al., SC'11) on int64 tensors holding 32-bit words.

    Args:
        counter: four broadcastable int64 tensors (words c0..c3, each in [0, 2**32)).
        key: two int64 tensors (k0, k1).
    Returns:
        ``(..., 4)`` int64 tensor of output words.
    """
    c0, c1, c2, c3 = counter
    k0, k1 = key
    for r in range(rounds):
        p0, p1 = c0 * _M0, c2 * _M1  # < 2**64: int64 wraps, and the bit pattern is exact mod 2**64
        c0, c1, c2, c3 = ((p1 >> 32) & _MASK) ^ c1 ^ k0, p1 & _MASK, ((p0 >> 32) & _MASK) ^ c3 ^ k1, p0 & _MASK
        if r < rounds - 1:
            k0 = (k0 + _W0) & _MASK
            k1 = (k1 + _W1) & _MASK
    return torch.stack((c0, c1, c2, c3), -1)


_philox_kernel = None
_PHILOX_BLOCK = 256
_philox_broken = []  # the error of a kernel that failed to build or run here: then the torch ops


def _philox_failed(exc: Exception) -> None:
    """Fall back to the torch ops for the rest of the process, with one warning (the same bits)."""
    _philox_broken.append(exc)
    warnings.warn(
        f"torchflow.core.random: the fused Philox kernel failed ({type(exc).__name__}: {exc}); "
        "drawing with torch ops instead (the same numbers, more kernel launches)",
        RuntimeWarning,
        stacklevel=3,
    )


def _philox_fusable(device) -> bool:
    """The Triton Philox kernel applies: ``tuning.fused_philox``, Triton importable, it has not
    failed in this process, and the device is CUDA (or the CPU under Triton's interpreter,
    ``TRITON_INTERPRET=1``: tests)."""
    if not tuning.get().fused_philox or _philox_broken:
        return False
    return _triton.runs_on(device)


def philox4x32_fused(keys: torch.Tensor, counter: int, blocks: int, rounds: int = 10) -> torch.Tensor:
    """:func:`philox4x32` of the counters ``counter + j`` (``j < blocks``; words ``(lo, hi, 0, 0)``)
    under each trial's key, as one Triton kernel: ``keys (B, 2)`` int64 32-bit words ->
    ``(B, blocks, 4)`` int64 words, the same bits as the torch ops. Needs Triton."""
    global _philox_kernel
    if _philox_kernel is None:
        from torchflow.core._philox_kernel import philox_kernel

        _philox_kernel = philox_kernel
    B = keys.shape[0]
    keys = keys.contiguous()
    out = torch.empty(B, blocks, 4, dtype=torch.int64, device=keys.device)
    total = B * blocks
    if total:
        grid = (-(-total // _PHILOX_BLOCK),)
        _philox_kernel[grid](keys, out, int(counter), blocks, total, ROUNDS=rounds, BLOCK=_PHILOX_BLOCK)
    return out


Generatorish = Union[torch.Generator, TrialStreams]


def check_generator(generator, who: str = "generator", trials: Optional[int] = None) -> Generatorish:
    """Raise unless ``generator`` is a ``torch.Generator`` or :class:`TrialStreams` (made for
    ``trials`` trials, when given).

    ``None`` is refused: a filter that silently fell back on torch's global random state would not
    be reproducible from its arguments."""
    if isinstance(generator, TrialStreams) and trials is not None and len(generator) != int(trials):
        raise ArgumentError(
            f"{who}: TrialStreams made for {len(generator)} trials, but the observations have "
            f"B = {int(trials)} trials (make it with TrialStreams(seed, {int(trials)}, ...), or "
            f"select trials with streams[a:b])"
        )
    if isinstance(generator, (torch.Generator, TrialStreams)):
        return generator
    raise ArgumentTypeError(
        f"{who}: expected a torch.Generator or torchflow.core.random.TrialStreams, "
        f"got {type(generator).__name__}{generator_hint(generator)}"
    )


def generator_hint(generator) -> str:
    """How to pass randomness instead of ``generator`` (an int seed or ``None``), for error messages."""
    if isinstance(generator, (int, np.integer)) and not isinstance(generator, bool):
        return f" (for a seed, pass torch.Generator().manual_seed({int(generator)}))"
    return (
        " (randomness comes only from a passed generator: pass torch.Generator().manual_seed(seed))"
        if generator is None
        else ""
    )


def uniform(shape, *, dtype, device, generator: Optional[Generatorish]) -> torch.Tensor:
    """Uniform ``[0, 1)`` draws from a ``torch.Generator``, a :class:`TrialStreams` or (``None``)
    torch's default generator."""
    if isinstance(generator, TrialStreams):
        return generator.uniform(shape, dtype=dtype, device=device)
    return torch.rand(shape, generator=generator, dtype=dtype, device=device)
