"""PF-PF on the Lorenz-96 regimes and Lorenz-63, where it must invent model noise: the truth and
observations come from the deterministic model (the experiment runner's data at seed 0, the
scoreboard's), and the PF-PF filters them with a copy of the model that adds ``N(0, q^2 I)`` per
observation interval (``q``: ``--noise``). The runner gives one model to every filter, so this
mismatch needs a script.

    python -m experiments.benchmarks.bench_lorenz96_pfpf                    # R1-R4, EDH, N = 100, q = 0.1
    python -m experiments.benchmarks.bench_lorenz96_pfpf --regimes r2 --flow ledh --trials 2 --steps 100
    python -m experiments.benchmarks.bench_lorenz96_pfpf --regimes l63 --noise 0.5 --flow ledh   # burn-in 64

Prints one Markdown row per regime (RMSE after the burn-in, mean and standard error over trials;
s per step of the batched call, one thread unless ``--threads``; mean ESS) and writes them to
``results_lorenz96_pfpf.json`` (``--out``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
#: the Lorenz96 settings of the scoreboard's regimes (configs/experiment/lorenz96_*.yaml)
REGIMES = {
    "r1": {},
    "r2": dict(dt=0.4, substeps=8),
    "r3": dict(obs_every=2, obs_operator="abs"),
    "r4": dict(obs_df=3),
    "l63": {},
}
#: the burn-in of each (the experiments' metrics.burn_in): Lorenz-63 DAPPER's 64 steps, Lorenz-96 200
BURN_IN = {"l63": 64}


def run(regime: str, flow: str, n: int, noise: float, trials: int, steps: int, burn_in: int, seed: int = 0) -> dict:
    from torchflow.core.random import TrialStreams
    from torchflow.filters import ParticleFlowParticleFilter
    from torchflow.flows import EDHFlow, LEDHFlow
    from torchflow.models import Lorenz63, Lorenz96

    cls = Lorenz63 if regime == "l63" else Lorenz96
    truth_model = cls(**REGIMES[regime])
    gen = torch.Generator().manual_seed(seed)  # as the runner: the data, then the prior, from one generator
    traj = truth_model.simulate(trials, steps, gen)
    mean, cov = truth_model.initial_belief(traj.states[:, 0], gen)
    model = cls(model_noise=noise, **REGIMES[regime])
    f = ParticleFlowParticleFilter(model, flow=EDHFlow() if flow == "edh" else LEDHFlow(), n_particles=n)
    t0 = time.perf_counter()
    with torch.no_grad():  # as the runner calls it (no gradient recorded: the flows' no-gradient paths)
        out = f(traj.observations, mean, cov, TrialStreams(seed + 2, trials, f.stream_name))
    sec = (time.perf_counter() - t0) / steps
    per_trial = (out.estimates - traj.states[:, 1:]).square().mean(-1).sqrt()[:, burn_in:].mean(-1)
    return dict(
        regime=regime,
        flow=flow,
        n=n,
        noise=noise,
        trials=trials,
        steps=steps,
        burn_in=burn_in,
        rmse=float(per_trial.mean()),
        se=float(per_trial.std() / trials**0.5),
        per_trial=[round(float(v), 4) for v in per_trial],
        ess=float(out.ess.mean()),
        sec_per_step=sec,
    )


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--regimes", nargs="+", default=list(REGIMES), choices=list(REGIMES))
    p.add_argument("--flow", default="edh", choices=["edh", "ledh"])
    p.add_argument("--n", type=int, default=100)
    p.add_argument("--noise", type=float, default=0.1)
    p.add_argument("--trials", type=int, default=10)
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--burn-in", type=int, default=None, help="steps left out of the RMSE (default: 200, Lorenz-63 64)")
    p.add_argument("--out", default=str(HERE / "results" / "results_lorenz96_pfpf.json"))
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    rows = []
    print("| regime | PF-PF | N | q | RMSE +- SE | ESS | s/step |")
    print("|---|---|---|---|---|---|---|")
    for r in a.regimes:
        burn = a.burn_in if a.burn_in is not None else BURN_IN.get(r, 200)
        row = run(r, a.flow, a.n, a.noise, a.trials, a.steps, burn)
        rows.append(row)
        print(
            f"| {r.upper()} | {a.flow.upper()} | {a.n} | {a.noise:g} | {row['rmse']:.3f} +- {row['se']:.3f} | "
            f"{row['ess']:.1f} | {row['sec_per_step']:.3g} |",
            flush=True,
        )
    Path(a.out).write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
