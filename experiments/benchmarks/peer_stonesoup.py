"""Peer baseline: Stone Soup's particle filters on torchflow's multi-target acoustic tracking model.

Runs Stone Soup (``stonesoup``, tested with 1.9.1) on the same model, data and prior as torchflow's
:class:`~torchflow.models.AcousticTracking`, so the benchmark suite can time it beside ours.
Stone Soup is imported lazily, so this module imports without it (``harness.peer("stonesoup")``
tells whether it is installed).

Configuration of the peer (everything not listed is Stone Soup's default as shipped):

* Transition model: ``stonesoup.models.transition.linear.LinearGaussianTimeInvariantTransitionModel``
  with ``transition_matrix=F`` (constant velocity, block diagonal over the 4 targets) and
  ``covariance_matrix=V`` (the filter's process noise, ``AcousticTracking.V_filter``). Its process
  noise is drawn by ``GaussianModel.rvs`` -> ``scipy.stats.multivariate_normal.rvs`` with numpy's
  global RNG.
* Measurement model: :class:`AcousticMeasurementModel` (built by :func:`_classes`), a subclass of
  ``stonesoup.models.measurement.nonlinear.NonLinearGaussianMeasurement`` with
  ``function(state) = sum_c psi / (|p_c - s| + d0)`` over the 25 sensors, vectorised over
  particles (``StateVectors``), ``noise_covar = sigma_w^2 I_25``, ``ndim_state=16``,
  ``mapping=(0, 1, 4, 5, 8, 9, 12, 13)`` (target positions) and ``ndim_meas=25``. ``rvs``, ``pdf``
  and ``logpdf`` are ``GaussianModel``'s. It overrides ``Model.jacobian`` with the analytic Jacobian
  ``dz_s/dp_c = -psi (p_c - s) / (r (r + d0)^2)`` (the same formula as
  ``AcousticTracking.measurement_jacobian``; velocities have zero columns), replacing Stone
  Soup's default finite-difference ``compute_jac``. The model has no ``matrix`` method, so the
  Gromov updater's ``measurement_model.matrix()`` raises ``AttributeError`` and it falls back to
  this ``jacobian(particle)``, as it is written to.
* Predictor (both kinds): ``stonesoup.predictor.particle.ParticlePredictor(transition_model)``
  (default ``DynamicsProposal``: propagate each particle through ``F`` plus a draw of N(0, V)).
* ``kind="bootstrap"``: ``stonesoup.updater.particle.ParticleUpdater(measurement_model,
  resampler=SystematicResampler())``, no regulariser, no constraint: weights are multiplied by the
  Gaussian likelihood, normalised in log space and the particles are resampled systematically at
  every step (Stone Soup's ``SystematicResampler`` always resamples). The resampler is a thin
  subclass that only records the effective sample size ``1 / sum w^2`` of the weights it is handed
  (i.e. after the likelihood weighting, before resampling); the per-step ``ess`` list reports it.
* ``kind="gromov"``: ``stonesoup.updater.particle.GromovFlowParticleUpdater(measurement_model)``.
  It has no parameters of its own; as shipped (1.9.1) its ``update`` hard-codes an Euler-Maruyama
  integration (``stonesoup.functions.sde_euler_maruyama_integration``) of the Gromov stochastic
  flow of Daum, Huang & Noushin (2017), eq. (12), over pseudo-time [0, 1] in ``num_steps = 20``
  exponentially growing steps with ratio ``b = 2`` (first step ``(b-1)/(b^20-1) ~ 9.5e-7``, last
  ~0.5). ``P`` is the weighted sample covariance of the predicted particles (ParticleState.covar),
  the Jacobian is evaluated at each particle's current position in the flow, the diffusion is
  ``cholesky_eps`` of ``Q = B H A``, and particles are moved one at a time in a Python loop. The
  particle weights are left unchanged (no importance reweighting, no resampling), so the reported
  ``ess`` is always ``N``. This is the updater exactly as shipped; we do not tune or fix it.
  Observed with 1.9.1 on this model (sigma_w = 0.1, N = 500, seeds 0-2): the particles blow up
  within the first one or two updates (position errors 1e15-1e130 m, overflow warnings), and the
  next update then raises ``ValueError: array must not contain infs or NaNs`` from
  ``scipy.linalg.inv(R + lambda H P H^T)``, since ``P`` (the particles' sample covariance) is no
  longer finite. A likely cause (not verified step by step): the largest eigenvalue of
  ``P H^T R^-1 H`` at the predicted prior is 1e4-2e5 here, and each particle's flow uses its own
  Jacobian but the shared sample ``P``, so 20 explicit Euler steps of up to 0.5 are not stable.

Each time step ``k = 1..T`` runs ``predict`` (timestamp ``t0 + k s``), builds a ``Detection`` with
``obs[k-1]`` and the measurement model, a ``SingleHypothesis``, and ``update``; the estimate is the
weighted particle mean (``ParticleState.mean``). Only predict + update are timed
(``time.perf_counter``); building the prior, the estimate and diagnostics are not. The initial
``ParticleState`` holds ``N`` draws of ``N(prior_mean, prior_cov)`` from
``numpy.random.default_rng(seed)`` with uniform weights; numpy's global RNG is seeded with
``seed`` too, since Stone Soup draws process noise, flow diffusion and the resampler's offset from
it. Exceptions inside a step are caught and reported (``error``, ``steps_completed``), never
raised; numpy floating-point warnings are counted and summarised in ``notes``.

    python -m experiments.benchmarks.peer_stonesoup             # smoke test: T=4, N=500, both kinds
    python -m experiments.benchmarks.peer_stonesoup --steps 3 --particles 200 --kinds bootstrap
"""
from __future__ import annotations

