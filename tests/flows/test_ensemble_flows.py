"""The ensemble flows of data assimilation (torchflow.flows.ensemble) go through the one
integrator: their drift at the members, their log-determinant, and the errors of a wrong pairing."""

import pytest
import torch

from torchflow.core.errors import ArgumentTypeError
from torchflow.filters import LagOneFlowFilter
from torchflow.flows import (
    EDHFlow,
    EnsembleMeasurement,
    FlowPrior,
    LagOneFlow,
    ensemble_prior,
    integrate_flow,
    regression_jacobian,
)
from torchflow.flows.schedules import ExponentialSchedule
from torchflow.models import LinearGaussian

F64 = dict(dtype=torch.float64)


def _linear(d=3, m=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    F = torch.eye(d, **F64) + 0.1 * torch.randn(d, d, generator=g, **F64)
    H = torch.randn(m, d, generator=g, **F64)
    return LinearGaussian(F, 1e-10 * torch.eye(d, **F64), H, 0.5 * torch.eye(m, **F64))


def test_the_regression_jacobian_of_a_linear_measurement_is_exact():
    g = torch.Generator().manual_seed(1)
    X = torch.randn(2, 9, 4, generator=g, **F64)
    H = torch.randn(3, 4, generator=g, **F64)
    Y = X @ H.T
    torch.testing.assert_close(regression_jacobian(X, Y - Y.mean(1, keepdim=True)), H.expand(2, 3, 4))
    Xs = X[:, :3]  # fewer members than coordinates: the minimum-norm fit in the members' span
    Hs = regression_jacobian(Xs, (Xs @ H.T) - (Xs @ H.T).mean(1, keepdim=True))
    D = Xs - Xs.mean(1, keepdim=True)
    torch.testing.assert_close(D @ Hs.transpose(1, 2), D @ H.T)


def test_the_lag_one_flow_s_log_det_is_that_of_the_members_map():
    """Linear dynamics and measurement: the regression is exact and the flow is one affine map of
    every member; the log-determinant the integrator sums is ``log|det|`` of that map (read from
    the members, N - 1 >= d) and the members reach the Kalman posterior of the ensemble's Gaussian."""
    model, d, N = _linear(), 3, 12
    g = torch.Generator().manual_seed(2)
    X0 = 1.0 + torch.randn(2, N, d, generator=g, **F64)
    z = torch.randn(2, 2, generator=g, **F64)
    f = LagOneFlowFilter(model, n_particles=N, inflation=1.0, rotate=False)
    prior = ensemble_prior(X0)
    meas = EnsembleMeasurement(z, whiten=lambda X: f.measure_images(X, z))
    out = integrate_flow(LagOneFlow(), model, X0, z, prior, ExponentialSchedule(200, 1.0), measurement=meas)
    D0 = X0 - X0.mean(1, keepdim=True)
    D1 = out.particles - out.particles.mean(1, keepdim=True)
    M = torch.linalg.lstsq(D0, D1).solution.transpose(1, 2)  # D1 = D0 M^T
    torch.testing.assert_close(D0 @ M.transpose(1, 2), D1)  # one affine map
    assert out.log_det.shape == (2, N) and bool((out.log_det == out.log_det[:, :1]).all())
    torch.testing.assert_close(out.log_det[:, 0], torch.linalg.slogdet(M).logabsdet, rtol=1e-10, atol=1e-10)
    # the Kalman update of N(xbar, P) through h(M(x)) = H F x
    P = prior.root @ prior.root.transpose(1, 2)
    HF = model.H @ model.F
    S = HF @ P @ HF.T + model.R
    K = torch.linalg.solve(S, HF @ P).transpose(1, 2)  # P H^T S^-1 (S, P symmetric)
    mk = prior.mean.squeeze(1) + (
        K @ (z - (HF @ prior.mean.squeeze(1).unsqueeze(-1)).squeeze(-1)).unsqueeze(-1)
    ).squeeze(-1)
    torch.testing.assert_close(out.particles.mean(1), mk, rtol=0, atol=5e-3)  # Euler's error at 200 steps: 3e-3


def test_a_wrong_pairing_is_refused_naming_it():
    model = _linear()
    X = torch.randn(1, 5, 3, generator=torch.Generator().manual_seed(0), **F64)
    z = torch.zeros(1, 2, **F64)
    prior = FlowPrior(X.mean(1), torch.eye(3, **F64).expand(1, 3, 3))
    with pytest.raises(ArgumentTypeError, match="points: 'ensemble' steps an ensemble flow .* got EDHFlow"):
        integrate_flow(EDHFlow(), model, X, z, prior, points="ensemble")
    with pytest.raises(ArgumentTypeError, match="measurement: an ensemble flow reads an EnsembleMeasurement"):
        integrate_flow(LagOneFlow(), model, X, z, ensemble_prior(X))
    with pytest.raises(NotImplementedError, match="ensemble flow: integrate it with points='ensemble'"):
        LagOneFlow().coefficients_at(None, prior, 0.5, 0.1)


def test_the_guide_s_example_of_an_ensemble_flow_runs(capsys):
    import re

    from tests.conftest import ROOT

    guide = (ROOT / "docs" / "guide" / "data-assimilation.md").read_text()
    block = next(b for b in re.findall(r"```python\n(.*?)```", guide, re.S) if "EnsembleMeasurement(z" in b)
    exec(compile(block, "data-assimilation.md", "exec"), {})
    out = capsys.readouterr().out
    assert out.startswith("torch.Size([1, 20, 10]) tensor(-") and "float64" in out
