"""Particle MCMC (:mod:`torchflow.inference`): PMMH on batched chains against the exact posterior."""
import math

import pytest
import torch
from torch.distributions import Normal, Uniform

from torchflow.filters import BootstrapParticleFilter, ExtendedKalmanFilter
from torchflow.inference import effective_sample_size, pmmh, rhat
from torchflow.inference.params import per_trial_values
from torchflow.linalg import standard_normal
from torchflow.models import GaussianStateSpaceModel, Structure

F64 = torch.float64


class ScalarAR(GaussianStateSpaceModel):
    """``x_t = a x_(t-1) + sqrt(q) v_t``, ``z_t = x_t + sqrt(r) w_t``, with ``a`` per trial
    (``(B,)`` or a scalar): linear and Gaussian, so the EKF is the exact Kalman filter."""

    state_dim = obs_dim = 1
    structure = Structure(measurement_noise="scalar", linear_measurement=True)
    per_trial_parameters = ("a",)

    def __init__(self, a=0.8, q=0.5, r=0.5):
        super().__init__()
        self.register_buffer("a", torch.tensor(a, dtype=F64))
        self.register_buffer("q", torch.tensor(q, dtype=F64))
        self.register_buffer("r", torch.tensor(r, dtype=F64))

    def _a(self, x):  # a (B,) viewed against x (B, ..., 1)
        return self.a.reshape(*self.a.shape, *([1] * (x.dim() - self.a.dim())))

    def transition_mean(self, x):
        return self._a(x) * x

    def transition_jacobian(self, x):
        return (self._a(x) * torch.ones_like(x)).unsqueeze(-1)

    def transition_cov(self, x=None):
        return self.q.reshape(1, 1)

    def measurement_matrix(self):
        return torch.ones(1, 1, dtype=F64, device=self.a.device)

    def measurement_cov(self, x=None):
        return self.r.reshape(1, 1)

    def initial_state(self, batch_size, generator=None):
        return standard_normal((batch_size, 1), dtype=F64, device=self.a.device, generator=generator)

    def initial_belief(self, states0, generator=None):
        B = states0.shape[0]
        return states0.new_zeros(B, 1), torch.ones(B, 1, 1, dtype=F64)


def _data(T=40):
    model = ScalarAR(a=0.8)
    traj = model.simulate(1, T, torch.Generator().manual_seed(3))
    return model, traj.observations[0]


def _exact_posterior(model, obs, prior):
    """Quadrature: the exact (Kalman) log-likelihood on a grid of a, all grid points as trials."""
    grid = torch.linspace(-0.995, 0.995, 800, dtype=F64)
    mean, cov = torch.zeros(800, 1, dtype=F64), torch.ones(800, 1, 1, dtype=F64)
    with per_trial_values(model, {"a": grid}):
        ll = ExtendedKalmanFilter(model)(obs.expand(800, -1, -1), mean, cov).log_evidence
    logp = ll + prior.log_prob(grid)
    w = torch.softmax(logp, 0)
    m = (w * grid).sum()
    return float(m), float(((w * (grid - m) ** 2).sum()).sqrt())


@pytest.mark.parametrize("estimator", ["exact", "bpf"])
def test_pmmh_matches_the_exact_posterior(estimator):
    """The posterior mean of a under PMMH with C = 8 chains agrees with quadrature within 4 Monte
    Carlo standard errors (sd / sqrt(ESS)); the standard deviation within 15 %. The particle filter's
    log-likelihood estimate (N = 400, T = 40) has a standard deviation of about 0.6 at the
    posterior mean."""
    model, obs = _data()
    prior = Uniform(torch.tensor(-1.0, dtype=F64), torch.tensor(1.0, dtype=F64))
    m_exact, s_exact = _exact_posterior(model, obs, prior)
    filt = (ExtendedKalmanFilter(model) if estimator == "exact"
            else BootstrapParticleFilter(model, n_particles=400))
    mean0, cov0 = torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64)
    res = pmmh(filt, obs, (mean0, cov0), {"a": prior}, 0, n_chains=8, n_iterations=300, n_adapt=100)
    a = res.samples["a"]
    assert a.shape == (8, 300) and res.log_likelihood.shape == (8, 300)
    ess = float(res.ess["a"])
    se = float(a.std()) / math.sqrt(ess)
    assert abs(float(a.mean()) - m_exact) < 4 * se, (float(a.mean()), m_exact, se, ess)
    assert abs(float(a.std()) / s_exact - 1) < 0.15, (float(a.std()), s_exact)
    assert float(res.rhat["a"]) < 1.1 and ess > 100
    assert ((res.acceptance > 0.1) & (res.acceptance < 0.9)).all()
    assert float(model.a) == pytest.approx(0.8)  # the model's own value is left alone


