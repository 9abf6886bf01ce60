"""Missing observations (NaN = not observed) in every filter (:mod:`torchflow.core.missing`)."""

import math

import pytest
import torch
from conftest import cuda, mild_lg, random_lg
from filters.test_contract import CONFIGS, IDS

from torchflow.core import missing, tuning
from torchflow.core.linalg import standard_normal
from torchflow.filters import (
    BootstrapParticleFilter,
    ExtendedKalmanFilter,
    KalmanFilter,
    ParticleFlowParticleFilter,
    UnscentedKalmanFilter,
)
from torchflow.flows import select
from torchflow.models import LinearGaussian, StateSpaceModel

F64 = torch.float64


def _with_gaps(obs, frac, seed, whole=()):
    """``obs`` with a fraction ``frac`` of its values NaN at random, and the (trial, step) pairs
    ``whole`` missing entirely."""
    obs = obs.clone()
    gen = torch.Generator().manual_seed(seed)
    obs[torch.rand(obs.shape, generator=gen, dtype=F64).to(obs.device) < frac] = float("nan")
    for b, t in whole:
        obs[b, t] = float("nan")
    return obs


def _reduced_kalman(model, obs, mean, cov):
    """The Kalman filter of the reduced measurement model ``z_o = H_o x + w_o``, ``w_o ~ N(0, R_oo)``,
    step by step and trial by trial (the observed rows selected by index): the exact log-evidence."""
    F, Q, H, R = model.transition_matrix(), model.transition_cov(), model.measurement_matrix(), model.measurement_cov()
    out = []
    for b in range(obs.shape[0]):
        mu, P, ll = mean[b], cov[b], 0.0
        for t in range(obs.shape[1]):
            mu, P = F @ mu, F @ P @ F.T + Q
            o = ~torch.isnan(obs[b, t])
            if o.any():
                Ho, r = H[o], obs[b, t][o] - H[o] @ mu
                S = Ho @ P @ Ho.T + R[o][:, o]
                ll += float(-0.5 * (r @ torch.linalg.solve(S, r)) - 0.5 * torch.logdet(2 * math.pi * S))
                K = torch.linalg.solve(S, Ho @ P).T
                mu, P = mu + K @ r, P - K @ S @ K.T
        out.append(ll)
    return torch.tensor(out, dtype=F64)


@pytest.mark.parametrize("noise", ["dense", "diagonal"])
@pytest.mark.parametrize("make", [KalmanFilter, ExtendedKalmanFilter, UnscentedKalmanFilter], ids=["kf", "ekf", "ukf"])
def test_kalman_family_equals_the_reduced_model(noise, make):
    """20 % of the coordinates missing at random and one whole step: the log-evidence is the reduced
    model's to 1e-10, for a dense and a declared diagonal R."""
    base = random_lg(3, 4, seed=2)
    R = base.measurement_cov() if noise == "dense" else torch.diag(base.measurement_cov().diagonal())
    model = LinearGaussian(
        base.transition_matrix(),
        base.transition_cov(),
        base.measurement_matrix(),
        R,
        P0=torch.eye(3, dtype=F64),
        measurement_noise=noise,
    )
    traj = model.simulate(6, 12, torch.Generator().manual_seed(0))
    obs = _with_gaps(traj.observations, 0.2, 1, whole=[(0, 3), (4, 0)])
    mean, cov = model.initial_belief(traj.states[:, 0])
    res = make(model)(obs, mean, cov)
    torch.testing.assert_close(res.log_evidence, _reduced_kalman(model, obs, mean, cov), atol=1e-10, rtol=0)
    assert res.log_evidence_increments[0, 3] == 0 and res.log_evidence_increments[4, 0] == 0


def test_a_step_with_nothing_observed_is_a_prediction():
    model = random_lg(3, 2)
    traj = model.simulate(2, 3, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0])
    obs = traj.observations.clone()
    obs[:, 1] = float("nan")
    res = KalmanFilter(model)(obs, mean, cov, return_covariances=True)
    F, Q = model.transition_matrix(), model.transition_cov()
    torch.testing.assert_close(res.estimates[:, 1], res.estimates[:, 0] @ F.T)
    torch.testing.assert_close(res.covariances[:, 1], F @ res.covariances[:, 0] @ F.T + Q)


