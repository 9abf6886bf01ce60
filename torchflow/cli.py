"""The command line: build a model and filters from the Hydra configs, run them, write results.

    torchflow                                                  # default acoustic comparison
    torchflow model=linear_gaussian 'filter=[kf,bpf]' trials=100 steps=10 n_particles=200
    torchflow experiment=seed000_table1                        # a paper table
    torchflow -m 'filter=[bpf]' n_particles=100,1000           # sweep; one folder per job

(``python -m torchflow`` and ``python experiments/run.py`` are the same command.) Writes the result
files (:mod:`torchflow.runner.writers`), ``run.log`` and figures into Hydra's output folder. Exit
status: 0 done; 1 a filter failed, or the results could not be written; 2 a configuration error
(one line); 130 interrupted (Ctrl-C, SIGTERM). Any other error keeps its traceback.
"""
from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import tempfile
import traceback
from pathlib import Path
from typing import List, Optional

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.errors import InstantiationException
from hydra.types import RunMode
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from . import __version__, tuning
from .registry import register_configs
from .runner import (
    STOP, SUMMARY_COLUMNS, ChunkStore, Shard, config as rc, figures, fingerprint, format_table, run_experiment, writers,
)
from .runner.plan import ConfigError

log = logging.getLogger("torchflow.cli")


def config_error(e: BaseException) -> Optional[str]:
    """The one-line message of a bad setting: ours, OmegaConf's, or a ``ValueError`` / ``TypeError`` of
    a constructor Hydra calls (named by its key); ``None`` for anything else (a failure)."""
    if not isinstance(e, InstantiationException):
        return str(e) if isinstance(e, (ConfigError, OmegaConfBaseException)) else None
    cause = e.__cause__ or e.__context__
    if not isinstance(cause, (ValueError, TypeError)):
        return None
    key = [ln.split(":", 1)[1].strip() + ": " for ln in str(e).splitlines() if ln.startswith("full_key:")]
    return (key[-1] if key else "") + str(cause).strip("'\"")


def _multirun() -> bool:
    return HydraConfig.get().mode == RunMode.MULTIRUN


_FLOW_NAMES = {"EDHFlow": "edh", "LEDHFlow": "ledh", "GeodesicFlow": "geodesic", "GromovFlow": "gromov",
               "OptimalDiffusionFlow": "osd"}


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
    flow, gs, words = getattr(f, "flow", None), hasattr(f, "n_components"), key.split("_")
    if hasattr(f, "method") or (flow is None and not gs):  # TDOA localisers: the key names the method
        return key
    fl = None if flow is None else flow_label(flow)
    named = [n for n in sorted(set(_FLOW_NAMES.values()), key=len, reverse=True) if n in words]
    if gs:  # the "pf" Gaussian-sum filters run LEDH, the others no flow
        expected = "ledh" if key.startswith("pf") else None
    else:  # the flow the key names; a key naming none (pfpf_clustered) runs LEDH by default
        expected = named[0] if named else "ledh"
    tags = [f"{f.particles_per_component}x{f.n_components}"] if gs else []
    tags += [] if fl == expected else [f"flow={fl}"]
    if gs and getattr(f, "estimate", "mixture_mean") != "mixture_mean":
        tags.append(f"estimate={f.estimate}")
    points = None if gs else getattr(getattr(f, "points", None), "name", None)
    if points is not None and points != ("clustered" if "clustered" in words else flow.points):
        tags.append(f"points={points}")
    return f"{key}[{','.join(tags)}]" if tags else key


def build(cfg: DictConfig):
    """``(model, {label: filter}, {config key: label})`` from the config."""
    if not cfg.get("filter"):
        raise ConfigError("filter: select at least one filter, e.g. filter=[kf,bpf]; available: "
                          + ", ".join(rc.group_options("filter") or []))
    model = instantiate(cfg.model)
    filters, labels = {}, {}
    for key, fcfg in cfg.filter.items():
        if "_target_" not in fcfg:  # e.g. an experiment's per-filter setting for a filter not selected
            log.warning(f"(filter.{key}: settings given but the filter is not selected; skipped)")
            continue
        f = instantiate(fcfg, model=model, name=key)
        f.name = labels[key] = row_label(key, f)
        filters[f.name] = f
    return model, filters, labels


def chunk_store(cfg: DictConfig, labels):
    """The run's :class:`~torchflow.runner.ChunkStore` (``None`` with ``checkpoint_dir=null``): one
    folder per filter, named by a fingerprint of everything that changes its numbers."""
    root, resume = cfg.get("checkpoint_dir"), cfg.get("resume", False)
    if root is None:
        if resume:
            raise ConfigError("resume=true needs checkpoint_dir (where the earlier run saved its chunks); it is null")
        return None
    common = {k: OmegaConf.to_container(cfg[k], resolve=True) if OmegaConf.is_config(cfg[k]) else cfg[k]
              for k in ("model", "trials", "steps", "seed", "inits_per_track", "device", "dtype", "rng_backend")}
    common["versions"] = {"torchflow": __version__, "torch": torch.__version__}
    settings = {labels[k]: dict(common, filter=OmegaConf.to_container(fcfg, resolve=True), label=labels[k])
                for k, fcfg in cfg.filter.items() if k in labels}  # not the settings of unselected filters
    keys = {label: "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in label) + "-" + fingerprint(s)
            for label, s in settings.items()}
    return ChunkStore(Path(hydra.utils.to_absolute_path(str(root))), keys, resume=resume, settings=settings)


