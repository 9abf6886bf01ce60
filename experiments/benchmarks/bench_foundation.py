"""Foundation benchmarks on ``SensorNetwork(d=64)``, T = 10: torchflow's batched filters against peers
looped over trials in Python (BLAS limited to ``--peer-threads``); best of repeats after a warm-up.

1. ``KalmanFilter`` (100 trials at once) vs filterpy's; estimates must agree to 1e-8. Goal: >= 50x.
2. ``UnscentedKalmanFilter`` (100 trials) vs filterpy's (20) with ``MerweScaledSigmaPoints`` of the same
   alpha, beta, kappa (square root with torchflow's Cholesky jitter: the known ``x_0`` has covariance
   0); both are the exact KF here: estimates must agree to 1e-6. No goal.
3. ``BootstrapParticleFilter`` (systematic, ESS < 0.5 N; 20 trials in cache-sized calls) vs
   ``particles.SMC`` (10 trials, 2 for N > 1000; ``PX0`` is the law of ``x_1``, the estimate the mean
   after reweighting) at N = 200 and 1e4; MSE against the truth (exact KF: the floor). Goal: >= 2x.

    python -m experiments.benchmarks.bench_foundation             # a few minutes on 2 cores
"""

from __future__ import annotations

import contextlib
import time

import numpy as np
import scipy.linalg  # (load scipy's BLAS before threadpoolctl limits it)
import torch

from torchflow.models import SensorNetwork

from . import harness as h
from .harness import CheckFailed

NAMES = {"kf": "Kalman filter vs filterpy", "ukf": "UKF vs filterpy", "bpf": "Bootstrap PF vs particles"}


mse = lambda est, truth: float(np.mean((est - truth) ** 2))


def row(key, setting, goal, library=None, B=1, P=1, T=1, t_ours=None, t_peer=None, **numbers) -> dict:
    """A row: ``skipped`` without the peer ``library``; else seconds, per trial-step, ratio and goal."""
    if library is not None:
        return dict(
            name=NAMES[key],
            setting=setting,
            status=h.skipped(library),
            per_ts_ours=None,
            per_ts_peer=None,
            ratio=None,
            goal=goal,
            met=None,
        )
    per_ours, per_peer = t_ours / (B * T), t_peer / (P * T)
    return dict(
        name=NAMES[key],
        setting=setting,
        trials_ours=B,
        trials_peer=P,
        steps=T,
        s_ours=t_ours,
        s_peer=t_peer,
        per_ts_ours=per_ours,
        per_ts_peer=per_peer,
        ratio=per_peer / per_ours,
        goal=goal,
        met=None if goal is None else per_peer / per_ours >= goal,
        **numbers,
    )


def check_line(r) -> str:
    """The row's agreement / accuracy line (printed, and listed under the table)."""
    if r.get("status"):
        return f"- {r['name']} ({r['setting']}): {r['status']}."
    if "particles" in r:
        o = r["mse_ours_peer_trials"]
        return (
            f"- BPF N={r['particles']} MSE vs truth: ours {r['mse_ours']:.4f} over {r['trials_ours']} trials "
            f"(exact KF {r['mse_kf']:.4f}); particles {r['mse_peer']:.4f} over {r['trials_peer']} trials "
            f"(exact KF {r['mse_kf_peer_trials']:.4f}"
            + (f", ours on the same trials {o:.4f}" if o is not None else "")
            + f"). RMS distance to the KF mean: ours {r['rmse_to_kf_ours']:.4f}, "
            f"particles {r['rmse_to_kf_peer']:.4f}. Ours mean ESS {r['mean_ess_ours']:.1f}."
        )
    if "alpha" in r:
        return (
            f"- UKF vs filterpy (MerweScaledSigmaPoints alpha={r['alpha']:g}, beta={r['beta']:g}, "
            f"kappa={r['kappa']:g} on both): max |estimate diff| {r['max_abs_diff_estimates']:.2e} over "
            f"{r['compared_trials']} trials (< 1e-6 required); max |diff| to the exact KF: ours "
            f"{r['max_abs_diff_to_kf_ours']:.2e}, filterpy {r['max_abs_diff_to_kf_peer']:.2e}; "
            f"|log-evidence diff| (trial 0) {r['log_evidence_diff_trial0']:.2e}; MSE {r['mse_ours']:.4f}."
        )
    return (
        f"- KF vs filterpy: max |estimate diff| {r['max_abs_diff_estimates']:.2e} (< 1e-8 required), "
        f"|log-evidence diff| (trial 0) {r['log_evidence_diff_trial0']:.2e}; MSE {r['mse_ours']:.4f}."
    )


def run_filterpy(f, x0, P0, Z, trials: int, args):
    """``(best time, estimates (trials, T, d), trial 0's log-evidence (untimed), BLAS info)`` of the
    filterpy filter ``f`` looped over ``trials`` trials after an untimed one."""
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


