"""Plan a run: check its arguments, simulate the data once, choose every filter's chunks of trials
from its memory formulas (trials draw from per-trial streams: the plan never changes their numbers).
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Dict, List, Mapping, Optional, Tuple, Union

import torch

from .._checks import check_count
from ..filters.base import Filter
from ..models.base import StateSpaceModel, Trajectory
from .distributed import Shard


class ConfigError(ValueError):
    """A bad run setting (a value, a name, a combination): the command line prints it as one line
    and exits with status 2. Any other exception is a failure and keeps its traceback."""


_DTYPES = {"float64": torch.float64, "float32": torch.float32, "double": torch.float64, "float": torch.float32}
#: back ends of the per-trial random streams (:class:`~torchflow.random.TrialStreams`)
RNG_BACKENDS = ("auto", "numpy", "philox")
#: seeds are in [0, SEED_LIMIT) (torch and numpy generators take a signed 64-bit seed)
SEED_LIMIT = 2**63


def require(ok: bool, name: str, what: str, got) -> None:
    """The runner's checks: a :class:`ConfigError` ``name: expected what, got got`` unless ``ok``."""
    if not ok:
        raise ConfigError(f"{name}: expected {what}, got {got!r}")


def resolve_dtype(dtype: Union[str, torch.dtype]) -> torch.dtype:
    require(isinstance(dtype, torch.dtype) or dtype in _DTYPES, "dtype", f"one of {sorted(_DTYPES)}", dtype)
    return _DTYPES.get(dtype, dtype)


def resolve_device(device: Union[str, torch.device]) -> torch.device:
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        dev = None
    require(dev is not None and dev.type in ("cpu", "cuda"), "device", "'cpu', 'cuda' or 'cuda:<index>'", device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device: 'cuda' requested but torch.cuda.is_available() is False "
                          "(a CPU-only torch build, or no GPU visible)")
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
    """``warmup``: ``"auto"``, ``True`` or ``False`` (see :func:`~torchflow.runner.run_experiment`)."""
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


def check_metric_settings(*, ospa_cutoff, ospa_order, lost_threshold) -> dict:
    """OSPA cut-off (> 0), order (>= 1) and the lost-track threshold (> 0, metres of OMAT)."""
    rules = {"ospa_cutoff": (ospa_cutoff, 0.0, "a positive number"), "ospa_order": (ospa_order, 1.0, "a number >= 1"),
             "lost_threshold": (lost_threshold, 0.0, "a positive number of metres")}
    for name, (v, low, what) in rules.items():
        require(_number(v) and v >= low and (name == "ospa_order" or v > low), f"metrics.{name}", what, v)
    return {name: float(v) for name, (v, _, _) in rules.items()}


