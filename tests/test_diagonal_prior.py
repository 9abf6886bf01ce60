"""A diagonal prior covariance (:class:`~torchflow.core.covariances.DiagonalCovariance`): what it offers
the code that passes a prior on, which filters take it as it is and which are given its matrix, the
same draws either way, its checks, and Lorenz-96 at a size where no ``d x d`` matrix could exist."""

import warnings

import pytest
import torch

import torchflow.filters as F
from torchflow.app.runner import ConfigError, run_experiment
from torchflow.app.runner.plan import filter_chunk
from torchflow.core.covariances import DiagonalCovariance, dense_prior, sample_prior
from torchflow.core.errors import ArgumentError
from torchflow.core.random import TrialStreams
from torchflow.models import Lorenz96
from torchflow.models.base import GaussianStateSpaceModel

F64 = torch.float64


def _var(B=3, d=5, seed=0):
    return 0.5 + torch.rand(B, d, dtype=F64, generator=torch.Generator().manual_seed(seed))


def test_it_stands_for_its_matrix_where_a_prior_is_passed_on():
    v = _var()
    cov = DiagonalCovariance(v)
    assert cov.shape == (3, 5, 5) and cov.dim() == 3 and len(cov) == 3 and cov.dtype == F64
    assert torch.equal(cov.dense(), torch.diag_embed(v)) and torch.equal(dense_prior(cov), torch.diag_embed(v))
    assert torch.equal(cov[1:3].variance, v[1:3]) and torch.equal(cov[torch.tensor([2, 0])].variance, v[[2, 0]])
    assert torch.equal(cov[1].dense(), torch.diag(v[1])) and cov[1].shape == (5, 5)
    assert torch.equal(cov.diagonal(dim1=-2, dim2=-1), v) and torch.equal(cov.scale(), v.sqrt())
    assert cov.to(torch.float32).dtype == torch.float32 and cov.detach().variance is not None
    shared = DiagonalCovariance(v[0])
    assert torch.equal(shared.expand(4, 5, 5).variance, v[0].expand(4, 5)) and shared.expand(4, -1, -1).shape == (
        4,
        5,
        5,
    )
    plain = torch.eye(2, dtype=F64)
    assert dense_prior(plain) is plain


@pytest.mark.parametrize(
    "bad, match",
    [
        (torch.ones(2, 3, 3, dtype=F64), r"variance: expected a floating-point tensor \(B, d\) or \(d,\).*\(2, 3, 3\)"),
        (torch.ones(3, dtype=torch.long), "floating-point"),
        ([1.0, 2.0], "got list"),
    ],
)
def test_a_bad_variance_is_named(bad, match):
    with pytest.raises(ArgumentError, match=match):
        DiagonalCovariance(bad)


def test_only_trials_are_selected():
    with pytest.raises(ArgumentError, match="only trials are selected"):
        DiagonalCovariance(_var())[0, 1]
    with pytest.raises(ArgumentError, match=r"expand: expected \(B, d, d\)"):
        DiagonalCovariance(_var()[0]).expand(4, 5, 6)


def test_the_draws_are_those_of_the_dense_factor():
    mean, v = torch.randn(3, 5, dtype=F64), _var()
    a = sample_prior(mean, DiagonalCovariance(v), 7, torch.Generator().manual_seed(3))
    b = sample_prior(mean, torch.diag_embed(v), 7, torch.Generator().manual_seed(3))
    assert a.shape == (3, 7, 5) and torch.allclose(a, b, rtol=0, atol=1e-14)


@pytest.mark.parametrize(
    "make",
    [
        lambda m: F.EnsembleTransformKalmanFilter(m, n_particles=6),
        lambda m: F.EnsembleKalmanFilter(m, n_particles=6),
        lambda m: F.BootstrapParticleFilter(m, n_particles=50),
    ],
)
def test_filters_that_sample_the_prior_keep_the_variances_and_match_the_matrix(make):
    model = Lorenz96(d=8, model_noise=0.2)
    f = make(model)
    assert f.diagonal_prior
    traj = model.simulate(3, 5, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator().manual_seed(1))
    assert isinstance(cov, DiagonalCovariance) and cov.variance.stride(-1) == 0  # a view: nothing per coordinate
    _, kept = f.check_prior(mean, cov, 3)
    assert isinstance(kept, DiagonalCovariance)
    a = f(traj.observations, mean, cov, TrialStreams(0, 3, "t"))
    b = f(traj.observations, mean, cov.dense(), TrialStreams(0, 3, "t"))
    assert torch.allclose(a.estimates, b.estimates, rtol=0, atol=1e-9)  # 5 steps: round-off has not grown