import datetime
import functools
import time
import traceback
import warnings
from pathlib import Path
from typing import Dict, Optional

import numpy as np

from .harness import peer, simulate

KINDS = ("gromov", "bootstrap")
_POSITION_INDICES = (0, 1, 4, 5, 8, 9, 12, 13)  # [px, py] of each target in the target-major state
_OUTLIER = 1e3  # |state component| beyond this (the field is 40 m wide) counts a particle as diverged


def stonesoup_version() -> Optional[str]:
    return getattr(peer("stonesoup"), "__version__", None)


@functools.lru_cache(maxsize=None)
def _classes():
    """Define the Stone Soup subclasses lazily (Stone Soup is an optional dependency)."""
    from stonesoup.base import Property
    from stonesoup.models.measurement.nonlinear import NonLinearGaussianMeasurement
    from stonesoup.resampler.particle import SystematicResampler
    from stonesoup.types.array import StateVector, StateVectors

    class AcousticMeasurementModel(NonLinearGaussianMeasurement):
        """Summed-amplitude acoustic sensors: ``z_s = sum_c psi / (|p_c - s_s| + d0) + w_s``,
        ``w ~ N(0, noise_covar)``. ``mapping`` lists the state indices of ``[px, py]`` of each
        target in order."""

        sensors: np.ndarray = Property(doc="Sensor positions, shape (m, 2).")
        psi: float = Property(default=10.0, doc="Source amplitude.")
        d0: float = Property(default=0.1, doc="Distance offset.")

        @property
        def ndim_meas(self) -> int:
            return int(np.asarray(self.sensors).shape[0])

        def _positions(self, state):
            sv = np.asarray(state.state_vector, dtype=np.float64)  # (d, N)
            pos = sv[list(self.mapping), :]  # (2C, N)
            return pos[0::2], pos[1::2]  # (C, N) each

        def function(self, state, noise=False, **kwargs):
            if isinstance(noise, bool) or noise is None:
                if noise:
                    noise = self.rvs(num_samples=state.state_vector.shape[1], **kwargs)
                else:
                    noise = 0
            px, py = self._positions(state)
            s = np.asarray(self.sensors, dtype=np.float64)
            dx = px[:, None, :] - s[None, :, 0:1]  # (C, m, N)
            dy = py[:, None, :] - s[None, :, 1:2]
            r = np.sqrt(dx * dx + dy * dy)
            z = (self.psi / (r + self.d0)).sum(0)  # (m, N)
            return StateVectors(z) + noise  # StateVector when N == 1

        def jacobian(self, state, **kwargs):
            """Analytic Jacobian ``(m, ndim_state)`` at a single state."""
            px, py = self._positions(state)
            px, py = px[:, 0], py[:, 0]  # (C,)
            s = np.asarray(self.sensors, dtype=np.float64)
            dx = px[:, None] - s[None, :, 0]  # (C, m)
            dy = py[:, None] - s[None, :, 1]
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

    return dict(AcousticMeasurementModel=AcousticMeasurementModel,
                ESSRecordingSystematicResampler=ESSRecordingSystematicResampler,
                StateVector=StateVector, StateVectors=StateVectors)


