"""torchflow's particle flows inside Stone Soup: :class:`FlowParticleUpdater`, a Stone Soup ``Updater``.

Stone Soup (https://github.com/dstl/Stone-Soup) builds trackers from predictors, updaters,
hypothesisers, data associators, initiators and deleters. Its one particle-flow updater,
``GromovFlowParticleUpdater``, moves the particles one by one in Python. This updater takes the same
place in a Stone Soup tracker and runs a torchflow flow (EDH, LEDH, Gromov, geodesic, optimised
diffusion) on all particles at once::

    from stonesoup.predictor.particle import ParticlePredictor
    from torchflow.interop.stonesoup import FlowParticleUpdater

    predictor = ParticlePredictor(transition_model)
    updater = FlowParticleUpdater(measurement_model, flow="ledh")
    prediction = predictor.predict(prior, timestamp=detection.timestamp)
    posterior = updater.update(SingleHypothesis(prediction, detection))   # a ParticleStateUpdate

**Weights.** Where the prediction carries its parent particles and transition model (Stone Soup's
``ParticlePredictor`` sets both) and the transition is linear-Gaussian, the update is the PF-PF's
(Li & Coates 2017): each flowed particle is weighted by ``p(x | x_prev) p(z | x) / q(x)`` with the
invertible flow's ``q(x) = p(eta_0 | x_prev) / |det d x / d eta_0|`` (EDH, LEDH, geodesic) or the
stochastic flow's exact Gaussian law (Gromov, optimised diffusion). Otherwise the particles keep
the prediction's weights and the flow alone moves them to the posterior (the unweighted flow
filter of Ding & Coates); a one-time warning says so.

**Flow prior.** The flows start from a Gaussian ``N(eta_bar_0, P)``. With a parent and a
linear-Gaussian transition, ``eta_bar_0 = F x_prev`` per particle (per-particle points) or its
weighted mean (EDH: one point), and ``flow_prior`` chooses ``P``: ``"transition"`` (default) ``P = Q``,
each particle's own law ``N(F x_prev, Q)``, so the flow carries exactly the distribution its particle
was drawn from; ``"predicted"``: ``P = F P_prev F^T + Q`` (``P_prev`` the parent's weighted sample
covariance), the spread of the whole cloud, like Li & Coates' EKF covariance. Both give exact
weights; on Stone Soup's tutorial scenario ``"transition"`` doubles the ESS of the bootstrap
``ParticleUpdater`` where ``"predicted"`` falls to a third of it (RESULTS.md, "Stone Soup"): a prior
wider than the particles' own law over-contracts them. Without a parent ``P`` is the prediction's
weighted sample covariance and ``eta_bar_0`` the particle itself (or the weighted mean).

**Models** are used as they are: Stone Soup's ``LinearGaussian`` measurement (its matrix),
``CartesianToBearingRange`` and ``CartesianToElevationBearingRange`` (rewritten in torch with their
translation and rotation offsets, differentiated by ``torch.func``; angle residuals wrapped to
(-pi, pi] around the detection) and linear-Gaussian transition models (``matrix``/``covar`` over the
prediction's time interval, e.g. ``CombinedLinearGaussianTransitionModel`` of ``ConstantVelocity``).
Any other measurement model goes through its vectorised ``function`` with a finite-difference
Jacobian (one batched call for all particles and directions; slower, and not on a GPU); any other
transition model gives the unweighted update. Weights are in log space both ways; states,
timestamps and the hypothesis are kept; float64 by default.
"""
from __future__ import annotations

import math
import warnings

import numpy as np
import torch
from scipy.special import logsumexp

