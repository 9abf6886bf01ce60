"""Geodesic, Gromov and optimised-diffusion flows, the stochastic integrator's proposal recursion,
the Zhang et al. (2024) schedule, and the PF-PF built on them."""

import math

import pytest
import torch
from conftest import mild_lg, random_lg
from conftest import replicated as _replicated
from test_flows import _lg_problem, _prior
from torch.func import jacrev

from torchflow.core import linalg
from torchflow.filters import KalmanFilter, ParticleFlowFilter, ParticleFlowParticleFilter
from torchflow.flows import (
    EDHFlow,
    FlowCoefficients,
    FlowPrior,
    GeodesicFlow,
    GromovFlow,
    OptimalDiffusionFlow,
    diffusion_condition_number,
    integrate_flow,
    optimal_diffusion_scale,
    symmetric_sqrt,
)
from torchflow.flows.measurement import whiten
from torchflow.flows.schedules import ExponentialSchedule, GeometricSchedule, UniformSchedule
from torchflow.models import AcousticTracking

F64 = torch.float64


# ---- Zhang et al. (2024) schedule ----------------------------------------------------------------------------
def test_geometric_schedule_closes_at_one():
    for (d1, beta), n in (((1e-4, 2.0), 14), ((1e-5, 1.5), 27), ((1.0, 2.0), 1)):
        s = GeometricSchedule(d1, beta)
        eps, lam = s.steps()
        assert len(s) == n and float(lam[-1]) == 1.0 and abs(float(eps.sum()) - 1) < 1e-14
        assert float(eps[0]) == d1 and 0 < float(eps[-1]) <= d1 * beta ** (n - 1) + 1e-15
        if n > 2:
            assert torch.allclose(eps[1:-1] / eps[:-2], torch.full((n - 2,), beta, dtype=F64))
        assert (lam >= eps).all()
    with pytest.raises(ValueError, match="first_step"):
        GeometricSchedule(0.0)
    with pytest.raises(ValueError, match="ratio"):
        GeometricSchedule(1e-3, 0.5)


# ---- coefficients -----------------------------------------------------------------------------------
def _dense_homotopy(model, aux, z, P, eta0, lam):
    """Reference quantities by explicit (test-only) inverses: M^-1, J, M^-1 H^T R^-1 (z - e), m."""
    H = model.measurement_jacobian(aux)
    R = model.measurement_cov(aux)
    e = model.measure(aux) - H @ aux
    Ri = torch.linalg.inv(R)
    J = H.T @ Ri @ H
    Mi = torch.linalg.inv(torch.linalg.inv(P) + lam * J)
    g = Mi @ H.T @ Ri @ (z - e)
    m = Mi @ (torch.linalg.inv(P) @ eta0 + lam * H.T @ Ri @ (z - e))
    return Mi, J, g, m


