"""Gradients through resampling: the Kalman filter's autograd gradient is the truth.

The estimator checked is the gradient of ``Z_hat / Z`` (``Z`` the Kalman evidence of the same data,
a constant): with ``resampling_gradient="stop_gradient"`` the particle filter's ``Z_hat`` is unbiased
and so is its gradient (pathwise terms through the draws plus the score-function term of every
ancestor draw), hence ``E[grad Z_hat] / Z = grad log Z`` exactly. (The gradient of ``log Z_hat``
itself is only consistent: a ratio, biased by O(1/N); measured with PF-PF(EDH), N = 200 -> 1000,
the largest entry's bias fell from 0.33 to 0.10.)

Tolerance: R = 20 repetitions of a B = 40-trial mean; each of the k non-zero entries (F and the raw
Cholesky parameters of Q and R; the raw upper triangles have gradient 0 and are left out: k = 10, 21,
36 at d = 2, 3, 4) is compared in units of its standard error over the repetitions (t with 19 degrees
of freedom). The bound is the two-sided Bonferroni quantile at a 1% family-wise level,
t_19(1 - 0.005 / k) (scipy.stats.t.ppf): 3.88, 4.21, 4.45. A correct estimator fails it by chance
with probability <= 1%; a bias of 4-5 standard errors fails it.
"""

import math

import pytest
import torch

from experiments.benchmarks.bench_gradients import problem
from torchflow.filters import BootstrapParticleFilter, KalmanFilter, ParticleFlowParticleFilter
from torchflow.flows.schedules import ExponentialSchedule

REPS, B, T = 20, 40, 20
T_CRIT = {10: 3.88, 21: 4.21, 36: 4.45}  # t_19(1 - 0.005 / k), k non-zero entries (docstring)


def _setup(d: int = 2):
    model, obs, mean, cov = problem(T, d)  # the gradient benchmark's model: F, Q, R learnable
    return model, obs.expand(B, -1, -1).contiguous(), mean.expand(B, -1), cov.expand(B, -1, -1)


def _params(model):
    """F and the unconstrained Q and R (their Cholesky parametrisation): what an optimiser moves."""
    return list(model.parameters())


def _grads(filt, model, obs, mean, cov):
    """Kalman gradient of log Z, and REPS repetitions of the mean over B trials of grad Z_hat / Z."""
    log_z = KalmanFilter(model)(obs[:1], mean[:1], cov[:1]).log_evidence.sum()
    exact = torch.cat([g.flatten() for g in torch.autograd.grad(log_z, _params(model))])
    reps = []
    for r in range(REPS):
        le = filt(obs, mean, cov, torch.Generator().manual_seed(100 + r)).log_evidence
        gr = torch.autograd.grad(torch.exp(le - log_z.detach()).mean(), _params(model))
        reps.append(torch.cat([g.flatten() for g in gr]))
    G = torch.stack(reps)
    keep = exact != 0  # the raw upper triangles of Q and R: no gradient in either
    assert bool((G[:, ~keep] == 0).all())
    return exact[keep], G.mean(0)[keep], G.std(0)[keep] / math.sqrt(REPS)


@pytest.mark.parametrize(
    "kind,d",
    [
        ("bpf", 2),
        ("pfpf_edh", 2),
        pytest.param("pfpf_ledh", 2, marks=pytest.mark.slow),  # 28 s; pfpf_edh and the score form stay
        ("bpf_score", 2),
        ("pfpf_ledh_score", 2),
        ("bpf", 4),
        pytest.param("pfpf_edh", 4, marks=pytest.mark.slow),  # 12 s
        pytest.param("pfpf_ledh_score", 3, marks=pytest.mark.slow),  # 13 s
    ],
)
def test_stop_gradient_matches_the_kalman_gradient(kind, d):
    """F, Q and R, d = 2..4. Also with ``proposal_gradient="score"`` (the proposal held constant):
    unbiased too."""
    model, obs, mean, cov = _setup(d)
    pg = "score" if kind.endswith("_score") else "pathwise"
    flow = kind.split("_")[1] if kind.startswith("pfpf") else None
    filt = (
        BootstrapParticleFilter(model, n_particles=1000, resampling_gradient="stop_gradient", proposal_gradient=pg)
        if flow is None
        else ParticleFlowParticleFilter(
            model,
            flow=flow,
            n_particles=200,
            resampling_gradient="stop_gradient",
            proposal_gradient=pg,
            schedule=ExponentialSchedule(10, 1.2),
        )
    )  # any schedule
    exact, est, se = _grads(filt, model, obs, mean, cov)
    assert exact.numel() == d * d + d * (d + 1)
    t = (est - exact) / se
    assert float(t.abs().max()) < T_CRIT[exact.numel()], (exact, est, se)


