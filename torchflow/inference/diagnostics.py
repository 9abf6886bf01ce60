"""Convergence diagnostics of MCMC chains: split R-hat and the effective sample size.

Both take draws ``(C, S, ...)`` (C chains of S draws each, any trailing shape) and reduce over the
first two dimensions. The formulas are the standard ones of Gelman et al. (Bayesian Data Analysis,
3rd ed., section 11.4-11.5): split chains in halves, compare within- and between-chain variances;
the effective sample size sums the chains' combined autocorrelations up to Geyer's initial
positive sequence.
"""

from __future__ import annotations

import torch

from torchflow.core.errors import ArgumentError


def _check(draws: torch.Tensor, who: str) -> torch.Tensor:
    if not isinstance(draws, torch.Tensor) or draws.dim() < 2 or draws.shape[1] < 4:
        shape = tuple(draws.shape) if isinstance(draws, torch.Tensor) else type(draws).__name__
        raise ArgumentError(f"{who}: expected draws (C, S, ...) with S >= 4 draws per chain, got {shape}")
    return draws.double()


def _split(draws: torch.Tensor) -> torch.Tensor:
    """Each chain cut in two halves: ``(C, S, ...)`` -> ``(2C, S // 2, ...)``."""
    half = draws.shape[1] // 2
    return torch.cat([draws[:, :half], draws[:, draws.shape[1] - half :]], 0)


def rhat(draws: torch.Tensor) -> torch.Tensor:
    """Split R-hat of ``draws (C, S, ...)`` -> ``(...)``: about 1 for chains that mix; above 1.01
    or so, run longer."""
    x = _split(_check(draws, "rhat"))
    n = x.shape[1]
    W = x.var(1).mean(0)  # within-chain variance
    B = n * x.mean(1).var(0)  # between-chain variance
    var_plus = (n - 1) / n * W + B / n
    return (var_plus / W).sqrt()


def effective_sample_size(draws: torch.Tensor) -> torch.Tensor:
    """Effective sample size of ``draws (C, S, ...)`` -> ``(...)`` (all chains together), from the
    split chains' autocorrelation (FFT), summed in pairs while the pairs stay positive; at most
    the number of draws (``C * S``, an even S per chain)."""
    x = _split(_check(draws, "effective_sample_size"))
    m, n = x.shape[:2]
    xc = x - x.mean(1, keepdim=True)
    size = 1 << (2 * n - 1).bit_length()
    f = torch.fft.rfft(xc, n=size, dim=1)
    acov = torch.fft.irfft(f * f.conj(), n=size, dim=1)[:, :n] / n  # (m, n, ...)
    W = x.var(1).mean(0)
    var_plus = (n - 1) / n * W + x.mean(1).var(0)
    rho = 1 - (W - acov.mean(0)) / var_plus  # (n, ...): rho_0 = 1
    # Geyer: sum rho_t in pairs (rho_2k + rho_2k+1) up to the first non-positive pair
    pairs = rho[: (n // 2) * 2].reshape(n // 2, 2, *rho.shape[1:]).sum(1)
    positive = torch.cumprod((pairs > 0).to(pairs.dtype), 0)
    tau = -1 + 2 * (pairs * positive).sum(0)
    if not isinstance(tau, torch.Tensor) or tau.dim() == 0:
        tau = torch.as_tensor(tau)
    # at most the number of draws: a Metropolis-Hastings chain's draws are at best independent, and
    # with few draws the autocorrelation sum is noise that can put the estimate far above them
    return (m * n / tau.clamp(min=1 / (m * n))).clamp(max=m * n)


__all__ = ["rhat", "effective_sample_size"]