@pytest.mark.parametrize("model_name", ["lg", "acoustic"])
def test_coefficients_match_dense_formulas(model_name):
    """Square-root information forms equal the textbook formulas built with explicit inverses."""
    if model_name == "lg":
        model, mean, P, z, *_ = _lg_problem(3, 5)
        aux, P, eta0, z = mean[0] + 0.2, P[0], mean[0], z[0]
    else:
        model = AcousticTracking()
        traj = model.simulate(1, 2, torch.Generator().manual_seed(0))
        eta0, z = traj.states[0, 1], traj.observations[0, 1]
        aux = eta0 + 0.3
        P = torch.diag(torch.tensor([2.0, 2.0, 0.1, 0.1] * 4, dtype=F64))
    lam, eps = torch.tensor(0.4, dtype=F64), torch.tensor(0.1, dtype=F64)
    prior = FlowPrior(eta0.unsqueeze(0), torch.linalg.cholesky(P).unsqueeze(0))
    Mi, J, g, m = _dense_homotopy(model, aux, z, P, eta0, lam)
    a, zz = aux.unsqueeze(0), z.unsqueeze(0)
    geo = GeodesicFlow(points="global").coefficients(model, zz, a, prior, lam, eps)
    torch.testing.assert_close(geo.dense_A()[0], -Mi @ J)
    torch.testing.assert_close(geo.b[0], g)
    I = torch.eye(len(eta0), dtype=F64)
    torch.testing.assert_close(geo.log_det[0], torch.linalg.slogdet(I - eps * Mi @ J)[1])
    gro = GromovFlow(points="global").coefficients(model, zz, a, prior, lam, eps)
    G = gro.noise_factor[0]
    torch.testing.assert_close(G @ G.T, Mi @ J @ Mi)
    torch.testing.assert_close(gro.dense_A(), geo.dense_A())
    sym = (
        GromovFlow(points="global", noise_root="symmetric").coefficients(model, zz, a, prior, lam, eps).noise_factor[0]
    )
    torch.testing.assert_close(sym, sym.T)
    torch.testing.assert_close(sym @ sym, Mi @ J @ Mi)
    c = 0.7
    osd = OptimalDiffusionFlow(c=c, points="global").coefficients(model, zz, a, prior, lam, eps)
    edh = EDHFlow().coefficients(model, zz, a, prior, lam, eps)
    # A_s = A_EDH - Q M / 2, b_s = b_EDH + Q M m / 2 with Q = c M^-1
    torch.testing.assert_close(osd.dense_A()[0], edh.dense_A()[0] - c / 2 * I)
    torch.testing.assert_close(osd.b[0], edh.b[0] + c / 2 * m)
    torch.testing.assert_close(osd.noise_factor[0] @ osd.noise_factor[0].T, c * Mi)


def test_osd_with_zero_diffusion_is_edh_and_gromov_is_edh_plus_its_diffusion():
    model, mean, P, z, *_ = _lg_problem(4, 2)
    L = linalg.safe_cholesky(P)
    prior = FlowPrior(mean, L)
    aux = mean + 0.1
    lam, eps = torch.tensor(0.3, dtype=F64), torch.tensor(0.05, dtype=F64)
    edh = EDHFlow().coefficients(model, z, aux, prior, lam, eps)
    osd0 = OptimalDiffusionFlow(c=0.0, points="global").coefficients(model, z, aux, prior, lam, eps)
    torch.testing.assert_close(osd0.dense_A(), edh.dense_A(), rtol=0, atol=1e-13)
    torch.testing.assert_close(osd0.b, edh.b, rtol=0, atol=1e-12)
    assert float(osd0.noise_factor.abs().max()) == 0.0
    # Gromov = EDH drift with Q = M^-1 J M^-1 added by the Fokker-Planck rule A_s = A - Q M / 2
    gro = GromovFlow(points="global").coefficients(model, z, aux, prior, lam, eps)
    Q = gro.noise_factor @ gro.noise_factor.transpose(-1, -2)
    M = torch.linalg.inv(L @ L.transpose(-1, -2)) + lam * model.H.T @ torch.linalg.inv(model.R) @ model.H
    torch.testing.assert_close(gro.dense_A(), edh.dense_A() - 0.5 * Q @ M)


def test_symmetric_sqrt_keeps_rank_of_singular_q():
    """A rank-2 Q in d = 4 has no Cholesky factor; the symmetric root reproduces it and its rank."""
    g = torch.Generator().manual_seed(0)
    G = torch.randn(3, 4, 2, dtype=F64, generator=g)
    Q = G @ G.transpose(-1, -2)
    R = symmetric_sqrt(Q)
    torch.testing.assert_close(R, R.transpose(-1, -2))
    torch.testing.assert_close(R @ R, Q)
    assert (torch.linalg.matrix_rank(R) == 2).all()
    assert (torch.linalg.eigvalsh(R) > -1e-12).all()
    assert not torch.linalg.cholesky_ex(Q).info.eq(0).all()