def test_none_misses_the_kalman_gradient():
    """The test above can fail: without the ancestors' score term the bootstrap PF's gradient is
    many standard errors off (this model resamples at most steps)."""
    model, obs, mean, cov = _setup()
    filt = BootstrapParticleFilter(model, n_particles=1000, resampling_gradient="none")
    exact, est, se = _grads(filt, model, obs, mean, cov)
    assert float(((est - exact) / se).abs().max()) > 10


@pytest.mark.parametrize("kind", ["bpf", "pfpf_ledh"])
def test_stop_gradient_forward_is_bit_identical(kind):
    """The estimators change gradients, not forward values. On one arithmetic: the fused flow
    kernels (``tuning.fused_flows``) run only where no gradient is recorded (the score estimator's
    proposal) and agree with the torch path to round-off, not bit for bit, so the torch path is
    pinned here."""
    from torchflow.core import tuning

    model, obs, mean, cov = _setup()
    outs = []
    for est, pg in (("none", "pathwise"), ("stop_gradient", "pathwise"), ("stop_gradient", "score")):
        f = (
            BootstrapParticleFilter(model, n_particles=64, resampling_gradient=est, proposal_gradient=pg)
            if kind == "bpf"
            else ParticleFlowParticleFilter(model, n_particles=64, resampling_gradient=est, proposal_gradient=pg)
        )
        with tuning.tuned(fused_flows=0):
            outs.append(f(obs[:4], mean[:4], cov[:4], torch.Generator().manual_seed(5)))
    for other in outs[1:]:
        assert torch.equal(outs[0].estimates, other.estimates)
        assert torch.equal(outs[0].log_evidence, other.log_evidence)
        assert torch.equal(outs[0].ess, other.ess)


def test_unknown_estimator_is_refused():
    model, *_ = _setup()
    with pytest.raises(ValueError, match="resampling_gradient"):
        BootstrapParticleFilter(model, resampling_gradient="bogus")


def test_soft_resampling_keeps_the_evidence_unbiased():
    """Soft resampling draws from q = a W + (1 - a)/N and weighs W_a / q_a: a valid resampling
    scheme, so E[Z_hat / Z] = 1 (within 4 standard errors over 400 runs). Its gradient is biased
    (no term for the draw): measured here at N = 1000, a = 0.5, tens of standard errors off, like
    "none" (reported, not asserted)."""
    model, obs, mean, cov = _setup()
    obs, mean, cov = (t[:1].expand(400, *t.shape[1:]) for t in (obs, mean, cov))
    log_z = KalmanFilter(model)(obs[:1], mean[:1], cov[:1]).log_evidence.detach()
    filt = BootstrapParticleFilter(model, n_particles=100, resampling_gradient="soft", ess_threshold=1.0)
    with torch.no_grad():
        out = filt(obs, mean, cov, torch.Generator().manual_seed(3))
    r = torch.exp(out.log_evidence - log_z)
    se = r.std() / math.sqrt(r.numel())
    assert abs(float(r.mean()) - 1) < 4 * float(se) and float(se) < 0.05, (float(r.mean()), float(se))
    # after a soft resampling the weights are not uniform (the forward pass differs from "none")
    state = filt.init(mean[:2], cov[:2], generator=torch.Generator().manual_seed(0))
    state = filt.step(state, obs[:2, 0], torch.Generator().manual_seed(1))
    assert bool(state.resampled.all()) and float(state.log_weights.detach().std()) > 0


