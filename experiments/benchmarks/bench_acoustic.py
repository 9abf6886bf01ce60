"""Acoustic tracking against Stone Soup: torchflow's Gromov flow filter, PF-PF(Gromov), PF-PF(LEDH) and
BPF beside Stone Soup's ``GromovFlowParticleUpdater`` and bootstrap ``ParticleUpdater``, N = 500, same
trajectories. Ours: wall time of the filter calls (preferred chunks, after a 1-trial warm-up) / (trials
x steps); Stone Soup: the mean predict + update time of the completed steps. Accuracy: OMAT and the
position RMSE without assignment. Goal (the peer-speed goal): PF-PF(LEDH) and PF-PF(Gromov) >= 30x faster than
Stone Soup's Gromov updater with its square root repaired (:func:`_repaired_gromov`) while tracking (finite,
mean OMAT <= 2 m); the updater as shipped is timed beside it.

    python -m experiments.benchmarks.bench_acoustic            # 20 trials x 10 steps (ours), peer 3 x 5

The peer (Stone Soup 1.9.1, imported lazily; without it, ``skipped`` rows), as shipped apart from the
measurement model: a ``ParticlePredictor`` of ``LinearGaussianTimeInvariantTransitionModel(F, V)``;
``AcousticMeasurementModel``, vectorised over particles, with the analytic Jacobian (it has no
``matrix()``, so the Gromov updater falls back to it, as written to); ``bootstrap``: ``ParticleUpdater``
with a ``SystematicResampler`` (every step; the subclass only records the ESS); ``gromov``:
``GromovFlowParticleUpdater`` (a hard-coded 20-step Euler-Maruyama integration, ratio 2, ``P`` the
particles' sample covariance, one particle at a time, weights unchanged), which diverges on this model
and then raises; ``gromov_repaired``: the same updater with only its diffusion's square root replaced
(``B B^T = Q``; :func:`_repaired_gromov` says what is wrong with the shipped one), nothing tuned. The prior particles
come from ``default_rng(seed)``; numpy's
global RNG (process noise, flow diffusion, resampler offset) is seeded with ``seed``.
"""

from __future__ import annotations

import datetime
import functools
import time
import traceback
import warnings
from pathlib import Path

import numpy as np
import torch

from torchflow.core import metrics
from torchflow.models import AcousticTracking

from . import harness as h

GOAL = 30.0
OURS = ("flow_gromov", "gromov", "ledh", "bpf")
PEERS = (
    ("gromov", "GromovFlowParticleUpdater (Stone Soup)"),
    ("gromov_repaired", "GromovFlowParticleUpdater (Stone Soup), square root repaired"),
    ("bootstrap", "ParticleUpdater bootstrap (Stone Soup)"),
)
_POSITION_INDICES = (0, 1, 4, 5, 8, 9, 12, 13)  # [px, py] of each target in the target-major state


