"""The gradient of the log-evidence with respect to the transition matrix F through the peer library
PyDPF's differentiable particle filters, on the linear-Gaussian problem of ``gradients_problem.pt``
(written by ``python -m experiments.benchmarks.bench_gradients --write-problem ...``: d = 2, T = 20),
for comparison with ``bench_gradients`` (torchflow's estimators).

Run with a Python that has PyDPF (it does not need torchflow), from the repository root:

    python experiments/benchmarks/peer_pydpf_gradients.py [--n 100,1000] [--trials 20] [--reps 10]
        [--threads 2] [--out experiments/benchmarks/results/results_peer_pydpf.md]

Model (the torchflow convention): ``x_0 ~ N(mean, cov)``; for t = 1..T: ``x_t = F x_{t-1} + N(0, Q)``,
``z_t = H x_t + N(0, R)`` with ``z_t = obs[0, t-1]``; ``log Z = sum_t log p(z_t | z_{1:t-1})``; x_0 is not
observed. PyDPF's filters (and its Kalman filter) weigh the first state they draw, from the prior,
with the first observation. So PyDPF is given, as its prior, the law of ``x_1``: a draw ``x_0 ~ N(mean, cov)``
pushed through ``x_1 = F x_0 + chol(Q) v`` inside the autograd graph (:class:`PredictedPrior`), so
that F's gradient flows through the first step exactly as it does in a filter that starts at x_0;
PyDPF's time 0 is our t = 1 and ``time_extent = T - 1``. No resampling happens between x_0 and x_1
(there is none in torchflow either: the weights are uniform there).

Before the benchmark the script checks the convention, and asserts: PyDPF's ``KalmanFilter`` (prior
``N(F mean, F cov F^T + Q)`` built from the F parameter) must reproduce ``log_z`` and ``grad_F`` of
the problem file, and a large-N PyDPF particle filter (``--check-n``) its ``log_z`` to Monte Carlo
error.

Estimators (PyDPF's classes that correspond to torchflow's ``resampling_gradient``), all resampling
multinomially at every step (PyDPF's ``ParticleFilter`` resamples unconditionally; torchflow's BPF
rows resample multinomially at ESS < N/2):

* ``none``: ``StraightThroughDPF(multinomial=True)``: particles gathered by the drawn indices (the
  gradient flows through their positions), new log-weights the constant ``-log N``, no term for the
  ancestor draw. (PyDPF's ``DPF`` is another thing, it detaches the particles and weights at every
  step: ``--estimators dpf_detach``.)
* ``stop_gradient``: ``StopGradientDPF(multinomial=True)`` (Scibior & Wood 2021): the log-weight of a
  resampled particle gains ``log W_a - stop_gradient(log W_a)``.
* ``soft``: ``SoftDPF(softness=alpha, multinomial=True)``: ancestors drawn from
  ``alpha W + (1 - alpha) / N``, weighted ``W_a / q_a`` (PyDPF leaves these weights unnormalised;
  torchflow normalises them).
* ``ot``: ``OptimalTransportDPF(regularisation=epsilon, max_iterations=iterations)``, the other knobs
  PyDPF's defaults (``decay_rate`` 0.9: epsilon-scaling from the squared extent of the scaled cloud,
  ``min_update_size`` 0.01: early stop, ``transport_gradient_clip`` 1.0: each entry of the gradient with
  respect to the transport matrix clipped). PyDPF scales the centred particles by their largest
  unweighted standard deviation times sqrt(d); torchflow by the largest weighted standard deviation,
  so the same epsilon is a somewhat different blur. Skipped above ``--ot-max-n``.

Extra rows on request (``--estimators``): ``dpf_detach`` (``DPF``), ``marginal_stop_gradient``
(``MarginalStopGradientDPF``, O(N^2)).

Columns as in ``bench_gradients``: per cell, ``reps`` repetitions, each the gradient with respect to
F of the mean over ``trials`` runs (batched as PyDPF batches) of ``log Z_hat``. ``bias``: the
Euclidean norm of (mean over repetitions - grad_F); ``max |t|``: the largest entry of
``|mean - grad_F| / (sd / sqrt(reps))``; ``sd/run``: the norm of the per-run standard deviation
(repetition sd x sqrt(trials)); ``|exact|``: the norm of grad_F. ``fwd s/ts``: seconds per
trial-step of a forward pass under ``torch.no_grad`` (median of ``--fwd-reps`` calls);
``fwd+bwd s/ts``: of forward with autograd plus backward (median over the repetitions).
All trials of a repetition run in one batched call, except for ``ot`` (and ``marginal_stop_gradient``)
where that would not fit ``--mem-gb`` (default 6 GB; ot keeps ~1.3 kB x N^2 per trial for the
backward pass, 25 GB for 20 trials at N = 1000): their trials run in several batched calls, and the
gradient of the mean over all trials is accumulated; the runs column then says how many per call.

The log-likelihood factors come from ``pydpf.LogLikelihoodFactors`` (PyDPF's ``SIS`` stores the
aggregated outputs in a float32 buffer; its gradient passes back in float64, the float32 rounding
of the forward value is ~1e-7 relative and only touches the printed log-likelihoods).
``NegLogDataLikelihood_Loss`` is a kernel-density loss against a ground-truth state, not the
log-evidence, so it is not used.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import sys
import time
import warnings
from pathlib import Path

import torch

# Before importing PyDPF: its class-level constants (log 2 pi) and its normal draws use the default
# dtype, and everything here is float64.
torch.set_default_dtype(torch.float64)
with warnings.catch_warnings():
    warnings.simplefilter("ignore")  # PyDPF warns that it found no CUDA device
    import pydpf

try:
    from importlib.metadata import version as _version

    PYDPF_VERSION = _version("pydpf")
except Exception:  # pragma: no cover
    PYDPF_VERSION = getattr(pydpf, "__version__", "unknown")

DTYPE = torch.float64
DEFAULT_ESTIMATORS = ("none", "stop_gradient", "soft", "ot")
EXTRA_ESTIMATORS = ("dpf_detach", "marginal_stop_gradient")


class PredictedPrior(pydpf.Module):
    """PyDPF prior model whose draws are ``x_1 = F x_0 + chol(Q) v``, ``x_0 ~ N(mean, cov)``: the law of
    the first observed state, built from the F parameter on every call so that its gradient flows
    through the first step (a reparameterised draw, as in a filter that starts at x_0)."""

    def __init__(
        self, F: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor, Q: torch.Tensor, generator: torch.Generator
    ):
        super().__init__()
        self.F = F
        self.m0 = mean
        self.L0 = torch.linalg.cholesky(cov)
        self.LQ = torch.linalg.cholesky(Q)
        self.Q = Q
        self.cov0 = cov
        self.generator = generator

    def sample(self, batch_size: int, n_particles: int, **data) -> torch.Tensor:
        d = self.m0.shape[-1]
        u = torch.randn((batch_size, n_particles, d), generator=self.generator, dtype=DTYPE)
        v = torch.randn((batch_size, n_particles, d), generator=self.generator, dtype=DTYPE)
        x0 = self.m0 + u @ self.L0.T
        return x0 @ self.F.T + v @ self.LQ.T

    def log_density(self, state: torch.Tensor, **data) -> torch.Tensor:
        """``log N(state; F mean, F cov F^T + Q)`` (unused by the bootstrap filters benchmarked here)."""
        m1 = self.F @ self.m0
        P1 = self.F @ self.cov0 @ self.F.T + self.Q
        return torch.distributions.MultivariateNormal(m1, covariance_matrix=P1).log_prob(state)


def load_problem(path: str) -> dict:
    P = torch.load(path)
    P = {k: (v.to(DTYPE) if torch.is_tensor(v) else v) for k, v in P.items()}
    for k in ("F", "Q", "R", "H", "obs", "mean", "cov", "log_z", "grad_F"):
        if k not in P:
            raise KeyError(f"{path}: missing {k!r}")
    return P


def time_major(obs: torch.Tensor, trials: int) -> torch.Tensor:
    """``obs (1, T, d)`` -> PyDPF's time-major ``(T, trials, d)``, the same sequence in every trial."""
    o = obs[0]
    return o.unsqueeze(1).expand(o.shape[0], trials, o.shape[1]).contiguous()


