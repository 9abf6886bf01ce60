import pytest
import torch

from torchflow.models import AcousticTracking, LinearGaussian, SensorNetwork


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


@pytest.fixture
def small_lg():
    return random_lg()


@pytest.fixture
def acoustic():
    return AcousticTracking()


@pytest.fixture
def sensor_net():
    return SensorNetwork(d=16)


cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
