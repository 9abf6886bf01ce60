"""Cost of per-trial random streams: the same filter calls with one ``torch.Generator`` per call and
with ``TrialStreams`` (one stream per trial, as ``run_experiment``), interleaved; then the draws alone.

    python -m experiments.benchmarks.bench_streams            # ~3 min on 2 cores
"""

from __future__ import annotations

import torch

from torchflow.core import linalg
from torchflow.core.random import TrialStreams
from torchflow.models import AcousticTracking, SensorNetwork

from . import harness as h


def cases(quick: bool):
    """``(name, model, filter, trials, steps)`` of each case."""
    lg, ac = SensorNetwork(d=64), AcousticTracking(sigma_w=0.1)
    s = 0.25 if quick else 1.0
    return [
        ("BPF, LG d=64, N=200", lg, h.make_filter("bpf", lg, 200), int(100 * s), 10),
        ("BPF, LG d=64, N=1e4", lg, h.make_filter("bpf", lg, 10_000), max(3, int(12 * s)), 10),
        ("PF-PF(LEDH), acoustic, N=500", ac, h.make_filter("ledh", ac, 500), max(2, int(8 * s)), 5),
        ("PF-PF(Gromov), acoustic, N=500", ac, h.make_filter("gromov", ac, 500), max(2, int(8 * s)), 5),
    ]


def run(argv=None) -> dict:
    a = h.options(__doc__, argv, None, repeats=5, threads=2)
    rows, draws = [], []
    with h.session("bench_streams", argv, a.threads) as info:
        for name, model, f, B, T in cases(a.quick):
            traj, mean, cov = h.simulate(model, B, T, 0)
            chunk = f.preferred_chunk_trials() or B
            kinds = {"generator": lambda s, e: torch.Generator().manual_seed(s), "streams": h.streams(0, f.stream_name)}
            h.filter_chunks(f, traj.observations[:1], mean[:1], cov[:1], chunk, kinds["streams"])  # warm-up
            best = {k: float("inf") for k in kinds}
            for _ in range(a.repeats):  # interleaved: drifts of machine speed hit both sides alike
                for k, mk in kinds.items():
                    t = h.time_calls(lambda: h.filter_chunks(f, traj.observations, mean, cov, chunk, mk))
                    best[k] = min(best[k], t.min / (B * T))
            rows.append(
                dict(
                    case=name,
                    trials=B,
                    steps=T,
                    generator=best["generator"],
                    streams=best["streams"],
                    ratio=best["streams"] / best["generator"],
                )
            )
            print(rows[-1], flush=True)
        # the draws alone: normals are ~30 % of a filter's time at most (BPF, N=1e4, d=64), so their cost
        # bounds the filters' far more tightly than whole-call timings on a noisy VM
        for B, n in ((25, 12_800), (100, 12_800), (3, 640_000), (8, 12_500)):
            best = {}
            for k, gen in (("generator", torch.Generator().manual_seed(0)), ("streams", TrialStreams(0, B, "bench"))):
                t = h.time_calls(
                    lambda: linalg.standard_normal((B, n), dtype=torch.float64, device="cpu", generator=gen),
                    repeats=5 * a.repeats,
                )
                best[k] = t.min / (B * n) * 1e9
            draws.append(
                dict(
                    B=B,
                    n=n,
                    generator_ns=best["generator"],
                    streams_ns=best["streams"],
                    ratio=best["streams"] / best["generator"],
                )
            )
            print(draws[-1], flush=True)
    md = h.report(
        "# Per-trial random streams: cost",
        a,
        info,
        [
            f"{a.threads} threads, minimum over {a.repeats} interleaved repeats. Seconds per trial-step of the "
            "same filter calls with one `torch.Generator` per call and with `TrialStreams` (one stream per "
            "trial, as `run_experiment` uses them)."
        ],
        ["case", "trials x steps", "generator s", "streams s", "streams / generator"],
        [
            [
                r["case"],
                f"{r['trials']} x {r['steps']}",
                f"{r['generator']:.4g}",
                f"{r['streams']:.4g}",
                f"{r['ratio']:.3f}",
            ]
            for r in rows
        ],
        "Normal draws alone (float64, ns per number, minimum of repeats):",
        "",
        *h.md_table(
            ["trials x numbers per trial", "generator ns", "streams ns", "ratio"],
            [
                [f"{r['B']} x {r['n']}", f"{r['generator_ns']:.2f}", f"{r['streams_ns']:.2f}", f"{r['ratio']:.3f}"]
                for r in draws
            ],
        ),
    )
    return {
        "threads": a.threads,
        "repeats": a.repeats,
        "rows": rows,
        "draws": draws,
        "machine": info,
        "args": vars(a),
        "markdown": md,
    }


if __name__ == "__main__":
    h.main(run, "streams")
