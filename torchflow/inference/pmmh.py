"""Particle marginal Metropolis-Hastings on chains batched in the trial dimension."""

from __future__ import annotations

import contextlib
import math
import numbers
from dataclasses import dataclass
from typing import Callable, Dict, Optional, Union

import torch
from torch.distributions import Distribution

from torchflow.core.checks import check_count
from torchflow.core.errors import ArgumentError, ArgumentTypeError
from torchflow.core.random import CorrelatedStreams, TrialStreams
from torchflow.core.resampling import Resampler
from torchflow.filters.base import Filter
from torchflow.inference.diagnostics import effective_sample_size, rhat
from torchflow.inference.params import ParameterSpace, RandomWalk, cpu_generator, one_series, per_trial_values, prior_of


@dataclass
class PMMHResult:
    """Output of :func:`pmmh`.

    Attributes:
        samples: name -> ``(C, S, *shape)`` constrained draws of each parameter (after the
            adaptation iterations), C chains of S draws.
        log_likelihood: ``(C, S)`` the filter's log-likelihood estimate at each draw.
        acceptance: ``(C,)`` acceptance rate of each chain after adaptation.
        scale: ``(C,)`` the random-walk scale each chain ended its adaptation with.
        rhat: name -> ``shape`` split R-hat over the chains.
        ess: name -> ``shape`` effective sample size of all chains together.
        seconds: wall time of the sampling (adaptation included).
    """

    samples: Dict[str, torch.Tensor]
    log_likelihood: torch.Tensor
    acceptance: torch.Tensor
    scale: torch.Tensor
    rhat: Dict[str, torch.Tensor]
    ess: Dict[str, torch.Tensor]
    seconds: float

    @classmethod
    def of(
        cls, space, U: torch.Tensor, ll: torch.Tensor, acceptance: torch.Tensor, walk, seconds: float
    ) -> "PMMHResult":
        """The result from the kept unconstrained draws ``U (C, S, p)``, with the diagnostics."""
        samples = space.constrained(U)
        enough = U.shape[1] >= 4
        return cls(
            samples=samples,
            log_likelihood=ll,
            acceptance=acceptance,
            scale=walk.log_scale.exp(),
            rhat={n: rhat(v) for n, v in samples.items()} if enough else {},
            ess={n: effective_sample_size(v) for n, v in samples.items()} if enough else {},
            seconds=seconds,
        )


