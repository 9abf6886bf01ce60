"""Seconds per trial-step of the filters whose speed a change must keep, one script for two checkouts
(the before/after check of a refactor; RESULTS.md, "Speed kept across refactors").

    git worktree add /tmp/before <commit> && git worktree add /tmp/after <commit>
    (cd /tmp/before && python -m experiments.benchmarks.bench_before_after before [filter names...])
    (cd /tmp/after && python -m experiments.benchmarks.bench_before_after after [filter names...])

Each filter runs 1 warm-up call and ``--repeats`` timed calls on the same data, under
``torch.no_grad()``, on 2 threads; the output is one line per filter (median, min, max seconds per
trial-step) and a JSON line of every timing. Run the two checkouts alternately on an idle machine.
The filters: BPF, PF-PF(LEDH), PF-PF(Gromov), GPFIS and PFGSPF on acoustic tracking (4 trials x 10
steps, N = 500 or G = 5 x 100); the clustered PF-PF (K = 100 clusters of 500 particles, 4 x 10);
the LETKF on Lorenz-96 (d = 40, N = 20, 4 x 50); PFGPF on the linear-Gaussian sensor network
(d = 64, N = 1000, 2 trials x 3 steps). Only public names are used, so any checkout since the
filters' names were fixed runs it.
"""

import argparse
import contextlib
import json
import time

import torch


def cases():
    """name -> (make the filter, make the model, trials, steps). Imports happen per case, so a
    checkout that lacks a filter or model skips that case only."""
    import torchflow.filters as F
    import torchflow.models as M

    return {
        "bpf": (lambda m: F.BootstrapParticleFilter(m, n_particles=500), M.AcousticTracking, 4, 10),
        "pfpf_ledh": (
            lambda m: F.ParticleFlowParticleFilter(m, flow="ledh", n_particles=500),
            M.AcousticTracking,
            4,
            10,
        ),
        "pfpf_gromov": (
            lambda m: F.ParticleFlowParticleFilter(m, flow="gromov", n_particles=500),
            M.AcousticTracking,
            4,
            10,
        ),
        "gpfis": (lambda m: F.GPFIS(m, n_particles=500), M.AcousticTracking, 4, 10),
        "pfgspf": (
            lambda m: F.ParticleFlowGaussianSumParticleFilter(m, n_components=5, particles_per_component=100),
            M.AcousticTracking,
            4,
            10,
        ),
        "pfpf_clustered": (
            lambda m: F.ClusteredParticleFlowParticleFilter(m, n_clusters=100, n_particles=500),
            M.AcousticTracking,
            4,
            10,
        ),
        "letkf": (
            lambda m: F.LocalEnsembleTransformKalmanFilter(m, n_particles=20),
            lambda: M.Lorenz96(d=40),
            4,
            50,
        ),
        "pfgpf_lg64": (
            lambda m: F.ParticleFlowGaussianParticleFilter(m, n_particles=1000),
            lambda: M.SensorNetwork(d=64),
            2,
            3,
        ),
    }


def _torch_path():
    """A context that turns the fused kernels off (the torch path), in either layout of the package."""
    try:
        from torchflow.core import tuning
    except ImportError:  # before the package's floors
        from torchflow import tuning
    return tuning.tuned(fused_flows=0, fused_weights=0)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("label", help="a name for this checkout's lines (before, after)")
    p.add_argument("names", nargs="*", help="filters to time (default: all)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument(
        "--torch-path", action="store_true", help="the fused kernels off (tuning.fused_flows=0, fused_weights=0)"
    )
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    table = cases()
    names = args.names or list(table)
    out = {}
    for name in names:
        make, make_model, B, T = table[name]
        try:
            model = make_model()
            f = make(model)
        except (AttributeError, ImportError, TypeError) as exc:  # not in this checkout
            print(f"{args.label} {name} skipped: {exc}", flush=True)
            continue
        traj = model.simulate(B, T, torch.Generator().manual_seed(0))
        mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator().manual_seed(1))
        times, mse = [], None
        for r in range(args.repeats + 1):
            t0 = time.perf_counter()
            with torch.no_grad(), _torch_path() if args.torch_path else contextlib.nullcontext():
                res = f(traj.observations, mean, cov, torch.Generator().manual_seed(r))
            times.append((time.perf_counter() - t0) / (B * T))
            mse = float(((res.estimates - traj.states[:, 1:]) ** 2).mean()) if r == 0 else mse
        times = sorted(times[1:])
        out[name] = times
        mid = times[len(times) // 2]
        print(
            f"{args.label} {name} median s/trial-step {mid:.5f}  min {times[0]:.5f}  max {times[-1]:.5f}  "
            f"MSE (first call) {mse:.6g}",
            flush=True,
        )
    print(json.dumps({args.label: out}))


if __name__ == "__main__":
    main()
