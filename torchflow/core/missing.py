"""Missing observations: a NaN in the observations means "this coordinate was not observed".

A NaN may mark one coordinate of a step's measurement ``z_k (m,)`` or all of them (a whole step
not observed). Every filter then conditions on the observed coordinates only:

* the Kalman family and every Gaussian measurement update (the trackers, the flows' covariance
  tracking) update on the observed rows, and the log-evidence is that of the reduced measurement
  model ``z_o = h_o(x) + w_o``, ``w_o ~ N(0, R_oo)`` (exact for the Kalman filter);
* particle filters weigh particles by the density of the observed coordinates
  (:meth:`~torchflow.models.StateSpaceModel.measurement_log_prob_observed`);
* particle flows migrate with the observed rows only; a step with nothing observed is a pure
  prediction.

There are no data-dependent shapes and no host reads inside a step: a mask ``observed (B, m)``
selects the rows, and the algebra is that of the full measurement with the unobserved rows of
the Jacobian and of the residual set to zero and the unobserved rows and columns of R replaced by
those of the identity. Then ``S = H P H^T + R`` is block-diagonal between observed and unobserved
rows, the gain's unobserved columns vanish, and ``log N(0; 0, 1) = -log(2 pi) / 2`` per unobserved
row is added back (:func:`gaussian_rows`).

Which computations take the masked path is decided once per call: :meth:`Filter.forward
<torchflow.filters.Filter.forward>` reads the observations once before the first step and, when
any value is NaN, runs the steps inside :func:`observations_missing` (the fused kernels and CUDA
graphs, which do not take masks, then stand aside for that call). Code that calls a filter's
``step`` itself with NaN in ``z`` wraps the calls in the same context::

    with torchflow.core.missing.observations_missing():
        state = filt.step(state, z, generator)

A non-finite value other than NaN (``inf``) is an error, not a missing value.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
from typing import Optional, Tuple

import torch

__all__ = [
    "active",
    "measurement_log_prob",
    "observations_missing",
    "observed",
    "gaussian_rows",
    "masked_noise",
    "unobserved_correction",
    "observed_like",
]

_ACTIVE = contextvars.ContextVar("torchflow_observations_missing", default=False)

_HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


def active() -> bool:
    """Whether the current steps may see NaN (unobserved) coordinates in ``z`` (a Python bool: no
    host read)."""
    return _ACTIVE.get()


@contextlib.contextmanager
def observations_missing(on: bool = True):
    """Run the enclosed filter steps with the masked (missing-observation) path on (``on``) or off."""
    token = _ACTIVE.set(bool(on))
    try:
        yield
    finally:
        _ACTIVE.reset(token)


def observed(z: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """``(mask, filled)``: ``mask = ~isnan(z)`` (True where observed) and ``z`` with its NaN
    replaced by 0 (a finite filler that never reaches a result: every use is masked; a NaN would
    poison gradients through ``torch.where``)."""
    mask = ~torch.isnan(z)
    return mask, torch.where(mask, z, torch.zeros_like(z))


def observed_like(mask: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """``mask (B, m)`` viewed to broadcast against ``like (B, ..., m)`` (points with any number of
    dimensions between the trials and the coordinates)."""
    if mask.dim() >= like.dim():
        return mask
    return mask.reshape(mask.shape[0], *([1] * (like.dim() - mask.dim())), *mask.shape[1:])


def masked_noise(R: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``R`` with the unobserved rows and columns replaced by the identity's: ``R_oo`` on the
    observed block, 1 on the unobserved diagonal, 0 between the two. ``R (..., m, m)`` (or
    ``(m, m)``), ``mask (..., m)`` -> ``(..., m, m)``."""
    mf = mask.to(R.dtype)
    outer = mf.unsqueeze(-1) * mf.unsqueeze(-2)
    return R * outer + torch.diag_embed(1 - mf)


def unobserved_correction(
    mask: torch.Tensor, log_var: Optional[torch.Tensor] = None, dtype: Optional[torch.dtype] = None
) -> torch.Tensor:
    """What to add to a log-density evaluated with the masked algebra to get the density of the
    observed rows alone: ``sum over unobserved rows of (log(2 pi) + log_var) / 2`` (``log_var``:
    the log-variance the masked algebra left on the unobserved diagonal, ``None`` for 1) in
    ``dtype`` (``log_var``'s, else float64). ``mask (..., m)`` -> ``(...)``."""
    un = (~mask).to(dtype or (torch.float64 if log_var is None else log_var.dtype))
    if log_var is None:
        return _HALF_LOG_2PI * un.sum(-1)
    return (un * (_HALF_LOG_2PI + 0.5 * log_var)).sum(-1)


def gaussian_rows(
    z: torch.Tensor, z_pred: torch.Tensor, H: torch.Tensor, R: torch.Tensor
) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The masked form of a Gaussian measurement update with NaN (unobserved) coordinates in ``z``.

    Args:
        z: ``(..., m)`` observation, NaN where not observed.
        z_pred: ``(..., m)`` predicted measurement.
        H: ``(..., m, d)`` Jacobian (or ``None``: not used).
        R: ``(..., m, m)`` noise covariance.

    Returns:
        ``(z, z_pred, H, R, correction)``: the observation and prediction equal (zero) on the
        unobserved rows, the Jacobian's unobserved rows zero, :func:`masked_noise`, and the
        ``(...)`` term to add to ``log N(z; z_pred, H P H^T + R)`` computed from them.
    """
    mask, zf = observed(z)
    shape = torch.broadcast_shapes(z.shape, z_pred.shape)
    mask, zf = mask.expand(shape), zf.expand(shape)
    z_pred = torch.where(mask, z_pred, torch.zeros_like(z_pred))
    H = None if H is None else H * mask.unsqueeze(-1).to(H.dtype)
    return zf, z_pred, H, masked_noise(R, mask), unobserved_correction(mask, dtype=zf.dtype)


def measurement_log_prob(model, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``log p(z | x)`` by ``model``, of the observed coordinates of ``z`` when :func:`active`
    (:meth:`~torchflow.models.StateSpaceModel.measurement_log_prob_observed`), else
    :meth:`~torchflow.models.StateSpaceModel.measurement_log_prob`: what every particle filter
    weighs with. ``z`` broadcastable to ``(..., m)``, ``x (..., d)`` -> ``(...)``."""
    if not active():
        return model.measurement_log_prob(z, x)
    mask, zf = observed(z)
    return model.measurement_log_prob_observed(zf, x, mask)
