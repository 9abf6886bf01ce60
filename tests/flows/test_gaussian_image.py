"""The Gaussian image (mu_1, Sigma_1) of the flow's prior, returned by every flow and every kind of
linearisation points (integrate_flow(..., gaussian_image=True)), against closed forms on a
linear-Gaussian model: the Kalman posterior N(m+, P+)."""

import pytest
import torch
from conftest import random_lg

from torchflow.core import linalg
from torchflow.filters import kalman_update
from torchflow.flows import EDHFlow, FlowPrior, GeodesicFlow, GromovFlow, LEDHFlow, OptimalDiffusionFlow, integrate_flow
from torchflow.flows.schedules import ExponentialSchedule, GeometricSchedule, UniformSchedule

SCHEDULES = [ExponentialSchedule(), UniformSchedule(7), GeometricSchedule(first_step=1e-2, ratio=2.0)]


def _setup(B=2, N=5):
    model = random_lg(3, 2, seed=2)
    g = torch.Generator().manual_seed(0)
    mean = torch.randn(B, 3, generator=g, dtype=torch.float64)
    P = 1.5 * torch.eye(3, dtype=torch.float64).expand(B, 3, 3)
    z = torch.randn(B, 2, generator=g, dtype=torch.float64)
    post_m, post_P, _ = kalman_update(mean, P, z, mean @ model.H.T, model.H.expand(B, 2, 3), model.R)
    x = mean[:, None] + torch.randn(B, N, 3, generator=g, dtype=torch.float64)
    return model, mean, P, z, x, post_m, post_P


def _prior(mean, P, points, N):
    L = linalg.safe_cholesky(P)
    if points == "global":
        return FlowPrior(mean, L)
    return FlowPrior(mean[:, None].expand(-1, N, -1), L[:, None])


@pytest.mark.parametrize("schedule", SCHEDULES, ids=lambda s: type(s).__name__)
@pytest.mark.parametrize("points", ["global", "particle"])
def test_gromov_image_is_the_posterior_for_any_schedule(schedule, points):
    model, mean, P, z, x, post_m, post_P = _setup()
    out = integrate_flow(
        GromovFlow(),
        model,
        x,
        z,
        _prior(mean, P, points, 5),
        schedule,
        points=points,
        gaussian_image=True,
        generator=torch.Generator().manual_seed(1),
    )
    m1 = out.image_mean if points == "global" else out.image_mean[:, 0]
    S1 = out.image_cov if points == "global" else out.image_cov[:, 0]
    torch.testing.assert_close(m1, post_m, rtol=0, atol=1e-10)
    torch.testing.assert_close(S1, post_P, rtol=0, atol=1e-10)


@pytest.mark.parametrize("schedule", SCHEDULES, ids=lambda s: type(s).__name__)
def test_geodesic_image_mean_is_exact_and_cov_over_contracted(schedule):
    """No diffusion: the mean follows the posterior mean exactly, the covariance shrinks to
    P+ P^-1 P+ (twice the posterior's rate: the documented over-contraction)."""
    model, mean, P, z, x, post_m, post_P = _setup()
    out = integrate_flow(
        GeodesicFlow(points="global"), model, x, z, _prior(mean, P, "global", 5), schedule, gaussian_image=True
    )
    torch.testing.assert_close(out.image_mean, post_m, rtol=0, atol=1e-10)
    torch.testing.assert_close(out.image_cov, post_P @ torch.linalg.solve(P, post_P), rtol=0, atol=1e-10)


def test_edh_image_converges_to_the_posterior_as_steps_shrink():
    """EDH's exact flow maps the prior onto the posterior; Euler's error is O(eps)."""
    model, mean, P, z, x, post_m, post_P = _setup()
    errs = []
    for n in (100, 1000):
        out = integrate_flow(
            EDHFlow(), model, x, z, _prior(mean, P, "global", 5), UniformSchedule(n), gaussian_image=True
        )
        errs.append(float((out.image_cov - post_P).abs().max() + (out.image_mean - post_m).abs().max()))
    assert errs[1] < 2e-3 and errs[1] < errs[0] / 5, errs


def test_image_for_particle_and_clustered_points_and_stochastic_osd():
    model, mean, P, z, x, post_m, post_P = _setup(N=6)
    L = linalg.safe_cholesky(P)
    per = integrate_flow(LEDHFlow(), model, x, z, _prior(mean, P, "particle", 6), gaussian_image=True)
    assert per.image_mean.shape == (2, 6, 3) and per.image_cov.shape[-2:] == (3, 3)
    # clustered: K = 2 points with the particles split between them; each image is the one of a
    # flow linearised at that point
    pts = x[:, :2]
    index = torch.tensor([[0, 1, 0, 1, 0, 1]] * 2)
    clus = integrate_flow(LEDHFlow(), model, x, z, FlowPrior(pts, L[:, None]), index=index, gaussian_image=True)
    own = integrate_flow(LEDHFlow(), model, pts, z, FlowPrior(pts, L[:, None]), gaussian_image=True)
    torch.testing.assert_close(clus.image_mean, own.image_mean, rtol=0, atol=1e-12)
    torch.testing.assert_close(clus.image_cov.expand_as(own.image_cov), own.image_cov, rtol=0, atol=1e-12)
    osd = integrate_flow(
        OptimalDiffusionFlow(points="global"),
        model,
        x,
        z,
        _prior(mean, P, "global", 6),
        gaussian_image=True,
        generator=torch.Generator().manual_seed(0),
    )
    assert torch.isfinite(osd.image_cov).all() and osd.image_mean.shape == (2, 3)
    # without the flag nothing extra is computed
    assert integrate_flow(EDHFlow(), model, x, z, _prior(mean, P, "global", 6)).image_cov is None
