"""Maximum-likelihood calibration of a model's parameters through a filter, from the command line.

    python experiments/learn.py                                    # acoustic: Psi and sigma_w, PF-PF(LEDH)
    python experiments/learn.py 'filter=[pfpf_ledh,bpf]' epochs=60
    python experiments/learn.py model=linear_gaussian model.d=4 learn=true 'start={alpha: 0.5}' 'filter=[bpf]'

Simulates ``trials`` tracks of ``steps`` steps from the model config (the truth), builds a second
model with ``learnable=<learn>`` and the constructor overrides ``start`` (the wrong starting values),
and fits it with each selected filter (particle filters with ``resampling_gradient`` and
``proposal_gradient``) through
:class:`~torchflow.lightning.FilterLightningModule` (Adam, loss = negative log-evidence per step).
The ``reference`` filter (EKF, or the Kalman filter on a linear model) is fitted the same way: its
estimate is the Kalman/EKF maximum-likelihood value the table compares against. Writes
``learn.csv`` / ``learn.json`` (per filter and parameter: start, final, truth, errors, seconds per
epoch) and ``curves.png`` (loss and parameters per epoch) into Hydra's output folder.
"""
from __future__ import annotations

import json
import logging
import math
import sys
import time
from pathlib import Path
from typing import Dict, List

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from . import cli  # noqa: F401 - registers the signature config nodes and the tf_pid resolver
from .runner import config as rc
from .runner import format_table, writers
from .registry import signature_defaults
from .runner.plan import ConfigError

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


def _learner(cfg: DictConfig):
    """The model to fit: the model config with ``learnable=<learn>`` and the ``start`` overrides."""
    learn = OmegaConf.to_container(cfg.learn, resolve=True) if OmegaConf.is_config(cfg.learn) else cfg.learn
    start = OmegaConf.to_container(cfg.start, resolve=True) if cfg.get("start") else {}
    return hydra.utils.instantiate(cfg.model, learnable=learn, **start)


def _fit(cfg: DictConfig, key: str, fcfg, data, names: List[str], out: Path) -> Dict:
    """Fit one filter's copy of the model; the per-epoch history and the final values."""
    import pytorch_lightning as pl
    from torch.utils.data import DataLoader

    from .lightning import FilterLightningModule

    model = _learner(cfg)
    target = hydra.utils.get_class(fcfg._target_) if "_target_" in fcfg else None
    kw = {"model": model, "name": key}
    accepted = signature_defaults(target) if target is not None else {}  # the keyword arguments it takes
    for key_ in ("resampling_gradient", "proposal_gradient"):
        if key_ in accepted:
            kw[key_] = cfg[key_]
    filt = hydra.utils.instantiate(fcfg, **kw)
    try:  # its options' errors (lr_decay, betas, checkpoint_steps, ...) are settings: one line
        module = FilterLightningModule(filt, lr=cfg.lr, seed=cfg.seed, checkpoint_steps=cfg.checkpoint_steps,
                                       memory_budget_gb=cfg.memory_budget_gb, lr_decay=cfg.lr_decay,
                                       common_random_numbers=cfg.common_random_numbers,
                                       betas=OmegaConf.to_container(cfg.betas) if OmegaConf.is_config(cfg.betas)
                                       else cfg.betas)
    except ValueError as e:
        raise ConfigError(str(e)) from e
    history = {"epoch": [], "nll_per_step": [], "seconds": [], **{n: [] for n in names}}

    class Record(pl.Callback):
        def on_train_epoch_start(self, trainer, pl_module):
            self.t0 = time.perf_counter()

        def on_train_epoch_end(self, trainer, pl_module):
            history["epoch"].append(trainer.current_epoch + 1)
            history["nll_per_step"].append(float(trainer.callback_metrics["train_nll_per_step"]))
            history["seconds"].append(time.perf_counter() - self.t0)
            for n in names:
                history[n].append(_value(model, n))
            log.info(f"{key} epoch {trainer.current_epoch + 1}: nll/step {history['nll_per_step'][-1]:.4f}, "
                     + ", ".join(f"{n} {_fmt(history[n][-1])}" for n in names))

    trainer = pl.Trainer(max_epochs=cfg.epochs, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, default_root_dir=str(out), callbacks=[Record()],
                         accelerator="cpu" if cfg.device == "cpu" else "auto")
    batch = cfg.batch_size or len(data)
    trainer.fit(module, DataLoader(data, batch_size=batch, shuffle=False))
    return {"history": history, "checkpoint_steps": bool(module.checkpoint_steps is True)}


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


