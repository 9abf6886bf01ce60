"""The smoothers behind :func:`torchflow.smoothing.smooth` (package docstring)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional

import torch

from torchflow.core import linalg, missing
from torchflow.core import resampling as _resampling
from torchflow.core.checks import check_choice, check_count
from torchflow.core.errors import ArgumentError, ArgumentTypeError
from torchflow.core.random import check_generator, uniform
from torchflow.core.resampling import gather_particles
from torchflow.filters.base import ANCESTOR, Filter, FilterResult, GaussianState, ParticleFilter, _Trace
from torchflow.filters.kalman import _GaussianFilter

#: the methods of :func:`smooth`
SMOOTHERS = ("auto", "rts", "ffbsi", "genealogy")


@dataclass
class SmoothingResult:
    """Output of :func:`smooth`.

    Attributes:
        means: ``(B, T+1, d)`` smoothed means ``E[x_t | z_1:T]``, index 0 the initial state.
        covariances: ``(B, T+1, d, d)`` smoothed covariances (``"rts"``), else ``None``.
        paths: ``(B, M, T+1, d)`` draws of the smoothing law (particle smoothers), else ``None``.
        filtered: the forward pass's :class:`~torchflow.filters.FilterResult` (filtered
            estimates, log-evidence, ESS, and the filtering law's standard deviation of each
            coordinate ``std (B, T, d)``).
        method: the smoother that ran (``"rts"``, ``"ffbsi"`` or ``"genealogy"``).
    """

    means: torch.Tensor
    covariances: Optional[torch.Tensor]
    paths: Optional[torch.Tensor]
    filtered: FilterResult
    method: str


def smooth(
    filt: Filter,
    observations: torch.Tensor,
    mean: torch.Tensor,
    cov: torch.Tensor,
    generator=None,
    *,
    method: str = "auto",
    n_paths: int = 100,
    n_particles: Optional[int] = None,
    path_chunk: Optional[int] = None,
) -> SmoothingResult:
    """Smooth ``observations (B, T, m)`` (NaN: not observed) from the prior ``N(mean, cov)`` with
    ``filt``'s forward pass.

    Args:
        filt: a Kalman-family filter (``"rts"``) or a :class:`~torchflow.filters.ParticleFilter`
            (``"ffbsi"``, ``"genealogy"``).
        observations, mean, cov, generator, n_particles: as :meth:`Filter.forward
            <torchflow.filters.Filter.forward>`; the particle smoothers also draw their paths from
            ``generator`` (a ``TrialStreams`` keeps each trial's numbers independent of the batch).
        method: ``"auto"`` (``"rts"`` for the Kalman family, ``"ffbsi"`` for particle filters),
            ``"rts"``, ``"ffbsi"`` or ``"genealogy"``.
        n_paths: M, paths drawn by the particle smoothers.
        path_chunk: backward simulation in blocks of this many paths (bounds its ``(B, M, N, d)``
            intermediates; ``None``: about 32 MB of them per block). The numbers do not depend on it.

    Returns:
        :class:`SmoothingResult`.

    Example::

        result = smooth(KalmanFilter(model), observations, mean, cov)             # exact RTS
        result = smooth(BootstrapParticleFilter(model), observations, mean, cov,
                        torch.Generator().manual_seed(0), n_paths=200)             # FFBSi
    """
    method = smoothing_method(filt, method)
    n_paths = check_count("n_paths", n_paths)
    path_chunk = None if path_chunk is None else check_count("path_chunk", path_chunk, hint=" or None")
    with torch.no_grad():
        obs, mean, cov, gaps = _checked(filt, observations, mean, cov, generator)
        with missing.observations_missing(gaps):
            if method == "rts":
                return _rts(filt, obs, mean, cov)
            return _particles(filt, obs, mean, cov, generator, method, n_paths, n_particles, path_chunk)


def smoothing_method(filt: Filter, method: str = "auto") -> str:
    """The smoother :func:`smooth` runs for ``filt`` with ``method`` (``"auto"``: ``"rts"`` for the
    Kalman family, ``"ffbsi"`` for particle filters); an :class:`~torchflow.core.errors.ArgumentError`
    naming ``method`` when the filter cannot be smoothed that way."""
    if not isinstance(filt, Filter):
        raise ArgumentTypeError(f"filt: expected a torchflow Filter, got {type(filt).__name__}")
    check_choice("method", method, SMOOTHERS)
    gaussian = isinstance(filt, _GaussianFilter)
    particle = isinstance(filt, ParticleFilter) and "init" in filt.kept
    if not gaussian and not particle:  # ensembles, flows, refitting particle filters: no belief to smooth
        why = (
            "it refits its belief (a Gaussian or Gaussian sum) at each step instead of keeping weighted particles"
            if isinstance(filt, ParticleFilter)
            else "the ensemble filters and unweighted flows keep neither a Gaussian belief nor weighted particles"
        )
        raise ArgumentError(
            f"method: no smoother takes {filt.name} ({type(filt).__name__}): 'rts' smooths the Kalman family "
            f"(kf, ekf, ukf) and 'ffbsi'/'genealogy' a particle filter whose belief is weighted particles "
            f"(bpf, the PF-PFs, gpfis, upf); {why}. Smooth one of those filters instead"
        )
    if method == "auto":
        method = "rts" if gaussian else "ffbsi"
    if method == "rts" and not gaussian:
        raise ArgumentError(
            f"method: 'rts' smooths the Kalman family (KalmanFilter, ExtendedKalmanFilter, "
            f"UnscentedKalmanFilter), got {filt.name}; a particle filter takes 'ffbsi' or 'genealogy'"
        )
    if method in ("ffbsi", "genealogy") and not particle:
        raise ArgumentError(
            f"method: {method!r} smooths a particle filter whose belief is weighted particles "
            f"(a ParticleFilter: bootstrap, PF-PF, GPFIS, UPF), got {filt.name}"
            + ("; the Kalman family takes 'rts'" if gaussian else "")
        )
    if method == "genealogy" and filt.resampler.gradient == "ot":
        raise ArgumentError(
            f"method: 'genealogy' follows ancestor indices, which {filt.name}'s optimal-transport "
            "resampling (resampling_gradient='ot') does not have; use 'ffbsi'"
        )
    if method == "ffbsi" and filt.model.structure.gaussian_transition:
        filt.require_definite(
            "transition",
            "FFBSi weighs every path backwards by the transition density p(x_k | x_(k-1)), which a singular "
            "transition covariance (deterministic dynamics) does not have. Give the model a positive definite "
            "transition noise, or use method='genealogy' (the particle filter's ancestral lines)",
        )
    return method


def rts(filt, observations, mean, cov) -> SmoothingResult:
    """:func:`smooth` with ``method="rts"``."""
    return smooth(filt, observations, mean, cov, method="rts")


def ffbsi(filt, observations, mean, cov, generator, **kwargs) -> SmoothingResult:
    """:func:`smooth` with ``method="ffbsi"``."""
    return smooth(filt, observations, mean, cov, generator, method="ffbsi", **kwargs)


def genealogy(filt, observations, mean, cov, generator, **kwargs) -> SmoothingResult:
    """:func:`smooth` with ``method="genealogy"``."""
    return smooth(filt, observations, mean, cov, generator, method="genealogy", **kwargs)


def _checked(filt, observations, mean, cov, generator):
    """The checks of :meth:`Filter.forward` (shapes, dtypes, the prior, the generator, the model)
    and whether the observations have gaps."""
    if filt.validate:
        filt.model.check_observations(observations)
        filt.check_model()
    mean, cov = filt.check_prior(mean, cov, observations.shape[0])
    if filt.uses_randomness:
        check_generator(generator, f"{filt.name}: generator", observations.shape[0])
    return observations, mean, cov, filt.check_missing(observations)


def _finish(filt, trace: _Trace, state) -> FilterResult:
    filt._check_trace(trace, warn=True)  # the forward pass's non-finite contract, one host read
    return trace.result(state)


# ---- Rauch-Tung-Striebel ---------------------------------------------------------------------------


def _predict(filt, m: torch.Tensor, P: torch.Tensor):
    """Predicted mean and covariance of step t+1 and the cross-covariance ``D = Cov(x_t, x_t+1)``
    ``(B, d, d)`` under the filter's Gaussian approximation (the Jacobian's for the KF/EKF, the
    sigma points' for the UKF)."""
    model = filt.model
    ut = getattr(filt, "unscented", None)
    if ut is not None:
        X = ut.sigma_points(m, P)
        m_pred, DXp = ut.moments(model.transition_mean(X))
        P_pred = linalg.symmetrize(ut.cross(DXp, DXp) + model.transition_cov(m_pred))
        return m_pred, P_pred, ut.cross(X - m.unsqueeze(-2), DXp)
    G = model.transition_matrix() if model.structure.linear_dynamics else model.transition_jacobian(m)
    m_pred, P_pred = filt.predict(m, P)
    return m_pred, P_pred, P @ G.transpose(-1, -2)


def _rts(filt, obs, mean, cov) -> SmoothingResult:
    B, T = obs.shape[:2]
    state = filt.init(mean, cov)
    trace = _Trace(B, obs.device, False, False, std=True)
    filtered = [(state.mean, state.cov)]
    predicted = []
    for t in range(T):
        m_pred, P_pred, D = _predict(filt, state.mean, state.cov)
        m, P, ll = filt.update(m_pred, P_pred, obs[:, t])
        state = GaussianState(m, P, ll, t + 1)
        trace.add(state, t)
        filtered.append((m, P))
        predicted.append((m_pred, P_pred, D))
    result = _finish(filt, trace, state)
    ms, Ps = filtered[-1]
    means, covs = [ms], [Ps]
    for t in range(T - 1, -1, -1):
        m, P = filtered[t]
        m_pred, P_pred, D = predicted[t]
        C = linalg.chol_solve(linalg.safe_cholesky(P_pred), D.transpose(-1, -2)).transpose(-1, -2)  # D P_pred^-1
        ms = m + linalg.matvec(C, ms - m_pred)
        Ps = linalg.symmetrize(P + C @ (Ps - P_pred) @ C.transpose(-1, -2))
        means.append(ms)
        covs.append(Ps)
    return SmoothingResult(torch.stack(means[::-1], 1), torch.stack(covs[::-1], 1), None, result, "rts")


# ---- particle smoothers --------------------------------------------------------------------------


def _categorical(log_w: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """One index per row of ``log_w (..., N)`` at the uniform ``u (...)``: the resamplers' inverse
    CDF (:mod:`torchflow.core.resampling`: a zero weight is never drawn), one position per row."""
    N = log_w.shape[-1]
    rows = log_w.reshape(-1, N)
    cdf = _resampling._scaled_cdf(_resampling._unnormalized_weights(rows))
    pos = _resampling._below(u.reshape(-1, 1).to(cdf.dtype) * N, cdf.new_tensor(float(N)))
    return _resampling._invert_cdf(cdf, pos).reshape(u.shape)


def _particles(filt, obs, mean, cov, generator, method, M, n_particles, path_chunk) -> SmoothingResult:
    B, T = obs.shape[:2]
    state = filt.init(mean, cov, n_particles, generator)
    N, d = state.particles.shape[1:]
    if method == "genealogy":  # each step then keeps its ancestor indices (filters.base.ancestor_extras)
        state.extras = {**state.extras, ANCESTOR: torch.arange(N, device=obs.device).expand(B, N)}
    trace = _Trace(B, obs.device, False, False, std=True)
    parts: List[torch.Tensor] = [state.particles]
    lws: List[torch.Tensor] = [state.log_weights]
    ancestors: List[torch.Tensor] = []
    for t in range(T):
        state = filt.step(state, obs[:, t], generator)
        trace.add(state, t)
        parts.append(state.particles)
        lws.append(state.log_weights)
        if method == "genealogy":
            ancestors.append(state.extras[ANCESTOR])
    result = _finish(filt, trace, state)
    if method == "genealogy":
        return _genealogy(parts, lws, ancestors, M, generator, result)
    return _ffbsi(filt.model, parts, lws, M, generator, result, path_chunk or max(1, 2**22 // max(1, B * N * d)))


def _genealogy(parts, lws, ancestors, M, generator, result) -> SmoothingResult:
    """The final particles' ancestral lines: ``i_(t-1) = a_t[i_t]`` (the particle after step t's
    resampling descends, through the proposal, from the same index before it)."""
    B, N, _ = parts[-1].shape
    T = len(ancestors)
    u = uniform((B, M), dtype=parts[-1].dtype, device=parts[-1].device, generator=generator)
    idx = _categorical(lws[-1].unsqueeze(1).expand(B, M, N), u)  # (B, M) drawn by the final weights
    line = torch.arange(N, device=idx.device).expand(B, N)  # every final particle's line, for the means
    w = lws[-1].exp()
    paths, means = [gather_particles(parts[-1], idx)], [torch.einsum("bn,bnd->bd", w, parts[-1])]
    for t in range(T, 0, -1):
        a = ancestors[t - 1]
        idx, line = a.gather(1, idx), a.gather(1, line)
        paths.append(gather_particles(parts[t - 1], idx))
        means.append(torch.einsum("bn,bnd->bd", w, gather_particles(parts[t - 1], line)))
    return SmoothingResult(torch.stack(means[::-1], 1), None, torch.stack(paths[::-1], 2), result, "genealogy")


def _ffbsi(model, parts, lws, M, generator, result, chunk) -> SmoothingResult:
    """Backward simulation: ``x_T ~ w_T``, then ``x_t ~ w_t^i p(x_t+1 | x_t^i)`` (Godsill, Doucet &
    West 2004), in blocks of ``chunk`` paths; the uniforms of a step are drawn for all M paths at
    once, so the numbers do not depend on the blocks."""
    B, N, d = parts[-1].shape
    T = len(parts) - 1
    dtype, device = parts[-1].dtype, parts[-1].device
    u = uniform((B, M), dtype=dtype, device=device, generator=generator)
    x = gather_particles(parts[-1], _categorical(lws[-1].unsqueeze(1).expand(B, M, N), u))  # (B, M, d)
    paths = [x]
    for t in range(T - 1, -1, -1):
        u = uniform((B, M), dtype=dtype, device=device, generator=generator)
        prev, lw = parts[t].unsqueeze(1), lws[t].unsqueeze(1)  # (B, 1, N, d), (B, 1, N)
        blocks = []
        for s in range(0, M, chunk):
            xb = x[:, s : s + chunk].unsqueeze(2)  # (B, c, 1, d)
            logw = lw + model.transition_log_prob(xb, prev)  # (B, c, N)
            # a path no particle can reach (every density underflowed): its filtering weights alone
            logw = torch.where(torch.isfinite(logw.logsumexp(-1, keepdim=True)), logw, lw.expand_as(logw))
            blocks.append(_categorical(logw, u[:, s : s + chunk]))
        x = gather_particles(parts[t], torch.cat(blocks, 1))
        paths.append(x)
    paths = torch.stack(paths[::-1], 2)  # (B, M, T+1, d)
    return SmoothingResult(paths.mean(1), None, paths, result, "ffbsi")