@pytest.mark.parametrize(
    "make",
    [
        lambda m: BootstrapParticleFilter(m, n_particles=1000),
        # LEDH: 15 s, second tier (``-m slow``); EDH takes the same route through the gaps here
        pytest.param(lambda m: ParticleFlowParticleFilter(m, flow="ledh", n_particles=200), marks=pytest.mark.slow),
        lambda m: ParticleFlowParticleFilter(m, flow="edh", n_particles=200),
    ],
    ids=["bpf", "pfpf_ledh", "pfpf_edh"],
)
def test_particle_evidence_is_unbiased_with_gaps(make):
    """One series with 20 % of its coordinates missing, filtered by 200 independent runs: the
    evidence estimate Z_hat / Z (Z: the Kalman filter's, exact) averages to 1 within 3 of its
    Monte Carlo standard errors."""
    model = mild_lg(3, 3, seed=1)
    traj = model.simulate(1, 10, torch.Generator().manual_seed(0))
    obs = _with_gaps(traj.observations, 0.2, 3, whole=[(0, 4)]).expand(200, -1, -1)
    mean, cov = model.initial_belief(traj.states[:, 0].expand(200, -1))
    exact = KalmanFilter(model)(obs, mean, cov).log_evidence
    est = make(model)(obs, mean, cov, torch.Generator().manual_seed(5)).log_evidence
    ratio = (est - exact).exp()
    se = ratio.std() / math.sqrt(len(ratio))
    assert abs(float(ratio.mean()) - 1) < 3 * float(se), (float(ratio.mean()), float(se))
    assert float(se) < 0.1  # the test can fail: the estimator is not so noisy that anything passes


@pytest.mark.parametrize("name,make_model,make_filter", CONFIGS, ids=IDS)
def test_every_filter_takes_gaps(name, make_model, make_filter):
    """Every filter runs with missing coordinates and a whole missing step: finite estimates; the
    step with nothing observed adds nothing to the evidence (a prediction, for particle filters
    the previous weights); same seed, same numbers."""
    model = make_model()
    f = make_filter(model)
    traj = model.simulate(3, 4, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator().manual_seed(1))
    obs = _with_gaps(traj.observations, 0.3, 2, whole=[(1, 2)])
    runs = [f(obs, mean, cov, torch.Generator().manual_seed(3)) for _ in range(2)]
    res = runs[0]
    assert torch.isfinite(res.estimates).all() and torch.isfinite(res.log_evidence).all()
    torch.testing.assert_close(res.log_evidence_increments[1, 2], torch.zeros((), dtype=F64), atol=1e-9, rtol=0)
    assert torch.equal(runs[0].estimates, runs[1].estimates)


def test_masked_flow_migrates_with_the_observed_rows_only():
    """A flow with an unobserved coordinate equals the flow of the model without that row."""
    model = random_lg(3, 3, seed=4)
    keep = torch.tensor([0, 2])
    R = model.measurement_cov()
    reduced = LinearGaussian(
        model.transition_matrix(),
        model.transition_cov(),
        model.measurement_matrix()[keep],
        R[keep][:, keep],
        P0=torch.eye(3, dtype=F64),
    )
    full = LinearGaussian(
        model.transition_matrix(), model.transition_cov(), model.measurement_matrix(), R, P0=torch.eye(3, dtype=F64)
    )
    traj = full.simulate(4, 5, torch.Generator().manual_seed(0))
    obs = traj.observations.clone()
    obs[..., 1] = float("nan")
    mean, cov = full.initial_belief(traj.states[:, 0])
    for flow in ("edh", "ledh"):
        a = ParticleFlowParticleFilter(full, flow=flow, n_particles=50)(
            obs, mean, cov, torch.Generator().manual_seed(1)
        )
        b = ParticleFlowParticleFilter(reduced, flow=flow, n_particles=50)(
            obs[..., keep], mean, cov, torch.Generator().manual_seed(1)
        )
        torch.testing.assert_close(a.estimates, b.estimates, atol=1e-9, rtol=1e-9)
        torch.testing.assert_close(a.log_evidence, b.log_evidence, atol=1e-9, rtol=1e-9)


def test_no_kernel_takes_a_mask():
    """With gaps, the fused kernels and graphs stand aside (they take no mask): the torch loop runs
    whatever the tuning (its kept spectrum of a fixed linear measurement, on with ``fused_flows``,
    agrees with the per-step path to round-off)."""
    model = random_lg(3, 2)
    traj = model.simulate(3, 4, torch.Generator().manual_seed(0))
    obs = _with_gaps(traj.observations, 0.3, 1)
    mean, cov = model.initial_belief(traj.states[:, 0])
    f = ParticleFlowParticleFilter(model, flow="ledh", n_particles=32)
    with torch.no_grad():
        with tuning.tuned(fused_flows=1):
            a = f(obs, mean, cov, torch.Generator().manual_seed(2))
        with tuning.tuned(fused_flows=0):
            b = f(obs, mean, cov, torch.Generator().manual_seed(2))
    assert dict(a.paths) == dict(b.paths) == {"torch": 4}  # no kernel ran
    torch.testing.assert_close(a.estimates, b.estimates, rtol=1e-10, atol=1e-12)
    with missing.observations_missing():
        from torchflow.flows import GaussianMeasurement

        meas = GaussianMeasurement.from_model(model, obs[:, 0])
        assert meas.observed is not None
        assert (
            select.flow_kernel(
                f.flow, meas, torch.zeros(3, 32, 3, dtype=F64), 3, per_particle=True, track=False, gaussian_image=False
            )
            is None
        )


