"""Ensemble Kalman filters: the ETKF's analysis is the Kalman update of its forecast ensemble's
moments (exact); the EnKF's perturbed mean follows its exact sampling law and approaches the KF;
the LETKF with an infinite radius is the ETKF and its taper localises; Lorenz-96 (Sakov & Oke 2008)
RMSEs near the published ones; missing observations (NaN); bad inputs."""

import math
import warnings

import pytest
import torch
from conftest import random_lg

from torchflow.core.errors import ArgumentError, ArgumentTypeError
from torchflow.core.geometry import gaspari_cohn, periodic_distances
from torchflow.core.trackers import kalman_update
from torchflow.filters import (
    EnsembleKalmanFilter,
    EnsembleTransformKalmanFilter,
    KalmanFilter,
    LocalEnsembleTransformKalmanFilter,
    ParticleState,
)
from torchflow.models import LinearGaussian, Lorenz96, SensorNetwork

ETKF, ENKF, LETKF = EnsembleTransformKalmanFilter, EnsembleKalmanFilter, LocalEnsembleTransformKalmanFilter


def _forecast_and_step(f, X0, z, seed=3):
    """The filter's forecast ensemble ``(B, N, d)`` (the same draws as its step) and the step's state."""
    g = torch.Generator().manual_seed(seed)
    Xf = f.model.sample_transition(X0, torch.Generator().manual_seed(seed))
    B, N = X0.shape[:2]
    state = ParticleState(
        X0,
        torch.full((B, N), -math.log(N), dtype=X0.dtype),
        X0.mean(1),
        torch.full((B,), float(N), dtype=X0.dtype),
        torch.zeros(B, dtype=X0.dtype),
        torch.zeros(B, dtype=torch.bool),
    )
    return Xf, f.step(state, z, g)


def _moments(X):
    mean = X.mean(1)
    A = X - mean.unsqueeze(1)
    return mean, A.transpose(1, 2) @ A / (X.shape[1] - 1)


def _kalman_of_ensemble(model, Xf, z, inflation=1.0):
    """Kalman update (observed coordinates of ``z`` only) of the inflated forecast ensemble's sample
    mean and covariance; returns mean, covariance and log N(z_o; H_o xbar, H_o P H_o^T + R_oo)."""
    mean, P = _moments(Xf)
    P = P * inflation**2
    H, R = model.measurement_matrix(), model.measurement_cov()
    out = []
    for b in range(z.shape[0]):  # a reference, trial by trial (observed rows differ)
        o = ~torch.isnan(z[b])
        mb, Pb, ll = kalman_update(mean[b], P[b], z[b, o], H[o] @ mean[b], H[o], R[o][:, o])
        out.append((mb, Pb, ll))
    return [torch.stack(v) for v in zip(*out)]


def _prior_ensemble(model, B, N, seed=0):
    g = torch.Generator().manual_seed(seed)
    return 2.0 * torch.randn(B, N, model.state_dim, generator=g, dtype=torch.float64)


def _diagonal_r_model():
    F, Q, H, _ = _lg_mats(5, 3)
    return LinearGaussian(
        F,
        Q,
        torch.randn(3, 5, generator=torch.Generator().manual_seed(4), dtype=torch.float64),
        torch.diag(torch.tensor([0.5, 1.0, 2.0], dtype=torch.float64)),
        measurement_noise="diagonal",
    )