@pytest.mark.parametrize("alpha", [0.0, 1.5, True])
def test_soft_alpha_is_checked(alpha):
    model, *_ = _setup()
    with pytest.raises(ValueError, match="soft_alpha"):
        BootstrapParticleFilter(model, resampling_gradient="soft", soft_alpha=alpha)


def test_sinkhorn_transport_marginals_and_mean():
    """Columns of the plan sum to one (each new particle a convex combination), rows to N W within
    the Sinkhorn tolerance, so the transported cloud keeps the weighted mean."""
    from torchflow.core.resampling import sinkhorn_transport

    g = torch.Generator().manual_seed(0)
    x = torch.randn(3, 200, 2, dtype=torch.float64, generator=g)
    lw = torch.log_softmax(-1.5 * ((x - 1) ** 2).sum(-1), -1)
    T = sinkhorn_transport(x, lw, epsilon=0.1, iterations=100)
    assert (T >= 0).all()
    torch.testing.assert_close(T.sum(1), torch.ones(3, 200, dtype=torch.float64), atol=1e-12, rtol=0)
    assert float((T.sum(2) / 200 - lw.exp()).abs().max()) < 2e-3
    new = torch.einsum("bij,bid->bjd", T, x)
    mean = torch.einsum("bn,bnd->bd", lw.exp(), x)
    assert float((new.mean(1) - mean).abs().max()) < 1e-2


@pytest.mark.parametrize("kind", ["bpf", "pfpf_ledh"])
def test_ot_resampling_is_differentiable_and_tracks(kind):
    """ "ot" moves resampled trials' particles by transport (per-particle covariances too): every
    trial resamples (ess_threshold = 1), the weights after it are uniform, the evidence stays close
    to the Kalman filter's (biased: measured here, not asserted beyond a loose bound) and every
    parameter gets a finite gradient."""
    model, obs, mean, cov = _setup()
    kw = dict(n_particles=100, resampling_gradient="ot", ess_threshold=1.0, ot_iterations=50)
    filt = (
        BootstrapParticleFilter(model, **kw) if kind == "bpf" else ParticleFlowParticleFilter(model, flow="ledh", **kw)
    )
    state = filt.init(mean[:2], cov[:2], generator=torch.Generator().manual_seed(0))
    state = filt.step(state, obs[:2, 0], torch.Generator().manual_seed(1))
    assert bool(state.resampled.all())
    torch.testing.assert_close(state.log_weights, torch.full_like(state.log_weights, -math.log(100)))
    out = filt(obs[:8], mean[:8], cov[:8], torch.Generator().manual_seed(2))
    log_z = KalmanFilter(model)(obs[:1], mean[:1], cov[:1]).log_evidence
    assert float((out.log_evidence - log_z).detach().abs().max()) < 5.0
    grads = torch.autograd.grad(out.log_evidence.mean(), _params(model))
    assert all(torch.isfinite(g).all() and g.abs().sum() > 0 for g in grads)


@pytest.mark.parametrize("bad", [{"ot_epsilon": 0.0}, {"ot_epsilon": True}, {"ot_iterations": 0}])
def test_ot_knobs_are_checked(bad):
    model, *_ = _setup()
    with pytest.raises(ValueError, match=next(iter(bad))):
        BootstrapParticleFilter(model, resampling_gradient="ot", **bad)


def test_every_particle_filter_takes_the_estimator():
    """One constructor argument on every particle filter (the Gaussian-sum family never resamples:
    accepted and validated, the gradient is pathwise whatever it says)."""
    from torchflow.filters import GPFIS, GaussianSumParticleFilter, ParticleFilter
    from torchflow.proposals import UnscentedProposal

    model, *_ = _setup()
    for est in ("stop_gradient", "soft", "ot"):
        for f in (
            GPFIS(model, resampling_gradient=est),
            GaussianSumParticleFilter(model, resampling_gradient=est),
            ParticleFilter(model, UnscentedProposal(model), resampling_gradient=est),
            ParticleFlowParticleFilter(model, flow="gromov", resampling_gradient=est),
        ):
            assert f.resampler.gradient == est
    with pytest.raises(ValueError, match="resampling_gradient"):
        GaussianSumParticleFilter(model, resampling_gradient="bogus")


