"""The ``torchflow`` command: build a model and filters from the Hydra configs, run them, write results.

    torchflow                                                  # default acoustic comparison
    torchflow model=linear_gaussian 'filter=[kf,bpf]' trials=100 steps=10 n_particles=200
    torchflow experiment=pal2019_table1                        # a paper table
    torchflow -m 'filter=[bpf]' n_particles=100,1000           # sweep; one folder per job
    torchflow model=linear_gaussian model.d=4 'filter=[kf,bpf]' data=series.csv   # recorded observations
    torchflow experiment=smooth_linear_gaussian                                # smoothers (task=smooth:
    torchflow.app.tasks)
    torchflow experiment=pmmh_stochastic_volatility                            # a parameter posterior (task=pmmh)

(``python -m torchflow`` and ``python experiments/run.py`` are the same command.) Writes the result
files (:mod:`torchflow.app.runner.writers`), ``run.log`` and figures into Hydra's output folder. It runs
in the command shell (:mod:`torchflow.app.runner.shell`), whose contracts it shares with
``torchflow-learn``: unknown settings refused in one line, the output folder guarded (earlier
results, a live run's lock file), SIGINT / SIGTERM stop at the next chunk with the finished
filters' results written (during the simulation: at once, nothing written). Sizes that cannot fit
in memory are refused before anything is simulated. Exit status: 0 done; 1 a filter failed, or the results could not be
written (any other error keeps its traceback); 2 a configuration error or a refused output folder
(one line); 130 stopped by Ctrl-C (SIGINT); 143 stopped by SIGTERM.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import List, Optional

import hydra
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from torchflow import __version__
from torchflow.app import tasks
from torchflow.app.runner import (
    STOP,
    SUMMARY_COLUMNS,
    ChunkStore,
    RunStopped,
    Shard,
    figures,
    fingerprint,
    format_table,
    run_experiment,
    shell,
    writers,
)
from torchflow.app.runner import (
    config as rc,
)
from torchflow.app.runner.plan import ConfigError
from torchflow.app.runner.shell import JobEnv, config_error, job_threads
from torchflow.filters.gaussian_sum import GaussianSumParticleFilter
from torchflow.flows.ensemble import EnsembleFlow

log = logging.getLogger("torchflow.app.cli")

#: where the summary table's columns are described (printed under the table)
COLUMNS_GUIDE = "docs/guide/command-line.md#the-summary-columns"


_FLOW_NAMES = {
    "EDHFlow": "edh",
    "LEDHFlow": "ledh",
    "GeodesicFlow": "geodesic",
    "GromovFlow": "gromov",
    "OptimalDiffusionFlow": "osd",
}


def flow_label(flow) -> str:
    """Config-style name of a flow: ``ledh``, ``gromov``; ``_global`` for a per-trial linearisation
    of a flow that is per particle by default."""
    name = _FLOW_NAMES.get(type(flow).__name__, type(flow).__name__)
    if name not in ("edh", "ledh") and getattr(flow, "points", "particle") != "particle":
        name += "_global"
    return name


def row_label(key: str, f) -> str:
    """A result row's label: the config key, plus the flow and linearisation points it really ran
    when an override made the key's name wrong (``pfpf_ledh`` run with
    ``flow@filter.pfpf_ledh.flow=edh`` -> ``pfpf_ledh[flow=edh]``; with
    ``filter.pfpf_ledh.points=global`` -> ``pfpf_ledh[points=global]``); Gaussian-sum filters: the
    seed's N* x G label too (``gspf[10x2]``)."""
    flow, gs, words = getattr(f, "flow", None), isinstance(f, GaussianSumParticleFilter), key.split("_")
    if f.output == "sets" or (flow is None and not gs) or isinstance(flow, EnsembleFlow):
        return key  # TDOA localisers, the data-assimilation filters (their flow is theirs): the key names it
    fl = None if flow is None else flow_label(flow)
    named = [n for n in sorted(set(_FLOW_NAMES.values()), key=len, reverse=True) if n in words]
    if gs:  # the "pf" Gaussian-sum filters run LEDH, the others no flow
        expected = "ledh" if key.startswith("pf") else None
    else:  # the flow the key names; a key naming none (pfpf_clustered) runs LEDH by default
        expected = named[0] if named else "ledh"
    tags = [f"{f.particles_per_component}x{f.n_components}"] if gs else []
    tags += [] if fl == expected else [f"flow={fl}"]
    if gs and f.estimate != "mixture_mean":
        tags.append(f"estimate={f.estimate}")
    points = None if gs else getattr(getattr(f, "points", None), "name", None)
    if points is not None and points != ("clustered" if "clustered" in words else flow.points):
        tags.append(f"points={points}")
    return f"{key}[{','.join(tags)}]" if tags else key


