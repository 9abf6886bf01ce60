"""log K_nu(x) (torchflow.core.special) against scipy.special.kve over the orders the skewed-t model
needs ((nu + d)/2 up to ~200), and where K overflows, against its small-x expansion."""

import math

import numpy as np
import pytest
import torch

from torchflow.core.special import log_bessel_k

scipy_special = pytest.importorskip("scipy.special")


@pytest.mark.parametrize("nu", [0.5, 1.0, 2.5, 4.5, 10.0, 36.0, 75.5, 120.0, 203.5, 250.0])
def test_log_bessel_k_matches_scipy(nu):
    x = torch.logspace(-3, 4, 300, dtype=torch.float64)
    ref = np.log(scipy_special.kve(nu, x.numpy())) - x.numpy()
    ok = np.isfinite(ref)  # kve overflows for large nu at small x
    assert ok.sum() > 100
    err = np.abs(log_bessel_k(nu, x).numpy()[ok] - ref[ok])  # absolute in log = relative in K
    assert err.max() < 1e-10, err.max()


def test_log_bessel_k_where_k_overflows():
    """K_203.5(1e-3) ~ 1e1000: compare with 1/2 Gamma(nu) (2/x)^nu (1 - x^2/(4(nu-1)) + ...)."""
    nu = torch.tensor([75.5, 203.5], dtype=torch.float64)
    x = torch.tensor([1e-3, 1e-2], dtype=torch.float64)
    nn, xx = torch.meshgrid(nu, x, indexing="ij")
    series = (
        torch.lgamma(nn)
        + (nn - 1) * math.log(2)
        - nn * torch.log(xx)
        + torch.log1p(-(xx**2) / (4 * (nn - 1)) + xx**4 / (32 * (nn - 1) * (nn - 2)))
    )
    torch.testing.assert_close(log_bessel_k(nn, xx), series, rtol=1e-13, atol=1e-10)


def test_log_bessel_k_gradient_is_the_recurrence():
    """d/dx log K_nu(x) = -K_{nu-1}(x) / K_nu(x) - nu / x, by autograd through the quadrature."""
    nu = 75.5
    x = torch.tensor([0.5, 5.0, 60.0, 300.0], dtype=torch.float64, requires_grad=True)
    (grad,) = torch.autograd.grad(log_bessel_k(nu, x).sum(), x)
    xn = x.detach().numpy()
    ref = -scipy_special.kve(nu - 1, xn) / scipy_special.kve(nu, xn) - nu / xn
    np.testing.assert_allclose(grad.numpy(), ref, rtol=1e-9)


def test_log_bessel_k_batches_and_is_symmetric_in_the_order():
    x = torch.rand(3, 4, dtype=torch.float64) * 10 + 0.1
    nu = torch.tensor([0.5, 3.0, 80.0, 150.0], dtype=torch.float64)
    out = log_bessel_k(nu, x)
    assert out.shape == (3, 4)
    torch.testing.assert_close(out, log_bessel_k(-nu, x), rtol=0, atol=0)
    torch.testing.assert_close(out[1, 2], log_bessel_k(80.0, x[1, 2]), rtol=1e-14, atol=1e-12)
