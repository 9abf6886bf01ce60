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
(d = 64, N = 1000, 2 trials x 3 steps); the lag-one flows (global, localised, weighted, localised
weighted) and the KPFF on Lorenz-96 / Lorenz-63 (4 x 50); the TDOA mixture importance samplers PFI-D
and PFI-OS (one scene, 100 components x 500 samples; per sensor step). Only public names are used,
so any checkout since the filters' names were fixed runs it (a filter it lacks is skipped).
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
        # the data-assimilation filters: the lag-one flows, global, localised and weighted, and the kernel flow
        "lag1_flow": (lambda m: F.LagOneFlowFilter(m, n_particles=40), lambda: M.Lorenz96(d=40), 4, 50),
        "lag1_flow_local": (
            lambda m: F.LagOneFlowFilter(m, n_particles=40, radius=30.0),
            lambda: M.Lorenz96(d=40),
            4,
            50,
        ),
        "lag1_pfpf": (lambda m: F.LagOneFlowParticleFilter(m, n_particles=100), M.Lorenz63, 4, 50),
        "lag1_pfpf_local": (
            lambda m: F.LocalLagOneFlowParticleFilter(m, n_particles=40, radius=30.0),
            lambda: M.Lorenz96(d=40, obs_every=2, obs_operator="abs"),
            4,
            50,
        ),
        "kpff": (lambda m: F.KernelParticleFlowFilter(m, n_particles=20), lambda: M.Lorenz96(d=40), 4, 50),
        # the TDOA mixture importance samplers (Zhang et al. 2024; zhang2024_table1's PFI-D and PFI-OS rows,
        # one scene, 100 components x 500 samples)
        "pfi_d": (lambda m: _localiser(m, "pfi_d", 1e-7), M.TDOA3D, 1, None),
        "pfi_os": (lambda m: _localiser(m, "pfi_os", 1e-5), M.TDOA3D, 1, None),
    }


def _localiser(model, method, first_step):
    """Zhang et al.'s flow-mixture localiser as ``experiment=zhang2024_table1`` sets it (the package's
    name for it in either layout)."""
    from torchflow.flows.schedules import GeometricSchedule

    try:
        from torchflow.tdoa import FlowMixtureLocaliser
    except ImportError:  # before the TDOA package was named for what it is
        from torchflow.localisation import FlowMixtureLocaliser
    schedule = GeometricSchedule(first_step=first_step, ratio=1.5)
    return FlowMixtureLocaliser(model, method, n_components=100, samples_per_component=500, schedule=schedule)


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
        tdoa = hasattr(traj, "mask")  # a localiser: one step per sensor, measurement sets with a mask
        T = traj.observations.shape[1]
        mean, cov = (None, None) if tdoa else model.initial_belief(traj.states[:, 0], torch.Generator().manual_seed(1))
        times, mse = [], None
        for r in range(args.repeats + 1):
            t0 = time.perf_counter()
            with torch.no_grad(), _torch_path() if args.torch_path else contextlib.nullcontext():
                if tdoa:
                    res = f(traj.observations, generator=torch.Generator().manual_seed(r), mask=traj.mask)
                else:
                    res = f(traj.observations, mean, cov, torch.Generator().manual_seed(r))
            times.append((time.perf_counter() - t0) / (B * T))
            if r == 0 and not tdoa:
                mse = float(((res.estimates - traj.states[:, 1:]) ** 2).mean())
            elif r == 0:  # the localiser's positions against the sources: not an MSE of states, so none
                mse = float("nan")
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
