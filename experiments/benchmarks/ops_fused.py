"""Aten ops and kernel launches per time step of PF-PF(LEDH) and the LEDH flow filter on the CUDA path
with the fused pseudo-step (``tuning.fused_flows``), counted on the CPU: Triton's interpreter runs the
kernel, and each of its calls counts as one launch (the ops inside the interpreter are not counted).
Acoustic tracking, 2 trials x 20 particles, the second time step, ``batched_jitter_cpu=1`` (the CUDA
path of ``safe_cholesky``). Slow (the interpreter: ~5 minutes on 2 cores); not in ``run_all``.

Also the bootstrap PF's step with per-trial streams as on a GPU (``TrialStreams`` with the Philox
backend: the runner's randomness off the CPU), with the Philox rounds as torch ops
(``tuning.fused_philox=0``) and as one Triton kernel (each call one launch); SensorNetwork d = 64,
4 trials x 200 particles, float32.

    python -m experiments.benchmarks.ops_fused            # both
    python -m experiments.benchmarks.ops_fused bpf        # the bootstrap PF only (seconds)
"""

import os

os.environ["TRITON_INTERPRET"] = "1"
import sys

import torch
from torch.utils._python_dispatch import _disable_current_modes

from experiments.benchmarks.bench_ops import VIEW_OPS, count, filters
from torchflow.flows.kernels import steps as fused
from torchflow.models import AcousticTracking


def counted(real, calls):
    """``real`` with each call counted in ``calls[0]`` as one launch, its inside (the interpreter's
    own torch calls) not counted as aten ops."""

    def run(*a, **k):
        calls[0] += 1
        with _disable_current_modes():
            return real(*a, **k)

    return run


launches = [0]
fused.dh_particle_step = counted(fused.dh_particle_step, launches)
model = AcousticTracking()
g = torch.Generator().manual_seed(0)
traj = model.simulate(2, 2, g)
mean, cov = model.initial_belief(traj.states[:, 0], g)
for name in ("PF-PF(LEDH)", "flow filter (LEDH)") if sys.argv[1:] != ["bpf"] else ():
    f = filters(model, 20)[name]
    launches[0] = 0
    c = count(f, traj.observations, mean, cov, True)
    views = sum(n for op, n in c.by_op.items() if op in VIEW_OPS)
    step_launches = launches[0] // 2  # count() runs two steps, the second counted
    print(
        f"{name}: {c.ops + step_launches} ops per time step ({c.ops} aten + {step_launches} fused launches), "
        f"{c.ops - views + step_launches} not views, {len(c.syncs)} host reads"
    )
    print("  most frequent:", ", ".join(f"{op.replace('aten.', '')} {n}" for op, n in c.by_op.most_common(6)))


from torchflow.core import random as R
from torchflow.core import tuning
from torchflow.core.profiling import OpCounter
from torchflow.filters import BootstrapParticleFilter
from torchflow.models import SensorNetwork

philox_calls = [0]
R.philox4x32_fused = counted(R.philox4x32_fused, philox_calls)
sn = SensorNetwork(d=64).to(dtype=torch.float32)
g = torch.Generator().manual_seed(0)
traj = sn.simulate(4, 3, g)
mean, cov = sn.initial_belief(traj.states[:, 0], g)
bpf = BootstrapParticleFilter(sn, n_particles=200)
for fuse in (0, 1):
    with tuning.tuned(fused_philox=fuse, batched_jitter_cpu=1), torch.no_grad():
        st = R.TrialStreams(0, 4, bpf.stream_name, backend="philox")
        state = bpf.step(
            bpf.step(bpf.init(mean, cov, None, st), traj.observations[:, 0], st), traj.observations[:, 1], st
        )
        philox_calls[0] = 0
        with OpCounter() as c:
            bpf.step(state, traj.observations[:, 2], st)
    views = sum(n for op, n in c.by_op.items() if op in VIEW_OPS)
    print(
        f"BPF, per-trial Philox streams, fused_philox={fuse}: {c.ops + philox_calls[0]} ops per time step "
        f"({c.ops} aten + {philox_calls[0]} Philox launches), {c.ops - views + philox_calls[0]} not views, "
        f"{len(c.syncs)} host reads"
    )
