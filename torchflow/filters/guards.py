"""The non-finite contract of :meth:`Filter.forward <torchflow.filters.Filter.forward>`.

Everything a filter returns is finite, or the call says where it was not:

- **Estimates, particles and weights, log-evidence increments** (forward pass): recorded on the
  device at every step and read once after the last step (no host synchronisation per step);
  the earliest offending step raises :class:`~torchflow.core.errors.NonFiniteError` naming the filter,
  the quantity, the step and the trials.
- **Steps that carried no measurement** (particle filters, ``nonfinite="recover"``): a step in
  which every particle's weight is zero (underflowed, or invalid and repaired) keeps the previous
  particles and weights, so that the trial goes on, and contributes an evidence estimate of zero
  (an increment of ``-inf``, which is what the estimator gives). That is the documented treatment,
  counted per trial in ``n_repaired``; :func:`dead_step_warning` says which trials and steps were
  left without the measurement. ``nonfinite="raise"`` makes it an error.
- **Gradients** (under autograd, :attr:`Filter.check_gradients`): a tensor hook on each step's
  input state checks the gradient flowing back into it, so the first step in the backward pass
  whose gradient is NaN or infinite raises naming the filter, that step and the trials; a
  parameter of the model whose gradient is non-finite although every step's was finite is named
  by a hook on the parameter. One host read per step in the backward pass (none in the forward).
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
import weakref
from typing import List, Optional, Tuple

import torch

from torchflow.core.errors import NonFiniteError

#: quantities in the order :class:`NonFiniteError` lists them
QUANTITIES = ("estimate", "particles or weights", "log-evidence increment")


def first_steps(est: torch.Tensor, invalid: Optional[torch.Tensor], inc: torch.Tensor, recover: bool) -> torch.Tensor:
    """Per trial, on the device: ``(B, 6)`` long tensor ``[first bad step, estimate bad then,
    invalid then, increment bad then, first dead step, dead steps]`` (steps 1-based, 0 where none).

    Args:
        est: ``(B, T, d)`` estimates; invalid: ``(B, T)`` flagged steps or ``None``;
        inc: ``(B, T)`` log-evidence increments;
        recover: a ``-inf`` increment is a dead step (documented treatment), not an error.
    """
    est_bad = ~torch.isfinite(est).all(-1)
    inv = torch.zeros_like(est_bad) if invalid is None else invalid
    if recover:
        dead = inc == float("-inf")
        inc_bad = torch.isnan(inc) | (inc == float("inf"))
    else:
        dead = torch.zeros_like(est_bad)
        inc_bad = ~torch.isfinite(inc)
    bad = est_bad | inv | inc_bad
    T = bad.shape[1]
    steps = torch.arange(1, T + 1, device=bad.device)
    first = torch.where(bad, steps, T + 1).amin(1)
    at = (first - 1).clamp(max=T - 1).unsqueeze(1)
    flags = [q.gather(1, at).squeeze(1) & (first <= T) for q in (est_bad, inv, inc_bad)]
    first_dead = torch.where(dead, steps, T + 1).amin(1)
    return torch.stack(
        [
            first.masked_fill(first > T, 0),
            *[f.long() for f in flags],
            first_dead.masked_fill(first_dead > T, 0),
            dead.sum(1),
        ],
        1,
    )


def raise_first(name: str, table: List[List[int]], hint: Optional[str] = None) -> None:
    """Raise :class:`NonFiniteError` for the earliest bad step in ``table`` (rows of
    :func:`first_steps`, read to the host), naming every quantity bad at that step; return if none.
    ``hint``: the filter's own advice for a non-finite estimate (its :attr:`nonfinite_hint`)."""
    bad = [(r[0], i) for i, r in enumerate(table) if r[0] > 0]
    if not bad:
        return
    step = min(s for s, _ in bad)
    trials = [i for s, i in bad if s == step]
    what = [q for k, q in enumerate(QUANTITIES) if any(table[i][1 + k] for i in trials)]
    if what == [QUANTITIES[2]]:  # finite estimates: the density of the observation itself under/overflowed
        hint = (
            "an observation so far from its prediction, or a predicted spread so small, that its density "
            "under- or overflows: look at that step's observations and the noise scales"
        )
    raise NonFiniteError(name, step, trials, what=" and ".join(what) or "estimate", hint=hint)


