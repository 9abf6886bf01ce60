"""A neural network inside a state-space model, learned end to end through a particle filter.

The acoustic tracking model (Li & Coates' 4 targets, 5 x 5 sensors, sigma_w = 0.1) with its sensor
response ``Psi / (r + d0)`` replaced by a small MLP (:class:`torchflow.models.NeuralAcoustic`,
:class:`~torchflow.models.ResponseMLP` with one hidden layer of 16 tanh units, 49 parameters). The
data come from the true model; the MLP starts from a wrong law (fitted to ``5 / (r + 0.1)^0.75``)
and is learned by maximum likelihood through

* (a) PF-PF(LEDH), N = 100, ``proposal_gradient="score"``, and
* (b) the bootstrap PF, N = 1000,

both with ``resampling_gradient="stop_gradient"``, through
:class:`~torchflow.app.lightning.FilterLightningModule` (Adam, lr 0.02, betas (0.5, 0.9); one optimiser
step per epoch on all training tracks, fresh random numbers each step), each for the same CPU-time
budget (``time.process_time()``, one thread). Snapshots of the MLP are taken at fixed fractions of
the budget and evaluated afterwards on held-out tracks: log-likelihood per step (PF-PF(LEDH),
N = 200, mean of ``--repeats`` runs with the same seeds for every model, with its Monte Carlo
standard error), the OMAT tracking error (Li & Coates' metric: targets matched by the best
assignment, since the measurement cannot tell them apart) and the position RMSE (targets by label,
so a swap counts); the true and the initial model are evaluated the same way.

    python -m experiments.neural_acoustic                 # about 20 CPU-minutes
    python -m experiments.neural_acoustic --quick         # a smoke run (seconds per stage)

Writes ``docs/assets/neural_acoustic.csv`` (learning curves), ``docs/assets/neural_acoustic.png``
(curves and response) and ``experiments/results/neural_acoustic.md`` (the table).
"""

from __future__ import annotations

import argparse
import copy
import csv
import math
import os
import time
from pathlib import Path

# Numba's threading layer otherwise raises torch's intra-op threads to its own count on the first
# flow kernel call (measured here: 1 -> 2), and process time then counts a spinning second thread
os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import torch

from torchflow.core.metrics import omat
from torchflow.filters import BootstrapParticleFilter, ParticleFlowParticleFilter
from torchflow.models import InverseDistance, NeuralAcoustic, ResponseMLP

ROOT = Path(__file__).resolve().parents[1]


def wrong_law(r: torch.Tensor) -> torch.Tensor:
    """The initial response the MLP is fitted to: weaker and decaying more slowly than the truth."""
    return 5.0 / (r + 0.1) ** 0.75


def make_data(args):
    truth = NeuralAcoustic(InverseDistance(10.0, 0.1), n_targets=args.targets, sensor_grid=args.grid)
    out = {}
    for name, seed, B in (("train", 0, args.train_tracks), ("test", 1, args.test_tracks)):
        g = torch.Generator().manual_seed(seed)
        traj = truth.simulate(B, args.steps, g)
        mean, cov = truth.initial_belief(traj.states[:, 0], g)
        out[name] = (traj, mean, cov)
    return truth, out


def initial_model(args) -> NeuralAcoustic:
    model = NeuralAcoustic(ResponseMLP(seed=0), n_targets=args.targets, sensor_grid=args.grid)
    rms = model.response.fit(wrong_law, 60.0)
    print(f"initial MLP fitted to 5 / (r + 0.1)^0.75: rms error of log g {rms:.4f}")
    return model


def make_filter(kind: str, model, n: int):
    if kind == "pfpf_ledh":
        return ParticleFlowParticleFilter(model, flow="ledh", n_particles=n, proposal_gradient="score")
    return BootstrapParticleFilter(model, n_particles=n)


