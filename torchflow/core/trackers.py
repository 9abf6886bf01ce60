"""Gaussian trackers: EKF and UKF prediction and update on ``(..., d)`` beliefs.

They sit below proposals and filters: the Kalman-family filters (:mod:`torchflow.filters.kalman`)
step with them, and so does every proposal that tracks a covariance (the PF-PF's flow prior, the
unscented particle filter's per-particle UKF). Any leading batch shape works: per trial
``(B, d)``, per particle ``(B, N, d)``.

* :func:`kalman_update`: the linear(ised) Gaussian measurement update (Joseph form).
* :func:`ekf_predict`, :func:`ekf_update`: linearised at the mean (Jacobians from the model:
  ``torch.func`` by default, analytic where the model provides them, constant when it declares
  linearity).
* :class:`UnscentedTransform`: scaled sigma points (Wan & van der Merwe) with
  :meth:`~UnscentedTransform.predict` and :meth:`~UnscentedTransform.update`.
* :class:`Tracker`: a model and one of the two, as a module (``tracker(model, "ekf" | "ukf")``).
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch
from torch import nn

from torchflow.core import linalg, missing, tuning
from torchflow.core.errors import ArgumentError

TRACKERS = ("ekf", "ukf")


def kalman_update(
    mean_pred: torch.Tensor,
    cov_pred: torch.Tensor,
    z: torch.Tensor,
    z_pred: torch.Tensor,
    H: torch.Tensor,
    R: torch.Tensor,
) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Linear(ised) Gaussian measurement update, any leading batch shape ``(...)``.

    Args:
        mean_pred: ``(..., d)`` predicted mean.
        cov_pred: ``(..., d, d)`` predicted covariance P.
        z: ``(..., m)`` observation (broadcastable); inside :func:`torchflow.core.missing.observations_missing`
            a NaN coordinate is not observed and the update uses the observed rows only.
        z_pred: ``(..., m)`` predicted measurement (``H mean_pred`` for a linear model).
        H: ``(..., m, d)`` measurement Jacobian.
        R: ``(..., m, m)`` measurement noise covariance (broadcastable).

    Returns:
        posterior mean ``(..., d)``, covariance ``(..., d, d)`` (Joseph form, symmetrised) and
        the log-density of ``z`` under ``N(z_pred, S)``, ``S = H P H^T + R``: ``(...)``.
    """
    correction = None
    if missing.active():  # NaN rows of z not observed: the update on the observed rows (torchflow.core.missing)
        z, z_pred, H, R, correction = missing.gaussian_rows(z, z_pred, H, R)
    HP = H @ cov_pred  # (..., m, d)
    S = linalg.symmetrize(HP @ H.transpose(-1, -2) + R)
    L = linalg.safe_cholesky(S)
    Kt = linalg.chol_solve(L, HP)  # (..., m, d) = S^{-1} H P  (= K^T)
    K = Kt.transpose(-1, -2)
    innov = z - z_pred
    mean = mean_pred + linalg.matvec(K, innov)
    d = mean_pred.shape[-1]
    IKH = torch.eye(d, dtype=H.dtype, device=H.device) - K @ H
    cov = linalg.symmetrize(IKH @ cov_pred @ IKH.transpose(-1, -2) + K @ R @ K.transpose(-1, -2))
    loglik = linalg.mvn_log_prob(z, z_pred, L)
    return mean, cov, loglik if correction is None else loglik + correction


