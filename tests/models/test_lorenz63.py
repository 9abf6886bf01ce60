"""Lorenz-63: the Runge-Kutta map's Jacobian is exact (against torch.func), the Sakov et al. (2012)
defaults, the per-observation densities, and bad inputs."""

import math

import pytest
import torch
from torch.func import jacrev, vmap

from torchflow.core.errors import ArgumentError
from torchflow.models import Lorenz63, Lorenz96


def test_jacobian_of_the_integrated_dynamics_is_exact():
    model = Lorenz63()
    x = model.initial_state(5, torch.Generator().manual_seed(0))
    ref = vmap(jacrev(model.transition_mean))(x)
    torch.testing.assert_close(model.transition_jacobian(x), ref, atol=1e-10, rtol=1e-10)
    mean, J = model.transition_mean_and_jacobian(x.unsqueeze(1))
    torch.testing.assert_close(mean.squeeze(1), model.transition_mean(x))


def test_the_compiled_jacobian_equals_the_torch_tangents():
    """Where Numba is installed the CPU float64 path is one compiled loop; it gives the torch path's
    numbers to round-off (1e-12 relative), for any batch shape, and a state that records a gradient
    takes the torch path (differentiable)."""
    from torchflow.models.dynamics import rk4_with_tangent
    from torchflow.models.lorenz63 import _kernel_available

    if not _kernel_available():
        pytest.skip("Numba is not installed")
    model = Lorenz63()
    x = model.initial_state(6, torch.Generator().manual_seed(1)).reshape(2, 3, 3)
    mean, J = model.transition_mean_and_jacobian(x)
    ref_mean, ref_J = rk4_with_tangent(model._tendency, model._tendency_jacobian, x, model.dt, model.substeps)
    assert J.shape == (2, 3, 3, 3) and mean.shape == (2, 3, 3)
    torch.testing.assert_close(J, ref_J, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(mean, ref_mean, rtol=1e-12, atol=1e-12)
    xg = x.clone().requires_grad_(True)
    model.transition_mean_and_jacobian(xg)[1].sum().backward()
    assert xg.grad is not None and bool(torch.isfinite(xg.grad).all())


def test_sakov2012_defaults_and_simulation():
    model = Lorenz63()
    assert (model.dt, model.substeps, model.obs_dim) == (0.25, 25, 3)
    torch.testing.assert_close(model.measurement_cov(), 2.0 * torch.eye(3, dtype=torch.float64))
    traj = model.simulate(3, 10, torch.Generator().manual_seed(0))
    assert traj.states.shape == (3, 11, 3) and traj.observations.shape == (3, 10, 3)
    # no model noise: the truth follows the dynamics exactly
    torch.testing.assert_close(traj.states[:, 1:], model.transition_mean(traj.states[:, :-1]))
    mean, cov = model.initial_belief(traj.states[:, 0])
    torch.testing.assert_close(mean, torch.tensor([[1.509, -1.531, 25.46]], dtype=torch.float64).expand(3, 3))
    torch.testing.assert_close(cov, 2.0 * torch.eye(3, dtype=torch.float64).expand(3, 3, 3))


@pytest.mark.parametrize("make", [lambda: Lorenz63(observed=[0, 2]), lambda: Lorenz96(d=8, obs_every=2)])
def test_measurement_terms_sum_to_the_density_and_skip_missing(make):
    model = make()
    x = torch.randn(4, model.state_dim, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    z = model.sample_measurement(x, torch.Generator().manual_seed(1))
    terms = model.measurement_log_prob_terms(z, x)
    torch.testing.assert_close(terms.sum(-1), model.measurement_log_prob(z, x))
    z[:, 0] = float("nan")
    assert bool((model.measurement_log_prob_terms(z, x)[:, 0] == 0).all())


def test_bad_inputs_are_named():
    for bad in ([3], [], [0, 0], "xyz", [0.5]):
        with pytest.raises(ArgumentError, match="observed: expected distinct coordinate indices"):
            Lorenz63(observed=bad)
    with pytest.raises(ArgumentError, match="prior_mean: expected 3 numbers"):
        Lorenz63(prior_mean=[1.0, 2.0])
    with pytest.raises(ArgumentError, match="dt"):
        Lorenz63(dt=0.0)
    with pytest.raises(ArgumentError, match="obs_std"):
        Lorenz63(obs_std=-1.0)
    assert math.isclose(float(Lorenz63(model_noise=0.5).transition_cov()[0, 0]), 0.25)
