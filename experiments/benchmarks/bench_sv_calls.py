"""Seconds per trial of the bootstrap PF on the stochastic-volatility series, per call shape (one thread).

    python -m experiments.benchmarks.bench_sv_calls 1:1000:5 1:10000:3 100:1000:1 100:10000:1
    python -m experiments.benchmarks.bench_sv_calls fused_weights=0 1:1000:5     # a tuning knob set first

Each argument is ``B:N:reps``: ``reps`` calls of B trials at N particles on the 750 GBP/USD returns
(``experiments.data.gbpusd``; needs ``particles``) after an untimed warm-up call; prints seconds per
trial. A quick before/after of a change to the particle filters' step (run it at both commits,
interleaved, or with a ``knob=value`` of :mod:`torchflow.core.tuning` against its default); ``bench_sv`` is
the full comparison with ``particles`` and the exact filter.
"""

import sys
import time

import torch


def main(specs) -> dict:
    """``{spec: seconds per trial}`` of each ``"B:N:reps"`` in ``specs`` (printed as they finish)."""
    from experiments.data.gbpusd import returns
    from torchflow.core import tuning
    from torchflow.filters import BootstrapParticleFilter
    from torchflow.models import StochasticVolatility

    torch.set_num_threads(1)
    y = torch.tensor(returns())[None, :, None]
    model = StochasticVolatility()
    f = BootstrapParticleFilter(model)
    mean, cov = model.initial_belief(torch.zeros(1, 1, dtype=torch.float64))
    out = {}
    knobs = {k: int(v) for k, v in (a.split("=") for a in specs if "=" in a)}
    if knobs:
        tuning.set(**knobs)
        print("tuning:", knobs, flush=True)
    for spec in (a for a in specs if "=" not in a):
        B, n, reps = map(int, spec.split(":"))
        with torch.no_grad():
            f(
                y[:, :20].expand(2, -1, -1),
                mean.expand(2, -1),
                cov.expand(2, -1, -1),
                torch.Generator().manual_seed(0),
                n_particles=n,
            )
            t0 = time.perf_counter()
            for i in range(reps):
                f(
                    y.expand(B, -1, -1),
                    mean.expand(B, -1),
                    cov.expand(B, -1, -1),
                    torch.Generator().manual_seed(i),
                    n_particles=n,
                )
            out[spec] = (time.perf_counter() - t0) / reps / B
        print(f"B={B} N={n} reps={reps}: {out[spec]:.4f} s/trial", flush=True)
    return out


if __name__ == "__main__":
    main(sys.argv[1:])
