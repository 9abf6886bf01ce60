"""log Z error of the PF-PFs and the BPF on Pal & Coates (2019) Table I (LG d = 64, N = 200, T = 10, 100 trials)
under several definitions of the paper's "relative MSE of log Z" (the paper does not define it):

* final: ``((log Zhat_T - log Z_T) / log Z_T)^2`` averaged over trials (the runner's column);
* per-step cumulative: the same at every step t for ``log Z_{1:t}``, averaged over steps and trials;
* per-increment: the same for the increments ``log p(z_t | z_{1:t-1})``.

Also prints the mean and sd of ``log Zhat - log Z`` (the Kalman filter gives log Z exactly).

    python experiments/logz_definitions.py      # ~1 min on 2 cores
"""

import torch

from torchflow.core.random import TrialStreams
from torchflow.filters import BootstrapParticleFilter, KalmanFilter, ParticleFlowParticleFilter
from torchflow.models import SensorNetwork

model = SensorNetwork(d=64, sigma_z=0.5)
g = torch.Generator().manual_seed(0)
B, T = 100, 10
traj = model.simulate(B, T, g)
mean, cov = model.initial_belief(traj.states[:, 0])
kf = KalmanFilter(model)(traj.observations, mean, cov)
rows = {}
for name, f in [
    ("pfpf_edh", ParticleFlowParticleFilter(model, flow="edh", n_particles=200)),
    ("pfpf_ledh", ParticleFlowParticleFilter(model, flow="ledh", n_particles=200)),
    ("pfpf_gromov", ParticleFlowParticleFilter(model, flow="gromov", n_particles=200)),
    ("bpf", BootstrapParticleFilter(model, n_particles=200)),
]:
    r = f(traj.observations, mean, cov, TrialStreams(0, B, f.random_stream))
    diff = r.log_evidence - kf.log_evidence
    final = ((diff) / kf.log_evidence).pow(2)
    cum_hat, cum = r.log_evidence_increments.cumsum(1), kf.log_evidence_increments.cumsum(1)
    per_step_cum = ((cum_hat - cum) / cum).pow(2).mean(1)
    per_inc = ((r.log_evidence_increments - kf.log_evidence_increments) / kf.log_evidence_increments).pow(2).mean(1)
    se = lambda x: float(x.std() / B**0.5)
    print(
        f"{name}: logZhat-logZ mean {float(diff.mean()):.2f} (SE {se(diff):.2f}) sd {float(diff.std()):.2f}; "
        f"relMSE final {float(final.mean()):.2e} (SE {se(final):.1e}); per-step cumulative "
        f"{float(per_step_cum.mean()):.2e}; "
        f"per-increment {float(per_inc.mean()):.2e}; logZ mean {float(kf.log_evidence.mean()):.1f}"
    )
