"""Lambda schedules and EDH/LEDH flows: exactness on linear-Gaussian models, exact log|det|."""

import pytest
import torch
from conftest import random_lg
from torch.func import jacrev

from torchflow.core import linalg
from torchflow.filters.kalman import kalman_update
from torchflow.flows import EDHFlow, FlowPrior, LEDHFlow, integrate_flow
from torchflow.flows.schedules import ExponentialSchedule, UniformSchedule
from torchflow.models import AcousticTracking


def test_exponential_schedule_matches_li_coates():
    eps, lam = ExponentialSchedule().steps()
    assert len(eps) == 29 and abs(float(eps.sum()) - 1) < 1e-14 and float(lam[-1]) == 1.0
    assert abs(float(eps[0]) - 1.01619e-3) < 1e-8 and abs(float(eps[-1]) - 0.16751) < 1e-5
    assert torch.allclose(eps[1:] / eps[:-1], torch.full((28,), 1.2, dtype=torch.float64))
    assert (lam >= eps).all()  # flows rely on lambda_j >= eps_j (positive-definite log-det factors)


def test_uniform_schedule_and_errors():
    eps, lam = UniformSchedule(4).steps(dtype=torch.float32)
    assert eps.dtype == torch.float32 and torch.allclose(lam, torch.tensor([0.25, 0.5, 0.75, 1.0]))
    with pytest.raises(ValueError, match="n_steps"):
        UniformSchedule(0)
    with pytest.raises(ValueError, match="ratio"):
        ExponentialSchedule(ratio=-1.0)


def test_schedule_steps_are_built_once_and_follow_their_settings():
    """steps() and host_steps() are cached per dtype (and device); a changed setting rebuilds them;
    the host floats are the device steps' values, rounded alike."""
    s = ExponentialSchedule(5, 1.3)
    a, b = s.steps(dtype=torch.float32), s.steps(dtype=torch.float32)
    assert a[0] is b[0] and a[1] is b[1] and s.steps()[0].dtype == torch.float64
    assert s.host_steps(torch.float32) == tuple(a[0].tolist()) and s.host_steps() == tuple(s.steps()[0].tolist())
    s.n_steps = 7
    assert len(s.steps()[0]) == 7 and len(s.host_steps()) == 7
    assert "_cache" not in repr(s)


def _lg_problem(d, m, seed=2):
    model = random_lg(d, m, seed=seed)
    g = torch.Generator().manual_seed(seed)
    mean = torch.randn(2, d, dtype=torch.float64, generator=g)
    A = torch.randn(d, d, dtype=torch.float64, generator=g)
    P = (A @ A.T + 0.5 * torch.eye(d, dtype=torch.float64)).expand(2, d, d)
    z = torch.randn(2, m, dtype=torch.float64, generator=g)
    post_m, post_P, _ = kalman_update(mean, P, z, model.measure(mean), model.H, model.R)
    return model, mean, P, z, post_m, post_P, g


def _prior(flow, mean, L, N):
    if flow.points == "particle":
        B, d = mean.shape
        return FlowPrior(mean.unsqueeze(1).expand(B, N, d), L.unsqueeze(1).expand(B, N, d, d))
    return FlowPrior(mean, L)


@pytest.mark.parametrize("flow", [EDHFlow(), LEDHFlow()], ids=["edh", "ledh"])
@pytest.mark.parametrize("dm", [(3, 5), (4, 2)])
def test_flow_is_exact_affine_map_to_kf_posterior(flow, dm):
    """On a linear-Gaussian model the flow is affine; its image of the prior mean and its Jacobian
    J give the pushed-forward Gaussian N(f(mean), J P J^T), which must converge to the KF posterior
    as the schedule is refined (Euler error O(1/n_steps): ~1e-3 at 1000 steps)."""
    d, m = dm
    model, mean, P, z, post_m, post_P, _ = _lg_problem(d, m)
    L = linalg.safe_cholesky(P)
    for n, tol in ((100, 3e-2), (1000, 3e-3)):
        # the map is affine: push the mean and the mean + unit vectors through it in one batch
        pts = torch.cat([mean[:1], mean[:1] + torch.eye(d, dtype=torch.float64)]).unsqueeze(0)  # (1, d+1, d)
        out = integrate_flow(flow, model, pts, z[:1], _prior(flow, mean[:1], L[:1], d + 1), UniformSchedule(n))
        f_mean = out.particles[0, 0]
        J = (out.particles[0, 1:] - f_mean).T  # column i = f(mean + e_i) - f(mean)
        err_m = (f_mean - post_m[0]).abs().max()
        err_P = (J @ P[0] @ J.T - post_P[0]).abs().max()
        scale = post_P[0].abs().max()
        assert err_m < tol * scale.sqrt() * 3 and err_P < tol * scale, (n, float(err_m), float(err_P))


