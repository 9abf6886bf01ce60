"""Clustered PF-PF(LEDH) (the clustered PF-PF paper (Li & Coates)): exactness at K = N, unbiased log-evidence for any
K, the batched K-medoids and the mixed distance."""

import math

import pytest
import torch
from conftest import mild_lg, random_lg, replicated

from torchflow.core.random import TrialStreams
from torchflow.filters import ClusteredParticleFlowParticleFilter, KalmanFilter, ParticleFlowParticleFilter
from torchflow.flows import cluster_distance, kmedoids
from torchflow.models import AcousticTracking

_replicated = replicated


def test_k_equal_n_is_pfpf_ledh_on_the_same_draws():
    """Every particle its own medoid: on a linear model (where every particle's EKF covariance is
    the shared one) this is PF-PF(LEDH) exactly."""
    model = random_lg(3, 2, seed=4)
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(4, 5, g)
    mean, cov = model.initial_belief(traj.states[:, 0])
    N = 32
    ledh = ParticleFlowParticleFilter(model, flow="ledh", n_particles=N)(
        traj.observations, mean, cov, TrialStreams(0, 4, "pfpf")
    )
    clus = ClusteredParticleFlowParticleFilter(model, n_clusters=N, n_particles=N)(
        traj.observations, mean, cov, TrialStreams(0, 4, "pfpf")
    )
    torch.testing.assert_close(clus.estimates, ledh.estimates, rtol=0, atol=1e-10)
    torch.testing.assert_close(clus.log_evidence, ledh.log_evidence, rtol=0, atol=1e-10)
    torch.testing.assert_close(clus.ess, ledh.ess, rtol=0, atol=1e-10)


@pytest.mark.parametrize("K", [1, 4, 64])
def test_clustered_log_evidence_unbiased_on_lg(K):
    """E[Z_hat / Z] = 1 within 4 standard errors over 400 runs on the same data (the test of the
    other PF-PFs), for one cluster, a few, and one per particle."""
    model = mild_lg()
    obs, mean, cov = _replicated(model, 400, 6)
    logz = KalmanFilter(model)(obs[:1], mean[:1], cov[:1]).log_evidence
    f = ClusteredParticleFlowParticleFilter(model, n_clusters=K, n_particles=64)
    res = f(obs, mean, cov, TrialStreams(1, 400, "pfpf"))
    r = torch.exp(res.log_evidence - logz)
    se = r.std() / math.sqrt(r.numel())
    assert abs(float(r.mean()) - 1) < 4 * float(se), (float(r.mean()), float(se))
    assert float(se) < 0.05


def test_without_the_cluster_jacobian_the_evidence_is_biased():
    """The seed's printed algorithm (no theta in the weight): biased far beyond the tolerance above,
    so that test can fail."""
    model = mild_lg()
    obs, mean, cov = _replicated(model, 400, 6)
    logz = KalmanFilter(model)(obs[:1], mean[:1], cov[:1]).log_evidence
    f = ClusteredParticleFlowParticleFilter(model, n_clusters=4, n_particles=64, jacobian_in_weight=False)
    r = torch.exp(f(obs, mean, cov, TrialStreams(1, 400, "pfpf")).log_evidence - logz)
    assert abs(float(r.mean()) - 1) > 10 * float(r.std() / 20), float(r.mean())


def test_kmedoids_finds_separated_groups_and_is_batch_independent():
    g = torch.Generator().manual_seed(0)
    centres = torch.tensor([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]], dtype=torch.float64)
    pts = centres.repeat_interleave(20, 0) + 0.1 * torch.randn(60, 2, generator=g, dtype=torch.float64)
    perm = torch.randperm(60, generator=g)
    pts = pts[perm]
    group = torch.arange(3).repeat_interleave(20)[perm]
    D = torch.cdist(pts, pts)
    batch = torch.stack([D, D.flip(0).flip(1), D])  # three trials
    index, medoids = kmedoids(batch, 3)
    # trial 0: same partition as the true groups (up to relabelling), medoids inside their clusters
    pairs = {(int(a), int(b)) for a, b in zip(index[0], group)}
    assert len(pairs) == 3
    assert torch.equal(index[0][medoids[0]], torch.arange(3))
    # a trial's result does not depend on the other trials in the batch
    one_index, one_medoids = kmedoids(batch[1:2], 3)
    assert torch.equal(one_index[0], index[1]) and torch.equal(one_medoids[0], medoids[1])
    assert torch.equal(index[0], index[2])
    # K >= N: every point its own medoid
    idx, med = kmedoids(batch[:, :5, :5], 7)
    assert torch.equal(idx, torch.arange(5).expand(3, 5)) and torch.equal(med, idx)


