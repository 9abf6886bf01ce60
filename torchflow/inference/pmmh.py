"""Particle marginal Metropolis-Hastings on chains batched in the trial dimension."""
from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from typing import Callable, Dict, Optional, Union

import torch
from torch.distributions import Distribution, transform_to

from .._checks import check_count
from ..errors import ArgumentError, ArgumentTypeError
from ..filters.base import Filter
from ..random import TrialStreams, check_generator
from .diagnostics import effective_sample_size, rhat


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


@contextlib.contextmanager
def per_trial_values(model, values: Dict[str, torch.Tensor]):
    """Within the block, ``model``'s parameters or buffers named in ``values`` hold those tensors
    (one value per trial, ``(B, ...)``); the model's own are put back afterwards, also on error. A
    constrained (parametrised) parameter takes its constrained value here."""
    from torch.nn.utils import parametrize

    saved = {}
    try:
        for name, value in values.items():
            if parametrize.is_parametrized(model, name):
                raise ArgumentError(f"{name}: a constrained learnable parameter of {type(model).__name__}; sample "
                                    "the posterior of a model built with it as a buffer (learnable=False)")
            table = model._parameters if name in model._parameters else model._buffers
            if name not in table:
                raise ArgumentError(f"{name}: {type(model).__name__} has no parameter or buffer of that name")
            saved[name] = (table, table[name])
            table[name] = value
        yield model
    finally:
        for name, (table, value) in saved.items():
            table[name] = value


def _per_trial_names(model) -> tuple:
    return tuple(getattr(model, "per_trial_parameters", ()) or ())


