"""Marginal particle weights (``weights="marginal"``, :mod:`torchflow.filters.marginal`)."""

import math

import pytest
import torch
from conftest import cuda, mild_lg, random_lg

from torchflow.core import linalg
from torchflow.core.errors import ArgumentError
from torchflow.filters import GPFIS, BootstrapParticleFilter, KalmanFilter, ParticleFlowParticleFilter, marginal

F64 = torch.float64
FLOWS = [("edh", "global"), ("ledh", "particle"), ("ledh", "clustered"), ("gromov", "particle")]


def _flow_filter(model, flow, points, **kw):
    return ParticleFlowParticleFilter(model, flow=flow, points=points, n_clusters=7, **kw)


def _problem(model, B, T, seed=0):
    traj = model.simulate(1, T, torch.Generator().manual_seed(seed))
    mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator().manual_seed(seed + 1))
    return (
        traj.observations.expand(B, -1, -1).contiguous(),
        mean.expand(B, -1).contiguous(),
        cov.expand(B, -1, -1).contiguous(),
    )


@pytest.mark.parametrize("flow,points", FLOWS)
def test_ancestor_law_is_the_proposal_density_given_the_own_parent(flow, points):
    """The Gaussian law a flow reports for each parent, evaluated at the particle it proposed from
    its own parent, is the proposal density the standard weight uses (``log p(eta_0 | x') -
    log|det|``, or the stochastic flow's tracked density): 1e-9."""
    model = random_lg(d=3, m=2, seed=2)
    f = _flow_filter(model, flow, points, n_particles=40, weights="marginal")
    obs, mean, cov = _problem(model, 3, 2)
    g = torch.Generator().manual_seed(5)
    state = f.init(mean, cov, generator=g)
    state = f.step(state, obs[:, 0], g)  # a resampled, non-uniform cloud to start from
    with torch.no_grad():
        prop = f.proposal.propose(state.particles, state.log_weights, state.estimate, obs[:, 1], state.cov, g)
    law_mean, law_tril = prop.ancestor_law
    own = linalg.mvn_log_prob(prop.particles, law_mean, law_tril.expand(*prop.particles.shape, 3))
    torch.testing.assert_close(own, prop.log_q, atol=1e-9, rtol=1e-9)


def test_pairs_match_the_direct_densities():
    """Both pair evaluators (one factor per trial; one per component) and the generic transition
    path equal ``mvn_log_prob`` pair by pair, and blocks of rows do not change the mixture."""
    g = torch.Generator().manual_seed(0)
    B, N, J, d = 2, 7, 5, 3
    x, mu = torch.randn(B, N, d, generator=g, dtype=F64), torch.randn(B, J, d, generator=g, dtype=F64)
    A = torch.randn(B, J, d, d, generator=g, dtype=F64)
    L = torch.linalg.cholesky(A @ A.transpose(-1, -2) + 0.5 * torch.eye(d, dtype=F64))
    for factor in (L[:, 0], L):
        pairs = marginal.gaussian_pairs(x, mu, factor)
        full = factor.unsqueeze(1) if factor.dim() == 3 else factor
        direct = linalg.mvn_log_prob(x.unsqueeze(2), mu.unsqueeze(1), full.unsqueeze(1))
        torch.testing.assert_close(pairs.block(slice(0, N)), direct, atol=1e-10, rtol=1e-10)
        lw = torch.log_softmax(torch.randn(B, J, generator=g, dtype=F64), -1)
        (whole,) = marginal.mixture_logsumexp(pairs, [lw], N, N)
        (rows2,) = marginal.mixture_logsumexp(pairs, [lw], N, 2)
        torch.testing.assert_close(whole, torch.logsumexp(direct + lw.unsqueeze(1), -1), atol=1e-10, rtol=1e-10)
        torch.testing.assert_close(rows2, whole, atol=1e-12, rtol=1e-12)


def test_bootstrap_marginal_weights_equal_the_standard_ones_after_resampling():
    """With every step resampled the previous weights are uniform, the transition mixture cancels
    the proposal mixture, and the bootstrap PF's marginal weights are its standard ones: the same
    evidence and estimates (round-off)."""
    model = random_lg(d=2, m=2, seed=1)
    obs, mean, cov = _problem(model, 4, 6)
    out = [
        BootstrapParticleFilter(model, n_particles=50, ess_threshold=1.0, weights=w)(
            obs, mean, cov, torch.Generator().manual_seed(3)
        )
        for w in ("standard", "marginal")
    ]
    torch.testing.assert_close(out[1].log_evidence, out[0].log_evidence, atol=1e-9, rtol=0)
    torch.testing.assert_close(out[1].estimates, out[0].estimates, atol=1e-9, rtol=0)


