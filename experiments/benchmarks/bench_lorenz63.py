"""Lorenz-63 (Sakov, Oliver & Bertino 2012 set-up): torchflow's filters and DAPPER's on the same data.

The truth and the observations are simulated by torchflow (``Lorenz63()``: an observation of all three
coordinates every 0.25 time units, R = 2 I, no model noise). DAPPER (``mods/Lorenz63/sakov2012``)
filters the same observations from the same prior N((1.509, -1.531, 25.46), 2 I) in its own interpreter
(``--dapper-python``; it needs numpy 2 and Python 3.11 for 1.7.1); it is handed the truth at every
integration step of 0.01 as well (its own statistics read it), integrated by torchflow from the
observation-time states. The score is the analysis RMSE at the observation times, averaged after a
burn-in, mean and standard error over trials; time per assimilation step of one trial, one thread.
DAPPER's settings are its file's suggested ones; ours are the experiment config's.

    python -m experiments.benchmarks.bench_lorenz63 --dapper-python /path/to/venv-with-dapper/bin/python

Writes ``results_lorenz63.md`` and ``.json`` in ``results/`` (``--out`` to change).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
#: DAPPER methods (label, class, arguments, its file's published rmse.a)
DAPPER = [
    ("EnKF Sqrt N=10 infl 1.02 rot", "EnKF", dict(upd_a="Sqrt", N=10, infl=1.02, rot=True), 0.60),
    ("EnKF PertObs N=10 infl 1.04", "EnKF", dict(upd_a="PertObs", N=10, infl=1.04), 0.65),
    ("iEnKS Sqrt N=10 infl 1.02 rot", "iEnKS", dict(upd_a="Sqrt", N=10, infl=1.02, rot=True), 0.31),
    ("PartFilt N=100 reg 2.4 NER 0.3", "PartFilt", dict(N=100, reg=2.4, NER=0.3), 0.38),
]
#: torchflow filters (label, registry name, arguments)
OURS = [
    ("UKF", "ukf", {}),
    ("ETKF N=10 infl 1.02 (no rotation)", "etkf", dict(n_particles=10, inflation=1.02)),
    (
        "ETKF N=10 infl 1.02 rotate, analysis inflation (DAPPER's semantics)",
        "etkf",
        dict(n_particles=10, inflation=1.02, inflate="analysis", rotate=True),
    ),
    ("EnKF (perturbed obs) N=10 infl 1.04", "enkf", dict(n_particles=10, inflation=1.04)),
    (
        "EnKF (perturbed obs) N=10 infl 1.04, analysis inflation (DAPPER's semantics)",
        "enkf",
        dict(n_particles=10, inflation=1.04, inflate="analysis"),
    ),
    ("KPFF N=20", "kpff", dict(n_particles=20)),
    ("KPFF N=100", "kpff", dict(n_particles=100)),
    ("LPF (global) N=100 jitter 0.1", "lpf", dict(n_particles=100, radius=float("inf"), jitter=0.1)),
]


def dapper_worker(inp: str, out: str) -> None:
    """Run DAPPER's methods on the data of ``inp`` (npz) and save the analysis means."""
    import time

    import dapper.da_methods as da
    import dapper.mods as modelling
    import numpy as np
    from dapper.mods.Lorenz63 import sakov2012
    from dapper.tools.seeding import set_seed

    data = np.load(inp, allow_pickle=True)
    fine, yy, mean0 = data["fine_states"], data["observations"], data["mean0"]
    methods = json.loads(str(data["methods"]))
    B, T, _ = yy.shape
    res = {}
    for label, name, kwargs in methods:
        means, secs = np.empty((B, T, 3)), 0.0
        for b in range(B):
            HMM = sakov2012.HMM.copy()
            HMM.tseq = modelling.Chronology(0.01, dko=25, Ko=T - 1, BurnIn=0)
            HMM.X0 = modelling.GaussRV(mu=mean0, C=2.0)
            set_seed(1000 + b)
            xp = getattr(da, name)(**kwargs)
            t0 = time.perf_counter()
            xp.assimilate(HMM, fine[b], yy[b], liveplots=False)
            secs += time.perf_counter() - t0
            means[b] = xp.stats.mu.a  # (Ko + 1, 3): the analysis means at the observation times
        res[label] = dict(means=means, sec_per_step=secs / (B * T))
        print(label, flush=True)
    np.savez(
        out,
        **{f"{k}|means": v["means"] for k, v in res.items()},
        **{f"{k}|sec": v["sec_per_step"] for k, v in res.items()},
    )