def train(kind: str, n: int, model, data, args):
    """Fit ``model`` through the ``kind`` filter with N = ``n`` for ``args.budget`` CPU seconds;
    returns the snapshots ``[(cpu seconds, optimiser steps, state_dict)]`` and the per-step losses."""
    import pytorch_lightning as pl
    from torch.utils.data import DataLoader

    from torchflow.app.lightning import FilterLightningModule, TrajectoryDataset

    traj, mean, cov = data
    marks = [args.budget * f for f in (0.0, 0.125, 0.25, 0.5, 0.75, 1.0)]
    snaps, losses = [], []

    class Budget(pl.Callback):
        """Stops the fit when the CPU time of training reaches the budget; snapshots the model at
        the marks (the copies' own time is not counted)."""

        def on_train_start(self, trainer, module):
            self.t0, self.paused, self.steps = time.process_time(), 0.0, 0
            self._snap(0.0)

        def _snap(self, used):
            t = time.process_time()
            while marks and marks[0] <= used + 1e-9:
                marks.pop(0)
                snaps.append((used, self.steps, copy.deepcopy(model.state_dict())))
            self.paused += time.process_time() - t

        def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
            self.steps += 1
            used = time.process_time() - self.t0 - self.paused
            losses.append((self.steps, used, float(outputs["loss"])))
            if used >= args.budget:
                marks[:] = [used]  # the last snapshot: where the budget ran out
                trainer.should_stop = True
            self._snap(used)

    module = FilterLightningModule(
        make_filter(kind, model, n), lr=args.lr, betas=(0.5, 0.9), lr_decay=args.lr_decay, seed=args.seed
    )
    trainer = pl.Trainer(
        max_epochs=100000,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        accelerator="cpu",
        devices=1,
        callbacks=[Budget()],
    )
    trainer.fit(module, DataLoader(TrajectoryDataset(traj, mean, cov), batch_size=traj.observations.shape[0]))
    print(f"{kind} N={n}: {losses[-1][0]} steps in {losses[-1][1]:.1f} CPU s; last nll/step {losses[-1][2]:.2f}")
    return snaps, losses


def evaluate(model, data, args):
    """Held-out log-likelihood per step, OMAT and position RMSE: one value each per repeat (means over
    tracks and steps)."""
    traj, mean, cov = data
    flt = ParticleFlowParticleFilter(model, flow="ledh", n_particles=args.eval_particles)
    T = traj.observations.shape[1]
    true_pos = model.positions(traj.states[:, 1:])
    lls, omats, rmses = [], [], []
    with torch.no_grad():
        for s in range(args.repeats):
            out = flt(traj.observations, mean, cov, torch.Generator().manual_seed(1000 + s))
            pos = model.positions(out.estimates)
            lls.append(float(out.log_evidence.mean()) / T)
            omats.append(float(omat(pos, true_pos).mean()))
            rmses.append(float((pos - true_pos).pow(2).sum(-1).mean().sqrt()))
    return lls, omats, rmses


def mean_se(v):
    m = sum(v) / len(v)
    sd = math.sqrt(sum((x - m) ** 2 for x in v) / (len(v) - 1)) if len(v) > 1 else float("nan")
    return m, sd / math.sqrt(len(v))


def response_error(model, truth) -> float:
    """RMS error of ``log g`` against the truth over r in [0.5, 50] (log-spaced)."""
    r = torch.logspace(math.log10(0.5), math.log10(50.0), 200, dtype=torch.float64)
    with torch.no_grad():
        return float((model.response(r).log() - truth.response(r).log()).pow(2).mean().sqrt())


