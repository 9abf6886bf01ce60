"""Foundation benchmarks: torchflow's batched filters against established single-trial libraries.

What is measured (seconds per trial-step = wall time / (trials * steps), one run, this machine):

1. **Kalman filter vs filterpy.** Linear-Gaussian sensor network ``SensorNetwork(d=64)``
   (``x_k = 0.9 x_{k-1} + v``, ``z_k = x_k + w``, known ``x_0 = 0``), B = 100 trials, T = 10 steps.
   Ours: ``torchflow.filters.KalmanFilter(model)`` on all trials at once (one warm-up call, then
   best of ``--kf-repeats``). Peer (after one untimed warm-up trial):
   ``filterpy.kalman.KalmanFilter(dim_x=64, dim_z=64)`` looped over
   trials in Python, ``predict()`` / ``update(z)`` per step (best of ``--peer-repeats``). Both must
   give the same estimates (max |diff| < 1e-8, checked and printed) so the timing compares equal
   work; the log-evidence of trial 0 is checked against filterpy's ``log_likelihood`` too
   (untimed). Goal (issue): ours >= 50x faster.

2. **Unscented Kalman filter vs filterpy.** Same model and trajectory seed as 1, T = 10.
   Ours: ``torchflow.filters.UnscentedKalmanFilter(model, alpha, beta, kappa)`` (defaults
   ``alpha = 1``, ``beta = 2``, ``kappa = 3 - d``, i.e. -61 at d = 64; override with
   ``--ukf-alpha/--ukf-beta/--ukf-kappa``) on ``--kf-trials`` trials at once (warm-up, then best of
   ``--kf-repeats``). Peer (after one untimed warm-up trial): ``filterpy.kalman.UnscentedKalmanFilter(
   dim_x=64, dim_z=64, dt=1, fx=lambda x, dt: F @ x, hx=lambda x: H @ x, points=...)`` with ``Q``,
   ``R`` set and ``points = MerweScaledSigmaPoints(n=64, alpha, beta, kappa)`` taking the SAME
   alpha / beta / kappa as ours (read back from our filter), so both use the same ``2d + 1`` scaled
   sigma points and weights, redrawn after the prediction; looped over ``--ukf-peer-trials``
   trials (default 20) in Python, ``predict()`` / ``update(z)`` per step (best of
   ``--peer-repeats``). The known ``x_0`` has covariance 0, on which filterpy's default
   ``scipy.linalg.cholesky`` square root fails, so the peer's ``sqrt_method`` is
   ``scipy.linalg.cholesky`` with torchflow's ``safe_cholesky`` jitter fallback (a diagonal
   ``10 eps 10^k max(mean|diag|, tiny)``, only used at the first step). Times are normalised
   per trial-step since the trial counts differ. On this linear model both equal the exact KF:
   estimates must agree (max |diff| < 1e-6, checked and printed; the diff to our KF and the
   log-evidence of trial 0 against filterpy's ``log_likelihood`` are printed too). No goal is set
   by the issue (goal "-").

3. **Bootstrap particle filter vs ``particles`` (N. Chopin's library)**, one row per particle count
   in ``--particles`` (default ``200,10000``: the issue's N = 200 and N = 1e4). Same model,
   systematic resampling when ESS < 0.5 N, T = 10. Ours:
   ``BootstrapParticleFilter(model, n_particles=N, resampling="systematic", ess_threshold=0.5)``
   on ``--bpf-trials`` trials at once (default 20; warm-up, then best of ``--repeats``). Peer: a
   ``particles.state_space_models.StateSpaceModel`` subclass with ``PX(t, xp) = MvNormal(0.9 xp, Q)``
   and ``PY(t, xp, x) = MvNormal(x, R)``, run through ``particles.SMC(fk=Bootstrap(...), N=N,
   resampling="systematic", ESSrmin=0.5)`` per trial in a Python loop over ``--peer-trials`` trials
   (default 10 for N <= 1000, 2 above; best of ``--peer-repeats``). ``--bpf-trials`` and
   ``--peer-trials`` take one value for every N or a comma-separated list, one per N.
   particles' time index starts at the first observation, so its ``PX0`` is the exact law of
   ``x_1`` given the known ``x_0 = m0``: ``MvNormal(F m0, Q)``; the weighted particle mean at each
   step (a ``Moments`` collector, weights after reweighting, before resampling) is its estimate,
   which is the same quantity torchflow reports. Accuracy is compared as the MSE of the estimates
   against the true states (averaged over trials, steps and coordinates), with the exact Kalman
   MSE on the same trials as the floor. Goal (issue): ours >= 2x faster (at each N).

Threads: torchflow runs with ``--threads`` torch threads (default: torch's default). The numpy /
scipy peers run with their BLAS limited to ``--peer-threads`` (default 1, via threadpoolctl);
pass ``--peer-threads 0`` to leave BLAS at its default. Both settings are printed.

Run from the repository root (a few minutes with the defaults on a 2-core machine)::

    python -m experiments.benchmarks.bench_foundation
    python -m experiments.benchmarks.bench_foundation --quick     # smoke test, < 30 s

A peer library that is not installed (``pip install -e ".[bench]"``) turns its rows into
``skipped: <library> not installed`` rows; the other rows still run.

The markdown table is printed and written to ``--out`` (default
``experiments/benchmarks/results_foundation.md``; ``--quick`` defaults to
``results_foundation_quick.md`` so a smoke test never overwrites the full results), with the raw
numbers in a JSON file of the same name next to it.

From another script, ``run(argv)`` (``argv`` a list of the same options) runs the benchmarks
without writing files and returns ``{"machine": {...}, "rows": [...], "markdown": str, "args":
{...}}``; each row has at least ``name``, ``setting``, ``per_ts_ours``, ``per_ts_peer``, ``ratio``
(peer / ours), ``goal`` (float or None) and ``met`` (bool or None). A failed agreement check
raises :class:`~experiments.benchmarks.harness.CheckFailed` (the command line turns it into
``SystemExit``).
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import scipy.linalg  # (load scipy's BLAS before threadpoolctl limits it)
import torch

from torchflow.models import SensorNetwork

from . import harness as h
from .harness import CheckFailed


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------
def mse(est: np.ndarray, truth: np.ndarray) -> float:
    return float(np.mean((est - truth) ** 2))


def int_list(text) -> list:
    """``"200,10000"`` / ``"1e4"`` / ``20`` -> list of ints."""
    if isinstance(text, (int, float)):
        return [int(text)]
    if isinstance(text, (list, tuple)):
        return [int(v) for v in text]
    return [int(float(v)) for v in str(text).split(",") if v.strip()]


def per_n(values: list, n_count: int, option: str) -> list:
    """One value per particle count: a single value is used for all."""
    if len(values) == 1:
        return values * n_count
    if len(values) != n_count:
        raise SystemExit(f"{option}: expected 1 or {n_count} comma-separated values (one per --particles), "
                         f"got {len(values)}")
    return values


def skipped_row(name: str, setting: str, library: str, goal=None) -> dict:
    """The row of a benchmark whose peer ``library`` is not installed."""
    print(f"[{name}] {h.skipped(library)}")
    return dict(name=name, setting=setting, status=h.skipped(library), per_ts_ours=None, per_ts_peer=None,
                ratio=None, goal=goal, met=None)


def time_ours(f, args_, repeats: int):
    """Best of ``repeats`` calls ``f(*args_)`` under ``torch.no_grad()`` after one warm-up call."""
    with torch.no_grad():
        return h.time_calls(lambda: f(*args_), repeats=repeats, warmup=1)


def run_filterpy(f, x0, P0, Z, trials: int, args):
    """Time a filterpy filter ``f`` (KalmanFilter or UnscentedKalmanFilter) looped over ``trials``
    trials in Python (one untimed warm-up trial first, BLAS limited to ``--peer-threads``).

    Returns ``(best time, estimates (trials, T, d), log-evidence of trial 0, BLAS info)``; the
    log-evidence is summed from filterpy's per-step ``log_likelihood`` in an untimed extra run."""
    T, d = Z.shape[1], x0.shape[-1]

    def one(b, out=None):
        f.x, f.P = x0[b].copy(), P0[b].copy()
        ll = 0.0
        for t in range(T):
            f.predict()
            f.update(Z[b, t])
            if out is None:
                ll += float(f.log_likelihood)
            else:
                out[b, t] = f.x
        return ll

    def peer():
        out = np.empty((trials, T, d))
        for b in range(trials):
            one(b, out)
        return out

    with h.blas_limit(args.peer_threads):
        peer_blas = h.blas_threads()
        one(0, np.empty((1, T, d)))  # warm-up: first-call import / allocation costs
        t = h.time_calls(peer, repeats=args.peer_repeats)
        ll_peer = one(0)
    return t.min, t.result, ll_peer, peer_blas


