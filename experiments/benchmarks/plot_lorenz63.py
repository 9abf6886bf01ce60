"""Lorenz-63 (Sakov, Oliver & Bertino 2012 set-up) figure: analysis RMSE against the ensemble size N
for the particle flows built for deterministic dynamics (the lag-one flow, the kernel particle flow
filter) beside the ETKF with DAPPER's semantics, with DAPPER's iEnKS (N = 10) and PartFilt (N = 100)
on the same data as reference lines (``results_lorenz63.json``, ``bench_lorenz63``).

    python -m experiments.benchmarks.plot_lorenz63            # ~8 min on one thread
    python -m experiments.benchmarks.plot_lorenz63 --replot   # the figure again from the saved numbers

10 trials x 1000 steps, burn-in 64 (the experiment's scoring), one random stream per trial. Writes
``docs/assets/lorenz63_rmse_n.png`` and ``results_lorenz63_n.json`` (per N and filter: the mean
RMSE, its standard error over trials and the per-trial RMSEs, so a lost trial shows).
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
ASSETS = HERE.parents[1] / "docs" / "assets"
FILTERS = {"lag1_flow": dict(), "kpff": dict(), "etkf": dict(inflation=1.02, inflate="analysis", rotate=True)}
LABELS = {"lag1_flow": "lag-one flow (EDH)", "kpff": "kernel particle flow (KPFF)", "etkf": "ETKF, infl 1.02, rotation"}
SIZES = [10, 20, 40, 100]


def rmse_against_n(trials=10, steps=1000, burn_in=64, seed=0):
    from torchflow.core.random import TrialStreams
    from torchflow.core.registry import lookup
    from torchflow.models import Lorenz63

    model = Lorenz63()
    traj = model.simulate(trials, steps, torch.Generator().manual_seed(seed))
    mean, cov = model.initial_belief(traj.states[:, 0])
    rows = []
    for name, kw in FILTERS.items():
        for n in SIZES:
            f = lookup("filter", name)(model, n_particles=n, **kw)
            est = f(traj.observations, mean, cov, TrialStreams(seed + 2, trials, f.stream_name)).estimates
            per_trial = (est - traj.states[:, 1:]).pow(2).mean(-1).sqrt()[:, burn_in:].mean(-1)
            rows.append(
                dict(
                    filter=name,
                    n=n,
                    rmse=float(per_trial.mean()),
                    se=float(per_trial.std() / trials**0.5),
                    per_trial=[round(float(v), 4) for v in per_trial],
                    trials=trials,
                    steps=steps,
                    burn_in=burn_in,
                )
            )
            print(rows[-1], flush=True)
    return rows


def main():
    import sys

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    torch.set_num_threads(1)
    if "--replot" in sys.argv[1:]:
        rows = json.loads((HERE / "results" / "results_lorenz63_n.json").read_text())
    else:
        rows = rmse_against_n()
        (HERE / "results" / "results_lorenz63_n.json").write_text(json.dumps(rows, indent=1) + "\n")
    dapper = {
        r["setting"].split()[0]: r
        for r in json.loads((HERE / "results" / "results_lorenz63.json").read_text())["rows"]
        if r["library"].startswith("DAPPER")
    }
    fig, ax = plt.subplots(figsize=(8.2, 3.8))
    for name in FILTERS:
        rs = [r for r in rows if r["filter"] == name]
        ax.errorbar(
            [r["n"] for r in rs],
            [r["rmse"] for r in rs],
            yerr=[r["se"] for r in rs],
            marker="o",
            capsize=3,
            label=LABELS[name],
        )
    for key, style in (("iEnKS", "--"), ("PartFilt", ":")):
        r = dapper.get(key)
        if r is not None:
            ax.axhline(r["rmse"][0], color="grey", lw=0.9, ls=style, label=f"DAPPER {r['setting']} (same data)")
    ax.set(
        xscale="log",
        yscale="log",
        xlabel="ensemble members N",
        ylabel="analysis RMSE",
        title="Lorenz-63 (Sakov et al. 2012 set-up)",
    )
    ax.set_xticks(SIZES, [str(n) for n in SIZES])
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    fig.tight_layout()
    fig.savefig(ASSETS / "lorenz63_rmse_n.png", dpi=120)


if __name__ == "__main__":
    main()
