"""Plan a run: check its arguments, simulate the data once, choose every filter's chunks of trials
from its memory formulas (trials draw from per-trial streams: the plan never changes their numbers).
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Mapping, Optional, Tuple, Union

import torch

from torchflow.app.data import declared_prior
from torchflow.app.runner.distributed import Shard
from torchflow.core.checks import allocation_failure, check_count
from torchflow.core.covariances import DiagonalCovariance, prior_bytes
from torchflow.core.errors import ArgumentError, NonFiniteError
from torchflow.filters.base import Filter
from torchflow.models.base import StateSpaceModel, Trajectory


class ConfigError(ArgumentError):
    """A bad run setting (a value, a name, a combination): the command line prints it as one line
    and exits with status 2. Any other exception is a failure and keeps its traceback."""


_DTYPES = {"float64": torch.float64, "float32": torch.float32, "double": torch.float64, "float": torch.float32}
#: back ends of the per-trial random streams (:class:`~torchflow.core.random.TrialStreams`)
RNG_BACKENDS = ("auto", "numpy", "philox")
#: seeds are in [0, SEED_LIMIT) (torch and numpy generators take a signed 64-bit seed)
SEED_LIMIT = 2**63


#: what a run does with a trial whose filter goes non-finite (``nonfinite_trials``): ``"lose"``
#: marks it lost and scores the others, ``"fail"`` fails the filter's row (every trial of it)
NONFINITE_TRIALS = ("lose", "fail")


def require(ok: bool, name: str, what: str, got) -> None:
    """The runner's checks: a :class:`ConfigError` ``name: expected what, got got`` unless ``ok``."""
    if not ok:
        raise ConfigError(f"{name}: expected {what}, got {got!r}")


def resolve_dtype(dtype: Union[str, torch.dtype]) -> torch.dtype:
    ok = dtype in (torch.float32, torch.float64) if isinstance(dtype, torch.dtype) else dtype in _DTYPES
    require(ok, "dtype", f"one of {sorted(_DTYPES)} (or torch.float32 / torch.float64)", dtype)
    return _DTYPES.get(dtype, dtype)