def _every_particle_filter(model, **kw):
    """Every particle filter (named, with its flows), built with the constructor arguments ``kw``."""
    from torchflow.filters import (
        GPFIS,
        ClusteredParticleFlowParticleFilter,
        GaussianParticleFilter,
        GaussianSumParticleFilter,
        ParticleFilter,
        ParticleFlowGaussianSumParticleFilter,
    )
    from torchflow.proposals import UnscentedProposal

    yield "bpf", BootstrapParticleFilter(model, n_particles=30, **kw)
    for flow in ("edh", "ledh", "geodesic", "gromov", "osd"):
        yield (
            f"pfpf_{flow}",
            ParticleFlowParticleFilter(model, flow=flow, n_particles=30, schedule=ExponentialSchedule(4, 1.2), **kw),
        )
    yield (
        "pfpf_clustered",
        ClusteredParticleFlowParticleFilter(model, n_particles=30, schedule=ExponentialSchedule(4, 1.2), **kw),
    )
    yield "gpfis", GPFIS(model, n_particles=30, schedule=ExponentialSchedule(4, 1.2), **kw)
    yield "upf", ParticleFilter(model, UnscentedProposal(model), n_particles=30, **kw)
    yield "gpf", GaussianParticleFilter(model, n_particles=30, **kw)
    yield "gspf", GaussianSumParticleFilter(model, n_components=2, particles_per_component=15, **kw)
    yield (
        "pfgspf",
        ParticleFlowGaussianSumParticleFilter(
            model, n_components=2, particles_per_component=15, schedule=ExponentialSchedule(4, 1.2), **kw
        ),
    )


def test_every_particle_filter_passes_a_gradient_to_every_parameter():
    """Every particle filter, every flow (pathwise): F, Q and R all receive a finite, non-zero
    gradient of the log-evidence (flow maps, log|det|, stochastic-flow laws, EKF/UKF covariance
    tracking: no path cut)."""
    model, obs, mean, cov = _setup()
    o, m, c = obs[:3, :4], mean[:3], cov[:3]
    params = dict(model.named_parameters())
    assert len(params) == 3  # F and the raw Q and R
    seen = []
    for name, f in _every_particle_filter(model, resampling_gradient="stop_gradient"):
        seen.append(name)
        le = f(o, m, c, torch.Generator().manual_seed(0)).log_evidence.sum()
        grads = torch.autograd.grad(le, list(params.values()), allow_unused=True)
        for (pname, p), g in zip(params.items(), grads):
            assert g is not None and bool(torch.isfinite(g).all()), (name, pname, g)
            assert float(g.abs().sum()) > 0, (name, pname)
    assert len(seen) == 12


def test_stop_gradient_is_every_particle_filter_s_default_and_its_forward_pass_is_that_of_none():
    """The default estimator is ``stop_gradient``; with autograd on (so that its score term is
    built) the estimates, ESS and log-evidence are bit for bit those of an explicit ``"none"``, for
    every particle filter; in each filter that resamples, some trial resampled (else the
    comparison would not reach the estimator); the bootstrap PF's gradients differ."""
    model, obs, mean, cov = _setup()
    o, m, c = obs[:3, :4], mean[:3], cov[:3]
    for (name, default), (_, none) in zip(
        _every_particle_filter(model), _every_particle_filter(model, resampling_gradient="none")
    ):
        assert default.resampler.gradient == "stop_gradient" and none.resampler.gradient == "none", name
        a = default(o, m, c, torch.Generator().manual_seed(3))
        b = none(o, m, c, torch.Generator().manual_seed(3))
        assert a.log_evidence.requires_grad, name  # autograd on: the score term was built
        for key in ("estimates", "log_evidence", "log_evidence_increments", "ess"):
            x, y = getattr(a, key), getattr(b, key)
            assert (x is None and y is None) or torch.equal(x, y), (name, key)
        if name not in ("gpf", "gspf", "pfgspf"):  # the Gaussian(-sum) PFs redraw, never resample
            assert bool((a.ess < 0.5 * default.n_particles).any()), name
        if name == "bpf":  # only the gradient changes: the ancestors' score terms
            ga, gb = (torch.autograd.grad(r.log_evidence.sum(), model.F)[0] for r in (a, b))
            assert not torch.equal(ga, gb)