def test_gromov_diffusion_is_rank_deficient_on_acoustic_and_integrates_finite():
    """Velocities are unobserved: J has rank <= 8 of 16, so Q = M^-1 J M^-1 is singular. The thin
    factor and the symmetric root both give finite Euler-Maruyama paths of the right law."""
    model = AcousticTracking(sigma_w=0.001)
    g = torch.Generator().manual_seed(1)
    traj = model.simulate(2, 3, g)
    mean = traj.states[:, 2]
    P = torch.diag(torch.tensor([1.0, 1.0, 0.1, 0.1] * 4, dtype=F64)).expand(2, 16, 16)
    L = linalg.safe_cholesky(P)
    z = traj.observations[:, 2]
    lam, eps = torch.tensor(0.5, dtype=F64), torch.tensor(0.1, dtype=F64)
    co = GromovFlow(points="global").coefficients(model, z, mean, FlowPrior(mean, L), lam, eps)
    Q = co.noise_factor @ co.noise_factor.transpose(-1, -2)
    assert (torch.linalg.matrix_rank(Q, rtol=1e-10) <= 8).all()
    for root in ("factor", "symmetric"):
        N = 200
        x0 = linalg.sample_mvn(mean, L, (N,), g)
        out = integrate_flow(
            GromovFlow(noise_root=root),
            model,
            x0,
            z,
            _prior(GromovFlow(), mean, L, N),
            ExponentialSchedule(29, 1.2),
            generator=g,
            proposal=FlowPrior(mean.unsqueeze(1).expand(2, N, 16), L.unsqueeze(1)),
        )
        assert torch.isfinite(out.particles).all() and torch.isfinite(out.log_proposal).all()


# ---- optimal diffusion scale --------------------------------------------------------------------------
def _objective(flow_A, c_values, alpha):
    """J(c) = kappa(A_s(c)) + alpha c, kappa from the eigenvalues of the flow's actual A_s matrix."""
    out = []
    for A in flow_A:
        ev = torch.linalg.eigvals(A).abs()
        out.append(float(ev.max() / ev.min()))
    return torch.tensor(out, dtype=F64) + alpha * torch.as_tensor(c_values, dtype=F64)


@pytest.mark.parametrize("case", ["lg-full-rank", "acoustic-rank-deficient"])
def test_optimal_c_minimises_objective(case):
    """c* (closed form) beats its neighbours on J and equals a numeric 1-D minimisation of J built
    from the eigenvalues of the drift matrix the flow actually uses."""
    alpha = 0.1
    if case == "lg-full-rank":
        model, mean, P, z, *_ = _lg_problem(3, 5)
        mean, P, z = mean[:1], P[:1], z[:1]
    else:
        model = AcousticTracking()
        traj = model.simulate(1, 2, torch.Generator().manual_seed(0))
        mean, z = traj.states[:, 1], traj.observations[:, 1]
        P = torch.diag(torch.tensor([2.0, 2.0, 0.1, 0.1] * 4, dtype=F64)).unsqueeze(0)
    prior = FlowPrior(mean, linalg.safe_cholesky(P))
    lam, eps = torch.tensor(0.2, dtype=F64), torch.tensor(0.01, dtype=F64)

    def A_at(c):
        return (
            OptimalDiffusionFlow(c=float(c), points="global").coefficients(model, z, mean, prior, lam, eps).dense_A()[0]
        )

    flow = OptimalDiffusionFlow(alpha=alpha, points="global")
    W, _ = whiten(model, mean, z)
    L = prior.scale_tril
    S = (W @ L).transpose(-1, -2) @ (W @ L)
    c_star = float(flow.scale(S, lam)[0])
    assert c_star > 0
    J = lambda cs: _objective([A_at(c) for c in cs], cs, alpha)
    Js = J([c_star, 0.9 * c_star, 1.1 * c_star, 0.5 * c_star, 2 * c_star])
    assert (Js[0] < Js[1:]).all(), Js
    # numeric minimisation: golden section on log c over [1e-6, 1e6] (J is convex in c)
    lo, hi = math.log(1e-6), math.log(1e6)
    phi = (math.sqrt(5) - 1) / 2
    for _ in range(120):
        a, b = hi - phi * (hi - lo), lo + phi * (hi - lo)
        if J([math.exp(a)])[0] < J([math.exp(b)])[0]:
            hi = b
        else:
            lo = a
    c_num = math.exp((lo + hi) / 2)
    assert abs(c_num - c_star) < 1e-4 * c_star, (c_num, c_star)