def raise_never_measured(name: str, table: List[List[int]], steps: int) -> None:
    """Raise :class:`NonFiniteError` for trials in which *no* step's weights carried the
    measurement (every one of ``steps`` dead): their estimates never saw the data and their
    log-evidence is ``-inf``, which no repair makes meaningful (a singular measurement density, a
    measurement function returning NaN, a noise scale that underflows)."""
    never = [i for i, r in enumerate(table) if r[5] >= steps]
    if never:
        raise NonFiniteError(
            name,
            1,
            never,
            what=(
                f"log-evidence (-inf: no particle's weight carried the measurement at any of the {steps} step(s), "
                "every "
                "weight zero or invalid; look at the measurement model's noise scale and outputs)"
            ),
        )


def dead_step_warning(name: str, table: List[List[int]]) -> Optional[str]:
    """The warning for trials with steps that carried no measurement (``None`` when none did)."""
    dead = [(i, r[4], r[5]) for i, r in enumerate(table) if r[5] > 0]
    if not dead:
        return None
    trials = [i for i, _, _ in dead]
    shown = trials[:10]
    more = "" if len(trials) <= 10 else f" (and {len(trials) - 10} more)"
    steps = sum(n for _, _, n in dead)
    first = min(s for _, s, _ in dead)
    return (
        f"{name}: no particle's weight carried the measurement at {steps} step(s) (first at time step {first}) "
        f"in trial(s) {shown}{more}: every weight was zero or invalid, so those steps kept the previous "
        "particles (nonfinite='recover') and those trials' log-evidence is -inf. Look at the measurement "
        "model (a tiny noise scale, NaN outputs) or use more particles; nonfinite='raise' makes this an error"
    )


def warn_dead_steps(name: str, table: List[List[int]]) -> None:
    """Warn (``RuntimeWarning``) with :func:`dead_step_warning`'s text, if any."""
    text = dead_step_warning(name, table)
    if text is not None:
        warnings.warn(text, RuntimeWarning, stacklevel=3)


#: a cloud whose every coordinate spans at most this many units of round-off (relative to its size)
#: is collapsed: its particles are copies of fewer than two distinct points
COLLAPSE_ROUNDOFF = 64


def collapsed(particles: torch.Tensor) -> torch.Tensor:
    """``(B,)`` bool, on the device: whether the cloud ``particles (B, N, d)`` has collapsed, every
    coordinate's range over the particles being within round-off of its size
    (``COLLAPSE_ROUNDOFF eps (1 + max |x|)``): fewer than two distinct particles, whatever the
    weights (copies of one point share equal weights, so the ESS stays high)."""
    lo, hi = torch.aminmax(particles.detach(), dim=1)  # (B, d)
    size = torch.maximum(lo.abs(), hi.abs()).amax(-1)
    tol = COLLAPSE_ROUNDOFF * torch.finfo(particles.dtype).eps * (1.0 + size)
    return (hi - lo).amax(-1) <= tol


#: what puts spread back into a collapsed cloud, for a particle filter that resamples
COLLAPSE_REMEDY = (
    "regularisation after resampling (regularization=..., or relative to the spread: "
    "regularization_relative=...), or a filter for deterministic dynamics (filter=lag1_flow, kpff, lpf, the "
    "ensemble Kalman filters)"
)


