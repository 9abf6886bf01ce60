"""Particle MCMC (:mod:`torchflow.inference`): PMMH on batched chains against the exact posterior."""

import math

import pytest
import torch
from torch.distributions import Normal, Uniform

from torchflow.core.errors import ArgumentError
from torchflow.core.linalg import standard_normal
from torchflow.filters import BootstrapParticleFilter, ExtendedKalmanFilter
from torchflow.inference import effective_sample_size, pmmh, rhat
from torchflow.inference.params import per_trial_values
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
    filt = ExtendedKalmanFilter(model) if estimator == "exact" else BootstrapParticleFilter(model, n_particles=400)
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


def test_pmmh_carries_the_current_likelihood_estimate_and_runs_the_filter_once_per_iteration():
    """Pseudo-marginal MCMC is exact because the current state's likelihood estimate is kept until a
    proposal replaces it; re-estimating it each iteration (Monte Carlo within Metropolis) targets
    another law. So: one filter call per iteration (plus one at the start), and on every rejected
    iteration the recorded log-likelihood is the previous one, bit for bit."""
    model, obs = _data(15)
    filt = BootstrapParticleFilter(model, n_particles=30)
    calls = []
    filt.register_forward_hook(lambda *_: calls.append(1))
    prior = Uniform(torch.tensor(-1.0, dtype=F64), torch.tensor(1.0, dtype=F64))
    prior0 = (torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64))
    res = pmmh(filt, obs, prior0, {"a": prior}, 0, n_chains=4, n_iterations=40, n_adapt=10)
    assert len(calls) == 1 + 10 + 40
    a, ll = res.samples["a"], res.log_likelihood
    stayed = a[:, 1:] == a[:, :-1]
    assert 10 < int(stayed.sum()) < stayed.numel() - 10, int(stayed.sum())  # both kinds of step happened
    assert torch.equal(ll[:, 1:][stayed], ll[:, :-1][stayed])
    assert (ll[:, 1:][~stayed] != ll[:, :-1][~stayed]).all()


@pytest.mark.slow
def test_pmmh_is_exact_where_monte_carlo_within_metropolis_is_not():
    """With a noisy likelihood estimate (bootstrap PF, N = 200, T = 40: log-likelihood standard
    deviation about 1) PMMH still samples the exact posterior: over C = 32 chains of 400 kept draws
    the posterior mean and standard deviation of a agree with quadrature within 4 of their Monte
    Carlo standard errors (sd / sqrt(ESS); relative 1 / sqrt(2 ESS)). Re-estimating the current
    state's likelihood at each iteration (Monte Carlo within Metropolis) fails this, over-dispersed
    and shifted: measured z 9.1 (mean) and 7.0 (sd) here, with the exact sampler's z 0.5 and 0.0
    (ESS 699). The default-tier PMMH tests at N = 400 could not tell the two apart (z 2.97)."""
    model, obs = _data()
    prior = Uniform(torch.tensor(-1.0, dtype=F64), torch.tensor(1.0, dtype=F64))
    m_exact, s_exact = _exact_posterior(model, obs, prior)
    filt = BootstrapParticleFilter(model, n_particles=200)
    prior0 = (torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64))
    res = pmmh(filt, obs, prior0, {"a": prior}, 0, n_chains=32, n_iterations=400, n_adapt=200)
    a = res.samples["a"]
    ess = float(res.ess["a"])
    assert ess > 200 and float(res.rhat["a"]) < 1.1, (ess, float(res.rhat["a"]))
    z_mean = (float(a.mean()) - m_exact) / (float(a.std()) / math.sqrt(ess))
    z_sd = (float(a.std()) / s_exact - 1) * math.sqrt(2 * ess)
    assert abs(z_mean) < 4 and abs(z_sd) < 4, (z_mean, z_sd, ess)


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
    stuck = torch.stack(
        [torch.zeros(500, dtype=F64), torch.ones(500, dtype=F64) + 0.01 * torch.randn(500, generator=g, dtype=F64)]
    )
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
    runs = [
        pmmh(
            f,
            obs,
            prior0,
            {"a": Uniform(torch.tensor(-1.0, dtype=F64), torch.tensor(1.0, dtype=F64))},
            7,
            n_chains=3,
            n_iterations=8,
            n_adapt=4,
        )
        for _ in range(2)
    ]
    assert torch.equal(runs[0].samples["a"], runs[1].samples["a"])
    other = pmmh(
        f,
        obs,
        prior0,
        {"a": Uniform(torch.tensor(-1.0, dtype=F64), torch.tensor(1.0, dtype=F64))},
        8,
        n_chains=3,
        n_iterations=8,
        n_adapt=4,
    )
    assert not torch.equal(runs[0].samples["a"], other.samples["a"])