def build_ssm(P: dict, F: torch.Tensor, g: torch.Generator):
    d = F.shape[0]
    zero = torch.zeros(d, dtype=DTYPE)
    dyn = pydpf.LinearGaussian(weight=F, bias=zero, cholesky_covariance=torch.linalg.cholesky(P["Q"]), generator=g)
    obs = pydpf.LinearGaussian(
        weight=P["H"], bias=zero.clone(), cholesky_covariance=torch.linalg.cholesky(P["R"]), generator=g
    )
    prior = PredictedPrior(F, P["mean"][0], P["cov"][0], P["Q"], g)
    return pydpf.FilteringModel(dynamic_model=dyn, observation_model=obs, prior_model=prior)


def build_filter(est: str, ssm, g: torch.Generator, a):
    if est == "none":
        return pydpf.StraightThroughDPF(ssm, resampling_generator=g, multinomial=True)
    if est == "stop_gradient":
        return pydpf.StopGradientDPF(ssm, resampling_generator=g, multinomial=True)
    if est == "soft":
        return pydpf.SoftDPF(ssm, softness=a.soft_alpha, resampling_generator=g, multinomial=True)
    if est == "ot":
        return pydpf.OptimalTransportDPF(
            ssm, regularisation=a.ot_epsilon, max_iterations=a.ot_iterations, transport_gradient_clip=a.ot_clip
        )
    if est == "dpf_detach":
        return pydpf.DPF(ssm, resampling_generator=g, multinomial=True)
    if est == "marginal_stop_gradient":
        return pydpf.MarginalStopGradientDPF(ssm, resampling_generator=g, multinomial=True)
    raise ValueError(f"unknown estimator {est!r}")


