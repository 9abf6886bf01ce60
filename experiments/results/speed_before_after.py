"""Speed per trial-step of five filters, one script for two checkouts (the before/after check of the
redesign; RESULTS.md, "Speed before and after the redesign"):

    git worktree add /tmp/before 5d2894d && git worktree add /tmp/after 3a0f806
    PYTHONPATH=/tmp/before python experiments/results/speed_before_after.py before [name filters...]
    PYTHONPATH=/tmp/after python experiments/results/speed_before_after.py after [name filters...]
"""

import json
import sys
import time

import torch

torch.set_num_threads(2)
from torchflow.filters import (
    GPFIS,
    BootstrapParticleFilter,
    ParticleFlowGaussianSumParticleFilter,
    ParticleFlowParticleFilter,
)
from torchflow.models import AcousticTracking

label = sys.argv[1]
B, T = 4, 10
model = AcousticTracking()
traj = model.simulate(B, T, torch.Generator().manual_seed(0))
mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator().manual_seed(1))
ALL = {
    "bpf N=500": BootstrapParticleFilter(model, n_particles=500),
    "pfpf_ledh N=500": ParticleFlowParticleFilter(model, flow="ledh", n_particles=500),
    "pfpf_gromov N=500": ParticleFlowParticleFilter(model, flow="gromov", n_particles=500),
    "gpfis N=500": GPFIS(model, n_particles=500),
    "pfgspf G=5x100": ParticleFlowGaussianSumParticleFilter(model, n_components=5, particles_per_component=100),
}
filters = {k: v for k, v in ALL.items() if any(s in k for s in sys.argv[2:])} if len(sys.argv) > 2 else ALL
out = {}
for name, f in filters.items():
    times = []
    for r in range(4):
        t0 = time.perf_counter()
        with torch.no_grad():
            res = f(traj.observations, mean, cov, torch.Generator().manual_seed(r))
        times.append((time.perf_counter() - t0) / (B * T))
    times = sorted(times[1:])
    out[name] = times
    print(label, name, "median s/trial-step %.5f  min %.5f  max %.5f" % (times[1], times[0], times[2]), flush=True)
print(json.dumps(out))