def test_conditional_smc_leaves_the_smoothing_law_invariant():
    """16 chains of 150 conditional-SMC sweeps (N = 20) on a linear-Gaussian series: the average
    path (after 30 sweeps) is within 4 standard errors of the RTS smoothed means at every step and
    coordinate (the standard error from the spread of the 16 chains' averages)."""
    from conftest import random_lg

    from torchflow.core.random import TrialStreams
    from torchflow.filters import KalmanFilter
    from torchflow.inference import conditional_smc
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


@pytest.mark.slow  # 13 s
def test_particle_gibbs_matches_the_exact_posterior():
    from torchflow.inference import particle_gibbs

    model, obs = _data()
    prior = Uniform(torch.tensor(-1.0, dtype=F64), torch.tensor(1.0, dtype=F64))
    m_exact, s_exact = _exact_posterior(model, obs, prior)
    res = particle_gibbs(
        model,
        obs,
        (torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64)),
        {"a": prior},
        0,
        n_particles=30,
        n_chains=8,
        n_iterations=300,
        n_adapt=100,
    )
    a = res.samples["a"]
    ess = float(res.ess["a"])
    se = float(a.std()) / math.sqrt(ess)
    assert abs(float(a.mean()) - m_exact) < 4 * se, (float(a.mean()), m_exact, se, ess)
    assert abs(float(a.std()) / s_exact - 1) < 0.2, (float(a.std()), s_exact)
    assert ess > 50 and float(res.rhat["a"]) < 1.1


# ---------------------------------------------------------------------------
# Correlated pseudo-marginal PMMH
# ---------------------------------------------------------------------------
@pytest.mark.slow  # 21 s each
@pytest.mark.parametrize("rho, n_particles", [(0.0, 100), (0.99, 50)])
def test_correlated_pmmh_matches_the_exact_posterior(rho, n_particles):
    """PMMH with correlated auxiliary normals targets the same posterior: with rho = 0 (fresh
    normals each iteration, the law of standard PMMH) and with rho = 0.99 at N = 50, the posterior
    mean of a over C = 32 chains agrees with quadrature within 4 Monte Carlo standard errors
    (sd / sqrt(ESS)) and the standard deviation within 4 of its standard errors (1 / sqrt(2 ESS),
    relative)."""
    model, obs = _data()
    prior = Uniform(torch.tensor(-1.0, dtype=F64), torch.tensor(1.0, dtype=F64))
    m_exact, s_exact = _exact_posterior(model, obs, prior)
    filt = BootstrapParticleFilter(model, n_particles=n_particles)
    res = pmmh(
        filt,
        obs,
        (torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64)),
        {"a": prior},
        0,
        n_chains=32,
        n_iterations=300,
        n_adapt=100,
        correlation=rho,
    )
    a = res.samples["a"]
    ess = float(res.ess["a"])
    se = float(a.std()) / math.sqrt(ess)
    assert ess > 100, ess
    assert abs(float(a.mean()) - m_exact) < 4 * se, (float(a.mean()), m_exact, se, ess)
    assert abs(float(a.std()) / s_exact - 1) < 4 / math.sqrt(2 * ess), (float(a.std()), s_exact, ess)
    assert float(res.rhat["a"]) < 1.1
    # the filter's resampler is put back as it was
    assert filt.resampler.sort is None and filt.resampler.ess_threshold == 0.5