def test_optimal_scale_closed_form_and_seed_convention():
    k_min = torch.tensor([0.0, 0.5, 2.0], dtype=F64)
    k_max = torch.tensor([40.0, 3.0, 2.05], dtype=F64)
    c = optimal_diffusion_scale(k_min, k_max, 0.1)
    # Zhang et al.'s (2024) formula minimises kappa + alpha' c' with A_s = A - c' I; the same noise is our
    # c = 2 c', so our objective kappa + 0.1 c is theirs with alpha' = 0.2
    seed = (torch.sqrt((k_max - k_min) / 0.2) - k_min).clamp_min(0)
    torch.testing.assert_close(c / 2, seed)
    torch.testing.assert_close(
        optimal_diffusion_scale(k_min, k_max, 0.05) / 2, (torch.sqrt((k_max - k_min) / 0.1) - k_min).clamp_min(0)
    )
    assert float(c[2]) == 0.0  # nearly isotropic drift: no diffusion needed
    k = torch.stack([k_min, k_max], -1)
    for i in range(3):
        grid = torch.linspace(0, 4 * float(c[i]) + 1, 20001, dtype=F64)
        Jg = diffusion_condition_number(k[i].expand(len(grid), 2), grid) + 0.1 * grid if float(k_min[i]) > 0 else None
        if Jg is not None:
            assert abs(float(grid[Jg.argmin()]) - float(c[i])) < 2e-3 * (4 * float(c[i]) + 1)
    with pytest.raises(ValueError, match="alpha"):
        optimal_diffusion_scale(k_min, k_max, 0.0)
    # the printed rule: Zhang et al.'s (2024) value as the diffusion scale itself (MODELS.md 12.1), the exact
    # minimiser of (k_max + c)/(k_min + c) + alpha c
    printed = optimal_diffusion_scale(k_min, k_max, 0.1, rule="printed")
    torch.testing.assert_close(printed, (torch.sqrt((k_max - k_min) / 0.1) - k_min).clamp_min(0))
    grid = torch.linspace(0, 40, 400001, dtype=F64)
    J = (k_max[1] + grid) / (k_min[1] + grid) + 0.1 * grid
    assert abs(float(grid[J.argmin()]) - float(printed[1])) < 1e-3
    # printed_shift: the printed value as the drift's shift c', so the diffusion scale is c = 2 c'
    torch.testing.assert_close(optimal_diffusion_scale(k_min, k_max, 0.1, rule="printed_shift"), 2 * printed)
    flow = OptimalDiffusionFlow(alpha=0.1, c_rule="printed_shift")
    S = torch.diag(torch.tensor([0.0, 40.0], dtype=F64)).unsqueeze(0)  # k = s / (2 (1 + lam s))
    k = 40.0 / (2 * (1 + 0.5 * 40.0))
    torch.testing.assert_close(flow.scale(S, 0.5), torch.tensor([2 * (k / 0.1) ** 0.5], dtype=F64))
    with pytest.raises(ValueError, match="rule"):
        optimal_diffusion_scale(k_min, k_max, 0.1, rule="numeric")
    with pytest.raises(ValueError, match="c_rule"):
        OptimalDiffusionFlow(c_rule="numeric")


def test_flow_argument_errors():
    with pytest.raises(ValueError, match="alpha"):
        OptimalDiffusionFlow(alpha=0)
    with pytest.raises(ValueError, match="c:"):
        OptimalDiffusionFlow(c=-1.0)
    with pytest.raises(ValueError, match="c:"):
        OptimalDiffusionFlow(c="big")
    with pytest.raises(ValueError, match="noise_root"):
        GromovFlow(noise_root="cholesky")


