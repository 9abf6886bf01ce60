"""Ensemble Kalman filters: stochastic EnKF, square-root ETKF and the local LETKF.

An ensemble of ``N`` members per trial, ``X (B, N, d)``, stands for the belief. Each step

1. **forecast**: every member moves through the model's transition (``model.sample_transition``,
   model noise included: a model without noise, Lorenz-96 by default, gives a deterministic
   forecast); the forecast anomalies ``A = X_f - xbar`` are multiplied by ``inflation >= 1``
   (or, with ``inflate="analysis"``, the analysis anomalies after step 2, as DAPPER does; an
   optional random rotation, ``rotate=True``, then mixes the analysis members);
2. **analysis**: each member is measured with the model's (possibly nonlinear) ``h``
   (``model.measure``; no Jacobian), ``Y = h(X_f) - ybar`` are the measurement anomalies and
   ``delta = z - ybar`` the innovation. Everything is whitened by the model's noise ``R = L L^T``
   (``Y_w = Y L^{-T}``, ``delta_w = L^{-1} delta``) and the update is written in the
   ``N``-dimensional ensemble space with the matrix ``M = (N - 1) I_N + Y_w Y_w^T`` (``(B, N, N)``).
   It is solved there when ``N <= m``, else through the ``m x m`` matrix
   ``Y_w^T Y_w + (N - 1) I_m`` (the same numbers up to round-off, at the cost of the smaller one: a
   large ensemble of a few observations never forms ``N x N`` matrices). With ``P_f = A^T A / (N - 1)`` this is the
   Kalman update with the ensemble's
   covariance: ``K = P_f H^T (H P_f H^T + R)^{-1} = A^T M^{-1} Y_w L^{-1}`` (push-through identity,
   ``H A^T`` replaced by ``Y^T``).

The three filters differ in how members are moved:

* :class:`EnsembleKalmanFilter` (perturbed observations, Burgers et al. 1998): member ``i`` takes
  ``x_i + A^T M^{-1} Y_w (delta_w - y_w,i + xi_i)``, ``xi_i ~ N(0, I_m)``;
* :class:`EnsembleTransformKalmanFilter` (Bishop et al. 2001; Hunt et al. 2007): the mean moves by
  ``A^T wbar``, ``wbar = M^{-1} Y_w delta_w``, and the anomalies by the symmetric square root
  ``W = sqrt(N - 1) M^{-1/2}`` (one ``eigh`` of an ``N x N`` matrix per trial); ``W 1 = 1``, so the
  analysis ensemble's mean is the Kalman mean (mean-preserving) and its sample covariance is
  ``A^T M^{-1} A``, the Kalman covariance of the forecast ensemble;
* :class:`LocalEnsembleTransformKalmanFilter` (Hunt et al. 2007): one ETKF analysis per state
  coordinate ``i``, in which observation ``j``'s precision is tapered by the Gaspari-Cohn
  function ``rho(dist(i, j))`` (compact support: zero beyond ``radius``); only the observations
  with ``rho > 0`` enter (at most ``K`` per coordinate, gathered once), and the ``d`` local
  analyses run as one batch ``(B, d, N, N)``.

**Missing observations.** A NaN in ``z (B, m)`` marks a coordinate not observed in that trial: its
rows of ``Y`` and ``delta`` (and of the EnKF's perturbations) are zero and its noise is taken as
unit, so it carries no information; a step with nothing observed is a pure forecast.

**Evidence.** The log-evidence increment is the Gaussian approximation from the forecast ensemble,
``log N(z; ybar, Y^T Y / (N - 1) + R)`` over the observed coordinates (computed in ensemble space
by the determinant lemma). It is exact only for a linear-Gaussian model with an infinite ensemble;
hence :attr:`estimates_evidence` is ``False`` (the runner does not score it).

The state is a :class:`~torchflow.filters.ParticleState` with uniform weights (``ESS = N``), the
estimate being the analysis ensemble's mean.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Tuple

import torch

from torchflow.core import linalg
from torchflow.core.checks import check_count, check_number
from torchflow.core.covariances import sample_prior
from torchflow.core.errors import ArgumentError, ArgumentTypeError
from torchflow.core.geometry import DIAGONAL_NOISE, check_radius, local_observations
from torchflow.core.random import uniform
from torchflow.filters.base import Filter, ParticleState

__all__ = [
    "EnsembleKalmanFilter",
    "EnsembleTransformKalmanFilter",
    "LocalEnsembleTransformKalmanFilter",
    "mean_preserving_rotation",
]

#: which anomalies the multiplicative inflation scales
INFLATE = ("forecast", "analysis")
_LOG_2PI = math.log(2.0 * math.pi)


def mean_preserving_rotation(batch: int, n: int, *, dtype, device, generator=None) -> torch.Tensor:
    """``(batch, n, n)`` random orthogonal matrices ``R`` with ``R 1 = 1``: a Haar-distributed rotation
    of the ``n - 1``-dimensional complement of the ones vector (QR of a Gaussian matrix, signs fixed by
    R's diagonal), embedded through the Helmert basis. Applied to an ensemble's anomalies it keeps
    their mean (zero) and their sample covariance, and mixes the members (the random rotation of
    square-root filters that DAPPER's ``rot=True`` applies, against members stuck as outliers)."""
    # the Helmert basis U (n, n - 1): column j is (1, .., 1, -(j + 1), 0, .., 0) / sqrt((j + 1)(j + 2))
    j = torch.arange(n - 1, device=device)
    U = torch.triu(torch.ones(n, n - 1, dtype=dtype, device=device))
    U[j + 1, j] = -(j + 1).to(dtype)
    U = U / ((j + 1) * (j + 2)).to(dtype).sqrt()
    G = linalg.standard_normal((batch, n - 1, n - 1), dtype=dtype, device=device, generator=generator)
    Q, Rq = torch.linalg.qr(G)
    Q = Q * torch.sign(Rq.diagonal(dim1=-2, dim2=-1)).unsqueeze(-2)
    return U @ Q @ U.transpose(0, 1) + 1.0 / n


def rotate_anomalies(X: torch.Tensor, generator=None) -> torch.Tensor:
    """The ensemble ``X (B, N, d)`` with its anomalies mixed by :func:`mean_preserving_rotation`
    (one rotation per trial): the same mean and sample covariance."""
    R = mean_preserving_rotation(X.shape[0], X.shape[1], dtype=X.dtype, device=X.device, generator=generator)
    xbar = X.mean(1, keepdim=True)
    return xbar + R @ (X - xbar)


def local_transport(X: torch.Tensor, weights: torch.Tensor, how: str = "systematic", generator=None) -> torch.Tensor:
    """Equally weighted members ``(B, N, d)`` from members ``X (B, N, d)`` with one set of normalised
    weights per coordinate ``weights (B, N, d)`` (each column sums to 1). ``"systematic"``: each
    coordinate's members resampled systematically with one uniform per trial (``generator``), so
    neighbouring coordinates with similar weights keep the same ancestors (Penny & Miyoshi's local
    particle filter); ``"quantile"``: member ``i``'s coordinate moves to the weighted members' quantile at
    its own rank, ``(rank_i + 1/2) / N``, linear between their mid-point cumulative weights (the
    monotone, one-dimensional optimal transport map: equal weights leave every member in place, to
    round-off, and draw nothing)."""
    B, N, d = X.shape
    W = weights.transpose(1, 2).contiguous()  # (B, d, N)
    V = X.transpose(1, 2)  # (B, d, N)
    if how == "systematic":
        u = uniform((B, 1), dtype=X.dtype, device=X.device, generator=generator).unsqueeze(-1)
        points = (torch.arange(N, dtype=X.dtype, device=X.device).view(1, 1, N) + u) / N  # (B, 1, N)
        cdf = W.cumsum(-1)
        cdf[..., -1] = 1.0
        ancestors = torch.searchsorted(cdf, points.expand(B, d, N).contiguous()).clamp_max(N - 1)  # (B, d, N)
        return V.gather(-1, ancestors).transpose(1, 2)
    values, order = V.sort(-1)
    w = W.gather(-1, order)
    mid = w.cumsum(-1) - 0.5 * w  # the weighted members' mid-point cumulative weights (increasing)
    q = (order.argsort(-1).to(X.dtype) + 0.5) / N  # each member's own rank's quantile level
    hi = torch.searchsorted(mid.contiguous(), q.contiguous()).clamp(1, N - 1)
    m0, m1 = mid.gather(-1, hi - 1), mid.gather(-1, hi)
    v0, v1 = values.gather(-1, hi - 1), values.gather(-1, hi)
    t = ((q - m0) / (m1 - m0).clamp_min(torch.finfo(X.dtype).tiny)).clamp(0.0, 1.0)
    return torch.lerp(v0, v1, t).transpose(1, 2)


@dataclass
class _Whitened:
    """The forecast ensemble seen through the measurement, whitened by R (module docstring).

    Attributes:
        Y: ``(B, N, m)`` whitened measurement anomalies ``(h(x_i) - ybar) L^{-T}`` (unobserved
            columns zero).
        delta: ``(B, m)`` whitened innovation ``L^{-1} (z - ybar)`` (unobserved entries zero).
        logdet_R: ``(B,)`` log det of R over the observed coordinates.
        n_obs: ``(B,)`` number of observed coordinates.
        observed: ``(B, m)`` bool mask.
    """

    Y: torch.Tensor
    delta: torch.Tensor
    logdet_R: torch.Tensor
    n_obs: torch.Tensor
    observed: torch.Tensor
    scale: Optional[torch.Tensor] = None  # (B, m): R's diagonal's square root (a diagonal R; unobserved: 1)
    images: Optional[torch.Tensor] = None  # (B, N, d): the states measured, where they are not the members


class _EnsembleFilter(Filter):
    """Forecast, inflation, whitening and the Gaussian evidence shared by the ensemble filters;
    subclasses give :meth:`analysis`."""

    uses_particles = True
    uses_randomness = True  # the initial ensemble (and the EnKF's perturbations, the model noise)
    diagonal_prior = True  # the initial ensemble is drawn with the variances alone
    random_stream = "ensemble_kalman"  # one family: the filters start from the same ensemble
    estimates_evidence = False  # a Gaussian approximation from the ensemble (module docstring)
    nonfinite_hint = (
        "the members diverged: an inflation too large, or dynamics that blow up at the model's time "
        "step (a smaller dt or more substeps)"
    )

    def __init__(
        self,
        model,
        *,
        n_particles: int = 20,
        inflation: float = 1.0,
        inflate: str = "forecast",
        rotate: bool = False,
        validate: bool = True,
        name: Optional[str] = None,
    ):
        super().__init__(model, validate=validate, name=name)
        #: ensemble members per trial N (>= 2: anomalies need two members)
        self.n_particles = check_count(
            "n_particles", n_particles, minimum=2, hint=" (ensemble members; anomalies need at least two)"
        )
        #: multiplicative inflation of the forecast anomalies (>= 1; 1: none)
        self.inflation = check_number(
            "inflation",
            inflation,
            lambda v: v >= 1,
            "a finite number >= 1 (multiplicative inflation of the forecast anomalies)",
        )
        if inflate not in INFLATE:
            raise ArgumentError(
                f"inflate: expected one of {INFLATE} (which anomalies `inflation` multiplies), got {inflate!r}"
            )
        #: ``"forecast"``: the forecast anomalies are inflated before the analysis; ``"analysis"``: the
        #: analysis anomalies after it (DAPPER's ``infl``, applied with its ``rot`` in its post-processing)
        self.inflate = inflate
        if not isinstance(rotate, bool):
            raise ArgumentTypeError(f"rotate: expected True or False, got {rotate!r}")
        #: rotate the analysis anomalies by a random orthogonal matrix that keeps the mean
        # (:func:`mean_preserving_rotation`)
        self.rotate = rotate

    def _resolve_n(self, n_particles):
        return (
            self.n_particles
            if n_particles is None
            else check_count("n_particles", n_particles, minimum=2, hint=" (ensemble members)")
        )

    def bytes_per_trial(self, n_particles=None):
        N, d, m = self._resolve_n(n_particles), self.model.state_dim, self.model.obs_dim
        return 8 * (6 * N * d + 4 * N * m + 6 * N * N + (m * m if self._dense_noise else 0))

    @property
    def _dense_noise(self) -> bool:
        return self.model.structure.measurement_noise not in DIAGONAL_NOISE

    def check_model(self) -> None:
        """The measurement noise R must be positive definite: the analysis whitens by it."""
        super().check_model()
        self.require_definite(
            "measurement",
            "ensemble Kalman filters whiten the measurements by R. Give the model "
            "a positive definite measurement noise",
        )

    # ---- contract ------------------------------------------------------------------------------
    def init(self, mean, cov, n_particles=None, generator=None) -> ParticleState:
        """N members per trial drawn from the prior ``N(mean (B, d), cov)``: ``cov (B, d, d)`` or a
        :class:`~torchflow.core.covariances.DiagonalCovariance` (variances ``(B, d)``)."""
        N = self._resolve_n(n_particles)
        X = sample_prior(mean, cov, N, generator)  # (B, N, d)
        return self._state(X, torch.zeros_like(mean[:, 0]), 0)

    def step(self, state: ParticleState, z: torch.Tensor, generator: Optional[torch.Generator] = None) -> ParticleState:
        """Forecast every member, inflate the anomalies, analyse with ``z (B, m)`` (NaN: not observed)."""
        xbar, A = self.forecast(state, generator)
        w = self.whiten(xbar + A, xbar.squeeze(1), z)
        Xa, ll = self.analysis(xbar, A, w, generator)
        if self.inflate == "analysis" and self.inflation != 1.0:
            ma = Xa.mean(1, keepdim=True)
            Xa = ma + self.inflation * (Xa - ma)
        if self.rotate:
            Xa = rotate_anomalies(Xa, generator)
        return self._state(Xa, ll, state.step + 1)

    def forecast(self, state: ParticleState, generator: Optional[torch.Generator]) -> Tuple[torch.Tensor, torch.Tensor]:
        """Every member through the model's transition: the forecast mean ``xbar (B, 1, d)`` and the
        anomalies ``A (B, N, d)``, multiplied by :attr:`inflation` (the forecast members are ``xbar + A``)."""
        Xf = self.model.sample_transition(state.particles, generator)  # (B, N, d)
        xbar = Xf.mean(1, keepdim=True)  # (B, 1, d)
        A = Xf - xbar
        return xbar, (A * self.inflation if self.inflation != 1.0 and self.inflate == "forecast" else A)

    def forecast_evidence(self, w: "_Whitened") -> torch.Tensor:
        """The Gaussian approximation ``(B,)`` of ``log p(z_k | z_{1:k-1})`` from the forecast ensemble
        seen through the measurement (:meth:`log_evidence`), for analyses that do not factorise ``M``
        themselves."""
        _, maha, logdet_M = _gain_solver(w.Y, w.delta)
        return self.log_evidence(w, maha, logdet_M)

    def analysis(
        self, xbar: torch.Tensor, A: torch.Tensor, w: _Whitened, generator
    ) -> Tuple[torch.Tensor, torch.Tensor]:
        """Analysis ensemble ``(B, N, d)`` and log-evidence increment ``(B,)`` from the forecast mean
        ``xbar (B, 1, d)``, (inflated) anomalies ``A (B, N, d)`` and the whitened measurement ``w``."""
        raise NotImplementedError

    # ---- helpers -------------------------------------------------------------------------------
    @staticmethod
    def _state(X: torch.Tensor, ll: torch.Tensor, step: int) -> ParticleState:
        B, N = X.shape[:2]
        lw = torch.full((B, N), -math.log(N), dtype=X.dtype, device=X.device)
        return ParticleState(
            particles=X,
            log_weights=lw,
            estimate=X.mean(1),
            ess=torch.full_like(ll, float(N)),
            log_evidence_increment=ll,
            resampled=torch.zeros(B, dtype=torch.bool, device=X.device),
            step=step,
        )

    def whiten(self, Xf: torch.Tensor, xbar: torch.Tensor, z: torch.Tensor) -> _Whitened:
        """Measure the forecast members ``Xf (B, N, d)`` and whiten anomalies and innovation by R
        (evaluated at the forecast mean ``xbar (B, d)`` when it depends on the state); NaN entries
        of ``z (B, m)`` are unobserved (zero rows, unit noise)."""
        model = self.model
        Yf = model.measure(Xf)  # (B, N, m)
        ybar = Yf.mean(1)
        observed = ~torch.isnan(z)
        keep = observed.to(Yf.dtype)
        Y = (Yf - ybar.unsqueeze(1)) * keep.unsqueeze(1)
        delta = torch.where(observed, z - ybar, torch.zeros_like(ybar))
        noise, scale = model.structure.measurement_noise, model.structure.measurement_noise_scale
        if noise in DIAGONAL_NOISE:
            if noise == "scalar" and scale is not None:  # R = r I declared: no (m, m) matrix formed
                r = torch.full_like(z, scale)
            else:
                r = self._measurement_variance(xbar).expand_as(z)
            r = torch.where(observed, r, torch.ones_like(r))  # (B, m)
            s = r.sqrt()
            Y, delta, logdet = Y / s.unsqueeze(1), delta / s, r.log().sum(-1)
            return _Whitened(Y, delta, logdet, keep.sum(-1), observed, s)
        else:  # dense: unobserved rows and columns replaced by the identity's
            both = observed.unsqueeze(-1) & observed.unsqueeze(-2)
            eye = torch.eye(z.shape[-1], dtype=z.dtype, device=z.device)
            L = linalg.safe_cholesky(torch.where(both, self._measurement_cov(xbar), eye))  # (B, m, m)
            Y = linalg.solve_triangular(L.transpose(-1, -2), Y, upper=True, left=False)  # Y L^{-T}
            delta = torch.linalg.solve_triangular(L, delta.unsqueeze(-1), upper=False).squeeze(-1)
            logdet = linalg.chol_logdet(L)
        return _Whitened(Y, delta, logdet, keep.sum(-1), observed)

    def _measurement_variance(self, xbar: torch.Tensor) -> torch.Tensor:
        """R's diagonal (a diagonal R), at the forecast mean ``xbar (B, d)`` where it depends on the state."""
        noise = self.model.structure.measurement_noise
        return self.model.measurement_variance(xbar if noise.startswith("state_dependent") else None)

    def _measurement_cov(self, xbar: torch.Tensor) -> torch.Tensor:
        """R, at the forecast mean ``xbar (B, d)`` where it depends on the state."""
        noise = self.model.structure.measurement_noise
        return self.model.measurement_cov(xbar) if noise.startswith("state_dependent") else self.model.measurement_cov()

    @staticmethod
    def log_evidence(w: _Whitened, maha: torch.Tensor, logdet_M: torch.Tensor) -> torch.Tensor:
        """``log N(z; ybar, Y^T Y / (N - 1) + R)`` ``(B,)`` over the observed coordinates, from
        ``maha = delta^T S^{-1} delta`` (:func:`_gain_solver`) and ``log det M``: with
        ``S = L (I + Y_w^T Y_w / (N - 1)) L^T``, ``log det S = log det R + log det M - N log(N - 1)``."""
        N = w.Y.shape[-2]
        logdet_S = w.logdet_R + logdet_M - N * math.log(N - 1)
        return -0.5 * (maha + logdet_S + w.n_obs * _LOG_2PI)

    def extra_repr(self) -> str:
        return (
            f"n_particles={self.n_particles}, inflation={self.inflation:g}"
            + (f", inflate={self.inflate!r}" if self.inflate != "forecast" else "")
            + (", rotate=True" if self.rotate else "")
        )


class EnsembleKalmanFilter(_EnsembleFilter):
    """Stochastic ensemble Kalman filter with perturbed observations (Evensen 1994; Burgers, van
    Leeuwen & Evensen 1998).

    Member ``i`` is updated with its own perturbed observation ``z + eps_i``, ``eps_i ~ N(0, R)``:
    ``x_i^a = x_i^f + K (z + eps_i - h(x_i^f))`` with the ensemble's gain
    ``K = A^T M^{-1} Y_w L^{-1}`` (module docstring), solved by one Cholesky factorisation of the
    ``N x N`` matrix ``M`` per trial. The analysis mean equals the Kalman mean of the forecast
    ensemble only in expectation over the perturbations.

    Args:
        model: a Gaussian-form model (``measure``, ``measurement_cov``, ``sample_transition``).
        n_particles: ensemble members N (>= 2).
        inflation: multiplicative inflation of the anomalies (>= 1; 1: none).
        inflate: which anomalies ``inflation`` multiplies: ``"forecast"`` (before the analysis) or
            ``"analysis"`` (after it, as DAPPER's ``infl``: its settings then mean the same here).
        rotate: mix the analysis anomalies by a random orthogonal matrix that keeps the mean and
            the sample covariance (:func:`mean_preserving_rotation`; DAPPER's ``rot=True``).
        validate, name: as :class:`~torchflow.filters.Filter`.

    Shapes: ensemble ``(B, N, d)``, observations ``z (B, m)`` (NaN: not observed).
    """

    def analysis(self, xbar, A, w, generator):
        xi = linalg.standard_normal(w.Y.shape, dtype=w.Y.dtype, device=w.Y.device, generator=generator)
        D = w.delta.unsqueeze(1) - w.Y + xi * w.observed.to(xi.dtype).unsqueeze(1)  # (B, N, m) member innovations
        solve, maha, logdet_M = _gain_solver(w.Y, w.delta)
        Xa = xbar + A + D @ solve(A)  # member i: x_i + A^T M^{-1} Y_w d_i
        return Xa, self.log_evidence(w, maha, logdet_M)


def _gain_solver(Y: torch.Tensor, delta: torch.Tensor):
    """``(solve, maha, log det M)`` for whitened anomalies ``Y (..., N, k)`` and innovation
    ``delta (..., k)``, with ``M = (N - 1) I_N + Y Y^T`` and ``b = Y delta``; ``solve(A (..., N, p))``
    is ``Y^T M^{-1} A (..., k, p)``; ``maha = delta^T (I + Y^T Y / (N - 1))^{-1} delta``, the
    innovation's whitened Mahalanobis term. One Cholesky factorisation of the smaller of ``M``
    (``N x N``: ``maha = |delta|^2 - b^T M^{-1} b``) and ``S = Y^T Y + (N - 1) I_k`` (``k x k``:
    ``maha = (N - 1) delta^T S^{-1} delta``, computed as such: with a tiny R both ``|delta|^2`` and
    ``b^T M^{-1} b`` are huge and their difference would lose every digit; push-through
    ``Y^T M^{-1} = S^{-1} Y^T``, ``log det M = (N - k) log(N - 1) + log det S``)."""
    N, k = Y.shape[-2:]
    c = float(N - 1)
    Yt = Y.transpose(-1, -2)
    if N <= k:
        L = linalg.cholesky_or_nan(_shifted_gram(Y, c))  # (..., N, N); c I + PSD: definite unless Y is not finite
        b = Y @ delta.unsqueeze(-1)
        maha = delta.square().sum(-1) - (b * linalg.chol_solve(L, b)).sum((-2, -1))
        return (lambda A: Yt @ linalg.chol_solve(L, A)), maha, linalg.chol_logdet(L)
    L = linalg.cholesky_or_nan(_shifted_gram(Yt, c))  # (..., k, k)
    dl = delta.unsqueeze(-1)
    maha = c * (dl * linalg.chol_solve(L, dl)).sum((-2, -1))  # directly: no |delta|^2 - b^T M^{-1} b
    return (lambda A: linalg.chol_solve(L, Yt @ A)), maha, (N - k) * math.log(c) + linalg.chol_logdet(L)


def _shifted_gram(Y: torch.Tensor, c: float) -> torch.Tensor:
    """``Y Y^T + c I`` for ``Y (..., n, k)`` -> ``(..., n, n)``."""
    M = Y @ Y.transpose(-1, -2)
    M.diagonal(dim1=-2, dim2=-1).add_(c)
    return M


def _transform(Y: torch.Tensor, delta: torch.Tensor, A: torch.Tensor):
    """The ETKF's analysis in weight space: ``(A^T (wbar 1^T + W))^T (..., N, p)`` (the analysis
    members about the forecast mean), ``maha`` (as :func:`_gain_solver`) and ``log det M``, for whitened anomalies
    ``Y (..., N, k)``, innovation ``delta (..., k)`` and state anomalies ``A (..., N, p)``;
    ``M = (N - 1) I + Y Y^T``, ``wbar = M^{-1} Y delta``, ``W = sqrt(N - 1) M^{-1/2}`` (symmetric).

    With ``N <= k``: one ``eigh`` of ``M`` (``N x N``). Otherwise of ``Y^T Y = V diag(lam) V^T``
    (``k x k``): ``M`` is ``N - 1`` on the complement of ``Y``'s columns, so
    ``W = I + Y V diag(g(lam)) V^T Y^T`` with ``g(s) = (sqrt(c / (c + s)) - 1) / s
    = -1 / (sqrt(c + s) (sqrt(c) + sqrt(c + s)))`` (``c = N - 1``; finite at ``s = 0``) and
    ``wbar = Y V diag(1 / (lam + c)) V^T delta``."""
    N, k = Y.shape[-2:]
    c = float(N - 1)
    if N <= k:
        lam, V = linalg.eigh(_shifted_gram(Y, c))  # lam >= c > 0 (threaded over a large CPU batch)
        Vt = V.transpose(-1, -2)
        wbar = V @ ((Vt @ (Y @ delta.unsqueeze(-1))) / lam.unsqueeze(-1))  # (..., N, 1)
        W = (V * (math.sqrt(c) * lam.rsqrt()).unsqueeze(-2)) @ Vt
        logdet = lam.log().sum(-1)
        out = W @ A
        maha = delta.square().sum(-1) - ((Y @ delta.unsqueeze(-1)) * wbar).sum((-2, -1))
    else:
        lam, V = linalg.eigh(Y.transpose(-1, -2) @ Y)  # (..., k), (..., k, k)
        lam = lam.clamp_min(0.0)
        YV = Y @ V  # (..., N, k)
        Vd = V.transpose(-1, -2) @ delta.unsqueeze(-1)  # (..., k, 1)
        wbar = YV @ (Vd / (lam + c).unsqueeze(-1))
        maha = (c * Vd.squeeze(-1).square() / (lam + c)).sum(-1)  # directly (see _gain_solver)
        sc = (lam + c).sqrt()
        g = -1.0 / (sc * (math.sqrt(c) + sc))
        out = A + YV @ (g.unsqueeze(-1) * (YV.transpose(-1, -2) @ A))
        logdet = (N - k) * math.log(c) + (lam + c).log().sum(-1)
    return out + wbar.transpose(-1, -2) @ A, maha, logdet


class EnsembleTransformKalmanFilter(_EnsembleFilter):
    """Ensemble transform Kalman filter: the deterministic square-root filter in ensemble space
    (Bishop, Etherton & Majumdar 2001; the symmetric form of Hunt, Kostelich & Szunyogh 2007).

    ``x_i^a = xbar + A^T (wbar + W e_i)`` with ``wbar = M^{-1} Y_w delta_w`` and the symmetric
    square root ``W = sqrt(N - 1) M^{-1/2}`` (module docstring). The analysis ensemble's mean and
    sample covariance are exactly the Kalman update of the forecast ensemble's sample mean and
    covariance (for a linear h; for a nonlinear one, with ``H P_f`` estimated from the members).

    Args:
        model: a Gaussian-form model (``measure``, ``measurement_cov``, ``sample_transition``).
        n_particles: ensemble members N (>= 2).
        inflation: multiplicative inflation of the anomalies (>= 1; 1: none).
        inflate: which anomalies ``inflation`` multiplies: ``"forecast"`` (before the analysis) or
            ``"analysis"`` (after it, as DAPPER's ``infl``: its settings then mean the same here).
        rotate: mix the analysis anomalies by a random orthogonal matrix that keeps the mean and
            the sample covariance (:func:`mean_preserving_rotation`; DAPPER's ``rot=True``).
        validate, name: as :class:`~torchflow.filters.Filter`.

    Shapes: ensemble ``(B, N, d)``, observations ``z (B, m)`` (NaN: not observed).
    """

    def analysis(self, xbar, A, w, generator):
        inc, maha, logdet_M = _transform(w.Y, w.delta, A)
        return xbar + inc, self.log_evidence(w, maha, logdet_M)


class LocalEnsembleTransformKalmanFilter(_EnsembleFilter):
    """Local ensemble transform Kalman filter (Hunt, Kostelich & Szunyogh 2007): one ETKF analysis
    per state coordinate, with the observations' precision tapered by distance.

    For coordinate ``i`` the whitened anomalies and innovation of observation ``j`` are scaled by
    ``sqrt(rho_ij)``, ``rho_ij = gaspari_cohn(dist(i, j), radius)`` (R^{-1} tapered: R must be
    diagonal), giving ``M_i = (N - 1) I + Y_i Y_i^T``, ``wbar_i`` and ``W_i`` as in the ETKF;
    coordinate ``i`` of member ``n`` is then ``xbar_i + sum_k (wbar_i + W_i e_n)_k A_ki``. The
    observations with ``rho_ij > 0`` (at most ``K`` per coordinate) are gathered once at
    construction, and the ``d`` analyses run as one batch ``(B, d, N, N)``. With
    ``radius = inf`` every ``M_i`` is the ETKF's and the filter is the ETKF. The log-evidence
    increment is the ETKF's global Gaussian approximation (not localised).

    Args:
        model: a Gaussian-form model with a diagonal measurement noise (declared ``scalar``,
            ``diagonal`` or ``state_dependent_diagonal``).
        n_particles: ensemble members N (>= 2).
        inflation: multiplicative inflation of the anomalies (>= 1; 1: none).
        inflate: which anomalies ``inflation`` multiplies: ``"forecast"`` (before the analysis) or
            ``"analysis"`` (after it, as DAPPER's ``infl``: its settings then mean the same here).
        rotate: mix the analysis anomalies by a random orthogonal matrix that keeps the mean and
            the sample covariance (:func:`mean_preserving_rotation`; DAPPER's ``rot=True``).
        radius: localisation radius (> 0, ``inf`` allowed): the distance beyond which an
            observation has no influence; the Gaspari-Cohn half-width is ``radius / 2``. The default
            suits Lorenz-96 (d = 40, all observed, N = 20; see the benchmark's results).
        distances: ``(d, m)`` distances between state coordinates and observations; ``None``: a
            periodic 1-D domain of ``d`` sites (Lorenz-96), observation ``j`` at the site
            ``model.observed[j]`` (the state coordinate it reads), or at site ``j`` when ``m = d``
            and the model has no ``observed``.
        local_chunk: run the ``d`` local analyses in blocks of this many coordinates, bounding the
            ``(B, c, N, K)`` and ``(B, c, N, N)`` intermediates (the same numbers up to round-off;
            ``None``: all at once, or as the experiment runner's memory budget sets it).
        validate, name: as :class:`~torchflow.filters.Filter`.

    Shapes: ensemble ``(B, N, d)``, observations ``z (B, m)`` (NaN: not observed).
    """

    def __init__(
        self,
        model,
        *,
        n_particles: int = 20,
        inflation: float = 1.0,
        radius: float = 15.0,
        distances: Optional[torch.Tensor] = None,
        local_chunk: Optional[int] = None,
        inflate: str = "forecast",
        rotate: bool = False,
        validate: bool = True,
        name: Optional[str] = None,
    ):
        super().__init__(
            model,
            n_particles=n_particles,
            inflation=inflation,
            inflate=inflate,
            rotate=rotate,
            validate=validate,
            name=name,
        )
        #: the local analyses run in blocks of this many coordinates (``None``: all d at once); the
        #: experiment runner sets it from the memory budget when one trial exceeds it (:meth:`plan_memory`)
        self.local_chunk = (
            None
            if local_chunk is None
            else check_count("local_chunk", local_chunk, hint=" (coordinates per block of local analyses) or None")
        )
        self._local_chunk_given = self.local_chunk is not None  # the runner's plan leaves a given one alone
        self.radius = check_radius(radius)
        if model.structure.measurement_noise not in DIAGONAL_NOISE:
            raise ArgumentTypeError(
                f"{self.name}: model: the LETKF tapers each observation's precision, which needs a diagonal "
                f"measurement noise (declared scalar, diagonal or state_dependent_diagonal); "
                f"{type(model).__name__} declares {model.structure.measurement_noise!r}. Use the ETKF or the EnKF"
            )
        self._set_neighbours(*local_observations(model, self.radius, distances))

    def _set_neighbours(self, taper: torch.Tensor, index: torch.Tensor) -> None:
        """``(d, K)`` the observations within reach of each coordinate, and their tapers."""
        model = self.model
        self.register_buffer("local_index", index.to(model.device), persistent=False)
        self.register_buffer("local_taper", taper.sqrt().to(model.dtype).to(model.device), persistent=False)

    @property
    def local_obs(self) -> int:
        """K: the most observations that one local analysis reads."""
        return self.local_index.shape[1]

    def _local_bytes(self, N: int) -> int:
        """Bytes of one coordinate's local analysis (its tapered anomalies and ``N x N`` matrices)."""
        return 8 * N * (2 * self.local_obs + 4 * N)

    def bytes_per_trial(self, n_particles=None):
        N, d = self._resolve_n(n_particles), self.model.state_dim
        return super().bytes_per_trial(n_particles) + min(d, self.local_chunk or d) * self._local_bytes(N)

    def plan_memory(self, budget_bytes: float, n_particles: Optional[int] = None) -> Optional[int]:
        """Set :attr:`local_chunk` so that one trial's local analyses fit ``budget_bytes`` with the
        rest of its step (``None`` when all d fit at once); returns it. Used by the experiment runner.
        A ``local_chunk`` given at construction is kept (returns ``None``: nothing planned)."""
        if self._local_chunk_given:
            return None
        N, d = self._resolve_n(n_particles), self.model.state_dim
        rest = super().bytes_per_trial(N)
        fit = (budget_bytes - rest) // self._local_bytes(N)
        self.local_chunk = None if fit >= d else max(1, int(fit))
        return self.local_chunk

    def describe_blocks(self, chunk: int) -> str:
        return f"{chunk} of its {self.model.state_dim} coordinates' local analyses"

    def analysis(self, xbar, A, w, generator):
        idx, s = self.local_index, self.local_taper.to(w.Y.dtype)
        d = idx.shape[0]
        c = min(d, self.local_chunk or d)
        parts = []
        for lo in range(0, d, c):  # blocks of coordinates (memory), not of trials or members
            i, si = idx[lo : lo + c], s[lo : lo + c]
            Yl = w.Y[:, :, i].permute(0, 2, 1, 3) * si.unsqueeze(1)  # (B, N, c, K) -> (B, c, N, K), tapered
            dl = w.delta[:, i] * si  # (B, c, K)
            Ad = A[:, :, lo : lo + c].transpose(1, 2).unsqueeze(-1)  # (B, c, N, 1): the coordinates' anomalies
            parts.append(_transform(Yl, dl, Ad)[0].squeeze(-1))  # (B, c, N)
        inc = parts[0] if len(parts) == 1 else torch.cat(parts, 1)
        # the evidence: the global (unlocalised) Gaussian approximation, one factorisation
        return xbar + inc.transpose(1, 2), self.forecast_evidence(w)

    def extra_repr(self) -> str:
        chunk = "" if self.local_chunk is None else f", local_chunk={self.local_chunk}"
        return super().extra_repr() + f", radius={self.radius:g}, local_obs={self.local_obs}{chunk}"