@pytest.mark.parametrize(
    "make_model",
    [lambda: random_lg(5, 3), _diagonal_r_model, lambda: SensorNetwork(d=9)],
    ids=["dense_R", "diagonal_R", "scalar_R"],
)
@pytest.mark.parametrize("inflation", [1.0, 1.3])
@pytest.mark.parametrize("missing", [False, True])
def test_etkf_analysis_is_the_kalman_update_of_the_forecast_ensemble(make_model, inflation, missing):
    model = make_model()
    B, N = 3, 8
    X0 = _prior_ensemble(model, B, N)
    z = torch.randn(B, model.obs_dim, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    if missing:  # trial 0 misses coordinate 1, trial 2 coordinates 0 and 2
        z[0, 1] = float("nan")
        z[2, [0, 2]] = float("nan")
    f = ETKF(model, n_particles=N, inflation=inflation)
    Xf, state = _forecast_and_step(f, X0, z)
    mean_k, cov_k, ll_k = _kalman_of_ensemble(model, Xf, z, inflation)
    mean_a, cov_a = _moments(state.particles)
    torch.testing.assert_close(mean_a, mean_k, atol=1e-10, rtol=0)
    torch.testing.assert_close(state.estimate, mean_k, atol=1e-10, rtol=0)
    torch.testing.assert_close(cov_a, cov_k, atol=1e-10, rtol=0)
    torch.testing.assert_close(state.log_evidence_increment, ll_k, atol=1e-10, rtol=0)
    assert (state.ess == N).all() and torch.allclose(
        state.log_weights.exp().sum(-1), torch.ones(B, dtype=torch.float64)
    )


@pytest.mark.parametrize("cls", [ETKF, ENKF, LETKF])
def test_a_step_with_nothing_observed_is_a_pure_forecast(cls):
    model = Lorenz96(d=8)
    X0 = 8.0 + _prior_ensemble(model, 2, 5)
    z = torch.full((2, 8), float("nan"), dtype=torch.float64)
    Xf, state = _forecast_and_step(cls(model, n_particles=5), X0, z)
    torch.testing.assert_close(state.particles, Xf, atol=1e-12, rtol=0)
    assert torch.equal(state.log_evidence_increment, torch.zeros(2, dtype=torch.float64))


def test_enkf_mean_follows_its_exact_sampling_law():
    """Given the forecast ensemble, the EnKF's analysis mean is the Kalman mean of the ensemble's
    moments plus ``K e``, ``e = mean_i(eps_i) ~ N(0, R / N)``. ``e`` is recovered from the deviation
    (K has full column rank m) and ``N e^T R^{-1} e`` summed over B = 200 trials is chi-square with
    B m = 600 degrees of freedom (sd 35): checked within 4 sd."""
    model = random_lg(5, 3)
    B, N, m = 200, 12, 3
    X0 = _prior_ensemble(model, B, N)
    z = torch.randn(B, m, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    Xf, state = _forecast_and_step(ENKF(model, n_particles=N), X0, z)
    mean_k, _, _ = _kalman_of_ensemble(model, Xf, z)
    _, P = _moments(Xf)
    H, R = model.measurement_matrix(), model.measurement_cov()
    K = torch.linalg.solve(H @ P @ H.T + R, H @ P).transpose(-1, -2)  # (B, d, m)
    r = (state.particles.mean(1) - mean_k).unsqueeze(-1)
    e = torch.linalg.lstsq(K, r).solution  # (B, m, 1)
    torch.testing.assert_close(K @ e, r, atol=1e-10, rtol=0)  # the deviation lies in K's range
    chi2 = N * (e.transpose(-1, -2) @ torch.linalg.solve(R, e)).sum()
    assert abs(float(chi2) - B * m) < 4 * math.sqrt(2 * B * m), float(chi2)


def test_enkf_approaches_the_kalman_filter_with_a_large_ensemble():
    """EnKF vs KF over 8 steps of a linear-Gaussian model: the estimate's error relative to the KF's
    posterior sd shrinks like 1/sqrt(N) (measured: RMS z-score ~0.5-0.6 x sqrt(250 / N)); checked:
    below 1.5 / sqrt(N / 250) at N = 250 and 4000, and a 16-fold ensemble at least 2.5 times closer."""
    model = random_lg(4, 3)
    g = torch.Generator().manual_seed(2)
    traj = model.simulate(20, 8, g)
    mean, cov = model.initial_belief(traj.states[:, 0])
    kf = KalmanFilter(model)(traj.observations, mean, cov, return_covariances=True)
    sd = kf.covariances.diagonal(dim1=-2, dim2=-1).sqrt()
    rms = {}
    for N in (250, 4000):
        est = ENKF(model, n_particles=N)(traj.observations, mean, cov, torch.Generator().manual_seed(N)).estimates
        rms[N] = float(((est - kf.estimates) / sd).square().mean().sqrt())
        assert rms[N] < 1.5 / math.sqrt(N / 250), rms
    assert rms[250] > 2.5 * rms[4000], rms


def test_etkf_with_a_large_ensemble_approaches_the_kalman_filter():
    model = random_lg(4, 3)
    traj = model.simulate(5, 8, torch.Generator().manual_seed(2))
    mean, cov = model.initial_belief(traj.states[:, 0])
    kf = KalmanFilter(model)(traj.observations, mean, cov, return_covariances=True)
    sd = kf.covariances.diagonal(dim1=-2, dim2=-1).sqrt()
    res = ETKF(model, n_particles=4000)(traj.observations, mean, cov, torch.Generator().manual_seed(0))
    assert float(((res.estimates - kf.estimates) / sd).abs().max()) < 0.15
    # the Gaussian evidence approximation converges to the exact log-evidence: the error of a step's
    # sample moments is ~ sqrt(m / N) in log-density, ~ sqrt(T m / N) = 0.08 over T = 8 steps (4 sd)
    assert float((res.log_evidence - kf.log_evidence).abs().max()) < 0.3


@pytest.mark.parametrize("N", [6, 16])  # below and above m = 12: the ensemble- and observation-space forms
def test_letkf_with_infinite_radius_is_the_etkf(N):
    model = Lorenz96(d=12)
    traj = model.simulate(3, 30, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator().manual_seed(1))
    obs = traj.observations.clone()
    obs[1, 4, 3] = float("nan")  # a missing coordinate takes the same path in both
    e = ETKF(model, n_particles=N, inflation=1.05)(obs[:, :4], mean, cov, torch.Generator().manual_seed(2))
    loc = LETKF(model, n_particles=N, inflation=1.05, radius=math.inf)
    assert loc.local_obs == 12
    lo = loc(obs[:, :4], mean, cov, torch.Generator().manual_seed(2))
    torch.testing.assert_close(lo.estimates, e.estimates, atol=1e-10, rtol=0)
    torch.testing.assert_close(lo.log_evidence, e.log_evidence, atol=1e-10, rtol=0)
    # missing values through step (forward accepts NaN only where the base class does)
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    s1, s2 = ETKF(model, n_particles=N).init(mean, cov, None, g1), loc.init(mean, cov, None, g2)
    for t in range(30):
        s1, s2 = ETKF(model, n_particles=N, inflation=1.05).step(s1, obs[:, t], g1), loc.step(s2, obs[:, t], g2)
    torch.testing.assert_close(s2.particles, s1.particles, atol=1e-9, rtol=0)


def test_letkf_localises_and_takes_a_distance_matrix():
    """Moving one observation changes the analysis only within the radius of its site; the given
    periodic distance matrix equals the default."""
    model = Lorenz96(d=20)
    X0 = 8.0 + _prior_ensemble(model, 2, 6)
    z = 8.0 + torch.randn(2, 20, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    z2 = z.clone()
    z2[:, 5] += 3.0
    f = LETKF(model, n_particles=6, radius=6.0)
    assert f.local_obs == 11  # the sites at distance 0 .. 5 (the taper is zero from the radius on)
    _, a = _forecast_and_step(f, X0, z)
    _, b = _forecast_and_step(f, X0, z2)
    moved = (a.particles - b.particles).abs().amax((0, 1)) > 0
    dist = periodic_distances(20, torch.tensor([5]))[:, 0]
    assert moved.tolist() == (dist < 6).tolist() and 0 < int(moved.sum()) < 20
    g = LETKF(model, n_particles=6, radius=6.0, distances=periodic_distances(20, torch.arange(20)))
    _, c = _forecast_and_step(g, X0, z)  # the same neighbours (found without the matrix), summed in another order
    torch.testing.assert_close(c.particles, a.particles, atol=1e-12, rtol=0)


def test_gaspari_cohn():
    r = torch.tensor([0.0, 1.0, 2.0, 3.0, 4.0, 5.0], dtype=torch.float64)
    rho = gaspari_cohn(r, 4.0)  # half-width 2
    assert rho[0] == 1 and rho[4] == 0 and rho[5] == 0
    assert abs(float(rho[2]) - 5.0 / 24.0) < 1e-12  # the value at the half-width
    assert bool((rho[:-1].diff() <= 0).all())
    x = torch.linspace(0, 1.999, 2001, dtype=torch.float64)
    near = gaspari_cohn(x, 2.0)  # continuous across r = 1 (half-width 1)
    assert float(near.diff().abs().max()) < 2e-3
    assert torch.equal(gaspari_cohn(r, math.inf), torch.ones_like(r))


@pytest.mark.parametrize(
    "cls,kwargs,bound",
    [
        (ETKF, dict(n_particles=28, inflation=1.02), 0.23),
        (LETKF, dict(n_particles=20, inflation=1.02, radius=15.0), 0.25),
    ],
)
def test_lorenz96_sakov2008_rmse(cls, kwargs, bound):
    """Sakov & Oke (2008) set-up (d = 40, dt = 0.05, all observed, R = I): analysis RMSE after 100
    steps of burn-in, 4 trials x 500 steps. DAPPER's published: ETKF (Sqrt, N = 28, infl 1.02)
    0.18, LETKF (N = 7) 0.22; measured here ~0.18-0.20 (ETKF) and ~0.19-0.21 (LETKF, N = 20) per
    trial, far below the observation noise (1)."""
    model = Lorenz96()
    traj = model.simulate(4, 500, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator().manual_seed(1))
    est = cls(model, **kwargs)(traj.observations, mean, cov, torch.Generator().manual_seed(2)).estimates
    rmse = (est - traj.states[:, 1:]).square().mean(-1).sqrt()[:, 100:].mean(1)
    assert bool((rmse > 0.12).all()) and bool((rmse < bound).all()), rmse


@pytest.mark.parametrize("cls", [ETKF, ENKF, LETKF])
def test_bad_inputs_are_named(cls):
    model = Lorenz96(d=8)
    with pytest.raises(ArgumentError, match="inflation: expected a finite number >= 1"):
        cls(model, inflation=0.9)
    with pytest.raises(ArgumentError, match="n_particles: expected an integer >= 2"):
        cls(model, n_particles=1)
    f = cls(model, n_particles=4)
    with pytest.raises(ArgumentError, match="n_particles: expected an integer >= 2"):
        f.init(torch.zeros(2, 8, dtype=torch.float64), torch.eye(8, dtype=torch.float64).expand(2, 8, 8), 1)


def test_letkf_bad_inputs_are_named():
    model = Lorenz96(d=8)
    for radius in (0.0, -1.0, float("nan"), "5"):
        with pytest.raises(ArgumentError, match="radius: expected a number > 0"):
            LETKF(model, radius=radius)
    with pytest.raises(ArgumentError, match=r"distances: expected a tensor \(8, 8\), got \(8, 7\)"):
        LETKF(model, distances=torch.ones(8, 7))
    with pytest.raises(ArgumentError, match="finite distances >= 0"):
        LETKF(model, distances=-torch.ones(8, 8))
    with pytest.raises(ArgumentTypeError, match="diagonal measurement noise"):
        LETKF(random_lg(3, 2))
    with pytest.raises(ArgumentError, match="does not say which state coordinate"):
        LETKF(LinearGaussian(*_lg_mats(4, 2), measurement_noise="scalar"))


def _lg_mats(d, m):
    """F, Q, H, R of a linear-Gaussian model with a scalar R and m < d."""
    eye = torch.eye(d, dtype=torch.float64)
    return 0.9 * eye, 0.1 * eye, eye[:m], torch.eye(m, dtype=torch.float64)


@pytest.mark.parametrize("obs_every,radius", [(1, 14.56), (2, 5.0), (3, 20.0)])
def test_ring_neighbours_equal_the_distance_matrix(obs_every, radius):
    """The ring's neighbours found directly (no (d, m) matrix: d = 10^5 and more) are the distance
    matrix's: the same LETKF analysis to round-off."""
    from torchflow.core.geometry import periodic_distances

    model = Lorenz96(d=40, obs_every=obs_every)
    direct = LocalEnsembleTransformKalmanFilter(model, n_particles=10, radius=radius)
    dense = LocalEnsembleTransformKalmanFilter(
        model, n_particles=10, radius=radius, distances=periodic_distances(40, model.observed)
    )
    assert direct.local_obs == dense.local_obs
    traj = model.simulate(2, 10, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator().manual_seed(1))
    a = direct(traj.observations, mean, cov, torch.Generator().manual_seed(2))
    b = dense(traj.observations, mean, cov, torch.Generator().manual_seed(2))
    torch.testing.assert_close(a.estimates, b.estimates, atol=1e-10, rtol=1e-10)


def test_letkf_builds_at_a_million_sites_without_a_distance_matrix():
    from torchflow.core.geometry import periodic_neighbours

    taper, index = periodic_neighbours(10**6, torch.arange(0, 10**6, 4), 15.0)
    reached = (taper > 0).sum(-1)  # observations every 4th site, radius 15: 7 or 8 within reach
    assert taper.shape == index.shape == (10**6, 8) and set(reached.unique().tolist()) == {7, 8}
    assert int(index[0, taper[0].argmax()]) == 0 and float(taper[0].max()) == 1.0


def test_random_rotation_keeps_mean_and_covariance_and_mixes_members():
    """``rotate=True`` (DAPPER's ``rot``): the rotation matrices are orthogonal and keep the ones
    vector, so an ETKF step's analysis mean and sample covariance are those without rotation (to
    round-off), while the members themselves change."""
    from torchflow.filters.ensemble import mean_preserving_rotation

    R = mean_preserving_rotation(4, 7, dtype=torch.float64, device="cpu", generator=torch.Generator().manual_seed(0))
    eye = torch.eye(7, dtype=torch.float64)
    torch.testing.assert_close(R @ R.transpose(1, 2), eye.expand(4, 7, 7))
    torch.testing.assert_close(R.sum(-1), torch.ones(4, 7, dtype=torch.float64))
    model = Lorenz96(d=8)
    X0 = 8.0 + 2.0 * torch.randn(3, 7, 8, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    z = model.sample_measurement(model.transition_mean(X0[:, 0]), torch.Generator().manual_seed(2))
    _, plain = _forecast_and_step(ETKF(model, n_particles=7, inflation=1.1), X0, z)
    _, rot = _forecast_and_step(ETKF(model, n_particles=7, inflation=1.1, rotate=True), X0, z)
    m0, P0 = _moments(plain.particles)
    m1, P1 = _moments(rot.particles)
    torch.testing.assert_close(m1, m0)
    torch.testing.assert_close(P1, P0)
    assert not torch.allclose(rot.particles, plain.particles)
    with pytest.raises(ArgumentTypeError, match="rotate: expected True or False"):
        ETKF(model, rotate="yes")


def test_analysis_inflation_scales_the_analysis_anomalies():
    """``inflate="analysis"`` (DAPPER's semantics): the step without inflation, then the analysis
    anomalies times ``inflation`` (same mean, covariance times inflation^2)."""
    model = Lorenz96(d=8)
    X0 = 8.0 + 2.0 * torch.randn(3, 7, 8, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    z = model.sample_measurement(model.transition_mean(X0[:, 0]), torch.Generator().manual_seed(2))
    for cls in (ETKF, LETKF):
        _, plain = _forecast_and_step(cls(model, n_particles=7), X0, z)
        _, infl = _forecast_and_step(cls(model, n_particles=7, inflation=1.3, inflate="analysis"), X0, z)
        m0, P0 = _moments(plain.particles)
        m1, P1 = _moments(infl.particles)
        torch.testing.assert_close(m1, m0)
        torch.testing.assert_close(P1, 1.3**2 * P0)
    with pytest.raises(ArgumentError, match="inflate: expected one of"):
        ETKF(model, inflate="both")


def test_the_ensemble_evidence_keeps_its_digits_when_r_is_tiny():
    """Case X33: at R = 1e-300 I the ETKF's log-evidence was about 1e284 (the EnKF's -3, the KF's
    -10): |delta_w|^2 and b^T M^{-1} b, both about 1/r, were subtracted. The whitened Mahalanobis
    term is now computed directly where the observations are fewer than the members, and the
    evidence at R = 1e-300 is the one at R = 1e-12 (to 2e-5, measured)."""
    from torchflow.filters import EnsembleKalmanFilter, EnsembleTransformKalmanFilter, KalmanFilter
    from torchflow.models import LinearGaussian

    eye = torch.eye(2, dtype=torch.float64)
    out = {}
    for r in (1e-12, 1e-300):
        m = LinearGaussian(0.9 * eye, 0.2 * eye, eye, r * eye, torch.zeros(2, dtype=torch.float64), eye)
        t = m.simulate(3, 6, torch.Generator().manual_seed(0))
        mean, cov = m.initial_belief(t.states[:, 0])
        out[r] = [KalmanFilter(m)(t.observations, mean, cov).log_evidence]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the analysis ensemble collapses onto the exact observations
            for F in (EnsembleKalmanFilter, EnsembleTransformKalmanFilter):
                out[r].append(
                    F(m, n_particles=200)(t.observations, mean, cov, torch.Generator().manual_seed(1)).log_evidence
                )
    for a, b in zip(out[1e-12], out[1e-300]):
        torch.testing.assert_close(b, a, rtol=0, atol=1e-3)  # measured: up to 2e-5 apart
    assert (out[1e-300][2] - out[1e-300][0]).abs().max() < 0.5  # the ETKF near the exact evidence