class _Output:
    """Writes into the run's folder: the first failed write (read-only folder, full disk) is reported
    in one line and turns the exit status to 1; nothing more is written, the run goes on."""

    def __init__(self, out: Path):
        self.out, self.failed = out, None

    def attempt(self, what: str, write, *args) -> None:
        try:
            if self.failed is None:
                write(*args)
        except OSError as e:
            self.failed = f"cannot write {what} into {self.out} ({type(e).__name__}: {e.strerror or e})"
            log.error(f"error: {self.failed}")


def _run_filters(cfg: DictConfig, model, filters, labels, out: Path, shard) -> int:
    store, writer = chunk_store(cfg, labels), _Output(out)
    trial_range = cfg.get("trial_range")
    result = run_experiment(
        model, filters, trials=cfg.trials, steps=cfg.steps, seed=cfg.seed, inits_per_track=cfg.inits_per_track,
        chunk_size=cfg.chunk_size, memory_budget_gb=cfg.memory_budget_gb, device=shard.device(cfg.device),
        dtype=cfg.dtype, ospa_cutoff=cfg.metrics.ospa_cutoff, ospa_order=cfg.metrics.ospa_order,
        lost_threshold=cfg.metrics.lost_threshold, progress=cfg.progress, rng_backend=cfg.rng_backend,
        on_filter_done=lambda rows: writer.attempt("summary.csv", writers.write_csv, out / "summary.csv", rows,
                                                   SUMMARY_COLUMNS),  # partial results
        store=store, shard=shard, warmup=cfg.get("warmup", "auto"),
        trial_range=OmegaConf.to_container(trial_range) if OmegaConf.is_config(trial_range) else trial_range)
    if result is None:  # a rank other than 0 of a torchrun run: rank 0 writes the files
        return 0
    model_name = cfg.model._target_.split(".")[-1]
    if store is not None and (store.loaded or store.reused_trials):
        log.info(f"resumed: {sum(store.loaded.values())} chunks loaded from {store.root} "
                 f"({sum(store.reused_trials.values())} trials of chunks with other boundaries), "
                 f"{sum(store.computed.values())} computed")
    lo, hi = result.config["trial_range"]
    which = f"{cfg.trials} trials" if (lo, hi) == (0, cfg.trials) else f"trials {lo}..{hi - 1} of {cfg.trials}"
    log.info(f"\n{model_name}: {which} x {result.config['steps']} steps, seed {cfg.seed}, {cfg.device}/{cfg.dtype}")
    log.info(format_table(result.summary))
    for name in result.failed:
        where = f" in {result.failures[name]}" if result.failures.get(name) else ""
        error = next(r["error"] for r in result.summary if r["filter"] == name)
        log.error(f"!! {name} failed{where}: {error} (traceback in run.log)")
    writer.attempt("the result files", writers.write_run, out, result, OmegaConf.to_container(cfg, resolve=True))
    if cfg.plots:
        writer.attempt("the figures", figures.save_run_figures, out, model, result, model_name)
    if writer.failed is None:
        log.info(f"results: {os.path.relpath(out)}")
    if result.interrupted:
        skipped = f"; not run: {', '.join(result.not_run)}" if result.not_run else ""
        log.warning(f"interrupted (Ctrl-C or SIGTERM): the results of the filters that finished are written{skipped}")
        if store is not None:
            log.warning(f"the finished chunks are saved under {store.root}; go on with\n  {rc.resume_command()}")
        return 130
    return 1 if (result.failed or writer.failed) else 0


