"""Gaussian-sum benchmark: seconds per trial-step of the PFGSPF (G components x N* particles) against
PF-PF(LEDH), the GSPF without flow and the BPF, each with the same total particle count G N*, on the
skewed-t / Poisson model (d = 144; issue 13's benchmark row) in one run.

    python -m experiments.benchmarks.bench_gaussian_sum                  # G = 5 x 200, 1 trial, 2 steps
    python -m experiments.benchmarks.bench_gaussian_sum --d 16 --components 3 --per-component 100 --quick

Every filter runs the same simulated data after an untimed one-step warm-up; times are whole filter
calls divided by trials x steps (min over ``--reps``). In d = 144 the LEDH-based filters solve a
144 x 144 system per particle and pseudo-time step (29 of them), which dominates their cost.
"""
from __future__ import annotations

from torchflow.models import SkewedTPoisson

from . import harness as h

FILTERS = ("pfgspf", "pfpf_ledh", "gspf", "bpf")


def run(argv=None) -> dict:
    """Run the benchmark (``argv``: CLI options); writes no files. Returns ``{"rows", "markdown", ...}``."""
    ap = h.parser(__doc__, "d = 16, G = 2 x 20, 1 step")
    ap.add_argument("--d", type=int, default=144, help="state dimension (a perfect square)")
    ap.add_argument("--components", type=int, default=5, help="G")
    ap.add_argument("--per-component", type=int, default=200, help="N*")
    ap.add_argument("--trials", type=int, default=1)
    ap.add_argument("--steps", type=int, default=2)
    ap.add_argument("--reps", type=int, default=1)
    ap.add_argument("--filters", default=",".join(FILTERS))
    a = ap.parse_args(argv)
    if a.quick:
        a.d, a.components, a.per_component, a.steps = 16, 2, 20, 1
    G, n = a.components, a.per_component
    total = G * n
    keys = h.keys_option(a.filters, FILTERS)
    model = SkewedTPoisson(d=a.d)
    traj, mean, cov = h.simulate(model, a.trials, a.steps, 0)
    mixture = dict(n_components=G, particles_per_component=n)
    info = h.machine(command=h.command("bench_gaussian_sum", argv))
    rows = []
    for key in keys:
        f = h.make_filter(key, model, **(mixture if "gspf" in key else dict(n_particles=total)))
        label = f"{h.LABELS[key.removeprefix('pfpf_')]} " + (f"({n} x {G})" if "gspf" in key else f"({total})")
        every = h.streams(0, f.stream_name)
        t = h.time_filter(f, traj.observations, mean, cov, None, every, warm=(None, 1), repeats=a.reps)
        mse = float((t.result[0].estimates - traj.states[:, 1:]).pow(2).mean())
        rows.append(dict(filter=label, key=key, particles=total, s_per_trial_step=t.min / (a.trials * a.steps),
                         mse=mse))
    info["load_end"] = h.loadavg()
    ref = next((r["s_per_trial_step"] for r in rows if r["key"] == "pfpf_ledh"), None)
    for r in rows:
        r["ratio_to_pfpf_ledh"] = None if ref is None else r["s_per_trial_step"] / ref
    lines = h.header(f"# Gaussian-sum benchmark: skewed-t / Poisson, d = {a.d}, {a.trials} trial(s) x {a.steps} "
                     "step(s)", a.quick, info)
    lines += h.md_table(["filter", "particles", "s per trial-step", "ratio to PF-PF(LEDH)", "MSE (these steps)"],
                        [[r["filter"], r["particles"], f"{r['s_per_trial_step']:.4g}",
                          "" if r["ratio_to_pfpf_ledh"] is None else f"{r['ratio_to_pfpf_ledh']:.2f}", f"{r['mse']:.3f}"] for r in rows])
    return {"rows": rows, "markdown": "\n".join(lines) + "\n", "args": vars(a), "machine": info}


if __name__ == "__main__":
    h.main(run, "gaussian_sum")
