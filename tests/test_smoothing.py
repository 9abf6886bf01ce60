"""Smoothers (:mod:`torchflow.smoothing`): RTS exact against the joint Gaussian, the particle
smoothers against RTS within Monte Carlo error."""

import math

import pytest
import torch
from conftest import cuda, mild_lg, random_lg

from torchflow.core.random import TrialStreams
from torchflow.filters import (
    BootstrapParticleFilter,
    ExtendedKalmanFilter,
    GaussianSumParticleFilter,
    KalmanFilter,
    ParticleFlowParticleFilter,
    UnscentedKalmanFilter,
)
from torchflow.models import AcousticTracking
from torchflow.smoothing import smooth

F64 = torch.float64


def _joint_posterior(model, obs, mean, cov):
    """The smoothed means and covariances of a linear-Gaussian model by conditioning the dense joint
    Gaussian of ``x_0:T`` and the observed steps of ``z_1:T`` (one trial ``obs (T, m)``; a step of
    NaN is left out of the joint)."""
    F, Q, H, R = model.transition_matrix(), model.transition_cov(), model.measurement_matrix(), model.measurement_cov()
    T, d, m = obs.shape[0], F.shape[0], H.shape[0]
    mu, var = [mean], [cov]
    for _ in range(T):
        mu.append(F @ mu[-1])
        var.append(F @ var[-1] @ F.T + Q)
    Sxx = torch.zeros((T + 1) * d, (T + 1) * d, dtype=F64)
    for s in range(T + 1):
        A = var[s]
        for t in range(s, T + 1):
            Sxx[t * d : (t + 1) * d, s * d : (s + 1) * d] = A
            Sxx[s * d : (s + 1) * d, t * d : (t + 1) * d] = A.T
            A = F @ A
    keep = [t for t in range(T) if not torch.isnan(obs[t]).all()]
    Hbig = torch.zeros(len(keep) * m, (T + 1) * d, dtype=F64)
    for i, t in enumerate(keep):
        Hbig[i * m : (i + 1) * m, (t + 1) * d : (t + 2) * d] = H
    mx = torch.cat(mu)
    Szz = Hbig @ Sxx @ Hbig.T + torch.block_diag(*[R] * len(keep))
    K = torch.linalg.solve(Szz, Hbig @ Sxx).T
    post_mean = mx + K @ (obs[keep].reshape(-1) - Hbig @ mx)
    post_cov = Sxx - K @ Hbig @ Sxx
    covs = torch.stack([post_cov[t * d : (t + 1) * d, t * d : (t + 1) * d] for t in range(T + 1)])
    return post_mean.reshape(T + 1, d), covs


@pytest.mark.parametrize("make", [KalmanFilter, ExtendedKalmanFilter, UnscentedKalmanFilter], ids=["kf", "ekf", "ukf"])
def test_rts_equals_the_joint_gaussian(make):
    model = random_lg(3, 2, seed=1)
    traj = model.simulate(2, 6, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0])
    cov = cov + torch.eye(3, dtype=F64)  # a proper prior: x_0 is smoothed too
    res = smooth(make(model), traj.observations, mean, cov)
    assert res.method == "rts" and res.means.shape == (2, 7, 3) and res.covariances.shape == (2, 7, 3, 3)
    for b in range(2):
        m, P = _joint_posterior(model, traj.observations[b], mean[b], cov[b])
        torch.testing.assert_close(res.means[b], m, atol=1e-10, rtol=0)
        torch.testing.assert_close(res.covariances[b], P, atol=1e-10, rtol=0)
    # the last smoothed step is the last filtered one
    torch.testing.assert_close(res.means[:, -1], res.filtered.estimates[:, -1], atol=0, rtol=0)


def test_rts_with_missing_observations_equals_the_joint_gaussian_of_the_observed():
    model = random_lg(3, 2, seed=1)
    traj = model.simulate(1, 5, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0])
    obs = traj.observations.clone()
    obs[0, 2] = float("nan")  # a whole step: drop it from the joint
    res = smooth(KalmanFilter(model), obs, mean, cov + torch.eye(3, dtype=F64))
    exact, _ = _joint_posterior(model, obs[0], mean[0], cov[0] + torch.eye(3, dtype=F64))
    torch.testing.assert_close(res.means[0], exact, atol=1e-10, rtol=0)


