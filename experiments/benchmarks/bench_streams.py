"""Cost of per-trial random streams: the same filter calls with one ``torch.Generator`` per call
(the batch shares a stream) and with :class:`torchflow.random.TrialStreams` (one stream per
trial, what ``run_experiment`` uses), interleaved in one run.

    python experiments/benchmarks/bench_streams.py            # ~3 min on 2 cores
    python experiments/benchmarks/bench_streams.py --quick

Reports seconds per trial-step (minimum over repeats) and the ratio streams / generator.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import loadavg  # noqa: E402

from torchflow.filters import BootstrapParticleFilter, ParticleFlowParticleFilter  # noqa: E402
from torchflow.models import AcousticTracking, SensorNetwork  # noqa: E402
from torchflow.random import TrialStreams  # noqa: E402


def cases(quick: bool):
    lg = SensorNetwork(d=64)
    ac = AcousticTracking(sigma_w=0.1)
    s = 0.25 if quick else 1.0
    return [
        # name, model, filter, trials, steps
        ("BPF, LG d=64, N=200", lg, BootstrapParticleFilter(lg, n_particles=200), int(100 * s), 10),
        ("BPF, LG d=64, N=1e4", lg, BootstrapParticleFilter(lg, n_particles=10_000), max(3, int(12 * s)), 10),
        ("PF-PF(LEDH), acoustic, N=500", ac, ParticleFlowParticleFilter(ac, flow="ledh", n_particles=500),
         max(2, int(8 * s)), 5),
        ("PF-PF(Gromov), acoustic, N=500", ac, ParticleFlowParticleFilter(ac, flow="gromov", n_particles=500),
         max(2, int(8 * s)), 5),
    ]


def time_calls(f, traj, mean, cov, make_gen):
    B = traj.observations.shape[0]
    chunk = f.preferred_chunk_trials() or B
    t0 = time.perf_counter()
    with torch.no_grad():
        for s in range(0, B, chunk):
            f(traj.observations[s:s + chunk], mean[s:s + chunk], cov[s:s + chunk], make_gen(s, min(B, s + chunk)))
    return time.perf_counter() - t0


def run(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", default=None, help="write JSON results here")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    rows = []
    for name, model, f, B, T in cases(a.quick):
        g = torch.Generator().manual_seed(0)
        traj = model.simulate(B, T, g)
        mean, cov = model.initial_belief(traj.states[:, 0], g)
        gens = {
            "generator": lambda s, e: torch.Generator().manual_seed(s),
            "streams": lambda s, e: TrialStreams(0, range(s, e), key=f.stream_name),
        }
        time_calls(f, traj[:1], mean[:1], cov[:1], gens["streams"])  # warm-up
        best = {k: float("inf") for k in gens}
        for _ in range(a.repeats):  # interleaved: drifts of machine speed hit both sides alike
            for k, mk in gens.items():
                best[k] = min(best[k], time_calls(f, traj, mean, cov, mk) / (B * T))
        rows.append(dict(case=name, trials=B, steps=T, generator=best["generator"], streams=best["streams"],
                         ratio=best["streams"] / best["generator"]))
        print(f"{name:34s} generator {best['generator']:.3e}  streams {best['streams']:.3e}  "
              f"ratio {rows[-1]['ratio']:.3f}", flush=True)
    md = ["# Per-trial random streams: cost", "",
          f"`python experiments/benchmarks/bench_streams.py{' --quick' if a.quick else ''}`; {a.threads} threads, "
          f"minimum over {a.repeats} interleaved repeats, load {loadavg()}. Seconds per trial-step of the same filter "
          "calls with one `torch.Generator` per call and with `TrialStreams` (one stream per trial, as "
          "`run_experiment` uses them).", "",
          "| case | trials x steps | generator s | streams s | streams / generator |", "|---|---|---|---|---|"]
    md += [f"| {r['case']} | {r['trials']} x {r['steps']} | {r['generator']:.4g} | {r['streams']:.4g} | "
           f"{r['ratio']:.3f} |" for r in rows]
    # the draws alone: the filters' time is ~30 % normals at most (BPF, N=1e4, d=64), so the
    # draw cost bounds the filters' cost far more tightly than whole-call timings on a noisy VM
    from torchflow import linalg

    draws = []
    for B, n in ((25, 12_800), (100, 12_800), (3, 640_000), (8, 12_500)):
        best = {}
        for k, mk in (("generator", lambda: torch.Generator().manual_seed(0)),
                      ("streams", lambda: TrialStreams(0, B, "bench"))):
            gen, t_best = mk(), float("inf")
            for _ in range(5 * a.repeats):
                t0 = time.perf_counter()
                linalg.standard_normal((B, n), dtype=torch.float64, device="cpu", generator=gen)
                t_best = min(t_best, time.perf_counter() - t0)
            best[k] = t_best / (B * n) * 1e9
        draws.append(dict(B=B, n=n, generator_ns=best["generator"], streams_ns=best["streams"],
                          ratio=best["streams"] / best["generator"]))
        print(draws[-1], flush=True)
    md += ["", "Normal draws alone (float64, ns per number, minimum of repeats):", "",
           "| trials x numbers per trial | generator ns | streams ns | ratio |", "|---|---|---|---|"]
    md += [f"| {r['B']} x {r['n']} | {r['generator_ns']:.2f} | {r['streams_ns']:.2f} | {r['ratio']:.3f} |"
           for r in draws]
    out = {"threads": a.threads, "repeats": a.repeats, "rows": rows, "draws": draws, "markdown": "\n".join(md) + "\n"}
    if a.out:
        Path(a.out).write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    from _common import write_results

    res = run()
    write_results(res, "streams", "--quick" in sys.argv)