def _log_ratios(filt, model, obs, R, a0, a1, rho, seed=1):
    """``(R,)`` log-likelihood ratios ``log p(z | a1, u') - log p(z | a0, u)`` with ``u'`` a Crank-
    Nicolson move of ``u`` (as :func:`pmmh` with ``correlation=rho`` proposes)."""
    from torchflow.core.random import CorrelatedStreams
    from torchflow.inference.pmmh import sorted_resampling

    mean, cov = torch.zeros(R, 1, dtype=F64), torch.eye(1, dtype=F64).expand(R, 1, 1)
    o = obs.expand(R, -1, -1)

    def ll(a, g):
        with torch.no_grad(), per_trial_values(model, {"a": torch.full((R,), a, dtype=F64)}):
            return filt(o, mean, cov, g).log_evidence

    with sorted_resampling(filt, True):
        u = CorrelatedStreams(seed, R, filt.stream_name)
        l0 = ll(a0, u)
        return ll(a1, u.crank_nicolson(rho, seed + 1)) - l0


def test_correlation_shrinks_the_variance_of_the_log_likelihood_ratio():
    """Bootstrap PF, N = 50, T = 40, a = 0.7 vs 0.72, R = 200 replicates: with rho = 0.99 the
    variance of the log-likelihood ratio is over 8 times smaller than with rho = 0 (measured: about
    30 times; the log of a ratio of two sample variances of 200 draws has a standard error of about
    0.14, so 8 is 10 standard errors below). With rho = 0 the ratio has the law of standard PMMH's
    (independent TrialStreams runs): the variances agree within 4 standard errors of their log,
    and the means within 4 standard errors."""
    from torchflow.core.random import TrialStreams

    model, obs = _data()
    R = 200
    filt = BootstrapParticleFilter(model, n_particles=50, ess_threshold=1.0)
    independent = _log_ratios(filt, model, obs, R, 0.7, 0.72, 0.0)
    correlated = _log_ratios(filt, model, obs, R, 0.7, 0.72, 0.99)
    assert float(independent.var()) > 8 * float(correlated.var()), (float(independent.var()), float(correlated.var()))
    mean, cov = torch.zeros(R, 1, dtype=F64), torch.eye(1, dtype=F64).expand(R, 1, 1)
    plain = []
    for a, seed in ((0.7, 5), (0.72, 6)):
        with torch.no_grad(), per_trial_values(model, {"a": torch.full((R,), a, dtype=F64)}):
            plain.append(filt(obs.expand(R, -1, -1), mean, cov, TrialStreams(seed, R, "bpf")).log_evidence)
    standard = plain[1] - plain[0]
    se_log = math.sqrt(4 / (R - 1))
    assert abs(math.log(float(independent.var()) / float(standard.var()))) < 4 * se_log
    se_mean = math.sqrt((float(independent.var()) + float(standard.var())) / R)
    assert abs(float(independent.mean() - standard.mean())) < 4 * se_mean


@pytest.mark.parametrize("name", ["bpf", "gpf", "enkf", "pfpf_edh"])
def test_correlation_works_through_every_draw_site(name):
    """Initial samples, transitions, resampling uniforms, Gaussian refits and flow-based proposals
    all draw through the helpers, so every stochastic filter's log-likelihood follows u (T = 15,
    N = 20, R = 64 replicates, a = 0.7 vs 0.72): the variance of the ratio falls over 5 times at
    rho = 0.99 (measured 35 to 70 times; the log variance ratio's standard error is about 0.25)."""
    from torchflow.filters import EnsembleKalmanFilter, GaussianParticleFilter, ParticleFlowParticleFilter

    model, obs = _data(15)
    filt = {
        "bpf": lambda: BootstrapParticleFilter(model, n_particles=20),
        "gpf": lambda: GaussianParticleFilter(model, n_particles=20),
        "enkf": lambda: EnsembleKalmanFilter(model, n_particles=20),
        "pfpf_edh": lambda: ParticleFlowParticleFilter(model, flow="edh", n_particles=20),
    }[name]()
    var = [float(_log_ratios(filt, model, obs, 64, 0.7, 0.72, rho, seed=0).var()) for rho in (0.0, 0.99)]
    assert var[0] > 5 * var[1], var