def run(cfg: DictConfig, out: Path) -> List[Dict]:
    """Simulate, fit every selected filter (and the reference), write the results; the table rows."""
    from .lightning import TrajectoryDataset

    if not cfg.get("filter"):
        raise ConfigError("filter: select at least one filter, e.g. 'filter=[pfpf_ledh,bpf]'")
    for k in ("epochs", "trials", "steps"):
        if not isinstance(cfg[k], int) or isinstance(cfg[k], bool) or cfg[k] < 1:
            raise ConfigError(f"{k}: expected a positive integer, got {cfg[k]!r}")
    if not (isinstance(cfg.lr, (int, float)) and cfg.lr > 0):
        raise ConfigError(f"lr: expected a positive learning rate, got {cfg.lr!r}")
    truth = hydra.utils.instantiate(cfg.model)
    g = torch.Generator().manual_seed(int(cfg.seed))
    traj = truth.simulate(cfg.trials, cfg.steps, g)
    mean, cov = truth.initial_belief(traj.states[:, 0], g)
    data = TrajectoryDataset(traj, mean, cov)
    probe = _learner(cfg)
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
    fits = {}
    for key, fcfg in fcfgs.items():
        log.info(f"fitting {', '.join(names)} with {key} ({cfg.epochs} epochs, {cfg.trials} trials x {cfg.steps} steps)")
        fits[key] = _fit(cfg, key, fcfg, data, names, out)
    rows = _rows(fits, true_values, start, names, reference or "")
    writers.write_csv(out / "learn.csv", rows, COLUMNS)
    writers.write_text(out / "learn.json", json.dumps({
        "config": OmegaConf.to_container(cfg, resolve=True), "rows": rows,
        "history": {k: f["history"] for k, f in fits.items()},
        "checkpoint_steps": {k: f["checkpoint_steps"] for k, f in fits.items()}}, indent=1))
    if cfg.plots:
        _plot(fits, true_values, names, out / "curves.png")
    return rows


def _reference_class(name: str) -> str:
    """The class path of the reference filter ``ekf`` | ``kf`` | ``ukf``."""
    from .registry import REGISTRY

    if name not in ("ekf", "kf", "ukf"):
        raise ConfigError(f"reference: expected one of ekf, kf, ukf or null, got {name!r}")
    return REGISTRY["filter"][name]


@hydra.main(config_path=rc.config_source(), config_name="learn", version_base="1.3")
def hydra_main(cfg: DictConfig) -> None:
    out = Path(HydraConfig.get().runtime.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    for name in ("pytorch_lightning", "lightning.pytorch", "lightning_fabric"):  # its banners, not our log
        logging.getLogger(name).setLevel(logging.WARNING)
    try:
        rows = run(cfg, out)
    except Exception as e:  # noqa: BLE001 - a configuration error is one line; anything else keeps its traceback
        bad = cli.config_error(e)
        if bad is None:
            raise
        log.error(f"error: {bad}")
        sys.exit(2)
    log.info("\n" + format_table(rows, COLUMNS))
    log.info(f"results: {out}")


def main() -> None:
    """The ``torchflow-learn`` command."""
    hydra_main()


__all__ = ["main", "run"]
