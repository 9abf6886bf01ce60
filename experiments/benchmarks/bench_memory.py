"""Large-N runs under a memory budget: the bootstrap PF with 1e6 particles and PF-PF(LEDH) with 1e4
particles on acoustic tracking, through the experiment runner (:func:`torchflow.experiment.run_experiment`)
with ``memory_budget_gb``: the runner picks the chunk of trials and, when one trial does not fit,
the filter's particle chunk (:meth:`~torchflow.filters.base.ParticleFilterBase.plan_memory`).

    python -m experiments.benchmarks.bench_memory                     # both cases, 1 trial x 40 steps
    python -m experiments.benchmarks.bench_memory --cases bpf --particles-bpf 1e5 --steps 5

Each case runs in its own process, so its peak resident memory (``ru_maxrss``) is its own. Reports
the wall time per step, peak RSS, the particle chunk chosen, the library's own per-trial memory
estimate, and tracking accuracy (OMAT, metres).
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys

from . import harness as h

CASES = {"bpf": "BPF", "ledh": "PF-PF(LEDH)", "gromov": "PF-PF(Gromov)"}


def _case(a) -> dict:
    """Run one case in this process and return its numbers."""
    from torchflow.experiment import run_experiment
    from torchflow.models import AcousticTracking

    with h.torch_threads(a.threads):
        model = AcousticTracking(sigma_w=a.sigma_w)
        N = int(float(a.particles_bpf if a.case == "bpf" else a.particles_flow))
        f = h.make_filter(a.case, model, N)
        est_gb = f.bytes_per_trial(N) / 2**30
        t = h.time_calls(lambda: run_experiment(model, {CASES[a.case]: f}, trials=a.trials, steps=a.steps,
                                                seed=a.seed, memory_budget_gb=a.memory_gb, progress=False,
                                                device=a.device, dtype=a.dtype))
    res, wall = t.result, t.min
    row = res.summary[0]
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB -> GiB (Linux)
    return dict(case=a.case, filter=CASES[a.case], particles=N, trials=a.trials, steps=a.steps,
                memory_budget_gb=a.memory_gb, estimate_gb_per_trial=est_gb,
                particle_chunk=res.config["particle_chunk"][CASES[a.case]],
                trial_chunk=res.config["chunk_size"][CASES[a.case]], wall_s=wall,
                s_per_step=wall / (a.trials * a.steps), peak_rss_gb=peak,
                omat=row.get("omat"), ospa=row.get("ospa"), ess=row.get("ess"),
                repaired=row.get("repaired", row.get("n_repaired")), dtype=a.dtype, device=a.device)


def parse(argv=None):
    ap = h.parser(__doc__, "1e5 / 2e3 particles, 3 steps")
    ap.add_argument("--cases", default="bpf,ledh", help=f"comma list of {sorted(CASES)}")
    ap.add_argument("--case", default=None, help=argparse.SUPPRESS)  # child process
    ap.add_argument("--particles-bpf", default="1e6")
    ap.add_argument("--particles-flow", default="1e4")
    ap.add_argument("--trials", type=int, default=1)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--memory-gb", type=float, default=4.0, help="the runner's memory budget")
    ap.add_argument("--sigma-w", type=float, default=0.1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--dtype", default="float64")
    a = ap.parse_args(argv)
    if a.quick:
        a.particles_bpf, a.particles_flow, a.steps = "1e5", "2e3", 3
    return a


def run(argv=None) -> dict:
    argv = list(argv or [])
    a = parse(argv)
    info = h.machine(a.device, command=h.command("bench_memory", argv))
    rows = []
    for case in h.keys_option(a.cases, CASES, "--cases"):
        cmd = [sys.executable, "-m", __spec__.name, *argv, "--case", case]
        p = subprocess.run(cmd, capture_output=True, text=True, cwd=h.HERE.parents[1])
        if p.returncode != 0:
            rows.append(dict(case=case, filter=CASES[case], error=(p.stderr or p.stdout)[-600:]))
        else:
            rows.append(json.loads(p.stdout.strip().splitlines()[-1]))
        print(f"[memory] {rows[-1]}")
    info["load_end"] = h.loadavg()
    return dict(rows=rows, machine=info, markdown=markdown(rows, info, a), args=vars(a))


def markdown(rows, info, a) -> str:
    lines = h.header("## Large-N runs under a memory budget", a.quick, info,
                     f"Acoustic tracking sigma_w = {a.sigma_w}, {a.trials} trial(s) x {a.steps} steps, {a.dtype}, "
                     f"runner memory budget {a.memory_gb} GiB.")
    lines += h.md_table(
        ["filter", "N", "particle chunk", "estimate GiB / trial", "peak RSS GiB", "s / step", "whole run (s)",
         "OMAT (m)", "mean ESS"],
        [[r["filter"]] + ["-"] * 5 + [f"failed: {r['error'][-200:]!r}", "-", "-"] if "error" in r else
         [r["filter"], f"{r['particles']:.0e}", r["particle_chunk"] or "all", f"{r['estimate_gb_per_trial']:.2f}",
          f"{r['peak_rss_gb']:.2f}", f"{r['s_per_step']:.3g}", f"{r['wall_s']:.1f}", f"{r['omat']:.3f}",
          f"{r['ess']:.1f}"] for r in rows])
    lines += ["", "- Peak RSS is the child process's maximum resident set (Python, torch and data included)."]
    return "\n".join(lines) + "\n"


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    a = parse(argv)
    if a.case:  # child: one case, JSON on the last line of stdout
        print(json.dumps(_case(a)))
        return
    h.main(run, "memory", argv)


if __name__ == "__main__":
    main()
