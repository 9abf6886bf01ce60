"""``run_experiment``: plan -> execute (every filter over its chunks of trials, with stop requests,
checkpoints and shards; a failing filter's traceback goes to the ``torchflow.app.runner`` log) -> score.
"""

from __future__ import annotations

import logging
import time
import traceback
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable, List, Mapping, Optional, Sequence, Tuple, Union

import torch
from tqdm.auto import tqdm

from torchflow.app.data import check_observations
from torchflow.app.runner.checkpoint import CHUNK_FIELDS, ChunkStore, fill_lost
from torchflow.app.runner.distributed import Shard
from torchflow.app.runner.plan import (
    NONFINITE_TRIALS,
    ConfigError,
    RunPlan,
    check_metric_settings,
    check_settings,
    check_warmup,
    data_sizes,
    make_plan,
    recorded,
)
from torchflow.app.runner.score import SUMMARY_COLUMNS, ExperimentResult, estimate_spread, make_scorer, score_filter
from torchflow.core import metrics, paths, tuning
from torchflow.core import progress as _progress
from torchflow.core.checks import NonFiniteError
from torchflow.core.errors import ArgumentError
from torchflow.core.random import TrialStreams
from torchflow.filters.base import Estimator, Filter
from torchflow.flows import select
from torchflow.models.base import StateSpaceModel, Trajectory

log = logging.getLogger("torchflow.app.runner")


class StopRequest:
    """Ctrl-C / SIGTERM handling that never tears a run apart mid-bookkeeping: :meth:`handler`
    (the command shell's for SIGINT and SIGTERM; in a script: ``signal.signal(signal.SIGTERM,
    STOP.handler)``) raises ``KeyboardInterrupt`` at once inside a filter's chunk and during the
    simulation (:class:`RunStopped`), else the run stops at the next chunk boundary (the finished
    chunks are always scored and written). Outside
    a chunk it only records the request: other loops (learning's epochs) poll :attr:`requested`.
    ``signum``: the first signal received; :attr:`exit_code`: ``128 + signum`` (130 for SIGINT,
    143 for SIGTERM; 130 when the request came without a signal number)."""

    def __init__(self):
        self.requested, self.signum, self._depth = False, None, 0

    def handler(self, signum, frame):
        self.requested = True
        if self.signum is None and isinstance(signum, int):
            self.signum = int(signum)
        if self._depth:
            raise KeyboardInterrupt

    @property
    def exit_code(self) -> int:
        """The exit status of a process this request stopped: ``128 + signum`` (130: Ctrl-C)."""
        return 128 + (self.signum or 2)

    @property
    def name(self) -> str:
        """``Ctrl-C`` (SIGINT), ``SIGTERM``, or the signal's name."""
        if self.signum in (None, 2):
            return "Ctrl-C"
        try:
            import signal

            return signal.Signals(self.signum).name
        except ValueError:
            return f"signal {self.signum}"

    def check(self) -> None:
        if self.requested:
            raise KeyboardInterrupt

    def reset(self) -> None:
        self.requested, self.signum = False, None

    @contextmanager
    def interruptible(self):
        self._depth += 1
        try:
            yield
        finally:
            self._depth -= 1


#: the process's stop request (see :class:`StopRequest`)
STOP = StopRequest()


class RunStopped(KeyboardInterrupt):
    """A stop request (:data:`STOP`) ended a run before its first filter started (during the
    simulation): nothing was computed. The message says so and names the signal."""


class _SimulationWatch:
    """The watcher of the loops before the filters (a model's simulation reports each time step
    through :mod:`torchflow.core.progress`): a stop request ends the loop at once; after
    ``first`` seconds and then every ``every`` seconds a log line says how far it got."""

    def __init__(self, what: str, first: float = 2.0, every: float = 10.0):
        self.what, self.every = what, every
        self.t0 = time.monotonic()
        self.due = self.t0 + first

    def __call__(self, done: int, total: int) -> None:
        if STOP.requested:
            raise KeyboardInterrupt
        now = time.monotonic()
        if now >= self.due:
            self.due = now + self.every
            log.info(f"{self.what}: {done:,} of {total:,} steps ({100 * done / total:.0f}%), {now - self.t0:.0f} s")