CLASS_OF = {
    "none": "StraightThroughDPF(multinomial=True)",
    "stop_gradient": "StopGradientDPF(multinomial=True)",
    "soft": "SoftDPF(softness={alpha}, multinomial=True)",
    "ot": "OptimalTransportDPF(regularisation={eps}, max_iterations={iters}, decay_rate=0.9, min_update_size=0.01, "
    "transport_gradient_clip={clip})",
    "dpf_detach": "DPF(multinomial=True)",
    "marginal_stop_gradient": "MarginalStopGradientDPF(multinomial=True)",
}


def log_evidence(pf, n: int, obs_tb: torch.Tensor) -> torch.Tensor:
    """``(trials,)`` estimates of log Z: the sum of PyDPF's per-step log-likelihood factors."""
    T = obs_tb.shape[0]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = pf(
            n_particles=n, time_extent=T - 1, aggregation_function=pydpf.LogLikelihoodFactors(), observation=obs_tb
        )
    if out.shape[0] != T:  # PyDPF stops early (with a warning) when every weight of a trial vanishes
        raise RuntimeError(
            f"PyDPF stopped after {out.shape[0]} of {T} steps: " + "; ".join(str(w.message) for w in caught)
        )
    return out.to(DTYPE).sum(0)


def kalman_check(P: dict) -> dict:
    """PyDPF's Kalman filter with the predicted prior, built from F: log Z and its gradient."""
    F = torch.nn.Parameter(P["F"].clone())
    g = torch.Generator().manual_seed(0)
    d = F.shape[0]
    m1 = F @ P["mean"][0]
    P1 = F @ P["cov"][0] @ F.T + P["Q"]
    prior = pydpf.MultivariateGaussian(mean=m1, cholesky_covariance=torch.linalg.cholesky(P1), generator=g)
    zero = torch.zeros(d, dtype=DTYPE)
    dyn = pydpf.LinearGaussian(weight=F, bias=zero, cholesky_covariance=torch.linalg.cholesky(P["Q"]), generator=g)
    obs = pydpf.LinearGaussian(
        weight=P["H"], bias=zero.clone(), cholesky_covariance=torch.linalg.cholesky(P["R"]), generator=g
    )
    kf = pydpf.KalmanFilter(prior_model=prior, dynamic_model=dyn, observation_model=obs)
    obs_tb = time_major(P["obs"], 1)
    _, _, factors = kf(time_extent=obs_tb.shape[0] - 1, observation=obs_tb)
    log_z = factors.sum()
    (grad,) = torch.autograd.grad(log_z, F)
    log_z = log_z.item()
    return dict(
        log_z=log_z,
        grad_F=grad.tolist(),
        log_z_err=abs(log_z - float(P["log_z"])),
        grad_err=float((grad - P["grad_F"]).abs().max()),
    )


