"""Gaussian-sum benchmark: seconds per trial-step of the PFGSPF (G components x N* particles)
against PF-PF(LEDH), the GSPF and the BPF with the same total G N* particles on the skewed-t / Poisson
model, d = 144, the same data, after an untimed one-step warm-up (min over ``--reps``).

    python -m experiments.benchmarks.bench_gaussian_sum                  # G = 5 x 200, 1 trial, 2 steps
"""

from __future__ import annotations

from torchflow.models import SkewedTPoisson

from . import harness as h

FILTERS = ("pfgspf", "pfpf_ledh", "gspf", "bpf")


def run(argv=None) -> dict:
    """Run the benchmark (``argv``: CLI options); writes no files. Returns ``{"rows", "markdown", ...}``."""
    a = h.options(
        __doc__,
        argv,
        dict(d=16, components=2, per_component=20, steps=1),
        d=144,
        components=5,
        per_component=200,
        trials=1,
        steps=2,
        reps=1,
        filters=",".join(FILTERS),
    )
    G, n, total = a.components, a.per_component, a.components * a.per_component
    keys = h.keys_option(a.filters, FILTERS)
    model = SkewedTPoisson(d=a.d)
    traj, mean, cov = h.simulate(model, a.trials, a.steps, 0)
    rows = []
    with h.session("bench_gaussian_sum", argv) as info:
        for key in keys:
            f = h.make_filter(
                key,
                model,
                **(dict(n_components=G, particles_per_component=n) if "gspf" in key else dict(n_particles=total)),
            )
            label = f"{h.LABELS[key.removeprefix('pfpf_')]} " + (f"({n} x {G})" if "gspf" in key else f"({total})")
            t = h.time_filter(
                f, traj.observations, mean, cov, None, h.streams(0, f.stream_name), warm=(None, 1), repeats=a.reps
            )
            mse = float((t.result[0].estimates - traj.states[:, 1:]).pow(2).mean())
            rows.append(
                dict(filter=label, key=key, particles=total, s_per_trial_step=t.min / (a.trials * a.steps), mse=mse)
            )
    ref = next((r["s_per_trial_step"] for r in rows if r["key"] == "pfpf_ledh"), None)
    for r in rows:
        r["ratio_to_pfpf_ledh"] = None if ref is None else r["s_per_trial_step"] / ref
    md = h.report(
        f"# Gaussian-sum benchmark: skewed-t / Poisson, d = {a.d}, {a.trials} trial(s) x {a.steps} step(s)",
        a,
        info,
        [],
        ["filter", "particles", "s per trial-step", "ratio to PF-PF(LEDH)", "MSE (these steps)"],
        [
            [
                r["filter"],
                r["particles"],
                f"{r['s_per_trial_step']:.4g}",
                h.fmt(r["ratio_to_pfpf_ledh"], "{:.2f}"),
                f"{r['mse']:.3f}",
            ]
            for r in rows
        ],
    )
    return {"rows": rows, "markdown": md, "args": vars(a), "machine": info}


if __name__ == "__main__":
    h.main(run, "gaussian_sum")