def fine_truth(model, states):
    """``(B, 25 T + 1, 3)``: the truth at every integration step, from the observation-time states
    ``(B, T + 1, 3)`` (:func:`experiments.benchmarks.bench_dapper._fine_truth`)."""
    from experiments.benchmarks.bench_dapper import _fine_truth

    return _fine_truth(model, states)


def compare(args):
    import numpy as np
    import torch

    from experiments.benchmarks.bench_lorenz96 import mean_se, rmse_after, run_ours
    from torchflow.models import Lorenz63

    torch.set_num_threads(1)
    model = Lorenz63()
    traj = model.simulate(args.trials, args.steps, torch.Generator().manual_seed(args.seed))
    mean, cov = model.initial_belief(traj.states[:, 0])
    truth = traj.states[:, 1:]
    rows = []
    for label, name, kw in OURS:
        est, sec = run_ours(name, kw, model, traj, mean, cov)
        per_trial = rmse_after(est, truth, args.burn_in)
        rows.append(
            dict(
                library="torchflow", setting=label, rmse=mean_se(per_trial), trials=per_trial.tolist(), sec_per_step=sec
            )
        )
        print(rows[-1]["setting"], rows[-1]["rmse"], flush=True)
    if args.dapper_python:
        fine = fine_truth(model, traj.states)
        torch.testing.assert_close(fine[:, :: model.substeps], traj.states, rtol=0, atol=1e-9)
        with tempfile.TemporaryDirectory() as tmp:
            inp, out = os.path.join(tmp, "in.npz"), os.path.join(tmp, "out.npz")
            np.savez(
                inp,
                fine_states=fine.numpy(),
                observations=traj.observations.numpy(),
                mean0=model.prior_mean.numpy(),
                methods=json.dumps([(lb, n, kw) for lb, n, kw, _ in DAPPER]),
            )
            env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1", MPLBACKEND="agg")
            subprocess.run([args.dapper_python, str(Path(__file__)), "--dapper-worker", inp, out], check=True, env=env)
            got = np.load(out)
            from experiments.benchmarks.bench_lorenz96 import mean_se, rmse_after  # (this side has torch)

            for label, _, _, published in DAPPER:
                per_trial = rmse_after(torch.as_tensor(got[f"{label}|means"]), truth, args.burn_in)
                rows.append(
                    dict(
                        library="DAPPER 1.7.1",
                        setting=label,
                        rmse=mean_se(per_trial),
                        trials=per_trial.tolist(),
                        sec_per_step=float(got[f"{label}|sec"]),
                        published=published,
                    )
                )
                print(label, rows[-1]["rmse"], flush=True)
    return rows


def write(args, rows):
    out = Path(args.out)
    lines = [
        "# Lorenz-63 (Sakov, Oliver & Bertino 2012): torchflow and DAPPER on the same data",
        "",
        f"{args.trials} trials x {args.steps} observation steps (every 0.25 time units, all observed, R = 2 I, "
        f"no model noise), analysis RMSE after a burn-in of {args.burn_in} steps, mean ± standard error over "
        "trials; the same truth, observations and prior for both libraries. Time: seconds per assimilation step "
        "of one trial, one thread (DAPPER's includes its own statistics).",
        "",
        "Command: `python -m experiments.benchmarks.bench_lorenz63 --dapper-python <python with dapper 1.7.1>`",
        "",
        "| library | setting | RMSE (same data) | DAPPER's published (its own data) | s/step |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        pub = f"{r['published']:.2f}" if r.get("published") is not None else ""
        lines.append(
            f"| {r['library']} | {r['setting']} | {r['rmse'][0]:.3f} ± {r['rmse'][1]:.3f} | {pub} | "
            f"{r['sec_per_step']:.2e} |"
        )
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    out.with_suffix(".json").write_text(json.dumps(dict(args=vars(args), rows=rows), indent=1))
    print("\n".join(lines))


def main(argv=None):
    if argv is None and len(sys.argv) > 1 and sys.argv[1] == "--dapper-worker":
        dapper_worker(sys.argv[2], sys.argv[3])
        return
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dapper-python", default=os.environ.get("DAPPER_PYTHON"))
    p.add_argument("--trials", type=int, default=10)
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--burn-in", type=int, default=64)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=str(HERE / "results" / "results_lorenz63"))
    args = p.parse_args(argv)
    write(args, compare(args))


if __name__ == "__main__":
    main()
