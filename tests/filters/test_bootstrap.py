"""Bootstrap PF against the exact Kalman posterior on a small linear-Gaussian model."""
import pytest
import torch

from torchflow.filters import BootstrapParticleFilter, KalmanFilter
from conftest import random_lg, simulate_with_belief


@pytest.mark.parametrize("scheme", ["systematic", "multinomial"])
def test_bpf_posterior_mean_within_monte_carlo_error_of_kf(scheme):
    model = random_lg(2, 1, seed=11)
    traj, mean, cov, g = simulate_with_belief(model, 6, 8)
    kf = KalmanFilter(model)(traj.observations, mean, cov, return_covariances=True)
    N = 20000
    pf = BootstrapParticleFilter(model, n_particles=N, resampling=scheme)(traj.observations, mean, cov, g)
    # Monte Carlo standard error of a weighted mean ~ sqrt(P_ii / ESS); resampling in earlier steps
    # inflates it by a modest factor, so we allow k = 6 standard errors.
    se = (kf.covariances.diagonal(dim1=-2, dim2=-1) / pf.ess.unsqueeze(-1)).sqrt()
    err = (pf.estimates - kf.estimates).abs()
    assert (err <= 6 * se).all(), float((err / se).max())
    assert (err / se).mean() < 2.0  # typical error is about one standard error
    # log-evidence: the relative variance of each step's evidence estimate is about
    # chi^2(posterior || proposal) / N ~ 1/ESS_t, so sd(log Z_hat) ~ sqrt(sum_t 1/ESS_t); allow 6 sd.
    dz = pf.log_evidence - kf.log_evidence
    sd = pf.ess.reciprocal().sum(1).sqrt()
    assert (dz.abs() <= 6 * sd).all(), (dz / sd).tolist()


def test_bpf_resampling_threshold_zero_never_resamples():
    model = random_lg(2, 1, seed=11)
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(3, 5, g)
    mean, cov = model.initial_belief(traj.states[:, 0])
    f = BootstrapParticleFilter(model, n_particles=50, ess_threshold=0.0)
    state = f.init(mean, cov, None, g)
    for t in range(5):
        state = f.step(state, traj.observations[:, t], g)
        assert not state.resampled.any()
    f1 = BootstrapParticleFilter(model, n_particles=50, ess_threshold=1.0)
    state = f1.step(f1.init(mean, cov, None, g), traj.observations[:, 0], g)
    assert state.resampled.all()
    torch.testing.assert_close(state.log_weights, torch.full_like(state.log_weights, -torch.log(torch.tensor(50.0)).item()))


def test_bpf_regularization_jitters_resampled_particles_only():
    model = random_lg(2, 1, seed=11)
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(2, 1, g)
    mean, cov = model.initial_belief(traj.states[:, 0])
    f = BootstrapParticleFilter(model, n_particles=200, ess_threshold=1.0, regularization=[1e-2, 0.0])
    state = f.step(f.init(mean, cov, None, g), traj.observations[:, 0], g)
    # after resampling without jitter particles would be duplicated; coordinate 0 is jittered, 1 is not
    n_unique0 = torch.unique(state.particles[0, :, 0]).numel()
    n_unique1 = torch.unique(state.particles[0, :, 1]).numel()
    assert n_unique0 == 200 and n_unique1 < 200
