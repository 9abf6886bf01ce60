"""Linear-Gaussian: Kalman filter, PF-PF(LEDH) and bootstrap PF

On a linear-Gaussian model the Kalman filter is the exact posterior, and its log-evidence
log p(z_1:T) is exact: the particle filters can be scored against it. This script runs the
Kalman filter, the particle-flow particle filter with the LEDH flow and the bootstrap particle
filter on the same simulated trials (a 4-dimensional state, 2 measured coordinates, a small
measurement noise so that the likelihood is peaked), and compares their state estimates and
their log-evidence estimates with the Kalman filter's.
"""

import matplotlib.pyplot as plt
import torch

from torchflow.filters import BootstrapParticleFilter, KalmanFilter, ParticleFlowParticleFilter
from torchflow.flows import LEDHFlow
from torchflow.models import LinearGaussian

d, m = 4, 2
F = 0.9 * torch.eye(d, dtype=torch.float64)
Q = 0.5 * torch.eye(d, dtype=torch.float64)
H = torch.eye(m, d, dtype=torch.float64)  # the first two coordinates are measured
R = 0.01 * torch.eye(m, dtype=torch.float64)  # a peaked likelihood
model = LinearGaussian(F, Q, H, R, torch.zeros(d), torch.eye(d, dtype=torch.float64))

g = torch.Generator().manual_seed(0)
traj = model.simulate(20, 25, g)  # 20 trials x 25 steps
mean, cov = model.initial_belief(traj.states[:, 0])

filters = {
    "KF": KalmanFilter(model),
    "PF-PF(LEDH), N=100": ParticleFlowParticleFilter(model, flow=LEDHFlow(), n_particles=100),
    "bootstrap PF, N=100": BootstrapParticleFilter(model, n_particles=100),
}
results = {name: f(traj.observations, mean, cov, torch.Generator().manual_seed(1)) for name, f in filters.items()}

exact = results["KF"]
print(f"{'filter':22s} {'MSE':>8s} {'|log Z - log Z_KF|':>20s} {'mean ESS / N':>13s}")
for name, res in results.items():
    mse = ((res.estimates - traj.states[:, 1:]) ** 2).mean()
    err = (res.log_evidence - exact.log_evidence).abs().mean()
    ess = "" if res.ess is None else f"{(res.ess / 100).mean():13.2f}"
    print(f"{name:22s} {mse:8.4f} {err:20.3f} {ess}")

fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.6))
steps = torch.arange(1, traj.observations.shape[1] + 1)
for i, (name, res) in enumerate(results.items()):
    if name == "KF":
        continue  # the reference: zero distance, no ESS
    ax1.plot(steps, ((res.estimates - exact.estimates) ** 2).sum(-1).mean(0), color=f"C{i}", label=name)
    ax2.plot(steps, (res.ess / 100).mean(0), color=f"C{i}", label=name)
ax1.set(
    yscale="log",
    xlabel="time step",
    ylabel="squared distance to the KF mean",
    title="distance to the exact posterior mean",
)
ax2.set(xlabel="time step", ylabel="ESS / N", ylim=(0, 1.05), title="effective sample size")
ax1.legend(fontsize=8)
ax2.legend(fontsize=8)
fig.tight_layout()

if __name__ == "__main__":  # run by hand: show the figure (the documentation build saves it instead)
    plt.show()