@contextmanager
def before_the_filters(phase: str, what: str = "simulating"):
    """A phase of a run before its filters (``phase``: "the simulation"): a signal (:data:`STOP`'s
    handler) ends it at once, a stop request at the model's next reported step; either raises
    :class:`RunStopped` ("stopped by SIGTERM during the simulation; nothing was computed"). Long
    loops log their progress (:class:`_SimulationWatch`, prefix ``what``)."""
    try:
        with STOP.interruptible(), _progress.watching(_SimulationWatch(what)):
            STOP.check()
            yield
    except RunStopped:
        raise
    except KeyboardInterrupt:
        raise RunStopped(f"stopped by {STOP.name} during {phase}; nothing was computed") from None


@dataclass
class Outcome:
    """What one filter's execution produced on this process (after gathering: on rank 0, all ranks').
    ``error``: ``"Type: message"`` when the filter failed; ``where``: ``"chunk i of n (trials a..b)"``;
    ``warmup``: seconds of the untimed warm-up call (``None``: none made)."""

    chunks: List[dict] = field(default_factory=list)
    error: Optional[str] = None
    where: Optional[str] = None
    interrupted: bool = False
    warmup: Optional[float] = None


def _timed_call(
    f: Filter,
    name: str,
    plan: RunPlan,
    s: int,
    e: int,
    steps: Optional[int] = None,
    progress=None,
    trials: Optional[Sequence[int]] = None,
):
    """``f`` on trials ``[s, e)`` (or on the run's trials ``trials``, a subset of them; their first
    ``steps`` time steps; ``None``: all) with the run's per-trial streams and the trajectory's mask,
    if any; ``(result, wall seconds)``, synchronised on a GPU. A :class:`NonFiniteError` names the
    trials by their index in the whole run."""
    st, traj = plan.settings, plan.traj
    T = traj.observations.shape[1] if steps is None else min(steps, traj.observations.shape[1])
    which = list(range(s, e)) if trials is None else list(trials)
    rows = slice(s, e) if trials is None else torch.tensor(which, device=traj.observations.device)
    g = TrialStreams(st.seed, which, key=f.stream_name, backend=st.rng_backend)
    mask = {"mask": traj.mask[rows, :T]} if f.padded_measurements else {}  # masked measurement sets
    if traj.states is None and f.output == "states":  # recorded data: each step's spread is reported
        mask["return_std"] = True
    sync = torch.cuda.synchronize if st.device.type == "cuda" else (lambda: None)
    sync()
    t0 = time.perf_counter()
    with torch.no_grad(), STOP.interruptible():
        try:
            res = f(traj.observations[rows, :T], plan.mean0[rows], plan.cov0[rows], g, progress=progress, **mask)
        except NonFiniteError as err:  # report trial indices in the whole run
            raise NonFiniteError(name, err.step, [which[i] for i in err.trials], what=err.what, hint=err.hint) from None
    sync()
    return res, time.perf_counter() - t0


def auto_warmup(f, device) -> bool:
    """``warmup="auto"``: on a GPU always (compiling and loading kernels, graph capture); on the CPU
    when ``f``'s flow takes a Numba kernel or its steps may take the weighting kernel (a first call
    compiles a kernel or loads it from Numba's cache: time that would otherwise land in the first
    timed chunk); the one-shot localisers are not time-stepped filters and are left alone there."""
    kind = torch.device(device).type
    return kind == "cuda" or (
        kind == "cpu"
        and isinstance(f, Filter)
        and select.cpu_kernels_installed()
        and (select.offers_flow_kernel(f) or select.may_weigh_in_kernel(f))
    )


