"""The performance paths compute exactly what the plain formulas compute: the
measurement-support reduction, the Gromov diffusion in operator form, the fused covariance
propagation, the single-threaded triangular solves and the model's shared linearisation."""

import pytest
import torch

from torchflow.core import linalg, tuning
from torchflow.filters import ParticleFlowParticleFilter
from torchflow.flows import (
    EDHFlow,
    FlowPrior,
    GeodesicFlow,
    GromovFlow,
    LEDHFlow,
    OptimalDiffusionFlow,
    daum_huang_coefficients,
    integrate_flow,
)
from torchflow.flows.schedules import ExponentialSchedule
from torchflow.models import AcousticTracking

F64 = torch.float64


class FullSupportAcoustic(AcousticTracking):
    """The same model without the declared support: every flow takes the full d x d path."""

    structure = AcousticTracking.structure.replace(measurement_support=None)


def _acoustic_points(B=2, N=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    model = AcousticTracking()
    traj = model.simulate(B, 2, g)
    z = traj.observations[:, 1]
    aux = traj.states[:, 1].unsqueeze(1) + 0.5 * torch.randn(B, N, 16, dtype=F64, generator=g)
    A = torch.randn(B, N, 16, 16, dtype=F64, generator=g)
    P = A @ A.transpose(-1, -2) / 16 + torch.diag(torch.tensor([2.0, 2.0, 0.1, 0.1] * 4, dtype=F64))
    return model, z, aux, P


def test_acoustic_support_jacobian_and_linearisation():
    model, _, aux, _ = _acoustic_points()
    sup = list(model.structure.measurement_support)
    assert sup == [0, 1, 4, 5, 8, 9, 12, 13]
    J = model.measurement_jacobian(aux)
    others = [i for i in range(16) if i not in sup]
    assert float(J[..., others].abs().max()) == 0.0  # the support is exact: velocities never enter h
    torch.testing.assert_close(model.measurement_jacobian_support(aux), J[..., sup], rtol=0, atol=0)
    h, Hs = model.linearize_measurement(aux, support=True, scale=torch.tensor(4.0, dtype=F64))
    torch.testing.assert_close(h, 4 * model.measure(aux))
    torch.testing.assert_close(Hs, 4 * J[..., sup])
    h, H = model.linearize_measurement(aux)
    torch.testing.assert_close(H, J)


@pytest.mark.parametrize(
    "flow",
    [LEDHFlow(), GeodesicFlow(), GromovFlow(), OptimalDiffusionFlow(c=0.3), GromovFlow(noise_root="symmetric")],
    ids=lambda f: type(f).__name__,
)
def test_support_reduction_equals_full_path(flow):
    """k x k systems at the measured coordinates give the d x d path's drift, log-det and diffusion."""
    model, z, aux, P = _acoustic_points()
    full_model = FullSupportAcoustic()
    prior = FlowPrior(aux, linalg.safe_cholesky(P))
    lam, eps = torch.tensor(0.35, dtype=F64), torch.tensor(0.02, dtype=F64)
    red = flow.coefficients(model, z, aux, prior, lam, eps)
    full = flow.coefficients(full_model, z, aux, prior, lam, eps)
    assert full.support is None
    if not isinstance(flow, OptimalDiffusionFlow):  # its A = -C/2 - (c/2) I is dense
        assert red.support is not None and red.A.shape[-1] == 8
    scale = float(full.dense_A().abs().max())
    torch.testing.assert_close(red.dense_A(), full.dense_A(), rtol=1e-9, atol=1e-12 * scale)
    torch.testing.assert_close(red.b, full.b, rtol=1e-8, atol=1e-11 * float(full.b.abs().max()))
    if full.log_det is not None:
        torch.testing.assert_close(red.log_det, full.log_det, rtol=1e-9, atol=1e-10)
    if flow.stochastic:
        Qr, Qf = red.diffusion_cov(), full.diffusion_cov()
        torch.testing.assert_close(Qr, Qf, rtol=1e-8, atol=1e-10 * float(Qf.abs().max()))


def test_gromov_operator_noise_is_the_exact_factor():
    """Per-particle Gromov: Q = C N^T is M^-1 J M^-1, and G xi = M^-1 W^T xi, by dense formulas."""
    model, z, aux, P = _acoustic_points(B=1, N=3)
    prior = FlowPrior(aux, linalg.safe_cholesky(P))
    lam, eps = torch.tensor(0.5, dtype=F64), torch.tensor(0.05, dtype=F64)
    co = GromovFlow().coefficients(model, z, aux, prior, lam, eps)
    assert co.noise_product is not None and co.noise_rank == 25  # G = U V^T, never formed
    xi = torch.randn(1, 3, 25, dtype=F64, generator=torch.Generator().manual_seed(3))
    Gxi = co.diffuse(xi)
    for n in range(3):
        H = model.measurement_jacobian(aux[0, n])
        W = H / model.sigma_w
        Mi = torch.linalg.inv(torch.linalg.inv(P[0, n]) + lam * W.T @ W)
        torch.testing.assert_close(co.diffusion_cov()[0, n], Mi @ W.T @ W @ Mi, rtol=1e-8, atol=1e-12)
        torch.testing.assert_close(Gxi[0, n], Mi @ W.T @ xi[0, n], rtol=1e-8, atol=1e-12)
        torch.testing.assert_close(co.dense_A()[0, n], -Mi @ W.T @ W, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("flow", ["ledh", "gromov", "edh"])
def test_pfpf_same_numbers_with_and_without_support(flow):
    """A whole PF-PF run: the support path changes only round-off, so the same seed gives the same
    estimates and log-evidence (to round-off amplified over a few steps)."""
    model, full_model = AcousticTracking(), FullSupportAcoustic()
    traj = model.simulate(2, 3, torch.Generator().manual_seed(1))
    mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator().manual_seed(2))
    out = []
    for m in (model, full_model):
        f = ParticleFlowParticleFilter(m, flow=flow, n_particles=40, resampling="systematic")
        with torch.no_grad():
            out.append(f(traj.observations, mean, cov, torch.Generator().manual_seed(5)))
    torch.testing.assert_close(out[0].estimates, out[1].estimates, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(out[0].log_evidence, out[1].log_evidence, rtol=1e-6, atol=1e-6)


def test_serial_triangular_solve_matches_and_restores_threads():
    g = torch.Generator().manual_seed(0)
    A = torch.randn(50, 6, 6, dtype=F64, generator=g)
    K = torch.linalg.cholesky(A @ A.transpose(-1, -2) + 6 * torch.eye(6, dtype=F64))
    R = torch.randn(50, 6, 3, dtype=F64, generator=g)
    n = torch.get_num_threads()
    X = linalg.solve_triangular(K, R, upper=False)
    assert torch.get_num_threads() == n
    torch.testing.assert_close(X, torch.linalg.solve_triangular(K, R, upper=False), rtol=0, atol=0)
    Y = linalg.chol_solve(K, R)
    torch.testing.assert_close(K @ K.transpose(-1, -2) @ Y, R)
    assert Y.is_contiguous()  # the transposed formulation returns row-major results


def test_stochastic_integrator_fused_covariance_matches_plain_recursion():
    """The proposal covariance of a per-particle Gromov flow (support path, fused baddbmm updates)
    equals the plain recursion S <- (I + eps A) S (I + eps A)^T + eps Q run by hand."""
    model, z, aux, P = _acoustic_points(B=1, N=4)
    prior = FlowPrior(aux, linalg.safe_cholesky(P))
    sched = ExponentialSchedule(n_steps=6)
    V = linalg.safe_cholesky(model.transition_cov())
    g = torch.Generator().manual_seed(0)
    out = integrate_flow(GromovFlow(), model, aux, z, prior, sched, generator=g, proposal=FlowPrior(aux, V))
    eps_all, lam_all = sched.steps(dtype=F64)
    Sig = (V @ V.T).expand(1, 4, 16, 16)
    a = aux
    I = torch.eye(16, dtype=F64)
    for eps, lam in zip(eps_all, lam_all):
        co = GromovFlow().coefficients(model, z, a, prior, lam, eps)
        A = co.dense_A()
        T = I + eps * A
        Sig = T @ Sig @ T.transpose(-1, -2) + eps * co.diffusion_cov()
        a = a + eps * (A @ a.unsqueeze(-1)).squeeze(-1) + eps * co.b
    torch.testing.assert_close(out.proposal_cov, linalg.symmetrize(Sig), rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(out.aux, a, rtol=1e-10, atol=1e-10)


def test_edh_flow_global_path_with_support():
    model, z, aux, P = _acoustic_points(B=2, N=1)
    mean = aux[:, 0]
    prior = FlowPrior(mean, linalg.safe_cholesky(P[:, 0]))
    x = mean.unsqueeze(1) + torch.randn(2, 7, 16, dtype=F64, generator=torch.Generator().manual_seed(1))
    a = integrate_flow(EDHFlow(), model, x, z, prior)
    b = integrate_flow(EDHFlow(), FullSupportAcoustic(), x, z, prior)
    torch.testing.assert_close(a.particles, b.particles, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(a.log_det, b.log_det, rtol=1e-9, atol=1e-9)


# ---- noise, structure and memory --------------------------------------------------------------------
def test_standard_normal_fast_path_is_reproducible_and_normal():
    from torchflow.core.linalg import FAST_NORMAL_MIN, standard_normal

    n = 4 * FAST_NORMAL_MIN
    a = standard_normal((n,), dtype=F64, device="cpu", generator=torch.Generator().manual_seed(7))
    b = standard_normal((n,), dtype=F64, device="cpu", generator=torch.Generator().manual_seed(7))
    c = standard_normal((n,), dtype=F64, device="cpu", generator=torch.Generator().manual_seed(8))
    assert torch.equal(a, b) and not torch.equal(a, c)
    # moments within 5 Monte Carlo standard errors: mean (1/sqrt n), variance (sqrt(2/n)), kurtosis
    se = n**-0.5
    assert abs(float(a.mean())) < 5 * se
    assert abs(float(a.var()) - 1) < 5 * (2**0.5) * se
    assert abs(float((a**4).mean()) - 3) < 5 * (96**0.5) * se
    # the generator advances: two draws from one generator differ
    g = torch.Generator().manual_seed(7)
    first = standard_normal((n,), dtype=F64, device="cpu", generator=g)
    assert not torch.equal(first, standard_normal((n,), dtype=F64, device="cpu", generator=g))
    # above FAST_NORMAL_BLOCK: independent streams per block, the same numbers for any thread count
    from torchflow.core.linalg import FAST_NORMAL_BLOCK

    big = (2 * FAST_NORMAL_BLOCK + 5,)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        x2 = standard_normal(big, dtype=F64, device="cpu", generator=torch.Generator().manual_seed(9))
        torch.set_num_threads(1)
        x1 = standard_normal(big, dtype=F64, device="cpu", generator=torch.Generator().manual_seed(9))
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(x1, x2)
    blocks = x1[: 2 * FAST_NORMAL_BLOCK].reshape(2, -1)
    assert not torch.equal(blocks[0], blocks[1])
    assert abs(float(torch.corrcoef(blocks)[0, 1])) < 5 * FAST_NORMAL_BLOCK**-0.5
    # small or float32 draws are torch.randn's
    small = standard_normal((5, 3), dtype=F64, device="cpu", generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(small, torch.randn(5, 3, dtype=F64, generator=torch.Generator().manual_seed(1)))


def test_sensor_network_scaled_identity_paths_equal_general_paths():
    from torchflow.models import SensorNetwork

    fast, general = SensorNetwork(d=16), SensorNetwork(d=16, learnable=True)  # parameters: general path
    g = torch.Generator().manual_seed(0)
    x = torch.randn(3, 1000, 16, dtype=F64, generator=g)
    z = torch.randn(3, 1, 16, dtype=F64, generator=g)
    torch.testing.assert_close(fast.measurement_log_prob(z, x), general.measurement_log_prob(z, x).detach())
    ref = linalg.mvn_log_prob(z, x, linalg.safe_cholesky(fast.R))
    torch.testing.assert_close(fast.measurement_log_prob(z, x), ref)
    a = fast.sample_transition(x, torch.Generator().manual_seed(4))
    b = general.sample_transition(x, torch.Generator().manual_seed(4)).detach()
    torch.testing.assert_close(a, b)


def test_particle_chunking_gives_the_same_filter_output():
    """Blocks of particles (likelihoods; local flows) change only round-off for deterministic
    flows and the bootstrap PF."""
    from torchflow.filters import BootstrapParticleFilter

    model = AcousticTracking()
    traj = model.simulate(2, 3, torch.Generator().manual_seed(1))
    mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator().manual_seed(2))
    for make in (
        lambda c: BootstrapParticleFilter(model, n_particles=300, particle_chunk=c),
        lambda c: ParticleFlowParticleFilter(model, flow="ledh", n_particles=60, particle_chunk=c),
        lambda c: ParticleFlowParticleFilter(model, flow="edh", n_particles=60, particle_chunk=c),
    ):
        with torch.no_grad():
            whole = make(None)(traj.observations, mean, cov, torch.Generator().manual_seed(5))
            parts = make(23)(traj.observations, mean, cov, torch.Generator().manual_seed(5))
        torch.testing.assert_close(parts.estimates, whole.estimates, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(parts.log_evidence, whole.log_evidence, rtol=1e-9, atol=1e-9)
    with pytest.raises(ValueError, match="particle_chunk"):
        BootstrapParticleFilter(model, particle_chunk=0)


def test_plan_memory_and_runner_chunk_particles_under_a_small_budget():
    from torchflow.app.runner import run_experiment
    from torchflow.filters import BootstrapParticleFilter

    model = AcousticTracking()
    f = BootstrapParticleFilter(model, n_particles=2000)
    per_trial = f.bytes_per_trial()
    assert f.plan_memory(10 * per_trial) is None
    c = f.plan_memory(per_trial / 4)
    assert c is not None and 400 <= c <= 500
    res = run_experiment(
        model,
        {"bpf": BootstrapParticleFilter(model, n_particles=2000)},
        trials=2,
        steps=2,
        memory_budget_gb=per_trial / 4 / 2**30,
        progress=False,
    )
    assert res.config["chunk_size"]["bpf"] == 1 and 400 <= res.config["particle_chunk"]["bpf"] <= 500


def test_float32_daum_huang_drift_is_promoted_where_float32_cancels():
    """sigma_w = 0.001: the EDH/LEDH offset b cancels terms ~lam |S| ~ 1e11 times larger than itself.
    With the float64 promotion a float32 run's drift matches float64's; without it, it is off by far
    more than the cloud's width (bench_float32: PF-PF(LEDH) lost every track)."""
    model = AcousticTracking(sigma_w=0.001)
    traj = model.simulate(1, 2, torch.Generator().manual_seed(0))
    z = traj.observations[:, 1]
    g = torch.Generator().manual_seed(1)
    aux = traj.states[:, 1].unsqueeze(1) + 0.3 * torch.randn(1, 20, 16, dtype=F64, generator=g)
    P = torch.diag(torch.tensor([2.0, 2.0, 0.1, 0.1] * 4, dtype=F64)).expand(1, 20, 16, 16)
    lam, eps = torch.tensor(0.6, dtype=F64), torch.tensor(0.05, dtype=F64)
    ref = LEDHFlow().coefficients(model, z, aux, FlowPrior(aux, linalg.safe_cholesky(P)), lam, eps)
    m32 = AcousticTracking(sigma_w=0.001).to(torch.float32)
    prior32 = FlowPrior(aux.float(), linalg.safe_cholesky(P.float()))
    step64 = eps * (ref.drift(aux)[0])
    flow = LEDHFlow()
    co = flow.coefficients(m32, z.float(), aux.float(), prior32, lam.float(), eps.float())
    assert co.b.dtype == torch.float32
    err = (eps.float() * co.drift(aux.float())[0]).double() - step64
    assert float(err.abs().max()) < 1e-3  # metres, one pseudo-time step
    flow.promote_low_precision = False
    co = flow.coefficients(m32, z.float(), aux.float(), prior32, lam.float(), eps.float())
    bad = (eps.float() * co.drift(aux.float())[0]).double() - step64
    assert float(bad.abs().max()) > 100 * float(err.abs().max())  # the failure the promotion prevents


@pytest.mark.parametrize("case", ["full", "support", "shared_W", "float32"])
def test_daum_huang_operator_form_equals_the_formed_matrix(case):
    """The operator form of the EDH/LEDH A (never formed; large k) gives the explicit form's b and
    log|det| to round-off, applies A to vectors as the matrix does, and forms the same matrix on
    demand (for the Gaussian image and clustered particles)."""
    g = torch.Generator().manual_seed(4)
    B, N, d, m = 2, 3, 6, 5
    k = 4 if case == "support" else d
    dt = torch.float32 if case == "float32" else F64
    W = (
        torch.randn(m, k, dtype=F64, generator=g)
        if case == "shared_W"
        else torch.randn(B, N, m, k, dtype=F64, generator=g)
    )
    y = torch.randn(B, N, m, dtype=F64, generator=g)
    X = torch.randn(B, N, d, d, dtype=F64, generator=g)
    Lfull = linalg.safe_cholesky(X @ X.transpose(-1, -2) + torch.eye(d, dtype=F64))
    support = torch.tensor([0, 2, 3, 5]) if case == "support" else None
    L = Lfull if support is None else Lfull[..., :k]  # a root whose first k columns carry the support rows
    Ls = None if support is None else L.index_select(-2, support)
    eta = torch.randn(B, N, d, dtype=F64, generator=g)
    lam, eps = torch.tensor(0.4, dtype=F64), torch.tensor(0.05, dtype=F64)
    kw = dict(L_support=Ls, support=support)
    ex = daum_huang_coefficients(W, y, L, eta, lam, eps, operator=False, **kw)
    op = daum_huang_coefficients(W, y, L, eta, lam, eps, operator=True, **kw)
    assert op.A is None and ex.A is not None
    torch.testing.assert_close(op.b, ex.b, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(op.log_det, ex.log_det, rtol=1e-10, atol=1e-12)
    x = torch.randn(B, N, d, dtype=F64, generator=g)
    for a, b in zip(op.drift(x, eta), ex.drift(x, eta)):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(op.dense_A(), ex.dense_A(), rtol=1e-10, atol=1e-12)  # formed on demand
    assert op.A is not None  # and kept
    if case == "float32":  # the flow's low-precision path: operator applied in float64, run's dtype out
        from torchflow.flows.measurement import Linearisation

        prior = FlowPrior(eta.to(dt), L.to(dt)).reduced(None)
        with tuning.tuned(flow_operator_min_dim=0):
            co = EDHFlow().coefficients_at(Linearisation(W.to(dt), y.to(dt)), prior, lam.to(dt), eps.to(dt))
        assert co.A is None and co.b.dtype == dt
        torch.testing.assert_close(co.drift(x.to(dt))[0].double(), ex.drift(x)[0], rtol=1e-4, atol=1e-4)
        assert co.dense_A().dtype == dt


def test_operator_form_is_chosen_by_size_and_cannot_be_gathered_without_form():
    g = torch.Generator().manual_seed(5)
    for k, expect_operator in ((31, False), (32, True)):
        W = torch.randn(1, 2, k, k, dtype=F64, generator=g)
        L = torch.eye(k, dtype=F64).expand(1, 2, k, k)
        co = daum_huang_coefficients(
            W,
            torch.zeros(1, 2, k, dtype=F64),
            L,
            torch.zeros(1, 2, k, dtype=F64),
            torch.tensor(0.5, dtype=F64),
            torch.tensor(0.1, dtype=F64),
        )
        assert (co.A is None) == expect_operator  # tuning.flow_operator_min_dim = 32
    from torchflow.flows import FlowCoefficients

    bare = FlowCoefficients(None, torch.zeros(1, 2, 3), None, apply_A=lambda V: V)
    with pytest.raises(TypeError, match="only as an operator"):
        bare.matrix()
    with pytest.raises(NotImplementedError, match="cannot be gathered"):
        bare.gather(torch.zeros(1, 2, dtype=torch.long))


@pytest.mark.parametrize("points", ["particle", "global", "clustered"])
def test_integrated_flow_and_gaussian_image_equal_with_operator_form(points):
    """integrate_flow with A as an operator (forced) equals the formed-A path: particles, log|det| and
    the Gaussian image, for per-particle, global (composed maps) and clustered (gathered) points."""
    model, z, aux, P = _acoustic_points(B=2, N=6)
    full = FullSupportAcoustic()  # k = 16: the d x d path
    L = linalg.safe_cholesky(P)
    x = aux + 0.1
    if points == "particle":
        prior, kw = FlowPrior(aux, L), {}
    elif points == "global":
        prior, kw = FlowPrior(aux[:, 0], L[:, 0]), {}
    else:
        prior, kw = FlowPrior(aux[:, :2], L[:, :2]), {"index": torch.tensor([[0, 1, 0, 1, 0, 1]] * 2)}
    outs = []
    for k_min in (0, 10**6):
        with tuning.tuned(flow_operator_min_dim=k_min):
            outs.append(integrate_flow(LEDHFlow(), full, x, z, prior, points=points, gaussian_image=True, **kw))
    op, ex = outs
    for a, b in ((op.particles, ex.particles), (op.log_det, ex.log_det), (op.image_mean, ex.image_mean)):
        torch.testing.assert_close(a, b, rtol=1e-7, atol=1e-7 * float(b.abs().max()))
    torch.testing.assert_close(op.image_cov, ex.image_cov, rtol=1e-6, atol=1e-6 * float(ex.image_cov.abs().max()))


def test_flattened_batch_products_give_torch_matmul_bits():
    """``linalg.matmul`` / ``matvec`` take one ``bmm`` over the flattened batch when the operands'
    batches agree: the same bits as ``torch.matmul``, for contiguous and transposed operands, and the
    broadcasting cases fall back to it."""
    g = torch.Generator().manual_seed(0)
    A = torch.randn(3, 5, 16, 8, generator=g, dtype=torch.float64)
    B = torch.randn(3, 5, 8, 7, generator=g, dtype=torch.float64)
    x = torch.randn(3, 5, 8, generator=g, dtype=torch.float64)
    Bt = torch.randn(3, 5, 7, 8, generator=g, dtype=torch.float64).transpose(-1, -2)  # a transposed view
    for a, b in ((A, B), (A, Bt), (A.transpose(-1, -2).contiguous().transpose(-1, -2), B)):
        assert torch.equal(linalg.matmul(a, b), a @ b)
    assert torch.equal(linalg.matvec(A, x), (A @ x.unsqueeze(-1)).squeeze(-1))
    shared = A[:, :1]  # (3, 1, 16, 8) against (3, 5, 8, 7): broadcast, the plain matmul
    assert torch.equal(linalg.matmul(shared, B), shared @ B)
    assert linalg.matmul(A, B).shape == (3, 5, 16, 7) and linalg.matvec(A, x).shape == (3, 5, 16)