@pytest.mark.parametrize("kind", ["bpf", "bpf_no_resampling", "edh", "ledh", "gromov"])
def test_marginal_evidence_is_unbiased(kind):
    """``E[Z_hat / Z] = 1`` (``Z`` the Kalman evidence) over 200 independent runs of one series:
    |z| < 3.5 (five filters, Bonferroni at ~0.2 % each), and the runs' standard error below 0.1.
    ``bpf_no_resampling`` never resamples, so the previous weights W' are not uniform: a mixture
    that dropped them would be biased here (with resampling at every step it is not)."""
    model = mild_lg(d=2, m=2, seed=0)
    B, T = 200, 6
    obs, mean, cov = _problem(model, B, T, seed=4)
    log_z = KalmanFilter(model)(obs[:1], mean[:1], cov[:1]).log_evidence
    f = (
        BootstrapParticleFilter(
            model, n_particles=100, weights="marginal", ess_threshold=0.0 if kind == "bpf_no_resampling" else 0.5
        )
        if kind.startswith("bpf")
        else _flow_filter(model, kind, None, n_particles=50, weights="marginal")
    )
    with torch.no_grad():
        ratio = (f(obs, mean, cov, torch.Generator().manual_seed(11)).log_evidence - log_z).exp()
    se = ratio.std() / math.sqrt(B)
    assert float(se) < 0.1
    assert abs(float((ratio.mean() - 1) / se)) < 3.5, (float(ratio.mean()), float(se))


def test_marginal_flow_weights_keep_their_effective_sample_size_where_the_standard_ones_collapse():
    """Where the predictive covariance is much wider than Q (``random_lg``: P0 = 1.5 I), each
    standard PF-PF weight divides by its own parent's narrow transition, whose ESS/N falls as N
    grows (infinite-variance weights); the marginal weights divide by the mixture over parents and
    keep a high ESS. Measured: mean ESS/N over steps and trials."""
    model = random_lg(d=3, m=2, seed=0)
    obs, mean, cov = _problem(model, 8, 6, seed=2)
    ess = {}
    for w in ("standard", "marginal"):
        f = ParticleFlowParticleFilter(model, flow="edh", n_particles=400, weights=w)
        with torch.no_grad():
            ess[w] = float(f(obs, mean, cov, torch.Generator().manual_seed(0)).ess.mean()) / 400
    assert ess["marginal"] > 0.8 and ess["marginal"] > 2 * ess["standard"], ess


def test_errors():
    model = random_lg(d=2, m=2)
    with pytest.raises(ArgumentError, match="weights: expected one of"):
        BootstrapParticleFilter(model, weights="mixture")
    with pytest.raises(ArgumentError, match="weights: 'marginal' needs .*GPFISProposal"):
        GPFIS(model, weights="marginal")


def test_chunks_do_not_change_the_numbers():
    model = random_lg(d=2, m=2, seed=3)
    obs, mean, cov = _problem(model, 3, 4)
    out = [
        ParticleFlowParticleFilter(model, flow="ledh", n_particles=30, weights="marginal", particle_chunk=c)(
            obs, mean, cov, torch.Generator().manual_seed(1)
        ).log_evidence
        for c in (None, 7)
    ]
    torch.testing.assert_close(out[0], out[1], atol=1e-10, rtol=0)


@cuda
@pytest.mark.parametrize("flow,points", FLOWS)
def test_marginal_cuda(flow, points):
    """On CUDA, marginal weights run for the bootstrap PF and every weighted flow, and match the CPU
    where the draws are the same (the flows' CPU draws moved to the GPU are not: finite only)."""
    model = mild_lg(d=2, m=2).to("cuda")
    traj = model.simulate(3, 4, torch.Generator(device="cuda").manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator(device="cuda").manual_seed(1))
    for f in (
        BootstrapParticleFilter(model, n_particles=64, weights="marginal"),
        _flow_filter(model, flow, points, n_particles=64, weights="marginal"),
    ):
        res = f(traj.observations, mean, cov, torch.Generator(device="cuda").manual_seed(3))
        assert torch.isfinite(res.log_evidence).all() and bool((res.ess > 1).all())


def test_marginal_weights_refuse_deterministic_dynamics_up_front():
    """Case A08: on Lorenz-96 without model noise the marginal weights failed as a -inf evidence that
    blamed the measurement model; the transition covariance is now named before the first step."""
    from torchflow.core.errors import ArgumentError
    from torchflow.filters import BootstrapParticleFilter
    from torchflow.models import Lorenz96

    model = Lorenz96(d=8)
    traj = model.simulate(2, 3, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator().manual_seed(1))
    with pytest.raises(ArgumentError, match="transition covariance is not positive definite.*weights='marginal'"):
        BootstrapParticleFilter(model, n_particles=20, weights="marginal")(
            traj.observations, mean, cov, torch.Generator().manual_seed(0)
        )
    out = BootstrapParticleFilter(model, n_particles=20)(traj.observations, mean, cov, torch.Generator().manual_seed(0))
    assert torch.isfinite(out.estimates).all()  # the standard bootstrap weights need no transition density
