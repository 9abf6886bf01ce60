"""Kalman-type filters: Kalman (exact, linear-Gaussian), extended and unscented Kalman filters."""

from __future__ import annotations

from typing import Optional, Tuple

import torch

from torchflow.core import linalg, missing
from torchflow.core.checks import check_number
from torchflow.core.errors import ArgumentTypeError
from torchflow.core.trackers import UnscentedTransform, ekf_predict, ekf_update, kalman_update
from torchflow.filters.base import Filter, GaussianState
from torchflow.models.trials import shared_structure, trial_names

__all__ = ["KalmanFilter", "ExtendedKalmanFilter", "UnscentedKalmanFilter", "kalman_update", "ekf_predict"]


class _GaussianFilter(Filter):
    """A Gaussian belief, moved by the subclass's :meth:`predict` and :meth:`update` each step.

    ``inflation >= 1`` multiplies the predicted covariance by ``inflation^2`` before the update (the
    multiplicative inflation of the ensemble filters, whose anomalies it scales by ``inflation``):
    on chaotic models it makes up for the spread the linearisation (EKF) or the sigma points (UKF)
    miss. 1: none."""

    def __init__(self, model, *, inflation: float = 1.0, validate: bool = True, name: Optional[str] = None):
        super().__init__(model, validate=validate, name=name)
        #: the predicted covariance is multiplied by ``inflation ** 2`` (1: none)
        self.inflation = check_number(
            "inflation",
            inflation,
            lambda v: v >= 1,
            "a finite number >= 1 (multiplicative inflation of the predicted covariance)",
        )

    def check_model(self) -> None:
        """With more measurements than states (``m > d``) the predicted measurement's covariance
        ``H P H^T + R`` is singular when R is: the measurement density, hence the log-evidence,
        does not exist, so a singular constant R is refused (``m <= d`` runs it)."""
        super().check_model()
        m, d = self.model.obs_dim, self.model.state_dim
        if m > d:
            self.require_definite(
                "measurement",
                f"with m = {m} measurements of d = {d} states, H P H^T + R is then singular and the measurement "
                "density (the log-evidence) does not exist. Give the model a positive definite measurement noise",
            )

    def init(self, mean, cov, n_particles=None, generator=None):
        return GaussianState(mean, cov, torch.zeros_like(mean[:, 0]), 0)

    def step(self, state, z, generator=None):
        m_pred, P_pred = self.predict(state.mean, state.cov)
        if self.inflation != 1.0:
            P_pred = P_pred * self.inflation**2
        mean, cov, ll = self.update(m_pred, P_pred, z)
        return GaussianState(mean, cov, ll, state.step + 1)


