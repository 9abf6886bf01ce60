"""A linear measurement with a constant R (declared) keeps ``S = L^T J L`` fixed over pseudo-time:
the Daum-Huang flows then take its eigendecomposition once per integration instead of two
Cholesky factorisations per step and point (no gradient recorded, ``tuning.fused_flows`` on). The
same flow to round-off, wherever it is used."""

import pytest
import torch

from torchflow.flows import EDHFlow, FlowPrior, GaussianMeasurement, LEDHFlow, integrate_flow
from torchflow.models import Lorenz96, SensorNetwork

F64 = dict(dtype=torch.float64)


def _both(flow, model, particles, z, prior, **kw):
    """The flow integrated with the kept eigendecomposition (no gradient) and with the per-step
    factorisations (gradient recorded, which turns the shortcut off)."""
    from torchflow.core import paths, tuning

    with torch.no_grad(), tuning.tuned(fused_flows=1), paths.recording() as taken:
        fast = integrate_flow(flow, model, particles, z, prior, **kw)
    assert dict(taken) == {"torch": 1}, taken  # the torch loop, not a kernel: the kept spectrum ran
    with torch.no_grad(), tuning.tuned(fused_flows=0):
        ref = integrate_flow(flow, model, particles, z, prior, **kw)
    with torch.enable_grad():
        grad = integrate_flow(flow, model, particles, z, prior, **kw)
    assert torch.equal(ref.particles, grad.particles)  # fused_flows=0 is the per-step path
    return fast, ref


@pytest.mark.parametrize("flow", [EDHFlow(), LEDHFlow()], ids=["edh", "ledh"])
@pytest.mark.parametrize("operator", [0, 10_000], ids=["operator", "explicit A"])
def test_the_kept_spectrum_gives_the_per_step_flow(flow, operator):  # noqa: D103
    from torchflow.core import tuning

    # A as an operator or formed; the reference loop (the lane kernel needs tiles that fit: off here)
    with tuning.tuned(flow_operator_min_dim=operator):
        _check(flow)


def _check(flow):
    model = SensorNetwork(d=36)
    assert GaussianMeasurement.from_model(model, torch.zeros(1, 36, **F64)).fixed  # linear, constant R
    g = torch.Generator().manual_seed(0)
    B, N, d = 2, 8, 36
    particles = torch.randn(B, N, d, generator=g, **F64)
    z = torch.randn(B, d, generator=g, **F64)
    A = torch.randn(B, N, d, d, generator=g, **F64) * 0.3
    P = A @ A.transpose(-1, -2) + 0.5 * torch.eye(d, **F64)
    per = flow.points == "particle"
    prior = FlowPrior(
        particles.mean(1) if not per else particles + 0.1,
        torch.linalg.cholesky(P[:, 0] if not per else P),
    )
    fast, ref = _both(flow, model, particles, z, prior, gaussian_image=not per)
    torch.testing.assert_close(fast.particles, ref.particles, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(fast.log_det, ref.log_det, rtol=1e-10, atol=1e-10)
    assert float((fast.particles - particles).abs().max()) > 0.1  # the flow moved them
    if not per:
        torch.testing.assert_close(fast.image_cov, ref.image_cov, rtol=1e-10, atol=1e-10)


def test_a_nonlinear_or_state_dependent_measurement_is_not_fixed():
    z = torch.zeros(1, 20, **F64)
    assert not GaussianMeasurement.from_model(Lorenz96(d=40, obs_every=2, obs_operator="abs"), z).fixed
    assert not GaussianMeasurement.lag_one(Lorenz96(d=40), torch.zeros(1, 40, **F64)).fixed
    assert GaussianMeasurement.from_model(Lorenz96(d=40), torch.zeros(1, 40, **F64)).fixed
