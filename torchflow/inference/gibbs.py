"""Particle Gibbs: conditional SMC with ancestor sampling, and a Metropolis-within-Gibbs parameter
step, on chains batched in the trial dimension."""

from __future__ import annotations

import math
import time
from typing import Callable, Dict, Optional, Union

import torch
from torch.distributions import Distribution

from torchflow.core import linalg, missing
from torchflow.core.checks import check_count
from torchflow.core.covariances import dense_prior, sample_prior
from torchflow.core.errors import ArgumentError, ArgumentTypeError
from torchflow.core.random import TrialStreams, uniform
from torchflow.core.resampling import gather_particles, multinomial
from torchflow.inference.params import ParameterSpace, RandomWalk, cpu_generator, one_series, per_trial_values, prior_of
from torchflow.inference.pmmh import PMMHResult
from torchflow.models.base import StateSpaceModel
from torchflow.smoothing.core import _categorical


def conditional_smc(
    model: StateSpaceModel,
    observations: torch.Tensor,
    mean: torch.Tensor,
    cov: torch.Tensor,
    reference: torch.Tensor,
    n_particles: int,
    generator,
) -> torch.Tensor:
    """One sweep of conditional SMC with ancestor sampling (Lindsten, Jordan & Schon 2014) for the
    bootstrap proposal: a new path whose law, given the ``reference`` path, leaves the smoothing
    distribution ``p(x_0:T | z_1:T)`` invariant.

    Particle ``N - 1`` is held at the reference; its ancestor at each step is drawn with weights
    ``w_(t-1)^i p(x*_t | x_(t-1)^i)``; the other particles are resampled (multinomial) and moved by
    the transition; all are weighed by the measurement density (of the observed coordinates, NaN:
    not observed). The new path is a final particle's ancestral line, drawn by its weight.

    Args:
        model: any model with the core contract (the transition density is needed).
        observations: ``(C, T, m)``, one series per chain.
        mean, cov: the prior of ``x_0``, ``(C, d)``, ``(C, d, d)``.
        reference: ``(C, T+1, d)`` the current path of each chain.
        n_particles: N (>= 2).
        generator: ``torch.Generator`` or :class:`~torchflow.core.random.TrialStreams` (one per chain).

    Returns:
        ``(C, T+1, d)`` the new paths.
    """
    N = check_count("n_particles", n_particles, minimum=2)
    C, T = observations.shape[:2]
    gaps = bool(torch.isnan(observations).any()) if observations.is_floating_point() else False
    x = sample_prior(mean, cov, N, generator)  # (C, N, d)
    x = torch.cat([x[:, : N - 1], reference[:, :1]], 1)
    parts, ancestors = [x], []
    lw = torch.zeros(C, N, dtype=x.dtype, device=x.device)
    with missing.observations_missing(gaps):
        for t in range(1, T + 1):
            a = multinomial(lw, generator, validate=False)  # (C, N): the first N - 1 are used
            ref = reference[:, t].unsqueeze(1)  # (C, 1, d)
            u = uniform((C,), dtype=x.dtype, device=x.device, generator=generator)
            a_ref = _categorical(lw + model.transition_log_prob(ref, x), u)  # ancestor sampling
            a = torch.cat([a[:, : N - 1], a_ref.unsqueeze(1)], 1)
            moved = model.sample_transition(gather_particles(x, a), generator)
            x = torch.cat([moved[:, : N - 1], ref], 1)
            lw = missing.measurement_log_prob(model, observations[:, t - 1].unsqueeze(1), x)
            parts.append(x)
            ancestors.append(a)
    k = _categorical(lw, uniform((C,), dtype=x.dtype, device=x.device, generator=generator)).unsqueeze(1)
    path = [gather_particles(parts[T], k)]
    for t in range(T, 0, -1):
        k = ancestors[t - 1].gather(1, k)
        path.append(gather_particles(parts[t - 1], k))
    return torch.cat(path[::-1], 1)  # (C, T+1, d)


def joint_log_density(
    model: StateSpaceModel, path: torch.Tensor, observations: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor
) -> torch.Tensor:
    """``log p(x_0:T, z_1:T)`` of ``path (C, T+1, d)`` and ``observations (C, T, m)`` (NaN: not
    observed) under the prior ``N(mean, cov)`` of ``x_0``: ``(C,)``."""
    x0, prev, nxt = path[:, 0], path[:, :-1], path[:, 1:]
    lp = linalg.mvn_log_prob(x0, mean, linalg.safe_cholesky(dense_prior(cov)))
    lp = lp + model.transition_log_prob(nxt, prev).sum(-1)
    gaps = bool(torch.isnan(observations).any()) if observations.is_floating_point() else False
    with missing.observations_missing(gaps):
        lp = lp + missing.measurement_log_prob(model, observations, nxt).sum(-1)
    return lp


