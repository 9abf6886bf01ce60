"""Particle marginal Metropolis-Hastings on the stochastic-volatility model and the GBP/USD returns:
torchflow's :func:`~torchflow.inference.pmmh` (C chains batched in the trial dimension, the bootstrap
PF as the likelihood estimator) beside ``particles``' ``mcmc.PMMH`` (one chain per run, its bootstrap
filter, its adaptive random walk), with the same priors and particle count.

    python -m experiments.benchmarks.bench_sv_pmmh            # ~5 min on one thread
    python -m experiments.benchmarks.bench_sv_pmmh --steps 200 --iterations 300   # smaller
    python -m experiments.benchmarks.bench_sv_pmmh --correlation 0.99 --particles 50 --no-peer \
        --out experiments/benchmarks/results/results_sv_cpm      # correlated PMMH beside standard, N = 50
    python -m experiments.benchmarks.bench_sv_pmmh --filter pfpf_ledh --particles 50 --no-peer \
        --out experiments/benchmarks/results/results_sv_pmmh_ledh   # PF-PF(LEDH) as the likelihood estimator

``--filter pfpf_ledh``: PF-PF(LEDH) on the log-squared form (``offset``: the series has zero returns);
its weights and log-evidence are those of the returns, so the posterior is the same.

Priors (``particles``' conventions): mu ~ N(0, 2^2), rho ~ U(-1, 1), sigma ~ Gamma(1, rate 1).
Reported per sampler: the posterior mean and standard deviation of each parameter over the kept
draws of all chains, the acceptance rate, the effective sample size (all chains, split-chain
autocorrelation, :func:`torchflow.inference.effective_sample_size` for both) and ESS per second of
sampling. Writes ``results_sv_pmmh.md`` and ``.json`` in ``results/``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
NAMES = ("mu", "rho", "sigma")


def torch_priors():
    from torch.distributions import Gamma, Normal, Uniform

    f = lambda v: torch.tensor(v, dtype=torch.float64)
    return {"mu": Normal(f(0.0), f(2.0)), "rho": Uniform(f(-1.0), f(1.0)), "sigma": Gamma(f(1.0), f(1.0))}


def stationary_prior(params):
    """The stationary law of x_0 at each chain's parameters: ``(C, 1)``, ``(C, 1, 1)``."""
    var = params["sigma"] ** 2 / (1 - params["rho"] ** 2)
    return params["mu"].unsqueeze(-1), var.reshape(-1, 1, 1)


def summarise(name, draws: dict, acceptance, seconds, chains, iterations):
    from torchflow.inference import effective_sample_size

    row = dict(
        sampler=name, chains=chains, iterations=iterations, seconds=seconds, acceptance=float(np.mean(acceptance))
    )
    for k in NAMES:
        x = torch.as_tensor(np.asarray(draws[k]), dtype=torch.float64)  # (C, S)
        ess = float(effective_sample_size(x))
        row[k] = dict(mean=float(x.mean()), sd=float(x.std()), ess=ess, ess_per_sec=ess / seconds)
    return row


def ours(y, args, correlation=None):
    from torchflow.filters import BootstrapParticleFilter, ParticleFlowParticleFilter
    from torchflow.inference import pmmh
    from torchflow.models import StochasticVolatility

    obs = torch.as_tensor(y).reshape(-1, 1)
    if args.filter == "pfpf_ledh":
        # the flow needs the log-squared form (slope one); its weights and evidence are the returns'
        model = StochasticVolatility(gaussian_form="log_squared", offset=args.offset)
        obs = model.transform_observations(obs)
        filt = ParticleFlowParticleFilter(model, flow="ledh", n_particles=args.particles)
    else:
        model = StochasticVolatility()
        filt = BootstrapParticleFilter(model, n_particles=args.particles)
    cpu0 = time.process_time()
    res = pmmh(
        filt,
        obs,
        stationary_prior,
        torch_priors(),
        args.seed,
        n_chains=args.chains,
        n_iterations=args.iterations,
        n_adapt=args.adapt,
        scale=0.1,
        init={"mu": -1.0, "rho": 0.9, "sigma": 0.2},
        correlation=correlation,
    )
    est = "PF-PF(LEDH)" if args.filter == "pfpf_ledh" else "BPF"
    name = (
        f"torchflow pmmh, {est} (C chains in one call per iteration)"
        if correlation is None
        else f"torchflow correlated pmmh, {est}, rho = {correlation} (resampling every step, sorted)"
    )
    row = summarise(
        name,
        {k: v.numpy() for k, v in res.samples.items()},
        res.acceptance.numpy(),
        res.seconds,
        args.chains,
        args.iterations,
    )
    # CPU seconds of the process (1 thread): ESS per CPU second does not depend on what else runs
    row["cpu_seconds"] = time.process_time() - cpu0
    for k in NAMES:
        row[k]["ess_per_cpu_sec"] = row[k]["ess"] / row["cpu_seconds"]
    return row