def model_matrices(model):
    return (getattr(model, k).numpy().copy() for k in ("F", "Q", "H", "R"))


# ---------------------------------------------------------------------------------------------
# 1. Kalman filter vs filterpy
# ---------------------------------------------------------------------------------------------
def bench_kf(args):
    B, T, d = args.kf_trials, args.steps, args.d
    setting = f"d={d}, B={B}, T={T}"
    filterpy = h.peer("filterpy", "kalman")
    if filterpy is None:
        return skipped_row("Kalman filter vs filterpy", setting, "filterpy", 50.0)
    model = SensorNetwork(d=d)
    traj, mean, cov = h.simulate(model, B, T, args.seed)
    t = time_ours(h.make_filter("kf", model), (traj.observations, mean, cov), args.kf_repeats)
    t_ours, res = t.min, t.result
    est_ours = res.estimates.numpy()

    fkf = filterpy.kalman.KalmanFilter(dim_x=d, dim_z=d)
    fkf.F, fkf.Q, fkf.H, fkf.R = model_matrices(model)
    t_peer, est_peer, ll_peer, peer_blas = run_filterpy(fkf, mean.numpy(), cov.numpy(), traj.observations.numpy(),
                                                        B, args)

    diff = float(np.abs(est_ours - est_peer).max())
    ll_diff = abs(float(res.log_evidence[0]) - ll_peer)
    truth = traj.states[:, 1:].numpy()
    steps = B * T
    r = dict(
        name="Kalman filter vs filterpy", d=d, trials_ours=B, trials_peer=B, steps=T,
        s_ours=t_ours, s_peer=t_peer,
        per_ts_ours=t_ours / steps, per_ts_peer=t_peer / steps, ratio=t_peer / t_ours, goal=50.0,
        max_abs_diff_estimates=diff, log_evidence_diff_trial0=ll_diff,
        mse_ours=mse(est_ours, truth), mse_peer=mse(est_peer, truth), peer_blas=peer_blas, setting=setting,
    )
    r["met"] = r["ratio"] >= r["goal"]
    print(f"[KF] d={d} B={B} T={T}: ours {t_ours:.4f}s ({r['per_ts_ours']:.3e} s/trial-step), "
          f"filterpy {t_peer:.4f}s ({r['per_ts_peer']:.3e} s/trial-step), ratio {r['ratio']:.1f}x")
    print(f"[KF] max |estimate diff| = {diff:.3e} (must be < 1e-8), "
          f"|log-evidence diff| trial 0 = {ll_diff:.3e}, MSE = {r['mse_ours']:.4f}")
    if not diff < 1e-8:
        raise CheckFailed(f"KF estimates disagree with filterpy (max diff {diff:.3e}): comparison invalid")
    return r


