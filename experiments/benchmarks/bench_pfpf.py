"""PF-PF benchmark: seconds per trial-step of the PF-PFs (LEDH, EDH, Gromov, Geodesic, optimised
diffusion) and the BPF on acoustic tracking: whole calls after an untimed warm-up, in each filter's
preferred chunk of trials (``--chunk`` overrides), over trials x steps, comparable with the papers'
per-step times of one run (MATLAB: 0.9-3.5 s for PF-PF(LEDH) N=500, 1.3 s for PF-PF(Gromov)).

    python -m experiments.benchmarks.bench_pfpf                 # 100 trials, N=500, 5 steps, float64

GPFIS (its autodiff Jacobian makes it an order of magnitude dearer) runs on the first ``--gpfis-trials``
trials only (default 10); its s / trial-step is comparable with the others', its OMAT and ESS are over
those trials. Goal (the CPU speed goal): GPFIS <= 5x PF-PF(LEDH) per trial-step.
"""

from __future__ import annotations

import torch

from torchflow.core import metrics
from torchflow.models import AcousticTracking

from . import harness as h

FILTERS = ("ledh", "edh", "gromov", "geodesic", "osd", "gpfis", "bpf")
GPFIS_GOAL = 5.0


def run(argv=None) -> dict:
    """Run the benchmark (``argv``: CLI options); writes no files. Returns ``{"rows", "markdown", "args", ...}``."""
    a = h.options(
        __doc__,
        argv,
        dict(trials=10, steps=3, gpfis_trials=2),
        trials=100,
        steps=5,
        particles=500,
        dtype="float64",
        sigma_w=0.1,
        chunk=None,
        filters=",".join(FILTERS),
        gpfis_trials=10,
    )
    keys = h.keys_option(a.filters, FILTERS)
    model = AcousticTracking(sigma_w=a.sigma_w).to(getattr(torch, a.dtype))
    traj, mean, cov = h.simulate(model, a.trials, a.steps, 0)
    rows = []
    with h.session("bench_pfpf", argv) as info:
        for key in keys:
            f = h.make_filter(key, model, a.particles)
            B = min(a.gpfis_trials, a.trials) if key == "gpfis" else a.trials
            chunk = min(a.chunk or f.preferred_chunk_trials(a.particles) or B, B)
            t = h.time_filter(
                f,
                traj.observations[:B],
                mean[:B],
                cov[:B],
                chunk,
                h.streams(0, f.stream_name),
                warm=(2, 1),
                warm_randomness=lambda s, e: torch.Generator().manual_seed(0),
            )  # as the runner
            est, ess = torch.cat([r.estimates for r in t.result]), torch.cat([r.ess for r in t.result])
            om = metrics.omat(model.positions(est), model.positions(traj.states[:B, 1:])).mean()
            rows.append(
                {
                    "filter": h.LABELS[key],
                    "N": a.particles,
                    "chunk": chunk,
                    "trials": B,
                    "sec_per_trial_step": t.min / (B * a.steps),
                    "whole_run_s": t.min,
                    "omat": float(om),
                    "ess": float(ess.mean()),
                }
            )
            print(rows[-1], flush=True)
    ref = next((r["sec_per_trial_step"] for r in rows if r["filter"] == "PF-PF(LEDH)"), None)
    for r in rows:
        r["vs_ledh"] = r["sec_per_trial_step"] / ref if ref else None
        r["goal"] = GPFIS_GOAL if r["filter"] == "GPFIS" and ref else None
        r["met"] = r["vs_ledh"] <= GPFIS_GOAL if r["goal"] else None
    md = h.report(
        "## PF-PF benchmark",
        a,
        info,
        [
            f"Acoustic sigma_w={a.sigma_w}, {a.trials} trials x {a.steps} "
            f"steps (GPFIS: the first {min(a.gpfis_trials, a.trials)}), {a.dtype}."
        ],
        [
            "filter",
            "N",
            "trials",
            "trials per call",
            "s / trial-step",
            "time / PF-PF(LEDH)",
            "goal",
            "met",
            "whole run (s)",
            "OMAT (m)",
            "mean ESS",
        ],
        [
            [
                r["filter"],
                r["N"],
                r["trials"],
                r["chunk"],
                f"{r['sec_per_trial_step']:.4g}",
                h.fmt(r["vs_ledh"], "{:.2f}"),
                h.fmt(r["goal"], "<= {:.0f}x"),
                h.met_cell(r["met"]),
                f"{r['whole_run_s']:.1f}",
                f"{r['omat']:.3f}",
                f"{r['ess']:.1f}",
            ]
            for r in rows
        ],
    )
    return {"machine": info, "rows": rows, "markdown": md, "args": vars(a)}


if __name__ == "__main__":
    h.main(run, "pfpf")
