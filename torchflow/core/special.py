"""Special functions torch lacks, in log space: ``log K_nu(x)``, the modified Bessel function of the
second kind, for the generalised-hyperbolic skewed-t density (Septier & Peters 2016; orders
``(nu + d) / 2`` reach ~75.5 at d = 144 and ~200 at d = 400, where ``K`` itself overflows).

Method: the integral ``K_nu(x) = 1/2 int_R exp(-x cosh t + nu t) dt`` (nu real, x > 0). Its log-
integrand ``f`` is concave with its maximum at ``sinh t* = nu / x``, where ``x cosh t* = r =
sqrt(x^2 + nu^2)`` and ``f''(t*) = -r``. With ``t = t* + sigma s``, ``sigma = r^{-1/2}``,

    f(t) - f(t*) = -2 r sinh^2(sigma s / 2) - nu (sinh(sigma s) - sigma s),
    f(t*) = -r + nu asinh(nu / x),

both without cancellation between large terms, and the trapezoidal rule on a fixed grid in ``s``
(exponentially accurate for this entire integrand) is summed by ``logsumexp``. Batched over any
shape, differentiable in ``x`` and ``nu`` by autograd, no host synchronisation. Accuracy against
``scipy.special.kve``: better than 1e-10 relative for nu in [0.5, 250] and x in [1e-3, 1e4]
(``tests/test_special.py``).
"""

from __future__ import annotations

import math

import torch

__all__ = ["log_bessel_k"]


def log_bessel_k(nu, x: torch.Tensor, *, points: int = 801, half_width: float = 40.0) -> torch.Tensor:
    """``log K_nu(x)`` elementwise for ``x > 0`` and real ``nu`` (``K_{-nu} = K_nu``).

    Args:
        nu: order, a number or a tensor broadcastable with ``x``.
        x: argument ``(...)``, positive.
        points, half_width: the trapezoidal grid ``s in [-half_width, half_width]`` in units of the
            integrand's width (defaults give the stated accuracy down to nu = 0.5; the left tail
            decays like ``exp(-sqrt(nu) |s|)`` for small x).

    Returns:
        ``(...)``, the broadcast shape of ``nu`` and ``x``, in ``x``'s dtype.
    """
    x = torch.as_tensor(x)
    nu = torch.as_tensor(nu, dtype=x.dtype, device=x.device).abs()
    nu, x = torch.broadcast_tensors(nu, x)
    r = torch.sqrt(x * x + nu * nu)
    sigma = r.rsqrt()
    s = torch.linspace(-half_width, half_width, points, dtype=x.dtype, device=x.device)
    h = s[1] - s[0]
    u = sigma.unsqueeze(-1) * s  # (..., points)
    g = -2 * r.unsqueeze(-1) * torch.sinh(0.5 * u).pow(2) - nu.unsqueeze(-1) * (torch.sinh(u) - u)
    peak = -r + nu * torch.asinh(nu / x)
    return math.log(0.5) + peak + torch.log(sigma * h) + torch.logsumexp(g, -1)
