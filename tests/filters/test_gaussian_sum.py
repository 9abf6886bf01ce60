"""Gaussian and Gaussian-sum particle filters, with and without the LEDH flow."""

import math

import pytest
import torch
from conftest import mild_lg, random_lg, simulate_with_belief

from torchflow.core.checks import NonFiniteError
from torchflow.core.random import TrialStreams
from torchflow.filters import (
    GaussianParticleFilter,
    GaussianSumParticleFilter,
    KalmanFilter,
    ParticleFlowGaussianParticleFilter,
    ParticleFlowGaussianSumParticleFilter,
)
from torchflow.filters.gaussian_sum import MixtureState, mixture_update
from torchflow.flows.schedules import ExponentialSchedule
from torchflow.models import AcousticTracking

SCHED = ExponentialSchedule(8, 1.3)


def _same_data(model, B, T, seed=0):
    """B copies of one simulated trajectory (so the spread over trials is Monte Carlo error only)."""
    traj, mean, cov, _ = simulate_with_belief(model, 1, T, seed)
    return traj.observations.expand(B, -1, -1), mean.expand(B, -1), cov.expand(B, -1, -1)


def _run_states(f, obs, mean, cov, gen):
    state = f.init(mean, cov, None, gen)
    states = []
    for t in range(obs.shape[1]):
        state = f.step(state, obs[:, t], gen)
        states.append(state)
    return states


@pytest.mark.parametrize(
    "make",
    [
        lambda m: GaussianParticleFilter(m, n_particles=40000),
        lambda m: GaussianParticleFilter(m, n_particles=40000, redraw_eta0=True),
        lambda m: ParticleFlowGaussianParticleFilter(m, particles_per_component=4000),
        lambda m: ParticleFlowGaussianParticleFilter(m, particles_per_component=4000, linearize_at="particle"),
    ],
    ids=["gpf", "gpf-redraw", "pfgpf", "pfgpf-particle"],
)
def test_gaussian_filters_match_the_kalman_posterior(make):
    """Linear-Gaussian model, large N*: after each of 4 steps the component's mean and covariance
    equal the KF posterior, to Monte Carlo error. 20 independent trials on the same data. Two
    sources of error, carried over from earlier steps: the weights (scale 1 / ESS_min, the smallest
    ESS so far) and the Gaussian fit of the predictive from N* samples (scale rho / N*, rho the
    largest ratio of predictive to posterior variance so far, which is what remains when the flow
    makes the weights uniform): s^2 = 1 / ESS_min + rho / N*.

    * Each trial's mean error is below 5 s posterior standard deviations, its relative variance
      error below 5 sqrt(2) s.
    * The mean error over trials is within 4 standard errors (from the spread over trials) plus
      1 / ESS_min, the order of the self-normalised weights' bias.
    * Variances have a second O(1/N*) bias: the posterior covariance is a concave function of the
      fitted predictive one (Jensen). Measured for PFGPF at N* = 4000: -0.019 +- 0.005 at step 4,
      -0.002 +- 0.0015 at N* = 4e4; allowed: 4 SE + 100 / N*.
    """
    model = mild_lg(d=3, m=2)
    B, T = 20, 4
    obs, mean, cov = _same_data(model, B, T)
    kf = KalmanFilter(model)(obs[:1], mean[:1], cov[:1], return_covariances=True)
    f = make(model)
    n = f.particles_per_component
    states = _run_states(f, obs, mean, cov, TrialStreams(0, range(B), f.stream_name))
    F, Q = model.transition_matrix(), model.transition_cov()
    ess, rho, P_prev = float("inf"), 0.0, cov[0]
    for t, s in enumerate(states):
        m_kf, P_kf = kf.estimates[0, t], kf.covariances[0, t]
        sd = P_kf.diagonal().sqrt()
        ess = min(ess, float(s.ess.mean()))
        rho = max(rho, float(((F @ P_prev @ F.T + Q).diagonal() / P_kf.diagonal()).max()))
        P_prev = P_kf
        scale = math.sqrt(1 / ess + rho / n)
        e = (s.means[:, 0] - m_kf) / sd  # (B, d) in posterior sds
        assert e.abs().max() < 5 * scale, (t, e.abs().max(), scale)
        assert (e.mean(0).abs() <= 4 * e.std(0) / math.sqrt(B) + 1 / ess).all(), (t, e.mean(0), e.std(0))
        r = s.covs[:, 0].diagonal(dim1=-2, dim2=-1) / P_kf.diagonal() - 1  # relative variance error
        assert r.abs().max() < 5 * math.sqrt(2) * scale, (t, r.abs().max(), scale)
        assert (r.mean(0).abs() <= 4 * r.std(0) / math.sqrt(B) + 100 / n).all(), (t, r.mean(0), r.std(0))


