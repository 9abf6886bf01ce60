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

Threads: torchflow runs with ``--threads`` torch threads (default: torch's default); the numpy /
scipy peers with their BLAS limited to ``--peer-threads`` (default 1, via threadpoolctl; 0 leaves
BLAS at its default). A failed agreement check raises ``CheckFailed`` (exit with its message).
Each row has ``name``, ``setting``, ``per_ts_ours``, ``per_ts_peer``, ``ratio`` (peer / ours),
``goal`` and ``met``, or ``status = "skipped: <library> not installed"`` and no numbers.

    python -m experiments.benchmarks.bench_foundation             # a few minutes on 2 cores
    python -m experiments.benchmarks.bench_foundation --quick     # smoke test, < 30 s
"""
from __future__ import annotations

import time

import numpy as np
import scipy.linalg  # (load scipy's BLAS before threadpoolctl limits it)
import torch

from torchflow.models import SensorNetwork

from . import harness as h
from .harness import CheckFailed

NAMES = {"kf": "Kalman filter vs filterpy", "ukf": "UKF vs filterpy", "bpf": "Bootstrap PF vs particles"}


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


def skipped_row(key: str, setting: str, library: str, goal=None) -> dict:
    """The row of a benchmark whose peer ``library`` is not installed."""
    return dict(name=NAMES[key], setting=setting, status=h.skipped(library), per_ts_ours=None, per_ts_peer=None,
                ratio=None, goal=goal, met=None)


def timed_row(key, setting, B, P, T, t_ours, t_peer, goal, **numbers) -> dict:
    """A row's times: total seconds, per trial-step (the trial counts may differ), ratio, goal."""
    per_ours, per_peer = t_ours / (B * T), t_peer / (P * T)
    return dict(name=NAMES[key], setting=setting, trials_ours=B, trials_peer=P, steps=T, s_ours=t_ours,
                s_peer=t_peer, per_ts_ours=per_ours, per_ts_peer=per_peer, ratio=per_peer / per_ours, goal=goal,
                met=None if goal is None else per_peer / per_ours >= goal, **numbers)


def check_line(r) -> str:
    """The row's agreement / accuracy line (printed, and listed under the table)."""
    if r.get("status"):
        return f"- {r['name']} ({r['setting']}): {r['status']}."
    if "particles" in r:
        o = r["mse_ours_peer_trials"]
        return (f"- BPF N={r['particles']} MSE vs truth: ours {r['mse_ours']:.4f} over {r['trials_ours']} trials "
                f"(exact KF {r['mse_kf']:.4f}); particles {r['mse_peer']:.4f} over {r['trials_peer']} trials "
                f"(exact KF {r['mse_kf_peer_trials']:.4f}" + (f", ours on the same trials {o:.4f}" if o is not None else "")
                + f"). RMS distance to the KF mean: ours {r['rmse_to_kf_ours']:.4f}, "
                  f"particles {r['rmse_to_kf_peer']:.4f}. Ours mean ESS {r['mean_ess_ours']:.1f}.")
    if "alpha" in r:
        return (f"- UKF vs filterpy (MerweScaledSigmaPoints alpha={r['alpha']:g}, beta={r['beta']:g}, "
                f"kappa={r['kappa']:g} on both): max |estimate diff| {r['max_abs_diff_estimates']:.2e} over "
                f"{r['compared_trials']} trials (< 1e-6 required); max |diff| to the exact KF: ours "
                f"{r['max_abs_diff_to_kf_ours']:.2e}, filterpy {r['max_abs_diff_to_kf_peer']:.2e}; "
                f"|log-evidence diff| (trial 0) {r['log_evidence_diff_trial0']:.2e}; MSE {r['mse_ours']:.4f}.")
    return (f"- KF vs filterpy: max |estimate diff| {r['max_abs_diff_estimates']:.2e} (< 1e-8 required), "
            f"|log-evidence diff| (trial 0) {r['log_evidence_diff_trial0']:.2e}; MSE {r['mse_ours']:.4f}.")


def report(r) -> dict:
    """Print a row's times and its check line as it completes."""
    if not r.get("status"):
        print(f"[{r['name']}] {r['setting']}: ours {r['per_ts_ours']:.3e}, peer {r['per_ts_peer']:.3e} "
              f"s/trial-step, ratio {r['ratio']:.1f}x")
    print(check_line(r), flush=True)
    return r


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


def bench_filterpy(args, kind: str) -> dict:
    """1. (``kind="kf"``) and 2. (``kind="ukf"``) above."""
    B, T, d = args.kf_trials, args.steps, args.d
    P = B if kind == "kf" else args.ukf_peer_trials
    model = SensorNetwork(d=d)
    ukf_params = dict(alpha=args.ukf_alpha, beta=args.ukf_beta, kappa=args.ukf_kappa) if kind == "ukf" else {}
    ours = h.make_filter(kind, model, **ukf_params)
    if kind == "ukf":  # the peer takes exactly our alpha, beta, kappa
        ukf_params = dict(alpha=ours.alpha, beta=ours.beta, kappa=ours.kappa)
        setting = f"d={d}, T={T}, ours B={B}, peer B={P}, " + ", ".join(f"{k}={v:g}" for k, v in ukf_params.items())
    else:
        setting = f"d={d}, B={B}, T={T}"
    goal, tol = (50.0, 1e-8) if kind == "kf" else (None, 1e-6)
    filterpy = h.peer("filterpy", "kalman")
    if filterpy is None:
        return skipped_row(kind, setting, "filterpy", goal)
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
        peer = filterpy.kalman.UnscentedKalmanFilter(dim_x=d, dim_z=d, dt=1.0, fx=lambda x, dt: F @ x,
                                                     hx=lambda x: H @ x, points=points)
    peer.Q, peer.R = Q, R
    t_peer, est_peer, ll_peer, peer_blas = run_filterpy(peer, mean.numpy(), cov.numpy(), traj.observations.numpy(),
                                                        P, args)
    n = min(B, P)
    truth = traj.states[:, 1:].numpy()
    r = timed_row(kind, setting, B, P, T, t.min, t_peer, goal, d=d,
                  max_abs_diff_estimates=float(np.abs(est_ours[:n] - est_peer[:n]).max()),
                  log_evidence_diff_trial0=abs(float(t.result.log_evidence[0]) - ll_peer),
                  mse_ours=mse(est_ours, truth[:B]), mse_peer=mse(est_peer, truth[:P]), peer_blas=peer_blas)
    if kind == "ukf":  # on this linear model both UKFs equal the exact KF (untimed)
        with torch.no_grad():
            est_kf = h.make_filter("kf", model)(traj.observations, mean, cov).estimates.numpy()
        r.update(ukf_params, compared_trials=n, max_abs_diff_to_kf_ours=float(np.abs(est_ours - est_kf[:B]).max()),
                 max_abs_diff_to_kf_peer=float(np.abs(est_peer - est_kf[:P]).max()))
    if not r["max_abs_diff_estimates"] < tol:
        raise CheckFailed(f"{kind.upper()} estimates disagree with filterpy (max diff "
                          f"{r['max_abs_diff_estimates']:.3e}): comparison invalid")
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
        return skipped_row("bpf", setting, "particles", 2.0)
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
        return particles.SMC(fk=ssms.Bootstrap(ssm=LGSensorNetwork(), data=data), N=n, resampling="systematic",
                             ESSrmin=0.5, collect=[particles.collectors.Moments(mom_func=lambda W, X: W @ X)])

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
    return timed_row(
        "bpf", setting, B, P, T, t.min, tp.min, 2.0, d=d, particles=N,
        mse_ours=mse(est_ours, truth[:B]), mse_ours_peer_trials=mse(est_ours[:P], truth[:P]) if P <= B else None,
        mse_peer=mse(est_peer, truth[:P]), mse_kf=mse(est_kf[:B], truth[:B]), mse_kf_peer_trials=mse(est_kf[:P], truth[:P]),
        rmse_to_kf_ours=float(np.sqrt(np.mean((est_ours - est_kf[:B]) ** 2))),
        rmse_to_kf_peer=float(np.sqrt(np.mean((est_peer - est_kf[:P]) ** 2))),
        mean_ess_ours=float(ess_ours.mean()), peer_blas=peer_blas)


def markdown(info, results, args) -> str:
    lines = h.header("## Foundation benchmarks", args.quick, info, f"Peer BLAS threads: {info['peer_blas_threads']}.")
    lines += h.md_table(
        ["benchmark", "setting", "ours s/trial-step", "peer s/trial-step", "ratio peer/ours", "goal", "met"],
        [[r["name"], r["setting"]] + ([r["status"], "-", "-"] if r.get("status") else
                                      [f"{r['per_ts_ours']:.3e}", f"{r['per_ts_peer']:.3e}", f"{r['ratio']:.1f}x"])
         + [h.fmt(r.get("goal"), ">= {:g}x"), h.met_cell(r["met"])] for r in results])
    lines += ["", "Checks / accuracy:", ""] + [check_line(r) for r in results]
    lines += ["", "Times are best of repeats, each side after an untimed warm-up; s/trial-step = time / (trials x steps)."]
    return "\n".join(lines) + "\n"


def parse_args(argv=None):
    p = h.parser(__doc__, "tiny sizes for a smoke test (< 30 s)")
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
    argv = list(argv or [])
    args = parse_args(argv)
    with h.torch_threads(args.threads):
        info = h.machine(peer_blas_threads=args.peer_threads if args.peer_threads > 0 else "default",
                         command=h.command("bench_foundation", argv))
        print(f"{h.machine_line(info)} Peer BLAS threads: {info['peer_blas_threads']} "
              f"(BLAS default now: {h.blas_threads()}).")
        t0 = time.perf_counter()
        rows = []
        for kind in ("kf", "ukf"):
            if not getattr(args, f"skip_{kind}"):
                rows.append(report(bench_filterpy(args, kind)))
        if not args.skip_bpf:
            for N, b_ours, b_peer in zip(args.particles, args.bpf_trials, args.peer_trials):
                rows.append(report(bench_bpf(args, N, b_ours, b_peer)))
        info["total_wall_s"] = time.perf_counter() - t0
        info["load_end"] = h.loadavg()
    return dict(machine=info, rows=rows, markdown=markdown(info, rows, args), args=vars(args))


if __name__ == "__main__":
    h.main(run, "foundation")
