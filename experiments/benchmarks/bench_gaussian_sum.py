"""Gaussian-sum benchmark: seconds per trial-step of the PFGSPF (G components x N* particles) against
PF-PF(LEDH), the GSPF without flow and the BPF, each with the same total particle count G N*, on the
skewed-t / Poisson model (d = 144; issue 13's benchmark row) in one run.

    python experiments/benchmarks/bench_gaussian_sum.py                       # G = 5 x 200, 1 trial, 2 steps
    python experiments/benchmarks/bench_gaussian_sum.py --d 16 --components 3 --per-component 100 --quick

Every filter runs the same simulated data after an untimed one-step warm-up; times are whole filter
calls divided by trials x steps (min over ``--reps``). In d = 144 the LEDH-based filters solve a
144 x 144 system per particle and pseudo-time step (29 of them), which dominates their cost.
"""
from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from _common import loadavg, write_results  # noqa: E402
from torchflow.filters import (BootstrapParticleFilter, GaussianSumParticleFilter,  # noqa: E402
                               ParticleFlowGaussianSumParticleFilter, ParticleFlowParticleFilter)
from torchflow.models import SkewedTPoisson  # noqa: E402
from torchflow.random import TrialStreams  # noqa: E402


def run(argv=None) -> dict:
    """Run the benchmark (``argv``: CLI options); writes no files. Returns ``{"rows", "markdown", ...}``."""
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--d", type=int, default=144, help="state dimension (a perfect square)")
    ap.add_argument("--components", type=int, default=5, help="G")
    ap.add_argument("--per-component", type=int, default=200, help="N*")
    ap.add_argument("--trials", type=int, default=1)
    ap.add_argument("--steps", type=int, default=2)
    ap.add_argument("--reps", type=int, default=1)
    ap.add_argument("--filters", default="pfgspf,pfpf_ledh,gspf,bpf")
    ap.add_argument("--quick", action="store_true", help="d = 16, G = 2 x 20, 1 step")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    if a.quick:
        a.d, a.components, a.per_component, a.steps = 16, 2, 20, 1
    G, n = a.components, a.per_component
    total = G * n
    model = SkewedTPoisson(d=a.d)
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(a.trials, a.steps, g)
    mean, cov = model.initial_belief(traj.states[:, 0])
    makers = {
        "pfgspf": (f"PFGSPF ({n} x {G})", lambda: ParticleFlowGaussianSumParticleFilter(
            model, n_components=G, particles_per_component=n)),
        "pfpf_ledh": (f"PF-PF(LEDH) ({total})", lambda: ParticleFlowParticleFilter(model, flow="ledh", n_particles=total)),
        "gspf": (f"GSPF ({n} x {G})", lambda: GaussianSumParticleFilter(model, n_components=G, particles_per_component=n)),
        "bpf": (f"BPF ({total})", lambda: BootstrapParticleFilter(model, n_particles=total)),
    }
    rows = []
    load0 = loadavg()
    for key in a.filters.split(","):
        if key not in makers:
            sys.exit(f"--filters: unknown {key!r}; expected a subset of {','.join(makers)}")
        label, make = makers[key]
        f = make()
        with torch.no_grad():
            f(traj.observations[:, :1], mean, cov, TrialStreams(0, range(a.trials), f.stream_name))  # warm-up
            times = []
            for _ in range(a.reps):
                t0 = time.perf_counter()
                res = f(traj.observations, mean, cov, TrialStreams(0, range(a.trials), f.stream_name))
                times.append((time.perf_counter() - t0) / (a.trials * a.steps))
        mse = float((res.estimates - traj.states[:, 1:]).pow(2).mean())
        rows.append(dict(filter=label, key=key, particles=total, s_per_trial_step=min(times), mse=mse))
    ref = next((r["s_per_trial_step"] for r in rows if r["key"] == "pfpf_ledh"), None)
    for r in rows:
        r["ratio_to_pfpf_ledh"] = None if ref is None else r["s_per_trial_step"] / ref
    machine = dict(platform=platform.platform(), torch=torch.__version__, torch_threads=torch.get_num_threads(),
                   load_start=load0, load_end=loadavg())
    lines = [f"# Gaussian-sum benchmark: skewed-t / Poisson, d = {a.d}, {a.trials} trial(s) x {a.steps} step(s)",
             "", f"Machine: {machine}", "",
             "| filter | particles | s per trial-step | ratio to PF-PF(LEDH) | MSE (these steps) |", "|---|---|---|---|---|"]
    for r in rows:
        ratio = "" if r["ratio_to_pfpf_ledh"] is None else f"{r['ratio_to_pfpf_ledh']:.2f}"
        lines.append(f"| {r['filter']} | {r['particles']} | {r['s_per_trial_step']:.4g} | {ratio} | {r['mse']:.3f} |")
    return {"rows": rows, "markdown": "\n".join(lines) + "\n", "args": vars(a), "machine": machine}


if __name__ == "__main__":
    ns = argparse.Namespace(quick="--quick" in sys.argv, out=None)
    if "--out" in sys.argv:
        ns.out = sys.argv[sys.argv.index("--out") + 1]
    write_results(run(), "gaussian_sum", quick=ns.quick, out=ns.out)
