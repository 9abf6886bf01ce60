"""PF-PF benchmark: seconds per trial-step of the PF-PFs (LEDH, EDH, Gromov, Geodesic, optimised
diffusion) and the BPF on acoustic tracking.

    python experiments/benchmarks/bench_pfpf.py                 # 100 trials, N=500, 5 steps, float64
    python experiments/benchmarks/bench_pfpf.py --steps 40 --quick
    python experiments/benchmarks/bench_pfpf.py --chunk 100     # all trials in one call

Times are for whole filter calls after an untimed warm-up, over trials in chunks of each filter's
preferred size (``--chunk`` overrides; local flows prefer 1e4 points per call), divided by
trials x steps, i.e. comparable with the per-step times the papers report for a single run
(MATLAB, 0.9-3.5 s per step for PF-PF(LEDH) N=500, 1.3 s for PF-PF(Gromov)).
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from torchflow.random import TrialStreams  # noqa: E402
from torchflow.filters import BootstrapParticleFilter, ParticleFlowParticleFilter  # noqa: E402
from torchflow.models import AcousticTracking  # noqa: E402
from torchflow import metrics  # noqa: E402


def run(argv=None) -> dict:
    """Run the benchmark (``argv``: CLI options); writes no files. Returns ``{"rows", "markdown", "args"}``."""
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--particles", type=int, default=500)
    ap.add_argument("--dtype", default="float64", choices=["float64", "float32"])
    ap.add_argument("--sigma-w", type=float, default=0.1)
    ap.add_argument("--chunk", type=int, default=None, help="trials per filter call (default: filter's choice)")
    ap.add_argument("--filters", default="ledh,edh,gromov,geodesic,osd,bpf",
                    help="comma-separated subset of ledh,edh,gromov,geodesic,osd,bpf")
    ap.add_argument("--quick", action="store_true", help="10 trials, 3 steps")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    if a.quick:
        a.trials, a.steps = 10, 3
    dtype = getattr(torch, a.dtype)
    model = AcousticTracking(sigma_w=a.sigma_w).to(dtype)
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(a.trials, a.steps, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    names = {"ledh": "PF-PF(LEDH)", "edh": "PF-PF(EDH)", "gromov": "PF-PF(Gromov)", "geodesic": "PF-PF(Geodesic)",
             "osd": "PF-PF(OSD)", "bpf": "BPF"}
    filters = {}
    for key in a.filters.split(","):
        if key not in names:
            sys.exit(f"--filters: unknown {key!r}; expected a subset of {','.join(names)}")
        filters[names[key]] = (BootstrapParticleFilter(model, n_particles=a.particles) if key == "bpf"
                               else ParticleFlowParticleFilter(model, flow=key, n_particles=a.particles))
    rows = []
    with torch.no_grad():
        for name, f in filters.items():
            chunk = a.chunk or f.preferred_chunk_trials(a.particles) or a.trials
            f(traj.observations[:2, :1], mean[:2], cov[:2], g)  # warm-up
            est, ess, dt = [], [], 0.0
            for i in range(0, a.trials, chunk):
                sl = slice(i, i + chunk)
                t0 = time.perf_counter()
                streams = TrialStreams(0, range(i, min(i + chunk, a.trials)), key=f.stream_name)  # as the runner
                res = f(traj.observations[sl], mean[sl], cov[sl], streams)
                dt += time.perf_counter() - t0
                est.append(res.estimates)
                ess.append(res.ess)
            est, ess = torch.cat(est), torch.cat(ess)
            om = metrics.omat(model.positions(est), model.positions(traj.states[:, 1:])).mean()
            rows.append({"filter": name, "N": a.particles, "chunk": min(chunk, a.trials),
                         "sec_per_trial_step": dt / (a.trials * a.steps),
                         "whole_run_s": dt, "omat": float(om), "ess": float(ess.mean())})
            print(rows[-1], flush=True)
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    head = (f"Machine: {platform.platform()}, {os.cpu_count()} CPUs, torch {torch.__version__} "
            f"({torch.get_num_threads()} threads), load {load}\n"
            f"Acoustic sigma_w={a.sigma_w}, {a.trials} trials x {a.steps} steps, {a.dtype}.\n"
            f"Command: `python experiments/benchmarks/bench_pfpf.py {' '.join(argv)}`\n\n")
    ref = next((r["sec_per_trial_step"] for r in rows if r["filter"] == "PF-PF(LEDH)"), None)
    for r in rows:
        r["vs_ledh"] = r["sec_per_trial_step"] / ref if ref else float("nan")
    table = ("| filter | N | trials per call | s / trial-step | time / PF-PF(LEDH) | whole run (s) | OMAT (m) | mean ESS |\n"
             "|---|---|---|---|---|---|---|---|\n")
    table += "\n".join(f"| {r['filter']} | {r['N']} | {r['chunk']} | {r['sec_per_trial_step']:.4g} | {r['vs_ledh']:.2f} | "
                       f"{r['whole_run_s']:.1f} | "
                       f"{r['omat']:.3f} | {r['ess']:.1f} |" for r in rows)
    md = "## PF-PF benchmark" + (" (--quick)" if a.quick else "") + "\n\n" + head + table + "\n"
    return {"rows": rows, "markdown": md, "args": vars(a)}


def main(argv=None):
    res = run(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _common import write_results

    write_results(res, "pfpf", res["args"]["quick"], res["args"]["out"])


if __name__ == "__main__":
    main()