# ---- integrator: exact proposal recursion ----------------------------------------------------------
@pytest.mark.parametrize("local", [False, True], ids=["global", "local"])
def test_gromov_proposal_recursion_is_the_exact_posterior_at_any_schedule(local):
    """On a linear-Gaussian model with the flow built for the particles' own law (P = S_0), the
    Gromov Euler-Maruyama law is exactly the posterior after every step, whatever the schedule:
    (I - eps M_j^-1 J) = M_j^-1 M_{j-1}, so S_j = M_j^-1 M_{j-1} M_{j-1}^-1 M_{j-1} M_j^-1 +
    eps M_j^-1 J M_j^-1 = M_j^-1. (With P = V, the posterior is the optimal proposal.)"""
    model, mean, P, z, post_m, post_P, g = _lg_problem(4, 3)
    L = linalg.safe_cholesky(P)
    N = 5
    x0 = linalg.sample_mvn(mean, L, (N,), g)
    flow = GromovFlow(points="particle" if local else "global")
    for sched in (UniformSchedule(1), ExponentialSchedule(5, 1.5), GeometricSchedule(1e-3, 2.0)):
        out = integrate_flow(
            flow,
            model,
            x0,
            z,
            _prior(flow, mean, L, N),
            sched,
            generator=g,
            proposal=FlowPrior(mean.unsqueeze(1).expand(2, N, 4), L.unsqueeze(1)),
        )
        torch.testing.assert_close(out.proposal_mean, post_m.unsqueeze(1).expand(2, N, 4), rtol=0, atol=1e-10)
        torch.testing.assert_close(
            out.proposal_cov.expand(2, N, 4, 4), post_P.unsqueeze(1).expand(2, N, 4, 4), rtol=0, atol=1e-10
        )


def test_osd_proposal_recursion_converges_to_the_posterior_as_schedule_is_refined():
    """The optimised-diffusion flow is exact only in continuous pseudo-time: its recursion's
    (mu, Sigma) error against the posterior falls like 1/n_steps."""
    model, mean, P, z, post_m, post_P, g = _lg_problem(4, 3)
    L = linalg.safe_cholesky(P)
    x0 = mean.unsqueeze(1)
    errs = []
    for n in (10, 100, 1000):
        out = integrate_flow(
            OptimalDiffusionFlow(points="global"),
            model,
            x0,
            z,
            FlowPrior(mean, L),
            UniformSchedule(n),
            generator=g,
            proposal=FlowPrior(x0, L.unsqueeze(1)),
        )
        errs.append(
            max(
                float((out.proposal_mean[:, 0] - post_m).abs().max()),
                float((out.proposal_cov[:, 0] - post_P).abs().max()),
            )
        )
    assert errs[0] > errs[1] > errs[2] and errs[2] < 1e-2 * float(post_P.abs().max()), errs
    assert errs[1] / errs[2] > 5  # first order


def test_stochastic_recursion_with_zero_diffusion_equals_log_det_weight():
    """Run the geodesic drift through the stochastic integrator with Q = 0: the tracked Gaussian
    density of the (deterministic) image must equal log p(eta_0) - log|det| from the
    deterministic path, on the nonlinear acoustic model (per-particle linearisation)."""

    class ZeroNoiseGeodesic(GeodesicFlow):
        stochastic = True

        def coefficients_at(self, *a):
            co = super().coefficients_at(*a)
            return FlowCoefficients(co.A, co.b, None, noise_factor=torch.zeros_like(co.A[..., :1]), support=co.support)

    model = AcousticTracking()
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(2, 3, g)
    B, N, d = 2, 6, 16
    x_prev = traj.states[:, 1].unsqueeze(1).expand(B, N, d)
    mu0, V = model.transition_mean(x_prev), model.transition_scale_tril(x_prev)
    eta0 = model.sample_transition(x_prev, g)
    P = torch.diag(torch.tensor([2.0, 2.0, 0.1, 0.1] * 4, dtype=F64)).expand(B, N, d, d)
    prior = FlowPrior(mu0, linalg.safe_cholesky(P))
    z, sched = traj.observations[:, 2], ExponentialSchedule(10, 1.3)
    det = integrate_flow(GeodesicFlow(), model, eta0, z, prior, sched)
    sto = integrate_flow(ZeroNoiseGeodesic(), model, eta0, z, prior, sched, generator=g, proposal=FlowPrior(mu0, V))
    torch.testing.assert_close(sto.particles, det.particles)
    expected = linalg.mvn_log_prob(eta0, mu0, V) - det.log_det
    torch.testing.assert_close(sto.log_proposal, expected, rtol=0, atol=1e-7)


