"""Kalman-family exactness: KF vs an independent dense joint-Gaussian computation; EKF/UKF = KF."""

import pytest
import torch
from conftest import random_lg
from torch.func import functional_call

from torchflow.filters import ExtendedKalmanFilter, KalmanFilter, UnscentedKalmanFilter


def dense_joint(model, z):
    """log p(z_{1:T}) and E[x_k | z_{1:k}] for every k from the joint Gaussian of (x_{0:T}, z_{1:T}),
    built directly from the model matrices (no recursion shared with the filter)."""
    F, Q, H, R, m0, P0 = model.F, model.Q, model.H, model.R, model.m0, model.P0
    B, T, m = z.shape
    d = F.shape[0]
    # x_k = F^k x_0 + sum_{j=1..k} F^{k-j} v_j: build the linear map from (x_0, v_1..v_T) to x_{0:T}
    n_src = d * (T + 1)
    M = torch.zeros(d * (T + 1), n_src, dtype=F.dtype)
    Fp = [torch.linalg.matrix_power(F, k) for k in range(T + 1)]
    for k in range(T + 1):
        for j in range(k + 1):
            M[k * d : (k + 1) * d, j * d : (j + 1) * d] = Fp[k - j]
    src_cov = torch.block_diag(P0, *([Q] * T))
    Cx = M @ src_cov @ M.T
    mx = M[:, :d] @ m0
    Hb = torch.block_diag(*([H] * T))
    Cx1 = Cx[d:, d:]  # x_{1:T}
    Cz = Hb @ Cx1 @ Hb.T + torch.block_diag(*([R] * T))
    mz = Hb @ mx[d:]
    zf = z.reshape(B, T * m)
    logz = torch.distributions.MultivariateNormal(mz, covariance_matrix=Cz).log_prob(zf)
    means = []
    for k in range(1, T + 1):
        idx = slice(0, k * m)
        Cxz = Cx1[(k - 1) * d : k * d] @ Hb[idx].T  # Cov(x_k, z_{1:k})
        gain = torch.linalg.solve(Cz[idx, idx], Cxz.T).T
        means.append(mx[k * d : (k + 1) * d] + (zf[:, idx] - mz[idx]) @ gain.T)
    return logz, torch.stack(means, 1)


def _data(model, B=4, T=6, seed=1):
    g = torch.Generator().manual_seed(seed)
    traj = model.simulate(B, T, g)
    mean, cov = model.initial_belief(traj.states[:, 0])
    return traj, mean, cov


def test_kf_matches_dense_joint_gaussian(small_lg):
    traj, mean, cov = _data(small_lg)
    res = KalmanFilter(small_lg)(traj.observations, mean, cov)
    logz, means = dense_joint(small_lg, traj.observations)
    torch.testing.assert_close(res.log_evidence, logz, atol=1e-10, rtol=0)
    torch.testing.assert_close(res.estimates, means, atol=1e-10, rtol=0)


def test_kf_per_trial_priors_match_shared_path(small_lg):
    """Different prior covariances per trial take the unshared Riccati path; equal ones share it.
    Both must agree trial by trial."""
    traj, mean, cov = _data(small_lg)
    kf = KalmanFilter(small_lg)
    shared = kf(traj.observations, mean, cov, return_covariances=True)
    cov2 = cov.clone()
    cov2[1] = cov2[1] * 2.0  # trial 1 differs -> no sharing
    unshared = kf(traj.observations, mean, cov2, return_covariances=True)
    for b in (0, 2, 3):
        torch.testing.assert_close(shared.estimates[b], unshared.estimates[b], atol=1e-12, rtol=0)
        torch.testing.assert_close(shared.covariances[b], unshared.covariances[b], atol=1e-12, rtol=0)
    assert not torch.allclose(shared.estimates[1], unshared.estimates[1])


@pytest.mark.parametrize("cls", [ExtendedKalmanFilter, UnscentedKalmanFilter])
@pytest.mark.parametrize("dm", [(3, 2), (2, 4)])
def test_ekf_ukf_equal_kf_on_linear_models(cls, dm):
    model = random_lg(*dm, seed=3)
    traj, mean, cov = _data(model)
    ref = KalmanFilter(model)(traj.observations, mean, cov, return_covariances=True)
    out = cls(model)(traj.observations, mean, cov, return_covariances=True)
    torch.testing.assert_close(out.estimates, ref.estimates, atol=1e-9, rtol=0)
    torch.testing.assert_close(out.covariances, ref.covariances, atol=1e-9, rtol=0)
    torch.testing.assert_close(out.log_evidence, ref.log_evidence, atol=1e-9, rtol=0)


def test_ukf_other_sigma_point_settings_still_exact(small_lg):
    traj, mean, cov = _data(small_lg)
    ref = KalmanFilter(small_lg)(traj.observations, mean, cov)
    out = UnscentedKalmanFilter(small_lg, alpha=0.5, beta=0.0, kappa=1.0)(traj.observations, mean, cov)
    torch.testing.assert_close(out.log_evidence, ref.log_evidence, atol=1e-9, rtol=0)


