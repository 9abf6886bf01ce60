"""The GH skewed-t / Poisson model: exact density (integrates to 1, matches a
scipy-Bessel evaluation), exact sampling (mean and covariance of the Gaussian fit), Poisson
likelihood, and filters running on it."""

import math

import numpy as np
import pytest
import torch

from torchflow.core.random import TrialStreams
from torchflow.models import SkewedTPoisson

special = pytest.importorskip("scipy.special")
stats = pytest.importorskip("scipy.stats")


def _scipy_log_density(model, x_next, x):
    """The same formula with scipy's exponentially scaled Bessel function."""
    d, nu = model.state_dim, model.nu
    S = model.Sigma.numpy()
    g = model.gamma.numpy()
    r = x_next.numpy() - model.alpha.item() * x.numpy()
    Si = np.linalg.inv(S)
    q = np.einsum("...i,ij,...j->...", r, Si, r)
    gSg = g @ Si @ g
    zeta = np.sqrt((nu + q) * gSg)
    k = (nu + d) / 2
    logc = (
        (1 - k) * math.log(2) - special.gammaln(nu / 2) - d / 2 * math.log(math.pi * nu) - 0.5 * np.linalg.slogdet(S)[1]
    )
    return logc + np.log(special.kve(k, zeta)) - zeta + r @ (Si @ g) + k * (np.log(zeta) - np.log1p(q / nu))


@pytest.mark.parametrize("d", [1, 16, 144])
def test_density_matches_a_scipy_bessel_evaluation(d):
    model = SkewedTPoisson(d=d)
    g = torch.Generator().manual_seed(0)
    x = torch.randn(5, d, generator=g, dtype=torch.float64)
    x_next = model.sample_transition(x, g)
    ours = model.transition_log_prob(x_next, x)
    np.testing.assert_allclose(ours.numpy(), _scipy_log_density(model, x_next, x), rtol=1e-10, atol=1e-9)


def test_density_integrates_to_one_in_d1():
    model = SkewedTPoisson(d=1)
    x = torch.linspace(-60, 400, 46001, dtype=torch.float64).unsqueeze(-1)
    p = model.transition_log_prob(x, torch.tensor([[0.5]], dtype=torch.float64)).exp()
    total = float(torch.trapezoid(p, x[:, 0]))
    assert abs(total - 1) < 1e-6, total


def test_sampling_matches_the_gaussian_fit_moments():
    """Mean alpha x + E[W] gamma and covariance Q_st = E[W] Sigma + Var[W] gamma gamma^T (d = 4),
    within Monte Carlo error of 400,000 draws."""
    model = SkewedTPoisson(d=4)
    n = 400_000
    x = torch.full((n, 4), 0.7, dtype=torch.float64)
    draws = model.sample_transition(x, torch.Generator().manual_seed(3))
    mean = draws.mean(0)
    se = draws.std(0) / math.sqrt(n)
    assert ((mean - model.transition_mean(x[0])).abs() < 4 * se).all(), (mean, model.transition_mean(x[0]))
    cov = torch.cov(draws.T)
    # standard error of every covariance entry from the spread of the per-draw products (finite for
    # nu = 7 > 4); 5 SE over the 10 distinct entries
    c = draws - draws.mean(0)
    se_cov = (c.unsqueeze(-1) * c.unsqueeze(-2)).std(0) / math.sqrt(n)
    z = (cov - model.Q_st) / se_cov
    assert z.abs().max() < 5, z
    # the test can fail: without the Var[W] gamma gamma^T term every entry is > 5 SE off
    z_without = (cov - model.EW * model.Sigma) / se_cov
    assert z_without.abs().min() > 5, z_without


def test_poisson_likelihood_and_declared_noise():
    model = SkewedTPoisson(d=4)
    x = torch.tensor([[0.3, -1.0, 2.0, 0.0]], dtype=torch.float64)
    z = torch.tensor([[1.0, 0.0, 3.0, 2.0]], dtype=torch.float64)
    lam = torch.exp(x / 3)
    ref = stats.poisson.logpmf(z.numpy(), lam.numpy()).sum()
    assert abs(float(model.measurement_log_prob(z, x)) - ref) < 1e-12
    assert model.structure.measurement_noise == "state_dependent_diagonal"
    torch.testing.assert_close(model.measurement_cov(x), torch.diag_embed(lam))
    with pytest.raises(ValueError, match="R depends on the state"):
        model.measurement_cov()
    with pytest.raises(ValueError, match="d: expected a perfect square"):
        SkewedTPoisson(d=10)
    with pytest.raises(ValueError, match=r"nu: expected an integer > 4"):
        SkewedTPoisson(nu=3)


def test_filters_run_on_the_skewed_t_model():
    """BPF and PF-PF(LEDH) (Gaussian fit for sampling and the flow, exact density in the weight) on
    d = 16: finite, and the PF-PF beats the BPF's MSE at the same N."""
    from torchflow.filters import BootstrapParticleFilter, ParticleFlowParticleFilter

    model = SkewedTPoisson(d=16)
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(4, 5, g)
    mean, cov = model.initial_belief(traj.states[:, 0])
    mse = {}
    for name, f in (
        ("bpf", BootstrapParticleFilter(model, n_particles=100)),
        ("pfpf", ParticleFlowParticleFilter(model, flow="ledh", n_particles=100)),
    ):
        res = f(traj.observations, mean, cov, TrialStreams(0, 4, name))
        assert torch.isfinite(res.estimates).all() and torch.isfinite(res.log_evidence).all(), name
        mse[name] = float((res.estimates - traj.states[:, 1:]).pow(2).mean())
    assert mse["pfpf"] < mse["bpf"], mse


