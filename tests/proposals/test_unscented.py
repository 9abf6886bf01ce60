"""The unscented particle filter: the ParticleFilter with UnscentedProposal (one proposal file)."""

import math

import pytest
import torch
from conftest import ROOT, mild_lg, random_lg, replicated, simulate_with_belief
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from torchflow.core.covariances import ParticleCovariance
from torchflow.filters import KalmanFilter, ParticleFilter
from torchflow.models import AcousticTracking
from torchflow.proposals import UnscentedProposal


def upf(model, n=64, **kw):
    return ParticleFilter(model, UnscentedProposal(model, **kw), n_particles=n)


@pytest.mark.parametrize("prior", ["posterior", "transition"])
def test_upf_log_evidence_unbiased_on_lg(prior):
    """E[Z_hat / Z] = 1 within 4 standard errors over 400 runs on the same data (the weight is
    p(x | x') p(z | x) / q with q the per-particle UKF's Gaussian, so Z_hat is unbiased whatever the
    tracker and whatever it predicts from); Z from the Kalman filter."""
    model = mild_lg()
    obs, mean, cov = replicated(model, 400, 6)
    logz = KalmanFilter(model)(obs[:1], mean[:1], cov[:1]).log_evidence
    r = torch.exp(upf(model, prior=prior)(obs, mean, cov, torch.Generator().manual_seed(1)).log_evidence - logz)
    se = r.std() / math.sqrt(r.numel())
    assert abs(float(r.mean()) - 1) < 4 * float(se), (float(r.mean()), float(se))
    assert float(se) < 0.05


def test_upf_without_proposal_density_would_be_biased(monkeypatch):
    """The test above can fail: dropping log q from the weight moves Z_hat far past its tolerance."""
    model = mild_lg()
    obs, mean, cov = replicated(model, 400, 6)
    logz = KalmanFilter(model)(obs[:1], mean[:1], cov[:1]).log_evidence
    real = UnscentedProposal.propose

    def no_q(self, *a, **k):
        out = real(self, *a, **k)
        out.log_q = torch.zeros_like(out.log_q)
        return out

    monkeypatch.setattr(UnscentedProposal, "propose", no_q)
    log_r = upf(model)(obs, mean, cov, torch.Generator().manual_seed(1)).log_evidence - logz
    assert abs(float(log_r.median())) > 2, float(log_r.median())


def test_upf_mean_tracks_the_kalman_filter():
    """On a linear-Gaussian model the UPF's estimates are the KF's posterior means within Monte Carlo
    error: |mean error| over 20 trials x 10 steps below 5 standard errors of the per-trial errors."""
    model = random_lg()
    traj, mean, cov, _ = simulate_with_belief(model, 20, 10)
    kf = KalmanFilter(model)(traj.observations, mean, cov).estimates
    est = upf(model, n=2000)(traj.observations, mean, cov, torch.Generator().manual_seed(0)).estimates
    err = (est - kf).flatten()
    se = err.std() / math.sqrt(err.numel())
    assert abs(float(err.mean())) < 5 * float(se) and float(err.abs().max()) < 0.3


def test_ekf_and_ukf_proposals_agree_on_a_linear_model():
    """Both trackers are exact on a linear-Gaussian model, so the EKF-PF and the UPF draw the same
    particles from the same random numbers (round-off aside); their per-particle covariances are
    declared identical (one (B, 1, d, d) per trial)."""
    model = random_lg()
    traj, mean, cov, _ = simulate_with_belief(model, 4, 5)
    runs = [
        upf(model, n=32, covariance=c)(traj.observations, mean, cov, torch.Generator().manual_seed(3))
        for c in ("ukf", "ekf")
    ]
    torch.testing.assert_close(runs[0].estimates, runs[1].estimates, rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(runs[0].log_evidence, runs[1].log_evidence, rtol=1e-8, atol=1e-10)
    carry = UnscentedProposal(model).init_carry(cov, 32)
    assert isinstance(carry, ParticleCovariance) and carry.identical and carry.matrix.shape == (4, 1, 3, 3)


def test_upf_carries_a_covariance_per_particle_on_a_nonlinear_model():
    model = AcousticTracking()
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(2, 2, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    f = upf(model, n=16)
    s = f.init(mean, cov, None, torch.Generator().manual_seed(0))
    s = f.step(s, traj.observations[:, 0], torch.Generator().manual_seed(1))
    assert s.cov.matrix.shape == (2, 16, 16, 16) and not s.cov.identical
    assert torch.isfinite(s.estimate).all() and f.stream_name == "upf"


def test_upf_config_builds_the_filter():
    with initialize_config_dir(str(ROOT / "configs"), version_base="1.3"):
        cfg = compose("config", overrides=["model=acoustic", "filter=[upf]", "filter.upf.proposal.covariance=ekf"])
    model = instantiate(cfg.model)
    f = instantiate(cfg.filter.upf, model=model)
    assert isinstance(f, ParticleFilter) and isinstance(f.proposal, UnscentedProposal)
    assert f.proposal.covariance == "ekf" and f.proposal.model is model


def test_upf_bad_covariance_is_named():
    with pytest.raises(ValueError, match="covariance: expected one of"):
        UnscentedProposal(mild_lg(), covariance="pf")


def test_transition_prior_is_the_linearised_optimal_proposal():
    """prior="transition" carries nothing and, on a linear-Gaussian model, draws from the exact
    optimal proposal p(x_k | x_{k-1}, z_k): the KF update of N(F x, Q) with z (checked against
    kalman_update); a bad prior name is refused naming the argument."""
    from torchflow.core.trackers import kalman_update

    model = random_lg()
    prop = UnscentedProposal(model, prior="transition")
    assert prop.init_carry(torch.eye(3).expand(2, 3, 3), 8) is None
    x = torch.randn(2, 8, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    z = torch.randn(2, model.obs_dim, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    out = prop.propose(x, None, None, z, None, torch.Generator().manual_seed(2))
    m = model.transition_mean(x)
    mean, cov, _ = kalman_update(
        m,
        model.transition_cov(m),
        z.unsqueeze(1),
        model.measure(m),
        model.measurement_matrix(),
        model.measurement_cov(m),
    )
    xi = torch.randn(x.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    L = torch.linalg.cholesky(cov)
    torch.testing.assert_close(out.particles, mean + (L @ xi.unsqueeze(-1)).squeeze(-1), rtol=1e-7, atol=1e-9)
    with pytest.raises(ValueError, match="prior"):
        UnscentedProposal(model, prior="bogus")