def test_geodesic_log_det_equals_jacobian_of_full_map():
    model = AcousticTracking()
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(1, 3, g)
    mean = traj.states[:, 2] + 0.5 * torch.randn(1, 16, dtype=F64, generator=g)
    L = linalg.safe_cholesky(torch.diag(torch.tensor([1.0, 1.0, 0.1, 0.1] * 4, dtype=F64)).unsqueeze(0))
    z, sched = traj.observations[:, 2], ExponentialSchedule(12, 1.3)
    x0 = mean + 0.3 * torch.randn(1, 16, dtype=F64, generator=g)
    flow = GeodesicFlow()

    def f(x):
        return integrate_flow(flow, model, x.reshape(1, 1, 16), z, _prior(flow, mean, L, 1), sched).particles.reshape(
            16
        )

    sign, logabs = torch.linalg.slogdet(jacrev(f)(x0[0]))
    out = integrate_flow(flow, model, x0.reshape(1, 1, 16), z, _prior(flow, mean, L, 1), sched)
    assert sign > 0 and abs(float(out.log_det[0, 0]) - float(logabs)) < 1e-9


@pytest.mark.parametrize(
    "flow",
    [
        GromovFlow(points="global"),
        GromovFlow(),
        GromovFlow(points="global", noise_root="symmetric"),
        OptimalDiffusionFlow(points="global"),
    ],
    ids=["gromov-global", "gromov-local", "gromov-sym", "osd"],
)
def test_stochastic_cloud_matches_kf_posterior_in_distribution(flow):
    """Prior samples pushed through the stochastic flow have the KF posterior's mean and covariance
    within 5 Monte Carlo sd (plus, for the optimised diffusion, its Euler bias at 200 steps; the
    Gromov law is exact at any schedule, so 20 steps suffice there)."""
    model, mean, P, z, post_m, post_P, g = _lg_problem(3, 5)
    N = 20000
    L = linalg.safe_cholesky(P)
    x0 = linalg.sample_mvn(mean, L, (N,), g)
    sched = UniformSchedule(20 if isinstance(flow, GromovFlow) else 200)
    out = integrate_flow(flow, model, x0, z, _prior(flow, mean, L, N), sched, generator=g)
    mu, C = linalg.weighted_mean_cov(out.particles, torch.zeros(2, N, dtype=F64))
    var = post_P.diagonal(dim1=-2, dim2=-1)
    sd_m = (var / N).sqrt()
    sd_C = ((var.unsqueeze(-1) * var.unsqueeze(-2) + post_P**2) / N).sqrt()
    scale = post_P.abs().amax((-1, -2))
    bias = (0.0 if isinstance(flow, GromovFlow) else 1.0 / 200) * scale
    assert ((mu - post_m).abs() <= 5 * sd_m + 3 * (bias * scale.sqrt()).unsqueeze(-1)).all()
    assert ((C - post_P).abs() <= 5 * sd_C + bias[:, None, None]).all()


def test_geodesic_cloud_over_contracts():
    """Without its diffusion the geodesic drift shrinks the cloud at twice the posterior's rate."""
    model, mean, P, z, post_m, post_P, g = _lg_problem(3, 5)
    N = 20000
    L = linalg.safe_cholesky(P)
    x0 = linalg.sample_mvn(mean, L, (N,), g)
    out = integrate_flow(GeodesicFlow(points="global"), model, x0, z, FlowPrior(mean, L), UniformSchedule(200))
    _, C = linalg.weighted_mean_cov(out.particles, torch.zeros(2, N, dtype=F64))
    assert (torch.linalg.eigvalsh(post_P - C) > 0).any(-1).all() and (
        C.diagonal(0, -2, -1) < post_P.diagonal(0, -2, -1)
    ).all()


def test_stochastic_flow_is_reproducible_and_uses_the_generator():
    model, mean, P, z, *_ = _lg_problem(3, 5)
    L = linalg.safe_cholesky(P)
    x0 = linalg.sample_mvn(mean, L, (50,), torch.Generator().manual_seed(0))
    run = lambda s: (
        integrate_flow(
            GromovFlow(points="global"),
            model,
            x0,
            z,
            FlowPrior(mean, L),
            UniformSchedule(5),
            generator=torch.Generator().manual_seed(s),
        ).particles
    )
    torch.testing.assert_close(run(1), run(1), rtol=0, atol=0)
    assert (run(1) - run(2)).abs().max() > 1e-3