@functools.lru_cache(maxsize=None)
def _classes():
    """Define the Stone Soup subclasses lazily (Stone Soup is an optional dependency)."""
    from stonesoup.base import Property
    from stonesoup.models.measurement.nonlinear import NonLinearGaussianMeasurement
    from stonesoup.resampler.particle import SystematicResampler
    from stonesoup.types.array import StateVector, StateVectors

    class AcousticMeasurementModel(NonLinearGaussianMeasurement):
        """``z_s = sum_c psi / (|p_c - s_s| + d0) + w_s``; ``mapping``: the indices of each target's ``[px, py]``."""

        sensors: np.ndarray = Property(doc="Sensor positions, shape (m, 2).")
        psi: float = Property(default=10.0, doc="Source amplitude.")
        d0: float = Property(default=0.1, doc="Distance offset.")

        @property
        def ndim_meas(self) -> int:
            return int(np.asarray(self.sensors).shape[0])

        def _positions(self, state):
            pos = np.asarray(state.state_vector, dtype=np.float64)[list(self.mapping), :]  # (2C, N)
            return pos[0::2], pos[1::2]  # (C, N) each

        def function(self, state, noise=False, **kwargs):
            if isinstance(noise, bool) or noise is None:
                noise = self.rvs(num_samples=state.state_vector.shape[1], **kwargs) if noise else 0
            px, py = self._positions(state)
            s = np.asarray(self.sensors, dtype=np.float64)
            dx = px[:, None, :] - s[None, :, 0:1]  # (C, m, N)
            dy = py[:, None, :] - s[None, :, 1:2]
            r = np.sqrt(dx * dx + dy * dy)
            return StateVectors((self.psi / (r + self.d0)).sum(0)) + noise  # (m, N); StateVector when N == 1

        def jacobian(self, state, **kwargs):
            """Analytic Jacobian ``(m, ndim_state)`` at a single state."""
            px, py = self._positions(state)
            s = np.asarray(self.sensors, dtype=np.float64)
            dx = px[:, 0, None] - s[None, :, 0]  # (C, m)
            dy = py[:, 0, None] - s[None, :, 1]
            r = np.sqrt(dx * dx + dy * dy)
            coef = -self.psi / (np.maximum(r, np.finfo(np.float64).tiny) * (r + self.d0) ** 2)
            H = np.zeros((self.ndim_meas, self.ndim_state))
            mapping = list(self.mapping)
            H[:, mapping[0::2]] = (coef * dx).T
            H[:, mapping[1::2]] = (coef * dy).T
            return H

    class ESSRecordingSystematicResampler(SystematicResampler):
        """``SystematicResampler`` that records the ESS of the weights it is given."""

        def resample(self, particles, nparts=None):
            lw = np.asarray(particles.log_weight, dtype=np.float64)
            w = np.exp(lw - np.max(lw))
            w /= w.sum()
            self.__dict__.setdefault("ess_log", []).append(float(1.0 / np.sum(w * w)))
            return super().resample(particles, nparts)

    return AcousticMeasurementModel, ESSRecordingSystematicResampler, StateVector, StateVectors, _repaired_gromov()


def psd_root(A: np.ndarray, lower: bool = False) -> np.ndarray:
    """A square root ``B`` of a symmetric positive semi-definite ``A`` with ``B B^T = A``: the symmetric
    root from an eigendecomposition, negative round-off eigenvalues set to 0 (``lower`` is accepted and
    ignored: the root is symmetric, so ``B = B^T`` either way)."""
    w, U = np.linalg.eigh((A + A.T) / 2)
    return (U * np.sqrt(np.clip(w, 0.0, None))) @ U.T


def _repaired_gromov():
    """Stone Soup's ``GromovFlowParticleUpdater`` with one change: the diffusion's square root.

    As shipped it takes ``B = cholesky_eps(Q)``, which returns the *upper* factor ``U`` (``Q = U^T U``)
    and uses it as ``B dW``: the noise covariance is ``U U^T``, not ``Q``. And ``Q = a H^T R^-1 H a``
    has rank at most the 8 measured coordinates of 16, so ``cholesky_eps`` floors the other pivots at
    ``sqrt(eps)`` and divides the later rows by them: entries of order 1e8 and a flow that diverges.
    Repaired: ``B = psd_root(Q)`` (``B B^T = Q``); everything else is Stone Soup's own code, run as is."""
    import stonesoup.updater.particle as ssp

    class RepairedGromovFlowParticleUpdater(ssp.GromovFlowParticleUpdater):
        def update(self, hypothesis, **kwargs):
            shipped = ssp.cholesky_eps
            ssp.cholesky_eps = psd_root  # the module global its update's closure looks up
            try:
                return super().update(hypothesis, **kwargs)
            finally:
                ssp.cholesky_eps = shipped

    return RepairedGromovFlowParticleUpdater