def say_slow_path(filters: Mapping, device) -> Optional[str]:
    """On the CPU without the Numba kernels, say once (a warning in the log) which filters' flows
    will run on the slower torch path, and how to get the fused one; the message, or ``None``."""
    if torch.device(device).type != "cpu" or select.cpu_kernels_installed():
        return None
    slow = [name for name, f in filters.items() if select.offers_flow_kernel(f)]
    if not slow:
        return None
    text = (
        f"the CPU kernels (Numba) are not installed: the flows of {', '.join(slow)} run on the slower torch path; "
        "pip install 'torchflow[kernels]' (or numba) for the fused kernels"
    )
    log.warning(text)
    return text


def _scatter(v: torch.Tensor, kept: torch.Tensor, n: int) -> torch.Tensor:
    """``v (k, ...)`` of the kept rows ``kept (k,)`` placed in ``(n, ...)``: NaN (floats), 0 or
    ``False`` in the rows of the lost trials."""
    fill = float("nan") if v.is_floating_point() else 0
    out = torch.full((n, *v.shape[1:]), fill, dtype=v.dtype)
    out[kept] = v
    return out


def run_chunk(f: Filter, name: str, plan: RunPlan, s: int, e: int, bar=None, lose: bool = True) -> dict:
    """Run filter ``f`` on trials ``[s, e)``: the chunk's :data:`CHUNK_FIELDS` as CPU tensors
    (floats as float64) and ``paths``, the execution paths its steps took
    (:attr:`~torchflow.filters.FilterResult.paths`). Padded measurement sets (a trajectory with a
    ``mask``) pass their mask.

    ``lose``: a :class:`NonFiniteError` marks the trials it names lost (``lost_at``: ``(e - s,)``
    long, the 1-based step at which each went non-finite, 0 for a kept trial) and the chunk is run
    again without them: every trial draws from its own stream, so the kept trials' numbers are those
    of a run without the lost ones. The lost trials' rows of the float fields are NaN. Every trial
    lost: only ``lost_at`` (and ``error``, the last error's text). ``elapsed`` counts every attempt.
    Without ``lose`` the error is raised."""
    n_all, lost_at, elapsed = e - s, torch.zeros(e - s, dtype=torch.long), 0.0
    kept = list(range(s, e))
    while True:
        cb = (lambda n=len(kept): bar.update(n)) if bar is not None else None
        t0 = time.perf_counter()
        try:
            res, t = _timed_call(f, name, plan, s, e, progress=cb, trials=None if len(kept) == n_all else kept)
            elapsed += t
            break
        except NonFiniteError as err:
            elapsed += time.perf_counter() - t0
            gone = sorted(set(err.trials) & set(kept))
            if not lose or not gone:
                raise
            lost_at[torch.tensor(gone) - s] = max(int(err.step), 1)
            gone_set = set(gone)
            kept = [i for i in kept if i not in gone_set]
            log.warning(
                f"{name}: trial(s) {gone[:10]}{' ...' if len(gone) > 10 else ''} lost ({err}); "
                + (f"the chunk's other {len(kept)} trial(s) run again" if kept else "none left in the chunk")
            )
            if not kept:
                return {"start": s, "stop": e, "elapsed": elapsed, "lost_at": lost_at, "error": str(err)}
    out = {"start": s, "stop": e, "elapsed": elapsed}
    if getattr(res, "paths", None) is not None:  # the execution paths taken (torchflow.core.paths)
        out["paths"] = dict(res.paths)
    rows = torch.tensor([i - s for i in kept], dtype=torch.long)
    for key in CHUNK_FIELDS:
        v = getattr(res, key, None)
        if v is not None:
            v = (v.double() if v.is_floating_point() else v).cpu()
            out[key] = v if len(kept) == n_all else _scatter(v, rows, n_all)
    if bool(lost_at.any()):
        out["lost_at"] = lost_at
    return out


