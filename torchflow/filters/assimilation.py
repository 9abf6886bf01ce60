"""Particle methods for data assimilation: deterministic dynamics, no transition density needed.

Both filters here move an ensemble of ``N`` members per trial, ``X (B, N, d)``, as the ensemble
Kalman filters do (:mod:`torchflow.filters.ensemble`): the forecast is the model's transition
sampler (a model without noise gives a deterministic forecast), and the analysis leaves equally
weighted members. Neither weighs by ``p(x_k | x_{k-1})``, which deterministic dynamics do not have.

* :class:`KernelParticleFlowFilter`, the particle flow filter with a matrix-valued kernel
  (Pulido & van Leeuwen 2019; Hu & van Leeuwen 2021). The analysis members follow, in pseudo-time
  ``s``, the flow of steepest descent of the Kullback-Leibler divergence to the posterior within a
  reproducing-kernel Hilbert space::

      dx_i/ds = D f(x_i),   f(x) = sum_j K(x_j, x) grad log p(x_j | z) + div_{x_j} K(x_j, x)

  The prior is the forecast ensemble's Gaussian ``N(xbar, P)`` with ``P`` its sample covariance,
  tapered by a Gaspari-Cohn correlation of the coordinates' distance (``radius``; on a ring of
  ``d`` sites by default, Lorenz-96); the likelihood is the model's own density (its gradient by
  automatic differentiation: nonlinear and non-Gaussian measurements alike). The kernel is
  diagonal, ``K = diag(k_a)`` with ``k_a(x, x') = exp(-(x_a - x'_a)^2 / (2 alpha P_aa))``: each
  coordinate's kernel reads that coordinate alone, which keeps the particles' mutual repulsion
  alive at large ``d`` (Hu & van Leeuwen 2021). ``f`` is divided, coordinate by coordinate, by the
  kernel's mass ``sum_j k_a(x_j, x)`` (a positive scaling: the flow's fixed points are unchanged, and
  a step of 1 is then a Newton step on a Gaussian posterior), and ``D`` is the linearised Gaussian
  posterior covariance ``P - P H^T (H P H^T + R)^{-1} H P`` (``preconditioner="posterior"``; ``H``
  the measurement Jacobian at the forecast mean) or ``P`` (``"prior"``, Hu & van Leeuwen's choice).
  ``flow_steps`` explicit Euler steps of ``step_size`` integrate it. In a linear-Gaussian model the
  flow's fixed point has nearly the Kalman mean of the forecast ensemble, and with ``alpha = 1 / N``
  nearly its covariance (measured in the tests: N = 64, mean within 0.02 posterior standard
  deviations, variances within 0.95-1.22 of Kalman's); a wider kernel (``alpha = 1``) shrinks the
  spread (0.38-0.83 of Kalman's variances), the mean-field limit. Cost per step
  ``O(flow_steps N^2 d + d^3)``: the dense ``d x d`` prior is the limit (d of a few thousand).

* :class:`LocalParticleFilter`, the local particle filter of Penny & Miyoshi (2016): every state
  coordinate ``i`` has its own weights, from the observations near it,
  ``log w_ni = sum_j rho(dist(i, j)) log p(z_j | x_n)`` (a Gaspari-Cohn taper ``rho`` vanishing at
  ``radius``), and is resampled by systematic resampling with one uniform per trial shared by all
  coordinates (neighbouring coordinates with similar weights then keep the same ancestors, so the
  analysis members stay nearly continuous in space). The estimate is each coordinate's weighted
  mean before resampling. Relaxation to the prior spread (``rtps``, Whitaker & Hamill 2012) and a
  Gaussian jitter scaled by each coordinate's forecast spread (``jitter``) keep the ensemble from
  collapsing. Cost ``O(N d K)`` per step (K: the observations within reach of a coordinate); memory
  ``O(N d)``. With ``radius = inf`` it is the bootstrap PF with resampling at every step.

**The flows** are :mod:`torchflow.flows.ensemble`'s (:class:`~torchflow.flows.KernelFlow`,
:class:`~torchflow.flows.LagOneFlow`, :class:`~torchflow.flows.LocalisedKalmanBucyFlow`), stepped by
:func:`~torchflow.flows.integrate_flow` (``points="ensemble"``); the filters here compose "flow,
then forecast" (or "forecast, then flow") around them and hold the flow as :attr:`flow`.

**Evidence.** Both report the forecast ensemble's Gaussian approximation of
``log p(z_k | z_{1:k-1})`` (as the ensemble Kalman filters do), so :attr:`estimates_evidence` is
``False``.

**Missing observations.** A NaN in ``z (B, m)`` is not observed: its likelihood term (and its row
of ``H`` in the preconditioner) is left out; a step with nothing observed is a pure forecast.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

import torch

from torchflow.core import linalg
from torchflow.core import missing as _missing
from torchflow.core.checks import check_count, check_number
from torchflow.core.errors import ArgumentError, ArgumentTypeError
from torchflow.core.geometry import (
    DIAGONAL_NOISE,
    check_distances,
    check_radius,
    declared_distances,
    gaspari_cohn,
    local_observations,
    periodic_distances,
)
from torchflow.filters.ensemble import _EnsembleFilter, local_transport, rotate_anomalies
from torchflow.flows.base import FlowPrior
from torchflow.flows.ensemble import (
    CACHE_ELEMENTS,
    EnsembleMeasurement,
    KernelFlow,
    LagOneFlow,
    LocalisedKalmanBucyFlow,
    ensemble_prior,
)
from torchflow.flows.integrate import integrate_flow
from torchflow.flows.schedules import ExponentialSchedule, UniformSchedule
from torchflow.models.base import GaussianStateSpaceModel

__all__ = ["KernelParticleFlowFilter", "LagOneFlowFilter", "LocalParticleFilter"]

PRECONDITIONERS = ("posterior", "prior")
#: how the lag-one flow linearises the measurement of the forecast
LINEARISATIONS = ("members", "bundle")
#: which covariance the lag-one flow's gain reads: the previous analysis's, or the flowed members'
FLOW_COVARIANCES = ("prior", "current")
#: the lag-one flow's likelihood in the members' covariance: R's Gaussian, or the model's own density's score
LIKELIHOODS = ("gaussian", "model")


def _grad_log_likelihood(model, z: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """``grad_x log p(z | x)`` at every member ``X (B, N, d)`` for ``z (B, m)`` (NaN: not observed),
    by automatic differentiation of the model's density (the members detached: the flow is not
    differentiated)."""
    with torch.enable_grad():
        x = X.detach().requires_grad_(True)
        ll = _missing.measurement_log_prob(model, z.unsqueeze(1), x).sum()
        (g,) = torch.autograd.grad(ll, x)
    return g


def _register_neighbours(f, distances: Optional[torch.Tensor]) -> None:
    """``f.local_index``, ``f.local_taper`` ``(d, K)``: the observations within ``f.radius`` of each
    coordinate and their Gaspari-Cohn tapers (:func:`~torchflow.core.geometry.local_observations`),
    on the model's dtype and device; both ``None`` when the radius is infinite (every observation
    everywhere)."""
    taper = index = None
    if distances is not None:  # checked even where an infinite radius leaves them unused
        check_distances("distances", distances, (f.model.state_dim, f.model.obs_dim))
    if not math.isinf(f.radius):
        model = f.model
        taper, index = local_observations(model, f.radius, distances)
        taper, index = taper.to(model.dtype).to(model.device), index.to(model.device)
    f.register_buffer("local_index", index, persistent=False)
    f.register_buffer("local_taper", taper, persistent=False)


class KernelParticleFlowFilter(_EnsembleFilter):
    """Particle flow filter with a matrix-valued kernel (module docstring; Pulido & van Leeuwen 2019,
    Hu & van Leeuwen 2021). Needs no transition density: it runs on deterministic dynamics.

    Args:
        model: a Gaussian-form model (``measure``, ``measurement_cov``, ``measurement_log_prob``,
            ``sample_transition``).
        n_particles: ensemble members N (>= 2; more than ``d`` when ``radius`` is ``inf``: the
            untapered sample covariance must be invertible).
        inflation: multiplicative inflation of the forecast anomalies (>= 1).
        radius: the distance at which the Gaspari-Cohn taper of the prior covariance vanishes
            (``inf``: no taper). Distances: ``state_distances`` or, by default, the model's declared
            geometry (Lorenz-96's ring, ``model.site_distances()``; a model declaring none is refused).
        state_distances: ``(d, d)`` distances between state coordinates (``None``: the model's).
        bandwidth: ``alpha``, the kernel's width relative to each coordinate's prior variance
            (``None``: ``1 / N``, Hu & van Leeuwen's choice, which gives nearly the Kalman spread in a
            linear-Gaussian model; wider kernels give a narrower analysis ensemble).
        step_size, flow_steps: the Euler step in pseudo-time and the number of steps.
        preconditioner: ``"posterior"`` (default: the linearised Gaussian posterior covariance) or
            ``"prior"`` (the tapered prior covariance).
        validate, name: as :class:`~torchflow.filters.Filter`.

    Shapes: ensemble ``(B, N, d)``, observations ``z (B, m)`` (NaN: not observed).
    """

    nonfinite_hint = (
        "the flow diverged: a smaller step_size with more flow_steps (preconditioner='prior' needs a step "
        "about 25 times smaller than 'posterior'), a smaller inflation, or, for a strongly nonlinear "
        "measurement, another filter (lag1_flow, lpf)"
    )

    def __init__(
        self,
        model,
        *,
        n_particles: int = 20,
        inflation: float = 1.0,
        radius: float = math.inf,
        state_distances: Optional[torch.Tensor] = None,
        bandwidth: Optional[float] = None,
        step_size: float = 0.5,
        flow_steps: int = 30,
        preconditioner: str = "posterior",
        validate: bool = True,
        name: Optional[str] = None,
    ):
        super().__init__(model, n_particles=n_particles, inflation=inflation, validate=validate, name=name)
        d = model.state_dim
        self.radius = check_radius(radius)
        if math.isinf(self.radius) and self.n_particles <= d:
            raise ArgumentError(
                f"n_particles: without a taper (radius = inf) the prior covariance of {self.n_particles} members in "
                f"d = {d} dimensions is singular; use more than {d} members or a finite radius"
            )
        #: ``alpha`` (``None``: ``1 / N``)
        self.bandwidth = (
            None
            if bandwidth is None
            else check_number(
                "bandwidth",
                bandwidth,
                lambda v: v > 0,
                "a number > 0 (the kernel width relative to the prior variance)",
            )
        )
        self.step_size = check_number("step_size", step_size, lambda v: v > 0, "a number > 0 (pseudo-time step)")
        self.flow_steps = check_count("flow_steps", flow_steps, minimum=1, hint=" (Euler steps in pseudo-time)")
        #: the flow (:class:`~torchflow.flows.KernelFlow`): ``flow_steps`` Euler steps of ``step_size``
        self.flow = KernelFlow(self.step_size * self.flow_steps)
        self.schedule = UniformSchedule(self.flow_steps)
        if preconditioner not in PRECONDITIONERS:
            raise ArgumentError(f"preconditioner: expected one of {PRECONDITIONERS}, got {preconditioner!r}")
        self.preconditioner = preconditioner
        taper = None
        given = None if state_distances is None else check_distances("state_distances", state_distances, (d, d))
        if not math.isinf(self.radius):
            if given is not None:
                dist = given
            elif model.structure.sites == "ring":
                dist = periodic_distances(d, torch.arange(d))
            else:
                dist = declared_distances(model, "state_distances")
            taper = gaspari_cohn(dist, self.radius).to(model.dtype).to(model.device)
        self.register_buffer("taper", taper, persistent=False)

    def bytes_per_trial(self, n_particles=None):
        N, d, m = self._resolve_n(n_particles), self.model.state_dim, self.model.obs_dim
        return 8 * (8 * N * d + 4 * N * N * d + 6 * d * d + 3 * m * d + 2 * m * m)

    def alpha(self, n_particles: int) -> float:
        """The kernel width relative to the prior variance for ``n_particles`` members."""
        return 1.0 / n_particles if self.bandwidth is None else self.bandwidth

    def step(self, state, z: torch.Tensor, generator: Optional[torch.Generator] = None):
        """Forecast, inflate, then move the members by the kernel flow towards ``p(x | z)``."""
        xbar, A = self.forecast(state, generator)
        Xf = xbar + A
        X = self.migrate(Xf, xbar, A, z)
        # a trial with nothing observed keeps its forecast (the prior-only flow would move it by its
        # finite-N spread correction; masked, no host read)
        X = torch.where((~torch.isnan(z)).any(-1).view(-1, 1, 1), X, Xf)
        return self._state(X, self.forecast_evidence(self.whiten(Xf, xbar.squeeze(1), z)), state.step + 1)

    def prior_covariance(self, A: torch.Tensor) -> torch.Tensor:
        """The tapered sample covariance ``(B, d, d)`` of the anomalies ``A (B, N, d)``."""
        P = A.transpose(1, 2) @ A / (A.shape[1] - 1)
        return P if self.taper is None else P * self.taper.to(P)  # the taper follows the model's dtype

    def migrate(self, Xf: torch.Tensor, xbar: torch.Tensor, A: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """The analysis members ``(B, N, d)`` from the forecast ``Xf (B, N, d)``, its mean
        ``xbar (B, 1, d)`` and (inflated) anomalies ``A (B, N, d)``: the kernel flow
        (:class:`~torchflow.flows.KernelFlow`) integrated by :func:`~torchflow.flows.integrate_flow`
        over ``flow_steps`` uniform steps."""
        model = self.model
        N = Xf.shape[1]
        P = self.prior_covariance(A)
        L = linalg.safe_cholesky(P)  # a Schur product with a positive definite taper: definite (jitter if not)
        D = self._posterior_covariance(P, xbar.squeeze(1), z) if self.preconditioner == "posterior" else P
        width = self.alpha(N) * P.diagonal(dim1=-2, dim2=-1)  # (B, d)
        self.flow.prepare(D, width, lambda X: _grad_log_likelihood(model, z, X))
        prior, meas = FlowPrior(xbar, L), EnsembleMeasurement(z, whiten=None)
        out = integrate_flow(self.flow, model, Xf, z, prior, self.schedule, points="ensemble", measurement=meas)
        return out.particles

    def _posterior_covariance(self, P: torch.Tensor, xbar: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """``P - P H^T (H P H^T + R)^{-1} H P`` ``(B, d, d)`` with H at the forecast mean (unobserved
        rows of H zero, their R rows and columns the identity's)."""
        model = self.model
        H = model.measurement_jacobian(xbar)  # (B, m, d)
        observed = ~torch.isnan(z)
        H = H * observed.unsqueeze(-1).to(H.dtype)
        R = self._measurement_cov(xbar)
        both = observed.unsqueeze(-1) & observed.unsqueeze(-2)
        eye = torch.eye(z.shape[-1], dtype=P.dtype, device=P.device)
        R = torch.where(both, R, eye)
        PHt = P @ H.transpose(1, 2)  # (B, d, m)
        S = H @ PHt + R
        D = P - PHt @ linalg.chol_solve(linalg.safe_cholesky(S), PHt.transpose(1, 2))
        return 0.5 * (D + D.transpose(1, 2))

    def extra_repr(self) -> str:
        bw = "1/N" if self.bandwidth is None else f"{self.bandwidth:g}"
        return (
            super().extra_repr() + f", radius={self.radius:g}, bandwidth={bw}, step_size={self.step_size:g}, "
            f"flow_steps={self.flow_steps}, preconditioner={self.preconditioner!r}"
        )


class LocalParticleFilter(_EnsembleFilter):
    """Local particle filter (Penny & Miyoshi 2016; module docstring): one set of weights per state
    coordinate from the observations near it, systematic resampling with one uniform per trial.

    Args:
        model: a model whose observations are independent given the state
            (:meth:`~torchflow.models.GaussianStateSpaceModel.measurement_log_prob_terms`: the
            Gaussian form with a diagonal R, or the model's own terms) and that says where each
            observation is (``observed`` on a ring, or ``distances``).
        n_particles: members N (>= 2).
        inflation: multiplicative inflation of the forecast anomalies (>= 1; 1: none).
        radius: the distance at which an observation's influence on a coordinate vanishes
            (Gaspari-Cohn taper of its log-likelihood; ``inf``: every observation everywhere, the
            global bootstrap PF).
        distances: ``(d, m)`` distances between state coordinates and observations (``None``: the
            ring of :class:`~torchflow.filters.LocalEnsembleTransformKalmanFilter`).
        rtps: relaxation to the prior spread, ``alpha`` in [0, 1] (0: none): each coordinate's
            analysis anomalies are scaled so that its spread is ``alpha sigma_f + (1 - alpha) sigma_a``.
        jitter: after resampling, Gaussian noise of standard deviation ``jitter`` times each
            coordinate's forecast spread (0: none; DAPPER's relative regularisation).
        validate, name: as :class:`~torchflow.filters.Filter`.

    Shapes: ensemble ``(B, N, d)``, observations ``z (B, m)`` (NaN: not observed).
    """

    collapse_remedy = (
        "jitter after resampling (jitter=..., relative to the forecast spread) or relaxation to the prior "
        "spread (rtps=...), or a filter that moves its members rather than resampling them (filter=lag1_flow, "
        "kpff, the ensemble Kalman filters)"
    )

    def __init__(
        self,
        model,
        *,
        n_particles: int = 40,
        inflation: float = 1.0,
        radius: float = 15.0,
        distances: Optional[torch.Tensor] = None,
        rtps: float = 0.0,
        jitter: float = 0.0,
        validate: bool = True,
        name: Optional[str] = None,
    ):
        super().__init__(model, n_particles=n_particles, inflation=inflation, validate=validate, name=name)
        self.radius = check_radius(radius)
        self.rtps = check_number("rtps", rtps, lambda v: 0 <= v <= 1, "a number in [0, 1] (relaxation to prior spread)")
        self.jitter = check_number(
            "jitter", jitter, lambda v: v >= 0, "a number >= 0 (jitter relative to the forecast spread)"
        )
        noise = model.structure.measurement_noise
        own_terms = type(model).measurement_log_prob_terms is not GaussianStateSpaceModel.measurement_log_prob_terms
        if noise not in DIAGONAL_NOISE and not own_terms:  # before any work, not at the first step
            who = type(model).__name__.removeprefix("Parametrized")  # a learnable model's class: torch's subclass
            raise ArgumentTypeError(
                f"{self.name}: model: the local particle filter weighs each observation on its own, which needs "
                f"observations independent given the state: a diagonal measurement noise (declared scalar, "
                f"diagonal or state_dependent_diagonal) or the model's own measurement_log_prob_terms; {who} "
                f"declares {noise!r} (a learned R is a dense matrix). Use kpff, lag1_flow or an ensemble Kalman filter"
            )
        _register_neighbours(self, distances)  # radius = inf: every observation weighs every coordinate

    def bytes_per_trial(self, n_particles=None):
        N, d, m = self._resolve_n(n_particles), self.model.state_dim, self.model.obs_dim
        K = m if self.local_index is None else self.local_index.shape[1]
        return 8 * (10 * N * d + 2 * N * m + 2 * N * d * min(K, m))

    def step(self, state, z: torch.Tensor, generator: Optional[torch.Generator] = None):
        """Forecast, then weigh, estimate and resample every coordinate locally."""
        xbar, A = self.forecast(state, generator)
        Xf = xbar + A
        B_, N, d = Xf.shape
        terms = self.model.measurement_log_prob_terms(z.unsqueeze(1), Xf)  # (B, N, m)
        if self.local_index is None:  # radius = inf: one set of weights for every coordinate
            lw = terms.sum(-1, keepdim=True).expand(B_, N, d)
        else:
            idx, taper = self.local_index.to(Xf.device), self.local_taper.to(Xf)  # follow the model's dtype, device
            lw = (terms[:, :, idx] * taper).sum(-1)  # (B, N, d)
        W = torch.softmax(lw, 1)
        estimate = (W * Xf).sum(1)  # (B, d): each coordinate's weighted mean
        Xa = local_transport(Xf, W, "systematic", generator)  # one uniform per trial for every coordinate
        if self.rtps > 0 or self.jitter > 0:
            sf = A.std(1, keepdim=True)  # (B, 1, d): each coordinate's forecast spread
        if self.rtps > 0:
            ma = Xa.mean(1, keepdim=True)
            sa = Xa.std(1, keepdim=True)
            scale = torch.where(sa > 0, 1.0 + self.rtps * (sf - sa) / sa.clamp_min(1e-300), torch.ones_like(sa))
            Xa = ma + (Xa - ma) * scale
        if self.jitter > 0:
            xi = linalg.standard_normal(Xa.shape, dtype=Xa.dtype, device=Xa.device, generator=generator)
            Xa = Xa + self.jitter * sf * xi
        # the evidence: the forecast ensemble's Gaussian approximation, as the ensemble filters report it
        ll = self.forecast_evidence(self.whiten(Xf, xbar.squeeze(1), z))
        return dataclasses.replace(self._state(Xa, ll, state.step + 1), estimate=estimate)

    def extra_repr(self) -> str:
        return super().extra_repr() + f", radius={self.radius:g}, rtps={self.rtps:g}, jitter={self.jitter:g}"


class LagOneFlowFilter(_EnsembleFilter):
    """The exact (EDH) particle flow on the lag-one target: the previous analysis members move to
    ``p(x_{k-1} | z_{1:k})`` and the model carries them to time ``k``.

    With deterministic dynamics ``x_k = M(x_{k-1})`` the filtering law at ``k`` is the image by
    ``M`` of the lag-one smoothing law
    ``p(x_{k-1} | z_{1:k}) ∝ p(x_{k-1} | z_{1:k-1}) p(z_k | M(x_{k-1}))``: in ``x_{k-1}`` the
    measurement is ``h(M(x))``, and the information the window's nonlinearity keeps from a
    forecast-then-analyse filter is used where it arises (the idea of the iterative ensemble
    Kalman smoother with a window of one cycle, Bocquet & Sakov 2014). The target here takes the
    previous analysis ensemble's Gaussian ``N(xbar, P)`` (anomalies times ``inflation``) for
    ``p(x_{k-1} | z_{1:k-1})``; the members follow the exact flow of Daum & Huang (2010)::

        dx/dlam = A(lam) x + b(lam),   A = -1/2 P H^T (lam H P H^T + R)^{-1} H,
        b = (I + 2 lam A) [(I + lam A) P H^T R^{-1} (z - e) + A xbar],

    ``lam`` from 0 to 1 in ``flow_steps`` exponentially growing steps (ratio ``step_ratio``), with
    ``h(M(x)) ~ e + H x`` re-linearised at every step by the least-squares regression of the
    flowed members' measurements ``h(M(x_i))`` on the members (the ensemble's statistical
    linearisation, minimum norm in the ensemble's span: no Jacobian, no model adjoint). In a
    linear-Gaussian model the flow carries the ensemble to the Kalman mean and covariance of the
    previous analysis ensemble updated by ``z_k`` (tested); nonlinearity is met by re-linearising
    along the way (a homotopy, like the iterations of a Gauss-Newton smoother). Then every member
    goes through ``model.sample_transition`` (with its model noise, if the model has any: the
    target above is then an approximation that ignores it).

    Everything is written in the ensemble's span (``P = A^T A / (N - 1)``): per flow step ``N``
    model runs and ``O(N^2 (d + m) + N^3)`` algebra, memory ``O(N (d + m))``; no ``d x d`` or
    ``m x m`` matrix. This flow is global: in many dimensions the ``N - 1`` directions of the
    ensemble bound what it can correct.

    **Localised** (``radius`` finite, ``covariance="current"``). The same target, with the flow
    written in the flowed members' own covariance ``P_lam`` (the deterministic ensemble
    Kalman-Bucy flow of Bergemann & Reich, 2010, in pseudo-time, whose localisation is a Schur
    product inside the flow)::

        dx_i/dlam = -(rho o P_lam H^T) R^{-1} ((h(M(x_i)) + ybar) / 2 - z)

    with ``P_lam H^T`` the members' cross-covariance of ``x`` and ``h(M(x))`` (the statistical
    linearisation again, now without a regression) and ``rho`` the Gaspari-Cohn taper of the
    distance between the coordinate and the observation (zero from ``radius`` on; R must be
    diagonal). On a linear-Gaussian model and ``radius = inf`` it reaches the same Kalman update
    (tested). Each observation reaches the ``K`` coordinates near it: per flow step ``N`` model runs
    and ``O(N d K)`` work, memory ``O(N (d + m))`` (the neighbourhood is gathered in blocks), so
    ``d = 10^5`` runs on one CPU core. The explicit steps are stable while ``step_ratio - 1`` (each
    step over the pseudo-time reached) stays small and the first step is small against the
    prior's signal-to-noise: the exponential schedule does both.

    Args:
        model: a Gaussian-form model with a deterministic ``transition_mean`` (the map ``M``),
            ``measure``, ``measurement_cov`` and ``sample_transition``.
        n_particles: ensemble members N (>= 2).
        inflation: multiplicative inflation of the previous analysis anomalies before the flow (>= 1).
        flow_steps, step_ratio: the pseudo-time schedule (Li & Coates' exponential spacing: step
            ``j`` is ``step_ratio`` times step ``j - 1``; ratio 1: uniform).
        linearisation: ``"members"`` (default): regression over the flowed members (their average
            sensitivity); ``"bundle"``: over the flowed mean plus the members' anomalies scaled by
            ``bundle`` (a finite-difference linearisation at the mean, the iterative ensemble
            Kalman smoother's bundle variant; the same cost).
        bundle: the bundle's scale, in (0, 1].
        covariance: ``"prior"``: the exact flow above with the previous analysis covariance
            throughout (global only); ``"current"``: the flowed members' covariance at every
            pseudo-time (localisable); ``None`` (default): ``"prior"`` when ``radius`` is infinite,
            else ``"current"``.
        radius: the localisation radius (``inf``, the default: none): the distance beyond which an
            observation does not move a coordinate (Gaspari-Cohn taper, half-width ``radius / 2``).
        distances: ``(d, m)`` distances between state coordinates and observations (``None``: the
            ring of :class:`~torchflow.filters.LocalEnsembleTransformKalmanFilter`).
        likelihood: with ``covariance="current"``: ``"gaussian"`` (default): the Gaussian of R, as
            above; ``"model"``: ``R^{-1} (z - y)`` replaced by the score ``d/dy log p(z | y)`` of the
            model's own density of each observation (``measurement_log_prob_terms``; errors additive,
            so that the density is a function of ``z - y``) at the midpoint ``y = (h(M(x_i)) + ybar) / 2``:
            for the Gaussian the same flow, for heavy tails a robust one (Student-t errors: an
            outlying observation's pull is bounded).
        rotate: mix the analysis members by a random mean-preserving rotation (as the ETKF's, and
            DAPPER's iEnKS with ``rot=True``); on by default: without it members that strayed stay
            outliers, and on Lorenz-63 one trial in ten lost the truth at N = 20 and 40 (with it, none;
            ``python -m experiments.benchmarks.bench_lorenz63``).
        validate, name: as :class:`~torchflow.filters.Filter`.

    The evidence is the Gaussian approximation of the forecast ensemble ``M(x_i)`` seen through the
    measurement (:attr:`estimates_evidence` is ``False``). A NaN in ``z (B, m)`` is not observed
    (a zero row of ``H``); a trial with nothing observed is a pure forecast.

    Shapes: ensemble ``(B, N, d)``, observations ``z (B, m)``.
    """

    nonfinite_hint = (
        "the members diverged: a smaller inflation, more flow_steps, or dynamics that blow up at the "
        "model's time step (a smaller dt or more substeps)"
    )

    def __init__(
        self,
        model,
        *,
        n_particles: int = 20,
        inflation: float = 1.02,
        flow_steps: int = 20,
        step_ratio: float = 1.2,
        linearisation: str = "members",
        bundle: float = 1e-4,
        rotate: bool = True,
        covariance: Optional[str] = None,
        radius: float = math.inf,
        distances: Optional[torch.Tensor] = None,
        likelihood: str = "gaussian",
        validate: bool = True,
        name: Optional[str] = None,
    ):
        super().__init__(
            model, n_particles=n_particles, inflation=inflation, rotate=rotate, validate=validate, name=name
        )
        if linearisation not in LINEARISATIONS:
            raise ArgumentError(f"linearisation: expected one of {LINEARISATIONS}, got {linearisation!r}")
        self.radius = check_radius(radius)
        local = not math.isinf(self.radius)
        if covariance is None:
            covariance = "current" if local else "prior"
        if covariance not in FLOW_COVARIANCES:
            raise ArgumentError(f"covariance: expected one of {FLOW_COVARIANCES} or None, got {covariance!r}")
        if local and covariance == "prior":
            raise ArgumentError(
                f"covariance: a finite radius ({self.radius:g}) localises the flowed members' covariance, so it "
                "needs covariance='current' (or None); got 'prior' (the exact flow is global: radius=inf)"
            )
        if covariance == "current" and linearisation == "bundle":
            raise ArgumentError(
                "linearisation: covariance='current' reads the flowed members' own measurements "
                "(their cross-covariance), so it needs linearisation='members'; got 'bundle'"
            )
        if likelihood not in LIKELIHOODS:
            raise ArgumentError(f"likelihood: expected one of {LIKELIHOODS}, got {likelihood!r}")
        if likelihood == "model" and covariance != "current":
            raise ArgumentError(
                "likelihood: 'model' (the score of the model's own measurement density) drives the "
                "flow in the members' covariance, so it needs covariance='current' or a finite radius"
            )
        if likelihood == "model" and model.structure.measurement_noise not in DIAGONAL_NOISE:
            raise ArgumentTypeError(
                f"{self.name}: model: likelihood='model' reads each observation's density on its own, which needs a "
                f"diagonal measurement noise; {type(model).__name__} declares {model.structure.measurement_noise!r}"
            )
        #: ``"gaussian"``: the Gaussian of R; ``"model"``: the score of the model's own density of each
        #: observation (``measurement_log_prob_terms``, additive errors: a function of ``z - h(x)``)
        self.likelihood = likelihood
        #: ``"prior"``: Daum & Huang's exact flow with the previous analysis covariance throughout (global);
        #: ``"current"``: the flowed members' covariance at every pseudo-time (localisable, ``radius``)
        self.covariance = covariance
        if local:
            if model.structure.measurement_noise not in DIAGONAL_NOISE:
                raise ArgumentTypeError(
                    f"{self.name}: model: a finite radius tapers each observation's influence, which needs a "
                    f"diagonal measurement noise (declared scalar, diagonal or state_dependent_diagonal); "
                    f"{type(model).__name__} declares {model.structure.measurement_noise!r}. Use radius=inf"
                )
        _register_neighbours(self, distances)
        #: ``"members"``: regression over the flowed members; ``"bundle"``: over the flowed mean plus
        #: the members' anomalies scaled by :attr:`bundle` (a finite-difference linearisation at the mean)
        self.linearisation = linearisation
        self.bundle = check_number("bundle", bundle, lambda v: 0 < v <= 1, "a number in (0, 1] (the bundle's scale)")
        self.flow_steps = check_count("flow_steps", flow_steps, minimum=1, hint=" (steps in pseudo-time)")
        self.step_ratio = check_number(
            "step_ratio", step_ratio, lambda v: v > 0, "a number > 0 (each pseudo-time step over the previous one)"
        )
        self.schedule = ExponentialSchedule(self.flow_steps, self.step_ratio)
        #: the flow (:mod:`torchflow.flows.ensemble`): Daum & Huang's exact flow linearised over the
        #: members (``covariance="prior"``), or the localised Kalman-Bucy flow (``"current"``)
        self.flow = (
            LagOneFlow(self.linearisation, self.bundle)
            if covariance == "prior"
            else LocalisedKalmanBucyFlow(self.local_index, self.local_taper, likelihood)
        )

    def bytes_per_trial(self, n_particles=None):
        N, d, m = self._resolve_n(n_particles), self.model.state_dim, self.model.obs_dim
        # the neighbourhoods' index and taper (d x K each), and the blocks the drift gathers them in
        local = 0 if self.local_index is None else 2 * d * self.local_index.shape[1] + 3 * CACHE_ELEMENTS
        return 8 * (10 * N * d + 6 * N * m + 8 * N * N + (m * m if self._dense_noise else 0) + local)

    def step(self, state, z: torch.Tensor, generator: Optional[torch.Generator] = None):
        """Flow the previous analysis members to ``p(x_{k-1} | z_{1:k})``, then forecast them."""
        X, ll = self.migrate(state.particles, z)
        Xa = self.model.sample_transition(X, generator)
        if self.rotate:
            Xa = rotate_anomalies(Xa, generator)
        return self._state(Xa, ll, state.step + 1)

    def migrate(self, X: torch.Tensor, z: torch.Tensor):
        """The previous analysis members ``X (B, N, d)`` moved by the flow (:attr:`flow`, through
        :func:`~torchflow.flows.integrate_flow`) to the lag-one target with ``z (B, m)``, and the
        forecast evidence ``(B,)`` (before the model carries them to time k)."""
        prior = ensemble_prior(X, self.inflation)  # N(xbar, A0^T A0), the anomalies inflated
        Xi = prior.mean + prior.root.transpose(1, 2) * math.sqrt(X.shape[1] - 1)  # the inflated members
        w0 = self.measure_images(Xi, z)
        meas = EnsembleMeasurement(
            z,
            whiten=lambda Y: self.measure_images(Y, z),
            first=w0,
            log_prob_terms=self.model.measurement_log_prob_terms,
            transition=self.model.transition_mean,
        )
        out = integrate_flow(self.flow, self.model, Xi, z, prior, self.schedule, points="ensemble", measurement=meas)
        # a trial with nothing observed keeps its members bit for bit (masked, no host read)
        return torch.where((~torch.isnan(z)).any(-1).view(-1, 1, 1), out.particles, X), self.forecast_evidence(w0)

    def measure_images(self, X: torch.Tensor, z: torch.Tensor):
        """The members' measurements on the lag-one target, ``h(M(x_i))``, whitened by R (at the
        members' mean where R depends on the state), with the images ``M(x_i)`` kept."""
        Xm = self.model.transition_mean(X)
        w = self.whiten(Xm, X.mean(1), z)
        w.images = Xm
        return w

    def extra_repr(self) -> str:
        local = ("" if self.local_index is None else f", radius={self.radius:g}") + (
            f", likelihood={self.likelihood!r}" if self.likelihood != "gaussian" else ""
        )
        return (
            super().extra_repr() + f", flow_steps={self.flow_steps}, step_ratio={self.step_ratio:g}, "
            f"covariance={self.covariance!r}{local}, linearisation={self.linearisation!r}"
            + (f", bundle={self.bundle:g}" if self.linearisation == "bundle" else "")
        )
