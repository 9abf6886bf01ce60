"""No host synchronisation inside any filter's step: one step of every filter, counted
on CPU with a ``TorchDispatchMode`` over the aten ops that read a value back to the host
(``_local_scalar_dense``: ``bool(t)``, ``.item()``, ``float(t)``; ``is_nonzero``; ``item``;
``nonzero``: a data-dependent shape). On a GPU each of them stalls the queue; the count must be 0.
(Before they were removed: PF-PF(LEDH) 3, PF-PF(Gromov) 33, the UPF 4 -- the jitter test of
``safe_cholesky`` and the Gromov covariance's step size read from a tensor.) ``safe_cholesky``
reads its failure flags on the CPU by default (a read is free there, its batched jitter ladder is
not), and so does the resampler (which trials resample); the step is counted as it runs on CUDA,
with ``tuning`` ``batched_jitter_cpu=1, host_reads_cpu=0``."""

import pytest
import torch

from experiments.benchmarks.bench_ops import count, filters
from torchflow.core import linalg, tuning
from torchflow.core.profiling import OpCounter
from torchflow.filters import BootstrapParticleFilter, KalmanFilter
from torchflow.models import AcousticTracking, LinearGaussian, SensorNetwork

CountSyncs = OpCounter
N = 40


def _every_filter(model):
    """The op benchmark's filters (every family), and the bootstrap PF with ``nonfinite="raise"``."""
    return {**filters(model, N), "BPF (raise)": BootstrapParticleFilter(model, n_particles=N, nonfinite="raise")}


FILTERS = sorted(_every_filter(AcousticTracking()))


def _second_step(model, f):
    """One time step (the second) as it runs on CUDA (``batched_jitter_cpu=1``)."""
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(2, 2, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    return count(f, traj.observations, mean, cov, batched=True)


@pytest.mark.parametrize("key", FILTERS)
def test_no_filter_step_synchronises(key):
    for model in (AcousticTracking(), SensorNetwork(d=16)):
        counts = _second_step(model, _every_filter(model)[key])
        assert counts.ops > 0 and counts.syncs == [], (key, type(model).__name__, counts.syncs)


def test_kalman_step_does_not_synchronise():
    eye = torch.eye(3, dtype=torch.float64)
    counts = _second_step(
        LinearGaussian(0.9 * eye, 0.1 * eye, eye, 0.2 * eye),
        KalmanFilter(LinearGaussian(0.9 * eye, 0.1 * eye, eye, 0.2 * eye)),
    )
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


def test_safe_cholesky_ladder_slots(monkeypatch):
    """The batched ladder (as on CUDA) gathers the failed matrices into
    ``max(min(n, LADDER_MIN_SLOTS), ceil(n / divisor))`` slots: under the slots, the factor of the
    whole-batch ladder (divisor 1) bit for bit and no host read; failed matrices beyond the slots
    (in batch order) take the ladder's largest jitter, and NaN where even that fails."""
    monkeypatch.setattr(linalg, "LADDER_MIN_SLOTS", 64)
    torch.manual_seed(1)
    n, d = 300, 4
    X = torch.randn(n, d, d, dtype=torch.float64)
    A = X @ X.transpose(-1, -2) + torch.eye(d, dtype=torch.float64)
    eye = torch.eye(d, dtype=torch.float64)
    v = torch.ones(d, dtype=torch.float64)
    bad = torch.outer(v, v) - 1e-13 * eye  # repaired by a jitter of the ladder (not the first)
    some = [3, 77, 150, 299]
    A_some = A.clone()
    A_some[some] = bad
    with tuning.tuned(batched_jitter_cpu=1, jitter_ladder_divisor=1):
        whole = linalg.safe_cholesky(A_some)
    with tuning.tuned(batched_jitter_cpu=1), CountSyncs() as counts:  # 64 slots for 300 matrices
        slotted = linalg.safe_cholesky(A_some)
    assert len(counts.syncs) == 0 and torch.equal(slotted, whole) and bool(torch.isfinite(slotted).all())
    assert torch.equal(slotted, linalg.safe_cholesky(A_some))  # the CPU default: a slot per failed matrix
    many = A.clone()
    many[:70] = bad  # 70 failures, 64 slots
    many[69] = -eye  # beyond the slots and beyond repair
    with tuning.tuned(batched_jitter_cpu=1):
        L = linalg.safe_cholesky(many)
    assert torch.equal(L[:64], whole[3:4].expand(64, d, d))  # the smallest jitter that works
    top = 10.0 * torch.finfo(torch.float64).eps * 10.0**5 * bad.diagonal().abs().mean()
    assert torch.equal(L[64:69], torch.linalg.cholesky(bad + top * eye).expand(5, d, d))  # the largest
    assert not torch.equal(L[64], L[0])
    assert bool(torch.isnan(L[69]).all()) and torch.equal(L[70:], torch.linalg.cholesky(A[70:]))
    with tuning.tuned(batched_jitter_cpu=1, jitter_ladder_divisor=4):  # 75 slots: all repaired alike
        L = linalg.safe_cholesky(many)
    assert torch.equal(L[:69], whole[3:4].expand(69, d, d)) and bool(torch.isnan(L[69]).all())
    monkeypatch.setattr(linalg, "LADDER_MIN_SLOTS", 4096)  # the default: a batch of 300 has a slot each
    with tuning.tuned(batched_jitter_cpu=1):
        L = linalg.safe_cholesky(many)
    assert torch.equal(L[:69], whole[3:4].expand(69, d, d))