def pmmh(
    filt: Filter,
    observations: torch.Tensor,
    prior: Union[Callable, tuple],
    priors: Dict[str, Distribution],
    generator: Union[torch.Generator, int],
    *,
    n_chains: int = 4,
    n_iterations: int = 1000,
    n_adapt: int = 200,
    init: Optional[Dict[str, torch.Tensor]] = None,
    scale: float = 0.5,
    target_acceptance: Optional[float] = None,
    correlation: Optional[float] = None,
    allow_approximate_evidence: bool = False,
) -> PMMHResult:
    """Sample the posterior of model parameters given ``observations`` by particle marginal
    Metropolis-Hastings, the filter's log-evidence estimate standing in for the likelihood.

    All C chains advance together: each iteration proposes one value per chain, runs ``filt`` once
    on the C trials (trial c filtering the observations with chain c's proposed parameters, its own
    random stream) and accepts or rejects each chain on its own. The parameters named in ``priors``
    must be declared per-trial by the model (:attr:`per_trial_parameters`): they are passed as
    ``(C, *shape)`` tensors for the call (``torch.func.functional_call``; the model's own values are
    left as they were).

    Proposals are Gaussian random walks on the unconstrained values ``u = transform_to(support)^-1
    (theta)`` (``torch.distributions.transform_to``), with the prior density carried over by the
    transform's log-Jacobian. During the first ``n_adapt`` iterations each chain's scale is adapted
    (Robbins-Monro on its logarithm) towards ``target_acceptance`` (default 0.44 for one scalar
    parameter, 0.234 for more); the draws kept are those after it, with the scale fixed, so the
    kept chain is a valid Metropolis-Hastings chain whose invariant law is the exact posterior for
    any unbiased likelihood estimate (particle filters' evidence is).

    Args:
        filt: any filter whose ``log_evidence`` estimates ``p(z_1:T | theta)`` (particle filters;
            a Kalman filter on a linear-Gaussian model gives the exact-likelihood MCMC).
        observations: ``(T, m)`` or ``(1, T, m)``: one series (NaN: not observed).
        prior: the filter's prior of the initial state, ``(mean (d,), cov (d, d))``, or a callable
            ``params -> (mean (C, d), cov (C, d, d))`` when the prior depends on the parameters (a
            stationary law); ``params`` maps each name to its ``(C, ...)`` values.
        priors: name -> ``torch.distributions.Distribution`` of the parameter's constrained value
            (its ``event_shape``/``batch_shape`` give the parameter's shape).
        generator: a seed (int) or a ``torch.Generator``: the chains' proposals and accept/reject
            draws; the filter's particles come from per-chain :class:`~torchflow.core.random.TrialStreams`
            seeded from it, one fresh stream per iteration.
        n_chains: C.
        n_iterations: draws kept per chain (after adaptation).
        n_adapt: adaptation iterations (discarded).
        init: name -> starting value (constrained; one for all chains, or ``(C, ...)``); default:
            a draw from each prior per chain.
        scale: initial random-walk standard deviation in the unconstrained space.
        target_acceptance: the adaptation's target.
        correlation: ``None`` (default): a fresh stream per iteration. A number ``rho`` in
            ``[0, 1)``: correlated pseudo-marginal MCMC (Deligiannidis, Doucet & Pitt 2018). Each
            chain keeps the standard normals ``u`` its filter run drew
            (:class:`~torchflow.core.random.CorrelatedStreams`; uniforms are ``Phi(u)``); an iteration
            proposes ``(theta', u')`` with ``u' = rho u + sqrt(1 - rho^2) eps`` and accepts or
            rejects both. The chain targets the same posterior for any ``rho`` (the move leaves
            ``u ~ N(0, I)`` invariant); with ``rho`` near 1 the two log-likelihood estimates are
            strongly correlated, so their difference has a small variance and the chain mixes with
            far fewer particles. For the call, a particle filter's resampler resamples at every
            step (``ess_threshold = 1``: the adaptive trigger would jump as ``u`` moves) and sorts
            the particles before resampling (``Resampler.sort``: along a Hilbert curve unless it
            was set), so that the ancestors move continuously with ``u`` (exactly in d = 1;
            approximately in higher dimensions, where the gain is smaller).

        allow_approximate_evidence: run with a filter whose log-evidence is only a Gaussian
            approximation (``estimates_evidence = False``: the ensemble Kalman filters, the
            Gaussian-sum and unweighted flow filters, the lag-one flow, the KPFF), refused by
            default: the chain then samples an approximate posterior, not the exact one.

    Returns:
        :class:`PMMHResult`.
    """
    import time

    if not isinstance(filt, Filter):
        raise ArgumentTypeError(f"filt: expected a torchflow Filter, got {type(filt).__name__}")
    if not filt.estimates_evidence and allow_approximate_evidence is not True:
        raise ArgumentError(
            f"filt: pmmh needs a log-evidence that estimates the likelihood without bias (a weighted "
            f"particle filter; the Kalman filter, or the EKF/UKF on a linear-Gaussian model: exact), got "
            f"{type(filt).__name__}, whose log-evidence is a Gaussian approximation; pass "
            f"allow_approximate_evidence=True to sample the approximate posterior it gives"
        )
    model = filt.model
    space = ParameterSpace(model, priors, n_chains)
    C, S = space.C, check_count("n_iterations", n_iterations)
    obs = one_series(observations, C)
    generator = cpu_generator(generator)
    walk = RandomWalk(C, space.dim, scale, n_adapt, target_acceptance, generator)
    base_seed = int(torch.randint(0, 2**40, (1,), generator=generator))
    u = space.initial(init, generator)

    rho = check_correlation(correlation, filt)
    aux = None if rho is None else CorrelatedStreams(base_seed, C, filt.stream_name)  # the chains' u

    def streams_at(it: int):
        if rho is None:
            return TrialStreams(base_seed + it, C, filt.stream_name)
        return aux.rewind() if it == 0 else aux.crank_nicolson(rho, base_seed + it)

    def log_likelihood(u_: torch.Tensor, streams) -> torch.Tensor:
        params = space.on_model(u_)
        mean, cov = prior_of(prior, params)
        with torch.no_grad(), per_trial_values(model, params):
            res = filt(obs, mean, cov, streams)
        return res.log_evidence.double().cpu()

    t0 = time.perf_counter()
    with sorted_resampling(filt, rho is not None):
        lp, ll = space.log_prior(u), log_likelihood(u, streams_at(0))
        kept_u, kept_ll, accepted = [], [], torch.zeros(C, dtype=torch.float64)
        for it in range(1, walk.n_adapt + S + 1):
            u_new = walk.propose(u)
            lp_new = space.log_prior(u_new)
            ok = torch.isfinite(lp_new)
            streams = streams_at(it)
            ll_new = log_likelihood(torch.where(ok.unsqueeze(-1), u_new, u), streams)
            accept = walk.accept(torch.where(ok, (lp_new + ll_new) - (lp + ll), torch.full_like(lp, -math.inf)), it)
            u = torch.where(accept.unsqueeze(-1), u_new, u)
            if rho is not None:
                aux = streams.where(accept, aux)
            walk.visit(u, it)
            lp, ll = torch.where(accept, lp_new, lp), torch.where(accept, ll_new, ll)
            if it > walk.n_adapt:
                accepted += accept.double()
                kept_u.append(u)
                kept_ll.append(ll)
    return PMMHResult.of(
        space, torch.stack(kept_u, 1), torch.stack(kept_ll, 1), accepted / S, walk, time.perf_counter() - t0
    )


def check_correlation(correlation, filt: Filter) -> Optional[float]:
    """``correlation`` as a float in ``[0, 1)`` (``None`` passes); refused for a filter that draws
    no random numbers (its likelihood is exact: nothing to correlate)."""
    if correlation is None:
        return None
    if isinstance(correlation, bool) or not isinstance(correlation, numbers.Real) or not 0 <= correlation < 1:
        raise ArgumentError(
            f"correlation: expected None or a number rho in [0, 1) (the Crank-Nicolson "
            f"correlation of the auxiliary normals; 0.99 is typical), got {correlation!r}"
        )
    if not filt.uses_randomness:
        raise ArgumentError(
            f"correlation: {filt.name} draws no random numbers (its log-likelihood is exact), so "
            "there is nothing to correlate; leave correlation=None"
        )
    return float(correlation)


@contextlib.contextmanager
def sorted_resampling(filt: Filter, on: bool):
    """Within the block, ``filt``'s resampler (if it has one) resamples at every step and sorts the
    particles (along a Hilbert curve, unless its ``sort`` is set) before resampling;
    its settings are put back afterwards."""
    resampler = getattr(filt, "resampler", None)
    if not on or not isinstance(resampler, Resampler):
        yield
        return
    saved = resampler.sort, resampler.ess_threshold
    resampler.sort, resampler.ess_threshold = saved[0] or "hilbert", 1.0
    try:
        yield
    finally:
        resampler.sort, resampler.ess_threshold = saved
