"""Learnable parameters that stay valid: covariances through their Cholesky factor or
log-variances, positive scalars through their logarithm; the value users read is the constrained one."""

import pytest
import torch

from torchflow.core import constraints
from torchflow.filters import KalmanFilter
from torchflow.models import AcousticTracking, LinearGaussian

EYE = torch.eye(2, dtype=torch.float64)


def _lg(**kw):
    return LinearGaussian(0.9 * EYE, 0.5 * EYE, EYE, 0.3 * EYE, torch.zeros(2, dtype=torch.float64), EYE, **kw)


def test_learnable_covariances_start_at_the_given_values():
    model = _lg(learnable=True)
    torch.testing.assert_close(model.Q, 0.5 * EYE)
    torch.testing.assert_close(model.R, 0.3 * EYE)
    torch.testing.assert_close(model.transition_scale_tril(), 0.5**0.5 * EYE)
    names = {n for n, _ in model.named_parameters()}
    assert names == {"F", "H", "parametrizations.Q.original", "parametrizations.R.original"}


def test_covariances_stay_positive_definite_under_any_optimiser_step():
    """A raw step of any size and sign leaves Q and R positive definite (a raw nn.Parameter Q
    would be indefinite after this step) and the Kalman filter still runs."""
    model = _lg(learnable=["Q", "R"])
    with torch.no_grad():
        for p in model.parameters():
            p.add_(torch.tensor([[-5.0, 3.0], [7.0, -9.0]], dtype=torch.float64)[: p.shape[0], : p.shape[-1]])
    for M in (model.Q, model.R):
        assert torch.allclose(M, M.T) and float(torch.linalg.eigvalsh(M.detach()).min()) > 0
    traj = _lg().simulate(2, 5, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0])
    assert torch.isfinite(KalmanFilter(model)(traj.observations, mean, cov).log_evidence).all()


def test_factor_is_the_parametrisation_not_a_cholesky():
    model = _lg(learnable=["Q"])
    L = model.transition_scale_tril()
    torch.testing.assert_close(L @ L.T, model.Q)
    assert L.grad_fn is not None and "Cholesky" not in type(L.grad_fn).__name__


def test_diagonal_measurement_noise_learns_log_variances():
    model = _lg(learnable=["R"], measurement_noise="diagonal")
    assert constraints.unconstrained(model, "R").shape == (2,)
    torch.testing.assert_close(model.R, 0.3 * EYE)


def test_singular_learnable_covariance_is_refused():
    with pytest.raises(ValueError, match="Q: a learnable covariance .* positive definite"):
        LinearGaussian(0.9 * EYE, torch.zeros(2, 2), EYE, 0.3 * EYE, learnable=["Q"])


def test_acoustic_amplitude_and_noise_are_positive_parameters():
    model = AcousticTracking(learnable=True, psi=5.0)
    assert abs(float(model.psi) - 5.0) < 1e-12 and abs(float(model.sigma_w) - 0.1) < 1e-12
    with torch.no_grad():
        constraints.unconstrained(model, "psi").sub_(100.0)
    assert float(model.psi) > 0
    raw = dict(model.named_parameters())
    assert set(raw) == {"parametrizations.psi.original", "parametrizations.sigma_w.original"}


def test_acoustic_learnable_names_are_checked():
    with pytest.raises(ValueError, match="learnable: expected a bool or a subset of"):
        AcousticTracking(learnable=["d0"])


def test_constrain_names_the_argument():
    m = torch.nn.Module()
    m.register_buffer("scale", torch.tensor(-1.0))
    with pytest.raises(ValueError, match="scale: expected a positive value"):
        constraints.constrain(m, "scale", "positive")
    with pytest.raises(ValueError, match="scale: expected a constraint in"):
        constraints.constrain(m, "scale", "bogus")


def test_an_interval_parameter_stays_inside_under_any_optimiser_step():
    """``constraint=(low, high)``: the value starts where it was set, stays in the open interval
    whatever the raw value (an autoregressive coefficient in (-1, 1)), and gets its gradient."""
    m = torch.nn.Module()
    m.register_buffer("rho", torch.tensor(0.9, dtype=torch.float64))
    constraints.constrain(m, "rho", (-1.0, 1.0))
    assert torch.allclose(m.rho, torch.tensor(0.9, dtype=torch.float64))
    raw = constraints.unconstrained(m, "rho")
    (m.rho**2).backward()
    assert raw.grad is not None and float(raw.grad) > 0
    for value in (-30.0, -3.0, 0.0, 3.0, 30.0):  # past |raw| ~ 37 float64 rounds to the bound itself
        with torch.no_grad():
            raw.fill_(value)
        assert -1.0 < float(m.rho) < 1.0


@pytest.mark.parametrize(
    "constraint, value, match",
    [
        ((-1.0, 1.0), 1.5, r"rho: expected a value inside \(-1, 1\)"),
        (
            (1.0, -1.0),
            0.0,
            r"rho: expected a constraint in .* or an interval \(low, high\) of finite numbers with low < high",
        ),
        ((0.0, float("inf")), 1.0, "finite numbers"),
        ((0.0,), 1.0, "an interval"),
    ],
)
def test_an_interval_constraint_names_what_is_wrong(constraint, value, match):
    m = torch.nn.Module()
    m.register_buffer("rho", torch.tensor(value, dtype=torch.float64))
    with pytest.raises(ValueError, match=match):
        constraints.constrain(m, "rho", constraint)