# ---------------------------------------------------------------------------------------------
# 2. Unscented Kalman filter vs filterpy
# ---------------------------------------------------------------------------------------------
def cholesky_upper_jitter(A: np.ndarray, max_tries: int = 6) -> np.ndarray:
    """filterpy's default sigma-point square root (``scipy.linalg.cholesky``, upper) with the same
    jitter fallback as ``torchflow.linalg.safe_cholesky``: needed for the known ``x_0`` (P = 0)."""
    try:
        return scipy.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        pass
    scale = max(float(np.abs(np.diag(A)).mean()), np.finfo(A.dtype).tiny)
    base = 10.0 * np.finfo(A.dtype).eps
    eye = np.eye(A.shape[-1], dtype=A.dtype)
    for k in range(max_tries):
        try:
            return scipy.linalg.cholesky(A + (base * 10.0**k) * scale * eye)
        except np.linalg.LinAlgError:
            continue
    raise np.linalg.LinAlgError("cholesky_upper_jitter: matrix not positive definite even with jitter")


def bench_ukf(args):
    B, P, T, d = args.kf_trials, args.ukf_peer_trials, args.steps, args.d
    model = SensorNetwork(d=d)
    ukf = h.make_filter("ukf", model, alpha=args.ukf_alpha, beta=args.ukf_beta, kappa=args.ukf_kappa)
    a, b, k = ukf.alpha, ukf.beta, ukf.kappa  # the peer takes exactly these
    setting = f"d={d}, T={T}, ours B={B}, peer B={P}, alpha={a:g}, beta={b:g}, kappa={k:g}"
    filterpy = h.peer("filterpy", "kalman")
    if filterpy is None:
        return skipped_row("UKF vs filterpy", setting, "filterpy")
    traj, mean_all, cov_all = h.simulate(model, max(B, P), T, args.seed)
    t = time_ours(ukf, (traj.observations[:B], mean_all[:B], cov_all[:B]), args.kf_repeats)
    t_ours, res = t.min, t.result
    est_ours = res.estimates.numpy()
    with torch.no_grad():  # exact KF on all trials (untimed): both UKFs must equal it
        est_kf = h.make_filter("kf", model)(traj.observations, mean_all, cov_all).estimates.numpy()

    F, Q, H, R = model_matrices(model)
    points = filterpy.kalman.MerweScaledSigmaPoints(n=d, alpha=a, beta=b, kappa=k, sqrt_method=cholesky_upper_jitter)
    fukf = filterpy.kalman.UnscentedKalmanFilter(dim_x=d, dim_z=d, dt=1.0, fx=lambda x, dt: F @ x,
                                                 hx=lambda x: H @ x, points=points)
    fukf.Q, fukf.R = Q, R
    t_peer, est_peer, ll_peer, peer_blas = run_filterpy(fukf, mean_all.numpy(), cov_all.numpy(),
                                                        traj.observations.numpy(), P, args)

    n_cmp = min(B, P)
    diff = float(np.abs(est_ours[:n_cmp] - est_peer[:n_cmp]).max())
    diff_kf_ours = float(np.abs(est_ours - est_kf[:B]).max())
    diff_kf_peer = float(np.abs(est_peer - est_kf[:P]).max())
    ll_diff = abs(float(res.log_evidence[0]) - ll_peer)
    truth = traj.states[:, 1:].numpy()
    per_ours, per_peer = t_ours / (B * T), t_peer / (P * T)
    r = dict(
        name="UKF vs filterpy", d=d, trials_ours=B, trials_peer=P, steps=T,
        alpha=a, beta=b, kappa=k, s_ours=t_ours, s_peer=t_peer,
        per_ts_ours=per_ours, per_ts_peer=per_peer, ratio=per_peer / per_ours, goal=None, met=None,
        max_abs_diff_estimates=diff, compared_trials=n_cmp, max_abs_diff_to_kf_ours=diff_kf_ours,
        max_abs_diff_to_kf_peer=diff_kf_peer, log_evidence_diff_trial0=ll_diff,
        mse_ours=mse(est_ours, truth[:B]), mse_peer=mse(est_peer, truth[:P]), peer_blas=peer_blas, setting=setting,
    )
    print(f"[UKF] d={d} T={T} alpha={a:g} beta={b:g} kappa={k:g}: ours B={B} {t_ours:.4f}s "
          f"({per_ours:.3e} s/trial-step), filterpy B={P} {t_peer:.4f}s ({per_peer:.3e} s/trial-step), "
          f"ratio {r['ratio']:.1f}x")
    print(f"[UKF] max |estimate diff| vs filterpy = {diff:.3e} over {n_cmp} trials (must be < 1e-6); "
          f"to the exact KF: ours {diff_kf_ours:.3e}, filterpy {diff_kf_peer:.3e}; "
          f"|log-evidence diff| trial 0 = {ll_diff:.3e}; MSE = {r['mse_ours']:.4f}")
    if not diff < 1e-6:
        raise CheckFailed(f"UKF estimates disagree with filterpy (max diff {diff:.3e}): comparison invalid")
    return r


