"""PF-PF benchmark: seconds per trial-step of the PF-PFs (LEDH, EDH, Gromov, Geodesic, optimised
diffusion) and the BPF on acoustic tracking.

    python -m experiments.benchmarks.bench_pfpf                 # 100 trials, N=500, 5 steps, float64
    python -m experiments.benchmarks.bench_pfpf --steps 40 --quick
    python -m experiments.benchmarks.bench_pfpf --chunk 100     # all trials in one call

Times are for whole filter calls after an untimed warm-up, over trials in chunks of each filter's
preferred size (``--chunk`` overrides; local flows prefer 1e4 points per call), divided by
trials x steps, i.e. comparable with the per-step times the papers report for a single run
(MATLAB, 0.9-3.5 s per step for PF-PF(LEDH) N=500, 1.3 s for PF-PF(Gromov)).
"""
from __future__ import annotations

import torch

from torchflow import metrics
from torchflow.models import AcousticTracking

from . import harness as h

FILTERS = ("ledh", "edh", "gromov", "geodesic", "osd", "bpf")


def run(argv=None) -> dict:
    """Run the benchmark (``argv``: CLI options); writes no files. Returns ``{"rows", "markdown", "args", ...}``."""
    ap = h.parser(__doc__, "10 trials, 3 steps")
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--particles", type=int, default=500)
    ap.add_argument("--dtype", default="float64", choices=["float64", "float32"])
    ap.add_argument("--sigma-w", type=float, default=0.1)
    ap.add_argument("--chunk", type=int, default=None, help="trials per filter call (default: filter's choice)")
    ap.add_argument("--filters", default=",".join(FILTERS), help=f"comma-separated subset of {','.join(FILTERS)}")
    a = ap.parse_args(argv)
    if a.quick:
        a.trials, a.steps = 10, 3
    keys = h.keys_option(a.filters, FILTERS)
    model = AcousticTracking(sigma_w=a.sigma_w).to(getattr(torch, a.dtype))
    traj, mean, cov = h.simulate(model, a.trials, a.steps, 0)
    info = h.machine(command=h.command("bench_pfpf", argv))
    rows = []
    for key in keys:
        f = h.make_filter(key, model, a.particles)
        chunk = min(a.chunk or f.preferred_chunk_trials(a.particles) or a.trials, a.trials)
        t = h.time_filter(f, traj.observations, mean, cov, chunk, h.streams(0, f.stream_name),  # as the runner
                          warm=(2, 1), warm_randomness=lambda s, e: torch.Generator().manual_seed(0))
        est, ess = torch.cat([r.estimates for r in t.result]), torch.cat([r.ess for r in t.result])
        om = metrics.omat(model.positions(est), model.positions(traj.states[:, 1:])).mean()
        rows.append({"filter": h.LABELS[key], "N": a.particles, "chunk": chunk,
                     "sec_per_trial_step": t.min / (a.trials * a.steps), "whole_run_s": t.min,
                     "omat": float(om), "ess": float(ess.mean())})
        print(rows[-1], flush=True)
    info["load_end"] = h.loadavg()
    ref = next((r["sec_per_trial_step"] for r in rows if r["filter"] == "PF-PF(LEDH)"), None)
    for r in rows:
        r["vs_ledh"] = r["sec_per_trial_step"] / ref if ref else None
    md = h.header("## PF-PF benchmark", a.quick, info,
                  f"Acoustic sigma_w={a.sigma_w}, {a.trials} trials x {a.steps} steps, {a.dtype}.")
    md += h.md_table(["filter", "N", "trials per call", "s / trial-step", "time / PF-PF(LEDH)", "whole run (s)",
                      "OMAT (m)", "mean ESS"],
                     [[r["filter"], r["N"], r["chunk"], f"{r['sec_per_trial_step']:.4g}", h.fmt(r["vs_ledh"], "{:.2f}"),
                       f"{r['whole_run_s']:.1f}", f"{r['omat']:.3f}", f"{r['ess']:.1f}"] for r in rows])
    return {"machine": info, "rows": rows, "markdown": "\n".join(md) + "\n", "args": vars(a)}


if __name__ == "__main__":
    h.main(run, "pfpf")