@pytest.mark.parametrize("flow", [EDHFlow(), LEDHFlow()], ids=["edh", "ledh"])
def test_flow_maps_prior_samples_to_kf_posterior(flow):
    model, mean, P, z, post_m, post_P, g = _lg_problem(3, 5)
    N = 4000
    L = linalg.safe_cholesky(P)
    x0 = linalg.sample_mvn(mean, L, (N,), g)
    out = integrate_flow(flow, model, x0, z, _prior(flow, mean, L, N), UniformSchedule(200))
    mu, C = linalg.weighted_mean_cov(out.particles, torch.zeros(2, N, dtype=torch.float64))
    var = post_P.diagonal(dim1=-2, dim2=-1)
    # Monte Carlo sd of a sample mean: sqrt(P_ii / N); of a sample covariance entry:
    # sqrt((P_ii P_jj + P_ij^2) / N). Allow 5 sd plus the Euler bias at 200 steps, bounded by the
    # affine-map test above (error ~ 0.3 / n_steps relative to the largest posterior entry).
    sd_m = (var / N).sqrt()
    sd_C = ((var.unsqueeze(-1) * var.unsqueeze(-2) + post_P**2) / N).sqrt()
    scale = post_P.abs().amax((-1, -2))
    bias = 0.3 / 200 * scale
    assert ((mu - post_m).abs() <= 5 * sd_m + 3 * (bias * scale.sqrt()).unsqueeze(-1)).all()
    assert ((C - post_P).abs() <= 5 * sd_C + bias[:, None, None]).all()


@pytest.mark.parametrize("flow", [EDHFlow(), LEDHFlow()], ids=["edh", "ledh"])
def test_log_det_equals_jacobian_of_full_map(flow):
    """Nonlinear acoustic model: the accumulated log|det(I + eps A)| equals log|det| of the
    torch.func Jacobian of the whole particle map eta_0 -> eta_1 (aux path held fixed)."""
    model = AcousticTracking()
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(1, 3, g)
    mean = traj.states[:, 2] + 0.5 * torch.randn(1, 16, dtype=torch.float64, generator=g)
    P = torch.diag(torch.tensor([1.0, 1.0, 0.1, 0.1] * 4, dtype=torch.float64)).unsqueeze(0)
    L = linalg.safe_cholesky(P)
    z = traj.observations[:, 2]
    sched = ExponentialSchedule(12, 1.3)
    x0 = mean + 0.3 * torch.randn(1, 16, dtype=torch.float64, generator=g)

    def f(x):
        return integrate_flow(flow, model, x.reshape(1, 1, 16), z, _prior(flow, mean, L, 1), sched).particles.reshape(
            16
        )

    J = jacrev(f)(x0[0])
    sign, logabs = torch.linalg.slogdet(J)
    out = integrate_flow(flow, model, x0.reshape(1, 1, 16), z, _prior(flow, mean, L, 1), sched)
    assert sign > 0
    assert abs(float(out.log_det[0, 0]) - float(logabs)) < 1e-9


def test_log_det_of_linear_flow_tends_to_posterior_volume_ratio():
    model, mean, P, z, post_m, post_P, _ = _lg_problem(3, 5)
    L = linalg.safe_cholesky(P)
    out = integrate_flow(EDHFlow(), model, mean.unsqueeze(1), z, FlowPrior(mean, L), UniformSchedule(500))
    expected = 0.5 * (torch.logdet(post_P) - torch.logdet(P))
    assert torch.allclose(out.log_det[:, 0], expected, atol=2e-2)