# ---------------------------------------------------------------------------------------------
# 3. Bootstrap PF vs particles
# ---------------------------------------------------------------------------------------------
def bench_bpf(args, N: int, bpf_trials: int, peer_trials: int):
    T, d, P = args.steps, args.d, peer_trials
    model = SensorNetwork(d=d)
    bpf = h.make_filter("bpf", model, N, resampling="systematic", ess_threshold=0.5)
    chunk = bpf.preferred_chunk_trials()  # cache-sized calls (3 trials at N = 1e4, d = 64)
    setting = f"d={d}, N={N}, T={T}, ours B={bpf_trials} ({min(chunk, bpf_trials)} per call), peer B={P}"
    particles = h.peer("particles", "collectors", "distributions", "state_space_models")
    if particles is None:
        return skipped_row("Bootstrap PF vs particles", setting, "particles", 2.0)
    collectors, dists, ssms = particles.collectors, particles.distributions, particles.state_space_models
    traj, mean, cov = h.simulate(model, max(bpf_trials, peer_trials), T, args.seed + 1)
    obs_ours, mean_ours, cov_ours = traj.observations[:bpf_trials], mean[:bpf_trials], cov[:bpf_trials]

    def ours():  # per-trial streams, as run_experiment uses them
        parts = h.filter_chunks(bpf, obs_ours, mean_ours, cov_ours, chunk, h.streams(args.seed + 2, "bpf"))
        return torch.cat([p.estimates for p in parts]), torch.cat([p.ess for p in parts], 0)

    t = h.time_calls(ours, repeats=args.repeats, warmup=1)
    t_ours, (est, ess_ours) = t.min, t.result
    est_ours = est.numpy()
    with torch.no_grad():  # exact KF on the same trials: the MSE floor
        est_kf = h.make_filter("kf", model)(traj.observations, mean, cov).estimates.numpy()

    F, Q, _, R = model_matrices(model)
    m0 = model.m0.numpy().copy()
    alpha = float(F[0, 0])
    if not np.allclose(F, alpha * np.eye(d)):
        raise CheckFailed("the particles peer model assumes F = alpha * I")

    class LGSensorNetwork(ssms.StateSpaceModel):
        """x_1 ~ N(F m0, Q) (x_0 = m0 known); x_t ~ N(alpha x_{t-1}, Q); y_t ~ N(x_t, R)."""

        def PX0(self):
            return dists.MvNormal(loc=F @ m0, cov=Q)

        def PX(self, t, xp):
            return dists.MvNormal(loc=alpha * xp, cov=Q)

        def PY(self, t, xp, x):
            return dists.MvNormal(loc=x, cov=R)

    def smc(data, n):
        return particles.SMC(fk=ssms.Bootstrap(ssm=LGSensorNetwork(), data=data), N=n, resampling="systematic",
                             ESSrmin=0.5, collect=[collectors.Moments(mom_func=lambda W, X: W @ X)])

    Z = traj.observations.numpy()

    def peer():
        np.random.seed(args.seed + 3)
        out = np.empty((P, T, d))
        for b in range(P):
            pf = smc(Z[b], N)
            pf.run()
            out[b] = np.stack(pf.summaries.moments)
        return out

    with h.blas_limit(args.peer_threads):
        peer_blas = h.blas_threads()
        smc(Z[0, :2], min(N, 1000)).run()  # one short untimed trial: first-call import / allocation costs
        t = h.time_calls(peer, repeats=args.peer_repeats)
    t_peer, est_peer = t.min, t.result

    truth = traj.states[:, 1:].numpy()
    per_ours = t_ours / (bpf_trials * T)
    per_peer = t_peer / (P * T)
    r = dict(
        name="Bootstrap PF vs particles", d=d, particles=N, trials_ours=bpf_trials, trials_peer=P,
        steps=T, s_ours=t_ours, s_peer=t_peer, per_ts_ours=per_ours, per_ts_peer=per_peer,
        ratio=per_peer / per_ours, goal=2.0,
        mse_ours=mse(est_ours, truth[: bpf_trials]),
        mse_ours_peer_trials=mse(est_ours[:P], truth[:P]) if P <= bpf_trials else None,
        mse_peer=mse(est_peer, truth[:P]),
        mse_kf=mse(est_kf[: bpf_trials], truth[: bpf_trials]),
        mse_kf_peer_trials=mse(est_kf[:P], truth[:P]),
        rmse_to_kf_ours=float(np.sqrt(np.mean((est_ours - est_kf[: bpf_trials]) ** 2))),
        rmse_to_kf_peer=float(np.sqrt(np.mean((est_peer - est_kf[:P]) ** 2))),
        mean_ess_ours=float(ess_ours.mean()), peer_blas=peer_blas, setting=setting,
    )
    r["met"] = r["ratio"] >= r["goal"]
    print(f"[BPF] d={d} N={N} T={T}: ours B={bpf_trials} {t_ours:.3f}s ({per_ours:.3e} s/trial-step), "
          f"particles B={P} {t_peer:.3f}s ({per_peer:.3e} s/trial-step), ratio {r['ratio']:.1f}x")
    o = r["mse_ours_peer_trials"]
    print(f"[BPF] MSE vs truth: ours {r['mse_ours']:.4f} (KF {r['mse_kf']:.4f}), "
          f"particles {r['mse_peer']:.4f} (KF on its trials {r['mse_kf_peer_trials']:.4f}, "
          f"ours on them {o if o is None else round(o, 4)})")
    return r