def test_cluster_distance_properties():
    g = torch.Generator().manual_seed(1)
    eta = torch.randn(2, 30, 6, generator=g, dtype=torch.float64)
    zeta = torch.randn(2, 30, 6, generator=g, dtype=torch.float64)
    for alpha in (0.0, 0.25, 1.0):
        D = cluster_distance(eta, zeta, alpha, support=(0, 1, 2))
        assert D.shape == (2, 30, 30)
        torch.testing.assert_close(D, D.transpose(-1, -2))
        assert (D >= -1e-12).all() and (D <= 2 + 1e-12).all()
        torch.testing.assert_close(
            D.diagonal(dim1=-2, dim2=-1), torch.zeros(2, 30, dtype=torch.float64), atol=1e-12, rtol=0
        )
    # alpha = 1: only the measured coordinates count
    D1 = cluster_distance(eta, zeta, 1.0, support=(0, 1, 2))
    eta2 = eta.clone()
    eta2[..., 3:] += 5.0
    torch.testing.assert_close(cluster_distance(eta2, zeta, 1.0, support=(0, 1, 2)), D1)
    with pytest.raises(ValueError, match=r"alpha: expected a weight in \[0, 1\], got 1.5"):
        cluster_distance(eta, zeta, 1.5)


def test_clustered_on_acoustic_and_argument_errors():
    model = AcousticTracking(sigma_w=0.1)
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(2, 3, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    res = ClusteredParticleFlowParticleFilter(model, n_clusters=10, n_particles=60)(
        traj.observations, mean, cov, TrialStreams(0, 2, "pfpf")
    )
    assert torch.isfinite(res.estimates).all() and torch.isfinite(res.log_evidence).all()
    gromov = ClusteredParticleFlowParticleFilter(model, flow="gromov", n_clusters=10, n_particles=60)(
        traj.observations, mean, cov, TrialStreams(0, 2, "pfpf")
    )
    assert torch.isfinite(gromov.estimates).all() and torch.isfinite(gromov.log_evidence).all()
    with pytest.raises(ValueError, match=r"n_clusters: expected a positive integer, got 0"):
        ClusteredParticleFlowParticleFilter(model, n_clusters=0)
    with pytest.raises(ValueError, match=r"alpha: expected a weight in \[0, 1\], got 2"):
        ClusteredParticleFlowParticleFilter(model, alpha=2)
    with pytest.raises(TypeError, match="jacobian_in_weight: expected a bool"):
        ClusteredParticleFlowParticleFilter(model, jacobian_in_weight="yes")


@pytest.mark.parametrize("K", [1, 4])
def test_clustered_gromov_log_evidence_unbiased_on_lg(K):
    """Stochastic flow with clustered points: each particle's Gaussian law is tracked exactly, so
    the evidence stays unbiased (same test as above)."""
    model = mild_lg()
    obs, mean, cov = _replicated(model, 400, 6)
    logz = KalmanFilter(model)(obs[:1], mean[:1], cov[:1]).log_evidence
    f = ClusteredParticleFlowParticleFilter(model, flow="gromov", n_clusters=K, n_particles=64)
    r = torch.exp(f(obs, mean, cov, TrialStreams(2, 400, "pfpf")).log_evidence - logz)
    se = r.std() / math.sqrt(r.numel())
    assert abs(float(r.mean()) - 1) < 4 * float(se), (float(r.mean()), float(se))
    assert float(se) < 0.05


def test_clustered_gromov_with_k_equal_n_is_pfpf_gromov_on_lg():
    model = random_lg(3, 2, seed=4)
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(3, 4, g)
    mean, cov = model.initial_belief(traj.states[:, 0])
    a = ParticleFlowParticleFilter(model, flow="gromov", n_particles=16)(
        traj.observations, mean, cov, TrialStreams(0, 3, "pfpf")
    )
    b = ClusteredParticleFlowParticleFilter(model, flow="gromov", n_clusters=16, n_particles=16)(
        traj.observations, mean, cov, TrialStreams(0, 3, "pfpf")
    )
    torch.testing.assert_close(b.estimates, a.estimates, rtol=0, atol=1e-10)
    torch.testing.assert_close(b.log_evidence, a.log_evidence, rtol=0, atol=1e-10)
