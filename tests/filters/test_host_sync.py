"""No host synchronisation inside any filter's step (issue 30): one step of every filter, counted
on CPU with a ``TorchDispatchMode`` over the aten ops that read a value back to the host
(``_local_scalar_dense``: ``bool(t)``, ``.item()``, ``float(t)``; ``is_nonzero``; ``item``;
``nonzero``: a data-dependent shape). On a GPU each of them stalls the queue; the count must be 0.
(Before issue 30: PF-PF(LEDH) 3, PF-PF(Gromov) 33, the UPF 4 -- the jitter test of
``safe_cholesky`` and the Gromov covariance's step size read from a tensor.) ``safe_cholesky``
reads its failure flags on the CPU by default (a read is free there, its batched jitter ladder is
not); the step is counted as it runs on CUDA, with ``tuning`` ``batched_jitter_cpu=1``."""
import pytest
import torch

from torchflow import linalg, tuning
from torchflow.filters import (GPFIS, BootstrapParticleFilter, ClusteredParticleFlowParticleFilter,
                               ExtendedKalmanFilter, GaussianParticleFilter, GaussianSumParticleFilter,
                               KalmanFilter, ParticleFilter, ParticleFlowFilter,
                               ParticleFlowGaussianSumParticleFilter, ParticleFlowParticleFilter,
                               UnscentedKalmanFilter)
from torchflow.models import AcousticTracking, LinearGaussian, SensorNetwork
from torchflow.profiling import OpCounter
from torchflow.proposals import UnscentedProposal
from torchflow.random import TrialStreams

CountSyncs = OpCounter


FILTERS = {
    "bpf": lambda m: BootstrapParticleFilter(m, n_particles=32),
    "bpf_raise": lambda m: BootstrapParticleFilter(m, n_particles=32, nonfinite="raise"),
    **{f"pfpf_{fl}": (lambda fl: lambda m: ParticleFlowParticleFilter(m, flow=fl, n_particles=32))(fl)
       for fl in ("edh", "ledh", "geodesic", "gromov", "osd")},
    "pfpf_clustered": lambda m: ClusteredParticleFlowParticleFilter(m, n_clusters=5, n_particles=32),
    "gpfis": lambda m: GPFIS(m, n_particles=32),
    "upf": lambda m: ParticleFilter(m, UnscentedProposal(m), n_particles=32),
    "gpf": lambda m: GaussianParticleFilter(m, n_particles=32),
    "gspf": lambda m: GaussianSumParticleFilter(m, n_components=2, particles_per_component=20),
    "pfgspf": lambda m: ParticleFlowGaussianSumParticleFilter(m, n_components=2, particles_per_component=20),
    "flow_filter": lambda m: ParticleFlowFilter(m, flow="ledh", n_particles=32),
    "ekf": ExtendedKalmanFilter,
    "ukf": UnscentedKalmanFilter,
}


def _second_step(model, f):
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(2, 2, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    streams = TrialStreams(0, 2, f.stream_name) if f.uses_randomness else None
    with torch.no_grad():
        state = f.step(f.init(mean, cov, None, streams), traj.observations[:, 0], streams)
        with tuning.tuned(batched_jitter_cpu=1), CountSyncs() as counts:
            f.step(state, traj.observations[:, 1], streams)
    return counts


@pytest.mark.parametrize("key", sorted(FILTERS))
def test_no_filter_step_synchronises(key):
    for model in (AcousticTracking(), SensorNetwork(d=16)):
        counts = _second_step(model, FILTERS[key](model))
        assert counts.ops > 0 and counts.syncs == [], (key, type(model).__name__, counts.syncs)


def test_kalman_step_does_not_synchronise():
    eye = torch.eye(3, dtype=torch.float64)
    counts = _second_step(LinearGaussian(0.9 * eye, 0.1 * eye, eye, 0.2 * eye), KalmanFilter(
        LinearGaussian(0.9 * eye, 0.1 * eye, eye, 0.2 * eye)))
    assert counts.ops > 0 and counts.syncs == []


def test_the_counter_sees_a_synchronisation():
    """The test above can fail: a read-back inside the block is counted."""
    with CountSyncs() as counts:
        x = torch.ones(3)
        bool(x.sum() > 0), x.sum().item(), torch.nonzero(x)
    assert len(counts.syncs) == 3


@pytest.mark.parametrize("batched", [1, 0])
def test_safe_cholesky_jitter_ladder(batched):
    """Clean matrices are untouched; a failing one gets the smallest jitter of the ladder under
    which it factors; one that fails every jitter gets NaN (the filter's non-finite path names it).
    Batched (as on CUDA): no host read; the CPU default reads the failure flags once."""
    torch.manual_seed(0)
    X = torch.randn(4, 3, 3, dtype=torch.float64)
    A = X @ X.transpose(-1, -2) + torch.eye(3, dtype=torch.float64)
    clean = A.clone()
    v = torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64)
    singular = torch.outer(v, v) - 1e-13 * torch.eye(3, dtype=torch.float64)  # rank 1, nudged indefinite
    A[1] = singular
    A[2] = -torch.eye(3, dtype=torch.float64)  # indefinite: no jitter of the ladder helps
    with tuning.tuned(batched_jitter_cpu=batched), CountSyncs() as counts:
        L = linalg.safe_cholesky(A)
    assert len(counts.syncs) == (0 if batched else 1)
    for i in (0, 3):
        assert torch.equal(L[i], torch.linalg.cholesky(A[i]))
    eps, scale = 10.0 * torch.finfo(torch.float64).eps, singular.diagonal().abs().mean()
    eye = torch.eye(3, dtype=torch.float64)
    k = next(k for k in range(6) if torch.linalg.cholesky_ex(singular + eps * 10.0**k * scale * eye)[1] == 0)
    assert k > 0  # the ladder is climbed, not its first rung only
    assert torch.equal(L[1], torch.linalg.cholesky(singular + eps * 10.0**k * scale * eye))
    assert bool(torch.isnan(L[2]).all())
    with tuning.tuned(batched_jitter_cpu=batched), CountSyncs() as counts:
        assert torch.equal(linalg.safe_cholesky(clean), torch.linalg.cholesky(clean))
    assert len(counts.syncs) == (0 if batched else 1)
