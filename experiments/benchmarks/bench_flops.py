"""Achieved GFLOP/s of PF-PF(LEDH) on acoustic tracking beside this machine's measured matrix-product
throughput.

    python -m experiments.benchmarks.bench_flops          # N = 500, 20 trials x 5 steps

The flop count is analytic, for the algorithm as implemented (``torchflow.flows.daum_huang`` with
the measurement-support reduction: the acoustic measurement reads k = 8 of d = 16 coordinates,
m = 25 sensors), per particle and pseudo-time step:

* linearisation (ranges, Jacobian, h): ~20 m C flops; whitened residual ``W x_s``: 2 m k;
* ``J = W^T W``: 2 m k^2; ``W^T y``: 2 m k; ``T = L_s^T J``, ``S = T L_s``: 2 x 2 k^3;
* two Cholesky factors of k x k: 2 k^3 / 3; ``(I + lam S)^{-1} T``: 2 k^3 (two triangular solves);
* ``A = -1/2 L (...)``: 2 d k^2; ``P H^T R^{-1}(z - e)``: 2 d k; A applied to 5 vectors: 10 d k;
  vector updates ~10 d;

plus, once per particle and time step, the EKF covariance prediction and update (~``4 d^3 + 4 m d^2``)
and the factor of the flow's prior (``d^3 / 3 + 2 d^3``). Only multiply-adds count (2 flops
each); transcendental functions count as one flop. Measured throughputs: a large float64 GEMM
(2048^3, the machine's practical peak) and batched float64 products of the flow's own small shapes
(10,000 products of 16 x 8 @ 8 x 8 and of 25 x 8 -> 8 x 8 Gram), each the best of 5.
"""
from __future__ import annotations

import torch

from torchflow.models import AcousticTracking
from torchflow.schedules import ExponentialSchedule

from . import harness as h


def ledh_flops_per_trial_step(N: int, d: int, k: int, m: int, C: int, n_lambda: int) -> float:
    per_flow_step = (20 * m * C + 2 * m * k + 2 * m * k * k + 2 * m * k + 4 * k**3 + 2 * k**3 / 3 + 2 * k**3
                     + 2 * d * k * k + 2 * d * k + 10 * d * k + 10 * d)
    per_time_step = 4 * d**3 + 4 * m * d * d + d**3 / 3 + 2 * d**3
    return N * (n_lambda * per_flow_step + per_time_step)


def best(fn, reps=5) -> float:
    """Best of ``reps`` timed calls after one untimed call."""
    return h.time_calls(fn, repeats=reps, warmup=1).min


def throughputs() -> dict:
    f64 = dict(dtype=torch.float64)
    n = 2048
    A, B = torch.randn(n, n, **f64), torch.randn(n, n, **f64)
    gemm = 2 * n**3 / best(lambda: A @ B) / 1e9
    Bn = 10_000
    L, X = torch.randn(Bn, 16, 8, **f64), torch.randn(Bn, 8, 8, **f64)
    small = 2 * Bn * 16 * 8 * 8 / best(lambda: L @ X) / 1e9
    W = torch.randn(Bn, 25, 8, **f64)
    gram = 2 * Bn * 25 * 8 * 8 / best(lambda: W.transpose(-1, -2) @ W) / 1e9
    L16, X16 = torch.randn(Bn, 16, 16, **f64), torch.randn(Bn, 16, 16, **f64)
    sq16 = 2 * Bn * 16**3 / best(lambda: L16 @ X16) / 1e9
    return dict(gemm_2048=gemm, bmm_16x8x8=small, bmm_gram_25x8=gram, bmm_16x16x16=sq16)


def run(argv=None) -> dict:
    ap = h.parser(__doc__)
    ap.add_argument("--particles", type=int, default=500)
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None)
    a = ap.parse_args(argv)
    if a.quick:
        a.trials, a.steps = 4, 2
    with h.torch_threads(a.threads):
        info = h.machine(command=h.command("bench_flops", argv))
        model = AcousticTracking()
        traj, mean, cov = h.simulate(model, a.trials, a.steps, 0)
        f = h.make_filter("ledh", model, a.particles)
        chunk = f.preferred_chunk_trials()
        one = lambda s, e: torch.Generator().manual_seed(1)  # noqa: E731
        wall = h.time_filter(f, traj.observations, mean, cov, chunk, one, warmup=1, repeats=2).min
        per_ts = wall / (a.trials * a.steps)
        fl = ledh_flops_per_trial_step(a.particles, 16, 8, 25, 4, len(ExponentialSchedule()))
        achieved = fl / per_ts / 1e9
        tp = throughputs()
        info["load_end"] = h.loadavg()
    rows = [dict(name="PF-PF(LEDH), acoustic, N=%d" % a.particles, gflops=achieved, per_ts=per_ts,
                 gflop_per_trial_step=fl / 1e9)] + [dict(name=k, gflops=v) for k, v in tp.items()]
    kernels = [(f"PF-PF(LEDH) whole filter ({fl / 1e9:.3f} GFLOP per trial-step, {per_ts:.4g} s per trial-step, "
                f"{min(chunk, a.trials)} trials per call)", achieved),
               ("batched 16x8 @ 8x8 (10^4 products; the flow's A = L (...) shape)", tp["bmm_16x8x8"]),
               ("batched Gram 8x25 @ 25x8 (10^4; J = W^T W)", tp["bmm_gram_25x8"]),
               ("batched 16x16 @ 16x16 (10^4)", tp["bmm_16x16x16"])]
    md = h.header("## PF-PF(LEDH) achieved GFLOP/s", a.quick, info, "float64.")
    md += h.md_table(["kernel", "GFLOP/s", "fraction of large GEMM"],
                     [[k, f"{v:.2f}", f"{v / tp['gemm_2048']:.1%}"] for k, v in kernels]
                     + [["one 2048^3 GEMM (practical peak)", f"{tp['gemm_2048']:.2f}", "100%"]])
    md += ["", "- The flow runs at the speed of batched small products, far below the large-GEMM peak: on CPU "
           "each of its ~10 products per pseudo-step handles 8-25-wide matrices, where per-matrix overhead "
           "and memory traffic, not arithmetic, set the time."]
    return dict(rows=rows, markdown="\n".join(md) + "\n", machine=info, args=vars(a))


if __name__ == "__main__":
    h.main(run, "flops")