# ---------------------------------------------------------------------------------------------
# report
# ---------------------------------------------------------------------------------------------
def _fmt_goal(r) -> tuple:
    if r.get("goal") is None:
        return "-", "-"
    return f">= {r['goal']:g}x", h.met_cell(r["met"])


def markdown(info, results, args) -> str:
    lines = ["## Foundation benchmarks" + (" (--quick smoke test)" if args.quick else ""), "",
             f"{h.machine_line(info)} Peer BLAS threads: {info['peer_blas_threads']}.",
             f"Command: `{info['command']}`", ""]
    rows = []
    for r in results:
        goal, met = _fmt_goal(r)
        if r.get("status"):
            rows.append([r["name"], r["setting"], r["status"], "-", "-", goal, met])
        else:
            rows.append([r["name"], r["setting"], f"{r['per_ts_ours']:.3e}", f"{r['per_ts_peer']:.3e}",
                         f"{r['ratio']:.1f}x", goal, met])
    lines += h.md_table(["benchmark", "setting", "ours s/trial-step", "peer s/trial-step", "ratio peer/ours",
                         "goal", "met"], rows)
    lines += ["", "Checks / accuracy:", ""]
    for r in results:
        if r.get("status"):
            lines.append(f"- {r['name']} ({r['setting']}): {r['status']}.")
        elif "particles" in r:
            o = r["mse_ours_peer_trials"]
            lines.append(
                f"- BPF N={r['particles']} MSE vs truth: ours {r['mse_ours']:.4f} over {r['trials_ours']} trials "
                f"(exact KF {r['mse_kf']:.4f}); particles {r['mse_peer']:.4f} over {r['trials_peer']} trials "
                f"(exact KF {r['mse_kf_peer_trials']:.4f}"
                + (f", ours on the same trials {o:.4f}" if o is not None else "")
                + f"). RMS distance to the KF mean: ours {r['rmse_to_kf_ours']:.4f}, "
                  f"particles {r['rmse_to_kf_peer']:.4f}. Ours mean ESS {r['mean_ess_ours']:.1f}.")
        elif "alpha" in r:
            lines.append(
                f"- UKF vs filterpy (MerweScaledSigmaPoints alpha={r['alpha']:g}, beta={r['beta']:g}, "
                f"kappa={r['kappa']:g} on both): max |estimate diff| {r['max_abs_diff_estimates']:.2e} over "
                f"{r['compared_trials']} trials (< 1e-6 required); max |diff| to the exact KF: ours "
                f"{r['max_abs_diff_to_kf_ours']:.2e}, filterpy {r['max_abs_diff_to_kf_peer']:.2e}; "
                f"|log-evidence diff| (trial 0) {r['log_evidence_diff_trial0']:.2e}; MSE {r['mse_ours']:.4f}.")
        else:
            lines.append(
                f"- KF vs filterpy: max |estimate diff| {r['max_abs_diff_estimates']:.2e} (< 1e-8 required), "
                f"|log-evidence diff| (trial 0) {r['log_evidence_diff_trial0']:.2e}; MSE {r['mse_ours']:.4f}.")
    lines += ["", "Times are best of repeats, each side after an untimed warm-up; s/trial-step = time / (trials x steps)."]
    return "\n".join(lines) + "\n"


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="tiny sizes for a smoke test (< 30 s)")
    p.add_argument("--out", default=None, help="markdown output (JSON written next to it)")
    p.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's)")
    p.add_argument("--peer-threads", type=int, default=1, help="BLAS threads for numpy peers (0: default)")
    p.add_argument("--d", type=int, default=None, help="state dimension, a perfect square (64)")
    p.add_argument("--steps", type=int, default=None, help="time steps T (10)")
    p.add_argument("--kf-trials", type=int, default=None, help="trials B of the KF (both sides) and of our UKF (100)")
    p.add_argument("--ukf-peer-trials", type=int, default=None, help="filterpy UKF trials (20)")
    p.add_argument("--ukf-alpha", type=float, default=1.0, help="UKF alpha, both sides (1)")
    p.add_argument("--ukf-beta", type=float, default=2.0, help="UKF beta, both sides (2)")
    p.add_argument("--ukf-kappa", type=float, default=None, help="UKF kappa, both sides (default 3 - d)")
    p.add_argument("--bpf-trials", default=None,
                   help="our BPF trials: one value or a comma list, one per --particles (20)")
    p.add_argument("--peer-trials", default=None,
                   help="particles trials: one value or a comma list, one per --particles "
                        "(10 for N <= 1000, else 2)")
    p.add_argument("--particles", default=None, help="particle counts N, comma-separated (200,10000)")
    p.add_argument("--kf-repeats", type=int, default=None, help="timed repeats of our KF and UKF (10; cheap)")
    p.add_argument("--repeats", type=int, default=None, help="timed repeats of our BPF (3)")
    p.add_argument("--peer-repeats", type=int, default=None, help="timed repeats of the peers (2)")
    p.add_argument("--skip-kf", action="store_true")
    p.add_argument("--skip-ukf", action="store_true")
    p.add_argument("--skip-bpf", action="store_true")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    full = dict(d=64, steps=10, kf_trials=100, ukf_peer_trials=20, bpf_trials="20", peer_trials=None,
                particles="200,10000", kf_repeats=10, repeats=3, peer_repeats=2)
    quick = dict(d=16, steps=5, kf_trials=10, ukf_peer_trials=2, bpf_trials="4", peer_trials="1",
                 particles="200,500", kf_repeats=3, repeats=1, peer_repeats=1)
    for k, v in (quick if args.quick else full).items():
        if getattr(args, k) is None:
            setattr(args, k, v)
    args.particles = int_list(args.particles)
    n = len(args.particles)
    if n == 0:
        raise SystemExit("--particles: give at least one particle count")
    args.bpf_trials = per_n(int_list(args.bpf_trials), n, "--bpf-trials")
    if args.peer_trials is None:
        args.peer_trials = [10 if N <= 1000 else 2 for N in args.particles]
    else:
        args.peer_trials = per_n(int_list(args.peer_trials), n, "--peer-trials")
    return args