def test_gradients_are_finite_through_gaps():
    model = random_lg(3, 2, learnable=True)
    traj = model.simulate(2, 5, torch.Generator().manual_seed(0))
    obs = _with_gaps(traj.observations.detach(), 0.3, 1, whole=[(0, 1)])
    mean, cov = model.initial_belief(traj.states[:, 0].detach())
    for f in (KalmanFilter(model), BootstrapParticleFilter(model, n_particles=64, resampling_gradient="stop_gradient")):
        model.zero_grad()
        f(obs, mean.detach(), cov.detach(), torch.Generator().manual_seed(0)).log_evidence.sum().backward()
        grads = [p.grad for p in model.parameters() if p.grad is not None]
        assert grads and all(torch.isfinite(g).all() for g in grads)


class _CoreOnly(StateSpaceModel):
    """Two independent Gaussian random walks, each measured: a core-only model (no Gaussian form,
    no density of one coordinate alone)."""

    state_dim = obs_dim = 2

    def __init__(self):
        super().__init__()
        self.register_buffer("s", torch.tensor(0.5, dtype=F64))

    def initial_state(self, batch_size, generator=None):
        return standard_normal((batch_size, 2), dtype=F64, device=self.s.device, generator=generator)

    def initial_belief(self, states0, generator=None):
        B = states0.shape[0]
        return states0.new_zeros(B, 2), torch.eye(2, dtype=F64).expand(B, 2, 2).clone()

    def sample_transition(self, x, generator=None):
        return x + self.s * standard_normal(x.shape, dtype=x.dtype, device=x.device, generator=generator)

    def transition_log_prob(self, x_next, x):
        r = (x_next - x) / self.s
        return (-0.5 * r * r - torch.log(self.s) - 0.5 * math.log(2 * math.pi)).sum(-1)

    def sample_measurement(self, x, generator=None):
        return x + standard_normal(x.shape, dtype=x.dtype, device=x.device, generator=generator)

    def measurement_log_prob(self, z, x):
        r = z - x
        return (-0.5 * r * r - 0.5 * math.log(2 * math.pi)).sum(-1)


def test_core_only_model_takes_whole_steps_and_refuses_partial_ones():
    model = _CoreOnly()
    traj = model.simulate(3, 4, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0])
    f = BootstrapParticleFilter(model, n_particles=100)
    obs = traj.observations.clone()
    obs[2, 1] = float("nan")  # a whole step
    res = f(obs, mean, cov, torch.Generator().manual_seed(1))
    assert res.log_evidence_increments[2, 1] == 0 and torch.isfinite(res.estimates).all()
    obs[0, 3, 1] = float("nan")  # one coordinate
    with pytest.raises(
        ValueError,
        match=r"BootstrapParticleFilter: observations: step 4 of trial 0 is partly observed"
        r".*measurement_log_prob_observed",
    ):
        f(obs, mean, cov, torch.Generator().manual_seed(1))


def test_step_takes_gaps_inside_the_context():
    """``step`` called directly: inside :func:`torchflow.core.missing.observations_missing` a NaN is not
    observed; the same numbers as ``forward``."""
    model = random_lg(3, 2)
    traj = model.simulate(2, 3, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0])
    obs = _with_gaps(traj.observations, 0.4, 1)
    kf = KalmanFilter(model)
    state = kf.init(mean, cov)
    with missing.observations_missing():
        for t in range(3):
            state = kf.step(state, obs[:, t])
    torch.testing.assert_close(state.mean, kf(obs, mean, cov).estimates[:, -1], atol=0, rtol=0)


@cuda
@pytest.mark.parametrize("name,make_model,make_filter", CONFIGS, ids=IDS)
def test_gaps_cuda(name, make_model, make_filter):
    model = make_model().to("cuda")
    f = make_filter(model)
    traj = model.simulate(3, 4, torch.Generator(device="cuda").manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator(device="cuda").manual_seed(1))
    obs = _with_gaps(traj.observations, 0.3, 2, whole=[(1, 2)])
    with torch.no_grad():
        res = f(obs, mean, cov, torch.Generator(device="cuda").manual_seed(3))
    assert torch.isfinite(res.estimates).all() and torch.isfinite(res.log_evidence).all()
