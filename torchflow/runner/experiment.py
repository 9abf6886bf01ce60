"""``run_experiment``: plan -> execute -> score, for every filter on the same simulated data."""
from __future__ import annotations

from typing import Callable, List, Mapping, Optional, Sequence, Union

import torch

from .. import tuning
from ..filters.base import Filter
from ..models.base import StateSpaceModel, Trajectory
from .checkpoint import ChunkStore
from .distributed import Shard
from .execute import STOP, execute
from .plan import check_metric_settings, check_settings, make_plan
from .score import SUMMARY_COLUMNS, ExperimentResult, make_scorer, score_filter


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
    simulator: Optional[Callable] = None,
) -> Optional[ExperimentResult]:
    """Simulate ``trials`` trajectories once and run every filter on the same observations.

    Args:
        model: the state-space model (moved to ``device``/``dtype``).
        filters: ``{name: filter}``; each filter must hold ``model``.
        trials: Monte Carlo trials B.
        steps: time steps T.
        seed: in ``[0, 2**63)``; seeds the simulation and every filter's randomness. Each trial of
            a filter draws from its own stream, :class:`~torchflow.random.TrialStreams` keyed by
            (seed, trial index, the filter's :attr:`~torchflow.filters.base.Filter.stream_name`),
            so a trial's numbers do not depend on ``chunk_size``, ``memory_budget_gb``, the order
            of the filters or their config names (same device and ``rng_backend``).
        inits_per_track: trials share a trajectory in groups of this size, each with its own
            prior draw (Li & Coates: 100 trajectories x 5 initialisations).
        chunk_size: trials per chunk for every filter; ``None`` picks each filter's from
            ``memory_budget_gb`` and :meth:`Filter.preferred_chunk_trials`.
        memory_budget_gb: memory one chunk may use (by the filters' own estimates). When even one
            trial exceeds it, a particle filter without an explicit ``particle_chunk`` gets one
            (:meth:`~torchflow.filters.base.ParticleFilterBase.plan_memory`), so e.g. a 1e6-particle
            bootstrap PF runs in blocks of particles; ``result.config["particle_chunk"]`` records it.
        device, dtype: where and in what precision filters run (metrics use float64).
        ospa_cutoff, ospa_order, lost_threshold: metric settings (tracking models; positive).
        progress: show a tqdm progress bar per filter (its time estimate is that filter's own).
        rng_backend: back end of the per-trial streams, ``auto`` (numpy on CPU, philox on GPU),
            ``numpy`` or ``philox`` (see :mod:`torchflow.random`).
        on_filter_done: called with the summary rows so far after each filter finishes (or
            fails), so a caller can save partial results of long runs.
        store: a :class:`~torchflow.runner.checkpoint.ChunkStore`: every finished chunk is saved
            at once, and with ``store.resume`` saved trials are loaded instead of computed. A
            store that cannot write warns once; the results do not depend on it.
        shard: this process's :class:`~torchflow.runner.distributed.Shard` in a ``torchrun`` run:
            it computes chunks ``rank, rank + world, ...`` of every filter and rank 0 gathers and
            scores them. Without ``chunk_size`` chunks are capped at ``ceil(trials / world)``
            trials so every rank has work. Returns ``None`` on ranks other than 0.
        trial_range: ``(start, stop)``: simulate all ``trials`` but run and score only trials
            ``start .. stop - 1`` (their data and random draws are those of the whole run, so a
            row of a long table can be rerun alone). Rows keep the global trial index; the
            summary's ``trials`` is ``stop - start``.
        simulator: replaces :func:`~torchflow.runner.plan.simulate` (same signature).

    ``sec_per_step`` is the filter's compute time (summed over chunks and ranks; a chunk loaded
    on resume counts the time it took when it was computed) divided by trials x steps.

    A filter that raises (including a non-finite estimate) does not stop the run: its row gets
    the error message, ``result.failures`` says where, and the other filters still run. A bad
    argument raises :class:`~torchflow.runner.errors.ConfigError` (a ``ValueError``) before
    anything runs.
    """
    s = check_settings(trials=trials, steps=getattr(model, "n_steps", steps), seed=seed, inits_per_track=inits_per_track, chunk_size=chunk_size,
                       memory_budget_gb=memory_budget_gb, device=device, dtype=dtype, rng_backend=rng_backend,
                       trial_range=trial_range)
    metric_settings = check_metric_settings(ospa_cutoff=ospa_cutoff, ospa_order=ospa_order,
                                            lost_threshold=lost_threshold)
    plan = make_plan(model, filters, s, shard, simulator)
    scorer = make_scorer(model, plan, **metric_settings)
    result = _run_filters(filters, plan, scorer, store=store, progress=progress, on_filter_done=on_filter_done)
    if result is None:  # a rank other than 0: rank 0 scores and returns the results
        return None
    result.config = dict(
        trials=s.trials, steps=s.steps, seed=s.seed, inits_per_track=s.inits_per_track, chunk_size=plan.chunks,
        particle_chunk={n: getattr(f, "particle_chunk", None) for n, f in filters.items()},
        memory_budget_gb=memory_budget_gb, rng_backend=s.rng_backend, world_size=plan.shard.world,
        trial_range=[s.lo, s.hi], device=str(s.device), dtype=str(s.dtype).replace("torch.", ""),
        tuning=tuning.as_dict())
    result.trajectory = Trajectory(plan.traj.states[s.lo:s.hi].cpu(), plan.traj.observations[s.lo:s.hi].cpu())
    return result


def _run_filters(filters: Mapping[str, Filter], plan, scorer, *, store, progress, on_filter_done
                 ) -> Optional[ExperimentResult]:
    """Execute and score every filter in turn (rank 0 gathers; other ranks return ``None``)."""
    s = plan.settings
    res = ExperimentResult([], [], [])
    for i_f, (name, f) in enumerate(filters.items()):
        out = execute(f, name, plan, store=store, progress=progress, desc=f"[{i_f + 1}/{len(filters)}] {name}")
        res.interrupted = out.interrupted
        if not plan.shard.is_main:
            if out.interrupted:
                break
            continue
        row = {c: None for c in SUMMARY_COLUMNS}
        row.update(filter=name, n_particles=getattr(f, "n_particles", None), trials=s.n_run, steps=s.steps)
        res.summary.append(row)
        if out.interrupted:
            row["error"] = f"interrupted after {sum(c['estimates'].shape[0] for c in out.chunks)} of {s.n_run} trials"
            break
        if out.error is not None:
            row["error"], res.failures[name] = out.error, out.where
        else:
            trial_rows, step_rows, res.examples[name] = score_filter(scorer, f, name, row, out.chunks, s.steps)
            res.per_trial += trial_rows
            res.per_step += step_rows
        if on_filter_done is not None:
            on_filter_done(res.summary)
    if not plan.shard.is_main:
        return None
    res.not_run = [n for n in filters if n not in {r["filter"] for r in res.summary}]
    return res

__all__ = ["run_experiment", "STOP"]