def warm_up(f: Filter, name: str, plan: RunPlan, chunks: Sequence[Tuple[int, int]]) -> float:
    """Untimed calls of ``f`` on the first two steps of its trials (their own streams; the results
    are discarded), so that the timed ``chunks`` do not pay the process's one-time costs (kernel
    compilation and loading, library handles, CUDA graph capture); their wall seconds. On a GPU one
    call per distinct chunk size (from the first chunk's first trial: CUDA graphs are captured, and
    kernels may be specialised, per shape); on the CPU one call on one trial (the Numba kernels
    compile once for every shape). A one-shot localiser (not a time-stepped filter: its measurements
    are one set per sensor) is warmed up on its whole data of those trials."""
    if not chunks:
        return 0.0
    s0 = chunks[0][0]
    sizes = sorted({e - s for s, e in chunks}, reverse=True) if plan.settings.device.type == "cuda" else [1]
    steps = 2 if isinstance(f, Filter) else None
    log.info(
        f"{name}: warming up on {'/'.join(map(str, sizes))} trial(s)"
        + (" x 2 steps" if steps else "")
        + " (its kernels are compiled on a machine's first run and loaded from the cache after)"
    )
    total = 0.0
    for n in sizes:
        t0 = time.perf_counter()
        try:
            total += _timed_call(f, name, plan, s0, s0 + n, steps=steps)[1]
        except NonFiniteError:  # its numbers are discarded: the timed call says which trials went non-finite
            total += time.perf_counter() - t0
    return total


def _one_chunk(f, name, plan, s, e, store, bar, before=None, lose: bool = True) -> dict:
    """A chunk from the store (saved with these or, resuming, other boundaries) or computed and saved;
    ``before()`` is called before any trial is computed (the warm-up); ``lose``: :func:`run_chunk`'s."""
    steps, meta = plan.settings.steps, plan.meta(f)

    def compute(a, b):
        if before is not None:
            before()
        return run_chunk(f, name, plan, a, b, bar, lose=lose)

    if store is None:
        return compute(s, e)
    chunk = store.load(name, s, e, steps, meta)
    if chunk is not None:
        if bar is not None:
            bar.update((e - s) * steps)
        return chunk
    # trials saved by a run with other chunk boundaries are reused
    assembled = store.assemble(name, s, e, steps, meta, compute=compute)
    chunk = assembled if assembled is not None else compute(s, e)
    store.save_or_warn(name, s, e, chunk, meta, computed=assembled is None)
    return chunk


def execute(
    f: Filter,
    name: str,
    plan: RunPlan,
    *,
    store: Optional[ChunkStore] = None,
    progress=False,
    desc="",
    warmup: bool = False,
    nonfinite_trials: str = "lose",
) -> Outcome:
    """Run ``f`` over this rank's chunks (a tqdm bar on rank 0 with ``progress``); the ranks' outcome.
    ``warmup``: first untimed calls on two steps (:func:`warm_up`), made before the first chunk
    that is computed (none when the store holds every chunk). ``nonfinite_trials``
    (:data:`NONFINITE_TRIALS`): ``"lose"``: a trial that goes non-finite is lost, the others go on
    (:func:`run_chunk`); ``"fail"``: the filter fails."""
    mine = plan.shard.mine(plan.trial_chunks(plan.chunks[name]))
    bar = (
        tqdm(
            total=sum(e - s for s, e in mine) * plan.settings.steps,
            unit="trial-step",
            leave=False,
            dynamic_ncols=True,
            desc=desc,
        )
        if progress and plan.shard.is_main
        else None
    )
    out, where = Outcome(), None
    pending = [bool(warmup and mine)]

    def before():  # the warm-up, once, before the first trial computed (none when every chunk is saved)
        nonlocal where
        if pending[0]:
            pending[0], chunk_where = False, where
            where = f"the warm-up call (from trial {mine[0][0]})"
            out.warmup = warm_up(f, name, plan, mine)
            where = chunk_where

    try:
        for i, (s, e) in enumerate(mine):
            STOP.check()
            where = f"chunk {i + 1} of {len(mine)} (trials {s}..{e - 1})"
            out.chunks.append(_one_chunk(f, name, plan, s, e, store, bar, before, lose=nonfinite_trials == "lose"))
        STOP.check()
    except KeyboardInterrupt:  # keep what finished; the caller writes it and says so
        out.interrupted = True
    except Exception as err:
        out.error, out.where = f"{type(err).__name__}: {err}", where
        log.error("filter %s failed in %s: %s\n%s", name, out.where, out.error, traceback.format_exc().rstrip())
    finally:
        if bar is not None:
            bar.close()
    return gather_outcome(out, plan)


