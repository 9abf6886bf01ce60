"""Where a filter's time goes: wall seconds per trial-step, then ``torch.profiler``'s table of the
ops (and, on a GPU, the kernels) that take it, for one filter on acoustic tracking.

    python -m experiments.benchmarks.profile_step --filter ledh --device cuda --trials 100 --particles 500
    python -m experiments.benchmarks.profile_step --filter ledh --quick          # CPU smoke test

Timed: ``--steps`` time steps after a warm-up call of 2 steps, best of ``--reps`` calls; then one
profiled call (``--profile-steps``), its ops sorted by device time on CUDA (self CPU time on the CPU),
the top ``--top`` rows (0: timing only). ``--graphs 0`` runs the flows' loop eagerly (``tuning.cuda_graphs``);
``--fused`` picks the fused
pseudo-step (``tuning.fused_flows``: 0 torch, 1 the fused kernel, with ``--rows-warps`` warps of 32
particles per program; ``--fused-measurement`` 0/1: the acoustic measurement linearised by torch or
inside the kernel; ``--fused-info`` 0/1: the GPU kernel in row or information form,
``tuning.fused_info``; ``--structured-update`` 0/1: the per-particle EKF update in the ``m x m`` Joseph form
or in ``k x k`` algebra, ``tuning.structured_update``).
"""

from __future__ import annotations

import time

import torch
from torch.profiler import ProfilerActivity, profile

from torchflow.core import tuning
from torchflow.models import AcousticTracking

from . import harness as h


def run(argv=None) -> dict:
    a = h.options(
        __doc__,
        argv,
        dict(trials=2, particles=50, steps=3, profile_steps=2, top=10, reps=1),
        filter="ledh",
        device="cpu",
        trials=100,
        particles=500,
        steps=10,
        profile_steps=3,
        reps=2,
        top=25,
        graphs=1,
        dtype="float64",
        threads=2,
        fused=-1,
        rows_warps=0,
        fused_measurement=-1,
        structured_update=-1,
        fused_info=-1,
    )
    torch.set_num_threads(a.threads)
    device, dtype = torch.device(a.device), getattr(torch, a.dtype)
    model = AcousticTracking().to(device=device, dtype=dtype)
    g = torch.Generator(device=device).manual_seed(0)
    traj = model.simulate(a.trials, max(a.steps, a.profile_steps, 2), g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    f = h.make_filter(a.filter, model, a.particles)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)

    def call(steps):
        with torch.no_grad():
            f(traj.observations[:, :steps], mean, cov, torch.Generator(device=device).manual_seed(1))
        sync()

    knobs = dict(cuda_graphs=int(a.graphs))
    if a.fused >= 0:
        knobs["fused_flows"] = int(a.fused)
    if a.fused_measurement >= 0:
        knobs["fused_measurement"] = int(a.fused_measurement)
    if a.structured_update >= 0:
        knobs["structured_update"] = int(a.structured_update)
    if a.fused_info >= 0:
        knobs["fused_info"] = int(a.fused_info)
    if a.rows_warps:
        from torchflow.flows.kernels import steps as fused

        fused.ROWS_WARPS = int(a.rows_warps)
    with tuning.tuned(**knobs):
        call(2)
        best = float("inf")
        for _ in range(a.reps):
            t0 = time.perf_counter()
            call(a.steps)
            best = min(best, time.perf_counter() - t0)
        if a.top:
            acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
            with profile(activities=acts) as prof:
                call(a.profile_steps)
    per = best / (a.trials * a.steps)
    print(
        f"{a.filter}: {a.trials} trials x {a.particles} particles on {device} ({a.dtype}, cuda_graphs={a.graphs}, "
        f"fused_flows={knobs.get('fused_flows', tuning.get().fused_flows)}, "
        f"fused_measurement={knobs.get('fused_measurement', tuning.get().fused_measurement)}, "
        f"fused_info={knobs.get('fused_info', tuning.get().fused_info)}, "
        f"structured_update={knobs.get('structured_update', tuning.get().structured_update)}, "
        f"rows_warps={a.rows_warps or 'default'}): {per:.3g} s per trial-step, {best / a.steps:.3g} s per time step"
    )
    if not a.top:
        return dict(sec_per_trial_step=per)
    key = "self_device_time_total" if device.type == "cuda" else "self_cpu_time_total"
    print(prof.key_averages().table(sort_by=key, row_limit=a.top, max_name_column_width=60))
    return dict(sec_per_trial_step=per)


if __name__ == "__main__":
    run()