def run_stonesoup(kind: str, model, obs, prior_mean, prior_cov, n_particles: int, seed: int):
    """Stone Soup's ``kind`` filter (``"gromov"``, ``"gromov_repaired"`` or ``"bootstrap"``) on one trial of
    ``model``: ``obs
    (T, 25)``, prior ``(16,)``, ``(16, 16)``. Returns the seconds of each completed step's predict +
    update, the estimates ``(steps completed, 16)`` and the error that stopped it (None or its text)."""
    from stonesoup.models.transition.linear import LinearGaussianTimeInvariantTransitionModel
    from stonesoup.predictor.particle import ParticlePredictor
    from stonesoup.types.detection import Detection
    from stonesoup.types.hypothesis import SingleHypothesis
    from stonesoup.types.state import ParticleState
    from stonesoup.updater.particle import GromovFlowParticleUpdater, ParticleUpdater

    np64 = lambda t: t.detach().cpu().double().numpy()
    obs, prior_mean, prior_cov = map(np64, (obs, prior_mean, prior_cov))
    Measurement, Resampler, StateVector, StateVectors, Repaired = _classes()
    sensors = np64(model.sensors)
    measurement = Measurement(
        ndim_state=16,
        mapping=_POSITION_INDICES,
        sensors=sensors,
        psi=float(model.psi),
        d0=float(model.d0),
        noise_covar=float(model.sigma_w) ** 2 * np.eye(sensors.shape[0]),
    )
    predictor = ParticlePredictor(
        LinearGaussianTimeInvariantTransitionModel(
            transition_matrix=np64(model.F), covariance_matrix=np64(model.transition_cov())
        )
    )
    resampler = Resampler() if kind == "bootstrap" else None
    updater = (
        ParticleUpdater(measurement, resampler=resampler)
        if kind == "bootstrap"
        else Repaired(measurement)
        if kind == "gromov_repaired"
        else GromovFlowParticleUpdater(measurement)
    )

    np.random.seed(seed)
    N, t0 = int(n_particles), datetime.datetime(2000, 1, 1)
    samples = np.random.default_rng(seed).multivariate_normal(prior_mean, prior_cov, size=N).T  # (16, N)
    state = ParticleState(StateVectors(samples), log_weight=np.full(N, -np.log(N)), timestamp=t0)
    step_times, estimates, error = [], [], None
    with warnings.catch_warnings(record=True), np.errstate(divide="warn", over="warn", invalid="warn"):
        warnings.simplefilter("always")
        for k in range(1, obs.shape[0] + 1):
            try:
                ts = t0 + datetime.timedelta(seconds=k)
                detection = Detection(StateVector(obs[k - 1]), timestamp=ts, measurement_model=measurement)
                tic = time.perf_counter()
                prediction = predictor.predict(state, timestamp=ts)
                state = updater.update(SingleHypothesis(prediction, detection))
                step_times.append(time.perf_counter() - tic)
            except Exception as exc:  # report, never raise: Gromov as shipped breaks here
                tb = traceback.extract_tb(exc.__traceback__)
                ss = [f for f in tb if "stonesoup" in f.filename]
                frames = ([ss[-1]] if ss and ss[-1] is not tb[-1] else []) + [tb[-1]]
                where = "; ".join(
                    f"{'/'.join(Path(f.filename).parts[-2:])}:{f.lineno} {f.name}: {f.line}" for f in frames
                )
                error = f"step {k}: {type(exc).__name__}: {exc} [at {where}]"
                break
            estimates.append(np.asarray(state.mean, np.float64).reshape(-1))
    return step_times, np.stack(estimates) if estimates else np.zeros((0, 16)), error


def omat(est: torch.Tensor, truth: torch.Tensor, model) -> float:
    """Mean OMAT (metres) of estimates ``(B, T, 16)`` against the true states."""
    return float(metrics.omat(model.positions(est.double()), model.positions(truth.double())).mean())


