"""Operations and host synchronisations per filter step: what each filter asks of a GPU.
Every aten op is a kernel launch on a GPU and every read of a value back to the host stalls its
queue; both are counted on the CPU with :class:`torchflow.core.profiling.OpCounter` over one time step
(the second: the first includes set-up) of every filter on acoustic tracking (d = 16, m = 25).

    python -m experiments.benchmarks.bench_ops            # B = 4 trials, N = 100; seconds
    python -m experiments.benchmarks.bench_ops --quick

Columns: ``ops`` and ``syncs`` with the CPU's default (``safe_cholesky`` reads its failure flags, a
free read on the CPU) and ``syncs (as on CUDA)`` with ``tuning.batched_jitter_cpu=1`` (the path a
CUDA tensor takes); ``target`` and ``met``: the op-count goals (PF-PF(LEDH) <= 1,000, PF-PF(Gromov)
<= 1,500, GPFIS <= 3,000 ops per time step). Counts do not depend on the machine; they grow with
the schedule's pseudo-steps (29 here), not with B or N. ``of which not views``: the ops left after
those that only make a view (``view``, ``expand``, ``unsqueeze``, ``permute``, ...; no kernel on a
GPU), i.e. about the kernel launches.
"""

from __future__ import annotations

import torch

from torchflow.core import tuning
from torchflow.core.profiling import OpCounter
from torchflow.core.random import TrialStreams
from torchflow.filters import (
    GPFIS,
    BootstrapParticleFilter,
    ClusteredParticleFlowParticleFilter,
    ExtendedKalmanFilter,
    GaussianParticleFilter,
    GaussianSumParticleFilter,
    ParticleFilter,
    ParticleFlowFilter,
    ParticleFlowGaussianSumParticleFilter,
    ParticleFlowParticleFilter,
    UnscentedKalmanFilter,
)
from torchflow.flows.kernels import steps as fused
from torchflow.models import AcousticTracking
from torchflow.proposals import UnscentedProposal

from . import harness as h

TARGETS = {"PF-PF(LEDH)": 1000, "PF-PF(Gromov)": 1500, "GPFIS": 3000}
#: ops that only make a new view of a tensor's memory: no kernel on a GPU
VIEW_OPS = frozenset(
    f"aten.{n}.default"
    for n in (
        "view",
        "expand",
        "_unsafe_view",
        "unsqueeze",
        "squeeze",
        "permute",
        "transpose",
        "t",
        "alias",
        "detach",
        "as_strided",
        "diagonal",
    )
)
VIEW_OPS = VIEW_OPS | {
    "aten.select.int",
    "aten.slice.Tensor",
    "aten.squeeze.dim",
    "aten.transpose.int",
    "aten.split.Tensor",
    "aten.unbind.int",
    "aten.squeeze.dims",
}


def filters(model, n: int) -> dict:
    """Every filter family, by its table name."""
    out = {
        "EKF": ExtendedKalmanFilter(model),
        "UKF": UnscentedKalmanFilter(model),
        "BPF": BootstrapParticleFilter(model, n_particles=n),
    }
    for flow, name in (
        ("edh", "EDH"),
        ("ledh", "LEDH"),
        ("geodesic", "geodesic"),
        ("gromov", "Gromov"),
        ("osd", "OSD"),
    ):
        out[f"PF-PF({name})"] = ParticleFlowParticleFilter(model, flow=flow, n_particles=n)
    out.update(
        {
            "clustered PF-PF": ClusteredParticleFlowParticleFilter(model, n_particles=n),
            "GPFIS": GPFIS(model, n_particles=n),
            "UPF": ParticleFilter(model, UnscentedProposal(model), n_particles=n),
            "GPF": GaussianParticleFilter(model, n_particles=n),
            "GSPF (2 components)": GaussianSumParticleFilter(
                model, n_components=2, particles_per_component=max(n // 2, 20)
            ),
            "PFGSPF (2 components)": ParticleFlowGaussianSumParticleFilter(
                model, n_components=2, particles_per_component=max(n // 2, 20)
            ),
            "flow filter (LEDH)": ParticleFlowFilter(model, flow="ledh", n_particles=n),
        }
    )
    return out


def count(f, obs, mean, cov, batched: bool) -> OpCounter:
    """One counted time step (the second) of ``f`` (``batched``: as it runs on a GPU, no host read)."""
    g = TrialStreams(0, obs.shape[0], f.stream_name) if f.uses_randomness else None
    with torch.no_grad():
        state = f.step(f.init(mean, cov, None, g), obs[:, 0], g)
        with tuning.tuned(batched_jitter_cpu=int(batched), host_reads_cpu=int(not batched)), OpCounter() as c:
            f.step(state, obs[:, 1], g)
    return c


def run(argv=None) -> dict:
    a = h.options(__doc__, argv, dict(particles=40), trials=4, particles=100, threads=2)
    rows = []
    with h.session("bench_ops", argv, a.threads) as info:
        model = AcousticTracking()
        g = torch.Generator().manual_seed(0)
        traj = model.simulate(a.trials, 2, g)
        mean, cov = model.initial_belief(traj.states[:, 0], g)
        for name, f in filters(model, a.particles).items():
            cpu, cuda = count(f, traj.observations, mean, cov, False), count(f, traj.observations, mean, cov, True)
            with tuning.tuned(fused_flows=0, fused_weights=0):  # the torch path (where the default takes a CPU kernel)
                eager = count(f, traj.observations, mean, cov, False).ops
            target = TARGETS.get(name)
            views = sum(n for op, n in cpu.by_op.items() if op in VIEW_OPS)
            rows.append(
                dict(
                    name=name,
                    ops=cpu.ops,
                    eager_ops=eager,
                    compute_ops=cpu.ops - views,
                    syncs=len(cpu.syncs),
                    syncs_cuda=len(cuda.syncs),
                    target=target,
                    met=None if target is None else cpu.ops <= target,
                    top=", ".join(
                        f"{op.replace('aten.', '').replace('.default', '')} {n}" for op, n in cpu.by_op.most_common(3)
                    ),
                )
            )
    md = h.report(
        "# Operations and host synchronisations per filter step",
        a,
        info,
        [
            f"Acoustic tracking, B = {a.trials} trials, N = {a.particles}, one time step (the second), "
            "29 pseudo-steps for the flows. CPU default: the fused EDH/LEDH pseudo-step and the particle "
            "filters' weighting kernel where Numba is "
            f"installed ({'here' if fused.runs_on('cpu') else 'not here'}); torch path: "
            "`tuning.fused_flows=0 fused_weights=0`."
        ],
        [
            "filter",
            "aten ops (CPU default)",
            "of which not views",
            "aten ops (torch path)",
            "syncs (CPU default)",
            "syncs (as on CUDA)",
            "target ops",
            "met (CPU default)",
            "most frequent ops",
        ],
        [
            (
                r["name"],
                r["ops"],
                r["compute_ops"],
                r["eager_ops"],
                r["syncs"],
                r["syncs_cuda"],
                h.fmt(r["target"], "{}"),
                h.met_cell(r["met"]),
                r["top"],
            )
            for r in rows
        ],
    )
    return dict(rows=rows, markdown=md, machine=info, args=vars(a))


if __name__ == "__main__":
    h.main(run, "ops")
