"""Batched Monte Carlo runner: simulate once, run every filter on the same data, score it.

``run_experiment`` is plain Python (no Hydra): ``experiments/run.py`` builds its arguments from
``configs/`` and writes the result files.
"""
from __future__ import annotations

import math
import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Union

import torch

from . import metrics, tuning
from ._checks import NonFiniteError, check_count
from .filters.base import Filter
from .filters.kalman import KalmanFilter
from .models.base import StateSpaceModel, Trajectory
from .checkpoint import ChunkStore
from .distributed import Shard
from .random import TrialStreams

SUMMARY_COLUMNS = [
    "filter", "n_particles", "trials", "steps", "mse", "omat", "omat_kept_mean", "omat_kept_sd",
    "ospa", "ess", "g_eff", "log_evidence", "log_evidence_relmse", "lost_tracks", "repaired", "sec_per_step", "error",
]
_DTYPES = {"float64": torch.float64, "float32": torch.float32, "double": torch.float64, "float": torch.float32}


@dataclass
class ExperimentResult:
    """Tidy results.

    Attributes:
        summary: one dict per filter with :data:`SUMMARY_COLUMNS` (``None`` where undefined).
        per_trial: one dict per filter x trial (mse, omat, ospa, ess, log_evidence, lost).
        per_step: one dict per filter x step with metric means over trials.
        trajectory: the simulated data (CPU tensors).
        config: the run's settings (chunk sizes, particle chunks, seed, device, ...).
        examples: ``{filter: (T, d)}`` estimates of trial 0 (for the track picture).
        interrupted: the run was stopped (Ctrl-C); the rows hold what finished, the interrupted
            filter's row says so in ``error``.
        not_run: filters that did not start because of the interruption.
    """

    summary: List[dict]
    per_trial: List[dict]
    per_step: List[dict]
    trajectory: Optional[Trajectory] = None
    config: dict = field(default_factory=dict)
    examples: Dict[str, torch.Tensor] = field(default_factory=dict)
    interrupted: bool = False
    not_run: List[str] = field(default_factory=list)


def resolve_dtype(dtype: Union[str, torch.dtype]) -> torch.dtype:
    if isinstance(dtype, torch.dtype):
        return dtype
    if dtype not in _DTYPES:
        raise ValueError(f"dtype: expected one of {sorted(_DTYPES)}, got {dtype!r}")
    return _DTYPES[dtype]


def resolve_device(device: Union[str, torch.device]) -> torch.device:
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        dev = None
    if dev is None or dev.type not in ("cpu", "cuda"):
        raise ValueError(f"device: expected 'cpu', 'cuda' or 'cuda:<index>', got {device!r}")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("device: 'cuda' requested but torch.cuda.is_available() is False "
                         "(a CPU-only torch build, or no GPU visible)")
    return dev


