"""The exact maximum-likelihood estimate of the stochastic-volatility parameters on the GBP/USD
returns (:mod:`experiments.data.gbpusd`), beside what ``torchflow-learn`` reached from a wrong start.

The exact log-likelihood is the grid filter's (:func:`experiments.grid_filter.grid_filter`), maximised
over ``(mu, rho, sigma)`` by Nelder-Mead (scipy) on ``(mu, atanh(rho), log(sigma))``; the learnt values
are read from a ``torchflow-learn`` run's ``learn.csv`` (its last epoch) and their exact
log-likelihood is evaluated too::

    python -m experiments.data.gbpusd gbpusd_returns.csv
    torchflow-learn model=stochastic_volatility data=gbpusd_returns.csv filter=bpf n_particles=500 trials=4 \\
        epochs=300 'learn=[mu,rho,sigma]' '~start' '+start={mu: -0.5, rho: 0.8, sigma: 0.4}' reference=null
    python -m experiments.sv_mle <that run's folder>/learn.csv
"""

from __future__ import annotations

import csv
import math
import sys

import numpy as np
import torch

from torchflow.models import StochasticVolatility

from .data.gbpusd import returns
from .grid_filter import grid_filter


def exact_log_lik(y: torch.Tensor, mu: float, rho: float, sigma: float, n_grid: int = 1000) -> float:
    """The grid filter's log-likelihood of the returns ``y (T,)`` at the parameters."""
    return grid_filter(StochasticVolatility(mu=mu, rho=rho, sigma=sigma), y, n_grid=n_grid)[0]


def exact_mle(y: torch.Tensor, start=(-1.02, 0.9702, 0.178), n_grid: int = 600):
    """Nelder-Mead on ``(mu, atanh(rho), log(sigma))``; returns ``(mu, rho, sigma)`` and its log-likelihood
    on a 1000-point grid."""
    from scipy.optimize import minimize

    def nll(v):
        mu, rho, sigma = v[0], math.tanh(v[1]), math.exp(v[2])
        return -exact_log_lik(y, mu, rho, sigma, n_grid)

    v0 = np.array([start[0], math.atanh(start[1]), math.log(start[2])])
    res = minimize(nll, v0, method="Nelder-Mead", options=dict(xatol=1e-4, fatol=1e-4, maxiter=2000))
    mu, rho, sigma = res.x[0], math.tanh(res.x[1]), math.exp(res.x[2])
    return (mu, rho, sigma), exact_log_lik(y, mu, rho, sigma)


def learnt(path: str):
    """The start and final ``(mu, rho, sigma)`` and the epochs of a ``torchflow-learn`` run's
    ``learn.csv`` (one row per parameter: ``parameter, start, final, epochs``)."""
    rows = {r["parameter"]: r for r in csv.DictReader(open(path))}
    pick = lambda key: tuple(float(rows[k][key]) for k in ("mu", "rho", "sigma"))
    return pick("start"), pick("final"), int(rows["mu"]["epochs"])


def main(argv):
    torch.set_num_threads(1)
    y = torch.tensor(returns(), dtype=torch.float64)
    (mu, rho, sigma), ll = exact_mle(y)
    print(f"exact MLE: mu {mu:.4f}, rho {rho:.4f}, sigma {sigma:.4f}; log-likelihood {ll:.4f}")
    if argv:
        first, last, epochs = learnt(argv[0])
        for label, p in (("learn, start", first), (f"learn, after {epochs} epochs", last)):
            print(
                f"{label}: mu {p[0]:.4f}, rho {p[1]:.4f}, sigma {p[2]:.4f}; exact log-likelihood "
                f"{exact_log_lik(y, *p):.4f}"
            )


if __name__ == "__main__":
    main(sys.argv[1:])
