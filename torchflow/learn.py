"""Maximum-likelihood calibration of a model's parameters through a filter: the ``torchflow-learn`` command.

    torchflow-learn                                                # acoustic: Psi and sigma_w, PF-PF(LEDH)
    torchflow-learn 'filter=[pfpf_ledh,bpf]' epochs=60
    torchflow-learn model=linear_gaussian model.d=4 learn=true 'start={alpha: 0.5}' 'filter=[bpf]'

(``python experiments/learn.py`` is the same command.) Simulates ``trials`` tracks of ``steps``
steps from the model config (the truth) through the runner's simulation, the one the
``torchflow`` command uses (:func:`~torchflow.runner.plan_run`: ``seed``, ``inits_per_track``,
``device``, ``dtype`` mean the same), builds a second model with ``learnable=<learn>`` and the
constructor overrides ``start`` (the wrong starting values), and fits it with each selected filter
(particle filters with ``resampling_gradient`` and ``proposal_gradient``) through
:class:`~torchflow.lightning.FilterLightningModule` (Adam, loss = negative log-evidence per step).
The ``reference`` filter (EKF, or the Kalman filter on a linear model) is fitted the same way: its
estimate is the Kalman/EKF maximum-likelihood value the table compares against. Writes
``learn.csv`` / ``learn.json`` (per filter and parameter: start, final, truth, errors, seconds per
epoch; the per-epoch history) and ``curves.png`` (loss and parameters per epoch) into Hydra's
output folder.

It runs in the command shell (:mod:`torchflow.runner.shell`), whose contracts it shares with
``torchflow``: an unknown setting (``+learning_rate=0.5``) is refused in one line with the
closest known keys; the output folder is guarded (earlier results unless ``overwrite=true``, a
live run's lock file); ``device``, ``dtype``, ``threads`` and ``tuning.*`` are set up the same
way; SIGINT / SIGTERM stop after the current optimiser step, and the finished epochs are written
(``learn.json`` says ``"interrupted": true``; a filter not started is listed under ``not_run``).
Exit status: 0 done; 1 a failure (the results could not be written; any other error keeps its
traceback); 2 a configuration error or a refused output folder (one line); 130 stopped by Ctrl-C
(SIGINT); 143 stopped by SIGTERM.
"""
from __future__ import annotations

import json
import logging
import math
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import hydra
from omegaconf import DictConfig, OmegaConf

from .registry import signature_defaults
from .runner import STOP, format_table, plan_run, shell, writers
from .runner.plan import ConfigError
from .runner.shell import JobEnv

log = logging.getLogger("torchflow.learn")

COLUMNS = ["filter", "parameter", "start", "final", "truth", "error_vs_truth_pct", "reference",
           "error_vs_reference_pct", "epochs", "sec_per_epoch", "final_nll_per_step"]


def _value(model, name: str) -> List[float]:
    return [float(v) for v in getattr(model, name).detach().reshape(-1)]


def _rel_error(a: List[float], b: List[float]) -> float:
    """``|a - b| / |b|`` (Euclidean norms), in per cent."""
    num = math.sqrt(sum((x - y) ** 2 for x, y in zip(a, b)))
    den = math.sqrt(sum(y * y for y in b))
    return 100.0 * num / den if den > 0 else float("nan")


def _learner(cfg: DictConfig, env: Optional[JobEnv] = None):
    """The model to fit: the model config with ``learnable=<learn>`` and the ``start`` overrides, on
    the job's device and dtype."""
    learn = OmegaConf.to_container(cfg.learn, resolve=True) if OmegaConf.is_config(cfg.learn) else cfg.learn
    start = OmegaConf.to_container(cfg.start, resolve=True) if cfg.get("start") else {}
    model = hydra.utils.instantiate(cfg.model, learnable=learn, **start)
    return model if env is None else model.to(device=env.device, dtype=env.dtype)


