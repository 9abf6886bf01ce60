"""Large-N runs under a memory budget: the BPF with 1e6 particles and PF-PF(LEDH) with 1e4 on acoustic
tracking through ``run_experiment(memory_budget_gb=...)``, which picks the chunk of trials and, when one
trial does not fit, the particle chunk. Each case runs in its own process (its own peak RSS).

    python -m experiments.benchmarks.bench_memory                     # both cases, 1 trial x 40 steps
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys

from . import harness as h

CASES = {"bpf": "BPF", "ledh": "PF-PF(LEDH)", "gromov": "PF-PF(Gromov)"}


def _case(a) -> dict:
    """Run one case in this process and return its numbers."""
    from torchflow.app.runner import run_experiment
    from torchflow.models import AcousticTracking

    with h.torch_threads(a.threads):
        model = AcousticTracking(sigma_w=a.sigma_w)
        N = int(float(a.particles_bpf if a.case == "bpf" else a.particles_flow))
        f = h.make_filter(a.case, model, N)
        est_gb = f.bytes_per_trial(N) / 2**30
        t = h.time_calls(
            lambda: run_experiment(
                model,
                {CASES[a.case]: f},
                trials=a.trials,
                steps=a.steps,
                seed=a.seed,
                memory_budget_gb=a.memory_gb,
                progress=False,
                device=a.device,
                dtype=a.dtype,
            )
        )
    res, wall, row = t.result, t.min, t.result.summary[0]
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB -> GiB (Linux)
    return dict(
        case=a.case,
        filter=CASES[a.case],
        particles=N,
        trials=a.trials,
        steps=a.steps,
        memory_budget_gb=a.memory_gb,
        estimate_gb_per_trial=est_gb,
        particle_chunk=res.config["particle_chunk"][CASES[a.case]],
        trial_chunk=res.config["chunk_size"][CASES[a.case]],
        wall_s=wall,
        s_per_step=wall / (a.trials * a.steps),
        peak_rss_gb=peak,
        omat=row.get("omat"),
        ospa=row.get("ospa"),
        ess=row.get("ess"),
        repaired=row.get("repaired", row.get("n_repaired")),
        dtype=a.dtype,
        device=a.device,
    )


def parse(argv):
    return h.options(
        __doc__,
        argv,
        dict(particles_bpf="1e5", particles_flow="2e3", steps=3),
        cases="bpf,ledh",
        case=None,
        particles_bpf="1e6",
        particles_flow="1e4",
        trials=1,
        steps=40,
        memory_gb=4.0,
        sigma_w=0.1,
        seed=0,
        threads=None,
        device="cpu",
        dtype="float64",
    )  # case: a child's one case


def run(argv=None) -> dict:
    argv = list(argv or [])
    a = parse(argv)
    rows = []
    with h.session("bench_memory", argv, device=a.device) as info:
        for case in h.keys_option(a.cases, CASES, "--cases"):
            cmd = [sys.executable, "-m", __spec__.name, *argv, "--case", case]
            p = subprocess.run(cmd, capture_output=True, text=True, cwd=h.HERE.parents[1])
            rows.append(
                json.loads(p.stdout.strip().splitlines()[-1])
                if p.returncode == 0
                else dict(case=case, filter=CASES[case], error=(p.stderr or p.stdout)[-600:])
            )
            print(f"[memory] {rows[-1]}")
    md = h.report(
        "## Large-N runs under a memory budget",
        a,
        info,
        [
            f"Acoustic tracking sigma_w = {a.sigma_w}, {a.trials} trial(s) x {a.steps} steps, {a.dtype}, "
            f"runner memory budget {a.memory_gb} GiB."
        ],
        [
            "filter",
            "N",
            "particle chunk",
            "estimate GiB / trial",
            "peak RSS GiB",
            "s / step",
            "whole run (s)",
            "OMAT (m)",
            "mean ESS",
        ],
        [
            [r["filter"]] + ["-"] * 5 + [f"failed: {r['error'][-200:]!r}", "-", "-"]
            if "error" in r
            else [
                r["filter"],
                f"{r['particles']:.0e}",
                r["particle_chunk"] or "all",
                f"{r['estimate_gb_per_trial']:.2f}",
                f"{r['peak_rss_gb']:.2f}",
                f"{r['s_per_step']:.3g}",
                f"{r['wall_s']:.1f}",
                f"{r['omat']:.3f}",
                f"{r['ess']:.1f}",
            ]
            for r in rows
        ],
        "- Peak RSS is the child process's maximum resident set (Python, torch and data included).",
    )
    return dict(rows=rows, machine=info, markdown=md, args=vars(a))


if __name__ == "__main__":
    if parse(sys.argv[1:]).case:  # a child: one case, JSON on the last line of stdout
        print(json.dumps(_case(parse(sys.argv[1:]))))
    else:
        h.main(run, "memory")