@pytest.mark.parametrize(
    "make",
    [
        lambda m: F.ExtendedKalmanFilter(m),
        lambda m: F.UnscentedKalmanFilter(m),
        lambda m: F.GaussianParticleFilter(m, n_particles=20),
    ],
)
def test_the_other_filters_are_given_the_matrix(make):
    model = Lorenz96(d=6, model_noise=0.3)
    f = make(model)
    assert not f.diagonal_prior
    v = _var(2, 6)
    _, dense = f.check_prior(torch.zeros(2, 6, dtype=F64), DiagonalCovariance(v), 2)
    assert isinstance(dense, torch.Tensor) and torch.equal(dense, torch.diag_embed(v))


def test_a_pf_pf_is_given_the_matrix_its_tracker_carries():
    model = Lorenz96(d=6, model_noise=0.3)
    f = F.ParticleFlowParticleFilter(model, n_particles=10)
    assert not f.diagonal_prior
    mean, cov = model.initial_belief(torch.zeros(2, 6, dtype=F64), torch.Generator().manual_seed(0))
    _, dense = f.check_prior(mean, cov, 2)
    assert isinstance(dense, torch.Tensor) and dense.shape == (2, 6, 6)
    assert f.init(mean, dense, generator=torch.Generator().manual_seed(1)).cov.matrix.shape[-2:] == (6, 6)


def test_a_bad_diagonal_prior_is_named():
    model = Lorenz96(d=4)
    f = F.EnsembleTransformKalmanFilter(model, n_particles=4)
    mean = torch.zeros(2, 4, dtype=F64)
    with pytest.raises(ArgumentError, match=r"cov.variance: expected variances >= 0.*-1 in trial 1"):
        f.check_prior(mean, DiagonalCovariance(torch.tensor([[1.0] * 4, [1.0, -1.0, 1.0, 1.0]], dtype=F64)), 2)
    with pytest.raises(ArgumentError, match=r"cov.variance"):
        f.check_prior(mean, DiagonalCovariance(torch.ones(2, 5, dtype=F64)), 2)
    with pytest.raises(ArgumentError, match=r"cov.variance.*(NaN|inf|non-finite)"):
        f.check_prior(mean, DiagonalCovariance(torch.tensor([[1.0, float("nan"), 1.0, 1.0]] * 2, dtype=F64)), 2)
    shared = f.check_prior(mean, DiagonalCovariance(torch.ones(4, dtype=F64)), 2)[1]
    assert shared.variance.shape == (2, 4)
    # variances given as a (B, d) tensor where a matrix is expected: the error says what to pass
    with pytest.raises(ArgumentError, match="DiagonalCovariance"):
        f.check_prior(mean, torch.ones(2, 4, dtype=F64), 2)


def test_lorenz96_densities_and_samplers_are_the_gaussian_forms_without_matrices():
    m = Lorenz96(d=12, obs_every=2, model_noise=0.3, obs_std=0.7)
    G = GaussianStateSpaceModel
    g = torch.Generator().manual_seed(0)
    x, xn = torch.randn(3, 5, 12, dtype=F64, generator=g), torch.randn(3, 5, 12, dtype=F64, generator=g)
    z = torch.randn(3, 1, 6, dtype=F64, generator=g)
    seen = torch.rand(3, 1, 6, generator=g) > 0.3
    assert torch.allclose(m.transition_log_prob(xn, x), G.transition_log_prob(m, xn, x), rtol=1e-13, atol=0)
    assert torch.allclose(m.measurement_log_prob(z, x), G.measurement_log_prob(m, z, x), rtol=1e-13, atol=0)
    h = x[..., ::2]
    expected = torch.where(seen, torch.distributions.Normal(h, 0.7).log_prob(z), torch.zeros(())).sum(-1)
    assert torch.allclose(m.measurement_log_prob_observed(z, x, seen), expected, rtol=1e-13, atol=0)
    assert torch.allclose(
        m.measurement_variance(x).expand(3, 5, 6),
        m.measurement_cov(x).diagonal(dim1=-2, dim2=-1).expand(3, 5, 6),
        rtol=1e-15,
        atol=0,
    )
    for method in ("sample_measurement", "sample_true_transition"):
        a = getattr(m, method)(x, torch.Generator().manual_seed(1))
        b = getattr(G, method)(m, x, torch.Generator().manual_seed(1))
        assert torch.allclose(a, b, rtol=0, atol=1e-14), method
    H = m.measurement_matrix()
    assert H.shape == (6, 12) and torch.equal(m.measure(x), x @ H.T) and torch.equal(m.H, H)