def build(cfg: DictConfig):
    """``(model, {label: filter}, {config key: label})`` from the config."""
    if not cfg.get("filter"):
        raise ConfigError(
            "filter: select at least one filter, e.g. filter=[kf,bpf]; available: "
            + ", ".join(rc.group_options("filter") or [])
        )
    model = instantiate(cfg.model)
    filters, labels = {}, {}
    stray = [k for k, v in cfg.filter.items() if not isinstance(v, Mapping)]
    if stray:  # a filter config of one's own without its package line merges into the filter node itself
        raise ConfigError(
            f"filter: expected one config per filter (filter.<name>: {{_target_: ..., ...}}), got the key(s) "
            f"{', '.join(map(str, stray))} directly under filter; a filter config of your own starts with the line "
            "'# @package filter.<name>' (its file name), as torchflow's configs/filter/*.yaml do"
        )
    for key, fcfg in cfg.filter.items():
        if "_target_" not in fcfg:  # e.g. an experiment's per-filter setting for a filter not selected
            log.warning(f"(filter.{key}: settings given but the filter is not selected; skipped)")
            continue
        f = instantiate(fcfg, model=model, name=key)
        f.name = labels[key] = row_label(key, f)
        filters[f.name] = f
    return model, filters, labels


def chunk_store(cfg: DictConfig, labels, data_sha256: Optional[str] = None):
    """The run's :class:`~torchflow.app.runner.ChunkStore` (``None`` with ``checkpoint_dir=null``): one
    folder per filter, named by a fingerprint of everything that changes its numbers (recorded
    data: the file's ``data_sha256`` too)."""
    root, resume = cfg.get("checkpoint_dir"), cfg.get("resume", False)
    if root is None:
        if resume:
            raise ConfigError("resume=true needs checkpoint_dir (where the earlier run saved its chunks); it is null")
        return None
    common = {
        k: OmegaConf.to_container(cfg[k], resolve=True) if OmegaConf.is_config(cfg[k]) else cfg[k]
        for k in ("model", "trials", "steps", "seed", "inits_per_track", "device", "dtype", "rng_backend")
    }
    common["versions"] = {"torchflow": __version__, "torch": torch.__version__}
    if data_sha256 is not None:
        common["data_sha256"] = data_sha256
        prior = cfg.get("prior") or {}
        if any(prior.get(k) is not None for k in ("mean", "cov")):  # the command line's prior changes the numbers
            common["prior"] = OmegaConf.to_container(prior, resolve=True) if OmegaConf.is_config(prior) else prior
    settings = {
        labels[k]: dict(common, filter=OmegaConf.to_container(fcfg, resolve=True), label=labels[k])
        for k, fcfg in cfg.filter.items()
        if k in labels
    }  # not the settings of unselected filters
    keys = {
        label: "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in label) + "-" + fingerprint(s)
        for label, s in settings.items()
    }
    store = ChunkStore(Path(hydra.utils.to_absolute_path(str(root))), keys, resume=resume, settings=settings)
    unsaved = [label for label in keys if not store.saved_ranges(label)] if resume else []
    if unsaved:  # a new checkpoint_dir, or settings other than the saved run's (saved under another key)
        every = len(unsaved) == len(keys)
        why = " (a new folder, or settings other than the saved run's, which save under another key)" if every else ""
        log.warning(
            f"resume=true: nothing is saved under {store.root}{'' if every else ' for ' + ', '.join(unsaved)} "
            f"with these settings{why}: {'every chunk is' if every else 'their chunks are'} computed"
        )
    return store