def collapse_warning(
    name: str, first: List[int], count: List[int], steps: int, remedy: Optional[str] = None
) -> Optional[str]:
    """The text of the collapse warning, or ``None``: ``first[b]`` the first step (1-based, 0 none) at
    which trial b's cloud had stayed collapsed (:func:`collapsed`) through two steps running while its
    ESS read 2 or more (a degenerate weight, ESS near 1, shows itself; a single degenerate step whose
    copies the model's noise spreads again is not a collapse) and ``count[b]`` in how many of the
    ``steps``. ``remedy``: the filter's own way to put spread back (its ``collapse_remedy``;
    default :data:`COLLAPSE_REMEDY`)."""
    trials = [b for b, f in enumerate(first) if f > 0]
    if not trials:
        return None
    shown = ", ".join(f"trial {b} from step {first[b]} ({count[b]} of {steps} steps)" for b in trials[:5])
    more = f" and {len(trials) - 5} more trials" if len(trials) > 5 else ""
    return (
        f"{name}: the particle cloud collapsed to fewer than 2 distinct particles (a spread within round-off) in "
        f"{shown}{more}. The ESS does not show it: copies of one point have equal weights. Its estimates then "
        "follow one point and its evidence is that point's. A model without noise needs spread put back: "
        f"{remedy or COLLAPSE_REMEDY}"
    )


def _check_step_gradient(name: str, step: int, grad: torch.Tensor) -> None:
    """A tensor hook: raise if the gradient reaching a step's input is non-finite (the step, or a
    later one not yet reported, produced it); one host read."""
    if grad is None:  # an undefined gradient (no path from the loss)
        return
    bad = ~torch.isfinite(grad.reshape(grad.shape[0], -1)).all(1)
    if bool(bad.any()):
        raise NonFiniteError(
            name, step, torch.nonzero(bad).flatten().tolist(), what="gradient (backward pass) of the step's computation"
        )


#: state fields a step returns but the next step does not read (their gradients come from the trace)
_OUTPUTS_ONLY = frozenset(("estimate", "ess", "log_evidence_increment", "g_eff", "invalid", "n_repaired"))
_INPUT_FIELDS: dict = {}


def guard_state(state, name: str, step: int):
    """Hook the gradient check onto ``state``'s tensors that the next step reads and that require
    grad, for ``step`` (1-based: the step this state is the input of); returns ``state``."""
    keys = _INPUT_FIELDS.get(type(state))
    if keys is None:
        keys = _INPUT_FIELDS[type(state)] = tuple(
            f.name for f in dataclasses.fields(state) if f.name not in _OUTPUTS_ONLY
        )
    for k in keys:
        t = getattr(state, k)
        if isinstance(t, torch.Tensor) and t.requires_grad and t.dim() >= 1:
            t.register_hook(functools.partial(_check_step_gradient, name, step))
    return state


_HOOKS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def replace_parameter_hooks(owner, model: torch.nn.Module) -> None:
    """Remove ``owner``'s hooks of its last call and add :func:`parameter_hooks` for this one."""
    for h in _HOOKS.pop(owner, []):
        h.remove()
    _HOOKS[owner] = parameter_hooks(model, owner.name)


def parameter_hooks(model: torch.nn.Module, name: str) -> list:
    """Hooks that raise :class:`NonFiniteError` when a parameter of ``model``'s gradient is
    non-finite (naming the parameter, as the user sets it: ``psi`` for ``parametrizations.psi.original``).
    Returns the handles."""
    handles = []
    for pname, p in model.named_parameters():
        if not p.requires_grad:
            continue
        label = pname.replace("parametrizations.", "").replace(".original", "")

        def hook(g, label=label):
            if g is not None and not bool(torch.isfinite(g).all()):
                raise NonFiniteError(
                    name,
                    0,
                    [],
                    what=f"gradient of the model parameter {label!r} (every step's "
                    "gradient was finite: the parameter's own terms overflowed)",
                )
            return g

        handles.append(p.register_hook(hook))
    return handles


def table_to_host(t: torch.Tensor) -> List[List[int]]:
    """The :func:`first_steps` table on the host (one read)."""
    return t.cpu().tolist()


__all__: Tuple[str, ...] = (
    "first_steps",
    "raise_first",
    "raise_never_measured",
    "dead_step_warning",
    "warn_dead_steps",
    "guard_state",
    "parameter_hooks",
    "replace_parameter_hooks",
    "QUANTITIES",
)