def test_lorenz96_at_a_million_coordinates_runs_without_a_d_by_d_matrix():
    """d = 10^6: one dense (d, d) matrix would be 8 TB, so any that were formed (the prior, H, R, Q,
    the shape checks, the memory plan) would fail at once. The ETKF runs through the runner."""
    d = 10**6
    model = Lorenz96(d=d, spin_up=1, obs_every=10)
    res = run_experiment(
        model,
        {"etkf": F.EnsembleTransformKalmanFilter(model, n_particles=4)},
        trials=1,
        steps=2,
        seed=0,
        progress=False,
    )
    row = res.summary[0]
    assert row["error"] is None and row["trials"] == 1 and 0 < row["rmse"] < 10


def test_the_letkf_plans_blocks_of_coordinates_within_the_budget():
    model = Lorenz96(d=10**6)
    f = F.LocalEnsembleTransformKalmanFilter(model, n_particles=20, radius=15.0)
    whole = f.bytes_per_trial()
    with pytest.warns(UserWarning, match=r"blocks of \d+ of its 1000000 coordinates' local analyses"):
        assert filter_chunk(f, 1, None, whole / 4 / 2**30) == 1
    assert f.local_chunk is not None and f.bytes_per_trial() <= whole / 4
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        g = F.LocalEnsembleTransformKalmanFilter(Lorenz96(d=40), n_particles=20)
        assert filter_chunk(g, 1, None, 1.0) == 1 and g.local_chunk is None


def test_the_letkf_in_blocks_gives_the_same_numbers():
    model = Lorenz96(d=60)
    traj = model.simulate(2, 20, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator().manual_seed(1))
    whole = F.LocalEnsembleTransformKalmanFilter(model, inflation=1.02)
    blocks = F.LocalEnsembleTransformKalmanFilter(model, inflation=1.02, local_chunk=7)
    a = whole(traj.observations, mean, cov, TrialStreams(0, 2, "x"))
    b = blocks(traj.observations, mean, cov, TrialStreams(0, 2, "x"))
    assert torch.allclose(a.estimates, b.estimates, rtol=0, atol=1e-9)
    with pytest.raises(ArgumentError, match="local_chunk"):
        F.LocalEnsembleTransformKalmanFilter(model, local_chunk=0)


def test_a_recorded_series_takes_a_diagonal_prior():
    model = Lorenz96(d=8)
    z = model.simulate(1, 6, torch.Generator().manual_seed(0)).observations[0]
    prior = (torch.full((8,), 8.0, dtype=F64), DiagonalCovariance(torch.full((8,), 4.0, dtype=F64)))
    res = run_experiment(
        model,
        {"etkf": F.EnsembleTransformKalmanFilter(model, n_particles=6), "ekf": F.ExtendedKalmanFilter(model)},
        observations=z,
        prior=prior,
        trials=2,
        progress=False,
    )
    assert all(r["error"] is None for r in res.summary)


def test_a_filter_whose_one_trial_cannot_fit_is_named_with_what_would_run():
    """At d = 10^5 the EKF's d x d matrices need terabytes for one trial: splitting the trials does
    not help, and the error says which filter and what scales instead."""
    model = Lorenz96(d=10**5, spin_up=1)
    filters = {"ekf": F.ExtendedKalmanFilter(model), "etkf": F.EnsembleTransformKalmanFilter(model, n_particles=4)}
    with pytest.raises(
        ConfigError,
        match=r"ekf alone needs about [\d,.]+ GiB for one trial at d = 100000, m = 100000, "
        r"so no split of the trials fits: leave it out of this run.*ensemble Kalman",
    ):
        run_experiment(model, filters, trials=1, steps=2, progress=False)


def test_a_local_chunk_given_is_kept_by_the_runner():
    f = F.LocalEnsembleTransformKalmanFilter(Lorenz96(d=10**6), n_particles=20, local_chunk=1000)
    assert filter_chunk(f, 1, None, 0.001) == 1 and f.local_chunk == 1000


def test_a_shared_diagonal_prior_stays_one_matrix_for_the_filters_that_need_it():
    f = F.ExtendedKalmanFilter(Lorenz96(d=6))
    _, dense = f.check_prior(torch.zeros(5, 6, dtype=F64), DiagonalCovariance(torch.full((6,), 2.0, dtype=F64)), 5)
    assert dense.shape == (5, 6, 6) and dense.stride(0) == 0 and torch.equal(dense[3], 2.0 * torch.eye(6, dtype=F64))


