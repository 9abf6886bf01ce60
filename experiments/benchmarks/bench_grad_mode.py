"""A filter call in grad mode with nothing that requires grad, against the same call under
``torch.no_grad()``: PF-PF(LEDH) on the acoustic model, N = 100, 10 trials x 10 steps, one thread.
Both modes are warmed up first (the kernels' compilation or cache load), then alternated ``--repeats``
times; prints each call's seconds, its execution paths and its mean log-evidence.

    python -m experiments.benchmarks.bench_grad_mode
"""

from __future__ import annotations

import argparse
import time


def main(argv=None) -> None:
    import torch

    from torchflow.filters import ParticleFlowParticleFilter
    from torchflow.models import AcousticTracking

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--n-particles", type=int, default=100)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    model = AcousticTracking()
    g = torch.Generator().manual_seed(0)
    data = model.simulate(10, 10, g)
    mean, cov = model.initial_belief(data.states[:, 0], g)
    f = ParticleFlowParticleFilter(model, flow="ledh", n_particles=args.n_particles)

    def call(no_grad: bool):
        with torch.no_grad() if no_grad else torch.enable_grad():
            return f(data.observations, mean, cov, torch.Generator().manual_seed(1))

    call(False), call(True)  # warm-up: compilation or the on-disk cache
    for _ in range(args.repeats):
        for no_grad in (False, True):
            t = time.perf_counter()
            r = call(no_grad)
            mode = "under torch.no_grad()" if no_grad else "grad mode on"
            print(f"{mode:22s} {time.perf_counter() - t:6.2f} s  {r.paths}  {float(r.log_evidence.mean()):.6f}")


if __name__ == "__main__":
    main()
