"""Maximum-likelihood calibration of a model's parameters through a filter: the ``torchflow-learn`` command.

    torchflow-learn                                                # acoustic: Psi and sigma_w, PF-PF(LEDH)
    torchflow-learn 'filter=[pfpf_ledh,bpf]' epochs=60
    torchflow-learn model=linear_gaussian model.d=4 learn=true '~start' '+start={alpha: 0.5}' 'filter=[bpf]'

(``python experiments/learn.py`` is the same command.) Simulates ``trials`` tracks of ``steps``
steps from the model config (the truth) through the runner's simulation, the one the
``torchflow`` command uses (:func:`~torchflow.app.runner.plan_run`: ``seed``, ``inits_per_track``,
``device``, ``dtype`` mean the same), builds a second model with ``learnable=<learn>`` and the
constructor overrides ``start`` (the wrong starting values), and fits it with each selected filter
(particle filters with ``resampling_gradient`` and ``proposal_gradient``) through
:class:`~torchflow.app.lightning.FilterLightningModule` (Adam, loss = negative log-evidence per step).
The ``reference`` filter (EKF, or the Kalman filter on a linear model) is fitted the same way: its
estimate is the Kalman/EKF maximum-likelihood value the table compares against. Writes
``learn.csv`` / ``learn.json`` (per filter and parameter: start, final, truth, errors, seconds per
epoch, a note; the per-epoch history) and ``curves.png`` (loss and parameters per epoch) into
Hydra's output folder. ``data=<file>`` fits recorded observations instead (no truth:
:func:`torchflow.app.runner.config.recorded_data`; each fit's filter starts from its model's declared
prior, recomputed at every optimiser step; ``truth`` is left empty).

Refused before anything runs (one line, exit 2): a ``start`` key that is no argument of the model
(naming its learnable parameters and the closest arguments); a filter whose log-evidence is only a
Gaussian approximation (``estimates_evidence = False``: the unweighted flow filters, the
Gaussian-sum particle filters) unless ``allow_approximate_evidence=true``, which fits it and labels
its results. A fit that meets the divergence rule (:data:`DIVERGENCE_GROWTH`,
:data:`DIVERGENCE_RISES`) is warned of and recorded (``learn.json``: ``diverged``). A non-finite
log-evidence, gradient or learned parameter, or a model the filter refuses once the optimiser has
moved its parameters, ends that filter's fit: one line naming the filter, the quantity and the
epoch; the epochs before it are written (``learn.json``: ``failed``), the other filters go on, and
the exit status is 1.

It runs in the command shell (:mod:`torchflow.app.runner.shell`), whose contracts it shares with
``torchflow``: an unknown setting (``+learning_rate=0.5``) is refused in one line with the
closest known keys; the output folder is guarded (earlier results unless ``overwrite=true``, a
live run's lock file); ``device``, ``dtype``, ``threads`` and ``tuning.*`` are set up the same
way; SIGINT / SIGTERM stop after the current optimiser step, and the finished epochs are written
(``learn.json`` says ``"interrupted": true``; a filter not started is listed under ``not_run``).
Exit status: 0 done; 1 a failure (a fit that failed, the results could not be written; any other
error keeps its traceback); 2 a configuration error or a refused output folder (one line); 130 stopped by Ctrl-C
(SIGINT); 143 stopped by SIGTERM.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import signal
import sys
import time
import warnings
from dataclasses import dataclass, field
from functools import reduce
from pathlib import Path
from typing import Dict, List, Optional

import hydra
from omegaconf import DictConfig, OmegaConf

from torchflow.app.runner import STOP, RunStopped, format_table, plan_run, shell, writers
from torchflow.app.runner.config import close_keys, config_dir, group_options, recorded_data
from torchflow.app.runner.plan import ConfigError
from torchflow.app.runner.shell import JobEnv
from torchflow.app.runner.writers import save_figure
from torchflow.core.errors import TorchflowError
from torchflow.core.registry import resolve, signature_defaults

log = logging.getLogger("torchflow.app.learn")

COLUMNS = [
    "filter",
    "parameter",
    "start",
    "final",
    "truth",
    "error_vs_truth_pct",
    "reference",
    "error_vs_reference_pct",
    "epochs",
    "sec_per_epoch",
    "final_nll_per_step",
    "note",
]

#: a fit is flagged as diverging (a warning, recorded in learn.json) when a learned parameter's size
#: (Euclidean norm) grows past this many times its start's (or 1, if the start is smaller) ...
DIVERGENCE_GROWTH = 1e3
#: ... or when the negative log-evidence per step rose in each of this many consecutive epochs and
#: ended more than 10% (at least 0.1 per step) above the first epoch's
DIVERGENCE_RISES = 2


def _value(model, name: str) -> List[float]:
    return [float(v) for v in reduce(getattr, name.split("."), model).detach().reshape(-1)]


def _norm(v: List[float]) -> float:
    return math.hypot(*v)  # no overflow on the way


def _divergence(history: Dict, start: Dict[str, List[float]]) -> Optional[str]:
    """Why the fit whose per-epoch ``history`` began at ``start`` is diverging (the rule of
    :data:`DIVERGENCE_GROWTH` and :data:`DIVERGENCE_RISES`), ``None`` if it is not."""
    for n, v0 in start.items():
        if _norm(history[n][-1]) > DIVERGENCE_GROWTH * max(_norm(v0), 1.0):
            return (
                f"{n} grew from {_fmt(v0)} to {_fmt(history[n][-1])}, more than {DIVERGENCE_GROWTH:g} times its start"
            )
    loss, k = history["nll_per_step"], DIVERGENCE_RISES
    if (
        len(loss) > k
        and all(loss[-i] > loss[-i - 1] for i in range(1, k + 1))
        and loss[-1] > loss[0] + 0.1 * max(abs(loss[0]), 1.0)
    ):
        return (
            f"the negative log-evidence per step rose in each of the last {k} epochs, from {loss[0]:.4g} "
            f"(epoch 1) to {loss[-1]:.4g}"
        )
    return None


def _rel_error(a: List[float], b: List[float]) -> float:
    """``|a - b| / |b|`` (Euclidean norms), in per cent."""
    num, den = math.hypot(*(x - y for x, y in zip(a, b))), _norm(b)
    return 100.0 * num / den if den > 0 else float("nan")


def _start(cfg: DictConfig) -> Dict:
    """The ``start`` overrides, checked: each must be a constructor argument of the model (one line
    naming ``start.<key>``, the model's learnable parameters and the closest arguments)."""
    given = (
        OmegaConf.to_container(cfg.start, resolve=True) if OmegaConf.is_config(cfg.get("start")) else cfg.get("start")
    )
    if given is None:
        return {}
    if not isinstance(given, dict):
        raise ConfigError(
            f"start: expected a mapping of constructor arguments of the model to fit, such as "
            f"start={{psi: 5.0}}, got {given!r}"
        )
    cls = hydra.utils.get_class(cfg.model._target_)
    accepted = [k for k in signature_defaults(cls) if k != "learnable"]
    unknown = [k for k in given if k not in accepted]
    if not unknown:
        return given
    try:
        from torchflow.app.lightning import learned_parameters

        learnable = ", ".join(learned_parameters(hydra.utils.instantiate(cfg.model, learnable=True)))
    except Exception:
        learnable = ""
    default = [k for k in unknown if k in (OmegaConf.load(config_dir() / "learn.yaml").get("start") or {})]
    bad = []
    for k in unknown:
        close = close_keys(str(k), accepted)
        bad.append(
            f"start.{k}: expected an argument of {cls.__name__}"
            + (f" (did you mean start.{' or start.'.join(close)}?)" if close else "")
            + f", got {k!r}"
        )
    raise ConfigError(
        "; ".join(bad)
        + (f"; its learnable parameters: {learnable}" if learnable else "")
        + (
            f"; {', '.join(default)} {'is' if len(default) == 1 else 'are'} in learn.yaml's default start, which "
            "start={...} merges into: replace it with '~start' '+start={...}'"
            if default
            else ""
        )
    )


def _learns(target: str) -> bool:
    """Whether the model class ``target`` is built with learnable parameters (a ``learnable``
    argument)."""
    return "learnable" in signature_defaults(resolve(target))


def _check_learnable_model(cfg: DictConfig) -> None:
    """A model without learnable parameters (no ``learnable`` argument: Lorenz-63, Lorenz-96) is
    refused in one line naming the models that have them."""
    target = cfg.model._target_
    if _learns(target):
        return
    models = []
    for name in group_options("model") or []:
        found = _filter_target(name, "model")
        if found and _learns(found):
            models.append(name)
    raise ConfigError(
        f"model: {target.split('.')[-1]} has no learnable parameters (it takes no learnable=...), so "
        f"torchflow-learn cannot fit it; the models it fits: {', '.join(models)}"
    )


def _learner(cfg: DictConfig, env: Optional[JobEnv] = None):
    """The model to fit: the model config with ``learnable=<learn>`` and the ``start`` overrides, on
    the job's device and dtype."""
    learn = OmegaConf.to_container(cfg.learn, resolve=True) if OmegaConf.is_config(cfg.learn) else cfg.learn
    _check_learnable_model(cfg)
    model = hydra.utils.instantiate(cfg.model, learnable=learn, **_start(cfg))
    return model if env is None else model.to(device=env.device, dtype=env.dtype)


def _filter_target(name: str, group: str = "filter") -> Optional[str]:
    """The class path of the config ``configs/<group>/<name>.yaml`` (its ``_target_``, or that of
    the config or signature node it extends)."""
    node = OmegaConf.load(config_dir() / group / f"{name}.yaml")
    if "_target_" in node:
        return node._target_
    for item in node.get("defaults") or []:
        if isinstance(item, str) and item.endswith("@_here_"):
            ref = item[: -len("@_here_")]
            return ref[len("/signature/") :] if ref.startswith("/signature/") else _filter_target(ref, group)
    return None


def _check_evidence(cfg: DictConfig, fcfgs: Dict) -> List[str]:
    """The selected filters whose log-evidence is only an approximation
    (``estimates_evidence = False``): refused (one line naming them and the filters that estimate
    it) unless ``allow_approximate_evidence=true``, then returned (their results are labelled)."""
    approximate = [
        k for k, f in fcfgs.items() if not getattr(hydra.utils.get_class(f._target_), "estimates_evidence", True)
    ]
    if approximate and not cfg.allow_approximate_evidence:
        good = [
            n
            for n in group_options("filter") or []
            if (t := _filter_target(n))
            and getattr(resolve(t), "estimates_evidence", None) is True
            and getattr(resolve(t), "uses_particles", False)
        ]
        names = ", ".join(f"{k} ({hydra.utils.get_class(fcfgs[k]._target_).__name__})" for k in approximate)
        raise ConfigError(
            f"filter: {names} reports a Gaussian approximation of the log-evidence, not an estimate of it, so "
            f"learning through it does not follow the likelihood's gradient; filters whose log-evidence gradient is "
            f"consistent: {', '.join(good)} (and kf on a linear-Gaussian model); or add "
            "allow_approximate_evidence=true to learn through it anyway (its results are labelled approximate)"
        )
    for k in approximate:
        log.warning(
            f"warning: {k}: learning through an approximate log-evidence (allow_approximate_evidence=true): its "
            "results are labelled approximate"
        )
    return approximate


def _stop_callback():
    """A Lightning callback that ends the fit after the optimiser step during which a stop request
    (:data:`~torchflow.app.runner.STOP`: SIGINT, SIGTERM) came; where the shell's handlers are in force
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
    counts its optimiser steps in ``steps``), whether it stopped early, the checkpointing used,
    whether it diverged (:func:`_divergence`: from which epoch, why) and why it failed (a
    non-finite value, :class:`~torchflow.core.errors.NonFiniteError`, or another error: the epoch, the
    message; the epochs before it are in the history)."""
    import pytorch_lightning as pl
    from pytorch_lightning.utilities.exceptions import SIGTERMException
    from torch.utils.data import DataLoader

    from torchflow.app.lightning import FilterLightningModule

    model = _learner(cfg, env)
    target = hydra.utils.get_class(fcfg._target_) if "_target_" in fcfg else None
    kw = {"model": model, "name": key}
    accepted = signature_defaults(target) if target is not None else {}  # the keyword arguments it takes
    for key_ in ("resampling_gradient", "proposal_gradient"):
        if key_ in accepted:
            kw[key_] = cfg[key_]
    filt = hydra.utils.instantiate(fcfg, **kw).to(device=env.device, dtype=env.dtype)
    try:  # its options' errors (lr_decay, betas, checkpoint_steps, ...) are settings: one line
        module = FilterLightningModule(
            filt,
            lr=cfg.lr,
            seed=cfg.seed,
            checkpoint_steps=cfg.checkpoint_steps,
            memory_budget_gb=cfg.memory_budget_gb,
            lr_decay=cfg.lr_decay,
            common_random_numbers=cfg.common_random_numbers,
            allow_approximate_evidence=cfg.allow_approximate_evidence,
            betas=OmegaConf.to_container(cfg.betas) if OmegaConf.is_config(cfg.betas) else cfg.betas,
        )
    except ValueError as e:
        raise ConfigError(str(e)) from e
    history = {"epoch": [], "steps": [], "nll_per_step": [], "seconds": [], **{n: [] for n in names}}
    begin = {n: _value(model, n) for n in names}
    diverged: Dict = {}

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
            log.info(
                f"{key} epoch {trainer.current_epoch + 1}: nll/step {history['nll_per_step'][-1]:.4f}, "
                + ", ".join(f"{n} {_fmt(history[n][-1])}" for n in names)
            )
            why = None if diverged else _divergence(history, begin)
            if why:
                diverged.update(epoch=trainer.current_epoch + 1, reason=why)
                log.warning(
                    f"warning: {key} is diverging (epoch {diverged['epoch']}): {why}; a smaller lr "
                    f"(now {cfg.lr}) may help"
                )

    cpu = env.device is None or env.device.type == "cpu"
    trainer = pl.Trainer(
        max_epochs=cfg.epochs,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        default_root_dir=str(out),
        callbacks=[Record(), _stop_callback()],
        accelerator="cpu" if cpu else "gpu",
        devices=1 if cpu else [env.device.index or 0],
    )
    batch = cfg.batch_size or len(data)
    failed = None
    try:
        trainer.fit(module, DataLoader(data, batch_size=batch, shuffle=False))
    except SIGTERMException:  # Lightning's own SIGTERM handling (where ours was not in force): a stop request
        if not STOP.requested:
            STOP.handler(signal.SIGTERM, None)
    except TorchflowError as e:  # NonFiniteError, a model refused: the module names the filter, what and the epoch
        failed = {"epoch": trainer.current_epoch + 1, "error": str(e)}
    except Exception as e:
        failed = {
            "epoch": trainer.current_epoch + 1,
            "error": f"{key}: {type(e).__name__}: {e} (epoch {trainer.current_epoch + 1})",
        }
        log.error(f"{key} failed in epoch {trainer.current_epoch + 1}", exc_info=True)
    stopped = STOP.requested and len(history["epoch"]) < cfg.epochs
    return {
        "history": history,
        "checkpoint_steps": bool(module.checkpoint_steps is True),
        "stopped": stopped,
        "diverged": diverged or None,
        "failed": failed,
    }


def _fmt(v: List[float]) -> str:
    return f"{v[0]:.4g}" if len(v) == 1 else "[" + ", ".join(f"{x:.3g}" for x in v) + "]"


def _rows(fits: Dict, truth: Optional[Dict], start: Dict, names: List[str], reference: str) -> List[Dict]:
    """The table: per filter and parameter (``truth`` ``None``: recorded data, no true values)."""
    rows = []
    for key, fit in fits.items():
        h = fit["history"]
        for n in names:
            final = h[n][-1]
            ref = fits[reference]["history"][n][-1] if reference in fits and key != reference else None
            rows.append(
                {
                    "filter": key,
                    "parameter": n,
                    "start": _fmt(start[n]),
                    "final": _fmt(final),
                    "truth": "" if truth is None else _fmt(truth[n]),
                    "error_vs_truth_pct": "" if truth is None else round(_rel_error(final, truth[n]), 3),
                    "reference": "" if ref is None else _fmt(ref),
                    "error_vs_reference_pct": "" if ref is None else round(_rel_error(final, ref), 3),
                    "epochs": len(h["epoch"]),
                    "sec_per_epoch": round(sum(h["seconds"]) / max(1, len(h["seconds"])), 3),
                    "final_nll_per_step": round(h["nll_per_step"][-1], 5),
                    "note": _note(fit),
                }
            )
    return rows


def _note(fit: Dict) -> str:
    """The table's note on a fit: approximate evidence, diverging, failed."""
    notes = ["approximate log-evidence"] if fit.get("approximate_evidence") else []
    if fit.get("diverged"):
        notes.append(f"diverging from epoch {fit['diverged']['epoch']}")
    if fit.get("failed"):
        notes.append(f"failed in epoch {fit['failed']['epoch']}")
    return "; ".join(notes)


def _plot(fits: Dict, truth: Optional[Dict], names: List[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 1 + len(names), figsize=(4.2 * (1 + len(names)), 3.4))
    for key, fit in fits.items():
        h = fit["history"]
        axes[0].plot(h["epoch"], h["nll_per_step"], label=key)
        for ax, n in zip(axes[1:], names):
            ax.plot(
                h["epoch"],
                [v[0] if len(v) == 1 else _norm(v) if truth is None else _rel_error(v, truth[n]) for v in h[n]],
                label=key,
            )
    axes[0].set(xlabel="epoch", ylabel="negative log-evidence per step")
    for ax, n in zip(axes[1:], names):
        scalar = len(next(iter(fits.values()))["history"][n][-1]) == 1
        if scalar and truth is not None:
            ax.axhline(truth[n][0], color="k", ls="--", lw=1, label="truth")
        ax.set(xlabel="epoch", ylabel=n if scalar else f"{n}: norm" if truth is None else f"{n}: % error vs truth")
    axes[-1].legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)


@dataclass
class LearnOutcome:
    """What :func:`learn` did: the table ``rows``, the ``fits`` (per filter: history, ...), whether a
    stop request ended it early (``interrupted``), the filters it did not start (``not_run``), the
    filters whose fit failed (``failed``: per filter the epoch and the one-line message), and why the
    results could not be written (``write_failed``; ``None``: written)."""

    rows: List[Dict]
    fits: Dict[str, Dict] = field(default_factory=dict)
    interrupted: bool = False
    not_run: List[str] = field(default_factory=list)
    write_failed: Optional[str] = None
    failed: Dict[str, Dict] = field(default_factory=dict)


def learn(cfg: DictConfig, out: Path, env: JobEnv) -> LearnOutcome:
    """Simulate (through :func:`~torchflow.app.runner.plan_run`), fit every selected filter (and the
    reference) until done or a stop request, and write the results of the epochs that finished."""
    from torchflow.app.lightning import TrajectoryDataset, learned_parameters

    if not cfg.get("filter"):
        raise ConfigError("filter: select at least one filter, e.g. 'filter=[pfpf_ledh,bpf]'")
    for k in ("epochs", "trials", "steps"):
        if not isinstance(cfg[k], int) or isinstance(cfg[k], bool) or cfg[k] < 1:
            raise ConfigError(f"{k}: expected a positive integer, got {cfg[k]!r}")
    if not (isinstance(cfg.lr, (int, float)) and cfg.lr > 0):
        raise ConfigError(f"lr: expected a positive learning rate, got {cfg.lr!r}")
    _start(cfg)
    reference = cfg.get("reference")
    fcfgs = {k: v for k, v in cfg.filter.items() if "_target_" in v}
    if reference and reference not in fcfgs:
        fcfgs[reference] = OmegaConf.create({"_target_": _reference_class(reference)})
    approximate = _check_evidence(cfg, fcfgs)
    probe = _learner(cfg, env)
    names = list(learned_parameters(probe))
    if not names:
        raise ConfigError(f"learn: the model has no learnable parameters with learn={cfg.learn!r}")
    recorded = recorded_data(cfg, probe)
    if recorded is None:  # simulate the training set from the model config (the truth)
        truth = hydra.utils.instantiate(cfg.model)
        plan = plan_run(
            truth,
            {},
            trials=cfg.trials,
            steps=cfg.steps,
            seed=cfg.seed,
            inits_per_track=cfg.get("inits_per_track", 1),
            memory_budget_gb=cfg.memory_budget_gb,
            device=env.device or "cpu",
            dtype=env.dtype or "float64",
        )
        data = TrajectoryDataset(plan.traj, plan.mean0, plan.cov0)
        true_values = {n: _value(truth, n) for n in names}
        sizes = {"trials": cfg.trials, "steps": plan.settings.steps, "inits_per_track": plan.settings.inits_per_track}
    else:  # recorded: no truth; each fit starts its filter from its model's declared prior at every step
        obs, trials, steps, sha = recorded.observations, recorded.trials, recorded.steps, recorded.sha256
        if recorded.states is not None or recorded.prior is not None:
            log.info(
                "data: the recording's states and prior are not used by learning (each fit starts from its "
                "model's declared prior; the fit is scored against no truth)"
            )
        data = TrajectoryDataset(obs.expand(trials, -1, -1) if obs.dim() == 2 else obs)
        true_values = None
        sizes = {"trials": trials, "steps": steps, "data": cfg.data, "data_sha256": sha}
    start = {n: _value(probe, n) for n in names}
    given = OmegaConf.to_container(cfg.start, resolve=True) if cfg.get("start") else {}
    fixed = {k: v for k, v in given.items() if k not in names}
    # start is a mapping: an override such as start={psi: 5} merges into the default (its sigma_w stays)
    log.info(
        f"model to fit: learned {', '.join(f'{n} from {_fmt(start[n])}' for n in names)}"
        + (f"; held at start values: {fixed}" if fixed else "")
    )
    res = LearnOutcome([])
    for key, fcfg in fcfgs.items():
        if STOP.requested:
            res.interrupted = True
            res.not_run.append(key)
            continue
        log.info(
            f"fitting {', '.join(names)} with {key} ({cfg.epochs} epochs, {len(data)} trials x "
            f"{data.obs.shape[1]} steps{'' if recorded is None else ' of data=' + str(cfg.data)})"
        )
        fit = _fit(cfg, key, fcfg, data, names, out, env)
        fit["approximate_evidence"] = key in approximate
        res.interrupted |= fit["stopped"]
        if fit["failed"]:
            res.failed[key] = fit["failed"]
        if fit["history"]["epoch"]:
            res.fits[key] = fit
        elif not fit["failed"]:  # stopped before its first step ended
            res.not_run.append(key)
    res.rows = _rows(res.fits, true_values, start, names, reference or "")
    writer = shell.Output(out)
    writer.attempt("learn.csv", writers.write_csv, out / "learn.csv", res.rows, COLUMNS)
    writer.attempt(
        "learn.json",
        writers.write_text,
        out / "learn.json",
        json.dumps(
            {
                "config": OmegaConf.to_container(cfg, resolve=True),
                "rows": res.rows,
                "history": {k: f["history"] for k, f in res.fits.items()},
                "checkpoint_steps": {k: f["checkpoint_steps"] for k, f in res.fits.items()},
                "interrupted": res.interrupted,
                "stopped_by": STOP.name if res.interrupted else None,
                "not_run": res.not_run,
                "failed": res.failed,
                "diverged": {k: f["diverged"] for k, f in res.fits.items() if f["diverged"]},
                "approximate_evidence": [k for k in fcfgs if k in approximate],
                "divergence_rule": {"growth": DIVERGENCE_GROWTH, "rises": DIVERGENCE_RISES},
                "run": {
                    **sizes,
                    "seed": cfg.seed,
                    "device": str(data.obs.device),
                    "dtype": str(data.obs.dtype).replace("torch.", ""),
                    "threads": env.threads,
                    "tuning": env.tuning,
                },
            },
            indent=1,
        ),
    )
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
    from torchflow.core.registry import REGISTRY

    if name not in ("ekf", "kf", "ukf"):
        raise ConfigError(f"reference: expected one of ekf, kf, ukf or null, got {name!r}")
    return REGISTRY["filter"][name]


@contextlib.contextmanager
def _lightning_quiet(quiet: bool = True):
    """Lightning's own lines (which accelerator, its tips, ``Trainer.fit`` stopped) and its
    deprecation warnings left out of the command's output while it fits (``quiet``); its warnings
    and errors still show. Lightning sets its loggers' level when imported, so it is imported first."""
    if not quiet:
        yield
        return
    import pytorch_lightning  # noqa: F401 - sets its loggers' level at import: ours must come after

    names = ("pytorch_lightning", "lightning.pytorch", "lightning_fabric", "lightning")
    before = {n: logging.getLogger(n).level for n in names}
    for n in names:
        logging.getLogger(n).setLevel(logging.WARNING)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", category=DeprecationWarning, module=r"(pytorch_)?lightning")
            warnings.filterwarnings("ignore", message=r".*treespec.*deprecated")  # Lightning's use of torch's pytree
            yield
    finally:
        for n, level in before.items():
            logging.getLogger(n).setLevel(level)


def _job(cfg: DictConfig, out: Path, env: JobEnv) -> int:
    """The learn command's job (in the shell's job environment); the exit status."""
    try:
        with _lightning_quiet(not (cfg is not None and cfg.get("lightning_messages", False))):
            res = learn(cfg, out, env)
    except RunStopped as stopped:  # during the simulation: nothing was fitted, nothing is written
        log.warning(str(stopped))
        return STOP.exit_code
    if res.rows:
        log.info("\n" + format_table(res.rows, COLUMNS))
    if res.write_failed is None:
        log.info(f"results: {shell.shown_path(out)}")
    done = ", ".join(
        f"{k}: {len(res.fits[k]['history']['epoch']) if k in res.fits else 0} of {cfg.epochs} epochs"
        for k in [*res.fits, *(k for k in res.failed if k not in res.fits)]
    )
    for key, failure in res.failed.items():
        log.error(f"error: {failure['error']}; learn.csv and learn.json hold the epochs that finished ({done})")
    if res.interrupted:
        skipped = f"; not run: {', '.join(res.not_run)}" if res.not_run else ""
        log.warning(
            f"interrupted by {STOP.name}: learn.csv and learn.json hold the epochs that finished "
            f"({done or 'none'}){skipped}"
        )
        return STOP.exit_code
    return shell.EXIT_FAILED if res.write_failed or res.failed else shell.EXIT_OK


#: the ``torchflow-learn`` command of the shell (``start`` holds constructor overrides: free-form)
LEARN = shell.Command(
    prog="torchflow-learn", config_name="learn", job=_job, free_form=("model", "filter", "hydra", "start")
)
hydra_main = shell.hydra_entry(LEARN)


def _open_start(argv: List[str]) -> List[str]:
    """``start=...`` and ``start.<key>=...`` as ``++start...``: ``start`` holds constructor
    arguments, which Hydra's struct mode would refuse to extend (``start={..., bogus: 1}``) before
    :func:`_start` can name the key; the merge into the default stays a merge."""
    return [f"++{a}" if a.startswith(("start=", "start.")) else a for a in argv]


def main(argv: Optional[List[str]] = None, prog: Optional[str] = None) -> None:
    """The ``torchflow-learn`` command (``argv``: the overrides; default ``sys.argv[1:]``)."""
    shell.main(LEARN, _open_start(list(sys.argv[1:] if argv is None else argv)), prog, entry=hydra_main)


__all__ = ["main", "run", "learn", "LearnOutcome", "LEARN"]