def test_the_flow_makes_the_weights_near_uniform_on_a_linear_gaussian_model():
    """The flow moves the predictive samples to the posterior: ESS near N*, against the GPF's."""
    model = mild_lg(d=3, m=2)
    obs, mean, cov = _same_data(model, 4, 3)
    gpf = GaussianParticleFilter(model, n_particles=2000)
    pfgpf = ParticleFlowGaussianParticleFilter(model, particles_per_component=2000)
    e0 = gpf(obs, mean, cov, TrialStreams(0, range(4), "x")).ess
    e1 = pfgpf(obs, mean, cov, TrialStreams(0, range(4), "x")).ess
    assert (e1 > 0.9 * 2000).all() and (e1 > 2 * e0).all(), (e0, e1)


def test_one_component_bank_equals_the_gaussian_filter():
    model = AcousticTracking()
    traj, mean, cov, g = None, None, None, torch.Generator().manual_seed(0)
    traj = model.simulate(2, 3, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    a = ParticleFlowGaussianSumParticleFilter(model, n_components=1, particles_per_component=40, schedule=SCHED)
    b = ParticleFlowGaussianParticleFilter(model, particles_per_component=40, schedule=SCHED)
    ra = a(traj.observations, mean, cov, TrialStreams(0, range(2), a.stream_name))
    rb = b(traj.observations, mean, cov, TrialStreams(0, range(2), b.stream_name))
    assert torch.equal(ra.estimates, rb.estimates) and torch.equal(ra.ess, rb.ess)
    assert torch.equal(ra.g_eff, torch.ones(2, 3, dtype=ra.g_eff.dtype))


@pytest.mark.parametrize("flow", [None, "ledh"])
def test_bank_update_equals_each_component_alone(flow):
    """All G components in one batched call: each component's moments equal those of a one-component
    filter fed the same particles, and alpha_j is proportional to alpha_j^- (1/N*) sum_i w_ij."""
    model = AcousticTracking()
    g = torch.Generator().manual_seed(3)
    traj = model.simulate(2, 1, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    G, n = 3, 30
    bank = GaussianSumParticleFilter(
        model, flow=flow, n_components=G, particles_per_component=n, schedule=SCHED, init="spread"
    )
    one = GaussianSumParticleFilter(model, flow=flow, n_components=1, particles_per_component=n, schedule=SCHED)
    streams = TrialStreams(0, range(2), bank.stream_name)
    state = bank.init(mean, cov, None, streams)
    state.log_alpha = torch.log_softmax(torch.tensor([[0.0, -1.0, 0.5], [2.0, 0.0, -3.0]], dtype=mean.dtype), -1)
    z = traj.observations[:, 0]
    draws = bank.draw(state, streams)
    new = bank.update(state, z, *draws)
    log_ev = []
    for j in range(G):
        sj = MixtureState(
            torch.zeros(2, 1, dtype=mean.dtype),
            state.means[:, j : j + 1],
            state.covs[:, j : j + 1],
            state.estimate,
            state.ess,
            state.g_eff,
            state.ess,
            state.n_repaired,
        )
        nj = one.update(sj, z, *(t[:, j : j + 1] for t in draws))
        torch.testing.assert_close(new.means[:, j], nj.means[:, 0], rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(new.covs[:, j], nj.covs[:, 0], rtol=1e-10, atol=1e-12)
        log_ev.append(nj.log_evidence_increment)
    expect = torch.log_softmax(state.log_alpha + torch.stack(log_ev, -1), -1)
    torch.testing.assert_close(new.log_alpha, expect, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(new.g_eff, 1 / expect.exp().pow(2).sum(-1))
    torch.testing.assert_close(new.estimate, (expect.exp().unsqueeze(-1) * new.means).sum(1))


def test_equal_mixture_weights_give_g_eff_equal_to_g():
    for G in (1, 2, 5):
        log_w = torch.randn(3, 1, 50, dtype=torch.float64).expand(3, G, 50)  # equal evidence in each component
        la, _, g_eff = mixture_update(torch.full((3, G), -math.log(G), dtype=torch.float64), log_w)
        torch.testing.assert_close(g_eff, torch.full((3,), float(G), dtype=torch.float64))
    # unequal weights: G_eff strictly inside (1, G)
    la, _, g_eff = mixture_update(
        torch.log(torch.tensor([[0.7, 0.2, 0.1]], dtype=torch.float64)), torch.zeros(1, 3, 4, dtype=torch.float64)
    )
    torch.testing.assert_close(g_eff, torch.tensor([1 / (0.49 + 0.04 + 0.01)], dtype=torch.float64))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_mixture_weights_stay_finite_when_components_differ_by_1e300(dtype):
    """Unnormalised component weights 1e300 apart (log 690.8): in log space the update is exact in
    float64 and float32 (where 1e300 itself overflows and 1e-300 underflows)."""
    big = math.log(1e300)
    log_w = torch.zeros(2, 3, 10, dtype=dtype)
    log_w[:, 0] += big
    log_w[:, 2] -= big
    la, inc, g_eff = mixture_update(torch.full((2, 3), -math.log(3), dtype=dtype), log_w)
    assert torch.isfinite(la).all() and torch.isfinite(inc).all() and torch.isfinite(g_eff).all()
    torch.testing.assert_close(la[:, 1], torch.full((2,), -big, dtype=dtype), rtol=1e-6, atol=1e-3)
    torch.testing.assert_close(la[:, 2], torch.full((2,), -2 * big, dtype=dtype), rtol=1e-6, atol=1e-3)
    torch.testing.assert_close(inc, torch.full((2,), big - math.log(3), dtype=dtype), rtol=1e-6, atol=1e-3)
    torch.testing.assert_close(g_eff, torch.ones(2, dtype=dtype))
    # and through a filter step: a state whose components' weights are 1e300 apart
    model = random_lg(3, 2).to(dtype=dtype)
    f = GaussianSumParticleFilter(model, n_components=3, particles_per_component=20)
    traj, mean, cov, g = simulate_with_belief(model, 2, 2)
    state = f.init(mean, cov, None, g)
    state.log_alpha = torch.tensor([0.0, -big, -2 * big], dtype=dtype).expand(2, 3)
    for t in range(2):
        state = f.step(state, traj.observations[:, t], g)
        assert torch.isfinite(state.log_alpha[:, 0]).all() and torch.isfinite(state.estimate).all()


def test_particle_blocks_do_not_change_the_numbers():
    model = AcousticTracking()
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(2, 3, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    runs = []
    for chunk in (None, 25):
        f = ParticleFlowGaussianSumParticleFilter(
            model, n_components=2, particles_per_component=30, schedule=SCHED, particle_chunk=chunk
        )
        runs.append(f(traj.observations, mean, cov, TrialStreams(0, range(2), f.stream_name)))
    torch.testing.assert_close(runs[0].estimates, runs[1].estimates, rtol=1e-10, atol=1e-10)


def test_linearisation_knob():
    """Linear measurement: the point does not matter (equal to 1e-10); acoustic: it does."""
    model = random_lg(3, 2)
    traj, mean, cov, _ = simulate_with_belief(model, 2, 3)
    out = []
    for at in ("auxiliary", "particle"):
        f = ParticleFlowGaussianParticleFilter(model, particles_per_component=50, schedule=SCHED, linearize_at=at)
        out.append(f(traj.observations, mean, cov, TrialStreams(0, range(2), f.stream_name)).estimates)
    torch.testing.assert_close(out[0], out[1], rtol=1e-10, atol=1e-10)
    model = AcousticTracking()
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(2, 2, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    out = []
    for at in ("auxiliary", "particle"):
        f = ParticleFlowGaussianParticleFilter(model, particles_per_component=50, schedule=SCHED, linearize_at=at)
        out.append(f(traj.observations, mean, cov, TrialStreams(0, range(2), f.stream_name)).estimates)
    assert (out[0] - out[1]).abs().max() > 1e-6


def test_non_finite_weights_are_repaired_or_raised():
    from test_contract import nan_likelihood_run

    model, traj, mean, cov = nan_likelihood_run()
    f = GaussianSumParticleFilter(model, n_components=2, particles_per_component=8, name="gspf-test")
    res = f(traj.observations, mean, cov, torch.Generator().manual_seed(0))
    assert torch.isfinite(res.estimates).all() and res.n_repaired.tolist() == [0, 1, 0]
    model, traj, mean, cov = nan_likelihood_run()
    f = GaussianSumParticleFilter(model, n_components=2, particles_per_component=8, nonfinite="raise", name="gspf-test")
    with pytest.raises(NonFiniteError, match=r"gspf-test: .* time step 3 in trial\(s\) \[1\]"):
        f(traj.observations, mean, cov, torch.Generator().manual_seed(0))


def test_bad_arguments():
    model = random_lg(3, 2)
    with pytest.raises(ValueError, match="n_components"):
        GaussianSumParticleFilter(model, n_components=0)
    with pytest.raises(ValueError, match=r"particles_per_component: expected at least d \+ 1 = 4 .* got 3"):
        GaussianSumParticleFilter(model, particles_per_component=3)
    with pytest.raises(ValueError, match="linearize_at"):
        GaussianSumParticleFilter(model, flow="ledh", linearize_at="mean")
    with pytest.raises(ValueError, match="init"):
        GaussianSumParticleFilter(model, init="random")
    with pytest.raises(ValueError, match="deterministic"):
        GaussianSumParticleFilter(model, flow="gromov")
    with pytest.raises(ValueError, match="estimate"):
        GaussianSumParticleFilter(model, estimate="median")
    with pytest.raises(ValueError, match="jitter"):
        GaussianSumParticleFilter(model, jitter=-1.0)
    f = GaussianSumParticleFilter(model, n_components=2, particles_per_component=10)
    traj, mean, cov, g = simulate_with_belief(model, 2, 2)
    with pytest.raises(ValueError, match="n_particles"):
        f(traj.observations, mean, cov, g, n_particles=7)


def test_top_component_estimate_is_the_heaviest_components_mean():
    model = AcousticTracking()
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(2, 2, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    f = ParticleFlowGaussianSumParticleFilter(
        model, n_components=3, particles_per_component=20, schedule=SCHED, estimate="top_component"
    )
    streams = TrialStreams(0, range(2), f.stream_name)
    s = f.step(f.init(mean, cov, None, streams), traj.observations[:, 0], streams)
    top = s.log_alpha.argmax(-1)
    torch.testing.assert_close(s.estimate, s.means[torch.arange(2), top])
    assert not torch.allclose(s.estimate, (s.log_alpha.exp().unsqueeze(-1) * s.means).sum(1))