def figure(rows, curves, out_png):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 4.2))
    colours = {"pfpf_ledh": "C0", "bpf": "C3"}
    for label, key in (("held-out log-likelihood per step", "ll"), ("held-out OMAT error (m)", "omat")):
        a = ax[0] if key == "ll" else ax[1]
        for method in ("pfpf_ledh", "bpf"):
            rs = [r for r in rows if r["method"] == method]
            a.errorbar(
                [r["cpu_s"] for r in rs],
                [r[key] for r in rs],
                yerr=[r[key + "_se"] for r in rs],
                marker="o",
                capsize=3,
                color=colours[method],
                label=rs[0]["label"],
            )
        for method, style in (("truth", "k--"), ("initial", "k:")):
            r = next(r for r in rows if r["method"] == method)
            a.axhline(r[key], color=style[0], linestyle=style[1:], label=r["label"])
        a.set_xlabel("training CPU seconds (1 thread)")
        a.set_ylabel(label)
        a.grid(alpha=0.3)
    ax[0].legend(fontsize=8)
    r = torch.logspace(math.log10(0.1), math.log10(57.0), 300, dtype=torch.float64)
    for name, (model, style) in curves.items():
        with torch.no_grad():
            ax[2].loglog(r.numpy(), model.response(r).numpy(), style, label=name)
    ax[2].set_xlabel("distance r (m)")
    ax[2].set_ylabel("per-target sensor response g(r)")
    ax[2].legend(fontsize=8)
    ax[2].grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(out_png, dpi=110)
    print(f"wrote {out_png}")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--budget", type=float, default=240.0, help="training CPU seconds per filter")
    p.add_argument("--targets", type=int, default=4)
    p.add_argument("--grid", type=int, default=5)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--train-tracks", type=int, default=4)
    p.add_argument("--test-tracks", type=int, default=4)
    p.add_argument("--pfpf-particles", type=int, default=100)
    p.add_argument("--bpf-particles", type=int, default=1000)
    p.add_argument("--eval-particles", type=int, default=200)
    p.add_argument("--repeats", type=int, default=4)
    p.add_argument("--lr", type=float, default=0.02)
    p.add_argument("--lr-decay", type=float, default=1.0, help="the learning rate's factor after every step")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quick", action="store_true", help="a smoke run: tiny sizes and budget")
    p.add_argument("--out", default=str(ROOT / "docs" / "assets"))
    p.add_argument("--table", default=str(ROOT / "experiments" / "results" / "neural_acoustic.md"))
    args = p.parse_args(argv)
    if args.quick:
        args.budget, args.targets, args.grid, args.steps = 4.0, 2, 3, 8
        args.pfpf_particles, args.bpf_particles, args.eval_particles, args.repeats = 20, 200, 50, 2
    torch.set_num_threads(1)
    start = time.process_time()
    truth, data = make_data(args)
    init = initial_model(args)
    rows = []

    def record(method, label, model, cpu_s=float("nan"), step=0):
        lls, omats, rmses = evaluate(model, data["test"], args)
        (ll, ll_se), (om, om_se), (rmse, rmse_se) = mean_se(lls), mean_se(omats), mean_se(rmses)
        rows.append(
            dict(
                method=method,
                label=label,
                step=step,
                cpu_s=cpu_s,
                ll=ll,
                ll_se=ll_se,
                omat=om,
                omat_se=om_se,
                rmse=rmse,
                rmse_se=rmse_se,
                log_response_rms=response_error(model, truth),
                ll_repeats=" ".join(f"{v:.3f}" for v in lls),
            )
        )
        print(
            f"{label:>28} step {step:4d} cpu {cpu_s:7.1f}: ll/step {ll:8.2f} ± {ll_se:.2f} ({rows[-1]['ll_repeats']}), "
            f"OMAT {om:.3f} ± {om_se:.3f}, RMSE {rmse:.3f} ± {rmse_se:.3f}, "
            f"log-response error {rows[-1]['log_response_rms']:.3f}",
            flush=True,
        )

    record("truth", "true response", truth)
    record("initial", "initial (wrong) response", init)
    finals = {}
    train_cpu = {}
    for kind, n, label in (
        ("pfpf_ledh", args.pfpf_particles, f"PF-PF(LEDH) N={args.pfpf_particles}"),
        ("bpf", args.bpf_particles, f"BPF N={args.bpf_particles}"),
    ):
        model = copy.deepcopy(init)
        snaps, losses = train(kind, n, model, data["train"], args)
        train_cpu[kind] = losses[-1][1]
        for cpu_s, step, state in snaps:
            if step == 0:  # the initial model, evaluated above
                rows.append(
                    {**next(r for r in rows if r["method"] == "initial"), "method": kind, "label": label, "cpu_s": 0.0}
                )
                continue
            model.load_state_dict(state)
            record(kind, label, model, cpu_s, step)
        finals[label] = copy.deepcopy(model)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = "neural_acoustic_quick" if args.quick else "neural_acoustic"
    with open(out / f"{stem}.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    curves = {"truth 10 / (r + 0.1)": (truth, "k-"), "initial MLP (fitted to 5 / (r + 0.1)^0.75)": (init, "k:")}
    for (label, model), style in zip(finals.items(), ("C0-", "C3--")):
        curves[f"learned through {label}"] = (model, style)
    figure(rows, curves, out / f"{stem}.png")
    lines = [
        f"Sizes: {args.targets} targets x {args.grid**2} sensors, T = {args.steps}, {args.train_tracks} "
        f"training and {args.test_tracks} held-out tracks; budget {args.budget:g} CPU s per filter; evaluation "
        f"PF-PF(LEDH) N = {args.eval_particles}, {args.repeats} repeats (SE over repeats).",
        "",
        "| model | optimiser steps | training CPU s | held-out log-lik / step | OMAT (m) | position RMSE (m) | "
        "log-response RMS error |",
        "|---|---|---|---|---|---|---|",
    ]
    for method in ("truth", "initial", "pfpf_ledh", "bpf"):  # the references; each fit at half and all its budget
        rs = [r for r in rows if r["method"] == method]
        for r in rs if len(rs) == 1 else [rs[len(rs) // 2], rs[-1]]:
            cpu = "-" if math.isnan(r["cpu_s"]) else f"{r['cpu_s']:.0f}"
            steps = "-" if len(rs) == 1 else str(r["step"])
            lines.append(
                f"| {r['label']} | {steps} | {cpu} | {r['ll']:.2f} ± {r['ll_se']:.2f} | "
                f"{r['omat']:.2f} ± {r['omat_se']:.2f} | {r['rmse']:.2f} ± {r['rmse_se']:.2f} | "
                f"{r['log_response_rms']:.3f} |"
            )
    text = "\n".join(lines) + "\n"
    print(text)
    if not args.quick:
        Path(args.table).parent.mkdir(parents=True, exist_ok=True)
        Path(args.table).write_text(text)
    print(f"total CPU s of this run (training, evaluation): {time.process_time() - start:.0f}")


if __name__ == "__main__":
    main()
