"""Per-trial parameters: what a model's methods use when a parameter holds one value per trial.

A model names the parameters that may carry a leading trial dimension in
:attr:`~torchflow.models.StateSpaceModel.per_trial_parameters`; within
:func:`torchflow.inference.per_trial_values` such a parameter holds ``(B, *shape)`` values instead of
its shared ``shape``, and every method of the model broadcasts trial ``b``'s value over trial ``b``'s
states, particles or sigma points ``(B, ..., d)``. The helpers here are what the built-in models do
with them:

* :func:`trial_names`: which parameters hold per-trial values now (empty outside the block);
* :func:`trial_view`: a parameter viewed to broadcast against states ``(B, ..., d)``;
* :func:`trial_factor`: the Cholesky factor of a per-trial covariance, factored once per value;
* :func:`batch_jacobian`: Jacobians of a map that reads per-trial values (it cannot be evaluated on
  one point at a time under ``vmap``, as :func:`torchflow.core.linearize.jacobian` does).
"""

from __future__ import annotations

from typing import Callable, Optional, Tuple

import torch
from torch.distributions import constraints as C

from torchflow.core import linalg
from torchflow.core.errors import ArgumentError


def trial_names(model) -> Tuple[str, ...]:
    """The names of ``model``'s parameters that hold one value per trial now (set by
    :func:`torchflow.inference.per_trial_values`; ``()`` outside it)."""
    return model.__dict__.get("_trial_names", ())


def parameter_domain(model, name: str):
    """The domain ``model`` declares for per-trial parameter ``name`` (a
    ``torch.distributions.constraints`` object), or ``None`` where it declares none (a tuple of
    names, or a name without one)."""
    declared = getattr(model, "per_trial_parameters", ()) or ()
    return declared.get(name) if isinstance(declared, dict) else None


def _bounds(c):
    """``(low, high)`` of a scalar interval constraint, or ``None``."""
    inf = float("inf")
    if c is C.real or isinstance(c, type(C.real)):
        return (-inf, inf)
    if isinstance(c, (type(C.greater_than(0.0)), type(C.greater_than_eq(0.0)))):
        return (float(c.lower_bound), inf)
    if isinstance(c, type(C.less_than(0.0))):
        return (-inf, float(c.upper_bound))
    if isinstance(c, (type(C.interval(0.0, 1.0)), type(C.half_open_interval(0.0, 1.0)))):
        return (float(c.lower_bound), float(c.upper_bound))
    return None


def support_within(support, domain) -> bool:
    """A distribution's ``support`` lies inside a parameter's ``domain`` (both
    ``torch.distributions.constraints``), as far as their bounds tell: a Gamma's ``[0, inf)`` fits a
    positive parameter (the end point has probability zero), a Normal's real line does not. A
    constraint of another kind (matrices, simplices) is taken as fitting."""
    if domain is None or support is domain:
        return True
    s, d = _bounds(support), _bounds(domain)
    if s is None or d is None:
        return True
    return s[0] >= d[0] and s[1] <= d[1]  # a shared end point has probability zero under a density


def check_trial_count(model, batch_size: int, who: str) -> None:
    """Raise unless every per-trial value of ``model`` (:func:`trial_names`) has ``batch_size``
    trials: a filter called on B trials reads trial b's value for trial b. Shapes only: no host read."""
    for name in trial_names(model):
        got = getattr(model, name).shape[0]
        if got != batch_size:
            raise ArgumentError(
                f"{who}: {type(model).__name__}.{name} holds values for {got} trials "
                f"(torchflow.inference.per_trial_values), but the call filters {batch_size} trials "
                f"(observations (B, T, m) with B = {batch_size}); give one value per trial"
            )


def shared_structure(model):
    """The structure ``model`` declares for values shared by every trial: its own, also within
    :func:`torchflow.inference.per_trial_values` (where ``model.structure`` is the per-trial one)."""
    return model.__dict__.get("_shared_structure", model.structure)


