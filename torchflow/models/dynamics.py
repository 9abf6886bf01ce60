"""Numerical pieces shared by the models of continuous-time dynamics (Lorenz-63, Lorenz-96):
classical Runge-Kutta integration, with or without the exact Jacobian of the discrete map, and the
isotropic Gaussian density that their scalar noise factors give."""

from __future__ import annotations

import math
from typing import Tuple

import torch

_LOG_2PI = math.log(2.0 * math.pi)


class RungeKuttaModel:
    """Mixin of the models integrated by :func:`rk4_steps` over ``dt`` in ``substeps`` steps: the
    advice a simulation that blows up gives (:func:`~torchflow.models.contract.check_simulated`)."""

    @property
    def simulation_hint(self) -> str:
        h = float(self.dt) / int(self.substeps)
        return (
            f"the Runge-Kutta step dt / substeps = {h:g} is too large for these dynamics: more substeps "
            "(model.substeps) or a smaller dt; or parameters that make the system itself blow up"
        )


def rk4_steps(tendency, x: torch.Tensor, dt: float, substeps: int) -> torch.Tensor:
    """``x (..., d)`` moved by ``substeps`` classical Runge-Kutta steps of ``dt / substeps`` of
    ``dx/dt = tendency(x)``."""
    h = dt / substeps
    for _ in range(substeps):  # a loop over sub-steps in time, not over trials or particles
        k1 = tendency(x)
        k2 = tendency(x + 0.5 * h * k1)
        k3 = tendency(x + 0.5 * h * k2)
        k4 = tendency(x + h * k3)
        x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return x


def rk4_with_tangent(
    tendency, tendency_jacobian, x: torch.Tensor, dt: float, substeps: int
) -> Tuple[torch.Tensor, torch.Tensor]:
    """``(x_T, J)``: ``x (..., d)`` moved by ``substeps`` classical Runge-Kutta steps of
    ``dt / substeps`` and the exact Jacobian ``(..., d, d)`` of that discrete map (the stages'
    derivatives carried alongside, forward mode)."""
    h = dt / substeps
    J = torch.eye(x.shape[-1], dtype=x.dtype, device=x.device).expand(*x.shape, x.shape[-1])
    for _ in range(substeps):  # a loop over sub-steps in time, not over trials or particles
        k1, D1 = tendency(x), tendency_jacobian(x) @ J
        x2 = x + 0.5 * h * k1
        k2, D2 = tendency(x2), tendency_jacobian(x2) @ (J + 0.5 * h * D1)
        x3 = x + 0.5 * h * k2
        k3, D3 = tendency(x3), tendency_jacobian(x3) @ (J + 0.5 * h * D2)
        x4 = x + h * k3
        k4, D4 = tendency(x4), tendency_jacobian(x4) @ (J + h * D3)
        x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        J = J + (h / 6.0) * (D1 + 2.0 * D2 + 2.0 * D3 + D4)
    return x, J


def isotropic_log_prob(resid: torch.Tensor, std: torch.Tensor) -> torch.Tensor:
    """``log N(resid; 0, std^2 I)`` over the last dim of ``resid (..., n)``; ``std`` a 0-d tensor or
    broadcastable to ``(..., 1)`` (one value per trial)."""
    n = resid.shape[-1]
    var = std * std
    if var.dim() > 0:
        var = var.squeeze(-1)
    return -0.5 * ((resid * resid).sum(-1) / var + n * (torch.log(var) + _LOG_2PI))


__all__ = ["rk4_steps", "rk4_with_tangent", "isotropic_log_prob"]