from stonesoup.base import Property
from stonesoup.models.measurement.base import MeasurementModel
from stonesoup.models.measurement.linear import LinearGaussian as _SSLinearGaussian
from stonesoup.models.measurement.nonlinear import CartesianToBearingRange, CartesianToElevationBearingRange
from stonesoup.models.base import GaussianModel, LinearModel
from stonesoup.resampler import Resampler
from stonesoup.types.angle import Angle
from stonesoup.types.array import StateVectors
from stonesoup.types.state import State
from stonesoup.types.update import ParticleStateUpdate, Update
from stonesoup.updater.base import Updater
from stonesoup.updater.particle import ParticleUpdater

from .. import linalg
from ..flows import FlowPrior, integrate_flow, resolve_points
from ..models.base import GaussianStateSpaceModel
from ..models.structure import Structure
from ..proposals.flow import FLOWS, resolve_flow
from ..schedules import LambdaSchedule, resolve_schedule
from ..errors import ArgumentError, ArgumentTypeError

__all__ = ["FlowParticleUpdater", "StoneSoupMeasurement", "SUPPORTED_MEASUREMENT_MODELS"]

#: measurement models rewritten in torch (others: vectorised ``function`` + finite differences)
SUPPORTED_MEASUREMENT_MODELS = (_SSLinearGaussian, CartesianToBearingRange, CartesianToElevationBearingRange)
_WARNED = set()


def _wrap(a: torch.Tensor) -> torch.Tensor:
    """Angles to [-pi, pi)."""
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