def cholesky_upper_jitter(A: np.ndarray, max_tries: int = 6) -> np.ndarray:
    """filterpy's ``scipy.linalg.cholesky`` with ``torchflow.core.linalg.safe_cholesky``'s jitter fallback."""
    try:
        return scipy.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        scale = max(float(np.abs(np.diag(A)).mean()), np.finfo(A.dtype).tiny)
    for k in range(max_tries):
        with contextlib.suppress(np.linalg.LinAlgError):
            return scipy.linalg.cholesky(A + (10.0 * np.finfo(A.dtype).eps * 10.0**k) * scale * np.eye(len(A)))
    raise np.linalg.LinAlgError("cholesky_upper_jitter: matrix not positive definite even with jitter")


def bench_filterpy(args, kind: str) -> dict:
    """1. (``kind="kf"``) and 2. (``kind="ukf"``) above."""
    B, T, d = args.kf_trials, args.steps, args.d
    P = B if kind == "kf" else args.ukf_peer_trials
    model = SensorNetwork(d=d)
    ours = h.make_filter(kind, model)
    ukf_params = dict(alpha=ours.alpha, beta=ours.beta, kappa=ours.kappa) if kind == "ukf" else {}
    setting = (
        f"d={d}, T={T}, ours B={B}, peer B={P}, " + ", ".join(f"{k}={v:g}" for k, v in ukf_params.items())
        if kind == "ukf"
        else f"d={d}, B={B}, T={T}"
    )
    goal, tol = (50.0, 1e-8) if kind == "kf" else (None, 1e-6)
    filterpy = h.peer("filterpy", "kalman")
    if filterpy is None:
        return row(kind, setting, goal, "filterpy")
    traj, mean, cov = h.simulate(model, max(B, P), T, args.seed)
    with torch.no_grad():
        t = h.time_calls(lambda: ours(traj.observations[:B], mean[:B], cov[:B]), repeats=args.kf_repeats, warmup=1)
    est_ours = t.result.estimates.numpy()
    F, Q, H, R = (getattr(model, k).numpy().copy() for k in ("F", "Q", "H", "R"))
    if kind == "kf":
        peer = filterpy.kalman.KalmanFilter(dim_x=d, dim_z=d)
        peer.F, peer.H = F, H
    else:
        points = filterpy.kalman.MerweScaledSigmaPoints(n=d, sqrt_method=cholesky_upper_jitter, **ukf_params)
        peer = filterpy.kalman.UnscentedKalmanFilter(
            dim_x=d, dim_z=d, dt=1.0, fx=lambda x, dt: F @ x, hx=lambda x: H @ x, points=points
        )
    peer.Q, peer.R = Q, R
    t_peer, est_peer, ll_peer, peer_blas = run_filterpy(
        peer, mean.numpy(), cov.numpy(), traj.observations.numpy(), P, args
    )
    n = min(B, P)
    truth = traj.states[:, 1:].numpy()
    r = row(
        kind,
        setting,
        goal,
        None,
        B,
        P,
        T,
        t.min,
        t_peer,
        d=d,
        max_abs_diff_estimates=float(np.abs(est_ours[:n] - est_peer[:n]).max()),
        log_evidence_diff_trial0=abs(float(t.result.log_evidence[0]) - ll_peer),
        mse_ours=mse(est_ours, truth[:B]),
        mse_peer=mse(est_peer, truth[:P]),
        peer_blas=peer_blas,
    )
    if kind == "ukf":  # on this linear model both UKFs equal the exact KF (untimed)
        with torch.no_grad():
            est_kf = h.make_filter("kf", model)(traj.observations, mean, cov).estimates.numpy()
        r.update(
            ukf_params,
            compared_trials=n,
            max_abs_diff_to_kf_ours=float(np.abs(est_ours - est_kf[:B]).max()),
            max_abs_diff_to_kf_peer=float(np.abs(est_peer - est_kf[:P]).max()),
        )
    if not r["max_abs_diff_estimates"] < tol:
        raise CheckFailed(
            f"{kind.upper()} estimates disagree with filterpy (max diff "
            f"{r['max_abs_diff_estimates']:.3e}): comparison invalid"
        )
    return r