_Output = shell.Output  # the first failed write turns the exit status to 1


def process_age() -> Optional[float]:
    """Seconds since this process started (Linux ``/proc``, 10 ms resolution), or ``None`` where
    that cannot be read: the start-up a command pays before its job (interpreter, imports, Hydra)."""
    try:
        ticks = os.sysconf("SC_CLK_TCK")
        start = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19]) / ticks
        return float(Path("/proc/uptime").read_text().split()[0]) - start
    except (OSError, ValueError, IndexError, AttributeError):
        return None


def _timings_line(timings, figures_sec: Optional[float]) -> str:
    """The run's wall seconds by phase, for the log (``result.timings`` with the command's own)."""
    names = [
        ("startup", "start-up"),
        ("plan", "data"),
        ("reference", "reference"),
        ("filters", "filters"),
        ("scoring", "scoring"),
        ("writing", "writing"),
    ]
    parts = [f"{label} {timings[k]:.2f}" for k, label in names if timings.get(k) is not None]
    if figures_sec is not None:
        parts.append(f"figures {figures_sec:.2f}")
    total = process_age()
    return "wall seconds: " + ", ".join(parts) + ("" if total is None else f"; {total:.2f} since the process started")


def _run_filters(cfg: DictConfig, model, filters, labels, out: Path, shard) -> int:
    startup = process_age()
    data = rc.recorded_data(cfg, model)
    obs, trials, steps, sha = (
        (data.observations, data.trials, data.steps, data.sha256)
        if data is not None
        else (None, cfg.trials, cfg.steps, None)
    )
    store, writer = chunk_store(cfg, labels, sha), _Output(out)
    trial_range = cfg.get("trial_range")
    result = run_experiment(
        model,
        filters,
        trials=trials,
        steps=steps,
        seed=cfg.seed,
        inits_per_track=cfg.inits_per_track,
        observations=obs,
        states=None if data is None else data.states,
        prior=None if data is None else data.prior,
        chunk_size=cfg.chunk_size,
        memory_budget_gb=cfg.memory_budget_gb,
        device=shard.device(cfg.device),
        dtype=cfg.dtype,
        ospa_cutoff=cfg.metrics.ospa_cutoff,
        ospa_order=cfg.metrics.ospa_order,
        lost_threshold=cfg.metrics.lost_threshold,
        burn_in=cfg.metrics.get("burn_in", 0),
        progress=cfg.progress,
        rng_backend=cfg.rng_backend,
        on_filter_done=lambda rows: writer.attempt(  # the finished filters' rows, under a partial name
            writers.PARTIAL_SUMMARY, writers.write_csv, out / writers.PARTIAL_SUMMARY, rows, SUMMARY_COLUMNS
        ),
        store=store,
        shard=shard,
        warmup=cfg.get("warmup", "auto"),
        trial_range=OmegaConf.to_container(trial_range) if OmegaConf.is_config(trial_range) else trial_range,
        nonfinite_trials=cfg.get("nonfinite_trials", "lose"),
        lost_rmse=cfg.metrics.get("lost_rmse"),
    )
    if result is None:  # a rank other than 0 of a torchrun run: rank 0 writes the files
        return 0
    model_name = cfg.model._target_.split(".")[-1]
    if store is not None and (store.loaded or store.reused_trials):
        log.info(
            f"resumed: {sum(store.loaded.values())} saved chunks read from {store.root} "
            f"({sum(store.reused_trials.values())} trials reused from chunks with other boundaries), "
            f"{sum(store.computed.values())} chunks computed"
        )
    lo, hi = result.config["trial_range"]
    which = f"{trials} trials" if (lo, hi) == (0, trials) else f"trials {lo}..{hi - 1} of {trials}"
    source = f" of data={cfg.data}" if data is not None else ""
    budget = result.config["memory_budget"]
    budget = "" if budget == "given" else f", memory budget {result.config['memory_budget_gb']:.3g} GiB ({budget})"
    log.info(
        f"\n{model_name}: {which} x {result.config['steps']} steps{source}, seed {cfg.seed}, "
        f"{cfg.device}/{cfg.dtype}{budget}"
    )
    log.info(format_table(result.summary))
    log.info(f"(the columns: {COLUMNS_GUIDE})")
    for name in result.failed:
        where = f" in {result.failures[name]}" if result.failures.get(name) else ""
        error = next(r["error"] for r in result.summary if r["filter"] == name)
        log.error(f"!! {name} failed{where}: {error} (traceback in run.log)")
    result.timings = {"startup": startup, **result.timings}
    t0 = time.perf_counter()
    writer.attempt("the result files", writers.write_run, out, result, OmegaConf.to_container(cfg, resolve=True))
    result.timings["writing"] = time.perf_counter() - t0
    t0, figures_sec = time.perf_counter(), None
    if cfg.plots:
        writer.attempt("the figures", figures.save_run_figures, out, model, result, model_name)
        figures_sec = time.perf_counter() - t0
    log.info(_timings_line(result.timings, figures_sec))
    if writer.failed is None:
        log.info(f"results: {shell.shown_path(out)}")
    if result.interrupted:
        skipped = f"; not run: {', '.join(result.not_run)}" if result.not_run else ""
        log.warning(f"interrupted by {STOP.name}: the results of the filters that finished are written{skipped}")
        if store is not None and not shell.multirun():  # a sweep's end says it once for every job
            log.warning(f"the finished chunks are saved under {store.root}; go on with\n  {rc.resume_command()}")
        return STOP.exit_code
    return 1 if (result.failed or writer.failed) else 0