def job_threads(threads=None) -> Optional[int]:
    """Torch threads of one job (numpy's random fills use as many): ``threads`` when given (a
    positive int); else, when ``OMP_NUM_THREADS`` is set, ``None`` (torch already follows it); else
    the cores this process may use divided among the jobs a Hydra launcher runs at once (the joblib
    launcher's ``n_jobs``; 1 for the sequential one), at least 1. Side by side with default threads,
    two torch processes each take every core and slow each other down many times over."""
    if threads is not None:
        if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
            raise ConfigError(f"threads: expected a positive number of threads or null, got {threads!r}")
        return threads
    if os.environ.get("OMP_NUM_THREADS"):
        return None
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    jobs = 1
    if HydraConfig.initialized() and _multirun():
        n_jobs = OmegaConf.select(HydraConfig.get(), "launcher.n_jobs", default=None)
        if isinstance(n_jobs, int) and n_jobs != 1:
            jobs = cores if n_jobs < 1 else n_jobs  # joblib: -1 means one job per core
    return max(1, cores // jobs)


@contextlib.contextmanager
def _torch_threads(n: Optional[int]):
    """``torch.set_num_threads(n)`` for the job (``None``: unchanged), restored after it."""
    before = torch.get_num_threads()
    if n is not None and n != before:
        torch.set_num_threads(n)
        log.debug(f"torch threads: {n}")
    try:
        yield
    finally:
        if torch.get_num_threads() != before:
            torch.set_num_threads(before)


def run_job(cfg: DictConfig) -> int:
    """One job: check the config, build, run, write; the exit status."""
    rc.check_config(cfg, HydraConfig.get().runtime.choices)
    out = Path(HydraConfig.get().runtime.output_dir)
    knobs = {k: v for k, v in (OmegaConf.to_container(cfg.get("tuning") or {}) or {}).items() if v is not None}
    with contextlib.ExitStack() as stack:
        try:
            stack.enter_context(tuning.tuned(**knobs))
        except (ValueError, TypeError) as e:
            raise ConfigError(str(e)) from None
        stack.enter_context(_torch_threads(job_threads(cfg.get("threads"))))
        shard = Shard.from_env(str(cfg.device), timeout_minutes=float(cfg.get("dist_timeout_min", 720)))
        stack.callback(shard.close)
        if shard.is_main:
            out.mkdir(parents=True, exist_ok=True)
            writers.clear_results(out)  # a reused folder (overwrite=true / resume=true) keeps no old file
        model, filters, labels = build(cfg)
        return _run_filters(cfg, model, filters, labels, out, shard)


def _job(cfg: DictConfig) -> int:
    """:func:`run_job` with its errors turned into messages and exit statuses."""
    try:
        return run_job(cfg)
    except KeyboardInterrupt:
        log.warning("interrupted outside a filter run: only summary.csv (rows of the filters that "
                    "finished, if any) was written")
        return 130
    except Exception as e:  # noqa: BLE001 - configuration errors: one line; anything else: its traceback
        bad = config_error(e)
        if bad is not None:
            message, code = f"error: {bad}", 2
            log.error(message + (" (job failed; the sweep goes on)" if _multirun() else ""))
        else:
            message, code = traceback.format_exc(), 1
            log.error(f"error: {type(e).__name__}: {e}\n{message.rstrip()}")
        if _multirun():  # the job's error.txt (collect and the end-of-sweep report name it); the sweep goes on
            out = Path(HydraConfig.get().runtime.output_dir)
            with contextlib.suppress(OSError):
                out.mkdir(parents=True, exist_ok=True)
                writers.write_text(out / "error.txt", message.rstrip() + "\n")
        return code


register_configs()  # the signature nodes the component configs extend (at import: sweep workers compose too)


@hydra.main(config_path=rc.config_source(), config_name="config", version_base="1.3")
def hydra_main(cfg: DictConfig) -> None:
    """Run one job; a sweep (``-m``) goes on after a failing job, Ctrl-C ends it (and says how to resume)."""
    STOP.reset()
    try:  # Ctrl-C and SIGTERM (kill, a scheduler's time limit) stop at once inside a chunk, else at the next one
        signal.signal(signal.SIGINT, STOP.handler)
        signal.signal(signal.SIGTERM, STOP.handler)
    except ValueError:  # not the main thread (some launchers): Python's own Ctrl-C handling only
        pass
    logging.captureWarnings(True)
    try:
        code = _job(cfg)
    finally:
        logging.captureWarnings(False)
    if _multirun() and code != 130:
        return  # the sweep goes on; the job's folder (error.txt, results.json) says what happened
    if code:
        sys.exit(code)


# cached: a launcher that resolves the sweep folder again in each worker (joblib, submitit) gets
# the main process's value, so every job lands in the one announced folder
OmegaConf.register_new_resolver("tf_pid", lambda: str(os.getpid()), replace=True, use_cache=True)


def main(argv: Optional[List[str]] = None, prog: str = "torchflow") -> None:
    """The ``torchflow`` command (``argv``: the overrides; default ``sys.argv[1:]``)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    help_only = any(a in ("-h", "--help", "--hydra-help", "--info", "-c", "--cfg", "--version") for a in argv)
    rank = os.environ.get("RANK", "0")
    try:
        rc.check_selections(argv)
        if int(rank) == 0 and not help_only:
            rc.check_output_folder(argv, Path.cwd())
        rc.remember_command(prog, argv)
        if int(rank) and any(a in ("-m", "--multirun") for a in argv):
            raise ConfigError("torchrun runs one job; run a sweep (-m) on a Hydra launcher instead")
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    if int(rank):  # ranks other than 0 of a torchrun run write no Hydra folder or log (rank 0 does)
        argv += [f"hydra.run.dir={tempfile.gettempdir()}/torchflow-rank{rank}-{os.getppid()}",
                 "hydra.output_subdir=null", "hydra/job_logging=disabled", "hydra/hydra_logging=disabled"]
    sys.argv = [sys.argv[0], *argv]
    hydra_main()


__all__ = ["main", "run_job", "config_error"]