def test_pmmh_correlation_errors_and_reproducibility():
    model, obs = _data(10)
    prior0 = (torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64))
    priors = {"a": Uniform(torch.tensor(-1.0, dtype=F64), torch.tensor(1.0, dtype=F64))}
    f = BootstrapParticleFilter(model, n_particles=30)
    for bad in (1.0, -0.1, 1.5, True, "0.9", float("nan")):
        with pytest.raises(ValueError, match=r"correlation: expected None or a number rho in \[0, 1\)"):
            pmmh(f, obs, prior0, priors, 0, n_iterations=2, n_adapt=1, correlation=bad)
    with pytest.raises(ValueError, match="draws no random numbers"):
        pmmh(ExtendedKalmanFilter(model), obs, prior0, priors, 0, n_iterations=2, n_adapt=1, correlation=0.9)
    runs = [pmmh(f, obs, prior0, priors, 7, n_chains=3, n_iterations=8, n_adapt=4, correlation=0.95) for _ in range(2)]
    assert torch.equal(runs[0].samples["a"], runs[1].samples["a"])
    assert torch.equal(runs[0].log_likelihood, runs[1].log_likelihood)
    plain = pmmh(f, obs, prior0, priors, 7, n_chains=3, n_iterations=8, n_adapt=4)
    assert not torch.equal(runs[0].log_likelihood, plain.log_likelihood)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("correlation", [None, 0.9])
def test_pmmh_cuda(correlation):
    """A few PMMH iterations with the chains' filter on CUDA (the model, the observations and the
    prior there; the chains' own draws from a CPU seed): finite log-likelihoods, draws in the prior's
    support, the same chains for the same seed."""
    model, obs = _data(10)
    model = model.to("cuda")
    obs = obs.to("cuda")
    f = BootstrapParticleFilter(model, n_particles=64)
    prior0 = (torch.zeros(1, dtype=F64, device="cuda"), torch.eye(1, dtype=F64, device="cuda"))
    prior_a = {"a": Uniform(torch.tensor(-1.0, dtype=F64), torch.tensor(1.0, dtype=F64))}
    runs = [
        pmmh(f, obs, prior0, prior_a, 3, n_chains=3, n_iterations=6, n_adapt=4, correlation=correlation)
        for _ in range(2)
    ]
    a = runs[0].samples["a"]
    assert torch.isfinite(runs[0].log_likelihood).all() and bool(((a > -1) & (a < 1)).all())
    assert torch.equal(a.cpu(), runs[1].samples["a"].cpu())


# ---- per-trial values and priors that cannot be right (issue cases P01, P07, P09, M10, P11) --------


def _lg():
    from torchflow.models import LinearGaussian

    eye = torch.eye(2, dtype=F64)
    return LinearGaussian(0.9 * eye, 0.2 * eye, eye, 0.1 * eye, torch.zeros(2, dtype=F64), eye)


def test_per_trial_values_for_another_number_of_trials_are_refused_naming_the_parameter():
    """Cases P01, P09: values for 2 trials on a call of 3 (and 3 on 2) gave raw broadcast errors."""
    from torchflow.core.errors import ArgumentError
    from torchflow.filters import KalmanFilter

    model = _lg()
    traj = model.simulate(3, 6, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0])
    F = model.F.detach().expand(2, 2, 2).clone()
    with per_trial_values(model, {"F": F}):
        with pytest.raises(ArgumentError, match=r"LinearGaussian.F holds values for 2 trials .* filters 3 trials"):
            KalmanFilter(model)(traj.observations, mean, cov)
        out = KalmanFilter(model)(traj.observations[:2], mean[:2], cov[:2])  # the matching call runs
        assert torch.isfinite(out.log_evidence).all()


