"""The data-assimilation filters' parts, each checked against its formula so that a change to it fails
a default-tier test of the filters that use it: the local particle filter's Gaspari-Cohn taper, the
lag-one flow's random rotation, the inflation of every assimilation filter, the Student-t score of the
localised flow, and Lorenz-96's ring (its dynamics and its geometry)."""

import math

import pytest
import torch
from conftest import random_lg

from torchflow.core.geometry import gaspari_cohn, local_observations, periodic_distances
from torchflow.filters import KernelParticleFlowFilter, LagOneFlowFilter, LocalParticleFilter, ParticleState
from torchflow.flows.ensemble import EnsembleMeasurement
from torchflow.models import Lorenz96
from torchflow.models.lorenz96 import lorenz96_tendency

F64 = dict(dtype=torch.float64)


def _state(X0):
    B, N = X0.shape[:2]
    return ParticleState(
        X0,
        torch.full((B, N), -math.log(N), **F64),
        X0.mean(1),
        torch.full((B,), float(N), **F64),
        torch.zeros(B, **F64),
        torch.zeros(B, dtype=torch.bool),
    )


def _moments(X):
    mean = X.mean(1)
    A = X - mean.unsqueeze(1)
    return mean, A.transpose(1, 2) @ A / (X.shape[1] - 1)


def test_local_pf_weighs_each_coordinate_by_the_gaspari_cohn_tapered_likelihood():
    """Each coordinate's estimate is its weighted mean under ``log w_ni = sum_j rho(dist(i, j)) log
    p(z_j | x_n)``, with ``rho`` the Gaspari-Cohn taper of the ring distance (recomputed here from
    the distances, not from the filter's gathered neighbourhoods): a hard cut-off (``rho`` = 1 within
    the radius) or a taper on the index line (no wrap) fails it."""
    d, N = 12, 24
    model = Lorenz96(d=d)
    f = LocalParticleFilter(model, n_particles=N, radius=5.0)
    X0 = 8.0 + 2.0 * torch.randn(2, N, d, generator=torch.Generator().manual_seed(0), **F64)
    z = model.sample_measurement(model.transition_mean(X0[:, 0]), torch.Generator().manual_seed(5))
    out = f.step(_state(X0), z, torch.Generator().manual_seed(1))
    Xf = model.transition_mean(X0)
    terms = model.measurement_log_prob_terms(z.unsqueeze(1), Xf)  # (B, N, m)
    rho = gaspari_cohn(periodic_distances(d, torch.arange(d)), 5.0)  # (d, m)
    assert 0 < float(rho[0, 2]) < 1 and float(rho[0, d - 2]) == float(rho[0, 2])  # tapered, and on the ring
    w = torch.softmax(terms @ rho.T, 1)  # (B, N, d)
    torch.testing.assert_close(out.estimate, (w * Xf).sum(1), rtol=1e-10, atol=1e-10)


