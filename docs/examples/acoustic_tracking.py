"""Acoustic tracking: four targets, 25 sensors

Li & Coates' multi-target acoustic tracking scenario (`torchflow.models.AcousticTracking`): four
targets move with nearly constant velocity in a 40 m x 40 m field, and 25 sensors on a grid
measure the sum of the amplitudes the targets emit, decaying with distance. The state has
d = 16 coordinates (position and velocity of each target), the measurement m = 25.

The script runs the extended Kalman filter, the bootstrap particle filter and PF-PF(LEDH) on the
same trials (small sizes: a few trials, few particles, a short horizon) and draws the first
trial's tracks and each filter's OMAT (the optimal-assignment position error, in metres) per time
step. The sizes of the published comparisons, and their results, are in `experiments/RESULTS.md`.
"""

import matplotlib.pyplot as plt
import torch

from torchflow.core import metrics
from torchflow.filters import BootstrapParticleFilter, ExtendedKalmanFilter, ParticleFlowParticleFilter
from torchflow.models import AcousticTracking

model = AcousticTracking(sigma_w=0.1)
g = torch.Generator().manual_seed(3)
traj = model.simulate(4, 25, g)  # 4 trials x 25 steps
mean, cov = model.initial_belief(traj.states[:, 0], g)  # the per-trial prior, drawn around the truth

filters = {
    "EKF": ExtendedKalmanFilter(model),
    "bootstrap PF, N=500": BootstrapParticleFilter(model, n_particles=500),
    "PF-PF(LEDH), N=50": ParticleFlowParticleFilter(model, flow="ledh", n_particles=50),
}
truth = model.positions(traj.states[:, 1:])  # (B, T, 4 targets, 2)
omat = {}
tracks = {}
for name, f in filters.items():
    res = f(traj.observations, mean, cov, torch.Generator().manual_seed(1))
    tracks[name] = model.positions(res.estimates)
    omat[name] = metrics.omat(tracks[name], truth)  # (B, T)
    print(f"{name:22s} OMAT {omat[name].mean():6.2f} m")

fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 5.4), gridspec_kw={"width_ratios": [1, 1.3]})
ax1.scatter(*model.sensors.T, marker="s", s=18, color="0.6", label="sensors")
start = model.positions(traj.states[0, 0])
ax1.plot(*start.T, "ko", ms=4)
for c in range(model.n_targets):
    ax1.plot(*truth[0, :, c].T, "k-", lw=2, label="truth" if c == 0 else None)
for i, name in enumerate(filters):
    for c in range(model.n_targets):
        ax1.plot(*tracks[name][0, :, c].T, "--", color=f"C{i}", lw=1.2, label=name if c == 0 else None)
ax1.set(xlim=(0, 40), ylim=(0, 40), aspect="equal", xlabel="x (m)", ylabel="y (m)", title="trial 0: tracks")
ax1.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)
steps = torch.arange(1, traj.observations.shape[1] + 1)
for i, name in enumerate(filters):
    ax2.plot(steps, omat[name].mean(0), color=f"C{i}", label=name)
ax2.set(yscale="log", xlabel="time step", ylabel="OMAT (m), mean over trials", title="position error")
ax2.legend(fontsize=8)
fig.tight_layout()

if __name__ == "__main__":  # run by hand: show the figure (the documentation build saves it instead)
    plt.show()
