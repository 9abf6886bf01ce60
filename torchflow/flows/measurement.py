"""The measurement term a flow is given: explicit tensors at the linearisation points.

A flow never sees the model. The filter (or :func:`~torchflow.flows.integrate_flow` on its
behalf) describes the Gaussian measurement term with a :class:`GaussianMeasurement`: the
observation ``z``, how to evaluate ``h`` and its Jacobian at points it chooses, and the noise ``R``
with its *declared* structure (``scalar``, ``diagonal``, ``dense``). At every pseudo-time step the
integrator evaluates it at the current points and hands the flow the whitened tensors of
:class:`Linearisation`:

    W = L_R^{-1} H (..., m, k),     y = L_R^{-1} (z - h(x) + H x) (..., m),

``H`` restricted to the measured coordinates (``support``, k of d) when the model declares them.
A filter with a state-dependent R, per-component moments (Gaussian-sum filters) or one term per
associated measurement builds its own ``GaussianMeasurement``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Sequence, Tuple

import torch

from torchflow.core import linalg, missing
from torchflow.core.errors import ArgumentError
from torchflow.models.structure import kernel_structure


@dataclass
class Linearisation:
    """Whitened measurement at the linearisation points: ``W (..., m, k)`` (or ``(m, k)``, shared by
    every point of a linear measurement) and ``y (..., m)``; ``diag (..., m)``: W's diagonal when W is
    diagonal by declaration (:attr:`GaussianMeasurement.diagonal`), for flows that can use it, else
    ``None``."""

    W: torch.Tensor
    y: torch.Tensor
    diag: Optional[torch.Tensor] = None


def _bcast_obs(z: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """``z (B, m)`` viewed to broadcast against points ``like (B, ..., d)``."""
    return z.reshape(z.shape[0], *([1] * (like.dim() - 2)), z.shape[-1])


class GaussianMeasurement:
    """``z = h(x) + w``, ``w ~ N(0, R)``, as the flows need it.

    Args:
        z: ``(B, m)`` observation.
        linearise: ``(points (..., d), support: bool, scale) -> (h (..., m), H (..., m, k|d))``, the
            measurement and its Jacobian at the points (restricted to the support columns when
            ``support`` is True; both multiplied by ``scale`` when given).
        scale_tril: ``points -> L_R`` (``(m, m)``, or ``(..., m, m)`` for a state-dependent R).
        noise: the declared structure of R: ``"scalar"``, ``"diagonal"`` or ``"dense"``.
        matrix: ``(m, d)`` measurement matrix of a linear measurement (one H for every point), else
            ``None``.
        measure: ``points -> h(points)`` (used with ``matrix``).
        support: the state coordinates h reads (``None``: all).
        diagonal: the Jacobian is diagonal (``m == d``, no support; the model's declared
            :attr:`~torchflow.models.Structure.measurement_jacobian_diagonal`): with a
            diagonal R, :meth:`at` also returns W's diagonal.
        hessian: ``(points (..., d), support: bool, scale) -> (..., m, n_b, b, b)``, h's second
            derivatives as diagonal blocks
            (:meth:`~torchflow.models.GaussianStateSpaceModel.measurement_hessian_blocks`), for
            :meth:`derivative`; only for a constant R (``None``: not available).
        form: the measurement in a named form that a kernel may linearise itself, ``(name,
            tensors)`` (the model's declared :attr:`~torchflow.models.Structure.measurement_form`
            with its parameters; :data:`torchflow.flows.select.FORMS`), or ``None``.
        diagonal_rows: ``points -> (h, dh/dx's diagonal, L_R's diagonal)`` for a ``diagonal``
            measurement with a diagonal R
            (:meth:`~torchflow.models.GaussianStateSpaceModel.linearize_measurement_diagonal`), for
            :meth:`at_diagonal`; ``None``: not available.
        fixed: the whitened Jacobian W is the same at every point and pseudo-time (a linear
            measurement with a constant R, declared): a flow may keep what it derives from W and
            the prior for a whole integration (:attr:`~torchflow.flows.base.FlowPrior.fixed`).
        observed: ``(B, m)`` bool, the coordinates of ``z`` that were observed (missing
            observations, :mod:`torchflow.core.missing`; ``z`` then holds a finite filler elsewhere), or
            ``None``: all. The whitened rows of the unobserved coordinates are zero (for a dense
            R, whitened by the factor of R with those rows and columns replaced by the
            identity's), so the flow sees the observed rows alone; no kernel takes a mask.
    """

    def __init__(
        self,
        z: torch.Tensor,
        linearise: Callable,
        scale_tril: Callable,
        noise: str,
        matrix: Optional[torch.Tensor] = None,
        measure: Optional[Callable] = None,
        support: Optional[Sequence[int]] = None,
        diagonal: bool = False,
        hessian: Optional[Callable] = None,
        form=None,
        diagonal_rows: Optional[Callable] = None,
        observed: Optional[torch.Tensor] = None,
        fixed: bool = False,
    ):
        if noise not in ("scalar", "diagonal", "dense"):
            raise ArgumentError(f"noise: expected 'scalar', 'diagonal' or 'dense', got {noise!r}")
        self.observed = observed
        if observed is not None:
            z = torch.where(observed, z, torch.zeros_like(z))
            if noise == "dense":  # whiten the observed block by its own factor (torchflow.core.missing)
                scale_tril = _masked_factor(scale_tril, observed)
            form = None  # a kernel's own linearisation takes no mask
        self.z, self.linearise, self.scale_tril, self.noise = z, linearise, scale_tril, noise
        self.matrix, self.measure = matrix, measure
        self.support = None if support is None else tuple(support)
        self.diagonal = bool(diagonal) and self.support is None
        self.hessian = hessian
        self.form = form
        self.diagonal_rows = diagonal_rows if self.diagonal and noise == "diagonal" else None
        self.fixed = bool(fixed) and matrix is not None
        #: ``1 / sigma`` (0-d) of a declared ``"scalar"`` R, once :meth:`prepare` has run (else ``None``)
        self.inv_sigma = None
        #: ``z / sigma`` ``(B, m)``, once :meth:`prepare` has run (else ``None``)
        self.z_scaled = None

    @classmethod
    def from_model(cls, model, z: torch.Tensor) -> "GaussianMeasurement":
        """The model's own measurement term (its declared noise structure and support)."""
        noise = model.structure.measurement_noise
        if noise == "state_dependent_diagonal":  # evaluated per point; whitening is a division
            noise = "diagonal"
        elif noise not in ("scalar", "diagonal", "dense"):  # state-dependent R: general whitening
            noise = "dense"
        linear = model.structure.linear_measurement
        constant_r = model.structure.measurement_noise in ("scalar", "diagonal", "dense")
        observed = ~torch.isnan(z) if missing.active() else None  # NaN: not observed
        return cls(
            z,
            model.linearize_measurement,
            model.measurement_scale_tril,
            noise,
            observed=observed,
            matrix=model.measurement_matrix() if linear else None,
            measure=model.measure if linear else None,
            support=model.structure.measurement_support,
            diagonal=model.structure.measurement_jacobian_diagonal and not linear,
            hessian=model.measurement_hessian_blocks if constant_r and not linear else None,
            form=measurement_form(model) if noise == "scalar" and not linear else None,
            diagonal_rows=model.linearize_measurement_diagonal,
            fixed=linear and constant_r,
        )

    @classmethod
    def lag_one(cls, model, z: torch.Tensor) -> "GaussianMeasurement":
        """The measurement of the forecast, ``z = h(M(x)) + w`` in the previous state ``x``, for
        deterministic dynamics ``x_k = M(x_{k-1})``: the likelihood of the lag-one target
        ``p(x_{k-1} | z_{1:k})``. Linearised by the chain rule, ``d h(M(x)) / dx = H(M(x)) J_M(x)``
        (:meth:`~torchflow.models.GaussianStateSpaceModel.transition_mean_and_jacobian`: one pass
        where the model gives it); the noise is the model's R (evaluated at ``M(x)`` where it depends
        on the state). Every state coordinate is read through ``M``: no support, no matrix."""
        noise = model.structure.measurement_noise
        dependent = noise.startswith("state_dependent")
        if noise == "state_dependent_diagonal":
            noise = "diagonal"
        elif noise not in ("scalar", "diagonal", "dense"):
            noise = "dense"

        def linearise(points, support=False, scale=None):
            Mx, J = model.transition_mean_and_jacobian(points)
            h, H = model.linearize_measurement(Mx, scale=scale)
            return h, H @ J

        def scale_tril(points):
            return model.measurement_scale_tril(model.transition_mean(points) if dependent else None)

        observed = ~torch.isnan(z) if missing.active() else None
        return cls(z, linearise, scale_tril, noise, observed=observed)

    def _scalar_inv_sigma(self, points):
        return 1 / self.scale_tril(points).diagonal(dim1=-2, dim2=-1)[..., 0]  # 0-d: "scalar" R is constant

    def prepare(self, points: torch.Tensor) -> "GaussianMeasurement":
        """Compute once what does not change between point sets (``1 / sigma`` of a declared
        ``"scalar"`` R), for a loop that calls :meth:`at` many times; the numbers are those of
        :meth:`at` alone. Call it outside any ``torch.func`` transform. Returns ``self``."""
        if self.noise == "scalar" and self.matrix is None:
            self.inv_sigma = self._scalar_inv_sigma(points)
            self.z_scaled = self.z * self.inv_sigma
        return self

    def at(self, points: torch.Tensor, support: Optional[torch.Tensor] = None) -> Linearisation:
        """Whitened linearisation at ``points (..., d)``; ``support`` is the ``(k,)`` index of the
        measured coordinates (:attr:`FlowPrior.support`) or ``None``. No test of R's values: its
        structure is declared (no host synchronisation). Unobserved rows (:attr:`observed`) are zero."""
        lin = self._at(points, support)
        if self.observed is None:
            return lin
        rows = _bcast_obs(self.observed, points).to(lin.y.dtype)
        return Linearisation(lin.W * rows.unsqueeze(-1), lin.y * rows, None if lin.diag is None else lin.diag * rows)

    def _at(self, points: torch.Tensor, support: Optional[torch.Tensor] = None) -> Linearisation:
        xs = points if support is None else points[..., support]  # cheaper than index_select on the CPU
        if self.noise == "scalar" and self.matrix is None:
            # R = sigma^2 I: whiten inside the linearisation (scale 1 / sigma), so W = H / sigma
            # and y = (z - h) / sigma + W x_s need no pass over the Jacobian
            if self.inv_sigma is not None:  # prepared: z / sigma too (the same product, made once)
                inv_sigma, zs = self.inv_sigma, _bcast_obs(self.z_scaled, points)
            else:
                inv_sigma = self._scalar_inv_sigma(points)
                zs = _bcast_obs(self.z, points) * inv_sigma
            hx, W = self.linearise(points, support=support is not None, scale=inv_sigma)
            return Linearisation(W, zs - hx + linalg.matvec(W, xs))
        if self.matrix is not None:  # a linear measurement has one H for every point: keep (m, d)
            H = self.matrix if support is None else self.matrix.index_select(-1, support)
            hx = self.measure(points)
        else:
            hx, H = self.linearise(points, support=support is not None)
        resid = _bcast_obs(self.z, points) - (hx - linalg.matvec(H, xs))
        LR = self.scale_tril(points)
        if self.noise == "scalar":
            sigma = LR.diagonal(dim1=-2, dim2=-1)[..., 0]
            return Linearisation(H / sigma, resid / sigma)  # a 0-d scale: much faster than a broadcast
        if self.noise == "diagonal":
            dr = LR.diagonal(dim1=-2, dim2=-1)
            W = H / dr.unsqueeze(-1)
            return Linearisation(W, resid / dr, W.diagonal(dim1=-2, dim2=-1) if self.diagonal else None)
        W = linalg.solve_triangular(LR, H, upper=False)
        y = linalg.solve_triangular(LR, resid.unsqueeze(-1), upper=False).squeeze(-1)
        return Linearisation(W, y)

    def at_diagonal(self, points: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """``(W's diagonal (..., m), y (..., m))`` of :meth:`at` for a measurement that is
        :attr:`diagonal` with a diagonal R, from the model's
        :meth:`~torchflow.models.GaussianStateSpaceModel.linearize_measurement_diagonal` (no ``m x m`` matrix
        per point; the same numbers as :meth:`at`); ``None`` for other measurements."""
        if self.diagonal_rows is None:
            return None
        hx, Hd, sd = self.diagonal_rows(points)
        resid = _bcast_obs(self.z, points) - (hx - Hd * points)
        if self.observed is not None:
            rows = _bcast_obs(self.observed, points).to(resid.dtype)
            return Hd / sd * rows, resid / sd * rows
        return Hd / sd, resid / sd

    def derivative(self, points: torch.Tensor, support: Optional[torch.Tensor] = None) -> Optional[torch.Tensor]:
        """The derivative of :meth:`at`'s ``W`` along each of the k (support) coordinates at
        ``points (..., d)``, as the declared :attr:`hessian`'s diagonal blocks ``(..., m, n_b, b, b)``:
        for ``t = (c, i)`` (coordinate i of group c), ``dW[a, (c', j)] / dx_t = [c = c'] D[a, c, i, j]``.
        ``dW = L_R^{-1} d^2h`` for a constant R; then ``y``'s derivative is ``dW x_s`` (the Jacobian
        terms of ``y = L_R^{-1} (z - h(x) + H x_s)`` cancel); zero for a linear measurement (``k``
        blocks of ``1 x 1``, broadcast over the points). ``None`` when no Hessian is given (a
        state-dependent R): differentiate :meth:`at` itself."""
        if self.matrix is not None:
            k = self.matrix.shape[-1] if support is None else support.shape[-1]
            return points.new_zeros(self.z.shape[-1], k, 1, 1)
        if self.hessian is None:
            return None
        dW = self._derivative(points, support)
        if self.observed is None:
            return dW
        rows = _bcast_obs(self.observed, points).to(dW.dtype)
        return dW * rows[..., None, None, None]

    def _derivative(self, points: torch.Tensor, support: Optional[torch.Tensor] = None) -> torch.Tensor:
        if self.noise == "scalar":
            inv_sigma = self.inv_sigma if self.inv_sigma is not None else self._scalar_inv_sigma(points)
            return self.hessian(points, support is not None, inv_sigma)
        dH = self.hessian(points, support is not None)  # (..., m, n_b, b, b)
        LR = self.scale_tril(points)
        if self.noise == "diagonal":
            return dH / LR.diagonal(dim1=-2, dim2=-1)[..., None, None, None]
        return linalg.solve_triangular(LR, dH.flatten(-3), upper=False).unflatten(-1, dH.shape[-3:])


def _masked_factor(scale_tril: Callable, observed: torch.Tensor) -> Callable:
    """``points -> the factor of R`` with the unobserved rows and columns of R replaced by the
    identity's (:func:`torchflow.core.missing.masked_noise`), per trial ``(B, 1.., m, m)`` (per point for
    a state-dependent R)."""

    def factor(points):
        L = scale_tril(points)
        R = L @ L.transpose(-1, -2)
        return linalg.safe_cholesky(missing.masked_noise(R, _bcast_obs(observed, points)))

    return factor


def measurement_form(model):
    """``(name, tensors)`` of the measurement form the model declares
    (:attr:`~torchflow.models.Structure.measurement_form`: a name and the names of the model's
    tensors it reads), or ``None``. Only where the model's own class declares its structure
    (:func:`~torchflow.models.structure.kernel_structure`): a subclass may change the measurement."""
    declared = kernel_structure(model).measurement_form
    if declared is None:
        return None
    name, params = declared
    return name, tuple(getattr(model, p) for p in params)


def whiten(model, points: torch.Tensor, z: torch.Tensor, support=None) -> Tuple[torch.Tensor, torch.Tensor]:
    """``(W, y)`` of the model's measurement at ``points`` (a convenience for tests and users)."""
    lin = GaussianMeasurement.from_model(model, z).at(points, support)
    return lin.W, lin.y


__all__ = ["GaussianMeasurement", "Linearisation", "measurement_form", "whiten"]