def theirs(y, args):
    import particles.distributions as dists
    from particles import mcmc
    from particles import state_space_models as ssm

    prior = dists.StructDist(
        {"mu": dists.Normal(scale=2.0), "rho": dists.Uniform(a=-1.0, b=1.0), "sigma": dists.Gamma(a=1.0, b=1.0)}
    )
    theta0 = np.zeros(1, dtype=prior.dtype)
    theta0["mu"], theta0["rho"], theta0["sigma"] = -1.0, 0.9, 0.2
    draws, acc, t0 = {k: [] for k in NAMES}, [], time.perf_counter()
    for c in range(args.chains):
        np.random.seed(args.seed + c)
        alg = mcmc.PMMH(
            ssm_cls=ssm.StochVol,
            prior=prior,
            data=list(y),
            Nx=args.particles,
            niter=args.adapt + args.iterations,
            theta0=theta0,
        )
        alg.run()
        for k in NAMES:
            draws[k].append(np.asarray(alg.chain.theta[k])[args.adapt :])
        acc.append(float(alg.acc_rate))
    return summarise(
        "particles mcmc.PMMH (adaptive random walk, one chain per run)",
        draws,
        acc,
        time.perf_counter() - t0,
        args.chains,
        args.iterations,
    )


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=750)
    p.add_argument("--chains", type=int, default=4)
    p.add_argument("--iterations", type=int, default=500)
    p.add_argument("--adapt", type=int, default=200)
    p.add_argument("--particles", type=int, default=200)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--correlation",
        type=float,
        default=None,
        help="also run correlated pseudo-marginal PMMH with this rho (beside the standard run)",
    )
    p.add_argument("--no-peer", action="store_true", help="leave out particles' PMMH")
    p.add_argument(
        "--filter",
        choices=("bpf", "pfpf_ledh"),
        default="bpf",
        help="our likelihood estimator: the bootstrap PF or PF-PF(LEDH) on the log-squared form",
    )
    p.add_argument("--offset", type=float, default=1e-4, help="log-squared form: log(y^2 + offset) (zero returns)")
    p.add_argument("--out", default=str(HERE / "results" / "results_sv_pmmh"))
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    from ..data.gbpusd import returns

    y = returns()[: args.steps]
    rows = [ours(y, args)]
    if args.correlation is not None:
        rows.append(ours(y, args, args.correlation))
    try:
        if not args.no_peer:
            rows.append(theirs(y, args))
    except ImportError:
        print("particles is not installed: its row is left out")
    lines = [
        f"# PMMH on stochastic volatility, GBP/USD returns (first {args.steps}), {args.chains} chains x "
        f"{args.iterations} kept draws after {args.adapt}, N = {args.particles}, 1 thread",
        "",
        "| sampler | acceptance | s | " + " | ".join(f"{k}: mean (sd), ESS, ESS/s" for k in NAMES) + " |",
        "|---|---|---|" + "---|" * len(NAMES),
    ]
    for r in rows:
        cells = [f"{r[k]['mean']:.3f} ({r[k]['sd']:.3f}), {r[k]['ess']:.0f}, {r[k]['ess_per_sec']:.2f}" for k in NAMES]
        lines.append(f"| {r['sampler']} | {r['acceptance']:.2f} | {r['seconds']:.0f} | " + " | ".join(cells) + " |")
    if any("cpu_seconds" in r for r in rows):
        lines += [
            "",
            "ESS per CPU second of the process (not wall time: the same under other load):",
            "",
            "| sampler | CPU s | " + " | ".join(f"{k}: ESS/CPU s" for k in NAMES) + " |",
            "|---|---|" + "---|" * len(NAMES),
        ]
        lines += [
            f"| {r['sampler']} | {r['cpu_seconds']:.0f} | "
            + " | ".join(f"{r[k]['ess_per_cpu_sec']:.2f}" for k in NAMES)
            + " |"
            for r in rows
            if "cpu_seconds" in r
        ]
    out = Path(args.out)
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    out.with_suffix(".json").write_text(json.dumps(dict(settings=vars(args), rows=rows), indent=1) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
