"""Stochastic volatility: densities against the closed forms and ``particles``' StochVol, the two
Gaussian forms and the log-squared transform, learnable parameters, the zero-slope warning of the
flow filters, and the particle filters' log-likelihood against an exact grid filter."""

import math
import warnings

import pytest
import torch

import torchflow.filters as F
from experiments.grid_filter import grid_filter
from torchflow.core.errors import ArgumentError
from torchflow.core.linearize import jacobian
from torchflow.models import StochasticVolatility
from torchflow.models.stochastic_volatility import LOG_CHI2_MEAN, LOG_CHI2_VAR
from torchflow.proposals.flow import check_informative

f64 = dict(dtype=torch.float64)


def _z_scale_check(log_z_hat: torch.Tensor, log_z: float, k: float = 3.0):
    """``exp(log Zhat - log Z)`` averages 1 (the particle estimate of Z is unbiased; log Zhat is not):
    its mean over trials is within ``k`` standard errors of 1. Returns (mean, SE)."""
    r = torch.exp(log_z_hat - log_z)
    mean, se = float(r.mean()), float(r.std() / math.sqrt(r.numel()))
    assert abs(mean - 1) < k * se, (mean, se)
    return mean, se


def _series(T=100, seed=0, **kw):
    model = StochasticVolatility(**kw)
    traj = model.simulate(1, T, torch.Generator().manual_seed(seed))
    return model, traj


# ---- the model's laws ------------------------------------------------------------------------


def test_densities_are_the_closed_forms_and_the_stationary_law():
    m = StochasticVolatility(mu=-0.5, rho=0.8, sigma=0.3)
    x, xn, y = (
        torch.tensor([[-1.0], [0.2]], **f64),
        torch.tensor([[-0.7], [0.4]], **f64),
        torch.tensor([[0.3], [-2.0]], **f64),
    )
    mean = -0.5 + 0.8 * (x + 0.5)
    want = -0.5 * math.log(2 * math.pi * 0.09) - (xn - mean).squeeze(-1) ** 2 / (2 * 0.09)
    assert torch.allclose(m.transition_log_prob(xn, x), want, atol=1e-14)
    want = -0.5 * (math.log(2 * math.pi) + x.squeeze(-1)) - y.squeeze(-1) ** 2 / (2 * x.squeeze(-1).exp())
    assert torch.allclose(m.measurement_log_prob(y, x), want, atol=1e-14)
    b_mean, b_cov = m.initial_belief(torch.zeros(3, 1, **f64))
    assert torch.allclose(b_mean, torch.full((3, 1), -0.5, **f64))
    assert torch.allclose(b_cov, torch.full((3, 1, 1), 0.09 / (1 - 0.64), **f64))


def test_densities_agree_with_particles_stochvol():
    ssm = pytest.importorskip("particles.state_space_models")
    np = pytest.importorskip("numpy")
    ref = ssm.StochVol()  # its defaults are ours
    m = StochasticVolatility()
    assert (float(m.mu), float(m.rho), float(m.sigma)) == (ref.mu, ref.rho, ref.sigma)
    xp, x, y = np.array([-1.5, -1.0, 0.3]), np.array([-1.4, -0.9, 0.1]), np.array([0.5, -0.2, 1.0])
    col = lambda a: torch.tensor(a, **f64).reshape(-1, 1)
    assert np.allclose(m.transition_log_prob(col(x), col(xp)).numpy(), ref.PX(1, xp).logpdf(x), atol=1e-12)
    assert np.allclose(m.measurement_log_prob(col(y), col(x)).numpy(), ref.PY(1, xp, x).logpdf(y), atol=1e-12)
    assert math.isclose(float(m.stationary_var().sqrt()), ref.sig0(), rel_tol=1e-12)


def test_simulated_states_have_the_stationary_law():
    m = StochasticVolatility()
    traj = m.simulate(4000, 3, torch.Generator().manual_seed(0))
    x = traj.states[:, 3, 0]  # independent over trials
    var = float(m.stationary_var())
    assert abs(float(x.mean()) + 1.02) < 4 * math.sqrt(var / x.numel())
    assert abs(float(x.var()) / var - 1) < 4 * math.sqrt(2 / x.numel())