def trial_view(value: torch.Tensor, rank: int, x: Optional[torch.Tensor], event: int = 1) -> torch.Tensor:
    """``value`` (shared: ``rank`` dimensions; per trial: ``(B, *shape)``, one more) viewed to broadcast
    against a tensor whose leading dimensions are those of the states ``x (B, ..., d)`` and whose last
    ``event`` dimensions are the value's own: a scalar against ``(B, ..., m)`` is ``(B, 1.., 1)``, a
    ``(B, d, d)`` matrix against ``(B, ..., d, d)`` is ``(B, 1.., d, d)``. States whose leading
    dimension is a trial-major multiple ``k B`` of the trials (rows ``b k .. b k + k - 1`` are trial
    b's: the library's convention, as in :func:`torchflow.core.linalg.standard_normal`; the Gaussian-sum
    filters flow their components so) take each trial's value k times. A shared value is returned as
    it is. ``x=None``: one row per trial, ``(B, 1.., *shape)`` with ``event - rank`` ones (a
    parameter's per-trial value where a method is called without states)."""
    if value.dim() == rank:
        return value
    if x is None:
        return value.reshape(value.shape[0], *([1] * (event - rank)), *value.shape[1:])
    n, trials = x.shape[0], value.shape[0]
    if n != trials and trials and n % trials == 0:
        value = value.repeat_interleave(n // trials, 0)
    return value.reshape(value.shape[0], *([1] * (x.dim() - 2 + event - rank)), *value.shape[1:])


def trial_factor(model, name: str, value: torch.Tensor) -> torch.Tensor:
    """The lower Cholesky factor of the per-trial covariance ``value (B, k, k)`` held by ``model.<name>``,
    factored once per value (:func:`torchflow.core.linalg.safe_cholesky`) and reused while the same tensor
    is in place; a value that records gradients is factored at every call (a kept factor would hold a
    graph that a first backward pass frees)."""
    if value.requires_grad:
        return linalg.safe_cholesky(value)
    memo = model.__dict__.setdefault("_trial_factors", {})
    kept = memo.get(name)
    if kept is not None and kept[0] is value and kept[1] == value._version:
        return kept[2]
    L = linalg.safe_cholesky(value)
    memo[name] = (value, value._version, L)
    return L


def batch_jacobian(fn: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """Jacobian ``(..., m, d)`` of a map ``fn: (B, ..., d) -> (B, ..., m)`` that acts on each point
    separately but reads per-trial values (so it runs on the whole batch, not on single points):
    forward-mode derivatives along the d coordinate directions, batched with ``vmap``."""
    from torch.func import jvp, vmap

    d = x.shape[-1]
    eye = torch.eye(d, dtype=x.dtype, device=x.device)
    tangents = eye.reshape(d, *([1] * (x.dim() - 1)), d).expand(d, *x.shape)
    cols = vmap(lambda t: jvp(fn, (x,), (t,))[1])(tangents)  # (d, ..., m)
    return cols.movedim(0, -1)


def per_trial_structure(
    model, names, *, dynamics: bool = True, measurement: bool = True, noise: bool = True
) -> "Structure":  # noqa: F821 - imported where used (models.base imports this module)
    """The structure ``model`` declares while ``names`` hold per-trial values, from its own: the
    shortcuts that assume one value for every trial stand aside. ``dynamics``: the transition
    matrix depends on them (no longer ``linear_dynamics``: its callers read one matrix, not one per
    trial; the Jacobian then comes from the model at each state); ``measurement``: the measurement
    matrix does (no longer ``linear_measurement``); ``noise``: R does (a declared ``"scalar"`` R
    becomes ``"diagonal"``, since the flows read a scalar R as one 0-d number, and its scale is
    dropped). Always: a kernel's named measurement form that reads one of ``names`` stands aside, and
    no step is replayed from a captured CUDA graph (a graph keeps the tensors it was captured with).
    The defaults (all True) suit a model that says nothing more."""
    s = model.structure
    form = s.measurement_form
    if form is not None and set(form[1]) & set(names):
        form = None
    changes = dict(measurement_form=form, graph_safe=False)
    if dynamics:
        changes.update(linear_dynamics=False, transition_matrix_scale=None)
    if measurement:
        changes.update(linear_measurement=False, measurement_matrix_scale=None)
    if noise:
        changes.update(
            measurement_noise_scale=None,
            measurement_noise="diagonal" if s.measurement_noise == "scalar" else s.measurement_noise,
        )
    return s.replace(**changes)


__all__ = [
    "trial_names",
    "check_trial_count",
    "parameter_domain",
    "support_within",
    "shared_structure",
    "trial_view",
    "trial_factor",
    "batch_jacobian",
    "per_trial_structure",
]