def _run(cfg: DictConfig, out: Path, env: JobEnv) -> int:
    """The run command's job (in the shell's job environment): build, run, write; the exit status.
    ``task=smooth`` / ``task=pmmh``: :mod:`torchflow.app.tasks`."""
    task = tasks.check_task(cfg)
    if task != "filter":
        model, filters, labels = build(cfg)
        return tasks.task_job(task, cfg, model, filters, labels, out, env)
    shard = Shard.from_env(str(cfg.device), timeout_minutes=float(cfg.get("dist_timeout_min", 720)))
    try:
        model, filters, labels = build(cfg)
        return _run_filters(cfg, model, filters, labels, out, shard)
    except RunStopped as stopped:  # during the simulation: nothing was computed, nothing is written
        log.warning(str(stopped))
        return STOP.exit_code
    finally:
        shard.close()


#: the ``torchflow`` command of the shell
RUN = shell.Command(prog="torchflow", config_name="config", job=_run, distributed=True, resumable=True)
hydra_main = shell.hydra_entry(RUN)


def run_job(cfg: DictConfig) -> int:
    """One job of the run command inside Hydra (check the config, build, run, write); the exit status."""
    return shell.run_job(RUN, cfg)


def main(argv: Optional[List[str]] = None, prog: Optional[str] = None) -> None:
    """The ``torchflow`` command (``argv``: the overrides; default ``sys.argv[1:]``; ``prog``: its name in
    messages, default: as invoked, ``torchflow`` or ``python <script>``)."""
    shell.main(RUN, argv, prog, entry=hydra_main)


__all__ = ["main", "run_job", "config_error", "job_threads", "build", "row_label", "RUN"]