def make_measurement_model(sensors, psi, d0, sigma_w):
    """The acoustic measurement model as a Stone Soup ``NonLinearGaussianMeasurement``."""
    sensors = np.asarray(sensors, dtype=np.float64)
    m = sensors.shape[0]
    return _classes()["AcousticMeasurementModel"](
        ndim_state=16, mapping=_POSITION_INDICES, noise_covar=float(sigma_w) ** 2 * np.eye(m),
        sensors=sensors, psi=float(psi), d0=float(d0))


def _ess(state) -> float:
    lw = np.asarray(state.log_weight, dtype=np.float64)
    if not np.all(np.isfinite(lw)) and not np.any(np.isfinite(lw)):
        return float("nan")
    w = np.exp(lw - np.max(lw))
    w /= w.sum()
    return float(1.0 / np.sum(w * w))


def _position_rmse(estimates: np.ndarray, truth: np.ndarray) -> float:
    """RMS over steps and targets of the Euclidean position error; nan if anything is non-finite."""
    if estimates.size == 0 or not np.all(np.isfinite(estimates)):
        return float("nan")
    idx = list(_POSITION_INDICES)
    err = (estimates[:, idx] - truth[:, idx]).reshape(len(estimates), -1, 2)
    return float(np.sqrt(np.mean(np.sum(err**2, -1))))