def bench_bpf(args, N: int, bpf_trials: int, peer_trials: int) -> dict:
    """3. above, at ``N`` particles."""
    T, d, P = args.steps, args.d, peer_trials
    model = SensorNetwork(d=d)
    bpf = h.make_filter("bpf", model, N, resampling="systematic", ess_threshold=0.5)
    chunk = bpf.preferred_chunk_trials()  # cache-sized calls (3 trials at N = 1e4, d = 64)
    setting = f"d={d}, N={N}, T={T}, ours B={bpf_trials} ({min(chunk, bpf_trials)} per call), peer B={P}"
    particles = h.peer("particles", "collectors", "distributions", "state_space_models")
    if particles is None:
        return row("bpf", setting, 2.0, "particles")
    dists, ssms = particles.distributions, particles.state_space_models
    traj, mean, cov = h.simulate(model, max(bpf_trials, peer_trials), T, args.seed + 1)
    obs_ours, mean_ours, cov_ours = traj.observations[:bpf_trials], mean[:bpf_trials], cov[:bpf_trials]

    def ours():  # per-trial streams, as run_experiment uses them
        parts = h.filter_chunks(bpf, obs_ours, mean_ours, cov_ours, chunk, h.streams(args.seed + 2, "bpf"))
        return torch.cat([p.estimates for p in parts]), torch.cat([p.ess for p in parts], 0)

    t = h.time_calls(ours, repeats=args.repeats, warmup=1)
    est_ours, ess_ours = t.result[0].numpy(), t.result[1]
    with torch.no_grad():  # exact KF on the same trials: the MSE floor
        est_kf = h.make_filter("kf", model)(traj.observations, mean, cov).estimates.numpy()

    F, Q, R, m0 = (getattr(model, k).numpy().copy() for k in ("F", "Q", "R", "m0"))
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
        return particles.SMC(
            fk=ssms.Bootstrap(ssm=LGSensorNetwork(), data=data),
            N=n,
            resampling="systematic",
            ESSrmin=0.5,
            collect=[particles.collectors.Moments(mom_func=lambda W, X: W @ X)],
        )

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
        tp = h.time_calls(peer, repeats=args.peer_repeats)
    est_peer, truth, B = tp.result, traj.states[:, 1:].numpy(), bpf_trials
    return row(
        "bpf",
        setting,
        2.0,
        None,
        B,
        P,
        T,
        t.min,
        tp.min,
        d=d,
        particles=N,
        mse_ours=mse(est_ours, truth[:B]),
        mse_ours_peer_trials=mse(est_ours[:P], truth[:P]) if P <= B else None,
        mse_peer=mse(est_peer, truth[:P]),
        mse_kf=mse(est_kf[:B], truth[:B]),
        mse_kf_peer_trials=mse(est_kf[:P], truth[:P]),
        rmse_to_kf_ours=float(np.sqrt(np.mean((est_ours - est_kf[:B]) ** 2))),
        rmse_to_kf_peer=float(np.sqrt(np.mean((est_peer - est_kf[:P]) ** 2))),
        mean_ess_ours=float(ess_ours.mean()),
        peer_blas=peer_blas,
    )


def markdown(info, results, args) -> str:
    return h.report(
        "## Foundation benchmarks",
        args,
        info,
        [f"Peer BLAS threads: {info['peer_blas_threads']}."],
        ["benchmark", "setting", "ours s/trial-step", "peer s/trial-step", "ratio peer/ours", "goal", "met"],
        [
            [r["name"], r["setting"]]
            + (
                [r["status"], "-", "-"]
                if r.get("status")
                else [f"{r['per_ts_ours']:.3e}", f"{r['per_ts_peer']:.3e}", f"{r['ratio']:.1f}x"]
            )
            + [h.fmt(r.get("goal"), ">= {:g}x"), h.met_cell(r["met"])]
            for r in results
        ],
        "Checks / accuracy:",
        "",
        *map(check_line, results),
        "",
        "Times are best of repeats, each side after an untimed warm-up; s/trial-step = time / (trials x steps).",
    )


def run(argv=None) -> dict:
    argv = list(argv or [])
    args = h.options(
        __doc__,
        argv,
        dict(
            d=16,
            steps=5,
            kf_trials=10,
            ukf_peer_trials=2,
            bpf_trials=4,
            peer_trials=1,
            particles="200,500",
            kf_repeats=3,
            repeats=1,
            peer_repeats=1,
        ),
        d=64,
        steps=10,
        kf_trials=100,
        ukf_peer_trials=20,
        bpf_trials=20,
        peer_trials=None,
        particles="200,10000",
        kf_repeats=10,
        repeats=3,
        peer_repeats=2,
        seed=0,
        threads=None,
        peer_threads=1,
    )  # peer_trials: default 10 for N <= 1000, else 2; peer_threads 0: BLAS default
    with h.session(
        "bench_foundation",
        argv,
        args.threads,
        peer_blas_threads=args.peer_threads if args.peer_threads > 0 else "default",
    ) as info:
        t0 = time.perf_counter()
        rows = [bench_filterpy(args, kind) for kind in ("kf", "ukf")] + [
            bench_bpf(args, N, args.bpf_trials, args.peer_trials or (10 if N <= 1000 else 2))
            for N in h.ints(args.particles, "--particles")
        ]
        info["total_wall_s"] = time.perf_counter() - t0
    return dict(machine=info, rows=rows, markdown=markdown(info, rows, args), args=vars(args))


if __name__ == "__main__":
    h.main(run, "foundation")