class StoneSoupMeasurement(GaussianStateSpaceModel):
    """A Stone Soup measurement model (and the detection it is evaluated against) as the torchflow
    measurement term the flows linearise. Angle components of ``h`` are returned within pi of the
    detection's, so every residual ``z - h(x)`` is the wrapped one.

    Args:
        model: a Stone Soup ``MeasurementModel`` (``ndim_state``, ``ndim_meas``, ``covar()``).
        z: the detection's ``(m,)`` state vector.
        dtype, device: of the torch tensors.
    """

    structure = Structure(measurement_noise="dense")

    def __init__(self, model: MeasurementModel, z: np.ndarray, dtype=torch.float64, device=None):
        super().__init__()
        if not isinstance(model, MeasurementModel):
            raise ArgumentTypeError(f"measurement_model: expected a Stone Soup MeasurementModel, got {type(model).__name__}")
        self.ss = model
        self.state_dim, self.obs_dim = int(model.ndim_state), int(model.ndim_meas)
        kw = dict(dtype=dtype, device=device)
        try:
            R = np.asarray(model.covar(), dtype=float)
        except TypeError as err:
            raise ArgumentTypeError(f"measurement_model: {type(model).__name__}.covar() needs arguments ({err}); supported: "
                            "models with a constant noise covariance") from None
        self.register_buffer("R", torch.as_tensor(R, **kw))
        self.register_buffer("z", torch.as_tensor(np.asarray(z, dtype=float).ravel(), **kw))
        typed = model._typed_vector().ravel() if hasattr(model, "_typed_vector") else ()
        self.angle_rows = tuple(i for i, v in enumerate(typed) if isinstance(v, Angle))
        self.kind = "generic"
        if isinstance(model, _SSLinearGaussian):
            self.kind = "linear"
            self.structure = self.structure.replace(linear_measurement=True)
            self.register_buffer("H", torch.as_tensor(np.asarray(model.matrix(), dtype=float), **kw))
        elif isinstance(model, (CartesianToBearingRange, CartesianToElevationBearingRange)):
            self.kind = "polar" if isinstance(model, CartesianToBearingRange) else "spherical"
            self.mapping = tuple(int(i) for i in model.mapping)
            off = np.asarray(model.translation_offset, dtype=float).ravel()
            self.register_buffer("offset", torch.as_tensor(off, **kw))
            self.register_buffer("rot", torch.as_tensor(np.asarray(model.rotation_matrix, dtype=float), **kw))

    def measurement_cov(self, x=None):
        return self.R

    def measurement_matrix(self):
        return self.H

    def measure(self, x: torch.Tensor) -> torch.Tensor:
        if self.kind == "linear":
            h = x @ self.H.transpose(-1, -2)
        elif self.kind in ("polar", "spherical"):
            h = self._polar(x)
        else:
            h = self._generic(x)
        if self.angle_rows:  # within pi of the detection: the residual z - h is the wrapped one
            rows = list(self.angle_rows)
            h = h.clone()
            h[..., rows] = self.z[rows] + _wrap(h[..., rows] - self.z[rows])
        return h

    def _polar(self, x):
        idx = list(self.mapping)
        xyz = x[..., idx] - self.offset[: len(idx)]
        if self.kind == "polar":  # Stone Soup rotates (x, y, 0)
            xyz = torch.cat([xyz, torch.zeros_like(xyz[..., :1])], -1)
        u = xyz @ self.rot.transpose(-1, -2)
        if self.kind == "polar":
            return torch.stack([torch.atan2(u[..., 1], u[..., 0]), torch.sqrt(u[..., 0] ** 2 + u[..., 1] ** 2)], -1)
        rho = torch.sqrt((u * u).sum(-1))
        return torch.stack([torch.asin(u[..., 2] / rho), torch.atan2(u[..., 1], u[..., 0]), rho], -1)

    def _generic(self, x):
        """The model's own vectorised ``function`` (numpy, noise-free) on every point at once."""
        flat = x.detach().reshape(-1, self.state_dim).cpu().numpy()
        out = np.asarray(self.ss.function(State(StateVectors(flat.T)), noise=False), dtype=float)
        return torch.as_tensor(out.T, dtype=x.dtype, device=x.device).reshape(*x.shape[:-1], self.obs_dim)

    def measurement_jacobian(self, x: torch.Tensor) -> torch.Tensor:
        if self.kind == "polar":  # analytic: u = Rot (p - offset, 0), bearing atan2(u1, u0), range |u|
            idx = list(self.mapping)
            xyz = torch.cat([x[..., idx] - self.offset[:2], torch.zeros_like(x[..., :1])], -1)
            u = xyz @ self.rot.transpose(-1, -2)
            r2 = u[..., 0] ** 2 + u[..., 1] ** 2
            r = torch.sqrt(r2)
            R0, R1 = self.rot[0, :2], self.rot[1, :2]  # d u0 / d(px, py), d u1 / d(px, py)
            dphi = (u[..., 0:1] * R1 - u[..., 1:2] * R0) / r2.unsqueeze(-1)
            drho = (u[..., 0:1] * R0 + u[..., 1:2] * R1) / r.unsqueeze(-1)
            J = x.new_zeros(*x.shape[:-1], 2, self.state_dim)
            J[..., 0, idx] = dphi
            J[..., 1, idx] = drho
            return J
        if self.kind != "generic":
            return super().measurement_jacobian(x)
        # central differences, all points and directions in one call of the model's function
        d = self.state_dim
        step = (torch.finfo(x.dtype).eps ** (1 / 3)) * x.abs().clamp_min(1.0)  # (..., d)
        E = torch.eye(d, dtype=x.dtype, device=x.device)
        pts = torch.cat([x.unsqueeze(-2) + step.unsqueeze(-2) * E, x.unsqueeze(-2) - step.unsqueeze(-2) * E], -2)
        h = self.measure(pts)  # (..., 2d, m), angles wrapped around z
        diff = h[..., :d, :] - h[..., d:, :]
        if self.angle_rows:
            rows = list(self.angle_rows)
            diff[..., rows] = _wrap(diff[..., rows])
        return (diff / (2 * step.unsqueeze(-1))).transpose(-1, -2)

    def measurement_jacobian_support(self, x):
        return self.measurement_jacobian(x)