def test_the_log_squared_observation_is_the_state_plus_a_log_chi_square():
    """z - x has mean psi(1/2) + log 2 and variance pi^2 / 2; the density of z integrates to 1 and
    is p(y | x) |y| at y = exp(z / 2)."""
    m = StochasticVolatility(gaussian_form="log_squared")
    x = torch.full((200000, 1), -0.7, **f64)
    w = (m.sample_measurement(x, torch.Generator().manual_seed(0)) - x).squeeze(-1)
    n = w.numel()
    assert abs(float(w.mean()) - LOG_CHI2_MEAN) < 4 * math.sqrt(LOG_CHI2_VAR / n)
    assert abs(float(w.var()) / LOG_CHI2_VAR - 1) < 0.03  # the log chi^2's kurtosis is 7: SE of the ratio ~0.006
    assert math.isclose(
        LOG_CHI2_MEAN, float(torch.special.digamma(torch.tensor(0.5, **f64))) + math.log(2), abs_tol=1e-14
    )
    zs = torch.linspace(-40.0, 8.0, 200001, **f64).reshape(-1, 1)
    x0 = torch.full_like(zs, -0.7)
    dens = m.log_squared_log_prob(zs, x0).exp()
    assert abs(float(torch.trapezoid(dens, zs.squeeze(-1))) - 1) < 1e-8
    y = torch.exp(zs / 2)
    returns = StochasticVolatility()
    assert torch.allclose(
        m.log_squared_log_prob(zs, x0), returns.measurement_log_prob(y, x0) + torch.log(y).squeeze(-1), atol=1e-10
    )


def test_the_log_squared_form_weighs_with_the_returns_density():
    """measurement_log_prob reads y^2 back from z: the returns' density, for a zero return too (offset)."""
    y = torch.tensor([[0.8], [-0.05], [0.0]], **f64)
    x = torch.tensor([[-1.0], [0.5], [-2.0]], **f64)
    returns, logsq = StochasticVolatility(), StochasticVolatility(gaussian_form="log_squared", offset=1e-6)
    z = logsq.transform_observations(y)
    assert torch.allclose(z, torch.log(y**2 + 1e-6))
    assert torch.allclose(logsq.measurement_log_prob(z, x), returns.measurement_log_prob(y, x), atol=1e-9)
    assert torch.equal(returns.transform_observations(y), y)
    with pytest.raises(
        ArgumentError,
        match=r"1 value\(s\) whose log-square is not finite \(first at index \(2, 0\)"
        r".*offset > 0",
    ):
        StochasticVolatility(gaussian_form="log_squared").transform_observations(y)


def test_both_forms_give_the_bootstrap_filter_the_same_weights_and_evidence():
    returns, traj = _series(T=40)
    logsq = StochasticVolatility(gaussian_form="log_squared")
    mean, cov = returns.initial_belief(traj.states[:, 0])
    a = F.BootstrapParticleFilter(returns, n_particles=100)(
        traj.observations, mean, cov, torch.Generator().manual_seed(1)
    )
    z = logsq.transform_observations(traj.observations)
    b = F.BootstrapParticleFilter(logsq, n_particles=100)(z, mean, cov, torch.Generator().manual_seed(1))
    assert torch.allclose(a.log_evidence, b.log_evidence, atol=1e-9)
    assert torch.allclose(a.estimates, b.estimates, atol=1e-9)


def test_the_gaussian_forms_and_their_declared_structure():
    x = torch.tensor([[[-1.0], [0.4]], [[0.0], [2.0]]], **f64)  # (B, N, 1)
    returns, logsq = StochasticVolatility(), StochasticVolatility(gaussian_form="log_squared")
    assert returns.structure.measurement_noise == "state_dependent_diagonal"
    assert logsq.structure.measurement_noise == "scalar" and logsq.structure.measurement_noise_scale == LOG_CHI2_VAR
    for s in (returns.structure, logsq.structure):
        assert s.gaussian_transition and not s.linear_dynamics and not s.linear_measurement
        assert s.measurement_jacobian_diagonal
    assert torch.equal(returns.measure(x), torch.zeros_like(x))
    assert torch.allclose(returns.measurement_cov(x), x.exp().unsqueeze(-1))
    with pytest.raises(ArgumentError, match="R = exp\\(x\\) depends on the state"):
        returns.measurement_cov()
    assert torch.allclose(logsq.measure(x), x - 1.2703628454614782)
    assert torch.allclose(logsq.measurement_cov(), torch.full((1, 1), math.pi**2 / 2, **f64))
    for m in (returns, logsq):  # the analytic Jacobians and diagonal forms are torch.func's and the dense ones
        assert torch.allclose(m.measurement_jacobian(x), jacobian(m.measure, x))
        assert torch.allclose(m.transition_jacobian(x), jacobian(m.transition_mean, x))
        h, J, sd = m.linearize_measurement_diagonal(x)
        assert torch.allclose(h, m.measure(x)) and torch.allclose(J, m.measurement_jacobian(x).squeeze(-1))
        assert torch.allclose(sd, m.measurement_scale_tril(x).squeeze(-1).expand_as(sd))


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(rho=1.0), r"rho: expected a number in \(-1, 1\)"),
        (dict(rho=-1.5), r"rho: expected a number in \(-1, 1\)"),
        (dict(sigma=0.0), "sigma: expected a finite number > 0"),
        (dict(mu=float("nan")), "mu: expected a finite number"),
        (dict(gaussian_form="log"), r"gaussian_form: expected one of \('returns', 'log_squared'\)"),
        (dict(offset=-1e-3), "offset: expected a finite number >= 0"),
        (dict(learnable=["phi"]), "learnable: expected a bool or a subset of"),
    ],
)
def test_bad_settings_are_named(kw, match):
    with pytest.raises(ArgumentError, match=match):
        StochasticVolatility(**kw)