def particle_check(P: dict, n: int, trials: int, seed: int) -> dict:
    """A large-N PyDPF bootstrap filter (multinomial, every step) under no_grad: mean log Z_hat."""
    F = torch.nn.Parameter(P["F"].clone())
    g = torch.Generator().manual_seed(seed)
    pf = pydpf.StopGradientDPF(build_ssm(P, F, g), resampling_generator=g, multinomial=True)
    with torch.no_grad():
        lz = log_evidence(pf, n, time_major(P["obs"], trials))
    mean = float(lz.mean())
    sd = float(lz.std()) if trials > 1 else float("nan")
    se = sd / math.sqrt(trials)
    # E[log Z_hat] ~ log Z - Var/2 (Jensen): allow that on top of 5 standard errors
    tol = 5 * se + 0.5 * sd**2
    return dict(N=n, trials=trials, mean=mean, se=se, sd=sd, tol=tol, err=mean - float(P["log_z"]))


def chunk_sizes(est: str, n: int, a) -> list:
    """Trials per batched call: all of them, except for the O(N^2) estimators, whose autograd graph
    keeps ~1.3 kB x N^2 per trial (measured for ot: 111 MB per trial at N = 300, so 25 GB for 20
    trials at N = 1000); these run in calls of as many trials as fit ``--mem-gb``."""
    per = a.trials
    if est in ("ot", "marginal_stop_gradient") and a.mem_gb > 0:
        per = max(1, min(a.trials, int(a.mem_gb * 1e9 // (OT_BYTES_PER_N2 * n * n))))
    return [min(per, a.trials - i) for i in range(0, a.trials, per)]


OT_BYTES_PER_N2 = 1300


def run_cell(P: dict, est: str, n: int, a) -> dict:
    exact = P["grad_F"]
    T = P["obs"].shape[1]
    sizes = chunk_sizes(est, n, a)
    obs_tb = {k: time_major(P["obs"], k) for k in set(sizes)}
    grads, fb = [], []
    for r in range(a.reps):
        F = torch.nn.Parameter(P["F"].clone())
        g = torch.Generator().manual_seed(a.seed + 1000 + r)
        pf = build_filter(est, build_ssm(P, F, g), g, a)
        grad = torch.zeros_like(F)
        t0 = time.perf_counter()
        for k in sizes:  # the gradient of the mean over all trials, accumulated over the calls
            lz = log_evidence(pf, n, obs_tb[k])
            grad = grad + torch.autograd.grad(lz.sum() / a.trials, F)[0]
        fb.append((time.perf_counter() - t0) / (a.trials * T))
        grads.append(grad.detach().flatten())
    fwd = []
    for r in range(a.fwd_reps):
        F = torch.nn.Parameter(P["F"].clone())
        g = torch.Generator().manual_seed(a.seed + 7 + r)
        pf = build_filter(est, build_ssm(P, F, g), g, a)
        with torch.no_grad():
            t0 = time.perf_counter()
            for k in sizes:
                log_evidence(pf, n, obs_tb[k])
            fwd.append((time.perf_counter() - t0) / (a.trials * T))
    G = torch.stack(grads)
    ok = torch.isfinite(G).all(1)
    Gk = G[ok]
    k = int(ok.sum())
    ex = exact.flatten()
    mu = Gk.mean(0)
    sd = Gk.std(0) if k > 1 else torch.full_like(mu, float("nan"))
    return dict(
        library="PyDPF",
        estimator=est,
        pydpf_class=CLASS_OF[est].format(alpha=a.soft_alpha, eps=a.ot_epsilon, iters=a.ot_iterations, clip=a.ot_clip),
        N=n,
        trials=a.trials,
        trials_per_call=sizes[0],
        reps=a.reps,
        finite_reps=k,
        runs=a.trials * k,
        bias=float((mu - ex).norm()),
        max_t=float(((mu - ex) / (sd / math.sqrt(k))).abs().max()),
        sd_run=float((sd * math.sqrt(a.trials)).norm()),
        exact_norm=float(ex.norm()),
        fwd=statistics.median(fwd) if fwd else float("nan"),
        fwd_bwd=statistics.median(fb),
        mean_grad=mu.reshape(exact.shape).tolist(),
        sd_grad=sd.reshape(exact.shape).tolist(),
    )


def fmt(x, spec="{:.3g}"):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "nan" if isinstance(x, float) and math.isnan(x) else str(x)
    return spec.format(x)


def parse_args(argv=None):
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--problem", default=str(Path(__file__).resolve().parent / "results" / "gradients_problem.pt"))
    p.add_argument("--n", default="100,1000", help="particle counts, comma-separated")
    p.add_argument("--trials", type=int, default=20)
    p.add_argument("--reps", type=int, default=10)
    p.add_argument("--fwd-reps", type=int, default=3, help="no_grad forward calls timed per cell (median)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--estimators", default=",".join(DEFAULT_ESTIMATORS), help=f"of {DEFAULT_ESTIMATORS + EXTRA_ESTIMATORS}"
    )
    p.add_argument("--soft-alpha", type=float, default=0.5)
    p.add_argument("--ot-epsilon", type=float, default=0.1)
    p.add_argument("--ot-iterations", type=int, default=50)
    p.add_argument("--ot-clip", type=float, default=1.0, help="PyDPF's transport_gradient_clip (its default 1)")
    p.add_argument("--ot-max-n", type=int, default=1000)
    p.add_argument(
        "--mem-gb",
        type=float,
        default=6.0,
        help="memory budget of one batched call of the O(N^2) estimators (ot): their trials are split "
        "into calls that fit it (0: never split)",
    )
    p.add_argument("--check-n", type=int, default=10000, help="particles of the large-N log-likelihood check")
    p.add_argument("--check-trials", type=int, default=16)
    p.add_argument("--out", default=None, help="write the markdown here and a .json beside it")
    a = p.parse_args(argv)
    a.ns = [int(s) for s in a.n.split(",") if s.strip()]
    a.ests = [s.strip() for s in a.estimators.split(",") if s.strip()]
    for e in a.ests:
        if e not in CLASS_OF:
            p.error(f"--estimators: unknown {e!r}; choose from {tuple(CLASS_OF)}")
    if a.reps < 2:
        p.error("--reps: at least 2 (the spread is estimated across repetitions)")
    return a


def main(argv=None) -> dict:
    a = parse_args(argv)
    torch.set_num_threads(a.threads)
    torch.manual_seed(a.seed)
    P = load_problem(a.problem)
    T = P["obs"].shape[1]
    command = "python " + " ".join(
        [os.path.relpath(sys.argv[0]) if argv is None else "peer_pydpf_gradients.py"]
        + (sys.argv[1:] if argv is None else list(argv))
    )
    started = time.time()

    kc = kalman_check(P)
    print(
        f"PyDPF KalmanFilter (predicted prior built from F): log Z = {kc['log_z']:.6f} "
        f"(file {float(P['log_z']):.6f}, |diff| {kc['log_z_err']:.2e}); grad_F max |diff| {kc['grad_err']:.2e}",
        flush=True,
    )
    assert kc["log_z_err"] < 1e-6, f"PyDPF's Kalman log Z {kc['log_z']} != {float(P['log_z'])}"
    assert kc["grad_err"] < 1e-6 * max(1.0, float(P["grad_F"].abs().max())), (
        f"PyDPF's Kalman gradient {kc['grad_F']} != {P['grad_F'].tolist()}"
    )
    t0 = time.perf_counter()
    pc = particle_check(P, a.check_n, a.check_trials, a.seed + 99)
    print(
        f"PyDPF particle filter N = {pc['N']} ({pc['trials']} trials): mean log Z_hat = {pc['mean']:.4f} "
        f"+- {pc['se']:.4f} (SE), error {pc['err']:+.4f}, tolerance {pc['tol']:.4f} "
        f"({time.perf_counter() - t0:.1f} s)",
        flush=True,
    )
    assert abs(pc["err"]) <= pc["tol"], f"PyDPF's particle log Z {pc['mean']} is off {float(P['log_z'])}"

    rows = []
    for n in a.ns:
        for est in a.ests:
            if est == "ot" and n > a.ot_max_n:
                print(f"skip ot at N = {n} (> --ot-max-n {a.ot_max_n})", flush=True)
                continue
            t0 = time.perf_counter()
            rows.append(run_cell(P, est, n, a))
            r = rows[-1]
            print(
                f"{est:>22s} N={n:<6d} bias {r['bias']:.3g} max|t| {r['max_t']:.1f} sd/run {r['sd_run']:.3g} "
                f"fwd {r['fwd']:.3g} fwd+bwd {r['fwd_bwd']:.3g} s/ts ({time.perf_counter() - t0:.1f} s)",
                flush=True,
            )

    head = ["library", "estimator", "N", "runs", "bias", "max abs t", "sd/run", "abs exact", "fwd s/ts", "fwd+bwd s/ts"]
    lines = [
        "# Gradients through PyDPF's differentiable particle filters (peer comparison)",
        "",
        f"PyDPF {PYDPF_VERSION}, torch {torch.__version__}, python {platform.python_version()}, "
        f"{a.threads} thread(s), {platform.machine()} {platform.processor() or ''} ({os.cpu_count()} CPUs), float64. "
        "Resampling: multinomial at every step (PyDPF's ParticleFilter resamples unconditionally; "
        "torchflow's rows resample multinomially at ESS < N/2).",
        f"Problem: {a.problem}, linear-Gaussian d = {P['F'].shape[0]}, T = {T}; gradient of log Z with respect to F "
        f"against the exact (Kalman) grad_F. x_0 is not observed: PyDPF's prior is the law of x_1 "
        "(x_0 ~ N(mean, cov) pushed through F inside the graph).",
        f"Checks: PyDPF KalmanFilter log Z = {kc['log_z']:.6f} (exact {float(P['log_z']):.6f}), its grad_F within "
        f"{kc['grad_err']:.1e}; PyDPF particle filter N = {pc['N']}, {pc['trials']} trials: mean log Z_hat "
        f"{pc['mean']:.4f} +- {pc['se']:.4f}.",
        "Estimators: "
        + "; ".join(
            f"{e}: {CLASS_OF[e].format(alpha=a.soft_alpha, eps=a.ot_epsilon, iters=a.ot_iterations, clip=a.ot_clip)}"
            for e in a.ests
        )
        + ". Per cell: "
        + f"{a.reps} repetitions x {a.trials} trials; "
        f"ot skipped above N = {a.ot_max_n}. Trials run in one batched call, except where the runs column says "
        f"otherwise (ot: split to fit --mem-gb {a.mem_gb:g}; the gradient is that of the mean over all trials "
        "either way).",
        f"Command: `{command}`",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    for r in rows:
        runs = str(r["runs"]) + (
            "" if r["finite_reps"] == r["reps"] else f" ({r['reps'] - r['finite_reps']} reps non-finite)"
        )
        if r["trials_per_call"] < r["trials"]:
            runs += f" ({r['trials_per_call']} trials/call)"
        cells = [
            "PyDPF",
            r["estimator"],
            str(r["N"]),
            runs,
            fmt(r["bias"]),
            fmt(r["max_t"], "{:.1f}"),
            fmt(r["sd_run"]),
            fmt(r["exact_norm"]),
            fmt(r["fwd"]),
            fmt(r["fwd_bwd"]),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    md = "\n".join(lines) + "\n"
    print()
    print(md, flush=True)
    result = dict(
        markdown=md,
        rows=rows,
        kalman_check=kc,
        particle_check=pc,
        pydpf_version=PYDPF_VERSION,
        torch_version=torch.__version__,
        threads=a.threads,
        resampling="multinomial, every step",
        args={k: v for k, v in vars(a).items()},
        command=command,
        seconds=time.time() - started,
        exact_grad_F=P["grad_F"].tolist(),
        exact_log_z=float(P["log_z"]),
    )
    if a.out:
        os.makedirs(os.path.dirname(os.path.abspath(a.out)) or ".", exist_ok=True)
        with open(a.out, "w") as fh:
            fh.write(md)
        with open(os.path.splitext(a.out)[0] + ".json", "w") as fh:
            json.dump(result, fh, indent=1)
        print(f"wrote {a.out} and {os.path.splitext(a.out)[0] + '.json'}")
    return result


if __name__ == "__main__":
    main()