def run_stonesoup(kind: str, states, obs, prior_mean, prior_cov, *, F, V, sensors, psi, d0, sigma_w,
                  n_particles: int = 500, seed: int = 0, stop_on_nonfinite: bool = False) -> Dict:
    """Run one Stone Soup particle filter (``kind`` in ``"gromov"``, ``"bootstrap"``) on one trajectory.

    Args:
        states: ``(T+1, 16)`` true states including ``x_0`` (for the error only).
        obs: ``(T, 25)`` measurements ``z_1..z_T``.
        prior_mean, prior_cov: ``(16,)``, ``(16, 16)`` Gaussian prior of ``x_0``.
        F, V: ``(16, 16)`` transition matrix and the filter's process-noise covariance.
        sensors: ``(25, 2)`` sensor positions; psi, d0, sigma_w: measurement parameters.
        n_particles: N; seed: seeds the initial draw and numpy's global RNG.
        stop_on_nonfinite: stop after the first step whose estimate is non-finite.

    Returns:
        dict with ``seconds_per_step`` (mean over completed steps), ``step_times``, ``estimates``
        ``(steps_completed, 16)``, ``finite``, ``position_rmse`` (nan if any estimate is non-finite),
        ``step_position_rmse`` (per step), ``first_nonfinite_step`` (1-based or None), ``ess``,
        ``step_outlier_fraction`` (per step, fraction of particles with a non-finite component or
        one beyond 1e3 in magnitude after the update), ``steps_completed``, ``error`` (None or the exception text), ``notes``, plus the
        configuration (``kind``, ``n_particles``, ``seed``, ``stonesoup_version``).
    """
    if kind not in KINDS:
        raise ValueError(f"kind: expected one of {KINDS}, got {kind!r}")
    states, obs = np.asarray(states, np.float64), np.asarray(obs, np.float64)
    prior_mean, prior_cov = np.asarray(prior_mean, np.float64), np.asarray(prior_cov, np.float64)
    T = obs.shape[0]
    if states.shape[0] != T + 1:
        raise ValueError(f"states: expected {T + 1} rows (x_0..x_T), got {states.shape[0]}")

    from stonesoup.models.transition.linear import LinearGaussianTimeInvariantTransitionModel
    from stonesoup.predictor.particle import ParticlePredictor
    from stonesoup.types.detection import Detection
    from stonesoup.types.hypothesis import SingleHypothesis
    from stonesoup.types.state import ParticleState
    from stonesoup.updater.particle import GromovFlowParticleUpdater, ParticleUpdater

    cls = _classes()
    transition = LinearGaussianTimeInvariantTransitionModel(
        transition_matrix=np.asarray(F, np.float64), covariance_matrix=np.asarray(V, np.float64))
    measurement = make_measurement_model(sensors, psi, d0, sigma_w)
    predictor = ParticlePredictor(transition)
    resampler = None
    if kind == "bootstrap":
        resampler = cls["ESSRecordingSystematicResampler"]()
        updater = ParticleUpdater(measurement, resampler=resampler)
    else:
        updater = GromovFlowParticleUpdater(measurement)

    np.random.seed(seed)
    rng = np.random.default_rng(seed)
    N = int(n_particles)
    t0 = datetime.datetime(2000, 1, 1)
    samples = rng.multivariate_normal(prior_mean, prior_cov, size=N).T  # (16, N)
    state = ParticleState(cls["StateVectors"](samples), log_weight=np.full(N, -np.log(N)), timestamp=t0)

    step_times, estimates, step_rmse, ess, outliers = [], [], [], [], []
    error, first_nonfinite = None, None
    idx = list(_POSITION_INDICES)
    with warnings.catch_warnings(record=True) as caught, np.errstate(divide="warn", over="warn", invalid="warn"):
        warnings.simplefilter("always")
        for k in range(1, T + 1):
            try:
                ts = t0 + datetime.timedelta(seconds=k)
                detection = Detection(cls["StateVector"](obs[k - 1]), timestamp=ts,
                                      measurement_model=measurement)
                tic = time.perf_counter()
                prediction = predictor.predict(state, timestamp=ts)
                state = updater.update(SingleHypothesis(prediction, detection))
                step_times.append(time.perf_counter() - tic)
            except Exception as exc:  # report, never raise: Gromov as shipped may break here
                tb = traceback.extract_tb(exc.__traceback__)
                ss = [f for f in tb if "stonesoup" in f.filename]
                frames = ([ss[-1]] if ss and ss[-1] is not tb[-1] else []) + [tb[-1]]
                where = "; ".join(f"{'/'.join(Path(f.filename).parts[-2:])}:{f.lineno} {f.name}: {f.line}"
                                  for f in frames)
                error = f"step {k}: {type(exc).__name__}: {exc} [at {where}]"
                break
            est = np.asarray(state.mean, np.float64).reshape(-1)
            estimates.append(est)
            ess.append(resampler.ess_log[-1] if resampler is not None else _ess(state))
            sv = np.asarray(state.state_vector, np.float64)
            outliers.append(float(np.mean(~np.all(np.isfinite(sv) & (np.abs(sv) < _OUTLIER), axis=0))))
            err = (est[idx] - states[k, idx]).reshape(-1, 2)
            step_rmse.append(float(np.sqrt(np.mean(np.sum(err**2, -1)))))
            if first_nonfinite is None and not np.all(np.isfinite(est)):
                first_nonfinite = k
                if stop_on_nonfinite:
                    break

    est_arr = np.stack(estimates) if estimates else np.zeros((0, 16))
    done = len(estimates)
    finite = bool(done > 0 and np.all(np.isfinite(est_arr)))
    notes = [f"Stone Soup {stonesoup_version()}; kind={kind}; N={N}; "
             + ("ParticlePredictor + GromovFlowParticleUpdater as shipped (20 Euler-Maruyama steps, "
                "ratio 2, weights unchanged, no resampling); analytic Jacobian"
                if kind == "gromov" else
                "ParticlePredictor + ParticleUpdater(resampler=SystematicResampler), resampling every step; "
                "ESS is before resampling")]
    if first_nonfinite is not None:
        notes.append(f"first non-finite estimate at step {first_nonfinite}")
    if error is not None:
        notes.append(f"stopped by exception after {done} completed steps: {error}")
    fp = [w for w in caught if issubclass(w.category, RuntimeWarning)]
    if fp:
        msgs = sorted({str(w.message) for w in fp})
        notes.append(f"{len(fp)} RuntimeWarnings: " + "; ".join(msgs[:5]))
    return dict(
        kind=kind, n_particles=N, seed=seed, stonesoup_version=stonesoup_version(),
        seconds_per_step=float(np.mean(step_times)) if step_times else float("nan"),
        step_times=[float(t) for t in step_times],
        estimates=est_arr,
        finite=finite,
        position_rmse=_position_rmse(est_arr, states[1:done + 1]),
        step_position_rmse=step_rmse,
        first_nonfinite_step=first_nonfinite,
        ess=[float(e) for e in ess],
        step_outlier_fraction=outliers,
        steps_completed=done,
        error=error,
        notes=". ".join(notes),
    )