@pytest.mark.parametrize("method", ["ffbsi", "genealogy"])
@pytest.mark.parametrize(
    "make",
    [
        lambda m: BootstrapParticleFilter(m, n_particles=400),
        lambda m: ParticleFlowParticleFilter(m, flow="ledh", n_particles=200),
    ],
    ids=["bpf", "pfpf_ledh"],
)
def test_particle_smoothers_agree_with_rts(method, make):
    """One series smoothed by 64 independent runs: each step's smoothed mean, averaged over runs,
    is within 4 Monte Carlo standard errors of RTS at every step and coordinate (the largest of
    d (T + 1) = 33 z-scores; 4 leaves a 0.2 % false-alarm rate; measured largest 2.0-2.7)."""
    model = mild_lg(3, 2, seed=2)
    B, T = 64, 10
    traj = model.simulate(1, T, torch.Generator().manual_seed(0))
    obs = traj.observations.expand(B, -1, -1)
    mean, cov = model.initial_belief(traj.states[:, 0].expand(B, -1))
    cov = cov + 0.5 * torch.eye(3, dtype=F64)
    exact = smooth(KalmanFilter(model), obs[:1], mean[:1], cov[:1]).means[0]
    res = smooth(make(model), obs, mean, cov, TrialStreams(0, B, "smooth"), method=method, n_paths=100)
    assert res.paths.shape == (B, 100, T + 1, 3) and res.means.shape == (B, T + 1, 3)
    avg, se = res.means.mean(0), res.means.std(0) / math.sqrt(B)
    z = ((avg - exact) / se).abs()
    assert float(z.max()) < 4, float(z.max())
    assert float(se.max()) < 0.1  # the test can fail: the standard errors are small (measured 0.03-0.07)
    # the smoothed law is not the filtering law: at the first steps the smoother moved the means
    assert (
        float(
            (exact[1:-1] - smooth(KalmanFilter(model), obs[:1], mean[:1], cov[:1]).filtered.estimates[0, :-1])
            .abs()
            .max()
        )
        > 0.05
    )


def test_ffbsi_numbers_do_not_depend_on_blocks_or_batch():
    model = random_lg(3, 2, seed=1)
    traj = model.simulate(3, 5, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0])
    f = BootstrapParticleFilter(model, n_particles=50)
    a = smooth(f, traj.observations, mean, cov, TrialStreams(1, 3, "s"), n_paths=20)
    b = smooth(f, traj.observations, mean, cov, TrialStreams(1, 3, "s"), n_paths=20, path_chunk=3)
    assert torch.equal(a.paths, b.paths)
    one = smooth(f, traj.observations[1:2], mean[1:2], cov[1:2], TrialStreams(1, 3, "s").select([1]), n_paths=20)
    torch.testing.assert_close(one.paths[0], a.paths[1], atol=0, rtol=0)


def test_smoother_errors():
    model = random_lg(3, 2)
    traj = model.simulate(2, 3, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0])
    g = torch.Generator().manual_seed(0)
    with pytest.raises(ValueError, match="method: 'rts' smooths the Kalman family"):
        smooth(BootstrapParticleFilter(model), traj.observations, mean, cov, g, method="rts")
    with pytest.raises(ValueError, match="method: 'ffbsi' smooths a particle filter.*the Kalman family takes 'rts'"):
        smooth(KalmanFilter(model), traj.observations, mean, cov, method="ffbsi")
    with pytest.raises(ValueError, match="method: expected one of"):
        smooth(KalmanFilter(model), traj.observations, mean, cov, method="forward")
    from torchflow.filters import EnsembleTransformKalmanFilter, GaussianParticleFilter, LagOneFlowFilter

    refit = GaussianParticleFilter(model, n_particles=20)  # a particle filter that keeps no weighted particles
    with pytest.raises(ValueError, match="^method: no smoother takes .* it refits its belief"):
        smooth(refit, traj.observations, mean, cov, g)
    for filt in (EnsembleTransformKalmanFilter(model), LagOneFlowFilter(model)):  # Q42: not a circle of hints
        for method in ("auto", "rts", "ffbsi", "genealogy"):
            with pytest.raises(ValueError, match=f"^method: no smoother takes {filt.name} .*Smooth one of those"):
                smooth(filt, traj.observations, mean, cov, g, method=method)
    with pytest.raises(ValueError, match="n_paths"):
        smooth(BootstrapParticleFilter(model), traj.observations, mean, cov, g, n_paths=0)
    with pytest.raises(ValueError, match="genealogy.*optimal-transport"):
        smooth(
            BootstrapParticleFilter(model, resampling_gradient="ot"),
            traj.observations,
            mean,
            cov,
            g,
            method="genealogy",
        )
    with pytest.raises(ValueError, match="a particle filter whose belief is weighted particles"):
        smooth(
            GaussianSumParticleFilter(model, n_components=2, particles_per_component=8), traj.observations, mean, cov, g
        )
    with pytest.raises(TypeError, match="filt: expected a torchflow Filter"):
        smooth(model, traj.observations, mean, cov)
    with pytest.raises(TypeError, match="generator: expected a torch.Generator"):
        smooth(BootstrapParticleFilter(model), traj.observations, mean, cov)