def resolve_device(device: Union[str, torch.device]) -> torch.device:
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        dev = None
    require(dev is not None and dev.type in ("cpu", "cuda"), "device", "'cpu', 'cuda' or 'cuda:<index>'", device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(
            "device: 'cuda' requested but torch.cuda.is_available() is False "
            "(a CPU-only torch build, or no GPU visible)"
        )
    return dev


def _count(name: str, value, hint: str = "", minimum: int = 1) -> int:
    try:
        return check_count(name, value, hint=hint, minimum=minimum)
    except ValueError as e:
        raise ConfigError(str(e)) from None


def check_seed(seed) -> int:
    """A seed in ``[0, 2**63)``."""
    seed = _count("seed", seed, minimum=0)
    require(seed < SEED_LIMIT, "seed", "an integer in [0, 2**63)", seed)
    return seed


def check_warmup(warmup) -> None:
    """``warmup``: ``"auto"``, ``True`` or ``False`` (see :func:`~torchflow.app.runner.run_experiment`)."""
    require(warmup == "auto" or isinstance(warmup, bool), "warmup", "auto, true or false", warmup)


def check_rng_backend(rng_backend) -> str:
    require(rng_backend in RNG_BACKENDS, "rng_backend", f"one of {', '.join(RNG_BACKENDS)}", rng_backend)
    return rng_backend


def check_trial_range(trial_range, trials: int) -> Tuple[int, int]:
    if trial_range is None:
        return 0, trials
    try:
        lo, hi = (int(v) for v in trial_range)
        ok = all(float(v) == int(v) for v in trial_range) and 0 <= lo < hi <= trials
    except (TypeError, ValueError):
        ok = False
    require(ok, "trial_range", f"[start, stop] with 0 <= start < stop <= trials = {trials}", trial_range)
    return lo, hi


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def check_metric_settings(*, ospa_cutoff, ospa_order, lost_threshold, burn_in=0, steps: Optional[int] = None) -> dict:
    """OSPA cut-off (> 0), order (>= 1), the lost-track threshold (> 0, metres of OMAT) and the
    burn-in (an integer >= 0 of steps, fewer than ``steps`` when given)."""
    rules = {
        "ospa_cutoff": (ospa_cutoff, 0.0, "a positive number"),
        "ospa_order": (ospa_order, 1.0, "a number >= 1"),
        "lost_threshold": (lost_threshold, 0.0, "a positive number of metres"),
    }
    for name, (v, low, what) in rules.items():
        require(_number(v) and v >= low and (name == "ospa_order" or v > low), f"metrics.{name}", what, v)
    whole = isinstance(burn_in, int) and not isinstance(burn_in, bool)
    if steps is None:
        require(whole and burn_in >= 0, "metrics.burn_in", "an integer >= 0 (steps dropped from the start)", burn_in)
    else:
        require(
            whole and 0 <= burn_in < steps,
            "metrics.burn_in",
            f"an integer in [0, steps = {steps}) (steps dropped from the start of the scores)",
            burn_in,
        )
    return {**{name: float(v) for name, (v, _, _) in rules.items()}, "burn_in": int(burn_in)}


def choose_chunk_size(filters: Mapping[str, Filter], trials: int, memory_budget_gb: float) -> int:
    """Largest chunk of trials whose estimated per-step memory fits the budget (at least 1)."""
    per_trial = max((f.bytes_per_trial() for f in filters.values()), default=1)
    fit = memory_budget_gb * 2**30 / max(per_trial, 1)  # a float: a huge budget is inf, not an error
    return max(1, min(trials, int(fit) if fit < trials else trials))


def filter_chunk(f: Filter, n_run: int, chunk_size: Optional[int], memory_budget_gb: float) -> int:
    """A filter's chunk of trials: ``chunk_size`` if given, else the most its memory estimate allows,
    capped by its preferred batch (a particle filter whose one trial exceeds the budget gets a
    ``particle_chunk``); its ``trials_per_call`` (the localisers: 1) caps both."""
    cap = f.trials_per_call
    if chunk_size:
        c = min(int(chunk_size), cap or int(chunk_size))
        need = c * f.bytes_per_trial()
        if need > memory_budget_gb * 2**30:
            warnings.warn(
                f"chunk_size={chunk_size}: {f.name} is estimated at {need / 2**30:.3g} GiB per chunk of {c} "
                f"trials, over memory_budget_gb={memory_budget_gb:g}; it may run out of memory (leave "
                "chunk_size unset to size chunks from the budget)",
                stacklevel=2,
            )
        return c
    c = choose_chunk_size({"f": f}, n_run, memory_budget_gb)
    if c == 1 and f.particle_chunk is None:  # one trial may still exceed it: chunk particles
        pc = f.plan_memory(memory_budget_gb * 2**30)
        if pc is not None:
            warnings.warn(
                f"memory_budget_gb={memory_budget_gb:g}: {f.name} runs one trial at a time in blocks "
                f"of {f.describe_blocks(pc)} (estimated {f.bytes_per_trial() / 2**30:.3g} "
                "GiB per trial); raise the budget if this machine has more memory",
                stacklevel=2,
            )
        elif f.bytes_per_trial() > memory_budget_gb * 2**30 and not getattr(f, "_local_chunk_given", False):
            warnings.warn(  # nothing smaller to run than one trial (a given local_chunk is the user's choice)
                f"memory_budget_gb={memory_budget_gb:g}: one trial of {f.name} is estimated at "
                f"{f.bytes_per_trial() / 2**30:.3g} GiB, over the budget, and it has no smaller unit of work: "
                "it runs one trial at a time over the budget (raise memory_budget_gb)",
                stacklevel=2,
            )
    return min(c, f.preferred_chunk_trials() or c, cap or c)


#: the share of the memory available on the run's device (:func:`available_memory`, read when the run
#: is planned) that one filter chunk may use per time step when ``memory_budget_gb`` is not given
#: (``None``/``auto``): two fifths, which leaves the simulated data, the results and other processes
#: room under the size check's warning at :data:`MEMORY_WARN_SHARE`
MEMORY_BUDGET_SHARE = 0.4


def auto_memory_budget(device: torch.device) -> Tuple[float, str]:
    """``(GiB, how)``: the default memory budget of a run on ``device``, :data:`MEMORY_BUDGET_SHARE`
    of what :func:`available_memory` finds there (a GPU's free memory, the host's available RAM
    under its limits), rounded down to a power of two GiB: the chunks, and so the round-off of
    filters whose batched linear algebra depends on a call's size, stay the same from run to run
    while the free memory moves a little. ``how`` says so in words, for the run's header and results."""
    avail, what = available_memory(device)
    share = MEMORY_BUDGET_SHARE * avail / 2**30
    gib = 2.0 ** math.floor(math.log2(share)) if share > 0 else 0.0
    return gib, f"{100 * MEMORY_BUDGET_SHARE:.0f}% of the {_gib(avail)} {what}, rounded down to a power of two"


#: the size check refuses a run whose estimated memory exceeds what is available, and warns above
#: this share of it (other processes need memory too; the estimate is rough)
MEMORY_WARN_SHARE = 0.5
#: host bytes of one small tensor a filter keeps per time step (object, storage, allocation; measured)
TENSOR_BYTES = 600
#: the tensors a filter keeps per time step (estimate, log-evidence increment, ESS, non-finite flag)
TENSORS_PER_STEP = 4
#: host bytes of one result row (a dict of a filter's numbers for one time step or one trial; measured 300-500)
ROW_BYTES = 512
#: float64 (trials, steps) series of one filter while it is scored, besides its estimates and the
#: truth (log-evidence increments, ESS, the metrics' values)
SCORED_SERIES = 6


def _gib(n: float) -> str:
    """``n`` bytes in MiB or GiB (three digits; whole GiB from 1000)."""
    return (
        f"{n / 2**20:.3g} MiB" if n < 2**28 else f"{n / 2**30:.3g} GiB" if n < 1000 * 2**30 else f"{n / 2**30:,.0f} GiB"
    )


@dataclass
class MemoryEstimate:
    """A run's memory (bytes), estimated before anything is simulated (:func:`estimate_memory`):
    ``data`` (the simulation's peak and the priors: the run's device), ``filters`` (the largest
    filter chunk: its per-step working memory as its memory formula gives it, which
    ``memory_budget_gb`` bounds, and the outputs it keeps for every time step), ``results`` (what
    the run keeps to score and write: per-trial and per-step rows, the scored series; the host)."""

    data: int
    filters: int
    results: int
    #: bytes on the host of a run on a GPU (its results, the per-step tensors' bookkeeping, the copies of the data)
    host: int = 0

    @property
    def total(self) -> int:
        return self.data + self.filters + self.results

    def parts(self) -> str:
        return f"simulated data {_gib(self.data)}, filter chunks {_gib(self.filters)}, results {_gib(self.results)}"


def estimate_memory(
    model: StateSpaceModel,
    filters: Mapping[str, Filter],
    s: "RunSettings",
    chunks: Mapping[str, int],
    simulated: bool = True,
) -> MemoryEstimate:
    """The memory of a run (:class:`MemoryEstimate`), from its sizes: ``trials`` B, ``steps`` T, the
    run's trials n (``trial_range``), the state and measurement dimensions d and m, the dtype's
    bytes b, each filter's chunk c and memory formula (``bytes_per_trial``), F filters:

    * data = the model's :meth:`~torchflow.models.StateSpaceModel.simulation_bytes` (at least
      b B ((T+1) d + T m)) + b B (d + d^2) (the priors; b B 2d for a
      declared diagonal prior), and the copy of ``inits_per_track`` > 1;
      ``simulated=False`` (given data): 0;
    * filters = max over filters of c bytes_per_trial + T (4 x 600 + 2 c b (d + 3));
    * results = F (T + n) 512 (the result rows) + 8 n T (2 d + 6) (the scored float64 series).
    """
    b = torch.empty((), dtype=s.dtype).element_size()
    B, T, n, d, m = s.trials, s.steps, s.n_run, model.state_dim, model.obs_dim or 0
    traj = b * B * ((T + 1) * d + T * m)
    data = 0
    if simulated:
        data = max(model.simulation_bytes(math.ceil(B / s.inits_per_track), T), 0) + B * (b * d + prior_bytes(model, b))
        data += traj if s.inits_per_track > 1 else 0
    bookkeeping = T * TENSORS_PER_STEP * TENSOR_BYTES
    work = max(
        (chunks[k] * f.bytes_per_trial() + 2 * T * chunks[k] * b * (d + 3) for k, f in filters.items()), default=0
    )
    results = len(filters) * (T + n) * ROW_BYTES + 8 * n * T * (2 * d + SCORED_SERIES) if filters else 0
    if s.device.type == "cpu":
        return MemoryEstimate(data, work + (bookkeeping if filters else 0), results)
    host = results + (bookkeeping if filters else 0) + traj * n // B
    return MemoryEstimate(data, work, results, host=host)


def available_memory(device: torch.device) -> Tuple[int, str]:
    """``(bytes, what)``: the memory this process can still use on ``device``: a GPU's free memory;
    on the host the least of the available RAM (``MemAvailable``), the room left under this
    process's address-space limit (``ulimit -v``) and under its cgroup's memory limit (a container)."""
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        return int(free), f"free on {device}"
    found = []
    try:
        found.append((_kib(Path("/proc/meminfo").read_text(), "MemAvailable:"), "available RAM"))
    except (OSError, IndexError, ValueError):
        try:
            found.append((os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"), "free RAM"))
        except (OSError, ValueError, AttributeError):
            pass
    try:
        import resource

        limit = resource.getrlimit(resource.RLIMIT_AS)[0]
        if limit != resource.RLIM_INFINITY:
            used = _kib(Path("/proc/self/status").read_text(), "VmSize:")
            found.append((max(limit - used, 0), "left under the address-space limit (ulimit -v)"))
    except (ImportError, OSError, IndexError, ValueError):
        pass
    try:
        cap = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if cap != "max":
            used = int(Path("/sys/fs/cgroup/memory.current").read_text())
            found.append((max(int(cap) - used, 0), "left under this container's memory limit"))
    except (OSError, ValueError):
        pass
    return min(found) if found else (2**62, "unknown")


def _kib(text: str, key: str) -> int:
    """The ``key: <n> kB`` entry of a ``/proc`` file, in bytes."""
    return int(text.split(key, 1)[1].split()[0]) * 1024


def check_memory(
    model: StateSpaceModel,
    filters: Mapping[str, Filter],
    s: "RunSettings",
    chunks: Mapping[str, int],
    simulated: bool = True,
) -> MemoryEstimate:
    """The size check before anything is simulated: a :class:`ConfigError` naming trials and steps,
    the estimate (:func:`estimate_memory`) and the memory available (:func:`available_memory`) when
    the run cannot fit; a warning when it needs more than :data:`MEMORY_WARN_SHARE` of it. A run on a
    GPU is checked there (data, filter chunks) and on the host (results)."""
    est = estimate_memory(model, filters, s, chunks, simulated)
    checks = [(est.total, est.data, s.device)]
    if s.device.type == "cuda":
        checks = [(est.data + est.filters, est.data, s.device), (est.host, 0, torch.device("cpu"))]
    sizes = f"trials={s.trials}, steps={s.steps}"
    for need, data, dev in checks:
        if need <= 0:
            continue
        avail, what = available_memory(dev)
        where = f"{_gib(avail)} {what}" + ("" if dev.type == "cpu" else f" ({dev})")
        if need > avail:
            split = (
                f"lower trials or steps (the simulated data alone needs {_gib(data)}; trial_range runs a part "
                "of the trials but simulates them all)"
                if data > avail
                else "lower trials or steps, or run the trials in parts with trial_range=[start, stop] (each part "
                "keeps only its trials' results)"
            )
            one = {k: f.bytes_per_trial() for k, f in filters.items()} if dev == s.device else {}
            alone = [k for k, b in one.items() if b > avail]
            if alone:  # no split of trials helps: one trial of these filters does not fit
                d, m = model.state_dim, model.obs_dim
                one_filter = len(alone) == 1
                split = (
                    f"{', '.join(alone)} alone need{'s' if one_filter else ''} about "
                    f"{_gib(max(one[k] for k in alone))} for one trial at d = {d}, m = {m}, so no split of the "
                    f"trials fits: leave {'it' if one_filter else 'them'} out of this run (filter=[...]), lower "
                    "the model's size, or use filters whose memory grows linearly in d (the ensemble Kalman "
                    "filters, the bootstrap PF)"
                )
            raise ConfigError(
                f"{sizes}: the run needs about {_gib(need)} of memory ({est.parts()}), more than the {where}; {split}"
            )
        if need > MEMORY_WARN_SHARE * avail:
            warnings.warn(
                f"{sizes}: the run needs about {_gib(need)} of memory ({est.parts()}), "
                f"{100 * need / avail:.0f}% of the {where}; it may run out of memory if other processes "
                "need some",
                stacklevel=3,
            )
    return est


def simulate(model: StateSpaceModel, trials: int, steps: int, inits_per_track: int, generator):
    """``trials`` trajectories (groups of ``inits_per_track`` share one) and each trial's prior."""
    n_tracks = math.ceil(trials / inits_per_track)
    try:
        traj = model.simulate(n_tracks, steps, generator)
    except NonFiniteError as e:  # the model's settings (a step too large, a parameter): one line, exit 2
        raise ConfigError(f"model: {e}") from None
    if inits_per_track > 1:
        traj = traj[torch.arange(trials, device=traj.states.device) // inits_per_track]
    mean, cov = model.initial_belief(traj.states[:, 0], generator)
    return traj, mean, cov


def data_sizes(observations: torch.Tensor, trials: Optional[int], steps: Optional[int]) -> Tuple[int, int]:
    """``(trials, steps)`` of a run on recorded ``observations``: ``(T, m)`` is one series that
    every trial filters (``trials``: how many independent runs; ``None``: 10); ``(B, T, m)`` holds B
    series, one per trial (``trials`` must be B or ``None``). ``steps`` must be T or ``None``."""
    T = observations.shape[-2]
    if observations.dim() == 3:
        B = observations.shape[0]
        require(
            trials is None or trials == B,
            "trials",
            f"the number of recorded series B = {B} (data (B, T, m): one "
            f"trial per series; leave trials unset or give {B})",
            trials,
        )
        trials = B
    require(steps is None or steps == T, "steps", f"the recorded series' length T = {T} (leave steps unset)", steps)
    return (10 if trials is None else trials), T


def recorded(observations: torch.Tensor, prior=None, states: Optional[torch.Tensor] = None):
    """A ``simulator`` (:func:`make_plan`) that simulates nothing: the recorded ``observations``
    (``(T, m)``: every trial filters the one series; ``(B, T, m)``: one series per trial), the true
    ``states`` (``(T+1, d)`` / ``(B, T+1, d)``; ``None``: the trajectory's ``states`` is ``None``, no
    truth), and the prior ``prior = (mean, cov)`` (``(d,)``/``(B, d)``, ``(d, d)``/``(B, d, d)``) or,
    if ``None``, with states the model's ``initial_belief`` at the true initial state (as
    :func:`simulate` draws it), without the model's declared prior
    (:func:`torchflow.app.data.declared_prior`)."""

    def simulator(model: StateSpaceModel, trials: int, steps: int, inits_per_track: int, generator):
        obs = observations.to(dtype=model.dtype, device=model.device)
        obs = obs.expand(trials, -1, -1).clone() if obs.dim() == 2 else obs  # one copy per trial: contiguous
        d = model.state_dim
        x = None
        if states is not None:
            x = states.to(dtype=model.dtype, device=model.device)
            x = x.expand(trials, -1, -1).clone() if x.dim() == 2 else x
            require(
                tuple(x.shape) == (trials, obs.shape[1] + 1, d),
                "states",
                f"the true states ({obs.shape[1] + 1}, {d}) or ({trials}, {obs.shape[1] + 1}, {d}) of the recorded "
                "series (the initial state, then one row per observation)",
                tuple(states.shape),
            )
        if prior is None and x is not None:  # scored as a simulation: its prior around the true initial state
            mean, cov = model.initial_belief(x[:, 0], generator)
            return Trajectory(x, obs), mean, cov
        if prior is None:
            try:
                mean, cov = declared_prior(model, trials)
            except ArgumentError as e:
                raise ConfigError(str(e)) from None
        else:
            require(
                isinstance(prior, (tuple, list)) and len(prior) == 2,
                "prior",
                "a pair (mean, cov)",
                type(prior).__name__,
            )
            mean, cov = prior
        ok = (
            isinstance(mean, torch.Tensor)
            and isinstance(cov, (torch.Tensor, DiagonalCovariance))
            and tuple(mean.shape) in ((d,), (trials, d))
            and tuple(cov.shape) in ((d, d), (trials, d, d))
        )
        got = [
            tuple(t.shape) if isinstance(t, (torch.Tensor, DiagonalCovariance)) else type(t).__name__
            for t in (mean, cov)
        ]
        require(
            ok,
            "prior",
            f"(mean, cov) of shapes (d,) or (B, d) and (d, d) or (B, d, d) (or a "
            f"DiagonalCovariance of (d,) or (B, d) variances) with d = {d}, B = {trials}",
            got,
        )
        mean = mean.detach().to(dtype=model.dtype, device=model.device).expand(trials, d)
        cov = cov.detach().to(dtype=model.dtype, device=model.device).expand(trials, d, d)
        return Trajectory(x, obs), mean, cov

    return simulator


@dataclass
class RunSettings:
    """The checked arguments of a run (:func:`check_settings`); trials ``[lo, hi)`` are run."""

    trials: int
    steps: int
    seed: int
    inits_per_track: int
    chunk_size: Optional[int]
    memory_budget_gb: float
    device: torch.device
    dtype: torch.dtype
    rng_backend: str
    lo: int
    hi: int
    #: where ``memory_budget_gb`` came from: ``"given"`` or the share of the free memory it is
    budget_from: str = "given"

    @property
    def n_run(self) -> int:
        return self.hi - self.lo


def check_settings(
    *, trials, steps, seed, inits_per_track, chunk_size, memory_budget_gb, device, dtype, rng_backend, trial_range
) -> RunSettings:
    """Every run argument checked; a bad one raises :class:`ConfigError` naming it."""
    trials = _count("trials", trials)
    if chunk_size is not None:
        chunk_size = _count("chunk_size", chunk_size, hint=" (or None: from memory_budget_gb)")
    auto = memory_budget_gb is None or memory_budget_gb == "auto"
    require(
        auto or (_number(memory_budget_gb) and memory_budget_gb > 0),
        "memory_budget_gb",
        "a positive number of GiB, or null/auto (a share of the memory free on the device)",
        memory_budget_gb,
    )
    inits_per_track = _count("inits_per_track", inits_per_track)
    warn_uneven_tracks(trials, inits_per_track)
    device = resolve_device(device)
    budget, how = auto_memory_budget(device) if auto else (float(memory_budget_gb), "given")
    return RunSettings(
        trials,
        _count("steps", steps),
        check_seed(seed),
        inits_per_track,
        chunk_size,
        budget,
        device,
        resolve_dtype(dtype),
        check_rng_backend(rng_backend),
        *check_trial_range(trial_range, trials),
        budget_from=how,
    )


def warn_uneven_tracks(trials: int, inits_per_track: int) -> None:
    """Trials share a trajectory in groups of ``inits_per_track`` (:func:`simulate`); a warning when
    the groups are not all that size: ``inits_per_track`` above ``trials`` (every trial shares one
    trajectory) or not dividing it (the last trajectory has fewer trials)."""
    if inits_per_track > trials:
        warnings.warn(
            f"inits_per_track={inits_per_track} is more than trials={trials}: all {trials} trials share "
            f"one trajectory (inits_per_track={trials} says so)",
            stacklevel=3,
        )
    elif trials % inits_per_track:
        last = trials % inits_per_track
        warnings.warn(
            f"inits_per_track={inits_per_track} does not divide trials={trials}: the last trajectory is "
            f"shared by {last} trial{'s' if last > 1 else ''}, the others by {inits_per_track} (trials="
            f"{-(-trials // inits_per_track) * inits_per_track} keeps the groups equal)",
            stacklevel=3,
        )


@dataclass
class RunPlan:
    """The data and the chunks of one run."""

    settings: RunSettings
    traj: Trajectory
    mean0: torch.Tensor
    cov0: torch.Tensor
    chunks: Dict[str, int]
    shard: Shard = field(default_factory=Shard)

    def trial_chunks(self, size: int) -> List[Tuple[int, int]]:
        """Chunks ``[(start, stop), ...]`` of ``size`` trials over the run's trial range."""
        return [(a, min(a + size, self.settings.hi)) for a in range(self.settings.lo, self.settings.hi, size)]

    def meta(self, f: Filter) -> dict:
        """What a saved chunk's header must repeat (see :class:`~torchflow.app.runner.checkpoint.ChunkStore`)."""
        s = self.settings
        return dict(
            seed=s.seed,
            trials=s.trials,
            steps=s.steps,
            inits_per_track=s.inits_per_track,
            stream=f.stream_name,
            rng_backend=s.rng_backend,
            dtype=str(s.dtype),
            device=s.device.type,
        )


def make_plan(
    model: StateSpaceModel,
    filters: Mapping[str, Filter],
    settings: RunSettings,
    shard: Optional[Shard] = None,
    simulator=None,
) -> RunPlan:
    """Move model and filters to the run's device/dtype, simulate, and choose the chunks.
    ``simulator``: replaces :func:`simulate` (same signature), e.g. to filter given data."""
    s = settings
    model.to(device=s.device, dtype=s.dtype)
    for name, f in filters.items():
        if f.model is not model:
            raise ConfigError(f"filters[{name!r}]: holds a different model instance than `model`")
        if model.structure.padded_measurements and not f.padded_measurements:
            raise ConfigError(
                f"filter.{name}: {type(f).__name__} cannot run on {type(model).__name__}, whose "
                "measurements are padded sets with a mask; select a localiser (bs, pfi_d, pfi_s, pfi_os)"
            )
        f.to(device=s.device, dtype=s.dtype)
    shard = shard or Shard()
    chunks = {name: filter_chunk(f, s.n_run, s.chunk_size, s.memory_budget_gb) for name, f in filters.items()}
    if shard.world > 1 and not s.chunk_size:  # every rank gets a share
        chunks = {name: min(c, -(-s.n_run // shard.world)) for name, c in chunks.items()}
    check_memory(model, filters, s, chunks, simulated=simulator in (None, simulate))  # given data: held already
    gen = torch.Generator(device=s.device).manual_seed(int(s.seed))
    try:
        traj, mean0, cov0 = (simulator or simulate)(model, s.trials, s.steps, s.inits_per_track, gen)
    except (MemoryError, RuntimeError) as err:  # the allocator's refusal, where the size check let it through
        asked = allocation_failure(err)
        if asked is None:
            raise
        raise ConfigError(
            f"trials={s.trials}, steps={s.steps}: the simulation ran out of memory{asked}; lower trials or steps"
        ) from None
    return RunPlan(s, traj, mean0, cov0, chunks, shard)
