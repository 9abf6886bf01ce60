"""Stochastic volatility on the GBP/USD daily returns: log-likelihood estimates of torchflow's
bootstrap PF against ``particles``' bootstrap filter and an exact grid filter, and PF-PF(LEDH) on
the log-squared Gaussian form beside them.

    python -m experiments.benchmarks.bench_sv            # ~10 min on one thread of a loaded 2-core machine
    python -m experiments.benchmarks.bench_sv --quick    # smoke test: a 50-step prefix, few runs

Data: ``particles.datasets.GBP_vs_USD_9798`` (751 daily rates, 1997-1999), preprocessed as
``particles`` does for its SV examples: 100 x the log-returns, 750 points
(``python -m experiments.data.gbpusd out.csv`` writes the same numbers as a CSV). Model: ``StochasticVolatility()``
with ``particles.StochVol``'s default parameters
(mu = -1.02, rho = 0.9702, sigma = 0.178).

Rows, each ``runs`` independent runs on the one series (log-likelihood mean, standard deviation, the
mean's standard error; its difference to the exact value; and ``mean exp(ll - exact)``, which is 1 for
an unbiased likelihood estimate, with its standard error; seconds per run):

* exact: :func:`experiments.grid_filter.grid_filter` (2000 points; 1000 and 4000 agree to 1e-9);
* ``particles``: ``SMC(Bootstrap(StochVol(), data), N)`` (systematic resampling when ESS < N/2), one
  run per call (its only mode);
* ours, BPF: ``BootstrapParticleFilter`` (the same scheme), the runs as B trials of one call, and one
  run per call (B = 1: timing);
* ours, PF-PF(LEDH), PF-PF(EDH): ``ParticleFlowParticleFilter`` on the log-squared form
  (``gaussian_form="log_squared"``, ``offset``: the series has two zero returns); its weights are the
  returns' exact density, so it estimates the same likelihood.

The Monte Carlo standard error of a mean over runs is ``sd / sqrt(runs)``; a difference of two
independent means has the root sum of squares of theirs. Everything runs on one thread (torch, BLAS).
"""

from __future__ import annotations

import math
import time
from typing import List

import numpy as np
import torch

from torchflow.filters import BootstrapParticleFilter, ParticleFlowParticleFilter
from torchflow.models import StochasticVolatility

from ..grid_filter import grid_filter
from . import harness as h

QUICK = dict(steps=50, runs=4, ns="200,1000", single_runs="2,1", flows="ledh:100:4,edh:100:4", flow_single=1)


def returns_series(particles=None) -> np.ndarray:
    """The 750 GBP/USD percentage log-returns of ``particles``' dataset (``experiments.data.gbpusd``)."""
    from ..data.gbpusd import returns

    return returns()


def stats(name: str, ll: np.ndarray, exact: float, seconds_per_run: float, **extra) -> dict:
    """The row of ``ll`` (one log-likelihood per run)."""
    R = ll.size
    sd = float(ll.std(ddof=1)) if R > 1 else float("nan")
    ratio = np.exp(ll - exact)
    return dict(
        name=name,
        runs=R,
        mean=float(ll.mean()),
        sd=sd,
        se=sd / math.sqrt(R),
        diff=float(ll.mean() - exact),
        ratio=float(ratio.mean()),
        ratio_se=float(ratio.std(ddof=1) / math.sqrt(R)) if R > 1 else float("nan"),
        sec_per_run=seconds_per_run,
        **extra,
    )


def ours(f, obs: torch.Tensor, model, runs: int, batched: bool, n: int, seed: int) -> (np.ndarray, float):
    """``runs`` log-likelihoods of filter ``f`` at ``n`` particles: one call of B = runs (``batched``)
    or ``runs`` calls of B = 1; and seconds per run."""
    mean, cov = model.initial_belief(torch.zeros(1, 1, dtype=torch.float64))
    calls = [(runs, seed)] if batched else [(1, seed + i) for i in range(runs)]
    with torch.no_grad():  # a warm-up call (compiled kernels, first-call checks), untimed
        f(
            obs[:, :20].expand(2, -1, -1),
            mean.expand(2, -1),
            cov.expand(2, -1, -1),
            torch.Generator().manual_seed(0),
            n_particles=n,
        )
    out, t0 = [], time.perf_counter()
    with torch.no_grad():
        for B, s in calls:
            res = f(
                obs.expand(B, -1, -1),
                mean.expand(B, -1),
                cov.expand(B, -1, -1),
                torch.Generator().manual_seed(s),
                n_particles=n,
            )
            out.append(res.log_evidence)
    return torch.cat(out).numpy(), (time.perf_counter() - t0) / runs


def peer_runs(particles, y: np.ndarray, n: int, runs: int, seed: int) -> (np.ndarray, float):
    """``runs`` log-likelihoods of ``particles``' bootstrap filter at ``n`` particles; seconds per run."""
    ssms = particles.state_space_models
    fk = ssms.Bootstrap(ssm=ssms.StochVol(), data=y)
    particles.SMC(fk=fk, N=n, collect=None).run()  # warm-up (Numba compiles on first use), untimed
    np.random.seed(seed)
    out, t0 = [], time.perf_counter()
    for _ in range(runs):
        alg = particles.SMC(fk=fk, N=n, resampling="systematic", ESSrmin=0.5, collect=None, verbose=False)
        alg.run()
        out.append(alg.logLt)
    return np.array(out), (time.perf_counter() - t0) / runs


def flow_specs(text: str) -> List[tuple]:
    """``"ledh:1000:10,edh:1000:20"`` -> ``[("ledh", 1000, 10), ...]`` (flow, particles, runs)."""
    try:
        return [(f, int(float(n)), int(r)) for f, n, r in (item.split(":") for item in str(text).split(",") if item)]
    except ValueError:
        raise SystemExit(f"--flows: expected flow:particles:runs items, got {text!r}") from None


