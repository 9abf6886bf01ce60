"""Learnable parameters that stay valid: constrained values through ``torch.nn.utils.parametrize``.

A model declares, per learnable parameter, which constraint it lives under; the optimiser moves an
unconstrained tensor (``module.parametrizations.<name>.original``) and the attribute the filters
(and users) read, ``module.<name>``, is always the constrained value:

* :class:`Positive`: a positive scalar or vector (noise scales, the acoustic amplitude Psi), stored
  as its logarithm (``value = exp(raw)``, so an optimiser step is a relative change);
* :class:`CholeskyCovariance`: a dense covariance ``L L^T``, ``L`` lower triangular with a positive
  diagonal (``L_ii = exp(raw_ii)``), positive definite for every raw value;
* :class:`DiagonalCovariance`: ``diag(exp(raw))``, a log-variance per coordinate (``raw (d,)``);
* :class:`Interval`: a value in an open interval ``(low, high)`` (an autoregressive coefficient in
  ``(-1, 1)``, a probability), ``value = low + (high - low) sigmoid(raw)``; declared as the pair
  ``constraint=(low, high)``.

The covariance constraints also give the factor ``L`` without a Cholesky factorisation
(:func:`scale_tril`), which the filters use for sampling, whitening and log-densities.
"""

from __future__ import annotations

import math
from typing import Optional

import torch
from torch import nn
from torch.nn.utils import parametrize

from torchflow.core.checks import check_psd
from torchflow.core.errors import ArgumentError

__all__ = [
    "Positive",
    "CholeskyCovariance",
    "DiagonalCovariance",
    "Interval",
    "CONSTRAINTS",
    "constrain",
    "scale_tril",
    "unconstrained",
]


class Positive(nn.Module):
    """``value = exp(raw)``; the raw tensor is ``log(value)``."""

    def forward(self, raw: torch.Tensor) -> torch.Tensor:
        return raw.exp()

    def right_inverse(self, value: torch.Tensor) -> torch.Tensor:
        if not bool((value > 0).all()):
            raise ArgumentError(f"a positive parameter: expected every value > 0, got {value.detach().tolist()}")
        return value.log()


class CholeskyCovariance(nn.Module):
    """``cov = L L^T``, ``L = tril(raw, -1) + diag(exp(diag(raw)))``; raw ``(d, d)``."""

    @staticmethod
    def tril(raw: torch.Tensor) -> torch.Tensor:
        """The factor ``L (d, d)`` of the covariance (lower triangular, positive diagonal)."""
        return torch.tril(raw, -1) + torch.diag_embed(raw.diagonal(dim1=-2, dim2=-1).exp())

    def forward(self, raw: torch.Tensor) -> torch.Tensor:
        L = self.tril(raw)
        return L @ L.transpose(-1, -2)

    def right_inverse(self, cov: torch.Tensor) -> torch.Tensor:
        L = torch.linalg.cholesky(cov)
        return torch.tril(L, -1) + torch.diag_embed(L.diagonal(dim1=-2, dim2=-1).log())


class DiagonalCovariance(nn.Module):
    """``cov = diag(exp(raw))``; raw ``(d,)`` holds the log-variances."""

    @staticmethod
    def tril(raw: torch.Tensor) -> torch.Tensor:
        return torch.diag_embed((0.5 * raw).exp())

    def forward(self, raw: torch.Tensor) -> torch.Tensor:
        return torch.diag_embed(raw.exp())

    def right_inverse(self, cov: torch.Tensor) -> torch.Tensor:
        diag = cov.diagonal(dim1=-2, dim2=-1)
        if not torch.equal(cov, torch.diag_embed(diag)):
            raise ArgumentError("a diagonal covariance: expected a diagonal matrix, got off-diagonal entries")
        return diag.log()


class Interval(nn.Module):
    """``value = low + (high - low) sigmoid(raw)``, in the open interval ``(low, high)`` for every raw
    value; the raw tensor is ``logit((value - low) / (high - low))``."""

    def __init__(self, low: float, high: float):
        super().__init__()
        self.low, self.high = float(low), float(high)

    def forward(self, raw: torch.Tensor) -> torch.Tensor:
        return self.low + (self.high - self.low) * torch.sigmoid(raw)

    def right_inverse(self, value: torch.Tensor) -> torch.Tensor:
        if not bool(((value > self.low) & (value < self.high)).all()):
            raise ArgumentError(
                f"an interval parameter: expected every value in ({self.low:g}, {self.high:g}), got "
                f"{value.detach().tolist()}"
            )
        return torch.logit((value - self.low) / (self.high - self.low))

    def extra_repr(self) -> str:
        return f"low={self.low:g}, high={self.high:g}"


#: constraint name -> parametrization (the ``constraint`` strings models accept)
CONSTRAINTS = {"positive": Positive, "cholesky": CholeskyCovariance, "diagonal": DiagonalCovariance}


def _interval(name: str, constraint) -> Optional[Interval]:
    """The :class:`Interval` of a ``(low, high)`` constraint (``None`` for a named constraint)."""
    if isinstance(constraint, str):
        return None
    bad = (
        not isinstance(constraint, (tuple, list))
        or len(constraint) != 2
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in constraint)
    )
    if bad or not constraint[0] < constraint[1]:
        raise ArgumentError(
            f"{name}: expected a constraint in {sorted(CONSTRAINTS)} or an interval (low, high) of "
            f"finite numbers with low < high, got {constraint!r}"
        )
    return Interval(*constraint)


def constrain(module: nn.Module, name: str, constraint, value: Optional[torch.Tensor] = None) -> None:
    """Make ``module.<name>`` a learnable parameter under ``constraint`` (a key of
    :data:`CONSTRAINTS`, or an open interval ``(low, high)``: :class:`Interval`), initialised at
    ``value`` (default: the attribute's current value).

    Raises:
        ValueError: unknown constraint, or a value outside it (named after ``name``).
    """
    interval = _interval(name, constraint)
    if interval is None and constraint not in CONSTRAINTS:
        raise ArgumentError(
            f"{name}: expected a constraint in {sorted(CONSTRAINTS)} or an interval (low, high), got {constraint!r}"
        )
    value = getattr(module, name) if value is None else value
    value = torch.as_tensor(value).detach().clone()
    if interval is not None:
        if not bool(((value > interval.low) & (value < interval.high)).all()):
            raise ArgumentError(
                f"{name}: expected a value inside ({interval.low:g}, {interval.high:g}) to learn "
                f"under an interval parametrisation, got {value.tolist()}"
            )
    elif constraint != "positive":
        check_psd(name, value)
    elif not bool((value > 0).all()):
        raise ArgumentError(
            f"{name}: expected a positive value to learn under a log parametrisation, got {value.tolist()}"
        )
    if name in module._buffers:
        del module._buffers[name]
    elif name in module._parameters:
        del module._parameters[name]
    setattr(module, name, nn.Parameter(value))
    parametrize.register_parametrization(module, name, interval if interval is not None else CONSTRAINTS[constraint]())


def unconstrained(module: nn.Module, name: str) -> torch.Tensor:
    """The raw tensor the optimiser moves for a constrained ``module.<name>``."""
    return module.parametrizations[name].original


def scale_tril(module: nn.Module, name: str) -> Optional[torch.Tensor]:
    """The factor ``L`` of a covariance learnt under ``"cholesky"`` or ``"diagonal"`` (no
    factorisation; differentiable in the raw tensor), else ``None``."""
    if not parametrize.is_parametrized(module, name):
        return None
    p = module.parametrizations[name]
    return p[0].tril(p.original) if hasattr(p[0], "tril") else None
