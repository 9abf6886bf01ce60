"""Flows take explicit tensors: the whitened measurement at the points, built from a
GaussianMeasurement that the filter (not the flow) chooses."""

import pytest
import torch
from conftest import random_lg

from torchflow.core import linalg
from torchflow.flows import EDHFlow, FlowPrior, GromovFlow, LEDHFlow, integrate_flow
from torchflow.flows.measurement import GaussianMeasurement
from torchflow.models import AcousticTracking, LinearGaussian


def test_whitened_tensors_match_their_definition():
    g = torch.Generator().manual_seed(0)
    for model in (random_lg(3, 2, seed=1), AcousticTracking()):
        d, m = model.state_dim, model.obs_dim
        aux = 10 * torch.rand(2, 4, d, generator=g, dtype=torch.float64)
        z = torch.randn(2, m, generator=g, dtype=torch.float64)
        lin = GaussianMeasurement.from_model(model, z).at(aux)
        LR = model.measurement_scale_tril()
        H = model.measurement_jacobian(aux)
        W = torch.linalg.solve_triangular(LR, H, upper=False)
        r = z[:, None] - model.measure(aux) + (H @ aux.unsqueeze(-1)).squeeze(-1)
        y = torch.linalg.solve_triangular(LR, r.unsqueeze(-1), upper=False).squeeze(-1)
        torch.testing.assert_close(lin.W.expand_as(W), W, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(lin.y, y, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("flow", [EDHFlow(), LEDHFlow(), GromovFlow()], ids=lambda f: type(f).__name__)
def test_the_filter_chooses_the_measurement(flow):
    """Flowing with model A but model B's measurement term is flowing with model B: the flow only
    sees the tensors it is given."""
    a = random_lg(3, 2, seed=3)
    R2 = 3.0 * a.R + 0.5 * torch.eye(2, dtype=torch.float64)
    b = LinearGaussian(a.F, a.Q, a.H, R2, a.m0, a.P0)
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 5, 3, generator=g, dtype=torch.float64)
    z = torch.randn(2, 2, generator=g, dtype=torch.float64)
    L = linalg.safe_cholesky(1.3 * torch.eye(3, dtype=torch.float64)).expand(2, 3, 3)
    prior = FlowPrior(x.mean(1), L) if flow.points != "particle" else FlowPrior(x, L[:, None])
    meas_b = GaussianMeasurement(
        z, b.linearize_measurement, b.measurement_scale_tril, "dense", matrix=b.measurement_matrix(), measure=b.measure
    )
    out_ab = integrate_flow(flow, a, x, z, prior, measurement=meas_b, generator=torch.Generator().manual_seed(1))
    out_b = integrate_flow(flow, b, x, z, prior, generator=torch.Generator().manual_seed(1))
    out_a = integrate_flow(flow, a, x, z, prior, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(out_ab.particles, out_b.particles, rtol=0, atol=1e-12)
    assert (out_ab.particles - out_a.particles).abs().max() > 1e-3


def test_measurement_noise_structure_is_checked():
    with pytest.raises(ValueError, match=r"noise: expected 'scalar', 'diagonal' or 'dense', got 'full'"):
        GaussianMeasurement(torch.zeros(1, 2), None, None, "full")


def test_prepare_precomputes_what_at_would_compute():
    """``prepare`` (called once per flow by the integrator) caches 1/sigma of a scalar R: the same
    bits as ``at`` alone; and it follows the model's sigma at the next prepare (a learned sigma)."""
    g = torch.Generator().manual_seed(0)
    model = AcousticTracking()
    aux = 40 * torch.rand(2, 3, 16, generator=g, dtype=torch.float64)
    z = torch.randn(2, model.obs_dim, generator=g, dtype=torch.float64)
    support = torch.as_tensor(model.structure.measurement_support)
    plain = GaussianMeasurement.from_model(model, z).at(aux, support)
    meas = GaussianMeasurement.from_model(model, z).prepare(aux)
    ready = meas.at(aux, support)
    assert torch.equal(plain.W, ready.W) and torch.equal(plain.y, ready.y)
    with torch.no_grad():
        model.sigma_w.mul_(2.0)
    assert torch.equal(meas.at(aux, support).W, ready.W)  # cached until the next prepare
    halved = meas.prepare(aux).at(aux, support)
    torch.testing.assert_close(halved.W, ready.W / 2, rtol=1e-14, atol=0)
