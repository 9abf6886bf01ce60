"""Lorenz-96 (Sakov & Oke 2008 set-up): torchflow's ensemble Kalman filters against DAPPER's, and
their cost as the dimension grows.

1. **DAPPER comparison** (d = 40, dt = 0.05, all observed, R = I, no model noise): the same truth
   and observations (simulated by torchflow) are filtered by DAPPER's EnKF variants and by ours,
   each from the same Gaussian prior per trial; analysis RMSE averaged over the steps after a
   burn-in, mean and standard error over trials; seconds per step (one trial, one thread; DAPPER's
   time includes its own per-step statistics). DAPPER runs in its own interpreter
   (``--dapper-python``, default ``$DAPPER_PYTHON``; it needs numpy 2, this project's environment
   has numpy 1): the data travel in an ``.npz`` file. Without it the rows say so and DAPPER's
   published numbers (its ``mods/Lorenz96/sakov2008.py`` list) are quoted, labelled as such.
2. **d-scaling**: ETKF and LETKF at d = 40, 400, 4000 (CPU), RMSE and time per step; PF-PF(LEDH) is
   not run: the set-up has no model noise, and its weights need the transition density.

    python -m experiments.benchmarks.bench_lorenz96 --dapper-python /path/to/venv-with-dapper/bin/python

Writes ``results_lorenz96.md`` and ``.json`` in ``results/`` (``--out`` to change).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
#: (label, DAPPER method, its arguments, torchflow filter, its arguments); DAPPER's radius is the
#: distance at which its Gaspari-Cohn taper is exp(-1/2) (half-width 1.82 r), ours the distance at
#: which the taper vanishes (2 x half-width): loc_rad 4 -> 14.56
PAIRS = [
    (
        "ETKF N=24 infl 1.013",
        "EnKF",
        dict(upd_a="Sqrt", N=24, infl=1.013, rot=True),
        "etkf",
        dict(n_particles=24, inflation=1.013),
    ),
    (
        "EnKF (perturbed obs) N=40 infl 1.06",
        "EnKF",
        dict(upd_a="PertObs", N=40, infl=1.06),
        "enkf",
        dict(n_particles=40, inflation=1.06),
    ),
    (
        "LETKF N=7 infl 1.04 loc 4 (ours: radius 14.56)",
        "LETKF",
        dict(N=7, infl=1.04, rot=True, loc_rad=4),
        "letkf",
        dict(n_particles=7, inflation=1.04, radius=2 * 1.82 * 4),
    ),
    (
        "LETKF N=20 infl 1.02 loc 4 (ours: radius 14.56)",
        "LETKF",
        dict(N=20, infl=1.02, rot=True, loc_rad=4),
        "letkf",
        dict(n_particles=20, inflation=1.02, radius=2 * 1.82 * 4),
    ),
]
#: DAPPER 1.7.1's published rmse.a for this set-up (mods/Lorenz96/sakov2008.py), where it lists one
PUBLISHED = {
    "ETKF N=24 infl 1.013": 0.18,
    "EnKF (perturbed obs) N=40 infl 1.06": 0.22,
    "LETKF N=7 infl 1.04 loc 4 (ours: radius 14.56)": 0.22,
}


# ------------------------------------------------------------------ the DAPPER side (its own interpreter)
def dapper_worker(inp: str, out: str) -> None:
    """Run DAPPER's methods on the truth/observations of ``inp`` (npz) and save analysis means."""
    import dapper.da_methods as da
    import dapper.mods as modelling
    import numpy as np
    from dapper.mods.Lorenz96 import sakov2008
    from dapper.tools.seeding import set_seed

    data = np.load(inp, allow_pickle=True)
    xx, yy, mean0, prior_var = data["states"], data["observations"], data["mean0"], float(data["prior_var"])
    methods = json.loads(str(data["methods"]))
    B, T1, d = xx.shape
    res = {}
    for label, name, kwargs in methods:
        means, secs = np.empty((B, T1 - 1, d)), 0.0
        for b in range(B):
            HMM = sakov2008.HMM.copy()
            HMM.tseq = modelling.Chronology(0.05, dko=1, Ko=T1 - 2, BurnIn=0)
            HMM.X0 = modelling.GaussRV(mu=mean0[b], C=prior_var)
            set_seed(1000 + b)
            xp = getattr(da, name)(**kwargs)
            t0 = time.perf_counter()
            xp.assimilate(HMM, xx[b], yy[b], liveplots=False)
            secs += time.perf_counter() - t0
            means[b] = xp.stats.mu.a  # (Ko + 1, d): the analysis means at the observation times
        res[label] = dict(means=means, sec_per_step=secs / (B * (T1 - 1)))
    np.savez(
        out,
        **{f"{k}|means": v["means"] for k, v in res.items()},
        **{f"{k}|sec": v["sec_per_step"] for k, v in res.items()},
    )


