import math

import pytest
import torch

from torchflow.core.linearize import jacobian
from torchflow.models import AcousticTracking, LinearGaussian, SensorNetwork, sensor_network_covariance


def test_acoustic_analytic_jacobian_equals_torch_func(acoustic):
    g = torch.Generator().manual_seed(0)
    x = acoustic.x0 + 5 * torch.randn(7, 3, 16, generator=g, dtype=torch.float64)
    J_ad = jacobian(acoustic.measure, x)
    J_an = acoustic.measurement_jacobian(x)
    assert J_an.shape == (7, 3, 25, 16)
    torch.testing.assert_close(J_an, J_ad, atol=1e-12, rtol=1e-10)
    assert (J_an[..., 2::4] == 0).all() and (J_an[..., 3::4] == 0).all()  # velocities unobserved


def test_acoustic_measurement_hand_value(acoustic):
    x = torch.zeros(16, dtype=torch.float64)
    x[0:2] = torch.tensor([0.0, 0.0])  # target 1 on sensor 0
    x[4:6] = torch.tensor([40.0, 0.0])  # target 2 on sensor 4 (x fastest)
    x[8:10] = torch.tensor([0.0, 40.0])  # target 3 on sensor 20
    x[12:14] = torch.tensor([40.0, 40.0])  # target 4 on sensor 24
    z = acoustic.measure(x)
    expected0 = 10 / 0.1 + 10 / (40 + 0.1) + 10 / (40 + 0.1) + 10 / (40 * math.sqrt(2) + 0.1)
    assert z.shape == (25,)
    assert abs(float(z[0]) - expected0) < 1e-12
    assert abs(float(z[24]) - expected0) < 1e-12
    assert acoustic.sensors[4].tolist() == [40.0, 0.0] and acoustic.sensors[5].tolist() == [0.0, 10.0]


def test_acoustic_simulation_respects_redraw_rule_and_noise(acoustic):
    g = torch.Generator().manual_seed(1)
    traj = acoustic.simulate(64, 40, g)
    assert traj.states.shape == (64, 41, 16) and traj.observations.shape == (64, 40, 25)
    pos = acoustic.positions(traj.states)
    assert (pos >= 2).all() and (pos <= 38).all()
    torch.testing.assert_close(traj.states[:, 0], acoustic.x0.expand(64, -1))
    # measurement residuals have sd sigma_w = 0.1 (64*40*25 samples: 5 sigma of the sd estimate ~ 0.0016)
    resid = traj.observations - acoustic.measure(traj.states[:, 1:])
    assert abs(float(resid.std()) - 0.1) < 0.002
    # process noise of the truth is V = 0.05 G, not the filter's V_f
    incr = traj.states[:, 1:] - acoustic.transition_mean(traj.states[:, :-1])
    assert abs(float(incr[..., 2].var()) - 0.05) < 0.01


def test_acoustic_prior_draw(acoustic):
    g = torch.Generator().manual_seed(2)
    s0 = acoustic.x0.expand(2000, -1)
    mean, cov = acoustic.initial_belief(s0, g)
    pos = acoustic.positions(mean)
    assert (pos >= 0).all() and (pos <= 40).all()
    torch.testing.assert_close(cov[0].diagonal(), torch.tensor([100.0, 100, 1, 1] * 4, dtype=torch.float64))
    vel_sd = (mean - s0)[:, 2::4].std()
    assert abs(float(vel_sd) - 1.0) < 0.05  # velocities are not truncated


def test_acoustic_filter_noise_option():
    assert torch.equal(AcousticTracking(filter_noise="truth").transition_cov(), AcousticTracking().V_true)
    assert AcousticTracking(filter_noise=True).filter_noise == "truth"  # YAML `true`
    assert AcousticTracking().transition_cov()[0, 0] == 3.0
    with pytest.raises(ValueError, match="filter_noise"):
        AcousticTracking(filter_noise="bogus")
    with pytest.raises(ValueError, match="sigma_w"):
        AcousticTracking(sigma_w=0.0)


def test_sensor_network_covariance_values():
    S = sensor_network_covariance(3)
    assert S.shape == (9, 9)
    assert abs(float(S[0, 0]) - 3.01) < 1e-14
    assert abs(float(S[0, 1]) - 3 * math.exp(-1 / 20)) < 1e-14  # horizontal neighbour
    assert abs(float(S[0, 4]) - 3 * math.exp(-2 / 20)) < 1e-14  # diagonal neighbour (squared dist 2)
    model = SensorNetwork(d=16, sigma_z=2.0)
    assert model.state_dim == 16 and model.obs_dim == 16
    assert float(model.R[0, 0]) == 4.0 and float(model.F[0, 0]) == 0.9
    with pytest.raises(ValueError, match="perfect square"):
        SensorNetwork(d=10)


def test_linear_gaussian_validates_shapes_and_psd():
    eye = torch.eye(2, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"H: expected \(m, d\)"):
        LinearGaussian(eye, eye, torch.ones(3, 3), torch.eye(3))
    with pytest.raises(ValueError, match="Q: covariance .* not positive semi-definite"):
        LinearGaussian(eye, -eye, eye, eye)
    m = LinearGaussian(eye, eye, torch.ones(1, 2, dtype=torch.float64), torch.eye(1, dtype=torch.float64))
    assert m.obs_dim == 1 and m.measure(torch.ones(5, 2, dtype=torch.float64)).shape == (5, 1)


def test_model_moves_dtype(acoustic):
    acoustic.to(torch.float32)
    assert acoustic.dtype == torch.float32
    x = acoustic.x0.expand(3, -1)
    assert acoustic.measure(x).dtype == torch.float32
    assert acoustic.measurement_jacobian(x).dtype == torch.float32