def run(argv) -> dict:
    a = h.options(
        __doc__,
        argv,
        QUICK,
        steps=0,
        runs=100,
        ns="1000,10000",
        single_runs="100,10",
        flows="ledh:1000:10,ledh:100:50,edh:1000:20",
        flow_single=2,
        offset=1e-4,
        seed=0,
    )
    ns, single = h.ints(a.ns, "--ns"), h.ints(a.single_runs, "--single-runs")
    if len(single) != len(ns):
        raise SystemExit("--single-runs: expected one count per --ns value")
    particles = h.peer("particles", "datasets", "state_space_models")
    y = returns_series(particles)
    if a.steps:
        y = y[: int(a.steps)]
    T = y.size
    obs = torch.tensor(y, dtype=torch.float64).reshape(1, T, 1)
    model = StochasticVolatility()
    logsq = StochasticVolatility(gaussian_form="log_squared", offset=float(a.offset))
    z = logsq.transform_observations(obs)
    rows = []
    with h.session("bench_sv", argv, threads=1) as info, h.blas_limit(1):
        t0 = time.perf_counter()
        exact, _ = grid_filter(model, obs[0])
        t_grid = time.perf_counter() - t0
        rows.append(
            dict(
                name="exact (grid, 2000 points)",
                runs=1,
                mean=exact,
                sd=0.0,
                se=0.0,
                diff=0.0,
                ratio=1.0,
                ratio_se=0.0,
                sec_per_run=t_grid,
                N=None,
                mode="-",
            )
        )
        bpf = BootstrapParticleFilter(model)
        for n, n_single in zip(ns, single):
            if particles is not None:
                ll, s = peer_runs(particles, y, n, a.runs, a.seed + 1000 * n)
                rows.append(stats("particles BPF", ll, exact, s, N=n, mode="1 run per call"))
            ll, s = ours(bpf, obs, model, a.runs, True, n, a.seed + n)
            rows.append(stats("ours BPF", ll, exact, s, N=n, mode=f"B = {a.runs}, one call"))
            ll, s = ours(bpf, obs, model, n_single, False, n, a.seed + 7 * n)
            rows.append(stats("ours BPF", ll, exact, s, N=n, mode="B = 1 per call"))
        for flow, n, runs in flow_specs(a.flows):
            f = ParticleFlowParticleFilter(logsq, flow=flow)
            ll, s = ours(f, z, logsq, runs, True, n, a.seed + 11 * n)
            label = f"ours PF-PF({flow.upper()}), log-squared form"
            rows.append(stats(label, ll, exact, s, N=n, mode=f"B = {runs}, one call"))
            if a.flow_single:
                ll, s = ours(f, z, logsq, int(a.flow_single), False, n, a.seed + 13 * n)
                rows.append(stats(label, ll, exact, s, N=n, mode="B = 1 per call"))
    pairs = []
    for n in ns:  # ours (batched) against particles at equal N
        mine = next(r for r in rows if r["name"] == "ours BPF" and r["N"] == n and "one call" in r["mode"])
        peer = next((r for r in rows if r["name"] == "particles BPF" and r["N"] == n), None)
        if peer is not None:
            d, se = mine["mean"] - peer["mean"], math.hypot(mine["se"], peer["se"])
            pairs.append(
                dict(
                    N=n,
                    diff=d,
                    se=se,
                    z=d / se,
                    var_ratio=(mine["sd"] / peer["sd"]) ** 2,
                    time_ratio=peer["sec_per_run"] / mine["sec_per_run"],
                )
            )
    head = [
        "estimator",
        "N",
        "mode",
        "runs",
        "mean log-lik",
        "sd",
        "SE",
        "mean - exact",
        "mean exp(ll - exact)",
        "s/run",
    ]
    table = [
        [
            r["name"],
            h.fmt(r["N"], "{}"),
            r["mode"],
            r["runs"],
            f"{r['mean']:.4f}",
            h.fmt(r["sd"], "{:.4f}"),
            h.fmt(r["se"], "{:.4f}"),
            h.fmt(r["diff"], "{:+.4f}"),
            "1" if r["runs"] == 1 else f"{r['ratio']:.3f} +- {r['ratio_se']:.3f}",
            h.fmt(r["sec_per_run"], "{:.3g}"),
        ]
        for r in rows
    ]
    more = [
        "`mean exp(ll - exact)` is 1 for an unbiased likelihood estimate; where the log-likelihood's sd is "
        "about 1 or more its mean is carried by rare runs and few runs understate it (and its SE).",
        "",
        "Ours (B = runs, one call) minus particles at equal N: "
        + "; ".join(
            f"N = {p['N']}: {p['diff']:+.4f} +- {p['se']:.4f} ({p['z']:+.1f} SE), variance ratio ours/particles "
            f"{p['var_ratio']:.2f}, particles' s/run over ours {p['time_ratio']:.2f}x"
            for p in pairs
        )
        if pairs
        else "particles not installed: no peer rows (pip install -e '.[bench]')",
    ]
    intro = [
        f"Series: GBP/USD daily log-returns x 100, T = {T}; StochasticVolatility() = particles' StochVol "
        f"defaults; the log-squared form with offset {a.offset:g}. One thread (torch and BLAS) on a shared machine."
    ]
    md = h.report("# Stochastic volatility: log-likelihood on GBP/USD (bench_sv)", a, info, intro, head, table, *more)
    return dict(machine=info, rows=rows, pairs=pairs, exact=exact, T=T, args=vars(a), markdown=md)


if __name__ == "__main__":
    h.main(run, "sv")