def run_dapper(python: str, states, observations, mean0, methods):
    import numpy as np

    with tempfile.TemporaryDirectory() as tmp:
        inp, out = os.path.join(tmp, "in.npz"), os.path.join(tmp, "out.npz")
        np.savez(
            inp,
            states=states.numpy(),
            observations=observations.numpy(),
            mean0=mean0.numpy(),
            prior_var=1.0,
            methods=json.dumps(methods),
        )
        env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1", MPLBACKEND="agg")
        subprocess.run(
            [python, str(Path(__file__)), "--dapper-worker", inp, out], check=True, env=env, stdout=subprocess.DEVNULL
        )
        got = np.load(out)
        return {label: (got[f"{label}|means"], float(got[f"{label}|sec"])) for label, _, _ in methods}


# ------------------------------------------------------------------ torchflow's side
def rmse_after(est, truth, burn_in):
    """Per-trial analysis RMSE ``(B,)``: sqrt(mean_j err^2) per step, averaged after ``burn_in``."""
    return (est - truth).square().mean(-1).sqrt()[:, burn_in:].mean(1)


def mean_se(x):
    import torch

    x = torch.as_tensor(x, dtype=torch.float64)
    return float(x.mean()), float(x.std() / x.numel() ** 0.5) if x.numel() > 1 else float("nan")


def run_ours(name, kwargs, model, traj, mean, cov, seed=2):
    """One call per trial (as DAPPER runs); on a GPU the first call of each is untimed (warm-up)."""
    import torch

    from torchflow.core.registry import lookup

    f = lookup("filter", name)(model, **kwargs)
    device = traj.observations.device
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)

    def call(b, steps=None):
        T = traj.observations.shape[1] if steps is None else steps
        return f(
            traj.observations[b : b + 1, :T],
            mean[b : b + 1],
            cov[b : b + 1],
            torch.Generator(device=device).manual_seed(seed + b),
        ).estimates

    if device.type == "cuda":
        call(0, 2)
    sync()
    t0 = time.perf_counter()
    est = torch.cat([call(b) for b in range(traj.observations.shape[0])])
    sync()
    return est.cpu(), (time.perf_counter() - t0) / traj.observations.shape[:2].numel()


def compare(args):
    import torch

    from torchflow.models import Lorenz96

    model = Lorenz96()
    traj = model.simulate(args.trials, args.steps, torch.Generator().manual_seed(args.seed))
    mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator().manual_seed(args.seed + 1))
    truth = traj.states[:, 1:]
    dapper = None
    if args.dapper_python:
        dapper = run_dapper(
            args.dapper_python,
            traj.states,
            traj.observations,
            mean,
            [(label, name, kw) for label, name, kw, _, _ in PAIRS],
        )
    rows = []
    for label, dname, dkw, ours, okw in PAIRS:
        est, sec = run_ours(ours, okw, model, traj, mean, cov)
        per_trial = rmse_after(est, truth, args.burn_in)
        row = dict(
            setting=label,
            ours=mean_se(per_trial),
            ours_trials=per_trial.tolist(),
            ours_sec_per_step=sec,
            published=PUBLISHED.get(label),
        )
        if dapper is not None:
            means, dsec = dapper[label]
            per_trial = rmse_after(torch.as_tensor(means), truth, args.burn_in)
            row.update(dapper=mean_se(per_trial), dapper_trials=per_trial.tolist(), dapper_sec_per_step=dsec)
        rows.append(row)
        print(row, flush=True)
    return rows