def gather_outcome(out: Outcome, plan: RunPlan) -> Outcome:
    """Every rank's outcome merged on rank 0 (other ranks: an empty outcome that only says whether
    the run was interrupted); every rank calls it for every filter, failed, interrupted or not."""
    shard = plan.shard
    if shard.world == 1:
        return out
    parts = shard.gather((out.chunks, out.error, out.interrupted, out.where))
    interrupted = bool(shard.broadcast(any(p[2] for p in parts) if shard.is_main else None))
    if not shard.is_main:
        return Outcome(interrupted=interrupted)
    failed = next((p for p in parts if p[1]), (None,) * 4)
    chunks = sorted((c for p in parts for c in p[0]), key=lambda c: c["start"])
    return Outcome(chunks, failed[1], failed[3], interrupted, out.warmup)


def plan_run(
    model: StateSpaceModel,
    filters: Mapping[str, Filter],
    *,
    trials: Optional[int],
    steps: Optional[int],
    seed: int,
    inits_per_track: int = 1,
    chunk_size: Optional[int] = None,
    memory_budget_gb: Optional[float] = None,
    device: Union[str, torch.device] = "cpu",
    dtype: Union[str, torch.dtype] = "float64",
    rng_backend: str = "auto",
    trial_range: Optional[Sequence[int]] = None,
    shard: Optional[Shard] = None,
    simulator: Optional[Callable] = None,
    observations: Optional[torch.Tensor] = None,
    prior=None,
    states: Optional[torch.Tensor] = None,
) -> RunPlan:
    """The arguments checked (:func:`~torchflow.app.runner.plan.check_settings`; a model with
    ``n_steps`` sets the steps), the model (and ``filters``, which may be empty) moved to the
    device and dtype, the chunks chosen, the run's memory checked (a run that cannot fit is refused
    with a :class:`~torchflow.app.runner.plan.ConfigError` before anything is simulated:
    :func:`~torchflow.app.runner.plan.check_memory`) and the data simulated once (``simulator`` or
    :func:`~torchflow.app.runner.plan.simulate`: ``inits_per_track`` trials share a trajectory): the
    data every command works on (:func:`run_experiment`, ``torchflow-learn``). A stop request
    (:data:`STOP`) during the simulation raises :class:`RunStopped` within a time step.

    ``observations``: recorded data instead of a simulation (:func:`~torchflow.app.runner.plan.recorded`:
    ``(T, m)`` filtered by every trial, ``(B, T, m)`` one series per trial; sizes by
    :func:`~torchflow.app.runner.plan.data_sizes`), from ``prior`` or the model's declared prior;
    ``states``: their true states (``(T+1, d)`` or ``(B, T+1, d)``), which make the run scored (and,
    without ``prior``, the prior is the model's ``initial_belief`` at the true initial state).
    ``trials`` / ``steps`` ``None``: 10 (the data's B) and 10 (the data's T)."""
    if observations is not None:
        if simulator is not None:
            raise ConfigError(
                "observations: recorded data replace the simulation; give observations or simulator, not both"
            )
        try:
            observations = check_observations(observations, model)
        except ArgumentError as e:
            raise ConfigError(str(e)) from None
        if inits_per_track != 1:
            raise ConfigError(
                f"inits_per_track: expected 1 with recorded data (every trial filters the recorded "
                f"series), got {inits_per_track!r}"
            )
        trials, steps = data_sizes(observations, trials, steps)
        simulator = recorded(observations, prior, states)
    elif states is not None:
        raise ConfigError("states: true states are given with recorded observations only")
    elif prior is not None:
        raise ConfigError(
            "prior: a prior is given with recorded observations only (a simulation draws each trial's "
            "prior around its true initial state)"
        )
    trials = 10 if trials is None else trials
    steps = 10 if steps is None else steps
    s = check_settings(
        trials=trials,
        steps=getattr(model, "n_steps", steps),
        seed=seed,
        chunk_size=chunk_size,
        inits_per_track=inits_per_track,
        memory_budget_gb=memory_budget_gb,
        device=device,
        dtype=dtype,
        rng_backend=rng_backend,
        trial_range=trial_range,
    )
    with before_the_filters("the simulation"):
        return make_plan(model, filters, s, shard, simulator)