def pmmh(filt: Filter, observations: torch.Tensor, prior: Union[Callable, tuple], priors: Dict[str, Distribution],
         generator: Union[torch.Generator, int], *, n_chains: int = 4, n_iterations: int = 1000, n_adapt: int = 200,
         init: Optional[Dict[str, torch.Tensor]] = None, scale: float = 0.5,
         target_acceptance: Optional[float] = None) -> PMMHResult:
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
            draws; the filter's particles come from per-chain :class:`~torchflow.random.TrialStreams`
            seeded from it, one fresh stream per iteration.
        n_chains: C.
        n_iterations: draws kept per chain (after adaptation).
        n_adapt: adaptation iterations (discarded).
        init: name -> starting value (constrained; one for all chains, or ``(C, ...)``); default:
            a draw from each prior per chain.
        scale: initial random-walk standard deviation in the unconstrained space.
        target_acceptance: the adaptation's target.

    Returns:
        :class:`PMMHResult`.
    """
    import time

    if not isinstance(filt, Filter):
        raise ArgumentTypeError(f"filt: expected a torchflow Filter, got {type(filt).__name__}")
    model = filt.model
    if not isinstance(priors, dict) or not priors:
        raise ArgumentError("priors: expected a dict name -> torch.distributions.Distribution (at least one)")
    declared = _per_trial_names(model)
    for name, dist in priors.items():
        if not isinstance(dist, Distribution):
            raise ArgumentTypeError(f"priors[{name!r}]: expected a torch.distributions.Distribution, "
                                    f"got {type(dist).__name__}")
        if name not in declared:
            raise ArgumentError(f"priors: {type(model).__name__} does not declare {name!r} as a per-trial parameter "
                                f"(it declares {list(declared)}): a chain's value must reach its own trial")
    C = check_count("n_chains", n_chains)
    S = check_count("n_iterations", n_iterations)
    n_adapt = int(n_adapt)
    if n_adapt < 0:
        raise ArgumentError(f"n_adapt: expected an integer >= 0, got {n_adapt}")
    if not (isinstance(scale, (int, float)) and scale > 0):
        raise ArgumentError(f"scale: expected a number > 0, got {scale!r}")
    obs = observations if observations.dim() == 3 else observations.unsqueeze(0)
    if obs.dim() != 3 or obs.shape[0] != 1:
        raise ArgumentError(f"observations: expected one series (T, m) or (1, T, m), got {tuple(observations.shape)}")
    obs = obs.expand(C, -1, -1)
    dtype, device = model.dtype, model.device
    if isinstance(generator, int):
        generator = torch.Generator().manual_seed(generator)
    check_generator(generator, "generator")
    if generator.device.type != "cpu":
        raise ArgumentError("generator: expected a CPU torch.Generator (the chains' own draws; the filter's "
                            "streams are made on the model's device)")
    base_seed = int(torch.randint(0, 2**40, (1,), generator=generator))

    names = list(priors)
    transforms = {n: transform_to(priors[n].support) for n in names}
    sizes = {n: int(math.prod(priors[n].batch_shape + priors[n].event_shape)) for n in names}
    shapes = {n: tuple(priors[n].batch_shape + priors[n].event_shape) for n in names}

    def constrained(u: torch.Tensor) -> Dict[str, torch.Tensor]:
        out, i = {}, 0
        for n in names:
            out[n] = transforms[n](u[:, i:i + sizes[n]].reshape(C, *shapes[n]))
            i += sizes[n]
        return out

    def log_prior(u: torch.Tensor) -> torch.Tensor:
        total, i = torch.zeros(C, dtype=torch.float64), 0
        for n in names:
            uu = u[:, i:i + sizes[n]].reshape(C, *shapes[n])
            theta = transforms[n](uu)
            lp = priors[n].log_prob(theta) + transforms[n].log_abs_det_jacobian(uu, theta)
            total = total + lp.reshape(C, -1).sum(-1)
            i += sizes[n]
        return total

    if init is None:  # torch.distributions draw from torch's global generator: seeded from ours, then restored
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(torch.randint(0, 2**40, (1,), generator=generator)))
            start = {n: priors[n].sample((C,)) for n in names}
    else:
        missing_init = [n for n in names if n not in init]
        if missing_init:
            raise ArgumentError(f"init: expected a starting value for every parameter in priors, missing {missing_init}")
        start = {n: torch.as_tensor(init[n], dtype=torch.float64).expand(C, *shapes[n]) for n in names}
    u = torch.cat([transforms[n].inv(start[n].double()).reshape(C, -1) for n in names], 1)

    def log_likelihood(u_: torch.Tensor, it: int) -> torch.Tensor:
        params = {n: v.to(dtype=dtype, device=device) for n, v in constrained(u_).items()}
        if callable(prior):
            mean, cov = prior(params)
        else:
            mean, cov = prior
        streams = TrialStreams(base_seed + it, C, filt.stream_name)
        with torch.no_grad(), per_trial_values(model, params):
            res = filt(obs, mean, cov, streams)
        return res.log_evidence.double().cpu()

    t0 = time.perf_counter()
    lp, ll = log_prior(u), log_likelihood(u, 0)
    log_scale = torch.full((C,), math.log(scale), dtype=torch.float64)
    target = target_acceptance if target_acceptance is not None else (0.44 if u.shape[1] == 1 else 0.234)
    kept_u, kept_ll, accepted = [], [], torch.zeros(C, dtype=torch.float64)
    for it in range(1, n_adapt + S + 1):
        step = torch.randn(u.shape, generator=generator, dtype=torch.float64) * log_scale.exp().unsqueeze(-1)
        u_new = u + step
        lp_new = log_prior(u_new)
        ok = torch.isfinite(lp_new)
        ll_new = log_likelihood(torch.where(ok.unsqueeze(-1), u_new, u), it)
        log_alpha = torch.where(ok, (lp_new + ll_new) - (lp + ll), torch.full_like(lp, -math.inf))
        log_alpha = torch.nan_to_num(log_alpha, nan=-math.inf)
        accept = torch.log(torch.rand(C, generator=generator, dtype=torch.float64)) < log_alpha
        u = torch.where(accept.unsqueeze(-1), u_new, u)
        lp, ll = torch.where(accept, lp_new, lp), torch.where(accept, ll_new, ll)
        if it <= n_adapt:  # Robbins-Monro on log(scale), then fixed
            log_scale = log_scale + (accept.double() - target) / it ** 0.6
        else:
            accepted += accept.double()
            kept_u.append(u)
            kept_ll.append(ll)
    seconds = time.perf_counter() - t0
    U = torch.stack(kept_u, 1)  # (C, S, p)
    samples, i = {}, 0
    for n in names:
        uu = U[..., i:i + sizes[n]].reshape(C, S, *shapes[n])
        samples[n] = transforms[n](uu)
        i += sizes[n]
    diag_ok = S >= 4
    return PMMHResult(samples=samples, log_likelihood=torch.stack(kept_ll, 1), acceptance=accepted / S,
                      scale=log_scale.exp(),
                      rhat={n: rhat(v) for n, v in samples.items()} if diag_ok and C >= 1 else {},
                      ess={n: effective_sample_size(v) for n, v in samples.items()} if diag_ok else {},
                      seconds=seconds)


__all__ = ["pmmh", "PMMHResult", "per_trial_values"]