def test_diagnostics_on_known_chains():
    g = torch.Generator().manual_seed(0)
    iid = torch.randn(4, 2000, generator=g, dtype=F64)
    assert abs(float(rhat(iid)) - 1) < 0.01
    assert 6000 < float(effective_sample_size(iid)) < 10000
    # AR(1) chains with phi = 0.9: ESS about n (1 - phi) / (1 + phi)
    x = torch.zeros(4, 4000, dtype=F64)
    e = torch.randn(4, 4000, generator=g, dtype=F64)
    for t in range(1, 4000):
        x[:, t] = 0.9 * x[:, t - 1] + e[:, t]
    ess = float(effective_sample_size(x))
    assert 0.5 * 16000 / 19 < ess < 1.6 * 16000 / 19
    stuck = torch.stack([torch.zeros(500, dtype=F64), torch.ones(500, dtype=F64) + 0.01 * torch.randn(500, generator=g,
                                                                                                    dtype=F64)])
    assert float(rhat(stuck)) > 1.5


def test_pmmh_errors():
    model, obs = _data(10)
    filt = ExtendedKalmanFilter(model)
    prior0 = (torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64))
    with pytest.raises(ValueError, match="does not declare 'q' as a per-trial parameter"):
        pmmh(filt, obs, prior0, {"q": Uniform(0.1, 1.0)}, 0)
    with pytest.raises(TypeError, match=r"priors\['a'\]: expected a torch.distributions.Distribution"):
        pmmh(filt, obs, prior0, {"a": 0.5}, 0)
    with pytest.raises(ValueError, match="observations: expected one series"):
        pmmh(filt, obs.expand(2, -1, -1), prior0, {"a": Normal(0.0, 1.0)}, 0)
    with pytest.raises(ValueError, match="n_chains"):
        pmmh(filt, obs, prior0, {"a": Normal(0.0, 1.0)}, 0, n_chains=0)


def test_pmmh_same_seed_same_chains():
    model, obs = _data(10)
    f = BootstrapParticleFilter(model, n_particles=50)
    prior0 = (torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64))
    runs = [pmmh(f, obs, prior0, {"a": Uniform(torch.tensor(-1.0, dtype=F64), torch.tensor(1.0, dtype=F64))}, 7,
                 n_chains=3, n_iterations=8, n_adapt=4) for _ in range(2)]
    assert torch.equal(runs[0].samples["a"], runs[1].samples["a"])
    other = pmmh(f, obs, prior0, {"a": Uniform(torch.tensor(-1.0, dtype=F64), torch.tensor(1.0, dtype=F64))}, 8,
                 n_chains=3, n_iterations=8, n_adapt=4)
    assert not torch.equal(runs[0].samples["a"], other.samples["a"])


def test_conditional_smc_leaves_the_smoothing_law_invariant():
    """16 chains of 150 conditional-SMC sweeps (N = 20) on a linear-Gaussian series: the average
    path (after 30 sweeps) is within 4 standard errors of the RTS smoothed means at every step and
    coordinate (the standard error from the spread of the 16 chains' averages)."""
    from conftest import random_lg
    from torchflow.filters import KalmanFilter
    from torchflow.inference import conditional_smc
    from torchflow.random import TrialStreams
    from torchflow.smoothing import smooth

    model = random_lg(2, 2, seed=3)
    C, T = 16, 8
    traj = model.simulate(1, T, torch.Generator().manual_seed(0))
    obs = traj.observations.expand(C, -1, -1)
    mean, cov = model.initial_belief(traj.states[:, 0].expand(C, -1))
    cov = cov + torch.eye(2, dtype=F64)
    exact = smooth(KalmanFilter(model), obs[:1], mean[:1], cov[:1]).means[0]
    path = torch.zeros(C, T + 1, 2, dtype=F64)
    total = torch.zeros_like(path)
    for it in range(150):
        path = conditional_smc(model, obs, mean, cov, path, 20, TrialStreams(it, C, "csmc"))
        if it >= 30:
            total += path
    avg = total / 120
    z = ((avg.mean(0) - exact) / (avg.std(0) / math.sqrt(C))).abs()
    assert float(z.max()) < 4, float(z.max())
    assert float((avg.std(0) / math.sqrt(C)).max()) < 0.15


def test_particle_gibbs_matches_the_exact_posterior():
    from torchflow.inference import particle_gibbs

    model, obs = _data()
    prior = Uniform(torch.tensor(-1.0, dtype=F64), torch.tensor(1.0, dtype=F64))
    m_exact, s_exact = _exact_posterior(model, obs, prior)
    res = particle_gibbs(model, obs, (torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64)), {"a": prior}, 0,
                         n_particles=30, n_chains=8, n_iterations=300, n_adapt=100)
    a = res.samples["a"]
    ess = float(res.ess["a"])
    se = float(a.std()) / math.sqrt(ess)
    assert abs(float(a.mean()) - m_exact) < 4 * se, (float(a.mean()), m_exact, se, ess)
    assert abs(float(a.std()) / s_exact - 1) < 0.2, (float(a.std()), s_exact)
    assert ess > 50 and float(res.rhat["a"]) < 1.1