def scaling(args):
    import torch

    from torchflow.models import Lorenz96

    rows = []
    device = torch.device(args.device)
    for d in args.dims:
        model = Lorenz96(d=d).to(device)
        trials = 1 if d >= 4000 else 2
        traj = model.simulate(trials, args.scaling_steps, torch.Generator(device=device).manual_seed(args.seed))
        mean, cov = model.initial_belief(traj.states[:, 0], torch.Generator(device=device).manual_seed(args.seed + 1))
        for name, kw in (
            ("etkf", dict(n_particles=28, inflation=1.02)),
            ("letkf", dict(n_particles=20, inflation=1.02, radius=15.0)),
        ):
            est, sec = run_ours(name, kw, model, traj, mean, cov)
            r = mean_se(rmse_after(est, traj.states[:, 1:].cpu(), args.scaling_steps // 4))
            rows.append(dict(d=d, filter=name, trials=trials, rmse=r, sec_per_step=sec, device=str(device)))
            print(rows[-1], flush=True)
    return rows


def write(args, cmp_rows, scale_rows):
    out = Path(args.out)
    fmt = lambda ms: "" if ms is None else f"{ms[0]:.3f} ± {ms[1]:.3f}"
    lines = [
        "# Lorenz-96 (Sakov & Oke 2008): ensemble Kalman filters, torchflow vs DAPPER",
        "",
        f"d = 40, F = 8, dt = 0.05, every coordinate observed, R = I, no model noise; {args.trials} trials x "
        f"{args.steps} steps, analysis RMSE averaged over steps after a burn-in of {args.burn_in}, mean ± standard "
        "error over trials. The same truth and observations (simulated by torchflow) and the same prior "
        "N(x0 + xi, I) per trial for both libraries. Time: seconds per assimilation step of one trial, 1 thread, "
        "on a shared 2-core CPU (other jobs running; DAPPER's time includes its own statistics).",
        "",
        "Command: `python -m experiments.benchmarks.bench_lorenz96 --dapper-python <python with dapper 1.7.1>`",
        "",
        "| setting | torchflow RMSE | DAPPER RMSE (same data) | DAPPER published | torchflow s/step | DAPPER s/step |",
        "|---|---|---|---|---|---|",
    ]
    for r in cmp_rows:
        pub = "" if r["published"] is None else f"{r['published']:.2f}"
        dsec = f"{r['dapper_sec_per_step']:.2e}" if "dapper_sec_per_step" in r else "not run"
        lines.append(
            f"| {r['setting']} | {fmt(r['ours'])} | {fmt(r.get('dapper')) or 'not run'} | {pub} | "
            f"{r['ours_sec_per_step']:.2e} | {dsec} |"
        )
    lines += ["", "Per-trial RMSE (torchflow; DAPPER):", ""]
    for r in cmp_rows:
        trials = lambda key: ", ".join(f"{v:.3f}" for v in r.get(key, [])) or "not run"
        lines.append(f"- {r['setting']}: {trials('ours_trials')}; {trials('dapper_trials')}")
    lines += [
        "",
        "Differences of method (not of data): DAPPER inflates the analysis ensemble and applies a random "
        "rotation (`rot=True`) to the square-root filters' anomalies, ours inflates the forecast anomalies and "
        "uses the symmetric square root; DAPPER's taper radius is where its Gaspari-Cohn taper is exp(-1/2) "
        "(half-width 1.82 r), ours where it vanishes (2 x 1.82 x 4 = 14.56).",
        "",
        f"## d-scaling (CPU, 1 thread; {args.scaling_steps} steps, burn-in {args.scaling_steps // 4})",
        "",
        "| d | filter | trials | RMSE | s/step |",
        "|---|---|---|---|---|",
    ]
    for r in scale_rows:
        lines.append(f"| {r['d']} | {r['filter']} | {r['trials']} | {fmt(r['rmse'])} | {r['sec_per_step']:.2e} |")
    lines += [
        "",
        "PF-PF(LEDH) is not in the table: the set-up has no model noise, so the transition density its "
        "weights need does not exist (the filter refuses the model by name).",
    ]
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    out.with_suffix(".json").write_text(
        json.dumps(dict(settings=vars(args), compare=cmp_rows, scaling=scale_rows), indent=1, default=str) + "\n"
    )
    print("\n".join(lines))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dapper-worker", nargs=2, metavar=("IN", "OUT"), help=argparse.SUPPRESS)
    p.add_argument("--dapper-python", default=os.environ.get("DAPPER_PYTHON"))
    p.add_argument("--trials", type=int, default=4)
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--burn-in", type=int, default=200)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--dims", type=int, nargs="*", default=[40, 400, 4000])
    p.add_argument("--scaling-steps", type=int, default=200)
    p.add_argument("--out", default=str(HERE / "results" / "results_lorenz96"))
    p.add_argument("--device", default="cpu", help="the d-scaling's device (cuda: a GPU run of the scaling only)")
    p.add_argument("--scaling-only", action="store_true", help="skip the DAPPER comparison")
    args = p.parse_args(argv)
    if args.dapper_worker:
        return dapper_worker(*args.dapper_worker)
    import torch

    torch.set_num_threads(1)
    if args.scaling_only:
        rows = scaling(args)
        Path(args.out).with_suffix(".json").write_text(
            json.dumps(dict(settings=vars(args), scaling=rows), indent=1, default=str) + "\n"
        )
        for r in rows:
            print(
                f"| {r['d']} | {r['filter']} | {r['trials']} | {r['rmse'][0]:.3f} +- {r['rmse'][1]:.3f} | "
                f"{r['sec_per_step']:.2e} | {r['device']} |",
                flush=True,
            )
        return
    write(args, compare(args), scaling(args))


if __name__ == "__main__":
    sys.exit(main())