def choose_chunk_size(filters: Mapping[str, Filter], trials: int, memory_budget_gb: float) -> int:
    """Largest chunk of trials whose estimated per-step memory fits the budget (at least 1)."""
    per_trial = max((f.bytes_per_trial() for f in filters.values()), default=1)
    return max(1, min(trials, int(memory_budget_gb * 2**30 // max(per_trial, 1))))


def _simulate(model: StateSpaceModel, trials: int, steps: int, inits_per_track: int, generator):
    if inits_per_track < 1:
        raise ValueError(f"inits_per_track: expected >= 1, got {inits_per_track}")
    n_tracks = math.ceil(trials / inits_per_track)
    traj = model.simulate(n_tracks, steps, generator)
    if inits_per_track > 1:
        rep = lambda t: t.repeat_interleave(inits_per_track, 0)[:trials]  # noqa: E731
        traj = Trajectory(rep(traj.states), rep(traj.observations))
    mean, cov = model.initial_belief(traj.states[:, 0], generator)
    return traj, mean, cov


class StopRequest:
    """Ctrl-C / SIGTERM handling that never tears a run apart mid-bookkeeping.

    :meth:`handler` (installed for SIGINT and SIGTERM by ``experiments/run.py``; install it in
    your own script with ``signal.signal(signal.SIGTERM, STOP.handler)``) records the request.
    Inside a filter's chunk it raises ``KeyboardInterrupt`` at once; anywhere else (gathering
    ranks, scoring, writing files) the run stops at the next chunk boundary, so the finished
    chunks are always scored and written. Without the handler, Python's own Ctrl-C still
    interrupts a chunk as before.
    """

    def __init__(self):
        self.requested = False
        self._depth = 0

    def handler(self, signum, frame):  # noqa: ARG002 - signal handler signature
        self.requested = True
        if self._depth:
            raise KeyboardInterrupt

    def check(self) -> None:
        if self.requested:
            raise KeyboardInterrupt

    def reset(self) -> None:
        self.requested = False

    @contextmanager
    def interruptible(self):
        self._depth += 1
        try:
            yield
        finally:
            self._depth -= 1


#: the process's stop request (see :class:`StopRequest`)
STOP = StopRequest()


def _run_chunk(f: Filter, name: str, traj, mean0, cov0, s: int, e: int, seed: int, rng_backend: str, dev,
               bar, steps: int) -> dict:
    """Run filter ``f`` on trials ``[s, e)``: the chunk's results as CPU float64 tensors."""
    g = TrialStreams(seed, range(s, e), key=f.stream_name, backend=rng_backend)
    cb = (lambda n=e - s: bar.update(n)) if bar is not None else None
    if dev.type == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    with torch.no_grad(), STOP.interruptible():
        try:
            res = f(traj.observations[s:e], mean0[s:e], cov0[s:e], g, progress=cb)
        except NonFiniteError as err:  # report trial indices in the whole run
            raise NonFiniteError(name, err.step, [s + i for i in err.trials]) from None
    if dev.type == "cuda":
        torch.cuda.synchronize()
    out = {"start": s, "stop": e, "elapsed": time.perf_counter() - t0,
           "estimates": res.estimates.double().cpu(), "log_evidence": res.log_evidence.double().cpu()}
    if res.ess is not None:
        out["ess"] = res.ess.double().cpu()
    if res.n_repaired is not None:
        out["n_repaired"] = res.n_repaired.cpu()
    if res.g_eff is not None:
        out["g_eff"] = res.g_eff.double().cpu()
    return out


def _check_trial_range(trial_range, trials: int):
    if trial_range is None:
        return 0, trials
    try:
        lo, hi = (int(v) for v in trial_range)
        ok = all(float(v) == int(v) for v in trial_range) and 0 <= lo < hi <= trials
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"trial_range: expected [start, stop] with 0 <= start < stop <= trials = {trials}, "
                         f"got {trial_range!r}")
    return lo, hi


def run_experiment(
    model: StateSpaceModel,
    filters: Mapping[str, Filter],
    *,
    trials: int = 10,
    steps: int = 10,
    seed: int = 0,
    inits_per_track: int = 1,
    chunk_size: Optional[int] = None,
    memory_budget_gb: float = 4.0,
    device: Union[str, torch.device] = "cpu",
    dtype: Union[str, torch.dtype] = "float64",
    ospa_cutoff: float = 40.0,
    ospa_order: float = 1.0,
    lost_threshold: float = 2.0,
    progress: bool = True,
    rng_backend: str = "auto",
    on_filter_done: Optional[Callable[[List[dict]], None]] = None,
    store: Optional[ChunkStore] = None,
    shard: Optional[Shard] = None,
    trial_range: Optional[Sequence[int]] = None,
) -> Optional[ExperimentResult]:
    """Simulate ``trials`` trajectories once and run every filter on the same observations.

    Args:
        model: the state-space model (moved to ``device``/``dtype``).
        filters: ``{name: filter}``; each filter must hold ``model``.
        trials: Monte Carlo trials B.
        steps: time steps T.
        seed: seeds the simulation and every filter's randomness. Each trial of a filter draws
            from its own stream, :class:`~torchflow.random.TrialStreams` keyed by (seed, trial
            index, the filter's :attr:`~torchflow.filters.base.Filter.stream_name`), so a trial's
            numbers do not depend on ``chunk_size``, ``memory_budget_gb``, the order of the
            filters or their config names (same device and ``rng_backend``).
        inits_per_track: trials share a trajectory in groups of this size, each with its own
            prior draw (Li & Coates: 100 trajectories x 5 initialisations).
        chunk_size: trials per chunk for every filter; ``None`` picks each filter's from
            ``memory_budget_gb`` and :meth:`Filter.preferred_chunk_trials`.
        memory_budget_gb: memory one chunk may use (by the filters' own estimates). When even one
            trial exceeds it, a particle filter without an explicit ``particle_chunk`` gets one
            (:meth:`~torchflow.filters.base.ParticleFilterBase.plan_memory`), so e.g. a 1e6-particle
            bootstrap PF runs in blocks of particles; ``result.config["particle_chunk"]`` records it.
        device, dtype: where and in what precision filters run (metrics use float64).
        ospa_cutoff, ospa_order, lost_threshold: metric settings (tracking models).
        progress: show a tqdm progress bar per filter (its time estimate is that filter's own).
        rng_backend: back end of the per-trial streams, ``auto`` (numpy on CPU, philox on GPU),
            ``numpy`` or ``philox`` (see :mod:`torchflow.random`).
        on_filter_done: called with the summary rows so far after each filter finishes (or
            fails), so a caller can save partial results of long runs.
        store: a :class:`~torchflow.checkpoint.ChunkStore`: every finished chunk is saved to a
            small file at once, and with ``store.resume`` chunks saved by an earlier run of the
            same settings are loaded instead of computed (a killed run goes on where it stopped).
        shard: this process's :class:`~torchflow.distributed.Shard` in a ``torchrun`` run: it
            computes chunks ``rank, rank + world, ...`` of every filter and rank 0 gathers and
            scores them. Without ``chunk_size`` chunks are capped at ``ceil(trials / world)``
            trials so every rank has work. Returns ``None`` on ranks other than 0.
        trial_range: ``(start, stop)``: simulate all ``trials`` but run and score only trials
            ``start .. stop - 1`` (their data and random draws are those of the whole run, so a
            row of a long table can be rerun alone). Rows keep the global trial index; the
            summary's ``trials`` is ``stop - start``.

    ``sec_per_step`` is the filter's compute time (summed over chunks and ranks; a chunk loaded
    on resume counts the time it took when it was computed) divided by trials x steps.

    A filter that raises (including a non-finite estimate) does not stop the run: its row gets
    the error message and the other filters still run.
    """
    trials = check_count("trials", trials)
    steps = check_count("steps", steps)
    inits_per_track = check_count("inits_per_track", inits_per_track)
    seed = check_count("seed", seed, minimum=0)
    if chunk_size is not None:
        chunk_size = check_count("chunk_size", chunk_size, hint=" (or None: from memory_budget_gb)")
    if isinstance(memory_budget_gb, bool) or not isinstance(memory_budget_gb, (int, float)) \
            or not math.isfinite(memory_budget_gb) or memory_budget_gb <= 0:
        raise ValueError(f"memory_budget_gb: expected a positive number of GiB, got {memory_budget_gb!r}")
    lo, hi = _check_trial_range(trial_range, trials)
    n_run = hi - lo
    dev, dt = resolve_device(device), resolve_dtype(dtype)
    model.to(device=dev, dtype=dt)
    for name, f in filters.items():
        if f.model is not model:
            raise ValueError(f"filters[{name!r}]: holds a different model instance than `model`")
        f.to(device=dev, dtype=dt)
    gen = torch.Generator(device=dev).manual_seed(int(seed))
    traj, mean0, cov0 = _simulate(model, trials, steps, inits_per_track, gen)
    def filter_chunk(f: Filter) -> int:
        """A filter's chunk of trials: ``chunk_size`` if given, else the most its memory estimate
        allows, capped by the filter's preferred batch (local flows slow down past ~1e4 points)."""
        if chunk_size:
            return int(chunk_size)
        c = choose_chunk_size({"f": f}, n_run, memory_budget_gb)
        if c == 1 and getattr(f, "particle_chunk", 0) is None:  # one trial may still exceed it: chunk particles
            pc = f.plan_memory(memory_budget_gb * 2**30)
            if pc is not None:
                warnings.warn(f"memory_budget_gb={memory_budget_gb:g}: {f.name} runs one trial at a time in blocks "
                              f"of {pc} of its {f.n_particles} particles (estimated {f.bytes_per_trial() / 2**30:.3g} "
                              "GiB per trial); raise the budget if this machine has more memory", stacklevel=4)
        pref = f.preferred_chunk_trials()
        return min(c, pref) if pref else c

    shard = shard or Shard()
    chunks = {name: filter_chunk(f) for name, f in filters.items()}
    if shard.world > 1 and not chunk_size:  # every rank gets a share
        chunks = {name: min(c, -(-n_run // shard.world)) for name, c in chunks.items()}
    truth = traj.states[lo:hi, 1:].double().cpu()  # chunks come back as CPU float64 (from any rank)
    tracking = model.has_positions
    true_pos = model.positions(truth) if tracking else None

    reference_logz = None
    if shard.is_main and model.linear_dynamics and model.linear_measurement:  # the Kalman filter is exact: the reference
        with torch.no_grad():
            kf = KalmanFilter(model, validate=False)
            c = filter_chunk(kf)
            reference_logz = torch.cat([kf(traj.observations[s:min(s + c, hi)], mean0[s:min(s + c, hi)],
                                           cov0[s:min(s + c, hi)]).log_evidence
                                        for s in range(lo, hi, c)]).double().cpu()

    try:
        from tqdm.auto import tqdm
    except ImportError:  # pragma: no cover
        tqdm = None

    summary, per_trial, per_step, examples = [], [], [], {}
    interrupted = False
    for i_f, (name, f) in enumerate(filters.items()):
        n_part = getattr(f, "n_particles", None)
        row = {c: None for c in SUMMARY_COLUMNS}
        row.update(filter=name, n_particles=n_part, trials=n_run, steps=steps)
        f_chunk = chunks[name]
        plan = [(s, min(s + f_chunk, hi)) for s in range(lo, hi, f_chunk)]
        mine = shard.mine(plan)
        # one bar per filter: its time estimate is that filter's own, not an average over filters
        # of very different cost
        bar = None
        if progress and tqdm is not None and shard.is_main:
            bar = tqdm(total=sum(e - s for s, e in mine) * steps, unit="trial-step", leave=False,
                       dynamic_ncols=True, desc=f"[{i_f + 1}/{len(filters)}] {name}")
        done, error = [], None
        meta = dict(seed=seed, trials=trials, steps=steps, inits_per_track=inits_per_track, stream=f.stream_name,
                    rng_backend=rng_backend, dtype=str(dt), device=dev.type)
        try:
            for s, e in mine:
                STOP.check()
                chunk = None if store is None else store.load(name, s, e, steps, meta)
                if chunk is None:
                    chunk = _run_chunk(f, name, traj, mean0, cov0, s, e, seed, rng_backend, dev, bar, steps)
                    if store is not None:
                        store.save(name, s, e, chunk, meta)
                elif bar is not None:
                    bar.update((e - s) * steps)
                done.append(chunk)
            STOP.check()
        except KeyboardInterrupt:  # keep what finished; the caller writes it and says so
            interrupted = True
        except Exception as e:  # one failing filter must not lose the others' results
            error = f"{type(e).__name__}: {e}"
        if bar is not None:
            bar.close()
        if shard.world > 1:  # every rank reaches this for every filter, failed, interrupted or not
            parts = shard.gather((done, error, interrupted))
            interrupted = bool(shard.broadcast(any(p[2] for p in parts) if shard.is_main else None))
            if not shard.is_main:
                if interrupted:
                    break
                continue
            errors = [err for _, err, _ in parts if err]
            error = errors[0] if errors else None
            done = sorted((c for cs, _, _ in parts for c in cs), key=lambda c: c["start"])
        if interrupted:
            error = f"interrupted after {sum(c['estimates'].shape[0] for c in done)} of {n_run} trials"
        if error is not None:
            row["error"] = error
            summary.append(row)
            if interrupted:
                break
            if on_filter_done is not None:
                on_filter_done(summary)
            continue
        est = torch.cat([c["estimates"] for c in done])
        examples[name] = est[0]
        logz = torch.cat([c["log_evidence"] for c in done])
        ess_bt = torch.cat([c["ess"] for c in done]) if "ess" in done[0] else None
        mse_bt = metrics.mse(est, truth)
        cols = {"mse": mse_bt}
        if tracking:
            est_pos = model.positions(est)
            cols["omat"] = metrics.omat(est_pos, true_pos)
            cols["ospa"] = metrics.ospa(est_pos, true_pos, cutoff=ospa_cutoff, order=ospa_order)
        if ess_bt is not None:
            cols["ess"] = ess_bt
        if "g_eff" in done[0]:
            cols["g_eff"] = torch.cat([c["g_eff"] for c in done])
        row["sec_per_step"] = sum(float(c["elapsed"]) for c in done) / (n_run * steps)
        if f.estimates_evidence:
            row["log_evidence"] = float(logz.mean())
        if "n_repaired" in done[0]:
            row["repaired"] = int(torch.cat([c["n_repaired"] for c in done]).sum())
        for k, v in cols.items():
            row[k] = float(v.mean())
        lost = None
        if tracking:
            lost = metrics.lost_tracks(cols["omat"], threshold=lost_threshold)
            row["lost_tracks"] = int(lost.sum())
            kept = cols["omat"].mean(1)[~lost]
            row["omat_kept_mean"] = float(kept.mean()) if kept.numel() else None
            row["omat_kept_sd"] = float(kept.std()) if kept.numel() > 1 else None
        if reference_logz is not None and f.estimates_evidence:
            row["log_evidence_relmse"] = float(metrics.log_evidence_relative_error(logz, reference_logz).mean())
        summary.append(row)
        for b in range(n_run):
            r = {"filter": name, "trial": lo + b, "log_evidence": float(logz[b])}
            r.update({k: float(v[b].mean()) for k, v in cols.items()})
            if lost is not None:
                r["lost"] = bool(lost[b])
            per_trial.append(r)
        means = {k: v.mean(0) for k, v in cols.items()}
        for t in range(steps):
            r = {"filter": name, "step": t + 1}
            r.update({k: float(v[t]) for k, v in means.items()})
            per_step.append(r)
        if on_filter_done is not None:
            on_filter_done(summary)
    if not shard.is_main:
        return None
    not_run = [n for n in filters if n not in {r["filter"] for r in summary}]
    particle_chunks = {name: getattr(f, "particle_chunk", None) for name, f in filters.items()}
    config = dict(trials=trials, steps=steps, seed=seed, inits_per_track=inits_per_track, chunk_size=chunks,
                  particle_chunk=particle_chunks, memory_budget_gb=memory_budget_gb, rng_backend=rng_backend,
                  world_size=shard.world, trial_range=[lo, hi],
                  device=str(dev), dtype=str(dt).replace("torch.", ""), tuning=tuning.as_dict())
    cpu_traj = Trajectory(traj.states[lo:hi].cpu(), traj.observations[lo:hi].cpu())
    return ExperimentResult(summary, per_trial, per_step, cpu_traj, config, examples=examples,
                            interrupted=interrupted, not_run=not_run)


def format_table(summary: List[dict], columns: Optional[List[str]] = None) -> str:
    """Markdown table of the summary rows, dropping columns that are empty in every row."""
    columns = columns or SUMMARY_COLUMNS
    cols = [c for c in columns if any(r.get(c) is not None for r in summary)]

    def fmt(v):
        if v is None:
            return ""
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(fmt(r.get(c)) for c in cols) + " |" for r in summary]
    return "\n".join(lines)
