"""The 3-D TDOA scenario of Zhang et al. (2024)."""

import math

import pytest
import torch
from torch.func import jacrev, vmap

from torchflow.flows import EDHFlow, FlowPrior, GromovFlow, flow_gaussian
from torchflow.flows.schedules import ExponentialSchedule
from torchflow.models import TDOA3D
from torchflow.tdoa import sensor_measurement


def test_default_geometry():
    m = TDOA3D()
    assert m.receivers.shape == (6, 3) and m.n_sensors == 9
    assert {tuple(p) for p in m.pairs.tolist()} == {(a, b) for a in (0, 2, 4) for b in (1, 3, 5)}
    # opposite faces 2000 m apart, adjacent ones 1000 sqrt(2)
    torch.testing.assert_close(m.feasible_half_width(0), torch.tensor(2000 / 1500, dtype=torch.float64))
    torch.testing.assert_close(m.feasible_half_width(1), torch.tensor(1000 * math.sqrt(2) / 1500, dtype=torch.float64))


def test_measurement_and_analytic_gradient_against_torch_func():
    m = TDOA3D()
    g = torch.Generator().manual_seed(0)
    x = (torch.rand(7, 3, generator=g, dtype=torch.float64) * 2 - 1) * 900
    for s in range(m.n_sensors):
        pa, pb = m.receivers[m.pairs[s]]
        ref = (torch.linalg.vector_norm(x - pa, dim=-1) - torch.linalg.vector_norm(x - pb, dim=-1)) / 1500
        torch.testing.assert_close(m.measure(x, s), ref)
        auto = vmap(jacrev(lambda v: m.measure(v, s)))(x)
        torch.testing.assert_close(m.jacobian(x, s), auto, rtol=1e-12, atol=1e-15)
    # a long-tensor sensor index broadcasts against the points
    sens = torch.arange(9).view(9, 1)
    assert m.measure(x.unsqueeze(0), sens).shape == (9, 7)


def test_simulation_statistics():
    """Detections ~ p_d, clutter ~ Poisson(mu_c) on the feasible interval, noise sd sigma_v."""
    m = TDOA3D(clutter_rate=2.0, p_d=0.8)
    B = 2000
    d = m.simulate(B, generator=torch.Generator().manual_seed(1))
    m.check_measurements(d.z, d.mask)
    assert d.sources.shape == (B, 3, 3) and (d.sources.abs() <= 1000).all()
    det = ((d.origin >= 0) & d.mask).sum((-1,)).double() / 3  # per run and sensor
    clut = ((d.origin < 0) & d.mask).sum(-1).double()
    n = B * 9
    assert abs(float(det.mean()) - 0.8) < 4 * math.sqrt(0.8 * 0.2 / (3 * n))
    assert abs(float(clut.mean()) - 2.0) < 4 * math.sqrt(2.0 / n)
    assert abs(float(clut.var()) - 2.0) < 0.15  # Poisson: variance = mean
    w = m.feasible_half_width(torch.arange(9)).view(1, 9, 1)
    assert ((d.z.abs() <= w + 1e-12) | ~d.mask).all()
    # detected measurements: residual sd sigma_v
    src = d.sources.gather(1, d.origin.clamp_min(0).reshape(B, -1, 1).expand(-1, -1, 3)).reshape(*d.z.shape, 3)
    h = m.measure(src, torch.arange(9).view(1, 9, 1))
    r = (d.z - h)[(d.origin >= 0) & d.mask] / m.sigma_v
    assert abs(float(r.std()) - 1) < 0.03 and abs(float(r.mean())) < 0.03
    # padding is masked out and last
    assert (~d.mask[..., 1:] | d.mask[..., :-1]).all()


def test_flowed_gaussian_on_a_tdoa_measurement_moves_towards_the_source():
    """A broad Gaussian around a source, one exact TDOA: the flowed mean's predicted TDOA is closer
    to the measurement, and the flowed covariance shrinks along the gradient (PFI-D and PFI-S)."""
    m = TDOA3D()
    src = torch.tensor([[200.0, -300.0, 100.0]], dtype=torch.float64)
    z = m.measure(src, 0)
    mu = src + torch.tensor([[60.0, -40.0, 30.0]], dtype=torch.float64)
    L = torch.eye(3, dtype=torch.float64).expand(1, 3, 3) * 50
    for flow in (EDHFlow(), GromovFlow(points="global")):
        mu1, P1 = flow_gaussian(flow, sensor_measurement(m, z, 0), FlowPrior(mu, L), ExponentialSchedule())
        assert abs(float(m.measure(mu1, 0) - z)) < 0.1 * abs(float(m.measure(mu, 0) - z))
        gvec = m.jacobian(mu1, 0)[0]
        gvec = gvec / gvec.norm()
        assert float(gvec @ P1[0] @ gvec) < 0.1 * 2500


def test_bad_input():
    with pytest.raises(ValueError, match=r"receivers: receivers 0 and 1 coincide"):
        TDOA3D(receivers=[[0.0, 0, 0], [0.0, 0, 0], [1.0, 0, 0]], pairs=[(0, 2)])
    with pytest.raises(
        ValueError, match=r"pairs: expected pairs \(a, b\) of distinct receiver indices in \[0, 6\), got \(0, 7\)"
    ):
        TDOA3D(pairs=[(0, 7)])
    with pytest.raises(ValueError, match="pairs: expected at least one"):
        TDOA3D(pairs=[])
    with pytest.raises(ValueError, match="clutter_rate"):
        TDOA3D(clutter_rate=-1.0)
    for p_d in (0.0, 1.5):
        with pytest.raises(ValueError, match=r"p_d: expected a detection probability in \(0, 1\]"):
            TDOA3D(p_d=p_d)
    m = TDOA3D()
    z = torch.zeros(2, 9, 4, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"mask: expected a bool tensor shaped like z \(2, 9, 4\), got \(2, 9, 3\)"):
        m.check_measurements(z, torch.ones(2, 9, 3, dtype=torch.bool))
    with pytest.raises(ValueError, match="z: expected"):
        m.check_measurements(torch.zeros(2, 8, 4), torch.ones(2, 8, 4, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"steps: TDOA3D has one step per sensor; expected None or 9, got 40"):
        m.simulate(2, 40, torch.Generator())
    with pytest.raises(TypeError, match="generator: expected a torch.Generator"):
        m.simulate(2)


def test_a_state_space_model_with_padded_measurements():
    """The sensors are the steps, the static sources the state; indexing keeps the mask."""
    m = TDOA3D(n_sources=2)
    d = m.simulate(3, generator=torch.Generator().manual_seed(0))
    assert d.states.shape == (3, 10, 6) and (d.states == d.states[:, :1]).all()
    assert torch.equal(m.positions(d.states[:, 0]), d.sources) and d.sources.shape == (3, 2, 3)
    sub = d[torch.tensor([2, 2, 0])]
    assert torch.equal(sub.mask, d.mask[[2, 2, 0]]) and torch.equal(sub.origin, d.origin[[2, 2, 0]])
    mean, cov = m.initial_belief(d.states[:, 0])
    torch.testing.assert_close(cov[0], torch.eye(6, dtype=torch.float64) * 1000.0**2 / 3)
    assert mean.abs().max() == 0 and m.n_steps == 9 and m.state_dim == 6