def peer_row(kind, label, model, traj, mean, cov, a) -> dict:
    """Stone Soup's ``kind`` filter over ``--peer-trials`` trajectories, one trial at a time."""
    times, rmses, finite, completed, fails, omats, steps = [], [], [], 0, [], [], []
    pos = lambda x: x[:, list(_POSITION_INDICES)].reshape(len(x), -1, 2)
    with h.blas_limit(a.peer_threads):
        for b in range(a.peer_trials):
            t, est, error = run_stonesoup(
                kind, model, traj.observations[b, : a.peer_steps], mean[b], cov[b], a.particles, a.seed + b
            )
            truth = traj.states[b, 1 : 1 + len(est)].double().numpy()
            with np.errstate(over="ignore", invalid="ignore"):  # a diverged filter's errors overflow
                sq = np.sum((pos(est) - pos(truth)) ** 2, -1)  # (steps, targets)
            times += t
            completed += len(est)
            finite.append(bool(len(est) and np.all(np.isfinite(est))))
            rmses.append(float(np.sqrt(np.mean(sq))) if finite[-1] else float("nan"))
            steps.append([float(v) for v in np.sqrt(np.mean(sq, -1))])
            if len(est):  # OMAT over the completed steps (inf where non-finite)
                omats.append(omat(torch.as_tensor(est).nan_to_num(1e300)[None], torch.as_tensor(truth)[None], model))
            if error:
                fails.append(f"trial {b}: step {len(est) + 1} raised {error[:160]}")
    per_ts = float(np.mean(times)) if times else float("nan")
    print(f"[peer] {label}: {per_ts:.4g} s/step over {completed} completed steps; failures: {fails}")
    return dict(
        name=label,
        side="peer",
        trials=a.peer_trials,
        steps=a.peer_steps,
        steps_completed=completed,
        per_ts=per_ts,
        finite=all(finite),
        position_rmse=float(np.nanmax(rmses)) if rmses else float("nan"),
        step_position_rmse=steps,
        failures=fails,
        chunk=1,
        omat=float(np.mean(omats)) if omats else None,
        stonesoup=getattr(h.peer("stonesoup"), "__version__", None),
    )


def run(argv=None) -> dict:
    a = h.options(
        __doc__,
        argv,
        dict(trials=4, steps=3, peer_trials=1, peer_steps=2),
        trials=20,
        steps=10,
        particles=500,
        peer_trials=3,
        peer_steps=5,
        sigma_w=0.1,
        seed=0,
        threads=None,
        peer_threads=1,
        no_peer=False,
    )  # peer_threads: numpy BLAS threads for Stone Soup (0: default)
    with h.session("bench_acoustic", argv, a.threads) as info:
        model = AcousticTracking(sigma_w=a.sigma_w)
        traj, mean, cov = h.simulate(model, max(a.trials, a.peer_trials), max(a.steps, a.peer_steps), a.seed)
        obs, truth = traj.observations[: a.trials, : a.steps], traj.states[: a.trials, 1 : a.steps + 1]
        rows = []
        for key in OURS:
            f = h.make_filter(key, model, a.particles)
            chunk = f.preferred_chunk_trials() or a.trials
            t = h.time_filter(
                f,
                obs,
                mean[: a.trials],
                cov[: a.trials],
                chunk,
                h.streams(a.seed + 1, f.stream_name),
                warm_randomness=lambda s, e: torch.Generator().manual_seed(a.seed + 1),
            )  # as the runner
            est = torch.cat([p.estimates for p in t.result])
            d = model.positions(est.double()) - model.positions(truth.double())
            rows.append(
                dict(
                    name=f"{h.LABELS[key]} (torchflow)",
                    side="ours",
                    trials=a.trials,
                    steps=a.steps,
                    chunk=min(chunk, a.trials),
                    per_ts=t.min / (a.trials * a.steps),
                    wall=t.min,
                    finite=bool(torch.isfinite(est).all()),
                    omat=omat(est, truth, model),
                    error=None,
                    position_rmse=float(d.pow(2).sum(-1).mean().sqrt()),
                )
            )
            print(rows[-1], flush=True)
        if not a.no_peer:
            have = h.peer("stonesoup", "updater.particle") is not None
            for kind, label in PEERS:
                rows.append(
                    peer_row(kind, label, model, traj, mean, cov, a)
                    if have
                    else dict(name=label, side="peer", status=h.skipped("stonesoup"), per_ts=None)
                )
    shipped, ref, boot = (
        next((r for r in rows if r["name"] == label and r["per_ts"] is not None), None) for _, label in PEERS
    )
    for r in rows:
        r["vs_stonesoup_gromov"] = ref["per_ts"] / r["per_ts"] if ref and r["side"] == "ours" else None
        r["vs_stonesoup_gromov_shipped"] = shipped["per_ts"] / r["per_ts"] if shipped and r["side"] == "ours" else None
        r["vs_stonesoup_bootstrap"] = boot["per_ts"] / r["per_ts"] if boot and r["name"].startswith("BPF") else None
        r["goal"] = GOAL if r["name"].startswith(("PF-PF(LEDH)", "PF-PF(Gromov)")) and ref else None
        r["met"] = (r["vs_stonesoup_gromov"] >= GOAL and status(r) == "tracking") if r["goal"] else None
    return dict(machine=info, rows=rows, markdown=markdown(info, rows, a), args=vars(a))