def run_experiment(
    model: StateSpaceModel,
    filters: Mapping[str, Filter],
    *,
    trials: Optional[int] = None,
    steps: Optional[int] = None,
    seed: int = 0,
    inits_per_track: int = 1,
    chunk_size: Optional[int] = None,
    memory_budget_gb: Optional[float] = None,
    device: Union[str, torch.device] = "cpu",
    dtype: Union[str, torch.dtype] = "float64",
    ospa_cutoff: float = 40.0,
    ospa_order: float = 1.0,
    lost_threshold: float = 2.0,
    burn_in: int = 0,
    progress: bool = True,
    rng_backend: str = "auto",
    on_filter_done: Optional[Callable[[List[dict]], None]] = None,
    store: Optional[ChunkStore] = None,
    shard: Optional[Shard] = None,
    trial_range: Optional[Sequence[int]] = None,
    simulator: Optional[Callable] = None,
    warmup: Union[str, bool] = "auto",
    observations: Optional[torch.Tensor] = None,
    prior=None,
    nonfinite_trials: str = "lose",
    lost_rmse: Optional[float] = None,
    states: Optional[torch.Tensor] = None,
) -> Optional[ExperimentResult]:
    """Simulate ``trials`` trajectories of ``steps`` steps once (``model.n_steps``, where the model
    has one, sets it) and run every filter of ``filters`` (``{name: filter holding model}``) on the
    same observations. Each trial of a filter draws from its own stream keyed by (``seed`` in
    ``[0, 2**63)``, trial, the filter's ``stream_name``; ``rng_backend``: ``auto`` = numpy on CPU,
    philox on GPU), so its numbers do not depend on the chunks, the filters' order or ``shard``.

    ``inits_per_track``: trials share a trajectory in groups of this size, each with its own prior
    draw. ``chunk_size``: trials per chunk (``None``: from ``memory_budget_gb`` and the filters'
    memory formulas). ``memory_budget_gb``: the working memory one chunk may use per time step
    (``None``: :data:`~torchflow.app.runner.plan.MEMORY_BUDGET_SHARE` of the memory free on the device
    when the run is planned; ``config["memory_budget"]`` says which). ``ospa_cutoff``, ``ospa_order``,
    ``lost_threshold``: metric settings;
    ``burn_in``: steps dropped from the start of the burn-in metrics' trial and summary values
    (``rmse``; fewer than the steps).
    ``on_filter_done(summary rows)`` runs after each filter. ``store``: a
    :class:`~torchflow.app.runner.checkpoint.ChunkStore`. ``shard``: this process's
    :class:`~torchflow.app.runner.distributed.Shard` (ranks other than 0 return ``None``).
    ``trial_range``: ``(start, stop)``: simulate every trial, run and score only these.
    ``simulator``: replaces :func:`~torchflow.app.runner.plan.simulate`. ``warmup``: before each
    filter's timed chunks, one untimed call on its first trial's first two steps (its numbers
    discarded; every trial's stream is its own, so no result moves), so that ``sec_per_step`` is
    the steady-state compute time and the one-time costs (on a GPU, compiling and loading kernels:
    seconds) are reported apart as ``warmup_sec``; ``"auto"``: on a GPU, and on the CPU for the
    filters that take a Numba kernel (:func:`auto_warmup`). ``trials`` and
    ``steps`` default to 10.

    ``observations``: recorded data, filtered instead of a simulation (no true states): ``(T, m)``
    is one series that each of ``trials`` independent runs filters (its own random stream);
    ``(B, T, m)`` holds one series per trial (``trials``: B or unset); ``steps`` is T (or unset);
    NaN marks a coordinate not observed. The filters start from ``prior = (mean, cov)``
    (``(d,)``/``(B, d)``, ``(d, d)``/``(B, d, d)``) or, without it, from the model's declared prior
    (:func:`torchflow.app.data.declared_prior`). ``states``: the recorded series' true states
    (``(T+1, d)`` or ``(B, T+1, d)``; a ``.npz`` recording's, :func:`torchflow.app.data.load_recording`):
    the run is scored as a simulated one is (without ``prior``: the model's ``initial_belief`` at
    the true initial state, as a simulation draws it). Without states the metrics that need the truth
    (:attr:`~torchflow.core.metrics.Metric.needs_truth`: MSE, RMSE, OMAT, OSPA) are left out (logged once); the
    log-evidence (with its standard error over trials), the ESS and the per-step mean and spread of
    the estimates (``result.estimate_summary``) are reported.

    A trial whose filter goes non-finite (:class:`NonFiniteError` naming it) is *lost* with
    ``nonfinite_trials="lose"`` (the default; ``"fail"``: the filter's row fails): the chunk runs again
    without it (the others' numbers do not move: each trial has its own stream), a warning names it,
    and ``lost_rmse`` (``None``: off) also loses a trial whose RMSE (after ``burn_in``) is above it,
    as DAPPER counts divergence. The summary row's ``lost_trials`` counts them and every metric,
    the log-evidence included, is over the kept trials; the per-trial rows say ``lost_trial`` and
    ``lost_step`` (the step at which it went non-finite; 0: lost by ``lost_rmse`` or kept).

    A filter that raises does not stop the run (its row gets the error, ``result.failures`` where);
    Ctrl-C (:data:`STOP`) keeps the finished filters; before the first filter (the simulation) it
    raises :class:`RunStopped`. A bad argument, or sizes whose memory cannot fit
    (:func:`~torchflow.app.runner.plan.check_memory`), raises
    :class:`~torchflow.app.runner.plan.ConfigError` before anything runs.
    """
    if not isinstance(filters, Mapping) or not all(isinstance(f, Estimator) for f in filters.values()):
        got = (
            type(filters).__name__
            if not isinstance(filters, Mapping)
            else "a mapping with "
            + ", ".join(sorted({type(f).__name__ for f in filters.values() if not isinstance(f, Estimator)}))
        )
        raise ConfigError(
            f"filters: expected a mapping of names to filters (torchflow Estimators: the filters and the "
            f"localisers), e.g. {{'kf': KalmanFilter(model)}}, got {got}"
        )
    check_warmup(warmup)
    if nonfinite_trials not in NONFINITE_TRIALS:
        raise ConfigError(f"nonfinite_trials: expected one of {NONFINITE_TRIALS}, got {nonfinite_trials!r}")
    if lost_rmse is not None and (
        isinstance(lost_rmse, bool) or not isinstance(lost_rmse, (int, float)) or not lost_rmse > 0
    ):
        raise ConfigError(f"lost_rmse: expected a positive RMSE over which a trial is lost, or None; got {lost_rmse!r}")
    n_steps = getattr(model, "n_steps", steps)
    metric_settings = check_metric_settings(
        ospa_cutoff=ospa_cutoff,
        ospa_order=ospa_order,
        lost_threshold=lost_threshold,
        burn_in=burn_in,
        steps=n_steps if isinstance(n_steps, int) and n_steps > 0 else None,
    )
    t0 = time.perf_counter()
    plan = plan_run(
        model,
        filters,
        trials=trials,
        steps=steps,
        seed=seed,
        inits_per_track=inits_per_track,
        chunk_size=chunk_size,
        memory_budget_gb=memory_budget_gb,
        device=device,
        dtype=dtype,
        rng_backend=rng_backend,
        trial_range=trial_range,
        shard=shard,
        simulator=simulator,
        observations=observations,
        prior=prior,
        states=states,
    )
    s = plan.settings
    truthless = plan.traj.states is None
    if truthless and plan.shard.is_main:
        left = [name for name, m in metrics.REGISTRY.items() if m.needs_truth]
        log.info(
            f"recorded data (no true states): {', '.join(left) or 'no metric'} left out; reported: the "
            "log-evidence, the ESS and the estimates' per-step mean and spread"
        )
    if plan.shard.is_main:
        say_slow_path(filters, s.device)
    t1 = time.perf_counter()
    with before_the_filters("the Kalman filter's reference log-evidence"):
        scorer = make_scorer(model, plan, lost_rmse=lost_rmse, **metric_settings)
    res = ExperimentResult([], [], [])
    res.timings = {"plan": t1 - t0, "reference": time.perf_counter() - t1, "filters": 0.0, "scoring": 0.0}
    for i, (name, f) in enumerate(filters.items()):
        t2 = time.perf_counter()
        out = execute(
            f,
            name,
            plan,
            store=store,
            progress=progress,
            desc=f"[{i + 1}/{len(filters)}] {name}",
            warmup=auto_warmup(f, s.device) if warmup == "auto" else warmup,
            nonfinite_trials=nonfinite_trials,
        )
        if out.error is None and not out.interrupted and out.chunks:
            every = fill_lost(out.chunks)  # lost trials: NaN rows; none kept: nothing to score
            if every is not None:
                out.error, out.where = f"NonFiniteError: every trial lost; the last: {every}", "every chunk"
        t3 = time.perf_counter()
        res.timings["filters"] += t3 - t2
        res.interrupted = out.interrupted
        if plan.shard.is_main:
            row = {
                **dict.fromkeys(SUMMARY_COLUMNS),
                "filter": name,
                "n_particles": f.n_particles,
                "trials": s.n_run,
                "steps": s.steps,
            }
            res.summary.append(row)
            if out.interrupted:
                row["error"] = (
                    f"interrupted after {sum(c['stop'] - c['start'] for c in out.chunks)} of {s.n_run} trials"
                )
            elif out.error is not None:
                row["error"], res.failures[name] = out.error, out.where
            else:  # sec_per_step: compute time (a loaded chunk: its original time) per trial-step
                row["sec_per_step"] = sum(float(c["elapsed"]) for c in out.chunks) / (s.n_run * s.steps)
                row["warmup_sec"] = out.warmup
                res.paths[name] = paths.merge(*(c.get("paths") for c in out.chunks))
                row["path"] = paths.describe(res.paths[name])
                trial_rows, step_rows, res.examples[name] = score_filter(scorer, f, name, row, out.chunks, s.steps)
                spread = estimate_spread(out.chunks)
                if spread is not None:
                    res.estimate_summary[name] = spread
                res.per_trial += trial_rows
                res.per_step += step_rows
            if on_filter_done is not None and not out.interrupted:
                on_filter_done(res.summary)
        res.timings["scoring"] += time.perf_counter() - t3
        if out.interrupted:
            break
    if not plan.shard.is_main:  # rank 0 scores and returns the results
        return None
    res.not_run = [n for n in filters if n not in {r["filter"] for r in res.summary}]
    res.config = dict(
        trials=s.trials,
        steps=s.steps,
        seed=s.seed,
        inits_per_track=s.inits_per_track,
        chunk_size=plan.chunks,
        particle_chunk={n: f.particle_chunk for n, f in filters.items()},
        memory_budget_gb=float(f"{s.memory_budget_gb:.4g}"),  # 4 significant digits: a tiny budget is not 0
        memory_budget=s.budget_from,
        rng_backend=s.rng_backend,
        world_size=plan.shard.world,
        trial_range=[s.lo, s.hi],
        device=str(s.device),
        dtype=str(s.dtype).replace("torch.", ""),
        tuning=tuning.as_dict(),
        threads=torch.get_num_threads(),
    )
    res.recorded = truthless
    res.trajectory = Trajectory(
        None if truthless else plan.traj.states[s.lo : s.hi].cpu(), plan.traj.observations[s.lo : s.hi].cpu()
    )
    return res