def test_learnable_parameters_stay_valid_and_get_gradients():
    m = StochasticVolatility(learnable=True)
    names = {n for n, p in m.named_parameters()}
    assert names == {"mu", "parametrizations.rho.original", "parametrizations.sigma.original"}
    rho, sigma = float(m.rho.detach()), float(m.sigma.detach())
    assert math.isclose(rho, 0.9702, rel_tol=1e-12) and math.isclose(sigma, 0.178, rel_tol=1e-12)
    with torch.no_grad():  # any raw value short of the sigmoid's float64 saturation (|raw| > ~37) is a valid model
        m.parametrizations.rho.original.fill_(15.0)
        m.parametrizations.sigma.original.fill_(-15.0)
    assert -1 < float(m.rho.detach()) < 1 and float(m.sigma.detach()) > 0 and torch.isfinite(m.stationary_var())
    m = StochasticVolatility(learnable=["sigma"])
    assert {n for n, _ in m.named_parameters()} == {"parametrizations.sigma.original"} and "rho" in dict(
        m.named_buffers()
    )
    m = StochasticVolatility(learnable=True)
    traj = m.simulate(2, 20, torch.Generator().manual_seed(0))
    mean, cov = m.initial_belief(traj.states[:, 0])
    out = F.BootstrapParticleFilter(m, n_particles=50)(traj.observations, mean, cov, torch.Generator().manual_seed(1))
    out.log_evidence.sum().backward()
    for n, p in m.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs() > 0, n


# ---- the zero-slope warning ------------------------------------------------------------------


def test_a_flow_on_the_returns_form_does_not_move_particles():
    """h(x) = 0: the flows' drift vanishes and PF-PF is the bootstrap PF, draw for draw."""
    m, traj = _series(T=20)
    mean, cov = m.initial_belief(traj.states[:, 0])
    a = F.BootstrapParticleFilter(m, n_particles=64)(traj.observations, mean, cov, torch.Generator().manual_seed(1))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        b = F.ParticleFlowParticleFilter(m, flow="ledh", n_particles=64)(
            traj.observations, mean, cov, torch.Generator().manual_seed(1)
        )
    assert torch.allclose(a.log_evidence, b.log_evidence, atol=1e-10)


@pytest.mark.parametrize(
    "make",
    [
        lambda m: F.ParticleFlowParticleFilter(m, flow="ledh", n_particles=8),
        lambda m: F.ParticleFlowParticleFilter(m, flow="edh", n_particles=8),
        lambda m: F.ParticleFlowFilter(m, n_particles=8),
    ],
    ids=["pfpf_ledh", "pfpf_edh", "ledh"],
)
def test_flow_filters_warn_once_of_a_zero_slope_measurement(make):
    m = StochasticVolatility()
    f = make(m)
    mean, _ = m.initial_belief(torch.zeros(3, 1, **f64))
    with pytest.warns(UserWarning) as caught:
        check_informative(f.proposal, mean, f.name)
    assert len(caught) == 1
    text = str(caught[0].message)
    for part in (
        f.name,
        "StochasticVolatility",
        "zero Jacobian",
        "will not move the particles",
        "bootstrap particle filter",
        "gaussian_form='log_squared'",
    ):
        assert part in text, part
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_informative(f.proposal, mean, f.name)  # once per filter
        g = make(StochasticVolatility(gaussian_form="log_squared"))  # slope one: informative
        check_informative(g.proposal, mean, g.name)
        b = F.BootstrapParticleFilter(m, n_particles=8)  # not a flow: nothing to say
        check_informative(b.proposal, mean, b.name)
        check_informative(None, mean, "KalmanFilter")


