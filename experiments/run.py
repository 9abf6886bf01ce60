"""Hydra entry point: build a model and filters from ``configs/``, run them, write results.

    python experiments/run.py                                   # default acoustic comparison
    python experiments/run.py model=linear_gaussian filter=[kf,bpf] trials=100 steps=10 n_particles=200
    python experiments/run.py experiment=seed000_table1         # a paper table
    python experiments/run.py -m filter=[bpf] n_particles=100,1000   # sweep; one folder per job

Writes ``summary.csv``, ``per_step.csv``, ``per_trial.csv``, ``results.json`` and (with
matplotlib) ``per_step.png`` into Hydra's output folder and prints the summary table.
"""
from __future__ import annotations

import csv
import json
import os
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a source checkout too

from torchflow.experiment import SUMMARY_COLUMNS, format_table, run_experiment  # noqa: E402


def _write_csv(path: Path, rows, columns=None):
    columns = columns or sorted({k for r in rows for k in r}, key=lambda k: (k not in ("filter", "step", "trial"), k))
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=columns, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in columns})


def _plot(path: Path, per_step, title: str):
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("(matplotlib not installed: no plots; pip install matplotlib)")
        return
    keys = [k for k in ("omat", "ospa", "mse", "ess") if any(k in r for r in per_step)]
    if not keys:
        return
    fig, axes = plt.subplots(1, len(keys), figsize=(4.2 * len(keys), 3.4), squeeze=False)
    for ax, key in zip(axes[0], keys):
        for name in dict.fromkeys(r["filter"] for r in per_step):
            rows = [r for r in per_step if r["filter"] == name and key in r]
            if rows:
                ax.plot([r["step"] for r in rows], [r[key] for r in rows], label=name)
        ax.set_xlabel("time step")
        ax.set_ylabel(key)
        if key in ("mse", "ess"):
            ax.set_yscale("log")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


@hydra.main(config_path="../configs", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    out = Path(HydraConfig.get().runtime.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    if not cfg.get("filter"):
        raise ValueError("filter: select at least one filter, e.g. filter=[kf,bpf]")
    model = instantiate(cfg.model)
    filters = {}
    for name, fcfg in cfg.filter.items():
        if "_target_" not in fcfg:  # e.g. an experiment's per-filter setting for a filter not selected
            print(f"(filter.{name}: settings given but the filter is not selected; skipped)", file=sys.stderr)
            continue
        filters[name] = instantiate(fcfg, model=model, name=name)
    result = run_experiment(
        model,
        filters,
        trials=int(cfg.trials),
        steps=int(cfg.steps),
        seed=int(cfg.seed),
        inits_per_track=int(cfg.inits_per_track),
        chunk_size=cfg.chunk_size,
        memory_budget_gb=float(cfg.memory_budget_gb),
        device=cfg.device,
        dtype=cfg.dtype,
        ospa_cutoff=float(cfg.metrics.ospa_cutoff),
        ospa_order=float(cfg.metrics.ospa_order),
        lost_threshold=float(cfg.metrics.lost_threshold),
        progress=bool(cfg.progress),
        rng_backend=str(cfg.get("rng_backend", "auto")),
        on_filter_done=lambda rows: _write_csv(out / "summary.csv", rows, SUMMARY_COLUMNS),  # partial results
    )
    _write_csv(out / "summary.csv", result.summary, SUMMARY_COLUMNS)
    _write_csv(out / "per_step.csv", result.per_step)
    _write_csv(out / "per_trial.csv", result.per_trial)
    with open(out / "results.json", "w") as fh:
        json.dump({"config": OmegaConf.to_container(cfg, resolve=True), "run": result.config,
                   "summary": result.summary}, fh, indent=2)
    if cfg.get("plots", True):
        _plot(out / "per_step.png", result.per_step, f"{cfg.model._target_.split('.')[-1]}, {cfg.trials} trials")
    model_name = cfg.model._target_.split(".")[-1]
    print(f"\n{model_name}: {cfg.trials} trials x {cfg.steps} steps, seed {cfg.seed}, {cfg.device}/{cfg.dtype}")
    print(format_table(result.summary))
    errors = [r for r in result.summary if r.get("error")]
    for r in errors:
        print(f"!! {r['filter']} failed: {r['error']}", file=sys.stderr)
    print(f"results: {os.path.relpath(out)}")


if __name__ == "__main__":
    main()
