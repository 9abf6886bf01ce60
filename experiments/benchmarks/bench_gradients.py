"""Gradient quality and cost through particle filters: bias and spread of the gradient of
the log-evidence against the Kalman filter's exact gradient, per resampling-gradient estimator, filter
and particle count, and what the backward pass costs.

    python -m experiments.benchmarks.bench_gradients --estimators none,stop_gradient,soft   # ~15 min, 2 cores
    python -m experiments.benchmarks.bench_gradients --d 8 --n 100,1000 --memory-n 0       # where it breaks
    python -m experiments.benchmarks.bench_gradients --quick
    python -m experiments.benchmarks.bench_gradients --write-problem experiments/benchmarks/results/gradients_problem.pt

``--params F``: the gradient with respect to F alone (as the PyDPF peer script measures it).
``--write-problem PATH`` only saves the d = ``--d``, T = ``--steps`` problem (F, Q, R, H, observations,
prior, the Kalman log-evidence and its gradient with respect to F) for the peer script
``peer_pydpf_gradients.py``, which runs where PyDPF installs (Python >= 3.12) and needs no torchflow.

Model: linear-Gaussian (``--d``, default 2), T = 20, F, Q and R learnable (Q and R through their
Cholesky parametrisation): at d = 2, 12 gradient entries, 10 of them non-zero (the raw upper triangles of Q and R
have none). One simulated trajectory; every run
filters it afresh. Per cell, ``reps`` repetitions of the mean over ``trials`` runs of
``grad log Z_hat`` (what an optimiser follows). ``bias``: the Euclidean norm of (mean - exact);
``max |t|``: the largest entry of (mean - exact) / SE, SE from the repetitions (|t| > 4 is a
bias beyond Monte Carlo error); ``sd/run``: the Euclidean norm of the per-run standard deviation
(repetition sd x sqrt(trials)); ``|exact|``: the norm of the Kalman gradient for scale.
``fwd`` and ``fwd+bwd``: seconds per trial-step of one call (forward under no_grad; forward with
autograd plus backward), ``saved MB/trial``: bytes autograd keeps for the backward pass, per trial,
counted by a ``saved_tensors_hooks`` (an upper estimate: views counted each time). ``ot`` at N = 10^4
would need 0.8 GB per trial for its plan: skipped (``--ot-max-n``, which also bounds ``marginal``).
``marginal``: marginal weights (``weights="marginal"``) with ``proposal_gradient="score"`` and
``stop_gradient`` resampling, the O(N^2) score estimator of :mod:`torchflow.filters.marginal`.

Memory (``--memory-n``, default 10^4; 0: none): the peak resident memory that one forward + backward
pass of ``--memory-trials`` trials adds, with and without ``checkpoint_steps`` (each time step
recomputed in the backward pass), measured as the growth of the peak resident set (``VmHWM``) in a
fresh process per cell, with its seconds.
"""

from __future__ import annotations

import json
import math
import resource
import subprocess
import sys
import time

import torch

from torchflow.filters import BootstrapParticleFilter, KalmanFilter, ParticleFlowParticleFilter
from torchflow.flows.schedules import ExponentialSchedule
from torchflow.models import LinearGaussian

from . import harness as h

ESTIMATORS = ("none", "stop_gradient", "soft", "ot", "marginal")
FILTERS = {"bpf": "BPF", "ledh": "PF-PF(LEDH)"}