def test_forward_warns_once_of_a_zero_slope_measurement():
    """Through ``forward``: the PF-PF says it once over two calls; the bootstrap PF is silent."""
    m = StochasticVolatility()
    traj = m.simulate(2, 3, torch.Generator().manual_seed(0))
    mean, cov = m.initial_belief(traj.states[:, 0])
    f = F.ParticleFlowParticleFilter(m, flow="ledh", n_particles=8)
    with pytest.warns(UserWarning, match="zero Jacobian") as caught:
        for seed in (1, 2):
            f(traj.observations, mean, cov, torch.Generator().manual_seed(seed))
    assert sum("zero Jacobian" in str(w.message) for w in caught) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        F.BootstrapParticleFilter(m, n_particles=8)(traj.observations, mean, cov, torch.Generator().manual_seed(1))


# ---- log-likelihoods against the exact grid filter -------------------------------------------


def test_the_grid_filter_has_converged():
    m, traj = _series(T=100)
    y = traj.observations[0]
    ll = [grid_filter(m, y, n_grid=n)[0] for n in (1000, 2000)]
    assert abs(ll[0] - ll[1]) < 1e-7


def test_the_bootstrap_filter_log_likelihood_agrees_with_the_grid_filter():
    """200 runs of the bootstrap PF (N = 500) on one simulated series of 100 steps: their mean
    likelihood ratio to the grid filter's is 1 within 3 Monte Carlo standard errors."""
    m, traj = _series(T=100)
    exact, _ = grid_filter(m, traj.observations[0])
    B = 200
    obs = traj.observations.expand(B, -1, -1)
    mean, cov = m.initial_belief(traj.states[:, 0].expand(B, -1))
    out = F.BootstrapParticleFilter(m, n_particles=500)(obs, mean, cov, torch.Generator().manual_seed(3))
    _z_scale_check(out.log_evidence, exact)
    assert abs(float(out.log_evidence.mean()) - exact) < 1.0  # and on the log scale: a Jensen gap of ~var/2


def test_pfpf_on_the_log_squared_form_agrees_with_the_grid_filter():
    """PF-PF(LEDH) moves particles with the log-squared Gaussian form and weighs them with the
    returns' density: its likelihood estimate is the returns' and unbiased."""
    m, traj = _series(T=60, seed=1, gaussian_form="log_squared")
    z = traj.observations
    exact, _ = grid_filter(m, z[0])
    returns = StochasticVolatility()
    y_abs = torch.exp(z[0] / 2)  # |y|: the returns form's exact value is the same number
    assert abs(grid_filter(returns, y_abs)[0] - exact) < 1e-9
    B = 100
    mean, cov = m.initial_belief(traj.states[:, 0].expand(B, -1))
    out = F.ParticleFlowParticleFilter(m, flow="ledh", n_particles=100)(
        z.expand(B, -1, -1), mean, cov, torch.Generator().manual_seed(4)
    )
    _z_scale_check(out.log_evidence, exact)


def test_the_log_squared_likelihood_relation():
    """log p(z_{1:T}) = log p(y_{1:T}) + sum_t log|y_t| for z = log y^2 (y -> z is two-to-one, so
    p(y) = p(z) / |y|, not 2 p(z) / |y|)."""
    m, traj = _series(T=80, seed=2)
    y = traj.observations[0]
    log_py, _ = grid_filter(m, y)
    logsq = StochasticVolatility(gaussian_form="log_squared")
    z = logsq.transform_observations(y)
    log_pz, _ = grid_filter(logsq, z, measurement_log_prob=logsq.log_squared_log_prob)
    assert abs(log_pz - (log_py + float(torch.log(y.abs()).sum()))) < 1e-8
    assert abs(log_pz - (log_py + float(torch.log(y.abs() / 2).sum()))) > 80 * math.log(2) - 1e-6