def test_the_model_check_forms_no_large_matrix_and_reads_a_declared_scale():
    """check_covariances does not form a Q or R of more than COVARIANCE_CHECK_NUMBERS numbers
    (d = 10^5: 80 GB) to check it; a declared R = r I of that size is checked by its scale."""
    from torchflow.models.contract import check_covariances

    big = Lorenz96(d=10**5)
    calls = []
    big.transition_cov = lambda x=None: calls.append("Q")
    big.measurement_cov = lambda x=None: calls.append("R")
    check_covariances(big, "x")
    assert calls == []
    big.structure = big.structure.replace(measurement_noise_scale=-1.0)
    with pytest.raises(ArgumentError, match=r"measurement covariance \(-1 I, declared\) is not positive semi-definite"):
        check_covariances(big, "x")


def test_learning_batches_a_diagonal_prior_as_variances():
    from torchflow.app.lightning import TrajectoryDataset

    model = Lorenz96(d=8)
    traj = model.simulate(3, 4, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator().manual_seed(1))
    data = TrajectoryDataset(traj, mean, cov)
    obs, m, v, i = torch.utils.data.default_collate([data[0], data[2]])
    assert v.shape == (2, 8) and torch.equal(v, cov.variance[[0, 2]])


def test_lorenz96_transition_density_runs_the_dynamics_once_per_state():
    m = Lorenz96(d=10, model_noise=0.5)
    x = torch.randn(2, 3, 1, 10, dtype=F64)  # (B, paths, 1, d) against particles (B, 1, N, d): FFBSi's layout
    xn = torch.randn(2, 1, 7, 10, dtype=F64)
    seen = []
    rk = m.transition_mean
    m.transition_mean = lambda v: seen.append(tuple(v.shape)) or rk(v)
    lp = m.transition_log_prob(xn, x)
    assert lp.shape == (2, 3, 7) and seen == [(2, 3, 1, 10)]
    assert torch.allclose(lp, GaussianStateSpaceModel.transition_log_prob(m, xn, x), rtol=1e-12, atol=0)


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_the_threaded_eigh_gives_the_numbers_of_one_call(threads):
    from torchflow.core import linalg

    g = torch.Generator().manual_seed(0)
    A = torch.randn(3, 700, 6, 9, dtype=F64, generator=g)
    M = A @ A.transpose(-1, -2)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        lam, V = linalg.eigh(M)
    finally:
        torch.set_num_threads(before)
    lam0, V0 = torch.linalg.eigh(M)
    assert torch.equal(lam, lam0) and torch.equal(V, V0)
    small = M[0, :10]
    assert all(torch.equal(a, b) for a, b in zip(linalg.eigh(small), torch.linalg.eigh(small)))
    Mg = M[0].clone().requires_grad_()
    linalg.eigh(Mg)[0].sum().backward()  # one call while gradients are recorded
    assert Mg.grad is not None and torch.isfinite(Mg.grad).all()


def test_the_lightning_module_rebuilds_a_batched_diagonal_prior():
    """A TrajectoryDataset batches a diagonal prior's variances; the module's loss gives the filter
    a DiagonalCovariance again, and the memory probe of ``checkpoint_steps="auto"`` checks it first
    (a Kalman-type filter is given the matrix)."""
    from torch.utils.data import DataLoader

    from torchflow.app.lightning import FilterLightningModule, TrajectoryDataset, backward_bytes_per_step

    model = Lorenz96(d=6, model_noise=0.3)
    traj = model.simulate(4, 5, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator().manual_seed(1))
    del model._buffers["forcing"]
    model.forcing = torch.nn.Parameter(torch.tensor(7.5, dtype=F64))  # learnable F
    ukf = F.UnscentedKalmanFilter(model)
    assert backward_bytes_per_step(ukf, traj.observations, mean, cov) > 0
    batch = next(iter(DataLoader(TrajectoryDataset(traj, mean, cov), batch_size=4)))
    loss = FilterLightningModule(ukf, lr=0.01)._loss(batch, 0)
    direct = -ukf(traj.observations, mean, cov.dense()).log_evidence.mean() / traj.observations.shape[1]
    assert torch.isfinite(loss) and loss.requires_grad
    assert torch.allclose(loss, direct, rtol=1e-12, atol=0)


def test_a_large_declared_measurement_noise_is_checked_by_its_scale():
    model = Lorenz96(d=5000, spin_up=0)
    model.structure = model.structure.replace(measurement_noise_scale=0.0)
    with pytest.raises(ArgumentError, match=r"measurement covariance is not positive definite \(declared 0 I\)"):
        F.EnsembleTransformKalmanFilter(model, n_particles=4).check_model()