class ExtendedKalmanFilter(_GaussianFilter):
    """Extended Kalman filter: linearise g at the posterior mean and h at the predicted mean.

    Jacobians come from the model (``torch.func`` by default, analytic where the model provides
    them). On a linear-Gaussian model (and ``inflation=1``) it is the Kalman filter.

    Args:
        model: a Gaussian-form model.
        inflation: the predicted covariance is multiplied by ``inflation^2`` (>= 1; 1: none).
        validate, name: as :class:`~torchflow.filters.Filter`.
    """

    def predict(self, mean: torch.Tensor, cov: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """``(..., d)``, ``(..., d, d)`` -> predicted mean and covariance (any leading shape)."""
        return ekf_predict(self.model, mean, cov)

    def update(self, mean_pred: torch.Tensor, cov_pred: torch.Tensor, z: torch.Tensor):
        """Measurement update linearised at ``mean_pred (..., d)``; ``z`` broadcasts to ``(..., m)``.
        Returns mean ``(..., d)``, covariance ``(..., d, d)`` and log N(z; h(mean_pred), S) ``(...)``."""
        return ekf_update(self.model, mean_pred, cov_pred, z)


class KalmanFilter(ExtendedKalmanFilter):
    """Exact Kalman filter for linear-Gaussian models: any model that declares
    :attr:`~torchflow.models.Structure.linear_dynamics` and ``linear_measurement`` (with
    additive Gaussian noise), e.g. :class:`~torchflow.models.LinearGaussian`.

    Log-evidence ``sum_k log N(z_k; H m_k^-, H P_k^- H^T + R)`` is exact and differentiable in the
    model's parameters.
    """

    def __init__(self, model, *, validate: bool = True, name: Optional[str] = None):
        super().__init__(model, validate=validate, name=name)
        structure = shared_structure(model)  # per-trial F or H: linear for each trial (steps go per trial)
        if not (structure.linear_dynamics and structure.linear_measurement):
            raise ArgumentTypeError(
                f"model: KalmanFilter needs a linear-Gaussian model (a LinearGaussian, or any model "
                f"declaring linear_dynamics and linear_measurement), got {type(model).__name__} "
                f"(linear_dynamics={structure.linear_dynamics}, linear_measurement={structure.linear_measurement}; "
                "use ExtendedKalmanFilter or UnscentedKalmanFilter for nonlinear models)"
            )

    def init(self, mean, cov, n_particles=None, generator=None):
        # The Riccati recursion does not depend on the data: when every trial starts from the same
        # covariance and the model's matrices are the same for every trial, run it once and share it
        # (a stride-0 expanded view keeps the (B, d, d) shape). Per-trial parameters
        # (torchflow.inference.per_trial_values) give each trial its own recursion.
        if cov.shape[0] > 1 and not trial_names(self.model) and bool((cov == cov[:1]).all()):
            cov = cov[:1].expand_as(cov)
        return super().init(mean, cov)

    def step(self, state, z, generator=None):
        B = state.mean.shape[0]
        # masks differ between trials, and so do per-trial parameters: one recursion per trial
        if B > 1 and state.cov.stride(0) == 0 and not missing.active() and not trial_names(self.model):
            return self._shared_step(state, z)
        return super().step(state, z, generator)

    def _shared_step(self, state, z):
        """All trials share one covariance: run the Riccati step once on ``(d, d)`` matrices and
        update the ``(B, d)`` means with three matrix products."""
        model = self.model
        F, Q = model.transition_matrix(), model.transition_cov()
        H, R = model.measurement_matrix(), model.measurement_cov()
        # a scaled identity F or H (the sensor network: 0.9 I, I; declared by the model) is a
        # scaling, not a product
        f, h = model.structure.transition_matrix_scale, model.structure.measurement_matrix_scale
        P = state.cov[0]
        # scalings and sums of symmetric matrices are exactly symmetric: symmetrize only products
        P_pred = (f * f) * P + Q if f is not None else linalg.symmetrize(F @ P @ F.T + Q)
        one = h == 1.0  # H = I (the sensor network): a product by 1 is the identity, bit for bit
        HP = P_pred if one else h * P_pred if h is not None else H @ P_pred
        S = HP + R if one else h * HP + R if h is not None else linalg.symmetrize(HP @ H.T + R)
        L = linalg.safe_cholesky(S)
        Kt = linalg.chol_solve(L, HP)  # (m, d) = K^T
        cov = linalg.symmetrize(P_pred - Kt.T @ HP)  # P - K S K^T; one shared, well-conditioned matrix
        m_pred = f * state.mean if f is not None else state.mean @ F.T  # (B, d)
        innov = z - (m_pred if one else h * m_pred if h is not None else m_pred @ H.T)  # (B, m)
        mean = torch.addmm(m_pred, innov, Kt)
        ll = linalg.mvn_log_prob(innov, torch.zeros_like(innov[:1]), L)
        return GaussianState(mean, cov.expand(state.mean.shape[0], -1, -1), ll, state.step + 1)


class UnscentedKalmanFilter(_GaussianFilter):
    """Unscented Kalman filter (scaled sigma points, Wan & van der Merwe; the transform is
    :class:`~torchflow.core.trackers.UnscentedTransform`).

    ``2d + 1`` sigma points ``m``, ``m +- sqrt(d + lambda) L_i`` with ``lambda = alpha^2 (d + kappa) - d``.
    Exact on linear-Gaussian models for any admissible (alpha, beta, kappa).

    Args:
        inflation: the predicted covariance is multiplied by ``inflation^2`` (>= 1; 1: none).
        alpha, beta, kappa: sigma-point spread and weights. Defaults ``alpha = 1``, ``beta = 2``,
            ``kappa = None`` meaning ``3 - d`` (Julier & Uhlmann's ``d + kappa = 3`` rule). On the
            acoustic model (d = 16, prior sd 10 m) ``kappa = 0`` puts sigma points 40 m from the
            mean, outside the field, and the UKF diverges (OMAT ~23 m vs ~5.7 m with 3 - d).
    """

    def __init__(
        self,
        model,
        *,
        alpha: float = 1.0,
        beta: float = 2.0,
        kappa: Optional[float] = None,
        inflation: float = 1.0,
        validate: bool = True,
        name: Optional[str] = None,
    ):
        super().__init__(model, inflation=inflation, validate=validate, name=name)
        # on the model's device and dtype (a filter built around a CUDA model must not keep CPU weights)
        self.unscented = UnscentedTransform(
            model.state_dim, alpha=alpha, beta=beta, kappa=kappa, dtype=model.dtype, device=model.device
        )

    alpha = property(lambda self: self.unscented.alpha)
    beta = property(lambda self: self.unscented.beta)
    kappa = property(lambda self: self.unscented.kappa)

    def check_model(self) -> None:
        """R must be positive definite: with a singular R the update makes the posterior covariance
        singular in the exactly measured directions, the next step's sigma points collapse onto a
        lower-dimensional set, and their measurement covariance is no longer invertible."""
        super().check_model()
        self.require_definite(
            "measurement",
            "the UKF's sigma points collapse once an exact measurement (zero noise) has been absorbed. Give the "
            "model a positive definite measurement noise, or use the Kalman filter or the EKF",
        )

    def predict(self, mean: torch.Tensor, cov: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """Unscented prediction for ``(..., d)``, ``(..., d, d)`` (any leading shape)."""
        return self.unscented.predict(self.model, mean, cov)

    def update(self, mean_pred: torch.Tensor, cov_pred: torch.Tensor, z: torch.Tensor):
        """Unscented update with sigma points redrawn from ``N(mean_pred, cov_pred)``; ``z``
        broadcasts to ``(..., m)``. Returns mean, covariance and log N(z; z_hat, S)."""
        return self.unscented.update(self.model, mean_pred, cov_pred, z)