@pytest.mark.slow
def test_marginal_score_gradient_matches_the_kalman_gradient_at_n_1000():
    """The marginal weights' score estimator (``weights="marginal"``, ``proposal_gradient="score"``,
    ``stop_gradient``: Poyiadjis, Doucet & Singh's O(N^2) recursion) of ``grad_F log Z`` at
    N = 1000 on the d = 2, T = 20 model: 12 repetitions of an 8-run mean, each entry within the
    Bonferroni bound t_11(1 - 0.005 / 4) = 3.9 of the Kalman gradient. Its per-run spread is
    about 0.1 (measured), some 60-100 times below ``stop_gradient``'s on the same model, so
    96 runs resolve an O(1/N) bias of about 0.03; the bias measured was about 0.02 on the
    largest entry (0.5 % of it)."""
    model, obs, mean, cov = problem(T, 2)
    B8, reps = 8, 12
    obs8, mean8, cov8 = obs.expand(B8, -1, -1).contiguous(), mean.expand(B8, -1), cov.expand(B8, -1, -1)
    log_z = KalmanFilter(model)(obs, mean, cov).log_evidence.sum()
    exact = torch.autograd.grad(log_z, [model.F])[0].flatten()
    filt = BootstrapParticleFilter(model, n_particles=1000, weights="marginal", proposal_gradient="score")
    G = torch.stack(
        [
            torch.autograd.grad(
                filt(obs8, mean8, cov8, torch.Generator().manual_seed(100 + r)).log_evidence.mean(), [model.F]
            )[0].flatten()
            for r in range(reps)
        ]
    )
    est, se = G.mean(0), G.std(0) / math.sqrt(reps)
    t = (est - exact) / se
    assert float(t.abs().max()) < 3.9, (exact, est, se)
    assert float((G.std(0) * math.sqrt(B8)).max()) < 0.5  # the per-run spread stays that small


def test_the_lag_one_flow_s_log_evidence_has_the_finite_difference_gradient():
    """Q72: with more members than state coordinates (N = 20, d = 4) the flow's regression went
    through an N x N eigendecomposition whose N - d repeated zero eigenvalues (and a masked
    reciprocal) made the gradient NaN, so learning through lag1_flow always failed. The d x d
    Cholesky form used there now gives the central finite difference's gradient (same streams)."""
    from torchflow.filters import LagOneFlowFilter
    from torchflow.models import SensorNetwork

    model = SensorNetwork(d=4, learnable=["R"])
    with torch.no_grad():
        traj = model.simulate(2, 5, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator().manual_seed(1))

    def log_evidence():
        res = LagOneFlowFilter(model, n_particles=20)(traj.observations, mean, cov, torch.Generator().manual_seed(2))
        return res.log_evidence.sum()

    log_evidence().backward()
    p = next(model.parameters())
    grad, eps = p.grad.clone(), 1e-6
    assert torch.isfinite(grad).all() and float(grad.abs().max()) > 1.0
    with torch.no_grad():
        p.view(-1)[0] += eps
        up = float(log_evidence())
        p.view(-1)[0] -= 2 * eps
        down = float(log_evidence())
        p.view(-1)[0] += eps
    assert abs(float(grad.view(-1)[0]) - (up - down) / (2 * eps)) < 1e-5 * abs(float(grad.view(-1)[0])), (
        grad,
        up,
        down,
    )
