"""Lorenz-96 (Sakov & Oke 2008 set-up) figures: analysis RMSE against the ensemble size N at d = 40
(ETKF, LETKF, EnKF; the bootstrap PF's particles beside), and against d (from
``results_lorenz96.json``'s CPU d-scaling, plus the GPU row of ``results_gpu_check.md``).

    python -m experiments.benchmarks.plot_lorenz96     # ~1 min on one thread

Writes ``docs/assets/lorenz96_rmse_n.png``, ``docs/assets/lorenz96_rmse_d.png`` and
``results_lorenz96_n.json`` (the RMSE-against-N numbers: mean and standard error over trials).
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
ASSETS = HERE.parents[1] / "docs" / "assets"
FILTERS = {"etkf": dict(inflation=1.02), "letkf": dict(inflation=1.02, radius=15.0), "enkf": dict(inflation=1.06)}
SIZES = [8, 12, 16, 20, 30, 40]
BPF_SIZES = [100, 1000, 10000]
GPU = {"letkf": [(4000, 0.209)], "etkf": [(4000, 4.78)]}  # results_gpu_check.md (H100), 1 trial each


def rmse_against_n(trials=3, steps=500, burn_in=100, seed=0):
    from torchflow.core.random import TrialStreams
    from torchflow.core.registry import lookup
    from torchflow.models import Lorenz96

    model = Lorenz96()
    traj = model.simulate(trials, steps, torch.Generator().manual_seed(seed))
    mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator().manual_seed(seed + 1))
    rows = []
    runs = [(name, kw, n) for name, kw in FILTERS.items() for n in SIZES] + [("bpf", {}, n) for n in BPF_SIZES]
    for name, kw, n in runs:
        f = lookup("filter", name)(model, n_particles=n, **kw)
        est = f(traj.observations, mean, cov, TrialStreams(seed + 2, trials, f.stream_name)).estimates
        per_trial = (est - traj.states[:, 1:]).pow(2).mean(-1).sqrt()[:, burn_in:].mean(-1)
        rows.append(
            dict(
                filter=name,
                n=n,
                rmse=float(per_trial.mean()),
                se=float(per_trial.std() / trials**0.5),
                trials=trials,
                steps=steps,
                burn_in=burn_in,
            )
        )
        print(rows[-1], flush=True)
    return rows


def main():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    torch.set_num_threads(1)
    rows = rmse_against_n()
    (HERE / "results" / "results_lorenz96_n.json").write_text(json.dumps(rows, indent=1) + "\n")
    fig, ax = plt.subplots(figsize=(5.2, 3.6))
    for name in [*FILTERS, "bpf"]:
        rs = [r for r in rows if r["filter"] == name]
        ax.errorbar(
            [r["n"] for r in rs],
            [r["rmse"] for r in rs],
            yerr=[r["se"] for r in rs],
            marker="o",
            label=name.upper() if name != "bpf" else "bootstrap PF (particles)",
        )
    ax.axhline(1.0, color="grey", lw=0.8, ls="--", label="observation noise")
    ax.set(
        xscale="log",
        yscale="log",
        xlabel="ensemble members / particles N",
        ylabel="analysis RMSE",
        title="Lorenz-96, d = 40 (Sakov & Oke 2008 set-up)",
    )
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(ASSETS / "lorenz96_rmse_n.png", dpi=120)
    scaling = json.loads((HERE / "results" / "results_lorenz96.json").read_text())["scaling"]
    fig, ax = plt.subplots(figsize=(5.2, 3.6))
    for name, label in (("etkf", "ETKF, N = 28"), ("letkf", "LETKF, N = 20")):
        rs = [r for r in scaling if r["filter"] == name]
        line = ax.plot([r["d"] for r in rs], [r["rmse"][0] for r in rs], marker="o", label=f"{label} (CPU)")[0]
        ax.plot(*zip(*GPU[name]), marker="s", ls="none", color=line.get_color(), label=f"{label} (H100)")
    ax.set(
        xscale="log",
        yscale="log",
        xlabel="state dimension d",
        ylabel="analysis RMSE",
        title="Lorenz-96: RMSE against d",
    )
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(ASSETS / "lorenz96_rmse_d.png", dpi=120)


if __name__ == "__main__":
    main()
