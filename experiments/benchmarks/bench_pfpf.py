"""PF-PF benchmark: seconds per trial-step of PF-PF(LEDH) and PF-PF(EDH) on acoustic tracking.

    python experiments/benchmarks/bench_pfpf.py                 # 100 trials, N=500, 5 steps, float64
    python experiments/benchmarks/bench_pfpf.py --steps 40 --quick

Times are for a whole filter call (all trials batched) after an untimed warm-up, divided by
trials x steps, i.e. comparable with the per-step times the papers report for a single run
(MATLAB, 0.9-3.5 s per step for PF-PF(LEDH) N=500).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from torchflow.filters import BootstrapParticleFilter, ParticleFlowParticleFilter  # noqa: E402
from torchflow.models import AcousticTracking  # noqa: E402
from torchflow import metrics  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--particles", type=int, default=500)
    ap.add_argument("--dtype", default="float64", choices=["float64", "float32"])
    ap.add_argument("--sigma-w", type=float, default=0.1)
    ap.add_argument("--quick", action="store_true", help="10 trials, 3 steps")
    ap.add_argument("--out", default=str(Path(__file__).with_name("results_pfpf.md")))
    a = ap.parse_args()
    if a.quick:
        a.trials, a.steps = 10, 3
    dtype = getattr(torch, a.dtype)
    model = AcousticTracking(sigma_w=a.sigma_w).to(dtype)
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(a.trials, a.steps, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    filters = {
        "PF-PF(LEDH)": ParticleFlowParticleFilter(model, flow="ledh", n_particles=a.particles),
        "PF-PF(EDH)": ParticleFlowParticleFilter(model, flow="edh", n_particles=a.particles),
        "BPF": BootstrapParticleFilter(model, n_particles=a.particles),
    }
    rows = []
    with torch.no_grad():
        for name, f in filters.items():
            f(traj.observations[:2, :1], mean[:2], cov[:2], g)  # warm-up
            t0 = time.perf_counter()
            res = f(traj.observations, mean, cov, g)
            dt = time.perf_counter() - t0
            om = metrics.omat(model.positions(res.estimates), model.positions(traj.states[:, 1:])).mean()
            rows.append({"filter": name, "N": a.particles, "sec_per_trial_step": dt / (a.trials * a.steps),
                         "whole_run_s": dt, "omat": float(om), "ess": float(res.ess.mean())})
            print(rows[-1], flush=True)
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    head = (f"Machine: {platform.platform()}, {os.cpu_count()} CPUs, torch {torch.__version__} "
            f"({torch.get_num_threads()} threads), load {load}\n"
            f"Acoustic sigma_w={a.sigma_w}, {a.trials} trials x {a.steps} steps, {a.dtype}.\n"
            f"Command: `python experiments/benchmarks/bench_pfpf.py {' '.join(sys.argv[1:])}`\n\n")
    table = "| filter | N | s / trial-step | whole run (s) | OMAT (m) | mean ESS |\n|---|---|---|---|---|---|\n"
    table += "\n".join(f"| {r['filter']} | {r['N']} | {r['sec_per_trial_step']:.4g} | {r['whole_run_s']:.1f} | "
                       f"{r['omat']:.3f} | {r['ess']:.1f} |" for r in rows)
    Path(a.out).write_text("## PF-PF benchmark\n\n" + head + table + "\n")
    Path(a.out).with_suffix(".json").write_text(json.dumps({"args": vars(a), "rows": rows}, indent=2))
    print(head + table)


if __name__ == "__main__":
    main()
