"""A particle filter's weighting and resampling in one Numba pass per trial, on the CPU.

What :meth:`torchflow.filters.ParticleFilter.weight_and_resample` does with some twenty eager
operations (each a pass over the ``(B, N)`` weights, 1-3 us of dispatch apiece at small N), done
in one compiled call (:func:`weigh_resample`):

1. ``lw = lw_prev + log_increment`` (a particle with a non-finite coordinate makes it NaN), the
   step's evidence increment ``c = logsumexp(lw)`` per trial; a trial whose ``c`` is not finite is
   flagged and left to the filter's reference path, which repairs it (the others are finished
   here, so a trial's numbers do not depend on its neighbours);
2. the normalised weights ``lw - c``, the weighted mean and the ESS ``1 / sum w^2``, with
   ``w = exp(lw - max) / sum`` from the exponentials of step 1 (one per particle);
3. the trials whose ESS is below the threshold: the systematic or stratified indices from the
   given uniforms, by the reference's rules (:func:`torchflow.core.resampling._strata_indices`: the
   CDF of ``exp(lw - max lw)`` scaled to end at exactly N, positions ``j + u_j`` kept below
   ``j + 1``, index ``#{i : S_i <= p_j}``), and ``-log N`` weights.

The resampled trials' particles are written to a new tensor as their ancestors are found; where
some trial resampled, the others' are copied beside them.

The same formulas as the reference code, rounded differently in three places: the sums are
accumulated in particle order (torch's reductions block and vectorise), the normalised weights
reuse the logsumexp's exponentials (``exp(lw - max) / sum`` for ``exp(lw - c)``), and so does the
resampling CDF (the same ``exp(lw - max)``). So the weights, increments and estimates agree to
round-off (a few ulp), and the ancestors are the same unless a position falls within round-off of
a CDF step (``tests/test_fused_weights.py``).
Trials are independent, so the numbers do not depend on the thread count; large batches run
their trials in parallel (:func:`weigh_resample_parallel`).
"""

import math
import types

import numba
import numpy as np


def _weigh_resample(lw_prev, log_inc, x, u, per_particle_u, thresh_n, log_n, lw_out, est, ess, inc, res, out, bad):
    """Arguments: ``lw_prev``, ``log_inc`` ``(B, N)``; particles ``x (B, N, d)``; uniforms ``u (B, 1)``
    (systematic) or ``(B, N)`` (stratified: ``per_particle_u``); ``thresh_n`` = threshold x N;
    ``log_n`` = -log N. Outputs: ``lw_out (B, N)``, ``est (B, d)``, ``ess``, ``inc (B,)``,
    ``res (B,)`` (resampled) and, where some trial resampled, the particles after resampling in
    ``out (B, N, d)`` (untouched otherwise); ``bad (B,)``: the trials whose increment is not
    finite (a particle to repair, or no weight left), whose outputs are left for the caller's
    reference path. Returns the number of resampled trials among the others.

    No ``(B, N)`` scratch: ``lw_out`` holds ``exp(lw - max)`` between the passes, and a kept trial's
    log-weights are recomputed from the inputs in a last pass. Every trial is computed on its own:
    its numbers do not depend on the others in the batch."""
    B, N = lw_prev.shape
    d = x.shape[2]
    tots = np.empty(B)
    for b in numba.prange(B):
        m = -np.inf
        for n in range(N):
            v = _log_weight(lw_prev, log_inc, x, b, n)
            lw_out[b, n] = v
            if v > m:
                m = v
        tot = 0.0
        for n in range(N):
            w = math.exp(lw_out[b, n] - m)  # the one exponential per particle: 1 at the maximum
            lw_out[b, n] = w
            tot += w
        c = m + math.log(tot)
        inc[b] = c
        tots[b] = tot
        bad[b] = not math.isfinite(c)
    count = 0
    for b in numba.prange(B):
        if bad[b]:
            res[b] = False
            continue
        r = 1.0 / tots[b]
        for k in range(d):
            est[b, k] = 0.0
        s2 = 0.0
        for n in range(N):
            w = lw_out[b, n] * r  # exp(lw - c)
            s2 += w * w
            for k in range(d):
                est[b, k] += w * x[b, n, k]
        v = 1.0 / s2
        ess[b] = v
        flag = v < thresh_n
        res[b] = flag
        if flag:
            count += 1
            _strata(lw_out, b, u, per_particle_u, x, out)
            for n in range(N):
                lw_out[b, n] = log_n
        else:
            c = inc[b]
            for n in range(N):
                lw_out[b, n] = _log_weight(lw_prev, log_inc, x, b, n) - c
    if count > 0:  # the kept trials' particles join the resampled ones in ``out``
        for b in numba.prange(B):
            if not res[b] and not bad[b]:
                for n in range(N):
                    for k in range(d):
                        out[b, n, k] = x[b, n, k]
    return count


@numba.njit(cache=True, inline="always")
def _log_weight(lw_prev, log_inc, x, b, n):
    """``lw_prev + log_inc``, NaN where a coordinate of the particle is not finite (``s - s``)."""
    s = x[b, n, 0]
    for k in range(1, x.shape[2]):
        s += x[b, n, k]
    return lw_prev[b, n] + log_inc[b, n] + (s - s)


@numba.njit(cache=True, inline="always")
def _strata(e, b, u, per_particle_u, x, out):
    """Trial ``b``'s systematic/stratified resampling of ``x[b]`` into ``out[b]``, from its weights
    ``e[b]`` (``exp(lw - max lw)``), with the ancestors :func:`torchflow.core.resampling._strata_indices`
    defines: the cumulative weights scaled to end at exactly N, positions ``j + u_j`` kept below
    ``j + 1``, and the ancestor of position j the number of scaled cumulative weights ``<= p_j``
    (at most N - 1)."""
    N = e.shape[1]
    d = x.shape[2]
    cs = np.empty(N)
    acc = 0.0
    for n in range(N):
        acc += e[b, n]
        cs[n] = acc
    total = cs[N - 1]
    scale = N / total
    fn = float(N)
    i = 0
    for j in range(N):
        uj = u[b, j] if per_particle_u else u[b, 0]
        p = min(j + uj, np.nextafter(j + 1.0, 0.0))
        # advance past every i with S_i <= p (S non-decreasing: a merge of two sorted lists)
        while i < N:
            S = fn if cs[i] >= total else min(cs[i] * scale, fn)
            if S <= p:
                i += 1
            else:
                break
        a = min(i, N - 1)
        for k in range(d):
            out[b, j, k] = x[b, a, k]


def _renamed(fn, name: str):
    """A copy of ``fn`` under another name: Numba's on-disk cache keys a function by its name and
    line, not by its compile options, so the serial and parallel variants need two names."""
    extra = {"co_qualname": name} if hasattr(fn.__code__, "co_qualname") else {}  # Python >= 3.11
    code = fn.__code__.replace(co_name=name, **extra)
    out = types.FunctionType(code, fn.__globals__, name, fn.__defaults__, fn.__closure__)
    out.__qualname__ = name
    return out


weigh_resample = numba.njit(cache=True)(_weigh_resample)
weigh_resample_parallel = numba.njit(cache=True, parallel=True)(_renamed(_weigh_resample, "_weigh_resample_parallel"))
