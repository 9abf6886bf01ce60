import os
from pathlib import Path

# The suite runs processes side by side (pytest-xdist's workers, the commands tests start). OpenMP
# threads that spin-wait between parallel regions (libgomp's default; Numba's "omp" layer keeps a
# pool of NUMBA_NUM_THREADS threads that spins even when one thread is asked for) then take the
# cores from the other processes: measured 5-20x slower tests with two workers. Passive waiting
# changes scheduling, not results. Set before torch loads its OpenMP runtime; subprocesses inherit it.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import pytest
import torch

from torchflow.core.registry import register_configs
from torchflow.models import AcousticTracking, LinearGaussian, SensorNetwork

register_configs()  # the signature nodes configs/ extend (tests compose the configs without the command line)

if os.environ.get("PYTEST_XDIST_WORKER"):
    # pytest-xdist (addopts: -n auto) runs one worker per core: each worker computes on one torch
    # thread (Numba's kernels follow torch's count), and so do the commands it starts (torchflow's
    # job threads follow OMP_NUM_THREADS). Tests that compare numbers across thread counts set the
    # counts they compare themselves.
    os.environ["OMP_NUM_THREADS"] = "1"
    torch.set_num_threads(1)


def random_lg(d=3, m=2, seed=0, learnable=False, prior=True):
    """A small random linear-Gaussian model with m != d and a proper prior."""
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(d, d, generator=g, dtype=torch.float64)
    F = 0.9 * A / torch.linalg.matrix_norm(A, 2)
    Lq = torch.randn(d, d, generator=g, dtype=torch.float64) * 0.3
    Q = Lq @ Lq.T + 0.2 * torch.eye(d, dtype=torch.float64)
    H = torch.randn(m, d, generator=g, dtype=torch.float64)
    Lr = torch.randn(m, m, generator=g, dtype=torch.float64) * 0.2
    R = Lr @ Lr.T + 0.3 * torch.eye(m, dtype=torch.float64)
    m0 = torch.randn(d, generator=g, dtype=torch.float64)
    P0 = torch.eye(d, dtype=torch.float64) * (1.5 if prior else 0.0)
    return LinearGaussian(F, Q, H, R, m0, P0, learnable=learnable)


def simulate_with_belief(model, trials, steps, seed=0):
    """``(traj, mean, cov, g)``: ``trials`` simulated trajectories of ``steps`` steps, the model's
    prior belief around their first states, and the generator (seeded ``seed``) that drew them."""
    g = torch.Generator().manual_seed(seed)
    traj = model.simulate(trials, steps, g)
    mean, cov = model.initial_belief(traj.states[:, 0])
    return traj, mean, cov, g


@pytest.fixture
def small_lg():
    return random_lg()


@pytest.fixture
def acoustic():
    return AcousticTracking()


@pytest.fixture
def sensor_net():
    return SensorNetwork(d=16)


ROOT = Path(__file__).resolve().parents[1]

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


def mild_lg(d=3, m=2, seed=0):
    """A linear-Gaussian model whose PF-PF weights have finite variance.

    The PF-PF pushes the transition sample eta_0 ~ N(F x_{k-1}, Q) through a flow built for the
    wider prior N(eta_bar_0, P), P the predictive covariance. Where P >> Q and the measurement
    contracts P strongly, the proposal is narrower than the target and the weights have infinite
    variance: ESS/N then falls as N grows and sample standard errors mean nothing (observed with
    ``random_lg`` and with R = I, P0 = I here). Statistical tests need finite variance, hence a
    small prior (P0 = 0.1 I) and an informative measurement (R = 0.1 I), so P stays close to Q;
    ESS/N is then stable at ~0.6 from N = 1e3 to 1e5.
    """
    g = torch.Generator().manual_seed(seed)
    H = torch.randn(m, d, generator=g, dtype=torch.float64)
    eye_d = torch.eye(d, dtype=torch.float64)
    return LinearGaussian(
        0.9 * eye_d,
        0.5 * eye_d,
        H,
        0.1 * torch.eye(m, dtype=torch.float64),
        torch.zeros(d, dtype=torch.float64),
        0.1 * eye_d,
    )


def replicated(model, B, T, seed=0):
    """One observation sequence replicated over B trials (unbiasedness is conditional on z)."""
    g = torch.Generator().manual_seed(seed)
    traj = model.simulate(1, T, g)
    obs = traj.observations.expand(B, -1, -1).contiguous()
    mean, cov = model.initial_belief(traj.states[:, 0].expand(B, -1))
    return obs, mean, cov
