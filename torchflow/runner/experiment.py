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
    model: StateSpaceModel, filters: Mapping[str, Filter], *, trials: int = 10, steps: int = 10, seed: int = 0,
    inits_per_track: int = 1, chunk_size: Optional[int] = None, memory_budget_gb: float = 4.0,
    device: Union[str, torch.device] = "cpu", dtype: Union[str, torch.dtype] = "float64", ospa_cutoff: float = 40.0,
    ospa_order: float = 1.0, lost_threshold: float = 2.0, progress: bool = True, rng_backend: str = "auto",
    on_filter_done: Optional[Callable[[List[dict]], None]] = None, store: Optional[ChunkStore] = None,
    shard: Optional[Shard] = None, trial_range: Optional[Sequence[int]] = None, simulator: Optional[Callable] = None,
) -> Optional[ExperimentResult]:
    """Simulate ``trials`` trajectories of ``steps`` steps once (a model with a fixed number of
    steps, such as :class:`~torchflow.models.TDOA3D`'s sensors, sets it: ``model.n_steps``) and run
    every filter of ``filters`` (``{name: filter holding model}``) on the same observations.

    Each trial of a filter draws from its own stream, :class:`~torchflow.random.TrialStreams` keyed
    by (``seed`` in ``[0, 2**63)``, trial, the filter's ``stream_name``), so its numbers do not
    depend on ``chunk_size``, ``memory_budget_gb``, the order or names of the filters, or ``shard``
    (same device and ``rng_backend``: ``auto`` = numpy on CPU, philox on GPU). ``inits_per_track``:
    trials share a trajectory in groups of this size, each with its own prior draw. ``chunk_size``:
    trials per chunk (``None``: from ``memory_budget_gb`` and the filters' memory formulas; a
    particle filter whose one trial exceeds it runs in blocks of particles). ``ospa_cutoff``,
    ``ospa_order``, ``lost_threshold``: metric settings. ``on_filter_done(summary rows)`` runs after
    each filter. ``store``: a :class:`~torchflow.runner.checkpoint.ChunkStore` saving every
    finished chunk (and, resuming, loading saved trials). ``shard``: this process's
    :class:`~torchflow.runner.distributed.Shard` under ``torchrun`` (ranks other than 0 return
    ``None``). ``trial_range``: ``(start, stop)``: simulate every trial, run and score only these.
    ``simulator``: replaces :func:`~torchflow.runner.plan.simulate`.

    A filter that raises does not stop the run: its row gets the error and ``result.failures``
    where; Ctrl-C (:data:`STOP`) keeps the finished filters. ``sec_per_step`` is compute time
    (a loaded chunk counts its original time) per trial-step. A bad argument raises
    :class:`~torchflow.runner.errors.ConfigError` before anything runs.
    """
    s = check_settings(trials=trials, steps=getattr(model, "n_steps", steps), seed=seed, chunk_size=chunk_size,
                       inits_per_track=inits_per_track, memory_budget_gb=memory_budget_gb, device=device, dtype=dtype,
                       rng_backend=rng_backend, trial_range=trial_range)
    metric_settings = check_metric_settings(ospa_cutoff=ospa_cutoff, ospa_order=ospa_order,
                                            lost_threshold=lost_threshold)
    plan = make_plan(model, filters, s, shard, simulator)
    scorer = make_scorer(model, plan, **metric_settings)
    res = ExperimentResult([], [], [])
    for i, (name, f) in enumerate(filters.items()):
        out = execute(f, name, plan, store=store, progress=progress, desc=f"[{i + 1}/{len(filters)}] {name}")
        res.interrupted = out.interrupted
        if plan.shard.is_main:
            row = {c: None for c in SUMMARY_COLUMNS}
            row.update(filter=name, n_particles=getattr(f, "n_particles", None), trials=s.n_run, steps=s.steps)
            res.summary.append(row)
            if out.interrupted:
                row["error"] = f"interrupted after {sum(c['stop'] - c['start'] for c in out.chunks)} of {s.n_run} trials"
            elif out.error is not None:
                row["error"], res.failures[name] = out.error, out.where
            else:
                trial_rows, step_rows, res.examples[name] = score_filter(scorer, f, name, row, out.chunks, s.steps)
                res.per_trial += trial_rows
                res.per_step += step_rows
            if on_filter_done is not None and not out.interrupted:
                on_filter_done(res.summary)
        if out.interrupted:
            break
    if not plan.shard.is_main:  # rank 0 scores and returns the results
        return None
    res.not_run = [n for n in filters if n not in {r["filter"] for r in res.summary}]
    res.config = dict(
        trials=s.trials, steps=s.steps, seed=s.seed, inits_per_track=s.inits_per_track, chunk_size=plan.chunks,
        particle_chunk={n: getattr(f, "particle_chunk", None) for n, f in filters.items()},
        memory_budget_gb=memory_budget_gb, rng_backend=s.rng_backend, world_size=plan.shard.world,
        trial_range=[s.lo, s.hi], device=str(s.device), dtype=str(s.dtype).replace("torch.", ""),
        tuning=tuning.as_dict())
    res.trajectory = Trajectory(plan.traj.states[s.lo:s.hi].cpu(), plan.traj.observations[s.lo:s.hi].cpu())
    return res


__all__ = ["run_experiment", "STOP"]
