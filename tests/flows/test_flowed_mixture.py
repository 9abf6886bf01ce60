"""Flowing Gaussian parameters (Zhang et al.'s (2024) flow-induced proposal-12.2)."""

import math

import pytest
import torch
from conftest import random_lg

from torchflow.core.random import TrialStreams
from torchflow.filters.kalman import kalman_update
from torchflow.flows import EDHFlow, FlowPrior, GaussianMeasurement, GromovFlow, OptimalDiffusionFlow, flow_gaussian
from torchflow.flows.schedules import ExponentialSchedule, UniformSchedule
from torchflow.proposals import FlowedMixtureProposal


def _linear_case(B=4, seed=0):
    model = random_lg(3, 2)
    g = torch.Generator().manual_seed(seed)
    mu = torch.randn(B, 3, generator=g, dtype=torch.float64)
    A = torch.randn(B, 3, 3, generator=g, dtype=torch.float64)
    P = A @ A.transpose(-1, -2) + 0.5 * torch.eye(3, dtype=torch.float64)
    z = torch.randn(B, 2, generator=g, dtype=torch.float64)
    H = model.measurement_matrix()
    post = kalman_update(mu, P, z, mu @ H.T, H, model.measurement_cov())
    return model, mu, P, z, post


def test_gromov_parameter_flow_is_the_kalman_posterior_on_any_grid():
    """P_l = M(lambda_l)^{-1} exactly at every step, so 5 coarse steps suffice (PFI-S)."""
    model, mu, P, z, post = _linear_case()
    for sched in (ExponentialSchedule(5, 2.0), UniformSchedule(3)):
        m1, P1 = flow_gaussian(
            GromovFlow(points="global"),
            GaussianMeasurement.from_model(model, z),
            FlowPrior(mu, torch.linalg.cholesky(P)),
            sched,
        )
        torch.testing.assert_close(m1, post[0], rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(P1, post[1], rtol=1e-10, atol=1e-10)


def test_edh_parameter_flow_converges_to_the_kalman_posterior_and_osd_with_c0_is_edh():
    """PFI-D: Euler error O(1/N_lambda) (2e-3 at 2000 uniform steps, 10x less at 10x the steps);
    PFI-OS with c = 0 is PFI-D to round-off."""
    model, mu, P, z, post = _linear_case()
    meas = GaussianMeasurement.from_model(model, z)
    prior = FlowPrior(mu, torch.linalg.cholesky(P))
    errs = []
    for n in (200, 2000):  # 1 ms per step on one thread
        m1, P1 = flow_gaussian(EDHFlow(), meas, prior, UniformSchedule(n))
        errs.append(max(float((m1 - post[0]).abs().max()), float((P1 - post[1]).abs().max())))
    assert errs[1] < 0.01 and 7 < errs[0] / errs[1] < 13, errs
    m2, P2 = flow_gaussian(OptimalDiffusionFlow(c=0.0, points="global"), meas, prior, UniformSchedule(2000))
    torch.testing.assert_close(m2, m1, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(P2, P1, rtol=1e-10, atol=1e-12)


def test_evaluate_at_takes_the_step_coefficients_at_the_end_or_the_start():
    """One EDH step over [0, 1]: the covariance is (I + A) P (I + A)^T with the EDH
    A(lambda) = -1/2 P H^T (lambda H P H^T + R)^{-1} H at lambda = 1 ("end") or 0 ("start"); the two
    differ, both converge to the Kalman posterior on a fine grid, and a bad value is refused."""
    model, mu, P, z, post = _linear_case()
    meas = GaussianMeasurement.from_model(model, z)
    prior = FlowPrior(mu, torch.linalg.cholesky(P))
    H, R = model.measurement_matrix(), model.measurement_cov()
    eye = torch.eye(3, dtype=torch.float64)
    for where, lam in (("end", 1.0), ("start", 0.0)):
        S = lam * H @ P @ H.T + R
        A = -0.5 * P @ H.T @ torch.linalg.solve(S, H.expand(S.shape[0], *H.shape))
        T = eye + A
        _, P1 = flow_gaussian(EDHFlow(), meas, prior, UniformSchedule(1), evaluate_at=where)
        torch.testing.assert_close(P1, T @ P @ T.transpose(-1, -2), rtol=1e-10, atol=1e-12)
        m2, P2 = flow_gaussian(EDHFlow(), meas, prior, UniformSchedule(2000), evaluate_at=where)
        assert float((m2 - post[0]).abs().max()) < 0.01 and float((P2 - post[1]).abs().max()) < 0.01
    with pytest.raises(ValueError, match="evaluate_at"):
        flow_gaussian(EDHFlow(), meas, prior, UniformSchedule(1), evaluate_at="middle")
    with pytest.raises(ValueError, match="evaluate_at"):
        FlowedMixtureProposal(EDHFlow(), UniformSchedule(1), evaluate_at="mid")


@pytest.mark.parametrize("ratio", ["mixture", "component"])
def test_flowed_mixture_evidence_is_unbiased(ratio):
    """The evidence of a linear-Gaussian measurement under a 3-component Gaussian-mixture prior,
    estimated by flowed-mixture importance sampling on a coarse EDH grid (a poor proposal, so the
    weights vary): 400 independent replications, the mean of Z_hat within 4 standard errors of the
    exact sum_n w_n N(z; H mu_n, H P_n H^T + R), and the estimate is not trivial (its spread > 0)."""
    model = random_lg(3, 2)
    g = torch.Generator().manual_seed(1)
    G, d = 3, 3
    means = torch.randn(G, d, generator=g, dtype=torch.float64) * 2
    A = torch.randn(G, d, d, generator=g, dtype=torch.float64)
    covs = A @ A.transpose(-1, -2) + 0.3 * torch.eye(d, dtype=torch.float64)
    log_w = torch.log(torch.tensor([0.5, 0.3, 0.2], dtype=torch.float64))
    z = torch.randn(1, 2, generator=g, dtype=torch.float64)
    H, R = model.measurement_matrix(), model.measurement_cov()
    S = H @ covs @ H.T + R
    exact = torch.logsumexp(log_w + torch.distributions.MultivariateNormal(means @ H.T, S).log_prob(z), 0)
    B = 400
    prop = FlowedMixtureProposal(EDHFlow(), ExponentialSchedule(3, 1.5), ratio=ratio)
    L = torch.linalg.cholesky(covs)
    mb, Lb, lw = means.expand(B, G, d), L.expand(B, G, d, d), log_w.expand(B, G)
    zz = z.expand(B * G, 2)
    m1, P1 = prop.flowed(mb, Lb, GaussianMeasurement.from_model(model, zz))
    L1 = torch.linalg.cholesky(P1)
    loglik = lambda x: model.measurement_log_prob(z.reshape(1, 1, 1, 2), x)
    x, log_omega, log_ev = prop.sample(lw, mb, Lb, m1, L1, loglik, 20, TrialStreams(0, range(B), "fmix"))
    assert x.shape == (B, G, 20, d) and log_omega.shape == (B, G, 20)
    Z = (log_ev - exact).exp()  # ratio to the exact evidence
    se = float(Z.std() / math.sqrt(B))
    assert abs(float(Z.mean()) - 1) < 4 * se, (float(Z.mean()), se)
    assert se > 1e-4  # the weights vary: the test can see a bias


def test_flowed_mixture_bad_input():
    with pytest.raises(ValueError, match="ratio"):
        FlowedMixtureProposal(EDHFlow(), ratio="both")
    with pytest.raises(TypeError, match="flow"):
        FlowedMixtureProposal("edh")
