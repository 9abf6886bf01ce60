"""Bootstrap PF against the exact Kalman posterior on a small linear-Gaussian model."""

import math

import pytest
import torch
from conftest import random_lg, simulate_with_belief

from torchflow.filters import BootstrapParticleFilter, KalmanFilter


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
    torch.testing.assert_close(
        state.log_weights, torch.full_like(state.log_weights, -torch.log(torch.tensor(50.0)).item())
    )


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


def test_a_collapsed_cloud_is_warned_of_whatever_the_ess():
    """Lorenz-63 has no model noise: resampled copies stay copies, and 20 particles coalesce into one
    point within a few dozen steps while the ESS reads 20 of 20. The run warns, naming the trials and
    the first step. With model noise a degenerate step's copies spread again at the next forecast:
    one collapsed step alone is not warned of (measured: 1 such step per trial in this run)."""
    import warnings

    from torchflow.models import Lorenz63

    model = Lorenz63()
    traj = model.simulate(2, 100, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0])
    with pytest.warns(RuntimeWarning, match=r"collapsed to fewer than 2 distinct particles .* trial 0 from step \d+"):
        res = BootstrapParticleFilter(model, n_particles=20)(
            traj.observations, mean, cov, torch.Generator().manual_seed(1)
        )
    assert bool((res.ess[:, -1] > 19.9).all())  # the ESS does not show it
    noisy = Lorenz63(model_noise=0.5)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning at all
        BootstrapParticleFilter(noisy, n_particles=20)(traj.observations, mean, cov, torch.Generator().manual_seed(1))


def test_relative_regularization_scales_with_the_cloud():
    """Equal weights, resampling forced: the jitter's variance is h^2 times each coordinate's
    weighted variance before resampling (N = 20000: the variance after is (1 + h^2) times the
    cloud's within 5 %, about 5 standard errors), whatever the cloud's scale; h = 0 adds nothing."""
    from torchflow.core.resampling import Resampler

    N = 20000
    g = torch.Generator().manual_seed(0)
    x = torch.randn(1, N, 2, generator=g, dtype=torch.float64) * torch.tensor([1.0, 100.0], dtype=torch.float64)
    lw = torch.full((1, N), -math.log(N), dtype=torch.float64)
    r = Resampler(2, ess_threshold=1.0, regularization_relative=0.5)
    out = r(x, lw, torch.Generator().manual_seed(1))[0]
    ratio = out.var(1) / x.var(1)
    assert bool(((ratio - 1.25).abs() < 0.05 * 1.25).all()), ratio
    lw = torch.log_softmax(torch.randn(1, N, generator=g, dtype=torch.float64), 1)  # unequal: some ancestors repeat
    same = Resampler(2, ess_threshold=1.0, regularization_relative=0.0)(x, lw, torch.Generator().manual_seed(1))[0]
    assert torch.unique(same[0, :, 0]).numel() < N  # copies stay copies
    with pytest.raises(Exception, match="regularization_relative: expected None or a number >= 0"):
        Resampler(2, regularization_relative=-1.0)