def ekf_predict(model, mean: torch.Tensor, cov: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """EKF prediction ``(g(m), G P G^T + Q)`` for ``mean (..., d)``, ``cov (..., d, d)``."""
    G = model.transition_matrix() if model.structure.linear_dynamics else model.transition_jacobian(mean)
    return model.transition_mean(mean), linalg.symmetrize(G @ cov @ G.transpose(-1, -2) + model.transition_cov(mean))


def ekf_update(model, mean_pred: torch.Tensor, cov_pred: torch.Tensor, z: torch.Tensor):
    """EKF measurement update linearised at ``mean_pred (..., d)``; ``z`` broadcasts to ``(..., m)``.
    Returns mean ``(..., d)``, covariance ``(..., d, d)`` and log N(z; h(mean_pred), S) ``(...)``.

    A nonlinear model that declares a scalar R (``measurement_noise = "scalar"``) and a measurement
    support of ``k <= m`` coordinates is updated in ``k x k`` algebra
    (:func:`kalman_update_scalar_support`; ``torchflow.core.tuning`` ``structured_update``, default 1);
    otherwise :func:`kalman_update`."""
    support = model.structure.measurement_support
    if (
        tuning.get().structured_update
        and not model.structure.linear_measurement
        and model.structure.measurement_noise == "scalar"
        and support is not None
        and len(support) <= model.obs_dim
    ):
        h, Hs = model.linearize_measurement(mean_pred, support=True)
        sigma2 = model.measurement_cov(mean_pred)[..., 0, 0]
        return kalman_update_scalar_support(mean_pred, cov_pred, z, h, Hs, sigma2, support)
    H = model.measurement_matrix() if model.structure.linear_measurement else model.measurement_jacobian(mean_pred)
    return kalman_update(mean_pred, cov_pred, z, model.measure(mean_pred), H, model.measurement_cov(mean_pred))


def kalman_update_scalar_support(
    mean_pred: torch.Tensor,
    cov_pred: torch.Tensor,
    z: torch.Tensor,
    z_pred: torch.Tensor,
    H_s: torch.Tensor,
    sigma2: torch.Tensor,
    support,
):
    """:func:`kalman_update` for ``R = sigma2 I`` and a Jacobian whose nonzero columns are
    ``support`` (k of d), in ``k x k`` algebra (Woodbury), for ``m >= k`` measurements.

    With ``P_ss = L L^T`` (the support block), ``C = P[:, s] L^{-T}`` ``(d, k)``, ``U = H_s L``
    ``(m, k)`` and ``G = U^T U + sigma2 I = K_G K_G^T`` (``k x k``):
    ``S = H P H^T + R = U U^T + sigma2 I``, so ``U^T S^{-1} = G^{-1} U^T`` and

    * mean: ``m + C G^{-1} U^T r`` (``r = z - z_pred``);
    * covariance: ``P - C C^T + sigma2 (C K_G^{-T})(C K_G^{-T})^T`` (symmetrised);
    * ``log det S = (m - k) log sigma2 + log det G``,
      ``r^T S^{-1} r = (r^T r - (U^T r)^T G^{-1} U^T r) / sigma2``.

    The same posterior as the Joseph form of :func:`kalman_update` up to round-off; per matrix
    ~1e4 flops instead of ~1e5 for acoustic tracking (d = 16, m = 25, k = 8), and one ``k x k``
    factorisation instead of an ``m x m`` one.

    Args:
        mean_pred ``(..., d)``, cov_pred ``(..., d, d)``, z ``(..., m)`` (broadcastable),
        z_pred ``(..., m)``, H_s ``(..., m, k)`` (the support columns of the Jacobian),
        sigma2: the noise variance (a 0-d tensor or a float), support: k coordinate indices.

    Returns:
        as :func:`kalman_update`.
    """
    sup = linalg.index_tensor(support, cov_pred.device)  # no copy from the host per step
    m, k = H_s.shape[-2], len(sup)
    P_cs = cov_pred[..., :, sup]  # (..., d, k)
    L = linalg.safe_cholesky(P_cs[..., sup, :])  # (..., k, k)
    C = linalg.solve_triangular(L, P_cs.transpose(-1, -2), upper=False).transpose(-1, -2)  # (..., d, k)
    U = linalg.matmul(H_s, L)  # (..., m, k)
    Ut = U.transpose(-1, -2)
    eye = torch.eye(k, dtype=U.dtype, device=U.device)
    r = z - z_pred
    correction = None
    if missing.active():  # unobserved rows: zero residual and Jacobian rows; S keeps sigma2 there
        mask, _ = missing.observed(z)
        mask = mask.expand(r.shape)
        r = torch.where(mask, r, torch.zeros_like(r))
        U = U * mask.unsqueeze(-1).to(U.dtype)
        Ut = U.transpose(-1, -2)
        log_s2 = torch.log(torch.as_tensor(sigma2, dtype=U.dtype, device=U.device)).expand(r.shape)
        correction = missing.unobserved_correction(mask, log_s2)
    KG = linalg.safe_cholesky(linalg.matmul(Ut, U) + sigma2 * eye)
    Ur = linalg.matvec(Ut, r.expand(U.shape[:-1]))  # (..., k)
    a = linalg.chol_solve(KG, Ur.unsqueeze(-1)).squeeze(-1)  # G^{-1} U^T r
    mean = mean_pred + linalg.matvec(C, a)
    Chat = linalg.solve_triangular(KG, C.transpose(-1, -2), upper=False).transpose(-1, -2)  # C K_G^{-T}
    cov = cov_pred - linalg.matmul(C, C.transpose(-1, -2)) + sigma2 * linalg.matmul(Chat, Chat.transpose(-1, -2))
    quad = ((r * r).sum(-1) - (Ur * a).sum(-1)) / sigma2
    logdet = (m - k) * torch.log(torch.as_tensor(sigma2, dtype=U.dtype, device=U.device)) + linalg.chol_logdet(KG)
    loglik = -0.5 * (quad + logdet + m * linalg._LOG_2PI)
    return mean, linalg.symmetrize(cov), loglik if correction is None else loglik + correction


class UnscentedTransform(nn.Module):
    """Scaled sigma points (Wan & van der Merwe): ``2d + 1`` points ``m``, ``m +- sqrt(d + lambda) L_i``
    with ``lambda = alpha^2 (d + kappa) - d``. Exact on linear-Gaussian models for any admissible
    (alpha, beta, kappa).

    Args:
        state_dim: d.
        alpha, beta, kappa: spread and weights; ``kappa = None`` means ``3 - d`` (Julier & Uhlmann's
            ``d + kappa = 3`` rule).
        dtype, device: of the weights (the model's).
    """

    def __init__(
        self,
        state_dim: int,
        *,
        alpha: float = 1.0,
        beta: float = 2.0,
        kappa: Optional[float] = None,
        dtype=torch.float64,
        device=None,
    ):
        super().__init__()
        d = int(state_dim)
        if kappa is None:
            kappa = 3.0 - d
        lam = alpha**2 * (d + kappa) - d
        if d + lam <= 0:
            raise ArgumentError(f"alpha, kappa: need alpha^2 (d + kappa) > 0, got alpha={alpha}, kappa={kappa}, d={d}")
        self.alpha, self.beta, self.kappa = float(alpha), float(beta), float(kappa)
        self.scale = (d + lam) ** 0.5
        wm = torch.full((2 * d + 1,), 0.5 / (d + lam), dtype=torch.float64)
        wc = wm.clone()
        wm[0] = lam / (d + lam)
        wc[0] = lam / (d + lam) + (1 - alpha**2 + beta)
        self.register_buffer("wm", wm.to(device=device, dtype=dtype))
        self.register_buffer("wc", wc.to(device=device, dtype=dtype))

    def sigma_points(self, mean: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
        """``(..., d)``, ``(..., d, d)`` -> sigma points ``(..., 2d + 1, d)``."""
        L = linalg.safe_cholesky(cov) * self.scale
        cols = L.transpose(-1, -2)  # rows = columns of L
        m = mean.unsqueeze(-2)
        return torch.cat([m, m + cols, m - cols], dim=-2)

    def moments(self, Y: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """Weighted mean ``(..., k)`` of sigma-point images ``Y (..., 2d + 1, k)`` and deviations."""
        mean = torch.einsum("s,...sd->...d", self.wm.to(Y), Y)  # .to: no-op unless moved alone
        return mean, Y - mean.unsqueeze(-2)

    def cross(self, D1: torch.Tensor, D2: torch.Tensor) -> torch.Tensor:
        """Weighted cross-covariance of deviations ``(..., s, i)``, ``(..., s, j)`` -> ``(..., i, j)``."""
        return torch.einsum("s,...si,...sj->...ij", self.wc.to(D1), D1, D2)

    def predict(self, model, mean: torch.Tensor, cov: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """Unscented prediction for ``(..., d)``, ``(..., d, d)`` (any leading shape)."""
        X = model.transition_mean(self.sigma_points(mean, cov))
        m_pred, DX = self.moments(X)
        return m_pred, linalg.symmetrize(self.cross(DX, DX) + model.transition_cov(m_pred))

    def update(self, model, mean_pred: torch.Tensor, cov_pred: torch.Tensor, z: torch.Tensor):
        """Unscented update with sigma points redrawn from ``N(mean_pred, cov_pred)``; ``z``
        broadcasts to ``(..., m)``. Returns mean, covariance and log N(z; z_hat, S)."""
        X = self.sigma_points(mean_pred, cov_pred)
        z_pred, DZ = self.moments(model.measure(X))
        DX = X - mean_pred.unsqueeze(-2)
        R = model.measurement_cov(mean_pred)
        correction = None
        if missing.active():  # unobserved coordinates: zero deviations and residual, identity noise rows
            mask = ~torch.isnan(z)
            z, z_pred, _, R, correction = missing.gaussian_rows(z, z_pred, None, R)
            DZ = DZ * mask.unsqueeze(-2).to(DZ.dtype)
        S = linalg.symmetrize(self.cross(DZ, DZ) + R)
        C = self.cross(DX, DZ)  # (..., d, m)
        L = linalg.safe_cholesky(S)
        Kt = linalg.chol_solve(L, C.transpose(-1, -2))  # S^{-1} C^T = K^T
        mean = mean_pred + linalg.matvec(Kt.transpose(-1, -2), z - z_pred)
        cov = linalg.symmetrize(cov_pred - C @ Kt)  # P - K S K^T = P - C S^{-1} C^T
        loglik = linalg.mvn_log_prob(z, z_pred, L)
        return mean, cov, loglik if correction is None else loglik + correction

    def extra_repr(self) -> str:
        return f"alpha={self.alpha}, beta={self.beta}, kappa={self.kappa}"


class Tracker(nn.Module):
    """A Gaussian tracker of a model: ``predict(mean, cov)`` and ``update(mean_pred, cov_pred, z)`` on
    any leading batch shape, by the EKF (``kind="ekf"``) or the UKF (``kind="ukf"``; ``alpha``,
    ``beta``, ``kappa`` as :class:`UnscentedTransform`)."""

    def __init__(self, model, kind: str = "ekf", **unscented):
        super().__init__()
        if kind not in TRACKERS:
            raise ArgumentError(f"covariance: expected one of {TRACKERS}, got {kind!r}")
        if unscented and kind != "ukf":
            raise ArgumentError(f"{sorted(unscented)}: sigma-point settings need kind='ukf', got {kind!r}")
        self.model, self.kind = model, kind
        self.unscented = (
            UnscentedTransform(model.state_dim, dtype=model.dtype, device=model.device, **unscented)
            if kind == "ukf"
            else None
        )

    def predict(self, mean: torch.Tensor, cov: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """``(..., d)``, ``(..., d, d)`` -> predicted mean and covariance."""
        if self.unscented is None:
            return ekf_predict(self.model, mean, cov)
        return self.unscented.predict(self.model, mean, cov)

    def update(self, mean_pred: torch.Tensor, cov_pred: torch.Tensor, z: torch.Tensor):
        """Mean ``(..., d)``, covariance ``(..., d, d)`` and ``log N(z; z_hat, S)`` ``(...)``."""
        if self.unscented is None:
            return ekf_update(self.model, mean_pred, cov_pred, z)
        return self.unscented.update(self.model, mean_pred, cov_pred, z)

    def extra_repr(self) -> str:
        return f"kind={self.kind!r}"


def tracker(model, kind: str = "ekf", **unscented) -> Tracker:
    """The EKF or UKF tracker of ``model`` (``kind``: ``"ekf"`` or ``"ukf"``)."""
    return Tracker(model, kind, **unscented)


__all__ = [
    "kalman_update",
    "kalman_update_scalar_support",
    "ekf_predict",
    "ekf_update",
    "UnscentedTransform",
    "Tracker",
    "tracker",
    "TRACKERS",
]