# ---- filters ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("flow", ["gromov", "osd", GromovFlow(points="global")], ids=["gromov", "osd", "gromov-global"])
def test_pfpf_stochastic_log_evidence_unbiased_on_lg(flow):
    """E[Z_hat / Z] = 1 within 4 standard errors over 400 runs on the same data (as for LEDH).

    PF-PF(Geodesic) is not tested this way: its over-contracting proposal is narrower than the
    target, so its weights have infinite variance and a sample standard error means nothing (its
    weight is the deterministic-flow weight, checked exactly by the log|det| tests)."""
    model = mild_lg()
    obs, mean, cov = _replicated(model, 400, 6)
    logz = KalmanFilter(model)(obs[:1], mean[:1], cov[:1]).log_evidence
    f = ParticleFlowParticleFilter(model, flow=flow, n_particles=64, schedule=ExponentialSchedule(15, 1.2))
    r = torch.exp(f(obs, mean, cov, torch.Generator().manual_seed(1)).log_evidence - logz)
    se = r.std() / math.sqrt(r.numel())
    assert abs(float(r.mean()) - 1) < 4 * float(se), (float(r.mean()), float(se))
    assert float(se) < 0.05
    assert abs(float(r.log().median())) < 0.5


def test_pfpf_gromov_without_proposal_density_would_be_biased(monkeypatch):
    """The test above can fail: weighting Gromov particles as if the flow were deterministic
    (dropping the tracked proposal density for p(eta_0)) biases Z_hat far beyond its tolerance."""
    from torchflow.proposals import StochasticFlowProposal

    def wrong(self, eta0, x_prev, z, prior, generator, log_q0, noise=None, index=None):
        out = integrate_flow(self.flow, self.model, eta0, z, prior, self.schedule, generator=generator)
        return out.particles, self.model.transition_log_prob(eta0, x_prev), None, None

    monkeypatch.setattr(StochasticFlowProposal, "_migrate", wrong)
    model = mild_lg()
    obs, mean, cov = _replicated(model, 400, 6)
    logz = KalmanFilter(model)(obs[:1], mean[:1], cov[:1]).log_evidence
    f = ParticleFlowParticleFilter(model, flow="gromov", n_particles=16, schedule=ExponentialSchedule(15, 1.2))
    log_r = f(obs, mean, cov, torch.Generator().manual_seed(1)).log_evidence - logz
    # the correct filter's log-ratios centre near 0 (median |log r| < 0.5 in the test above)
    assert abs(float(log_r.median())) > 5, float(log_r.median())


def test_pfpf_gromov_ess_above_ledh_and_geodesic_far_below_on_sensor_network():
    """Pal & Coates (2019) Table I ordering on a small sensor network (d = 16, 10 trials, N = 100)."""
    from torchflow.models import SensorNetwork

    model = SensorNetwork(d=16)
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(10, 5, g)
    mean, cov = model.initial_belief(traj.states[:, 0])
    ess = {}
    for fl in ("gromov", "ledh", "geodesic"):
        f = ParticleFlowParticleFilter(model, flow=fl, n_particles=100)
        ess[fl] = float(f(traj.observations, mean, cov, torch.Generator().manual_seed(1)).ess.mean())
    assert ess["gromov"] > ess["ledh"] > 3 * ess["geodesic"], ess


