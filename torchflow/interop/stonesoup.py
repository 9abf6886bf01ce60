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
``ParticleUpdater`` where ``"predicted"`` falls to a third of it (``experiments/stonesoup_example.py``): a prior
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

**Missed detections, timestamps, bad input** (docs/guide/stonesoup.md): a missed detection returns
the prediction carried forward (particles and weights unchanged, as a ``ParticleStateUpdate`` with
the hypothesis, not resampled). The posterior carries the prediction's timestamp; a detection at
another time is refused (predict to its time first), one without a timestamp is taken at the
prediction's. Bad input (no particles, non-finite particles or detection, NaN/+inf or all -inf
log-weights, a parent of another size, a prediction before its parent, a noise covariance that is
not symmetric positive definite) raises :class:`~torchflow.core.errors.ArgumentError` naming it, before
the flow runs; a non-finite result of the flow raises :class:`~torchflow.core.errors.NonFiniteError`.
Whatever ``update`` returns is finite.
"""

from __future__ import annotations

import datetime
import math
import warnings

import numpy as np
import torch
from scipy.special import logsumexp
from stonesoup.base import Property
from stonesoup.models.base import GaussianModel, LinearModel
from stonesoup.models.measurement.base import MeasurementModel
from stonesoup.models.measurement.linear import LinearGaussian as _SSLinearGaussian
from stonesoup.models.measurement.nonlinear import CartesianToBearingRange, CartesianToElevationBearingRange
from stonesoup.resampler import Resampler
from stonesoup.types.angle import Angle
from stonesoup.types.array import StateVectors
from stonesoup.types.state import State
from stonesoup.types.update import ParticleStateUpdate, Update
from stonesoup.updater.base import Updater
from stonesoup.updater.particle import ParticleUpdater

from torchflow.core import linalg
from torchflow.core.checks import check_choice
from torchflow.core.errors import ArgumentError, ArgumentTypeError, NonFiniteError
from torchflow.filters import marginal as _marginal
from torchflow.flows import FlowPrior, integrate_flow, resolve_points
from torchflow.flows.schedules import LambdaSchedule, resolve_schedule
from torchflow.models.base import GaussianStateSpaceModel
from torchflow.models.structure import Structure
from torchflow.proposals.flow import FLOWS, affine_law, resolve_flow

__all__ = ["FlowParticleUpdater", "StoneSoupMeasurement", "SUPPORTED_MEASUREMENT_MODELS"]

#: measurement models rewritten in torch (others: vectorised ``function`` + finite differences)
SUPPORTED_MEASUREMENT_MODELS = (_SSLinearGaussian, CartesianToBearingRange, CartesianToElevationBearingRange)
_WARNED = set()


def _wrap(a: torch.Tensor) -> torch.Tensor:
    """Angles to [-pi, pi)."""
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


def _shown(idx) -> str:
    """Up to ten indices, ``[3, 7]`` or ``[0, 1, ..., 9] (and 5 more)``."""
    idx = [int(i) for i in idx]
    return f"{idx[:10]}" + (f" (and {len(idx) - 10} more)" if len(idx) > 10 else "")


def _noise_covariance(model, name: str) -> np.ndarray:
    """The ``(m, m)`` noise covariance of a Stone Soup measurement model, refused unless it is
    finite, symmetric and positive definite (the flows and the likelihood need ``R^-1``)."""
    if not isinstance(model, MeasurementModel):
        raise ArgumentTypeError(f"{name}: expected a Stone Soup MeasurementModel, got {type(model).__name__}")
    try:
        R = np.asarray(model.covar(), dtype=float)
    except TypeError as err:
        raise ArgumentTypeError(
            f"{name}: {type(model).__name__}.covar() needs arguments ({err}); supported: "
            "models with a constant noise covariance"
        ) from None
    what = f"{name}.noise_covar" if hasattr(model, "noise_covar") else f"{name}.covar()"
    m = int(model.ndim_meas)
    if R.shape != (m, m):
        raise ArgumentError(f"{what}: expected a {m} x {m} matrix (ndim_meas = {m}), got shape {R.shape}")
    if not np.isfinite(R).all():
        raise ArgumentError(
            f"{what}: expected a finite symmetric positive definite matrix, got "
            f"{int((~np.isfinite(R)).sum())} NaN or infinite entries"
        )
    asym = float(np.abs(R - R.T).max())
    if asym > 1e-9 * max(float(np.abs(R).max()), np.finfo(float).tiny):
        raise ArgumentError(
            f"{what}: expected a symmetric positive definite matrix, got an asymmetric one "
            f"(largest |R - R^T| = {asym:.3g})"
        )
    low = float(np.linalg.eigvalsh(R).min())
    if not low > 0:
        raise ArgumentError(f"{what}: expected a symmetric positive definite matrix, got smallest eigenvalue {low:.3g}")
    return R


def _particles(state, name: str, n=None):
    """``(X (d, N), log_weight (N,))`` of a Stone Soup particle state, refused unless there is at
    least one particle (``n`` of them where given), every particle is finite and the log-weights are
    real or -inf (a zero weight) with at least one not -inf. Weights need not sum to one."""
    X = np.asarray(state.state_vector, dtype=float)
    N = X.shape[1]
    if N == 0:
        raise ArgumentError(f"{name}.state_vector: expected at least one particle, got none (shape {X.shape})")
    if n is not None and N != n:
        raise ArgumentError(
            f"{name}.state_vector: expected {n} particles (one per particle of the prediction), got {N}"
        )
    bad = np.flatnonzero(~np.isfinite(X).all(0))
    if bad.size:
        raise ArgumentError(
            f"{name}.state_vector: expected finite particles, got {bad.size} of {N} with NaN or "
            f"infinite entries (particles {_shown(bad)})"
        )
    lw = getattr(state, "log_weight", None)
    if lw is None:
        raise ArgumentError(f"{name}.log_weight: expected {N} log-weights, got None")
    lw = np.asarray(lw, dtype=float)
    if lw.shape != (N,):
        raise ArgumentError(f"{name}.log_weight: expected {N} log-weights (one per particle), got shape {lw.shape}")
    for count, kind in ((np.isnan(lw).sum(), "NaN"), (np.isposinf(lw).sum(), "+inf")):
        if count:
            raise ArgumentError(
                f"{name}.log_weight: expected real log-weights (-inf for a zero weight), got {count} {kind} of {N}"
            )
    if np.isneginf(lw).all():
        raise ArgumentError(
            f"{name}.log_weight: expected at least one positive weight, got all {N} weights zero "
            "(every log-weight -inf)"
        )
    return X, lw


class StoneSoupMeasurement(GaussianStateSpaceModel):
    """A Stone Soup measurement model (and the detection it is evaluated against) as the torchflow
    measurement term the flows linearise. Angle components of ``h`` are returned within pi of the
    detection's, so every residual ``z - h(x)`` is the wrapped one.

    Args:
        model: a Stone Soup ``MeasurementModel`` (``ndim_state``, ``ndim_meas``, ``covar()``, a
            symmetric positive definite noise covariance).
        z: the detection's ``(m,)`` state vector.
        dtype, device: of the torch tensors.
        name: the model's name in error messages.
    """

    structure = Structure(measurement_noise="dense")

    def __init__(
        self, model: MeasurementModel, z: np.ndarray, dtype=torch.float64, device=None, name: str = "measurement_model"
    ):
        super().__init__()
        R = _noise_covariance(model, name)
        self.ss = model
        self.state_dim, self.obs_dim = int(model.ndim_state), int(model.ndim_meas)
        kw = dict(dtype=dtype, device=device)
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
            if any(not 0 <= i < self.state_dim for i in self.mapping):
                raise ArgumentError(
                    f"{name}.mapping: expected state indices in [0, {self.state_dim}) (ndim_state = "
                    f"{self.state_dim}), got {self.mapping}"
                )
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
    schedule: LambdaSchedule = Property(
        default=None,
        doc="pseudo-time schedule (default: 29 exponential steps, ratio 1.2) or a name ('exponential', 'uniform')",
    )
    resampler: Resampler = Property(default=None, doc="Stone Soup resampler applied after the update (optional)")
    dtype: str = Property(default="float64", doc="'float64' (default) or 'float32'")
    device: str = Property(default="cpu", doc="torch device of the flow ('cpu', 'cuda')")
    seed: int = Property(default=0, doc="seed of the stochastic flows' diffusion noise (a torch.Generator)")
    flow_prior: str = Property(
        default="transition",
        doc="the flow's prior with PF-PF weights: 'transition' "
        "(default: each particle's own N(F x_prev, Q)) or 'predicted' "
        "(N(F x_prev, F P_prev F^T + Q), Li & Coates' EKF-style prior)",
    )
    weights: str = Property(
        default="standard",
        doc="PF-PF weights: 'standard' (each particle against its own "
        "parent) or 'marginal' (against the mixture over all parents, "
        "O(N^2): torchflow.filters.marginal)",
    )

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        if self.measurement_model is not None:  # None: every detection carries its own
            _noise_covariance(self.measurement_model, "measurement_model")
        self._flow = resolve_flow(self.flow)
        self._schedule = resolve_schedule(self.schedule)
        if self.flow_prior not in ("transition", "predicted"):
            raise ArgumentError(f"flow_prior: expected 'transition' or 'predicted', got {self.flow_prior!r}")
        check_choice("weights", self.weights, _marginal.WEIGHTS)
        if self.dtype not in ("float64", "float32"):
            raise ArgumentError(f"dtype: expected 'float64' or 'float32', got {self.dtype!r}")
        self._dtype = getattr(torch, self.dtype)
        if self.resampler is not None and (
            isinstance(self.resampler, type) or not callable(getattr(self.resampler, "resample", None))
        ):
            got = f"the class {self.resampler.__name__}" if isinstance(self.resampler, type) else repr(self.resampler)
            raise ArgumentTypeError(
                f"resampler: expected a Stone Soup Resampler instance (e.g. SystematicResampler()), got {got}"
            )
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)):
            raise ArgumentTypeError(f"seed: expected an integer, got {self.seed!r}")
        try:
            self._generator = torch.Generator(device=self.device).manual_seed(int(self.seed))
        except RuntimeError as err:
            raise ArgumentError(
                f"device: expected a torch device such as 'cpu' or 'cuda', got {self.device!r} "
                f"({str(err).splitlines()[0][:80]})"
            ) from None

    predict_measurement = ParticleUpdater.predict_measurement

    def _measurement_model(self, hypothesis):
        """``(model, name)``: the detection's model if it carries one (Stone Soup's rule), else the updater's."""
        if hypothesis.measurement.measurement_model is not None:
            model = hypothesis.measurement.measurement_model
            if not isinstance(model, MeasurementModel):
                raise ArgumentTypeError(
                    f"detection.measurement_model: expected a Stone Soup MeasurementModel, got "
                    f"{type(model).__name__} (a transition model?)"
                )
            return model, "detection.measurement_model"
        if self.measurement_model is None:
            raise ArgumentError(
                "FlowParticleUpdater: no measurement model: give measurement_model= or detections that carry one"
            )
        return self.measurement_model, "measurement_model"

    @staticmethod
    def _timestamp(pred, det):
        """The posterior's timestamp: the prediction's (as Stone Soup's ``ParticleUpdater``), or the
        detection's where the prediction has none. A detection at another time is refused."""
        tp, td = pred.timestamp, getattr(det, "timestamp", None)  # det None: a missed detection
        if tp is None or td is None or td == tp:
            return td if tp is None else tp
        parent = getattr(pred, "parent", None)
        tq = getattr(parent, "timestamp", None)
        before = f", before the prediction's parent at {tq}" if tq is not None and td < tq else ""
        raise ArgumentError(
            f"detection.timestamp: expected the prediction's timestamp {tp}, got {td} "
            f"({'after' if td > tp else 'before'} it by {abs(td - tp)}{before}); predict to the "
            "detection's time first: predictor.predict(prior, timestamp=detection.timestamp)"
        )

    @staticmethod
    def _transition(pred, N):
        """``(F, Q, X_parent, log_weight_parent)`` of a linear-Gaussian prediction with its parent,
        else ``None``; a parent that does not fit the prediction is refused."""
        parent, tm = getattr(pred, "parent", None), getattr(pred, "transition_model", None)
        if parent is None or tm is None or not (isinstance(tm, LinearModel) and isinstance(tm, GaussianModel)):
            return None
        Xp, lwp = _particles(parent, "prediction.parent", n=N)
        dt = None
        if pred.timestamp is not None and parent.timestamp is not None:
            dt = pred.timestamp - parent.timestamp
            if dt < datetime.timedelta(0):
                raise ArgumentError(
                    f"prediction.timestamp: expected a time at or after its parent's {parent.timestamp}, "
                    f"got {pred.timestamp} (a negative interval: detections out of order? the "
                    "transition model cannot predict backwards)"
                )
        try:
            F, Q = np.asarray(tm.matrix(time_interval=dt), float), np.asarray(tm.covar(time_interval=dt), float)
        except (AttributeError, TypeError) as err:
            raise ArgumentError(
                f"prediction.timestamp: {type(tm).__name__} needs the interval between the prediction "
                f"and its parent, got timestamps {pred.timestamp} and {parent.timestamp} ({err})"
            ) from None
        scale = max(float(np.abs(Q).max(initial=0.0)), np.finfo(float).tiny)
        if not (np.isfinite(F).all() and np.isfinite(Q).all()) or np.linalg.eigvalsh(Q).min() < -1e-9 * scale:
            raise ArgumentError(
                f"prediction.transition_model: expected a finite matrix and a positive semi-definite "
                f"covariance over the interval {dt}, got covar() with smallest eigenvalue "
                f"{np.linalg.eigvalsh(np.nan_to_num(Q)).min():.3g}"
            )
        return F, Q, Xp, lwp

    @staticmethod
    def _singular_hint(model, X):
        """Where a bearing-range model's singular point (the sensor: range 0) is near the particles or
        the detection, a sentence that says so (else empty)."""
        if model.kind not in ("polar", "spherical"):
            return ""
        idx, r = list(model.mapping), model.obs_dim - 1
        off = model.offset[: len(idx)]
        sd = float(model.R[r, r].sqrt())
        near = int((torch.linalg.vector_norm(X[..., idx] - off, dim=-1) <= sd).sum())
        if not near and float(model.z[r]) > sd:
            return ""
        return (
            f"; {type(model.ss).__name__} is singular at its sensor position {off.tolist()} (range 0: bearing and "
            f"Jacobian undefined): the detection's range is {float(model.z[r]):.3g} and {near} of {X.shape[-2]} "
            f"particles lie within one range-noise standard deviation ({sd:.3g}) of it"
        )

    def _marginal_log_weights(self, out, X, x1, m_pred, LQ, wp, model, z):
        """Marginal weights (:mod:`torchflow.filters.marginal`): ``p(z | x_i)`` times the mixture of the
        parents' transitions (their weights ``wp``) over the mixture of the flow's laws given each
        parent (uniform: slot i propagates parent i); ``(N,)`` numpy."""
        N = x1.shape[1]
        if self._flow.stochastic:
            law = (out.proposal_mean, linalg.safe_cholesky(out.proposal_cov))
        else:  # the parent's affine map pushes N(F x_prev, Q) to N(x1 - M (eta_0 - F x_prev), M Q M^T)
            law = affine_law(x1, X, m_pred, out.map_jacobian, LQ)
        rows = _marginal.pair_rows(1, N, N, x1.shape[-1], x1.element_size())
        (log_rho,) = _marginal.mixture_logsumexp(
            _marginal.gaussian_pairs(x1, m_pred, LQ), [wp.log().unsqueeze(0)], N, rows
        )
        (log_qbar,) = _marginal.mixture_logsumexp(
            _marginal.gaussian_pairs(x1, *law), [torch.full_like(log_rho, -math.log(N))], N, rows
        )
        log_w = model.measurement_log_prob(z.unsqueeze(1), x1) + log_rho - log_qbar
        return log_w[0].double().cpu().numpy()

    def update(self, hypothesis, **kwargs):
        """The particles of ``hypothesis.prediction`` moved by the flow towards
        ``hypothesis.measurement``; a ``ParticleStateUpdate`` (resampled if a resampler is set).

        A missed detection (``MissedDetection``, a hypothesis that is false) returns the prediction
        carried forward: its particles and weights as a ``ParticleStateUpdate`` with the hypothesis,
        neither flowed nor resampled. Bad input (a detection at another time than the prediction,
        non-finite values, no particles, invalid weights, a noise covariance that is not positive
        definite) raises an ``ArgumentError`` that names it; a non-finite result of the flow raises
        a ``NonFiniteError``. Whatever is returned is finite."""
        if not (hasattr(hypothesis, "prediction") and hasattr(hypothesis, "measurement")):
            raise ArgumentTypeError(
                f"hypothesis: expected a Stone Soup SingleHypothesis (a prediction and a detection), "
                f"got {type(hypothesis).__name__}"
            )
        pred = hypothesis.prediction
        if not hasattr(pred, "log_weight") or np.ndim(pred.state_vector) != 2:
            raise ArgumentTypeError(
                f"FlowParticleUpdater: expected a particle prediction (ParticleStatePrediction), got "
                f"{type(pred).__name__}"
            )
        Xn, lw_prev = _particles(pred, "prediction")
        timestamp = self._timestamp(pred, hypothesis.measurement)
        if not hypothesis:  # a missed detection: the prediction carried forward
            return Update.from_state(pred, hypothesis=hypothesis, timestamp=timestamp, target_type=ParticleStateUpdate)
        mm, mm_name = self._measurement_model(hypothesis)
        kw = dict(dtype=self._dtype, device=self.device)
        if hypothesis.measurement.state_vector is None:
            raise ArgumentError(f"detection.state_vector: expected {int(mm.ndim_meas)} values, got None")
        zv = np.asarray(hypothesis.measurement.state_vector, dtype=float).ravel()
        if zv.size != int(mm.ndim_meas):
            raise ArgumentError(
                f"FlowParticleUpdater: the detection has {zv.size} values, {type(mm).__name__} measures "
                f"ndim_meas = {int(mm.ndim_meas)}"
            )
        if not np.isfinite(zv).all():
            raise ArgumentError(
                f"detection.state_vector: expected finite values, got {zv.tolist()} (NaN or infinite "
                f"at entries {_shown(np.flatnonzero(~np.isfinite(zv)))})"
            )
        model = StoneSoupMeasurement(mm, zv, name=mm_name, **kw)
        X = torch.as_tensor(Xn.T, **kw).unsqueeze(0)  # (1, N, d)
        N, d = X.shape[1], X.shape[2]
        if model.state_dim != d:
            raise ArgumentError(
                f"FlowParticleUpdater: the measurement model has ndim_state {model.state_dim}, the "
                f"particles {d} dimensions"
            )
        trans = self._transition(pred, N)
        w = torch.as_tensor(np.exp(lw_prev - logsumexp(lw_prev)), **kw)
        if trans is not None:
            F, Q = torch.as_tensor(trans[0], **kw), torch.as_tensor(trans[1], **kw)
            Xp = torch.as_tensor(trans[2].T, **kw)  # (N, d)
            wp = torch.as_tensor(np.exp(trans[3] - logsumexp(trans[3])), **kw)
            mean_p = wp @ Xp
            Pp = ((Xp - mean_p).T * wp) @ (Xp - mean_p)
            P = F @ Pp @ F.T + Q if self.flow_prior == "predicted" else Q
            m_pred = (Xp @ F.T).unsqueeze(0)  # (1, N, d): each particle's noise-free prediction
            LQ = linalg.safe_cholesky(Q)
        else:
            if self.weights == "marginal":
                raise ArgumentError(
                    "weights: 'marginal' needs the prediction's parent particles and a linear-Gaussian "
                    "transition model (predict with Stone Soup's ParticlePredictor); this prediction "
                    "has none, so only the unweighted flow update is possible (weights='standard')"
                )
            if "unweighted" not in _WARNED:
                _WARNED.add("unweighted")
                warnings.warn(
                    "FlowParticleUpdater: the prediction carries no parent particles with a linear-Gaussian "
                    "transition model, so the update is the unweighted flow filter (particles keep their "
                    "weights); predict with Stone Soup's ParticlePredictor and a linear-Gaussian transition "
                    "for PF-PF weights",
                    UserWarning,
                    stacklevel=2,
                )
            mean = w @ X[0]
            P = ((X[0] - mean).T * w) @ (X[0] - mean)
            m_pred = X
        L = linalg.safe_cholesky(
            linalg.symmetrize(P) + 1e-12 * P.diagonal().abs().max().clamp_min(1.0) * torch.eye(d, **kw)
        )
        pts = resolve_points(self._flow, self.points)
        if pts.per_particle:
            prior = FlowPrior(m_pred, L.expand(1, N, d, d))
        else:
            prior = FlowPrior((w @ m_pred[0]).unsqueeze(0), L.unsqueeze(0))
        z = model.z.unsqueeze(0)
        proposal = FlowPrior(m_pred, LQ.expand(1, N, d, d)) if (trans is not None and self._flow.stochastic) else None
        where = f"the {type(self._flow).__name__} update at {timestamp}"
        with torch.no_grad():
            try:
                marginal = trans is not None and self.weights == "marginal"
                out = integrate_flow(
                    self._flow,
                    model,
                    X,
                    z,
                    prior,
                    self._schedule,
                    points=pts,
                    generator=self._generator if self._flow.stochastic else None,
                    proposal=proposal,
                    map_jacobian=marginal and not self._flow.stochastic,
                )
            except torch.linalg.LinAlgError as err:
                raise NonFiniteError(
                    "FlowParticleUpdater",
                    0,
                    [],
                    what=f"values in {where} (torch linear algebra "
                    f"failed: {str(err).splitlines()[0][:120]}){self._singular_hint(model, X)}",
                ) from None
            x1 = out.particles
            bad = int((~torch.isfinite(x1).all(-1)).sum())
            if bad:
                raise NonFiniteError(
                    "FlowParticleUpdater",
                    0,
                    [],
                    what=f"particle states after {where} ({bad} of {N} particles){self._singular_hint(model, X)}",
                )
            if marginal:
                log_w = self._marginal_log_weights(out, X, x1, m_pred, LQ, wp, model, z)
            elif trans is not None:
                log_q = out.log_proposal if self._flow.stochastic else linalg.mvn_log_prob(X, m_pred, LQ) - out.log_det
                log_w = (
                    torch.as_tensor(lw_prev, **kw)
                    + linalg.mvn_log_prob(x1, m_pred, LQ)
                    + model.measurement_log_prob(z.unsqueeze(1), x1)
                    - log_q
                )[0]
                log_w = log_w.double().cpu().numpy()
            else:
                log_w = lw_prev.copy()
        bad = int((np.isnan(log_w) | np.isposinf(log_w)).sum())
        if bad or np.isneginf(log_w).all():
            raise NonFiniteError(
                "FlowParticleUpdater",
                0,
                [],
                what=f"log-weights after {where} "
                f"({bad or N} of {N} particles NaN, +inf or all -inf){self._singular_hint(model, X)}",
            )
        log_w = log_w - logsumexp(log_w)
        update = Update.from_state(
            pred,
            state_vector=StateVectors(x1[0].double().cpu().numpy().T),
            log_weight=log_w,
            hypothesis=hypothesis,
            timestamp=timestamp,
            target_type=ParticleStateUpdate,
        )
        if self.resampler is not None:
            update = self.resampler.resample(update)
        return update
