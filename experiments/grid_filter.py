"""An exact (to quadrature error) filter for a model with a one-dimensional state, on a fixed grid:
the reference log-likelihood that the particle filters' estimates are checked against (the
stochastic-volatility tests and ``experiments/benchmarks/bench_sv.py``).

The state's density is held at ``n_grid`` equally spaced points covering ``mean +- half_width``
standard deviations of the filters' prior (the stationary law, for stochastic volatility); the
transition is a dense ``(n_grid, n_grid)`` matrix of the model's own ``transition_log_prob``
(midpoint rule), and each step multiplies by it and by the model's ``measurement_log_prob`` (or
another measurement density), accumulating ``log p(z_t | z_{1:t-1})``. With a smooth transition
resolved by tens of points per standard deviation the quadrature error is far below any Monte
Carlo error (``n_grid`` 1000 and 4000 agree to ~1e-9 on the tests' series).
"""

from __future__ import annotations

from typing import Callable, Optional, Tuple

import torch


def grid_filter(
    model,
    observations: torch.Tensor,
    *,
    n_grid: int = 2000,
    half_width: float = 10.0,
    measurement_log_prob: Optional[Callable] = None,
) -> Tuple[float, torch.Tensor]:
    """The log-likelihood of one series and the filtered means.

    Args:
        model: a torchflow model with ``state_dim == 1`` (its ``initial_belief``,
            ``transition_log_prob`` and ``measurement_log_prob`` are used).
        observations: ``(T,)`` or ``(T, 1)``, in the model's observation space.
        n_grid: grid points.
        half_width: the grid spans the prior mean +- this many prior standard deviations.
        measurement_log_prob: ``(z (..., 1), x (..., 1)) -> (...)`` instead of the model's.

    Returns:
        ``(log p(z_{1:T}), filtered means (T,))`` in float64.
    """
    z = observations.reshape(-1, 1).to(torch.float64)
    meas = measurement_log_prob or model.measurement_log_prob
    with torch.no_grad():
        mean, cov = model.initial_belief(torch.zeros(1, 1, dtype=model.dtype, device=model.device))
        m0, s0 = float(mean.reshape(())), float(cov.reshape(()).sqrt())
        x = torch.linspace(m0 - half_width * s0, m0 + half_width * s0, n_grid, dtype=torch.float64)
        dx = float(x[1] - x[0])
        col = x.reshape(-1, 1)  # (n, 1) grid points as states
        # K[i, j] = p(x_j | x_i) dx: the transition from point i to point j (midpoint rule)
        logK = model.transition_log_prob(col.unsqueeze(0), col.unsqueeze(1)).to(torch.float64)  # (n, n)
        K = torch.exp(logK) * dx
        w = torch.exp(-0.5 * ((x - m0) / s0) ** 2)
        w = w / w.sum()  # the prior x_0, as weights on the grid
        log_lik, means = 0.0, torch.empty(z.shape[0], dtype=torch.float64)
        for t in range(z.shape[0]):  # a loop over time steps
            pred = w @ K  # (n,)
            ll = meas(z[t].expand(n_grid, 1), col).to(torch.float64)  # (n,)
            shift = ll.max()
            post = pred * torch.exp(ll - shift)
            c = post.sum()
            log_lik += float(torch.log(c) + shift)
            w = post / c
            means[t] = (w * x).sum()
    return log_lik, means


__all__ = ["grid_filter"]