def test_per_trial_parameters_give_the_numbers_of_separate_calls():
    """mu, rho, sigma as one value per trial (MCMC chains): the bootstrap PF's per-trial results
    equal separate calls with each trial's scalar values and its own stream, bit for bit up to
    round-off; the EKF too (the Gaussian form's transition reads them)."""
    from torchflow.core.random import TrialStreams
    from torchflow.inference import per_trial_values

    values = {
        "mu": torch.tensor([-1.0, -0.5, 0.2], **f64),
        "rho": torch.tensor([0.9, 0.5, -0.3], **f64),
        "sigma": torch.tensor([0.2, 0.4, 0.8], **f64),
    }
    m = StochasticVolatility()
    y = StochasticVolatility().simulate(1, 12, torch.Generator().manual_seed(0)).observations.expand(3, -1, -1)
    f = F.BootstrapParticleFilter(m, n_particles=64)
    with per_trial_values(m, values):
        mean, cov = m.declared_prior(3)
        together = f(y, mean, cov, TrialStreams(5, 3, "sv"))
        ekf_together = F.ExtendedKalmanFilter(m)(y, mean, cov).log_evidence
    for b in range(3):
        mb = StochasticVolatility(**{k: float(v[b]) for k, v in values.items()})
        mean_b, cov_b = mb.declared_prior(1)
        alone = F.BootstrapParticleFilter(mb, n_particles=64)(
            y[b : b + 1], mean_b, cov_b, TrialStreams(5, 3, "sv").select([b])
        )
        torch.testing.assert_close(alone.log_evidence[0], together.log_evidence[b], rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(alone.estimates[0], together.estimates[b], rtol=1e-12, atol=1e-12)
        ekf_alone = F.ExtendedKalmanFilter(mb)(y[b : b + 1], mean_b, cov_b).log_evidence[0]
        torch.testing.assert_close(ekf_alone, ekf_together[b], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("flow", ["ledh", "edh"])
def test_per_trial_parameters_in_the_flows(flow):
    """PF-PF on the log-squared form with per-trial mu, rho, sigma: the numbers of separate calls."""
    from torchflow.core.random import TrialStreams
    from torchflow.inference import per_trial_values

    values = {
        "mu": torch.tensor([-1.0, 0.3], **f64),
        "rho": torch.tensor([0.9, 0.4], **f64),
        "sigma": torch.tensor([0.2, 0.6], **f64),
    }
    m = StochasticVolatility(gaussian_form="log_squared")
    z = m.simulate(1, 8, torch.Generator().manual_seed(0)).observations.expand(2, -1, -1)
    f = F.ParticleFlowParticleFilter(m, flow=flow, n_particles=16)
    with per_trial_values(m, values):
        mean, cov = m.declared_prior(2)
        together = f(z, mean, cov, TrialStreams(5, 2, "sv"))
    for b in range(2):
        mb = StochasticVolatility(gaussian_form="log_squared", **{k: float(v[b]) for k, v in values.items()})
        mean_b, cov_b = mb.declared_prior(1)
        alone = F.ParticleFlowParticleFilter(mb, flow=flow, n_particles=16)(
            z[b : b + 1], mean_b, cov_b, TrialStreams(5, 2, "sv").select([b])
        )
        torch.testing.assert_close(alone.log_evidence[0], together.log_evidence[b], rtol=1e-10, atol=1e-10)


def test_a_slope_zero_only_at_the_prior_mean_is_not_flat():
    """``h(x) = x^3 / 20`` has a zero Jacobian at a prior mean of 0 but not one standard deviation
    away: a flow linearised at the particles moves them, so there is no warning (the custom-model
    guide's example); at a prior whose variance is zero the slope is zero everywhere it is asked."""
    from torchflow.models import GaussianStateSpaceModel, Structure

    class Cubic(GaussianStateSpaceModel):
        state_dim = obs_dim = 1
        structure = Structure(measurement_noise="scalar")

        def __init__(self):
            super().__init__()
            self.register_buffer("Q", torch.eye(1, **f64))

        def transition_mean(self, x):
            return x / 2

        def transition_cov(self, x=None):
            return self.Q

        def measure(self, x):
            return x**3 / 20

        def measurement_cov(self, x=None):
            return self.Q

    mean, cov = torch.zeros(3, 1, **f64), torch.eye(1, **f64).expand(3, 1, 1)
    f = F.ParticleFlowParticleFilter(Cubic(), flow="ledh", n_particles=8)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_informative(f.proposal, mean, f.name, cov)
        check_informative(
            F.ParticleFlowParticleFilter(Cubic(), flow="ledh", n_particles=8).proposal, mean, f.name
        )  # no cov: a unit step
    with pytest.warns(UserWarning, match="zero Jacobian"):
        check_informative(F.ParticleFlowParticleFilter(Cubic(), n_particles=8).proposal, mean, f.name, 0 * cov)