def test_acoustic_ffbsi_runs():
    """A nonlinear model: finite paths of the right shape, whose consecutive states are joined by
    the transition density (a path assembled without the backward weights would not be)."""
    model = AcousticTracking()
    traj = model.simulate(2, 6, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator().manual_seed(1))
    res = smooth(
        ParticleFlowParticleFilter(model, flow="edh", n_particles=64),
        traj.observations,
        mean,
        cov,
        torch.Generator().manual_seed(2),
        n_paths=16,
    )
    assert res.paths.shape == (2, 16, 7, 16) and torch.isfinite(res.paths).all()
    # FFBSi draws each path's state at t given its state at t + 1 by the transition density: along
    # the drawn paths that density is higher than along the same states paired across paths
    # (where two paths share their state the pairing changes nothing: those pairs are left out;
    # measured over three seeds: along -10.5 to -15.5, across -16.2 to -25.7)
    x_next, x_prev = res.paths[:, :, 2:], res.paths[:, :, 1:-1]
    other = x_prev.roll(1, dims=1)
    differ = (x_prev != other).any(-1)
    along = model.transition_log_prob(x_next, x_prev)[differ].mean()
    across = model.transition_log_prob(x_next, other)[differ].mean()
    assert int(differ.sum()) >= 4 and float(along) > float(across) + 2.0, (float(along), float(across))


@cuda
@pytest.mark.parametrize("method", ["rts", "ffbsi", "genealogy"])
def test_smoothing_cuda(method):
    model = random_lg(3, 2).to("cuda")
    traj = model.simulate(2, 4, torch.Generator(device="cuda").manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0])
    filt = KalmanFilter(model) if method == "rts" else ParticleFlowParticleFilter(model, flow="ledh", n_particles=32)
    res = smooth(
        filt,
        traj.observations,
        mean,
        cov + torch.eye(3, dtype=F64, device="cuda"),
        TrialStreams(0, 2, "s"),
        method=method,
        n_paths=8,
    )
    assert res.means.device.type == "cuda" and torch.isfinite(res.means).all()


def test_ffbsi_refuses_deterministic_dynamics_naming_the_transition_covariance():
    """Case S10: Lorenz-96 without model noise has no transition density; FFBSi's backward weights
    were all NaN and were written as a result. The genealogy needs no density and runs."""
    from torchflow.core.errors import ArgumentError
    from torchflow.filters import BootstrapParticleFilter
    from torchflow.models import Lorenz96
    from torchflow.smoothing import smooth

    model = Lorenz96(d=8)  # model_noise = 0
    traj = model.simulate(2, 3, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator().manual_seed(1))
    f = BootstrapParticleFilter(model, n_particles=20)
    with pytest.raises(ArgumentError, match="FFBSi weighs every path backwards by the transition density"):
        smooth(f, traj.observations, mean, cov, torch.Generator().manual_seed(0), method="ffbsi", n_paths=4)
    out = smooth(f, traj.observations, mean, cov, torch.Generator().manual_seed(0), method="genealogy", n_paths=4)
    assert torch.isfinite(out.means).all()