def run(argv=None) -> dict:
    """Run the benchmarks (``argv``: the CLI options as a list).

    Writes no files. Returns ``{"machine": dict, "rows": [row, ...], "markdown": str, "args": dict}``,
    each row with ``name``, ``setting``, ``per_ts_ours``, ``per_ts_peer``, ``ratio`` (peer / ours),
    ``goal`` (float or None), ``met`` (bool or None) and the raw numbers of its benchmark (or
    ``status`` = ``skipped: <library> not installed`` and no numbers). Raises :class:`CheckFailed`
    when ours and a peer disagree.
    """
    argv = list(argv or [])
    args = parse_args(argv)
    with h.torch_threads(args.threads):
        info = h.machine(peer_blas_threads=args.peer_threads if args.peer_threads > 0 else "default",
                         command=h.command("bench_foundation", argv))
        print(f"{h.machine_line(info)} Peer BLAS threads: {info['peer_blas_threads']} "
              f"(BLAS default now: {h.blas_threads()}).")
        t0 = time.perf_counter()
        rows = []
        if not args.skip_kf:
            rows.append(bench_kf(args))
        if not args.skip_ukf:
            rows.append(bench_ukf(args))
        if not args.skip_bpf:
            for N, b_ours, b_peer in zip(args.particles, args.bpf_trials, args.peer_trials):
                rows.append(bench_bpf(args, N, b_ours, b_peer))
        info["total_wall_s"] = time.perf_counter() - t0
        info["load_end"] = h.loadavg()
    return dict(machine=info, rows=rows, markdown=markdown(info, rows, args), args=vars(args))


if __name__ == "__main__":
    h.main(run, "foundation")