def _stop_callback():
    """A Lightning callback that ends the fit after the optimiser step during which a stop request
    (:data:`~torchflow.runner.STOP`: SIGINT, SIGTERM) came; where the shell's handlers are in force
    it puts them back over the SIGTERM handler Lightning installs at the start of a fit (which
    would end the fit with ``SystemExit``)."""
    import pytorch_lightning as pl

    class StopAtStep(pl.Callback):
        def __init__(self):
            self.ours = signal.getsignal(signal.SIGTERM) == STOP.handler

        def on_train_start(self, trainer, pl_module):
            if self.ours:
                shell.install_stop_handlers()

        def on_train_batch_end(self, trainer, *args, **kwargs):
            if STOP.requested:
                trainer.should_stop = True

        def on_train_epoch_end(self, trainer, pl_module):
            if STOP.requested:
                trainer.should_stop = True

    return StopAtStep()


def _fit(cfg: DictConfig, key: str, fcfg, data, names: List[str], out: Path, env: JobEnv) -> Dict:
    """Fit one filter's copy of the model: the per-epoch history (an epoch a stop request cut short
    counts its optimiser steps in ``steps``), whether it stopped early, the checkpointing used."""
    import pytorch_lightning as pl
    from pytorch_lightning.utilities.exceptions import SIGTERMException
    from torch.utils.data import DataLoader

    from .lightning import FilterLightningModule

    model = _learner(cfg, env)
    target = hydra.utils.get_class(fcfg._target_) if "_target_" in fcfg else None
    kw = {"model": model, "name": key}
    accepted = signature_defaults(target) if target is not None else {}  # the keyword arguments it takes
    for key_ in ("resampling_gradient", "proposal_gradient"):
        if key_ in accepted:
            kw[key_] = cfg[key_]
    filt = hydra.utils.instantiate(fcfg, **kw).to(device=env.device, dtype=env.dtype)
    try:  # its options' errors (lr_decay, betas, checkpoint_steps, ...) are settings: one line
        module = FilterLightningModule(filt, lr=cfg.lr, seed=cfg.seed, checkpoint_steps=cfg.checkpoint_steps,
                                       memory_budget_gb=cfg.memory_budget_gb, lr_decay=cfg.lr_decay,
                                       common_random_numbers=cfg.common_random_numbers,
                                       betas=OmegaConf.to_container(cfg.betas) if OmegaConf.is_config(cfg.betas)
                                       else cfg.betas)
    except ValueError as e:
        raise ConfigError(str(e)) from e
    history = {"epoch": [], "steps": [], "nll_per_step": [], "seconds": [], **{n: [] for n in names}}

    class Record(pl.Callback):
        def on_train_epoch_start(self, trainer, pl_module):
            self.t0, self.steps = time.perf_counter(), 0

        def on_train_batch_end(self, trainer, *args, **kwargs):
            self.steps += 1

        def on_train_epoch_end(self, trainer, pl_module):
            history["epoch"].append(trainer.current_epoch + 1)
            history["steps"].append(self.steps)
            history["nll_per_step"].append(float(trainer.callback_metrics["train_nll_per_step"]))
            history["seconds"].append(time.perf_counter() - self.t0)
            for n in names:
                history[n].append(_value(model, n))
            log.info(f"{key} epoch {trainer.current_epoch + 1}: nll/step {history['nll_per_step'][-1]:.4f}, "
                     + ", ".join(f"{n} {_fmt(history[n][-1])}" for n in names))

    cpu = env.device is None or env.device.type == "cpu"
    trainer = pl.Trainer(max_epochs=cfg.epochs, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, default_root_dir=str(out), callbacks=[Record(), _stop_callback()],
                         accelerator="cpu" if cpu else "gpu", devices=1 if cpu else [env.device.index or 0])
    batch = cfg.batch_size or len(data)
    try:
        trainer.fit(module, DataLoader(data, batch_size=batch, shuffle=False))
    except SIGTERMException:  # Lightning's own SIGTERM handling (where ours was not in force): a stop request
        if not STOP.requested:
            STOP.handler(signal.SIGTERM, None)
    stopped = STOP.requested and len(history["epoch"]) < cfg.epochs
    return {"history": history, "checkpoint_steps": bool(module.checkpoint_steps is True), "stopped": stopped}


def _fmt(v: List[float]) -> str:
    return f"{v[0]:.4g}" if len(v) == 1 else "[" + ", ".join(f"{x:.3g}" for x in v) + "]"