def test_lag_one_flow_rotation_mixes_the_members_and_keeps_their_moments():
    """``rotate=True`` (the default) mixes the analysis members by a mean-preserving rotation: the
    same mean and covariance as without it, other members. Dropping the rotation fails it."""
    model = Lorenz96(d=8)
    X0 = 3.0 + torch.randn(2, 16, 8, generator=torch.Generator().manual_seed(0), **F64)
    z = model.sample_measurement(model.transition_mean(X0.mean(1)), torch.Generator().manual_seed(1))
    with_, without = (
        LagOneFlowFilter(model, n_particles=16, rotate=r).step(_state(X0), z, torch.Generator().manual_seed(2))
        for r in (True, False)
    )
    (m1, P1), (m2, P2) = _moments(with_.particles), _moments(without.particles)
    torch.testing.assert_close(m1, m2, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(P1, P2, rtol=1e-8, atol=1e-10)
    assert float((with_.particles - without.particles).abs().max()) > 0.1


@pytest.mark.parametrize("covariance", ["prior", "current"])
def test_lag_one_flow_inflates_the_previous_ensemble(covariance):
    """The flow's prior is the previous ensemble's Gaussian with its anomalies times ``inflation``:
    on a linear-Gaussian model the flowed members have the Kalman update of ``N(xbar, inflation^2
    P)`` (400 pseudo-time steps: within 0.005 posterior SDs and 0.5 % of the variances, as the
    uninflated test; inflation 1.5 moves the variances by tens of percent). Ignoring the inflation
    fails it."""
    model = random_lg(3, 2)
    B, N, infl = 2, 64, 1.5
    g = torch.Generator().manual_seed(0)
    X0 = 2.0 * torch.randn(B, N, 3, generator=g, **F64)
    z = torch.randn(B, 2, generator=g, **F64)
    xb, P = _moments(X0)
    P = infl**2 * P
    F = model.transition_matrix()
    H, R = model.measurement_matrix() @ F, model.measurement_cov()
    K = P @ H.T @ torch.linalg.inv(H @ P @ H.T + R)
    mk = xb + ((z - model.measure(model.transition_mean(xb))).unsqueeze(1) @ K.transpose(1, 2)).squeeze(1)
    vk = (P - K @ H @ P).diagonal(dim1=1, dim2=2)
    filt = LagOneFlowFilter(model, n_particles=N, inflation=infl, flow_steps=400, step_ratio=1.0, covariance=covariance)
    ma, Pa = _moments(filt.migrate(X0, z)[0])
    assert float(((ma - mk) / vk.sqrt()).abs().max()) < 0.005
    assert float((Pa.diagonal(dim1=1, dim2=2) / vk - 1).abs().max()) < 0.005


@pytest.mark.parametrize(
    "make",
    [
        lambda m: KernelParticleFlowFilter(m, n_particles=16, radius=4.0, flow_steps=3),
        lambda m: LocalParticleFilter(m, n_particles=16, radius=4.0),
    ],
    ids=["kpff", "lpf"],
)
def test_the_ensemble_flow_and_local_filters_inflate_their_forecast(make):
    """The kernel flow filter and the local particle filter inflate the forecast anomalies: one step
    from the same members and stream with inflation 1.5 gives the forecast spread times 1.5 (the
    local filter's estimate, a weighted mean of the inflated forecast, moves), and ignoring it fails."""
    model = Lorenz96(d=8)
    X0 = 3.0 + torch.randn(2, 16, 8, generator=torch.Generator().manual_seed(0), **F64)
    z = model.sample_measurement(model.transition_mean(X0.mean(1)), torch.Generator().manual_seed(1))
    f1, f2 = make(model), make(model)
    f2.inflation = 1.5
    s1 = f1.forecast(_state(X0), torch.Generator().manual_seed(2))
    s2 = f2.forecast(_state(X0), torch.Generator().manual_seed(2))
    torch.testing.assert_close(s2[1], 1.5 * s1[1], rtol=1e-12, atol=1e-12)
    a = f1.step(_state(X0), z, torch.Generator().manual_seed(2))
    b = f2.step(_state(X0), z, torch.Generator().manual_seed(2))
    assert float((a.estimate - b.estimate).abs().max()) > 1e-3


def test_localised_flow_reads_the_student_t_score():
    """``likelihood="model"`` on Student-t errors (3 degrees of freedom, scale s): the residual that
    drives the flow is minus the score of the t law at the members' midpoints whitened by R's square
    root (the t variance's, ``sigma = s sqrt(nu / (nu - 2))``): ``c = -sigma (nu + 1) r / (nu s^2 + r^2)``,
    ``r = z - (y_i + ybar) / 2``. Compared to that formula (a Gaussian score, or the t law's with
    another scale or degrees of freedom, fails it)."""
    d, N = 10, 6
    model = Lorenz96(d=d, obs_df=3, obs_std=0.7)
    f = LagOneFlowFilter(model, n_particles=N, radius=4.0, likelihood="model")
    g = torch.Generator().manual_seed(0)
    X = 3.0 + torch.randn(2, N, d, generator=g, **F64)
    Xm = model.transition_mean(X)
    z = model.measure(Xm).mean(1) + 3.0 * torch.randn(2, d, generator=g, **F64)
    w = f.whiten(Xm, X.mean(1), z)
    y = model.measure(Xm)  # (B, N, m)
    r = z.unsqueeze(1) - 0.5 * (y + y.mean(1, keepdim=True))
    nu, s = 3.0, 0.7
    sigma = s * math.sqrt(nu / (nu - 2))
    expected = -sigma * (nu + 1) * r / (nu * s * s + r * r)
    w.images = Xm
    meas = EnsembleMeasurement(z, whiten=None, log_prob_terms=model.measurement_log_prob_terms)
    torch.testing.assert_close(f.flow.residual(X, w, meas), expected, rtol=1e-9, atol=1e-12)


def test_lorenz96_is_a_ring_in_its_dynamics_and_its_geometry():
    """Site i's tendency is ``(x_(i+1) - x_(i-2)) x_(i-1) - x_i + F`` with indices modulo d (site 0
    reads d - 1 and d - 2), and the localising filters measure distance on the ring (site 0's
    neighbours within radius 3 are d - 2 .. 2). A model that does not wrap fails it."""
    d = 10
    model = Lorenz96(d=d)
    x = torch.randn(3, d, generator=torch.Generator().manual_seed(0), **F64)
    i = torch.arange(d)
    expected = (x[:, (i + 1) % d] - x[:, (i - 2) % d]) * x[:, (i - 1) % d] - x + model.forcing
    torch.testing.assert_close(lorenz96_tendency(x, model.forcing), expected, rtol=1e-12, atol=1e-12)
    taper, index = local_observations(model, 3.0)
    near = set(index[0][taper[0] > 0].tolist())
    assert near == {d - 2, d - 1, 0, 1, 2}, near