def test_kf_log_evidence_gradcheck():
    model = random_lg(2, 2, seed=5, learnable=True)
    traj, mean, cov = _data(model, B=2, T=3)
    kf = KalmanFilter(model)
    names = ["F", "parametrizations.Q.original", "H"]  # Q through its Cholesky parametrisation

    def f(Fm, Qm, Hm):
        out = functional_call(
            kf, {"model." + n: v for n, v in zip(names, (Fm, Qm, Hm))}, (traj.observations, mean, cov)
        )
        return out.log_evidence

    inputs = tuple(model.get_parameter(n).detach().clone().requires_grad_(True) for n in names)
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5)


def test_kf_log_evidence_backward_to_parameters():
    model = random_lg(3, 2, seed=6, learnable=True)
    traj, mean, cov = _data(model)
    KalmanFilter(model)(traj.observations, mean, cov).log_evidence.sum().backward()
    for p in model.parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0


def test_kf_requires_linear_model(acoustic):
    with pytest.raises(TypeError, match="LinearGaussian"):
        KalmanFilter(acoustic)


def test_scalar_support_update_equals_the_joseph_form():
    """The k x k (Woodbury) EKF update of a scalar-R model with a measurement support
    (``tuning.structured_update``) gives kalman_update's posterior and log-density to round-off,
    per particle, including for a nearly singular support block."""
    from torchflow.core import tuning
    from torchflow.core.trackers import ekf_update, kalman_update, kalman_update_scalar_support
    from torchflow.models import AcousticTracking

    m = AcousticTracking()
    g = torch.Generator().manual_seed(0)
    traj = m.simulate(3, 2, g)
    d = m.state_dim
    mean = traj.states[:, 1].unsqueeze(1) + 0.3 * torch.randn(3, 5, d, dtype=torch.float64, generator=g)
    A = 0.3 * torch.randn(3, 5, d, d, dtype=torch.float64, generator=g)
    P = A @ A.transpose(-1, -2) + 0.1 * torch.eye(d, dtype=torch.float64)
    P[0, 0] = P[0, 0] * 1e-6 + 1e-9 * torch.eye(d, dtype=torch.float64)  # a tight prior
    z = traj.observations[:, 1].unsqueeze(1)
    ref = kalman_update(mean, P, z, m.measure(mean), m.measurement_jacobian(mean), m.measurement_cov())
    h, Hs = m.linearize_measurement(mean, support=True)
    got = kalman_update_scalar_support(mean, P, z, h, Hs, m.measurement_cov()[0, 0], m.structure.measurement_support)
    for a, b in zip(got, ref):
        assert a.shape == b.shape
        assert ((a - b).abs().max() / b.abs().max()).item() < 1e-12
    with tuning.tuned(structured_update=1):
        on = ekf_update(m, mean, P, z)
    with tuning.tuned(structured_update=0):
        off = ekf_update(m, mean, P, z)
    for a, b in zip(on, off):
        assert ((a - b).abs().max() / b.abs().max()).item() < 1e-12
    assert not all(torch.equal(a, b) for a, b in zip(on, off))  # the knob picks another computation


@pytest.mark.parametrize("cls", [ExtendedKalmanFilter, UnscentedKalmanFilter])
def test_inflation_scales_the_predicted_covariance(cls):
    """One step with inflation c is the update of the prediction whose covariance is c^2 times the
    uninflated one; c = 1 is the filter unchanged; c < 1 is refused by name."""
    from torchflow.core.errors import ArgumentError
    from torchflow.filters import GaussianState

    model = random_lg(3, 2)
    g = torch.Generator().manual_seed(0)
    mean = torch.randn(2, 3, generator=g, dtype=torch.float64)
    cov = torch.eye(3, dtype=torch.float64).expand(2, 3, 3).clone()
    z = torch.randn(2, 2, generator=g, dtype=torch.float64)
    state = GaussianState(mean, cov, torch.zeros(2, dtype=torch.float64), 0)
    f = cls(model, inflation=1.2)
    out = f.step(state, z)
    m_pred, P_pred = f.predict(mean, cov)
    want_mean, want_cov, _ = f.update(m_pred, 1.44 * P_pred, z)
    torch.testing.assert_close(out.mean, want_mean)
    torch.testing.assert_close(out.cov, want_cov)
    plain = cls(model).step(state, z)
    assert not torch.allclose(plain.cov, out.cov)
    with pytest.raises(ArgumentError, match="inflation: expected a finite number >= 1"):
        cls(model, inflation=0.9)


def test_the_ukf_refuses_a_singular_measurement_noise_naming_it():
    """Case X31: R = 0 ran until the sigma points collapsed (a non-finite estimate at step 3 that
    named nothing); the KF and the EKF run the same model (m <= d, Joseph form)."""
    from torchflow.core.errors import ArgumentError
    from torchflow.filters import ExtendedKalmanFilter, KalmanFilter, UnscentedKalmanFilter
    from torchflow.models import LinearGaussian

    eye = torch.eye(2, dtype=torch.float64)
    model = LinearGaussian(0.9 * eye, 0.2 * eye, eye, 0 * eye, torch.zeros(2, dtype=torch.float64), eye)
    traj = model.simulate(2, 5, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0])
    with pytest.raises(ArgumentError, match="UnscentedKalmanFilter: .*measurement covariance is not positive definite"):
        UnscentedKalmanFilter(model)(traj.observations, mean, cov)
    for f in (KalmanFilter(model), ExtendedKalmanFilter(model)):
        assert torch.isfinite(f(traj.observations, mean, cov).estimates).all()