def _rows(fits: Dict, truth: Dict, start: Dict, names: List[str], reference: str) -> List[Dict]:
    rows = []
    for key, fit in fits.items():
        h = fit["history"]
        for n in names:
            final = h[n][-1]
            ref = fits[reference]["history"][n][-1] if reference in fits and key != reference else None
            rows.append({"filter": key, "parameter": n, "start": _fmt(start[n]), "final": _fmt(final),
                         "truth": _fmt(truth[n]), "error_vs_truth_pct": round(_rel_error(final, truth[n]), 3),
                         "reference": "" if ref is None else _fmt(ref),
                         "error_vs_reference_pct": "" if ref is None else round(_rel_error(final, ref), 3),
                         "epochs": len(h["epoch"]),
                         "sec_per_epoch": round(sum(h["seconds"]) / max(1, len(h["seconds"])), 3),
                         "final_nll_per_step": round(h["nll_per_step"][-1], 5)})
    return rows


def _plot(fits: Dict, truth: Dict, names: List[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 1 + len(names), figsize=(4.2 * (1 + len(names)), 3.4))
    for key, fit in fits.items():
        h = fit["history"]
        axes[0].plot(h["epoch"], h["nll_per_step"], label=key)
        for ax, n in zip(axes[1:], names):
            ax.plot(h["epoch"], [v[0] if len(v) == 1 else _rel_error(v, truth[n]) for v in h[n]], label=key)
    axes[0].set(xlabel="epoch", ylabel="negative log-evidence per step")
    for ax, n in zip(axes[1:], names):
        scalar = len(truth[n]) == 1
        if scalar:
            ax.axhline(truth[n][0], color="k", ls="--", lw=1, label="truth")
        ax.set(xlabel="epoch", ylabel=n if scalar else f"{n}: % error vs truth")
    axes[-1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


@dataclass
class LearnOutcome:
    """What :func:`learn` did: the table ``rows``, the ``fits`` (per filter: history, ...), whether a
    stop request ended it early (``interrupted``), the filters it did not start (``not_run``), and
    why the results could not be written (``write_failed``; ``None``: written)."""

    rows: List[Dict]
    fits: Dict[str, Dict] = field(default_factory=dict)
    interrupted: bool = False
    not_run: List[str] = field(default_factory=list)
    write_failed: Optional[str] = None


def learn(cfg: DictConfig, out: Path, env: JobEnv) -> LearnOutcome:
    """Simulate (through :func:`~torchflow.runner.plan_run`), fit every selected filter (and the
    reference) until done or a stop request, and write the results of the epochs that finished."""
    from .lightning import TrajectoryDataset

    if not cfg.get("filter"):
        raise ConfigError("filter: select at least one filter, e.g. 'filter=[pfpf_ledh,bpf]'")
    for k in ("epochs", "trials", "steps"):
        if not isinstance(cfg[k], int) or isinstance(cfg[k], bool) or cfg[k] < 1:
            raise ConfigError(f"{k}: expected a positive integer, got {cfg[k]!r}")
    if not (isinstance(cfg.lr, (int, float)) and cfg.lr > 0):
        raise ConfigError(f"lr: expected a positive learning rate, got {cfg.lr!r}")
    truth = hydra.utils.instantiate(cfg.model)
    plan = plan_run(truth, {}, trials=cfg.trials, steps=cfg.steps, seed=cfg.seed,
                    inits_per_track=cfg.get("inits_per_track", 1), memory_budget_gb=cfg.memory_budget_gb,
                    device=env.device or "cpu", dtype=env.dtype or "float64")
    data = TrajectoryDataset(plan.traj, plan.mean0, plan.cov0)
    probe = _learner(cfg, env)
    names = sorted(n.split(".")[1] if n.startswith("parametrizations.") else n
                   for n, p in probe.named_parameters() if p.requires_grad)
    if not names:
        raise ConfigError(f"learn: the model has no learnable parameters with learn={cfg.learn!r}")
    start = {n: _value(probe, n) for n in names}
    true_values = {n: _value(truth, n) for n in names}
    given = OmegaConf.to_container(cfg.start, resolve=True) if cfg.get("start") else {}
    fixed = {k: v for k, v in given.items() if k not in names}
    # start is a mapping: an override such as start={psi: 5} merges into the default (its sigma_w stays)
    log.info(f"model to fit: learned {', '.join(f'{n} from {_fmt(start[n])}' for n in names)}"
             + (f"; held at start values: {fixed}" if fixed else ""))
    reference = cfg.get("reference")
    fcfgs = {k: v for k, v in cfg.filter.items() if "_target_" in v}
    if reference and reference not in fcfgs:
        fcfgs[reference] = OmegaConf.create({"_target_": _reference_class(reference)})
    res = LearnOutcome([])
    for key, fcfg in fcfgs.items():
        if STOP.requested:
            res.interrupted = True
            res.not_run.append(key)
            continue
        log.info(f"fitting {', '.join(names)} with {key} ({cfg.epochs} epochs, {cfg.trials} trials x {cfg.steps} steps)")
        fit = _fit(cfg, key, fcfg, data, names, out, env)
        res.interrupted |= fit["stopped"]
        if fit["history"]["epoch"]:
            res.fits[key] = fit
        else:  # stopped before its first step ended
            res.not_run.append(key)
    res.rows = _rows(res.fits, true_values, start, names, reference or "")
    writer = shell.Output(out)
    writer.attempt("learn.csv", writers.write_csv, out / "learn.csv", res.rows, COLUMNS)
    writer.attempt("learn.json", writers.write_text, out / "learn.json", json.dumps({
        "config": OmegaConf.to_container(cfg, resolve=True), "rows": res.rows,
        "history": {k: f["history"] for k, f in res.fits.items()},
        "checkpoint_steps": {k: f["checkpoint_steps"] for k, f in res.fits.items()},
        "interrupted": res.interrupted, "stopped_by": STOP.name if res.interrupted else None,
        "not_run": res.not_run,
        "run": {"trials": cfg.trials, "steps": plan.settings.steps, "seed": plan.settings.seed,
                "inits_per_track": plan.settings.inits_per_track, "device": str(plan.settings.device),
                "dtype": str(plan.settings.dtype).replace("torch.", ""), "threads": env.threads,
                "tuning": env.tuning}}, indent=1))
    if cfg.plots and res.fits:
        writer.attempt("curves.png", _plot, res.fits, true_values, names, out / "curves.png")
    res.write_failed = writer.failed
    return res


def run(cfg: DictConfig, out: Path) -> List[Dict]:
    """Simulate, fit every selected filter (and the reference), write the results; the table rows
    (:func:`learn` in the job environment of ``cfg``: device, dtype, threads, tuning)."""
    with shell.job_environment(cfg) as env:
        return learn(cfg, out, env).rows


def _reference_class(name: str) -> str:
    """The class path of the reference filter ``ekf`` | ``kf`` | ``ukf``."""
    from .registry import REGISTRY

    if name not in ("ekf", "kf", "ukf"):
        raise ConfigError(f"reference: expected one of ekf, kf, ukf or null, got {name!r}")
    return REGISTRY["filter"][name]


def _job(cfg: DictConfig, out: Path, env: JobEnv) -> int:
    """The learn command's job (in the shell's job environment); the exit status."""
    for name in ("pytorch_lightning", "lightning.pytorch", "lightning_fabric"):  # its banners, not our log
        logging.getLogger(name).setLevel(logging.WARNING)
    res = learn(cfg, out, env)
    if res.rows:
        log.info("\n" + format_table(res.rows, COLUMNS))
    if res.write_failed is None:
        log.info(f"results: {out}")
    if res.interrupted:
        done = ", ".join(f"{k}: {len(f['history']['epoch'])} of {cfg.epochs} epochs" for k, f in res.fits.items())
        skipped = f"; not run: {', '.join(res.not_run)}" if res.not_run else ""
        log.warning(f"interrupted by {STOP.name}: learn.csv and learn.json hold the epochs that finished "
                    f"({done or 'none'}){skipped}")
        return STOP.exit_code
    return shell.EXIT_FAILED if res.write_failed else shell.EXIT_OK


#: the ``torchflow-learn`` command of the shell (``start`` holds constructor overrides: free-form)
LEARN = shell.Command(prog="torchflow-learn", config_name="learn", job=_job,
                      free_form=("model", "filter", "hydra", "start"))
hydra_main = shell.hydra_entry(LEARN)


def main(argv: Optional[List[str]] = None, prog: Optional[str] = None) -> None:
    """The ``torchflow-learn`` command (``argv``: the overrides; default ``sys.argv[1:]``)."""
    shell.main(LEARN, argv, prog, entry=hydra_main)


__all__ = ["main", "run", "learn", "LearnOutcome", "LEARN"]
