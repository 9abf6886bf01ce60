"""Aten ops and kernel launches per time step of PF-PF(LEDH) and the LEDH flow filter on the CUDA path
with the fused pseudo-step (``tuning.fused_flows``), counted on the CPU: Triton's interpreter runs the
kernel, and each of its calls counts as one launch (the ops inside the interpreter are not counted).
Acoustic tracking, 2 trials x 20 particles, the second time step, ``batched_jitter_cpu=1`` (the CUDA
path of ``safe_cholesky``). Slow (the interpreter: ~5 minutes on 2 cores); not in ``run_all``.

    python -m experiments.benchmarks.ops_fused
"""
import os; os.environ["TRITON_INTERPRET"]="1"
import torch
from torch.utils._python_dispatch import _disable_current_modes
from torchflow.flows import fused
from experiments.benchmarks.bench_ops import filters, count, VIEW_OPS
from torchflow.models import AcousticTracking
real = fused.dh_particle_step
launches = [0]
def stub(*a, **k):
    launches[0] += 1
    with _disable_current_modes():
        return real(*a, **k)
fused.dh_particle_step = stub
model = AcousticTracking(); g = torch.Generator().manual_seed(0)
traj = model.simulate(2, 2, g); mean, cov = model.initial_belief(traj.states[:, 0], g)
for name in ("PF-PF(LEDH)", "flow filter (LEDH)"):
    f = filters(model, 20)[name]
    launches[0] = 0
    c = count(f, traj.observations, mean, cov, True)
    views = sum(n for op, n in c.by_op.items() if op in VIEW_OPS)
    step_launches = launches[0] // 2  # count() runs two steps, the second counted
    print(f"{name}: {c.ops + step_launches} ops per time step ({c.ops} aten + {step_launches} fused launches), "
          f"{c.ops - views + step_launches} not views, {len(c.syncs)} host reads")
    print("  most frequent:", ", ".join(f"{op.replace('aten.', '')} {n}" for op, n in c.by_op.most_common(6)))
