"""Peer baseline: Stone Soup's particle filters (tested with 1.9.1) on torchflow's
:class:`~torchflow.models.AcousticTracking` model, data and prior, for ``bench_acoustic``. Stone Soup
is imported lazily (``harness.peer("stonesoup")`` tells whether it is installed).

The peer, as shipped apart from the measurement model:

* transition: ``LinearGaussianTimeInvariantTransitionModel(F, V)`` (``V``: the filter's process
  noise), propagated by ``ParticlePredictor`` (each particle through ``F`` plus a draw of N(0, V));
* measurement: :class:`AcousticMeasurementModel`, a ``NonLinearGaussianMeasurement`` with
  ``function(state) = sum_c psi / (|p_c - s| + d0)`` over the 25 sensors, vectorised over particles,
  ``noise_covar = sigma_w^2 I``, ``mapping`` the 8 target-position indices, and the analytic Jacobian
  ``dz_s/dp_c = -psi (p_c - s) / (r (r + d0)^2)`` in place of Stone Soup's finite differences. It
  has no ``matrix()``, so the Gromov updater falls back to ``jacobian(particle)``, as written to;
* ``bootstrap``: ``ParticleUpdater(resampler=SystematicResampler())``, resampling at every step (the
  resampler subclass only records the ESS of the weights it is handed);
* ``gromov``: ``GromovFlowParticleUpdater``, which hard-codes an Euler-Maruyama integration of the
  Gromov flow (Daum, Huang & Noushin 2017, eq. 12) over 20 exponentially growing pseudo-time steps
  (ratio 2), ``P`` the particles' weighted sample covariance, the Jacobian at each particle, one
  particle at a time in Python, weights unchanged and no resampling. On this model (sigma_w = 0.1,
  N = 500) its particles blow up within one or two updates and the next update raises ``ValueError:
  array must not contain infs or NaNs`` from ``inv(R + lambda H P H^T)``. We do not tune or fix it.

Each step ``k`` runs ``predict`` and ``update`` with a ``Detection`` of ``obs[k-1]`` (only those two are
timed); the estimate is the weighted particle mean. The prior particles are ``N`` draws of
``N(prior_mean, prior_cov)`` from ``numpy.random.default_rng(seed)``; numpy's global RNG (process
noise, flow diffusion, resampler offset) is seeded with ``seed`` too. An exception inside a step is
reported (``error``, ``steps_completed``), never raised.
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

from .harness import peer

_POSITION_INDICES = (0, 1, 4, 5, 8, 9, 12, 13)  # [px, py] of each target in the target-major state


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

    return AcousticMeasurementModel, ESSRecordingSystematicResampler, StateVector, StateVectors


def run_on_model(kind: str, model, states, obs, prior_mean, prior_cov, n_particles: int = 500, seed: int = 0) -> Dict:
    """Stone Soup's ``kind`` filter (``"gromov"`` or ``"bootstrap"``) on one trial of the torchflow
    ``AcousticTracking`` ``model``: ``states (T+1, 16)`` (``x_0..x_T``, for the errors only), ``obs (T,
    25)``, prior ``(16,)``, ``(16, 16)``. Returns ``step_times`` (predict + update, seconds), ``estimates
    (steps_completed, 16)``, ``finite``, ``position_rmse`` (nan if any estimate is non-finite),
    ``step_position_rmse``, ``ess`` (bootstrap), ``steps_completed`` and ``error`` (None or the text)."""
    from stonesoup.models.transition.linear import LinearGaussianTimeInvariantTransitionModel
    from stonesoup.predictor.particle import ParticlePredictor
    from stonesoup.types.detection import Detection
    from stonesoup.types.hypothesis import SingleHypothesis
    from stonesoup.types.state import ParticleState
    from stonesoup.updater.particle import GromovFlowParticleUpdater, ParticleUpdater

    np64 = lambda t: t.detach().cpu().double().numpy()  # noqa: E731
    states, obs, prior_mean, prior_cov = map(np64, (states, obs, prior_mean, prior_cov))
    Measurement, Resampler, StateVector, StateVectors = _classes()
    sensors = np64(model.sensors)
    measurement = Measurement(ndim_state=16, mapping=_POSITION_INDICES, sensors=sensors, psi=float(model.psi),
                              d0=float(model.d0), noise_covar=float(model.sigma_w) ** 2 * np.eye(sensors.shape[0]))
    predictor = ParticlePredictor(LinearGaussianTimeInvariantTransitionModel(
        transition_matrix=np64(model.F), covariance_matrix=np64(model.transition_cov())))
    resampler = Resampler() if kind == "bootstrap" else None
    updater = (ParticleUpdater(measurement, resampler=resampler) if kind == "bootstrap" else
               GromovFlowParticleUpdater(measurement))

    np.random.seed(seed)
    N, t0 = int(n_particles), datetime.datetime(2000, 1, 1)
    samples = np.random.default_rng(seed).multivariate_normal(prior_mean, prior_cov, size=N).T  # (16, N)
    state = ParticleState(StateVectors(samples), log_weight=np.full(N, -np.log(N)), timestamp=t0)
    step_times, estimates, step_rmse, error = [], [], [], None
    idx = list(_POSITION_INDICES)
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
                where = "; ".join(f"{'/'.join(Path(f.filename).parts[-2:])}:{f.lineno} {f.name}: {f.line}"
                                  for f in frames)
                error = f"step {k}: {type(exc).__name__}: {exc} [at {where}]"
                break
            estimates.append(np.asarray(state.mean, np.float64).reshape(-1))
            err = (estimates[-1][idx] - states[k, idx]).reshape(-1, 2)
            step_rmse.append(float(np.sqrt(np.mean(np.sum(err**2, -1)))))
    est = np.stack(estimates) if estimates else np.zeros((0, 16))
    finite = bool(len(est) and np.all(np.isfinite(est)))
    pos = lambda x: x[:, idx].reshape(len(x), -1, 2)  # noqa: E731  (steps, targets, 2)
    rmse = float(np.sqrt(np.mean(np.sum((pos(est) - pos(states[1:len(est) + 1])) ** 2, -1)))) if finite else np.nan
    return dict(step_times=step_times, estimates=est, finite=finite, step_position_rmse=step_rmse, position_rmse=rmse,
                ess=getattr(resampler, "ess_log", None), steps_completed=len(est), error=error)
