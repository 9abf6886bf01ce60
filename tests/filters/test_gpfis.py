"""GPFIS (Bunch & Godsill 2016, §13): the exact Gaussian transport on linear models,
the autodiff Jacobian including dH/dx on a nonlinear one, unbiased log-evidence, and tracking."""

import math

import pytest
import torch
from conftest import mild_lg, random_lg, replicated

from torchflow.core import linalg
from torchflow.core.random import TrialStreams
from torchflow.filters import KalmanFilter
from torchflow.filters.gpfis import GPFIS, gpfis_flow
from torchflow.flows import FlowPrior, GaussianMeasurement
from torchflow.flows.schedules import ExponentialSchedule, UniformSchedule
from torchflow.models import AcousticTracking


def _lg_step(model, B=2, N=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    d = model.state_dim
    x_prev = torch.randn(B, N, d, generator=g, dtype=torch.float64)
    z = torch.randn(B, model.obs_dim, generator=g, dtype=torch.float64)
    m0 = model.transition_mean(x_prev)
    L0 = model.transition_scale_tril(x_prev)
    x0 = m0 + linalg.matvec(L0, torch.randn(B, N, d, generator=g, dtype=torch.float64))
    return x0, m0, L0, z


@pytest.mark.parametrize("root", ["cholesky", "symmetric"])
def test_linear_model_transport_is_the_exact_posterior(root):
    """With a linear h every step is an affine map taking N(m_0, P_0) to the homotopy Gaussian, so
    the prior mean goes to the Kalman posterior mean and log|det| = (logdet P_post - logdet P_0)/2,
    for any grid and either root."""
    model = random_lg(4, 3, seed=2)
    x0, m0, L0, z = _lg_step(model)
    P0 = L0 @ L0.T
    H, R = model.measurement_matrix(), model.measurement_cov()
    S = H @ P0 @ H.T + R
    K = torch.linalg.solve(S, H @ P0).T
    post_m = m0 + linalg.matvec(K, z.unsqueeze(1) - linalg.matvec(H, m0))
    post_P = P0 - K @ H @ P0
    expect = 0.5 * (torch.logdet(post_P) - torch.logdet(P0))
    meas = GaussianMeasurement.from_model(model, z)
    for sched in (UniformSchedule(1), ExponentialSchedule(7, 1.3)):
        x_m, _ = gpfis_flow(meas, m0, FlowPrior(m0, L0), sched, root)
        torch.testing.assert_close(x_m, post_m, rtol=0, atol=1e-10)
        x1, log_det = gpfis_flow(meas, x0, FlowPrior(m0, L0), sched, root)
        torch.testing.assert_close(log_det, expect.expand_as(log_det), rtol=0, atol=1e-10)
        # the map is affine with Jacobian T, T P_0 T^T = P_post: the deviations' Mahalanobis norms match
        a = torch.linalg.solve_triangular(L0, (x0 - m0).unsqueeze(-1), upper=False).squeeze(-1)
        Lp = torch.linalg.cholesky(post_P)
        b = torch.linalg.solve_triangular(Lp, (x1 - post_m).unsqueeze(-1), upper=False).squeeze(-1)
        torch.testing.assert_close(a.norm(dim=-1), b.norm(dim=-1), rtol=1e-10, atol=0)


@pytest.mark.parametrize("jacobian", ["analytic", "autodiff"])
def test_autodiff_jacobian_includes_the_moving_linearisation(jacobian):
    """On acoustic tracking (h nonlinear, linearised at the moving particle) log|det| equals the
    autograd Jacobian of the whole map, both with the step's derivative written out (the model's
    analytic second derivatives) and traced by forward mode; dropping dH/dx would miss it by O(1)."""
    model = AcousticTracking(sigma_w=0.1)
    g = torch.Generator().manual_seed(3)
    x_prev = model.x0.expand(1, 2, -1) + 0.5 * torch.randn(1, 2, 16, generator=g, dtype=torch.float64)
    z = model.sample_measurement(model.x0.unsqueeze(0), g)
    prior = FlowPrior(model.transition_mean(x_prev), model.transition_scale_tril(x_prev))
    x0 = model.sample_transition(x_prev, g)
    meas = GaussianMeasurement.from_model(model, z)
    sched = ExponentialSchedule(5, 1.5)
    _, log_det = gpfis_flow(meas, x0, prior, sched, jacobian=jacobian)

    def one(v):  # particle 0 alone, other particle fixed
        x = torch.cat([v.reshape(1, 1, 16), x0[:, 1:]], 1)
        return gpfis_flow(meas, x, prior, sched)[0][0, 0]

    J = torch.autograd.functional.jacobian(one, x0[0, 0].clone())
    torch.testing.assert_close(log_det[0, 0], torch.linalg.slogdet(J)[1], rtol=1e-8, atol=1e-8)


def _acoustic_flow_setting(B=2, N=6, seed=5):
    model = AcousticTracking(sigma_w=0.1)
    g = torch.Generator().manual_seed(seed)
    x_prev = model.x0.expand(B, N, -1) + 0.5 * torch.randn(B, N, 16, generator=g, dtype=torch.float64)
    z = model.sample_measurement(model.x0.expand(B, -1), g)
    prior = FlowPrior(model.transition_mean(x_prev), model.transition_scale_tril(x_prev))
    return model, z, prior, model.sample_transition(x_prev, g)


def _same_flow(meas, x0, prior, sched=None):
    """The analytic and autodiff Jacobians move the particles identically (same ops on the primal)
    and agree on log|det| to round-off."""
    xa, la = gpfis_flow(meas, x0, prior, sched, jacobian="analytic")
    xr, lr = gpfis_flow(meas, x0, prior, sched, jacobian="autodiff")
    assert torch.equal(xa, xr)
    torch.testing.assert_close(la, lr, rtol=1e-9, atol=1e-9)
    return la


@pytest.mark.parametrize("noise", ["scalar", "diagonal", "dense"])
def test_analytic_jacobian_matches_autodiff_for_every_constant_noise(noise):
    """The model's second derivatives are whitened by R's declared structure (scalar: folded into
    the Hessian's scale; diagonal: a division; dense: a triangular solve)."""
    model, z, prior, x0 = _acoustic_flow_setting()
    m = model.obs_dim
    g = torch.Generator().manual_seed(9)
    LR = {
        "scalar": 0.1 * torch.eye(m, dtype=torch.float64),
        "diagonal": torch.diag(0.05 + 0.1 * torch.rand(m, generator=g, dtype=torch.float64)),
        "dense": torch.linalg.cholesky(
            0.01 * torch.eye(m, dtype=torch.float64)
            + 0.002 * (lambda a: a @ a.T)(torch.randn(m, m, generator=g, dtype=torch.float64))
        ),
    }[noise]
    meas = GaussianMeasurement(
        z,
        model.linearize_measurement,
        lambda x: LR,
        noise,
        support=model.structure.measurement_support,
        hessian=model.measurement_hessian_blocks,
    )
    _same_flow(meas, x0, prior, ExponentialSchedule(8, 1.4))


def test_analytic_jacobian_without_a_hessian_and_with_a_state_dependent_noise():
    """Without the model's second derivatives (a state-dependent R: the skewed-t / Poisson model),
    the analytic step still takes W's and y's derivatives from forward mode through the whitened
    linearisation, and matches forward mode through the whole step."""
    from torchflow.models import SkewedTPoisson

    model = SkewedTPoisson(d=9)
    g = torch.Generator().manual_seed(2)
    x_prev = torch.randn(2, 5, 9, generator=g, dtype=torch.float64)
    z = model.sample_measurement(x_prev[:, 0], g)
    prior = FlowPrior(model.transition_mean(x_prev), model.transition_scale_tril(x_prev))
    meas = GaussianMeasurement.from_model(model, z)
    assert meas.derivative(x_prev) is None
    _same_flow(meas, model.sample_transition(x_prev, g), prior, ExponentialSchedule(6, 1.3))


def test_acoustic_hessian_matches_autodiff():
    """The acoustic model's analytic second derivatives (one 2 x 2 block per sensor and target)
    equal forward-mode autodiff of its Jacobian (the base class's default)."""
    from torchflow.models.base import GaussianStateSpaceModel

    model, _, _, x = _acoustic_flow_setting(B=3, N=4)
    for support in (True, False):
        exact = GaussianStateSpaceModel.measurement_hessian(model, x, support, scale=0.5)
        torch.testing.assert_close(model.measurement_hessian(x, support, scale=0.5), exact, rtol=1e-12, atol=1e-12)
        blocks = model.measurement_hessian_blocks(x, support)
        assert blocks.shape == (3, 4, 25, 4, 2 if support else 4, 2 if support else 4)
        torch.testing.assert_close(linalg.block_diagonal(blocks), 2 * exact, rtol=1e-12, atol=1e-12)


def test_gpfis_log_evidence_unbiased_on_lg():
    """E[Z_hat / Z] = 1 within 4 standard errors over 400 runs on the same data (the PF-PF test)."""
    model = mild_lg()
    obs, mean, cov = replicated(model, 400, 6)
    logz = KalmanFilter(model)(obs[:1], mean[:1], cov[:1]).log_evidence
    res = GPFIS(model, n_particles=32, schedule=ExponentialSchedule(8, 1.5))(
        obs, mean, cov, TrialStreams(1, 400, "gpfis")
    )
    r = torch.exp(res.log_evidence - logz)
    se = r.std() / math.sqrt(r.numel())
    assert abs(float(r.mean()) - 1) < 4 * float(se), (float(r.mean()), float(se))
    assert float(se) < 0.05
    # on a linear model GPFIS samples the optimal proposal: weights depend on the parent only, so the
    # ESS stays high (a bootstrap PF on this model has a markedly lower one)
    assert float(res.ess.mean()) > 0.5 * 32


def test_gpfis_tracks_on_acoustic():
    """With an informative prior (position sd 2 m) GPFIS keeps every track with 64 particles (mean
    position error after the first step below 1.5 m), while a bootstrap PF with the same particles
    does not. (From the default 10 m prior every filter here loses most tracks at N = 100; the
    paper-size comparison is in RESULTS.md.)"""
    from torchflow.filters import BootstrapParticleFilter

    model = AcousticTracking(sigma_w=0.1, prior_std=(2.0, 2.0, 0.5, 0.5))
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(3, 8, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)

    def err(res):
        e = (model.positions(res.estimates) - model.positions(traj.states[:, 1:])).norm(dim=-1).mean(-1)
        return e[:, 1:].mean(-1)

    res = GPFIS(model, n_particles=64)(traj.observations, mean, cov, TrialStreams(0, 3, "gpfis"))
    assert torch.isfinite(res.estimates).all() and torch.isfinite(res.log_evidence).all()
    assert (err(res) < 1.5).all(), err(res)
    bpf = BootstrapParticleFilter(model, n_particles=64)(traj.observations, mean, cov, TrialStreams(0, 3, "bpf"))
    assert float(err(bpf).mean()) > 2 * float(err(res).mean()), (err(bpf), err(res))


def test_gpfis_argument_errors():
    model = random_lg()
    with pytest.raises(ValueError, match="gamma: only the deterministic GPFIS"):
        GPFIS(model, gamma=0.5)
    with pytest.raises(ValueError, match=r"root: expected one of \('cholesky', 'symmetric'\), got 'sqrtm'"):
        GPFIS(model, root="sqrtm")
    with pytest.raises(ValueError, match=r"jacobian: expected one of \('analytic', 'autodiff'\), got 'numeric'"):
        GPFIS(model, jacobian="numeric")