def particle_gibbs(
    model: StateSpaceModel,
    observations: torch.Tensor,
    prior: Union[Callable, tuple],
    priors: Dict[str, Distribution],
    generator: Union[torch.Generator, int],
    *,
    n_particles: int = 100,
    n_chains: int = 4,
    n_iterations: int = 1000,
    n_adapt: int = 200,
    init: Optional[Dict[str, torch.Tensor]] = None,
    scale: float = 0.5,
    target_acceptance: Optional[float] = None,
) -> PMMHResult:
    """Sample the joint posterior of parameters and states by particle Gibbs with ancestor sampling,
    C chains batched in the trial dimension (the parameters in ``priors`` declared per-trial by the
    model, as for :func:`~torchflow.inference.pmmh`).

    Each iteration: (1) a Metropolis random-walk step on the unconstrained parameters, targeting
    ``p(theta | x_0:T, z_1:T)`` through :func:`joint_log_density` at the chain's current path (the
    scale adapted during the first ``n_adapt`` iterations, then fixed); (2) a new path by
    :func:`conditional_smc` at the chain's parameters. The first path of each chain is a sweep
    conditioned on a path drawn from the prior.

    Args:
        model: the model (core contract; the transition density is needed).
        observations, prior, priors, generator, n_chains, n_iterations, n_adapt, init, scale,
            target_acceptance: as :func:`~torchflow.inference.pmmh`.
        n_particles: N of the conditional SMC sweeps.

    Returns:
        :class:`~torchflow.inference.PMMHResult` (its ``log_likelihood`` holds the joint log-density
        ``log p(x_0:T, z_1:T | theta)`` of each kept draw; ``acceptance``: of the parameter steps).
    """
    if not isinstance(model, StateSpaceModel):
        raise ArgumentTypeError(f"model: expected a torchflow StateSpaceModel, got {type(model).__name__}")
    space = ParameterSpace(model, priors, n_chains)
    C, S = space.C, check_count("n_iterations", n_iterations)
    N = check_count("n_particles", n_particles, minimum=2)
    obs = one_series(observations, C).to(dtype=model.dtype, device=model.device)
    generator = cpu_generator(generator)
    walk = RandomWalk(C, space.dim, scale, n_adapt, target_acceptance, generator)
    base_seed = int(torch.randint(0, 2**40, (1,), generator=generator))
    u = space.initial(init, generator)

    def joint(u_: torch.Tensor, path: torch.Tensor) -> torch.Tensor:
        params = space.on_model(u_)
        mean, cov = prior_of(prior, params, C)
        with per_trial_values(model, params):
            return joint_log_density(model, path, obs, mean, cov).double().cpu()

    def sweep(u_: torch.Tensor, path: torch.Tensor, it: int) -> torch.Tensor:
        params = space.on_model(u_)
        mean, cov = prior_of(prior, params, C)
        with per_trial_values(model, params):
            return conditional_smc(model, obs, mean, cov, path, N, TrialStreams(base_seed + it, C, "particle_gibbs"))

    t0 = time.perf_counter()
    with torch.no_grad():
        params0 = space.on_model(u)
        mean0, cov0 = prior_of(prior, params0, C)
        with per_trial_values(model, params0):  # a path from the prior, then a conditional sweep
            streams = TrialStreams(base_seed, C, "particle_gibbs_start")
            x = linalg.sample_mvn(mean0, linalg.safe_cholesky(dense_prior(cov0)), (), streams)
            path = [x]
            for _ in range(obs.shape[1]):
                x = model.sample_transition(x, streams)
                path.append(x)
        path = sweep(u, torch.stack(path, 1), 0)
        lj = joint(u, path)
        kept_u, kept_lj, accepted = [], [], torch.zeros(C, dtype=torch.float64)
        for it in range(1, walk.n_adapt + S + 1):
            u_new = walk.propose(u)
            lp, lp_new = space.log_prior(u), space.log_prior(u_new)
            ok = torch.isfinite(lp_new)
            lj_new = joint(torch.where(ok.unsqueeze(-1), u_new, u), path)
            accept = walk.accept(torch.where(ok, (lp_new + lj_new) - (lp + lj), torch.full_like(lp, -math.inf)), it)
            u = torch.where(accept.unsqueeze(-1), u_new, u)
            walk.visit(u, it)
            path = sweep(u, path, it)
            lj = joint(u, path)
            if it > walk.n_adapt:
                accepted += accept.double()
                kept_u.append(u)
                kept_lj.append(lj)
    if not kept_u:
        raise ArgumentError("n_iterations: expected at least one kept draw")
    return PMMHResult.of(
        space, torch.stack(kept_u, 1), torch.stack(kept_lj, 1), accepted / S, walk, time.perf_counter() - t0
    )


__all__ = ["conditional_smc", "joint_log_density", "particle_gibbs"]