def test_per_trial_values_must_be_finite():
    """Case P07: NaN values were accepted and surfaced as a non-finite estimate that named no parameter."""
    from torchflow.core.errors import ArgumentError

    model = _lg()
    F = model.F.detach().expand(3, 2, 2).clone()
    F[1, 0, 0] = float("nan")
    with pytest.raises(
        ArgumentError, match=r"values\['F'\]: expected finite values, got NaN or infinity in trial\(s\) \[1\]"
    ):
        with per_trial_values(model, {"F": F}):
            pass
    assert torch.isfinite(model.F).all()  # the model's own value is back


def test_a_prior_reaching_outside_the_parameter_s_domain_is_refused():
    """Cases M10, P11: a Normal prior on sigma > 0 gave negative draws of a standard deviation."""
    from torch.distributions import Gamma, HalfNormal

    from torchflow.core.errors import ArgumentError
    from torchflow.inference.params import ParameterSpace
    from torchflow.models import StochasticVolatility

    sv = StochasticVolatility()
    with pytest.raises(ArgumentError, match=r"priors\['sigma'\]: Normal's support \(Real\(\)\) reaches outside"):
        ParameterSpace(sv, {"sigma": Normal(0.0, 1.0)}, 2)
    with pytest.raises(ArgumentError, match=r"priors\['rho'\]: Uniform's support"):
        ParameterSpace(sv, {"rho": Uniform(-2.0, 1.0)}, 2)
    for ok in (
        {"sigma": Gamma(2.0, 2.0)},
        {"sigma": HalfNormal(1.0)},
        {"rho": Uniform(-1.0, 1.0)},
        {"mu": Normal(0.0, 1.0)},
    ):
        ParameterSpace(sv, ok, 2)  # supports inside the domains (a shared end point has probability zero)
    ParameterSpace(ScalarAR(), {"a": Normal(0.0, 1.0)}, 2)  # a model that declares no domain: anything


def test_the_effective_sample_size_of_stuck_chains_is_at_most_their_draws():
    """Q61: two chains of 6 draws that hardly move (one jump) gave an ESS of 85 from 12 draws; it is
    now at most the draws, so the task's convergence warning (ESS < its minimum) fires."""
    from torchflow.app.tasks import convergence_warnings

    a = torch.tensor([[4.288] + [7.0516] * 5, [7.0724] * 6], dtype=F64)
    ess = float(effective_sample_size(a))
    assert 0 < ess <= 12, ess
    summary = {"parameters": {"forcing": {"rhat": float(rhat(a)), "ess": ess}}}
    assert any("ESS" in w for w in convergence_warnings("bpf", summary))


def test_pmmh_refuses_an_approximate_log_evidence_unless_allowed():
    """Q93: the Python ``pmmh`` ran the ETKF (a Gaussian approximation of the evidence) and returned a
    'posterior'; like ``task=pmmh`` it now refuses it by name, and runs it when asked to."""
    from torchflow.filters import EnsembleTransformKalmanFilter

    model, obs = _data(10)
    prior = {"a": Uniform(torch.tensor(-1.0, dtype=F64), torch.tensor(1.0, dtype=F64))}
    prior0 = (torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64))
    filt = EnsembleTransformKalmanFilter(model, n_particles=10)
    with pytest.raises(ArgumentError, match="^filt: pmmh needs .* got EnsembleTransformKalmanFilter, whose"):
        pmmh(filt, obs, prior0, prior, 0, n_chains=2, n_iterations=4, n_adapt=2)
    res = pmmh(filt, obs, prior0, prior, 0, n_chains=2, n_iterations=4, n_adapt=2, allow_approximate_evidence=True)
    assert res.samples["a"].shape == (2, 4)