def run_on_model(kind: str, model, states, obs, prior_mean, prior_cov, **kwargs) -> Dict:
    """:func:`run_stonesoup` with the model parameters taken from a torchflow ``AcousticTracking``
    and torch tensors (one trial: ``states (T+1, 16)``, ``obs (T, 25)``, ``(16,)``, ``(16, 16)``)."""
    def np64(t):
        return t.detach().cpu().double().numpy() if hasattr(t, "detach") else np.asarray(t, np.float64)
    return run_stonesoup(kind, np64(states), np64(obs), np64(prior_mean), np64(prior_cov),
                         F=np64(model.F), V=np64(model.transition_cov()), sensors=np64(model.sensors),
                         psi=float(model.psi), d0=float(model.d0), sigma_w=float(model.sigma_w), **kwargs)


def _main():
    import argparse
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=4)
    ap.add_argument("--particles", type=int, default=500)
    ap.add_argument("--kinds", default="bootstrap,gromov")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    if peer("stonesoup", "updater.particle") is None:
        print("stonesoup is not installed; nothing to run")
        return
    from torchflow.models import AcousticTracking

    m = AcousticTracking()
    traj, mean, cov = simulate(m, 1, a.steps, a.seed)

    # analytic Jacobian vs torchflow's and vs Stone Soup's finite differences
    from stonesoup.functions import jacobian as fd_jacobian
    from stonesoup.types.state import State
    mm = make_measurement_model(m.sensors.numpy(), float(m.psi), float(m.d0), float(m.sigma_w))
    x1 = traj.states[0, 1].numpy()
    H = mm.jacobian(State(x1.reshape(-1, 1)))
    H_tf = m.measurement_jacobian(traj.states[0, 1]).numpy()
    H_fd = fd_jacobian(mm.function, State(x1.reshape(-1, 1)))
    z_tf = m.measure(traj.states[0, 1]).numpy()
    z_ss = np.asarray(mm.function(State(x1.reshape(-1, 1)))).ravel()
    print(f"measurement |h_ss - h_tf|max = {np.abs(z_ss - z_tf).max():.2e}; Jacobian |H - H_tf|max = "
          f"{np.abs(H - H_tf).max():.2e}, |H - H_fd|max = {np.abs(H - H_fd).max():.2e}")

    for kind in a.kinds.split(","):
        r = run_on_model(kind, m, traj.states[0], traj.observations[0], mean[0], cov[0],
                         n_particles=a.particles, seed=a.seed)
        print(f"\n[{kind}] N={a.particles}, T={a.steps}: {r['seconds_per_step']:.3f} s/step "
              f"(steps: {', '.join(f'{t:.3f}' for t in r['step_times'])})")
        print(f"  position RMSE {r['position_rmse']:.4g} m; per step "
              f"{', '.join(f'{e:.3g}' for e in r['step_position_rmse'])}; finite={r['finite']}; "
              f"steps completed {r['steps_completed']}/{a.steps}; error={r['error']}")
        print(f"  ESS {', '.join(f'{e:.1f}' for e in r['ess'])}; diverged-particle fraction "
              f"{', '.join(f'{e:.3f}' for e in r['step_outlier_fraction'])}")
        print(f"  notes: {r['notes']}")


if __name__ == "__main__":
    _main()