def status(r, lost_m: float = 2.0) -> str:
    """``skipped: ...``, ``diverged`` (non-finite or errors over 1 km; ``, then raised``), ``raised``,
    ``tracking`` (mean OMAT <= ``lost_m``, the tables' lost-track threshold) or ``finite, tracks lost``."""
    if r.get("status"):
        return r["status"]
    if not r["finite"] or not r["position_rmse"] < 1e3:
        return "diverged, then raised" if r.get("failures") else "diverged"
    return "raised" if r.get("failures") else "finite, tracks lost" if (r.get("omat") or 0) > lost_m else "tracking"


def markdown(info, rows, a) -> str:
    notes = []
    for r in rows:
        if r["side"] == "peer" and not r.get("status"):
            notes.append(
                f"- {r['name']} (stonesoup {r.get('stonesoup')}): {r['steps_completed']} of "
                f"{r['trials'] * r['steps']} steps completed; worst position RMSE "
                f"{h.fmt(r['position_rmse'])} m."
            )
            notes += [f"  - {msg}" for msg in r.get("failures", [])]
            steps = [e for e in (r.get("step_position_rmse") or []) if e]
            if r["name"].startswith("Gromov") and steps:
                notes.append(
                    "  - per-step position RMSE (m) by trial: "
                    + "; ".join(", ".join(h.fmt(v, "{:.2g}") for v in e) for e in steps)
                )
    return h.report(
        "## Acoustic tracking vs Stone Soup",
        a,
        info,
        [
            f"Stone Soup with numpy BLAS threads {a.peer_threads or 'default'}. Acoustic model sigma_w = {a.sigma_w}, "
            f"N = {a.particles}; ours {a.trials} trials x {a.steps} steps (float64, trials per call in the "
            "table), Stone "
            f"Soup {a.peer_trials} trials x up to {a.peer_steps} steps (its time is the mean over completed steps)."
        ],
        [
            "filter",
            "s / trial-step",
            "Stone Soup Gromov (repaired) time / ours",
            "Stone Soup Gromov (shipped) time / ours",
            "Stone Soup bootstrap time / ours",
            "goal",
            "met",
            "position RMSE (m)",
            "OMAT (m)",
            "status",
            "trials per call",
        ],
        [
            [
                r["name"],
                h.fmt(r["per_ts"], "{:.4g}"),
                h.fmt(r.get("vs_stonesoup_gromov"), "{:.1f}x"),
                h.fmt(r.get("vs_stonesoup_gromov_shipped"), "{:.1f}x"),
                h.fmt(r.get("vs_stonesoup_bootstrap"), "{:.1f}x"),
                h.fmt(r.get("goal"), ">= {:.0f}x"),
                h.met_cell(r.get("met")),
                h.fmt(r.get("position_rmse")),
                h.fmt(r.get("omat")),
                status(r),
                r.get("chunk", "-"),
            ]
            for r in rows
        ],
        *notes,
        "- Ratios are Stone Soup's time per step over ours per trial-step: both are the cost of "
        "filtering one trajectory for one time step.",
    )


if __name__ == "__main__":
    h.main(run, "acoustic")