def test_declared_diagonal_noise_whitens_like_the_general_path():
    """``state_dependent_diagonal`` whitens by a division; it must equal the triangular solve of a
    general state-dependent R at the same points."""
    from torchflow.flows.measurement import GaussianMeasurement

    model = SkewedTPoisson(d=9)
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 5, 9, generator=g, dtype=torch.float64)
    z = torch.poisson(torch.ones(2, 9, dtype=torch.float64) * 2, generator=g)
    fast = GaussianMeasurement.from_model(model, z)
    assert fast.noise == "diagonal"
    slow = GaussianMeasurement(z, model.linearize_measurement, model.measurement_scale_tril, "dense")
    a, b = fast.at(x), slow.at(x)
    torch.testing.assert_close(a.W, b.W, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(a.y, b.y, rtol=1e-12, atol=1e-12)


def test_pfpf_evidence_on_the_skewed_t_model_matches_the_bootstrap_filter():
    """Stochastic flows track a Gaussian proposal law, so on a non-Gaussian transition their eta_0
    must come from the Gaussian fit while the weight keeps the exact skewed-t
    density. Drawing eta_0 from the skewed-t itself made PF-PF(Gromov)'s evidence wrong by a factor
    of ~1e9 here. The mean evidence (ratio to a common constant) of PF-PF(Gromov) and PF-PF(LEDH)
    agrees with a 2e4-particle BPF's within 4 combined standard errors."""
    import math

    from torchflow.core.random import TrialStreams
    from torchflow.filters import BootstrapParticleFilter, ParticleFlowParticleFilter

    model = SkewedTPoisson(d=4)
    traj = model.simulate(1, 3, torch.Generator().manual_seed(3))
    mean, cov = model.initial_belief(traj.states[:, 0])

    def evidence(f, B):
        obs, mu, P = traj.observations.expand(B, -1, -1), mean.expand(B, -1), cov.expand(B, -1, -1)
        return f(obs, mu, P, TrialStreams(0, range(B), f.stream_name)).log_evidence

    ref = evidence(BootstrapParticleFilter(model, n_particles=20000), 20)
    c = ref.max()
    z_ref = (ref - c).exp()
    for flow in ("gromov", "ledh"):
        z = (evidence(ParticleFlowParticleFilter(model, flow=flow, n_particles=200), 40) - c).exp()
        se = math.sqrt(float(z.var()) / 40 + float(z_ref.var()) / 20)
        assert abs(float(z.mean() - z_ref.mean())) < 4 * se, (flow, float(z.mean()), float(z_ref.mean()), se)
        assert se < 0.05  # small enough to see a wrong weight


def test_counts_must_be_non_negative_integers():
    from torchflow.filters import BootstrapParticleFilter

    model = SkewedTPoisson(d=4)
    f = BootstrapParticleFilter(model, n_particles=10)
    mean, cov = model.initial_belief(torch.zeros(1, 4, dtype=torch.float64))
    for bad, what in ((-1.0, "-1.0"), (2.5, "2.5")):
        z = torch.ones(1, 3, 4, dtype=torch.float64)
        z[0, 1, 2] = bad
        with pytest.raises(
            ValueError,
            match=rf"observations: expected Poisson counts .* got {what} at trial 0, "
            r"step 1, cell 2",
        ):
            f(z, mean, cov, torch.Generator().manual_seed(0))


def test_declared_diagonal_jacobian_gives_the_same_numbers():
    """``measurement_jacobian_diagonal`` (declared by the skewed-t / Poisson model) lets the LEDH
    flow's operator form scale rows instead of multiplying by the d x d whitened Jacobian; the
    skipped terms are exact zeros, so PF-PF(LEDH) and the PFGSPF give the same bits as without the
    declaration (d = 36: the operator form, k >= 32), on the torch path."""
    import torch

    from torchflow.core import tuning
    from torchflow.core.random import TrialStreams
    from torchflow.filters import ParticleFlowGaussianSumParticleFilter, ParticleFlowParticleFilter
    from torchflow.flows.measurement import GaussianMeasurement
    from torchflow.models import SkewedTPoisson

    class Dense(SkewedTPoisson):
        structure = SkewedTPoisson.structure.replace(measurement_jacobian_diagonal=False)

    d = 36
    diag, dense = SkewedTPoisson(d=d), Dense(d=d)
    g = torch.Generator().manual_seed(0)
    traj = diag.simulate(2, 3, g)
    mean, cov = diag.initial_belief(traj.states[:, 0], g)
    x = torch.rand(2, 3, d, generator=g, dtype=torch.float64)
    lin = GaussianMeasurement.from_model(diag, traj.observations[:, 0]).at(x)
    assert lin.diag is not None and torch.equal(lin.diag, lin.W.diagonal(dim1=-2, dim2=-1))
    assert GaussianMeasurement.from_model(dense, traj.observations[:, 0]).at(x).diag is None
    for make in (
        lambda m: ParticleFlowParticleFilter(m, flow="ledh", n_particles=20),
        lambda m: ParticleFlowGaussianSumParticleFilter(m, n_components=2, particles_per_component=d + 1),
    ):
        out = []
        for model in (diag, dense):
            f = make(model)
            # the torch path: with Numba the declared model takes the diagonal CPU kernel (information
            # form, other arithmetic; tests/flows/test_fused.py compares it with this path)
            with torch.no_grad(), tuning.tuned(fused_flows=0):
                out.append(f(traj.observations, mean, cov, TrialStreams(0, 2, f.stream_name)))
        assert torch.equal(out[0].estimates, out[1].estimates), type(f).__name__
        assert torch.equal(out[0].ess, out[1].ess), type(f).__name__