def choose_chunk_size(filters: Mapping[str, Filter], trials: int, memory_budget_gb: float) -> int:
    """Largest chunk of trials whose estimated per-step memory fits the budget (at least 1)."""
    per_trial = max((f.bytes_per_trial() for f in filters.values()), default=1)
    return max(1, min(trials, int(memory_budget_gb * 2**30 // max(per_trial, 1))))


def filter_chunk(f: Filter, n_run: int, chunk_size: Optional[int], memory_budget_gb: float) -> int:
    """A filter's chunk of trials: ``chunk_size`` if given, else the most its memory estimate allows,
    capped by its preferred batch (a particle filter whose one trial exceeds the budget gets a
    ``particle_chunk``); its ``trials_per_call`` (the localisers: 1) caps both."""
    cap = f.trials_per_call
    if chunk_size:
        c = min(int(chunk_size), cap or int(chunk_size))
        need = c * f.bytes_per_trial()
        if need > memory_budget_gb * 2**30:
            warnings.warn(f"chunk_size={chunk_size}: {f.name} is estimated at {need / 2**30:.3g} GiB per chunk of {c} "
                          f"trials, over memory_budget_gb={memory_budget_gb:g}; it may run out of memory (leave "
                          "chunk_size unset to size chunks from the budget)", stacklevel=2)
        return c
    c = choose_chunk_size({"f": f}, n_run, memory_budget_gb)
    if c == 1 and f.particle_chunk is None:  # one trial may still exceed it: chunk particles
        pc = f.plan_memory(memory_budget_gb * 2**30)
        if pc is not None:
            warnings.warn(f"memory_budget_gb={memory_budget_gb:g}: {f.name} runs one trial at a time in blocks "
                          f"of {pc} of its {f.n_particles} particles (estimated {f.bytes_per_trial() / 2**30:.3g} "
                          "GiB per trial); raise the budget if this machine has more memory", stacklevel=2)
    return min(c, f.preferred_chunk_trials() or c, cap or c)


def simulate(model: StateSpaceModel, trials: int, steps: int, inits_per_track: int, generator):
    """``trials`` trajectories (groups of ``inits_per_track`` share one) and each trial's prior."""
    n_tracks = math.ceil(trials / inits_per_track)
    traj = model.simulate(n_tracks, steps, generator)
    if inits_per_track > 1:
        traj = traj[torch.arange(trials, device=traj.states.device) // inits_per_track]
    mean, cov = model.initial_belief(traj.states[:, 0], generator)
    return traj, mean, cov


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

    @property
    def n_run(self) -> int:
        return self.hi - self.lo


def check_settings(*, trials, steps, seed, inits_per_track, chunk_size, memory_budget_gb, device, dtype,
                   rng_backend, trial_range) -> RunSettings:
    """Every run argument checked; a bad one raises :class:`ConfigError` naming it."""
    trials = _count("trials", trials)
    if chunk_size is not None:
        chunk_size = _count("chunk_size", chunk_size, hint=" (or None: from memory_budget_gb)")
    require(_number(memory_budget_gb) and memory_budget_gb > 0, "memory_budget_gb", "a positive number of GiB",
             memory_budget_gb)
    inits_per_track = _count("inits_per_track", inits_per_track)
    warn_uneven_tracks(trials, inits_per_track)
    return RunSettings(trials, _count("steps", steps), check_seed(seed), inits_per_track,
                       chunk_size, float(memory_budget_gb), resolve_device(device), resolve_dtype(dtype),
                       check_rng_backend(rng_backend), *check_trial_range(trial_range, trials))


def warn_uneven_tracks(trials: int, inits_per_track: int) -> None:
    """Trials share a trajectory in groups of ``inits_per_track`` (:func:`simulate`); a warning when
    the groups are not all that size: ``inits_per_track`` above ``trials`` (every trial shares one
    trajectory) or not dividing it (the last trajectory has fewer trials)."""
    if inits_per_track > trials:
        warnings.warn(f"inits_per_track={inits_per_track} is more than trials={trials}: all {trials} trials share "
                      f"one trajectory (inits_per_track={trials} says so)", stacklevel=3)
    elif trials % inits_per_track:
        last = trials % inits_per_track
        warnings.warn(f"inits_per_track={inits_per_track} does not divide trials={trials}: the last trajectory is "
                      f"shared by {last} trial{'s' if last > 1 else ''}, the others by {inits_per_track} (trials="
                      f"{-(-trials // inits_per_track) * inits_per_track} keeps the groups equal)",
                      stacklevel=3)


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
        """What a saved chunk's header must repeat (see :class:`~torchflow.runner.checkpoint.ChunkStore`)."""
        s = self.settings
        return dict(seed=s.seed, trials=s.trials, steps=s.steps, inits_per_track=s.inits_per_track,
                    stream=f.stream_name, rng_backend=s.rng_backend, dtype=str(s.dtype), device=s.device.type)


def make_plan(model: StateSpaceModel, filters: Mapping[str, Filter], settings: RunSettings,
              shard: Optional[Shard] = None, simulator=None) -> RunPlan:
    """Move model and filters to the run's device/dtype, simulate, and choose the chunks.
    ``simulator``: replaces :func:`simulate` (same signature), e.g. to filter given data."""
    s = settings
    model.to(device=s.device, dtype=s.dtype)
    for name, f in filters.items():
        if f.model is not model:
            raise ConfigError(f"filters[{name!r}]: holds a different model instance than `model`")
        if model.structure.padded_measurements and not f.padded_measurements:
            raise ConfigError(f"filter.{name}: {type(f).__name__} cannot run on {type(model).__name__}, whose "
                              "measurements are padded sets with a mask; select a localiser (bs, pfi_d, pfi_s, pfi_os)")
        f.to(device=s.device, dtype=s.dtype)
    gen = torch.Generator(device=s.device).manual_seed(int(s.seed))
    traj, mean0, cov0 = (simulator or simulate)(model, s.trials, s.steps, s.inits_per_track, gen)
    shard = shard or Shard()
    chunks = {name: filter_chunk(f, s.n_run, s.chunk_size, s.memory_budget_gb) for name, f in filters.items()}
    if shard.world > 1 and not s.chunk_size:  # every rank gets a share
        chunks = {name: min(c, -(-s.n_run // shard.world)) for name, c in chunks.items()}
    return RunPlan(s, traj, mean0, cov0, chunks, shard)