class FlowParticleUpdater(Updater):
    """A Stone Soup ``Updater`` that moves the particles with a torchflow particle flow (see the
    module docstring for the weights, the flow prior and the supported models)."""

    flow: str = Property(default="ledh", doc=f"the flow: one of {sorted(FLOWS)} or a torchflow ParticleFlow")
    points: str = Property(default=None, doc="linearisation points ('global', 'particle'); default: the flow's own")
    schedule: LambdaSchedule = Property(default=None, doc="pseudo-time schedule (default: 29 exponential steps, "
                                                          "ratio 1.2) or a name ('exponential', 'uniform')")
    resampler: Resampler = Property(default=None, doc="Stone Soup resampler applied after the update (optional)")
    dtype: str = Property(default="float64", doc="'float64' (default) or 'float32'")
    device: str = Property(default="cpu", doc="torch device of the flow ('cpu', 'cuda')")
    seed: int = Property(default=0, doc="seed of the stochastic flows' diffusion noise (a torch.Generator)")
    flow_prior: str = Property(default="transition", doc="the flow's prior with PF-PF weights: 'transition' "
                                                          "(default: each particle's own N(F x_prev, Q)) or 'predicted' "
                                                          "(N(F x_prev, F P_prev F^T + Q), Li & Coates' EKF-style prior)")

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._flow = resolve_flow(self.flow)
        self._schedule = resolve_schedule(self.schedule)
        if self.flow_prior not in ("transition", "predicted"):
            raise ArgumentError(f"flow_prior: expected 'transition' or 'predicted', got {self.flow_prior!r}")
        if self.dtype not in ("float64", "float32"):
            raise ArgumentError(f"dtype: expected 'float64' or 'float32', got {self.dtype!r}")
        self._dtype = getattr(torch, self.dtype)
        try:
            self._generator = torch.Generator(device=self.device).manual_seed(int(self.seed))
        except RuntimeError as err:
            raise ArgumentError(f"device: expected a torch device such as 'cpu' or 'cuda', got {self.device!r} "
                             f"({str(err).splitlines()[0][:80]})") from None

    predict_measurement = ParticleUpdater.predict_measurement

    def _measurement_model(self, hypothesis):
        mm = hypothesis.measurement.measurement_model or self.measurement_model
        if mm is None:
            raise ArgumentError("FlowParticleUpdater: no measurement model: give measurement_model= or detections that "
                             "carry one")
        return mm

    @staticmethod
    def _transition(pred):
        """``(F, Q, parent)`` of a linear-Gaussian prediction with its parent, else ``None``."""
        parent, tm = getattr(pred, "parent", None), getattr(pred, "transition_model", None)
        if parent is None or tm is None or not (isinstance(tm, LinearModel) and isinstance(tm, GaussianModel)):
            return None
        try:
            dt = pred.timestamp - parent.timestamp
        except TypeError:
            dt = None
        return np.asarray(tm.matrix(time_interval=dt), float), np.asarray(tm.covar(time_interval=dt), float), parent

    def update(self, hypothesis, **kwargs):
        """The particles of ``hypothesis.prediction`` moved by the flow towards
        ``hypothesis.measurement``; a ``ParticleStateUpdate`` (resampled if a resampler is set)."""
        pred = hypothesis.prediction
        if not hasattr(pred, "log_weight") or np.ndim(pred.state_vector) != 2:
            raise ArgumentTypeError(f"FlowParticleUpdater: expected a particle prediction (ParticleStatePrediction), got "
                            f"{type(pred).__name__}")
        mm = self._measurement_model(hypothesis)
        kw = dict(dtype=self._dtype, device=self.device)
        zv = np.asarray(hypothesis.measurement.state_vector, dtype=float).ravel()
        if zv.size != int(mm.ndim_meas):
            raise ArgumentError(f"FlowParticleUpdater: the detection has {zv.size} values, {type(mm).__name__} measures "
                             f"ndim_meas = {int(mm.ndim_meas)}")
        model = StoneSoupMeasurement(mm, zv, **kw)
        X = torch.as_tensor(np.asarray(pred.state_vector, dtype=float).T, **kw).unsqueeze(0)  # (1, N, d)
        lw_prev = np.asarray(pred.log_weight, dtype=float)
        N, d = X.shape[1], X.shape[2]
        if model.state_dim != d:
            raise ArgumentError(f"FlowParticleUpdater: the measurement model has ndim_state {model.state_dim}, the "
                             f"particles {d} dimensions")
        trans = self._transition(pred)
        w = torch.as_tensor(np.exp(lw_prev - logsumexp(lw_prev)), **kw)
        if trans is not None:
            F, Q, parent = torch.as_tensor(trans[0], **kw), torch.as_tensor(trans[1], **kw), trans[2]
            Xp = torch.as_tensor(np.asarray(parent.state_vector, dtype=float).T, **kw)  # (N, d)
            lwp = np.asarray(parent.log_weight, dtype=float)
            wp = torch.as_tensor(np.exp(lwp - logsumexp(lwp)), **kw)
            mean_p = wp @ Xp
            Pp = ((Xp - mean_p).T * wp) @ (Xp - mean_p)
            P = F @ Pp @ F.T + Q if self.flow_prior == "predicted" else Q
            m_pred = (Xp @ F.T).unsqueeze(0)  # (1, N, d): each particle's noise-free prediction
            LQ = linalg.safe_cholesky(Q)
        else:
            if "unweighted" not in _WARNED:
                _WARNED.add("unweighted")
                warnings.warn("FlowParticleUpdater: the prediction carries no parent particles with a linear-Gaussian "
                              "transition model, so the update is the unweighted flow filter (particles keep their "
                              "weights); predict with Stone Soup's ParticlePredictor and a linear-Gaussian transition "
                              "for PF-PF weights", UserWarning, stacklevel=2)
            mean = w @ X[0]
            P = ((X[0] - mean).T * w) @ (X[0] - mean)
            m_pred = X
        L = linalg.safe_cholesky(linalg.symmetrize(P) + 1e-12 * P.diagonal().abs().max().clamp_min(1.0)
                                 * torch.eye(d, **kw))
        pts = resolve_points(self._flow, self.points)
        if pts.per_particle:
            prior = FlowPrior(m_pred, L.expand(1, N, d, d))
        else:
            prior = FlowPrior((w @ m_pred[0]).unsqueeze(0), L.unsqueeze(0))
        z = model.z.unsqueeze(0)
        proposal = FlowPrior(m_pred, LQ.expand(1, N, d, d)) if (trans is not None and self._flow.stochastic) else None
        with torch.no_grad():
            out = integrate_flow(self._flow, model, X, z, prior, self._schedule, points=pts,
                                 generator=self._generator if self._flow.stochastic else None, proposal=proposal)
            x1 = out.particles
            if trans is not None:
                log_q = (out.log_proposal if self._flow.stochastic
                         else linalg.mvn_log_prob(X, m_pred, LQ) - out.log_det)
                log_w = (torch.as_tensor(lw_prev, **kw) + linalg.mvn_log_prob(x1, m_pred, LQ)
                         + model.measurement_log_prob(z.unsqueeze(1), x1) - log_q)[0]
                log_w = log_w.double().cpu().numpy()
            else:
                log_w = lw_prev.copy()
        if not np.isfinite(log_w).any():
            raise FloatingPointError(f"FlowParticleUpdater: every particle's weight is invalid after the {type(self._flow).__name__} "
                                     f"update at {hypothesis.measurement.timestamp}")
        log_w = np.where(np.isfinite(log_w), log_w, -np.inf)
        log_w = log_w - logsumexp(log_w)
        update = Update.from_state(pred, state_vector=StateVectors(x1[0].double().cpu().numpy().T), log_weight=log_w,
                                   hypothesis=hypothesis, timestamp=hypothesis.measurement.timestamp,
                                   target_type=ParticleStateUpdate)
        if self.resampler is not None:
            update = self.resampler.resample(update)
        return update
