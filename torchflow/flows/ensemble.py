"""Ensemble flows: flows whose drift is stated at the whole ensemble of members, for data
assimilation with deterministic dynamics.

A Daum-Huang flow (:mod:`~torchflow.flows.daum_huang`) is linearised at points with the model's
Jacobian; the flows here read the *members* instead, as the ensemble Kalman filters do: the
measurement of every member (``h(M(x_i))`` on the lag-one target, whitened by R) and the members'
own spread. They take the same route as every flow (:func:`~torchflow.flows.integrate_flow`,
``points="ensemble"``): at each pseudo-time step the flow states its coefficients
(:class:`~torchflow.flows.base.FlowCoefficients`: ``A x + b`` and, where the map has one, the
log-determinant of ``I + eps A``) for the current members and an :class:`EnsembleMeasurement`,
and the integrator moves every member by them over the schedule.

* :class:`LagOneFlow`: Daum & Huang's exact flow with the ensemble's Gaussian prior
  ``N(xbar, A0^T A0)`` and ``h(M(x)) ~ e + H x`` re-linearised at every step by the least-squares
  regression of the members' measurements on the members (:func:`regression_jacobian`): the
  coefficients are :func:`~torchflow.flows.daum_huang.daum_huang_coefficients` with the
  regression as the whitened Jacobian and the anomalies ``A0^T`` as the prior's square root
  (``d x N``: every product in the ensemble's span, no ``d x d`` system).
* :class:`LocalisedKalmanBucyFlow`: the deterministic ensemble Kalman-Bucy flow of Bergemann &
  Reich (2010) in pseudo-time, the members' cross-covariance tapered by a Gaspari-Cohn correlation
  of the distance between coordinate and observation; its drift is not affine in one member
  (``A = 0``, ``b`` per member) and no log-determinant is stated.
* :class:`KernelFlow`: the matrix-valued-kernel flow of Pulido & van Leeuwen (2019) with Hu & van
  Leeuwen's (2021) diagonal kernel, preconditioned (``b`` per member, no log-determinant).

The data-assimilation filters (:mod:`torchflow.filters.assimilation`) compose "flow, then forecast"
from these.

Shapes: members ``(B, N, d)``, observations ``(B, m)``, whitened measurements ``(B, N, m)``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, Optional

import torch

from torchflow.core import linalg
from torchflow.flows.base import FlowCoefficients, FlowPrior, ParticleFlow
from torchflow.flows.daum_huang import daum_huang_coefficients

#: the members' gather blocks of the localised drift: about this many numbers (cache-sized)
CACHE_ELEMENTS = 1 << 16


@dataclasses.dataclass
class WhitenedMembers:
    """The members' measurements, whitened by R (``R = I`` in these coordinates).

    The flows read these attributes only; the ensemble filters' own whitening (which also carries
    the evidence's terms) has them too.

    Attributes:
        Y: ``(B, N, m)`` whitened anomalies ``s^-1 (y_i - ybar)`` (unobserved: 0).
        delta: ``(B, m)`` whitened innovation of the mean ``s^-1 (z - ybar)`` (unobserved: 0).
        observed: ``(B, m)`` bool.
        scale: ``(B, m)`` the square roots ``s`` of R's diagonal (diagonal noise), or ``None``.
        images: ``(B, N, d)`` the states the measurement read (``M(x_i)`` on the lag-one target), or
            ``None``.
    """

    Y: torch.Tensor
    delta: torch.Tensor
    observed: torch.Tensor
    scale: Optional[torch.Tensor] = None
    images: Optional[torch.Tensor] = None


@dataclasses.dataclass
class EnsembleMeasurement:
    """What an ensemble flow reads of the measurement: ``z (B, m)`` and ``whiten(X) ->``
    :class:`WhitenedMembers` of members ``X (B, N, d)`` (on the lag-one target, ``h(M(x_i))``; the
    filter's own function, which knows the model and its noise). ``first``: the whitening of the
    members the flow starts from, when the filter computed it already (the forecast evidence);
    ``log_prob_terms(z, X) -> (B, N, m)``: the model's own per-observation log-density (for
    :class:`LocalisedKalmanBucyFlow`'s ``likelihood="model"``); ``transition``: the map ``M`` whose
    images the measurement reads (``None``: the identity)."""

    z: torch.Tensor
    whiten: Callable[[torch.Tensor], WhitenedMembers]
    first: Optional[WhitenedMembers] = None
    log_prob_terms: Optional[Callable] = None
    transition: Optional[Callable[[torch.Tensor], torch.Tensor]] = None
    support = None  # every coordinate (the flows' measured-coordinate reduction does not apply)

    def members(self, X: torch.Tensor, j: int) -> WhitenedMembers:
        """The whitened measurements of ``X`` at pseudo-time step ``j`` (step 0: :attr:`first`, if given)."""
        return self.first if (j == 0 and self.first is not None) else self.whiten(X)


def pseudo_inverse(S: torch.Tensor, n: int) -> torch.Tensor:
    """The pseudo-inverse of a symmetric positive semi-definite ``S (B, k, k)`` (a Gram matrix of
    ``n`` members): its eigenvalues below ``10 n eps`` times the largest are taken as zero. The
    reciprocal is taken only of the kept ones (a floored reciprocal in the other branch of a
    ``where`` would put ``0 * inf = NaN`` into gradients)."""
    evals, V = torch.linalg.eigh(linalg.symmetrize(S))
    kept = evals > evals[..., -1:] * (n * torch.finfo(S.dtype).eps * 10)
    inv = torch.where(kept, 1.0 / torch.where(kept, evals, torch.ones_like(evals)), torch.zeros_like(evals))
    return (V * inv.unsqueeze(-2)) @ V.transpose(-1, -2)


def ridge_solve(S: torch.Tensor, b: torch.Tensor, n: int) -> torch.Tensor:
    """``(S + delta I)^{-1} b`` for a symmetric positive semi-definite ``S (B, k, k)`` (a Gram matrix
    of ``n`` members) and ``b (B, k, p)``, with ``delta = 10 n eps trace(S)`` (at least
    ``sqrt(tiny)``): where :func:`pseudo_inverse` cuts the directions below ``10 n eps`` of the
    largest, this ridge damps them, smoothly, so that the gradient stays defined where members
    coincide (a known initial state: ``S = 0``) or eigenvalues repeat, which differentiating
    through an eigendecomposition is not (it divides by their gaps). Elsewhere the two agree to
    about ``10 n eps cond``."""
    tiny = torch.finfo(S.dtype).tiny ** 0.5
    delta = (S.diagonal(dim1=-2, dim2=-1).sum(-1) * (n * torch.finfo(S.dtype).eps * 10)).clamp_min(tiny)
    shifted = linalg.symmetrize(S) + delta[..., None, None] * torch.eye(S.shape[-1], dtype=S.dtype, device=S.device)
    return linalg.chol_solve(linalg.safe_cholesky(shifted), b)


def regression_jacobian(X: torch.Tensor, Y: torch.Tensor) -> torch.Tensor:
    """The ensemble's statistical linearisation ``H (B, m, d)``: the minimum-norm least-squares
    fit of the measurement anomalies ``Y (B, N, m)`` on the members' anomalies, ``Y ~ D H^T``
    (``D = X - xbar``). With more members than coordinates the ``d x d`` normal equations (a ridge
    solve: a gradient everywhere); else the ``N x N`` pseudo-inverse of ``D D^T``. Cost
    ``O(N d (N + m))``."""
    N, d = X.shape[1], X.shape[2]
    D = X - X.mean(1, keepdim=True)
    if N > d:  # shapes only; the N x N form's gradient is undefined at D D^T's repeated zero eigenvalues
        Dt = D.transpose(1, 2)
        return ridge_solve(Dt @ D, Dt @ Y, N).transpose(1, 2)
    C = pseudo_inverse(D @ D.transpose(1, 2), N) @ Y  # (B, N, m): H v = C^T D v
    return C.transpose(1, 2) @ D


def ensemble_prior(X: torch.Tensor, inflation: float = 1.0) -> FlowPrior:
    """The ensemble's Gaussian ``N(xbar, A0^T A0)`` as a :class:`~torchflow.flows.base.FlowPrior`
    of an ensemble flow: ``mean (B, 1, d)``, ``root = A0^T (B, d, N)`` with ``A0`` the anomalies
    over ``sqrt(N - 1)`` times ``inflation``, so ``root root^T`` is the sample covariance
    (inflated). No Cholesky factor is formed (``scale_tril`` is ``None``)."""
    xbar = X.mean(1, keepdim=True)
    A0 = (X - xbar) * (inflation / math.sqrt(X.shape[1] - 1))
    root = A0.transpose(1, 2)
    return FlowPrior(xbar, None, root=root, cols=root, cols_support=root)


class EnsembleFlow(ParticleFlow):
    """An ensemble flow (module docstring): :meth:`ensemble_coefficients` states the drift at the
    members for the :class:`EnsembleMeasurement`; :func:`~torchflow.flows.integrate_flow` with
    ``points="ensemble"`` (their default) steps it."""

    points = "ensemble"

    def ensemble_coefficients(
        self, X: torch.Tensor, measurement: EnsembleMeasurement, prior: FlowPrior, lam, eps, j: int
    ) -> FlowCoefficients:
        """Coefficients at pseudo-time ``lam`` (after the step ``eps``, the ``j``-th) for the members
        ``X (B, N, d)``: the drift ``A x + b`` shared by the members (``b (B, d)``, ``A (B, d, d)``
        or ``apply_A`` on stacked vectors ``(B, d, r)``) with ``log_det (B,)`` of ``I + eps A``;
        or, for a drift that is not affine in one member, ``b (B, N, d)`` per member with neither
        ``A`` nor ``apply_A`` (and ``log_det`` ``None``)."""
        raise NotImplementedError

    def coefficients_at(self, lin, prior, lam, eps):
        raise NotImplementedError(f"{type(self).__name__} is an ensemble flow: integrate it with points='ensemble'")


class LagOneFlow(EnsembleFlow):
    """Daum & Huang's exact flow on the ensemble's Gaussian prior, linearised by regression over
    the members (module docstring)::

        A = -1/2 P H^T (lam H P H^T + I)^{-1} H,   b = (I + 2 lam A) [(I + lam A) P H^T y + A xbar]

    (whitened: ``R = I``), ``P = A0^T A0`` (:func:`ensemble_prior`), ``H``
    (:func:`regression_jacobian`) of ``h(M(x_i))`` on the members at every step, ``y`` the whitened
    pseudo-measurement ``z - e``, ``e = ybar - H xbar``. ``linearisation="bundle"``: the regression
    over the mean plus the anomalies scaled by ``bundle`` (a finite-difference linearisation at the
    mean). ``log_det``: the Euler map's, exact (:func:`~torchflow.flows.daum_huang.daum_huang_coefficients`).
    """

    kernel = None

    def __init__(self, linearisation: str = "members", bundle: float = 1e-4):
        super().__init__()
        self.linearisation, self.bundle = linearisation, bundle

    def ensemble_coefficients(self, X, measurement, prior, lam, eps, j):
        mean = X.mean(1, keepdim=True)
        if self.linearisation == "bundle":  # h(M(.)) at the mean plus the anomalies scaled down
            w = measurement.whiten(mean + self.bundle * (X - mean))
            Y = w.Y / self.bundle  # ~ the anomalies' measurements, to first order at the mean
        else:
            w = measurement.members(X, j)
            Y = w.Y
        H = regression_jacobian(X, Y)  # (B, m, d) whitened
        # z - e, whitened: z - (ybar - H xbar) = delta + H xbar (unobserved: zero)
        y = w.delta + linalg.matvec(H, mean.squeeze(1)) * w.observed.to(X.dtype)
        root = prior.root  # (B, d, N): P = root root^T
        return daum_huang_coefficients(H, y, root, prior.mean.squeeze(1), lam, eps, operator=True)

    def extra_repr(self) -> str:
        return f"linearisation={self.linearisation!r}" + (
            f", bundle={self.bundle:g}" if self.linearisation == "bundle" else ""
        )


class LocalisedKalmanBucyFlow(EnsembleFlow):
    """The deterministic ensemble Kalman-Bucy flow in the flowed members' own covariance
    (Bergemann & Reich 2010), localised::

        dx_i/dlam = -(rho o P_lam H^T) c_i,   c_i = (y_i + ybar) / 2 - z   (whitened)

    ``P_lam H^T`` the members' cross-covariance of state and whitened measurement, ``rho`` the
    taper ``local_taper (d, K)`` of the ``K`` observations ``local_index (d, K)`` near each
    coordinate (``None``: every observation everywhere, no taper). ``likelihood="model"``: ``c_i``
    is minus the score of the model's own density of each observation at the midpoint, times R's
    square root (``measurement.log_prob_terms``). Per step ``O(N d K)``, gathered in blocks of
    about :data:`CACHE_ELEMENTS` numbers. No log-determinant."""

    kernel = None

    def __init__(self, local_index=None, local_taper=None, likelihood: str = "gaussian"):
        super().__init__()
        self.likelihood = likelihood
        self.register_buffer("local_index", local_index, persistent=False)  # follow the filter's device
        self.register_buffer("local_taper", local_taper, persistent=False)

    def ensemble_coefficients(self, X, measurement, prior, lam, eps, j):
        w = measurement.members(X, j)
        c = self.residual(X, w, measurement)
        return FlowCoefficients(None, self.drift(X, w, c), None)  # no A: the drift per member

    def residual(self, X, w: WhitenedMembers, measurement: EnsembleMeasurement) -> torch.Tensor:
        """``c (B, N, m)``: minus the whitened score at the members' midpoints (class docstring)."""
        if self.likelihood == "gaussian":
            return 0.5 * w.Y - w.delta.unsqueeze(1)
        Xm = w.images if w.images is not None else (X if measurement.transition is None else measurement.transition(X))
        return model_residual(measurement.z, Xm, w, measurement.log_prob_terms)

    def drift(self, X, w: WhitenedMembers, c: torch.Tensor) -> torch.Tensor:
        """``-(rho o P_lam H^T) c_i`` ``(B, N, d)`` (class docstring)."""
        N = X.shape[1]
        D = X - X.mean(1, keepdim=True)  # (B, N, d)
        if self.local_index is None:  # every observation everywhere: N x N algebra
            T = w.Y @ c.transpose(1, 2)  # (B, N, N): T[n, i] = Y_n . c_i
            return -(T.transpose(1, 2) @ D) / (N - 1)
        idx, rho = self.local_index, self.local_taper.to(X.dtype)  # (d, K): the observations near each coordinate
        (d, K), B = idx.shape, X.shape[0]
        Yt = w.Y.transpose(1, 2).contiguous()  # (B, m, N)
        ct = c.transpose(1, 2).contiguous()  # (B, m, N)
        Dt = D.transpose(1, 2)  # (B, d, N)
        blk = max(1, min(d, CACHE_ELEMENTS // (B * K * N)))  # coordinates per block: about 2^16 numbers, in cache
        parts = []
        for lo in range(0, d, blk):  # blocks of coordinates (memory), not of trials or members
            i, r = idx[lo : lo + blk], rho[lo : lo + blk]  # (blk, K)
            Yl = Yt.index_select(1, i.reshape(-1)).view(B, -1, K, N)  # (B, blk, K, N): the nearby observations
            C = (Yl * Dt[:, lo : lo + blk].unsqueeze(2)).sum(-1) * r  # (B, blk, K): tapered cross-covariance
            cl = ct.index_select(1, i.reshape(-1)).view(B, -1, K, N)  # (B, blk, K, N): the residuals there
            parts.append((C.unsqueeze(-1) * cl).sum(2))  # (B, blk, N)
        drift = parts[0] if len(parts) == 1 else torch.cat(parts, 1)
        return -drift.transpose(1, 2) / (N - 1)

    def extra_repr(self) -> str:
        local = "global" if self.local_index is None else f"K={self.local_index.shape[1]}"
        return f"{local}, likelihood={self.likelihood!r}"


def model_residual(z, Xm, w: WhitenedMembers, log_prob_terms) -> torch.Tensor:
    """``c (B, N, m)`` of the model's own density: additive errors, ``log p(z | y) = f(z - y)``, so at
    ``y = (y_i + ybar) / 2`` the score is ``-f'(z - y)``, the derivative in z of the model's term at
    ``z' = z + (y_i - ybar) / 2`` and ``x = M(x_i)`` (``Xm``), times R's square root (unobserved: 0)."""
    half = 0.5 * w.Y * w.scale.unsqueeze(1)  # (y_i - ybar) / 2, unwhitened (unobserved: 0)
    z0 = torch.where(w.observed, z, torch.zeros_like(z)).unsqueeze(1)  # no NaN enters the gradient
    with torch.enable_grad():
        zp = (z0 + half).detach().requires_grad_(True)
        terms = log_prob_terms(zp, Xm.detach())
        (g,) = torch.autograd.grad(terms.sum(), zp)
    return g * w.scale.unsqueeze(1) * w.observed.unsqueeze(1).to(g.dtype)  # f'(.) s = -(score) s


class KernelFlow(EnsembleFlow):
    """The particle flow with a matrix-valued kernel (Pulido & van Leeuwen 2019), diagonal kernel
    ``K = diag(k_a)``, ``k_a(x, x') = exp(-(x_a - x'_a)^2 / (2 width_a))`` (Hu & van Leeuwen 2021)::

        dx_i/ds = D f(x_i),   f(x) = sum_j K(x_j, x) grad log p(x_j | z) + div_{x_j} K(x_j, x)

    divided coordinate by coordinate by the kernel's mass. The prior is ``N(xbar, P)`` with
    ``P = L L^T`` (the prior ``FlowPrior(xbar (B, 1, d), L)``), the likelihood's gradient
    ``grad_log_likelihood(X) -> (B, N, d)``, ``D (B, d, d)`` the preconditioner and ``width (B, d)``,
    the last three set per analysis by :meth:`prepare`. ``span``: the pseudo-time the flow runs (its
    ``flow_steps`` times its step size): the schedule's lambda in [0, 1] is ``s / span``, so the
    drift in lambda is ``span`` times the one in ``s``. Per step ``O(N^2 d)``; no log-determinant."""

    kernel = None

    def __init__(self, span: float):
        super().__init__()
        self.span = span
        self._ctx = None

    def prepare(self, D, width, grad_log_likelihood) -> None:
        """This analysis's preconditioner ``D (B, d, d)``, kernel widths ``(B, d)`` and likelihood
        gradient (class docstring); called before each integration."""
        self._ctx = (D.transpose(1, 2), width.unsqueeze(1).unsqueeze(1), grad_log_likelihood)

    def ensemble_coefficients(self, X, measurement, prior, lam, eps, j):
        (Dt, width, grad), xbar, L = self._ctx, prior.mean, prior.scale_tril
        g = grad(X) - linalg.chol_solve(L, (X - xbar).transpose(1, 2)).transpose(1, 2)  # + grad log prior
        diff = X.unsqueeze(1) - X.unsqueeze(2)  # [b, i, j] = x_j - x_i  (B, N, N, d)
        scaled = diff / width
        k = torch.exp(-0.5 * diff * scaled)
        # sum_j k_a(x_j, x_i) (g_j - (x_j - x_i) / width)_a, over the kernel's mass
        f = (k * (g.unsqueeze(1) - scaled)).sum(2) / k.sum(2)
        return FlowCoefficients(None, self.span * (f @ Dt), None)  # no A: the drift per member

    def extra_repr(self) -> str:
        return f"span={self.span:g}"