@pytest.mark.parametrize("flow", ["gromov", "geodesic", "osd"])
def test_stiff_acoustic_runs_finite_stochastic(flow):
    model = AcousticTracking(sigma_w=0.001)
    g = torch.Generator().manual_seed(3)
    traj = model.simulate(3, 8, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    res = ParticleFlowParticleFilter(model, flow=flow, n_particles=50)(traj.observations, mean, cov, g)
    assert torch.isfinite(res.estimates).all() and torch.isfinite(res.ess).all()
    assert torch.isfinite(res.log_evidence).all() and int(res.n_repaired.sum()) == 0


def test_unweighted_gromov_filter_tracks_kf_on_lg():
    model = random_lg(3, 2, seed=3)
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(4, 8, g)
    mean, cov = model.initial_belief(traj.states[:, 0])
    kf = KalmanFilter(model)(traj.observations, mean, cov, return_covariances=True)
    f = ParticleFlowFilter(model, flow="gromov", n_particles=4000, schedule=UniformSchedule(10))
    res = f(traj.observations, mean, cov, g)
    sd = kf.covariances.diagonal(dim1=-2, dim2=-1).sqrt()
    assert ((res.estimates - kf.estimates).abs() < 6 * sd / math.sqrt(4000) + 1e-9).all()


def test_pfpf_gromov_log_evidence_backpropagates():
    model = random_lg(3, 2, seed=5, learnable=True)
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(2, 4, g)
    mean, cov = model.initial_belief(traj.states[:, 0])
    for fl in ("gromov", "osd"):
        model.zero_grad()
        f = ParticleFlowParticleFilter(model, flow=fl, n_particles=20, schedule=ExponentialSchedule(8, 1.3))
        f(traj.observations, mean, cov, g).log_evidence.sum().backward()
        for p in model.parameters():
            assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0


def test_hydra_composes_the_new_flow_filters_and_schedule():
    from pathlib import Path

    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    cfg_dir = str(Path(__file__).resolve().parents[2] / "configs")
    names = ["geodesic", "gromov", "pfpf_geodesic", "pfpf_gromov", "pfpf_osd"]
    with initialize_config_dir(config_dir=cfg_dir, version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                "model=linear_gaussian",
                "model.d=4",
                f"filter=[{','.join(names)}]",
                "schedule@filter.pfpf_osd.schedule=geometric",
                "filter.pfpf_osd.flow.alpha=0.5",
            ],
        )
    model = instantiate(cfg.model)
    fs = {k: instantiate(v, model=model) for k, v in cfg.filter.items()}
    assert type(fs["pfpf_gromov"].flow) is GromovFlow and type(fs["gromov"].flow) is GromovFlow
    assert type(fs["pfpf_geodesic"].flow) is GeodesicFlow and isinstance(fs["geodesic"], ParticleFlowFilter)
    assert type(fs["pfpf_osd"].flow) is OptimalDiffusionFlow and fs["pfpf_osd"].flow.alpha == 0.5
    assert isinstance(fs["pfpf_osd"].schedule, GeometricSchedule) and len(fs["pfpf_osd"].schedule) == 14


@pytest.mark.parametrize(
    "flow", [GeodesicFlow(), OptimalDiffusionFlow(), GromovFlow()], ids=["geodesic", "osd", "gromov"]
)
def test_shared_prior_factor_path_equals_per_particle_path(flow):
    """Linear models share one prior factor per trial, (B, 1, d, d); the shared-solve path must give
    the same coefficients as the same factor expanded per particle, (B, N, d, d)."""
    model, mean, P, z, *_ = _lg_problem(3, 5)
    N = 7
    L = linalg.safe_cholesky(P).unsqueeze(1)
    aux = mean.unsqueeze(1) + torch.randn(2, N, 3, dtype=F64, generator=torch.Generator().manual_seed(0))
    lam, eps = torch.tensor(0.3, dtype=F64), torch.tensor(0.05, dtype=F64)
    shared = flow.coefficients(model, z, aux, FlowPrior(aux, L), lam, eps)
    full = flow.coefficients(model, z, aux, FlowPrior(aux, L.expand(2, N, 3, 3)), lam, eps)
    torch.testing.assert_close(shared.A.expand_as(full.A), full.A)
    torch.testing.assert_close(shared.b, full.b)
    if flow.stochastic:  # the diffusion too, and it stays shared (one d x d law per trial)
        Qs, Qf = shared.diffusion_cov(), full.diffusion_cov()
        assert Qs.shape[1] == 1
        torch.testing.assert_close(Qs.expand_as(Qf), Qf)
        xi = torch.randn(2, N, shared.noise_rank, dtype=F64, generator=torch.Generator().manual_seed(1))
        torch.testing.assert_close(shared.diffuse(xi), full.diffuse(xi))