def problem(T: int, d: int = 2):
    """A stable linear-Gaussian model with learnable F, Q, R and one simulated trajectory of T steps:
    ``(model, observations (1, T, d), mean (1, d), cov (1, d, d))``; the same for the tests."""
    eye = torch.eye(d, dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    F = 0.9 * eye + 0.05 * torch.randn(d, d, generator=g, dtype=torch.float64)
    truth = LinearGaussian(F, 0.5 * eye, eye, 0.5 * eye, torch.zeros(d, dtype=torch.float64), eye)
    traj = truth.simulate(1, T, torch.Generator().manual_seed(1))
    mean, cov = truth.initial_belief(traj.states[:, 0])
    model = LinearGaussian(
        F.clone(), 0.5 * eye, eye, 0.5 * eye, torch.zeros(d, dtype=torch.float64), eye, learnable=["F", "Q", "R"]
    )
    return model, traj.observations, mean, cov


def _flat(grads):
    return torch.cat([g.flatten() for g in grads])


def _filter(kind: str, model, n: int, est: str):
    # "marginal": marginal weights with the proposal held constant and stop_gradient resampling,
    # the O(N^2) score estimator (torchflow.filters.marginal)
    kw = (
        dict(n_particles=n, weights="marginal", proposal_gradient="score")
        if est == "marginal"
        else dict(n_particles=n, resampling_gradient=est, ot_iterations=50)
    )
    if kind == "bpf":
        return BootstrapParticleFilter(model, **kw)
    return ParticleFlowParticleFilter(model, flow="ledh", schedule=ExponentialSchedule(10, 1.2), **kw)


def _params(model, which: str):
    """What the gradient is taken with respect to: ``"all"`` (F and the raw Q, R) or ``"F"``."""
    return [model.F] if which == "F" else list(model.parameters())


def _cell(kind, est, n, model, obs, mean, cov, exact, trials, reps, d, which="all"):
    params = _params(model, which)
    f = _filter(kind, model, n, est)
    o, m, c = (t.expand(trials, *t.shape[1:]).contiguous() for t in (obs, mean, cov))
    T = obs.shape[1]
    means, fb = [], []
    for r in range(reps):
        t0 = time.perf_counter()
        le = f(o, m, c, torch.Generator().manual_seed(1000 + r)).log_evidence
        g = torch.autograd.grad(le.mean(), params)
        fb.append((time.perf_counter() - t0) / (trials * T))
        means.append(_flat(g))
    G = torch.stack(means)
    keep = exact != 0
    mu, sd = G.mean(0)[keep], G.std(0)[keep]
    with torch.no_grad():
        t0 = time.perf_counter()
        f(o, m, c, torch.Generator().manual_seed(7))
        fwd = (time.perf_counter() - t0) / (trials * T)
    saved = [0]

    def pack(t):
        saved[0] += t.numel() * t.element_size()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        f(o[:1], m[:1], c[:1], torch.Generator().manual_seed(8))
    return dict(
        filter=FILTERS[kind],
        estimator=est,
        d=d,
        N=n,
        trials=trials,
        reps=reps,
        bias=float((mu - exact[keep]).norm()),
        max_t=float(((mu - exact[keep]) / (sd / math.sqrt(reps))).abs().max()),
        sd_run=float((sd * math.sqrt(trials)).norm()),
        exact_norm=float(exact.norm()),
        fwd=fwd,
        fwd_bwd=sorted(fb)[len(fb) // 2],
        saved_mb=saved[0] / 1e6,
    )


def write_problem(path: str, steps: int, d: int) -> dict:
    """Save :func:`problem` with its exact log-evidence and gradient with respect to F (for peers)."""
    model, obs, mean, cov = problem(steps, d)
    log_z = KalmanFilter(model)(obs, mean, cov).log_evidence.sum()
    (grad_f,) = torch.autograd.grad(log_z, [model.F])
    data = {k: v.detach().clone() for k, v in dict(F=model.F, Q=model.Q, R=model.R, H=model.H).items()}
    data.update(obs=obs, mean=mean, cov=cov, log_z=log_z.detach(), grad_F=grad_f)
    torch.save(data, path)
    print(f"wrote {path}: d = {d}, T = {steps}, log Z = {float(log_z):.6f}")
    return dict(markdown="", rows=[], path=path)


def peak_child(kind: str, n: int, trials: int, steps: int, d: int, ckpt: bool) -> dict:
    """In this process: the growth of the peak resident memory (MB) over one forward + backward
    pass, and its seconds (run by :func:`_peak` in a fresh process per cell)."""
    model, obs, mean, cov = problem(steps, d)
    f = _filter(kind, model, n, "stop_gradient")
    o, m, c = (t.expand(trials, *t.shape[1:]).contiguous() for t in (obs, mean, cov))
    le = f(o[:1, :2], m[:1], c[:1], torch.Generator().manual_seed(0)).log_evidence  # warm the code paths
    torch.autograd.grad(le.sum(), list(model.parameters()))
    before = _hwm_kb()
    t0 = time.perf_counter()
    le = f(o, m, c, torch.Generator().manual_seed(1), checkpoint_steps=ckpt).log_evidence
    torch.autograd.grad(le.mean(), list(model.parameters()))
    sec = time.perf_counter() - t0
    return dict(peak_mb=(_hwm_kb() - before) / 1024, seconds=sec)


def _hwm_kb() -> int:
    """This process's peak resident set in kB: ``VmHWM`` of /proc/self/status where it exists (not
    ``ru_maxrss``, which a process started by ``fork`` + ``exec`` inherits from its parent)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def _peak(kind, n, trials, steps, d, ckpt, threads) -> dict:
    code = (
        "import json, torch; torch.set_num_threads(%d); from experiments.benchmarks.bench_gradients import "
        "peak_child; print(json.dumps(peak_child(%r, %d, %d, %d, %d, %r)))" % (threads, kind, n, trials, steps, d, ckpt)
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=h.HERE.parent.parent, capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"bench_gradients: the memory cell {kind} N={n} failed:\n{out.stderr[-2000:]}")
    return dict(
        filter=FILTERS[kind],
        N=n,
        trials=trials,
        d=d,
        checkpoint_steps=ckpt,
        **json.loads(out.stdout.strip().splitlines()[-1]),
    )


def run(argv=None) -> dict:
    a = h.options(
        __doc__,
        argv,
        dict(n="100,1000", trials=8, reps=4, steps=10, memory_n=2000),
        n="100,1000,10000",
        trials=20,
        reps=10,
        steps=20,
        threads=2,
        filters="bpf,ledh",
        estimators=",".join(ESTIMATORS),
        d=2,
        ot_max_n=2000,
        memory_n=10000,
        memory_trials=8,
        write_problem="",
        params="all",
    )
    if a.params not in ("all", "F"):
        raise SystemExit(f"--params: expected all or F, got {a.params!r}")
    ns = h.ints(a.n, "--n")
    kinds = h.keys_option(a.filters, FILTERS, "--filters")
    ests = h.keys_option(a.estimators, ESTIMATORS, "--estimators")
    d = h.ints(a.d, "--d")[0]
    if a.write_problem:
        return write_problem(a.write_problem, a.steps, d)
    rows, memory = [], []
    with h.session("bench_gradients", argv, a.threads) as info:
        model, obs, mean, cov = problem(a.steps, d)
        log_z = KalmanFilter(model)(obs, mean, cov).log_evidence.sum()
        exact = _flat(torch.autograd.grad(log_z, _params(model, a.params)))
        for kind in kinds:
            for n in ns:
                for est in ests:
                    if est in ("ot", "marginal") and n > a.ot_max_n:
                        continue  # O(N^2) per trial-step: the (N, N) plan is 0.8 GB per trial at N = 1e4
                    big = n >= 10_000
                    trials, reps = (max(2, a.trials // 4), max(3, a.reps // 2)) if big else (a.trials, a.reps)
                    rows.append(_cell(kind, est, n, model, obs, mean, cov, exact, trials, reps, d, a.params))
                    print(rows[-1], flush=True)
        for kind in kinds if a.memory_n else ():
            for ckpt in (False, True):
                memory.append(_peak(kind, int(a.memory_n), int(a.memory_trials), a.steps, d, ckpt, a.threads))
                print(memory[-1], flush=True)
    head = [
        "filter",
        "estimator",
        "d",
        "N",
        "runs",
        "bias",
        "max abs t",
        "sd/run",
        "abs exact",
        "fwd s/ts",
        "fwd+bwd s/ts",
        "bwd/fwd",
        "saved MB/trial",
    ]
    table = [
        (
            r["filter"],
            r["estimator"],
            r["d"],
            r["N"],
            r["trials"] * r["reps"],
            h.fmt(r["bias"]),
            h.fmt(r["max_t"], "{:.1f}"),
            h.fmt(r["sd_run"]),
            h.fmt(r["exact_norm"]),
            h.fmt(r["fwd"]),
            h.fmt(r["fwd_bwd"]),
            h.fmt(r["fwd_bwd"] / r["fwd"], "{:.1f}"),
            h.fmt(r["saved_mb"]),
        )
        for r in rows
    ]
    more = []
    if memory:
        more = [
            f"Peak memory of one forward + backward pass ({a.memory_trials} trials, T = {a.steps}, d = {d}, "
            "stop_gradient), growth of the peak resident set in a fresh process:",
            "",
        ] + h.md_table(
            ["filter", "N", "checkpoint_steps", "peak MB", "seconds"],
            [
                (r["filter"], r["N"], r["checkpoint_steps"], h.fmt(r["peak_mb"], "{:.0f}"), h.fmt(r["seconds"]))
                for r in memory
            ],
        )
    md = h.report(
        "# Gradients through particle filters: bias, spread, cost",
        a,
        info,
        [
            f"Linear-Gaussian d = {d}, T = {a.steps}; gradient with respect to "
            f"{'F alone' if a.params == 'F' else 'F and the raw Cholesky parameters of Q and R'}; "
            "exact gradient: the Kalman filter's (autograd). "
            "See the module docstring for the columns. N = 10^4 cells use a quarter of the trials and half "
            "the repetitions."
        ],
        head,
        table,
        *more,
    )
    return dict(markdown=md, rows=rows, memory=memory, machine=info, args=vars(a))


if __name__ == "__main__":
    if any(a.startswith("--write-problem") for a in sys.argv[1:]):
        run(sys.argv[1:])  # the problem file only: no results files
    else:
        h.main(run, "gradients")
