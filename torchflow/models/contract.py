"""Checks of the model contract (:mod:`torchflow.models.base`), outside the models themselves.

* :func:`check_shapes`: every method a filter will call is evaluated once on a small batch, and an
  output of the wrong shape is an error naming the method, the expected and the received shape
  (a user model whose ``measure()`` returns ``(..., 1)`` where m = 2 would otherwise broadcast
  into plausible, wrong numbers). Once per model and dtype/device/batch layout; no host
  synchronisation (shapes are Python integers).
* :func:`check_dtype`, :func:`check_simulate_args`, :func:`check_covariances`: argument and
  parameter checks with clear errors.
"""

from __future__ import annotations

import itertools
import math
import weakref
from typing import Optional, Tuple

import torch

from torchflow.core.checks import check_count, check_psd
from torchflow.core.errors import ArgumentError, ArgumentTypeError, NonFiniteError
from torchflow.core.random import generator_hint
from torchflow.models.trials import trial_names

#: the Gaussian form's methods a filter reads (beyond the core)
GAUSSIAN_FORM = ("transition_mean", "transition_cov", "measure", "measurement_cov")

_checked: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()  # model -> set of checked keys


def check_dtype(model, who: str) -> None:
    """Raise unless the model is in float32 or float64 (the precisions filters support), with values
    (not on the meta device)."""
    if model.dtype not in (torch.float32, torch.float64):
        raise ArgumentTypeError(
            f"{who}: the model is in {model.dtype}; filters and simulation run in float32 or "
            "float64 (convert with model.double() or model.float())"
        )
    if model.device.type == "meta":
        raise ArgumentError(
            f"{who}: the model is on the meta device, which holds shapes but no values; filters and "
            "simulation need its numbers (model.to_empty(device=...) and load them, or build it on cpu)"
        )


def check_simulate_args(model, batch_size, steps, generator) -> Tuple[int, int]:
    """Validate :meth:`~torchflow.models.StateSpaceModel.simulate`'s arguments; returns
    ``(batch_size, steps)`` as ints."""
    who = f"{type(model).__name__}.simulate"
    batch_size = check_count(f"{who}: batch_size", batch_size)
    steps = check_count(f"{who}: steps", steps)
    if not isinstance(generator, torch.Generator):
        raise ArgumentTypeError(
            f"{who}: generator: expected a torch.Generator, got {type(generator).__name__}{generator_hint(generator)}"
        )
    check_dtype(model, who)
    return batch_size, steps


def check_simulated(who: str, traj, hint: Optional[str] = None) -> None:
    """Raise unless a simulated trajectory's states and observations are finite, naming the first
    (trial, step) and the count (one host read per simulation): non-finite simulated data come from
    the model (a parameter or a method returning NaN/inf), not from the observations' user.
    ``hint``: the model's own advice (its ``simulation_hint``, e.g. an integration step too large)."""
    for what, x in (("states", traj.states), ("observations", traj.observations)):
        bad = ~torch.isfinite(x).all(-1)  # (B, T)
        n = int(bad.sum())
        if n:
            b, t = (int(v) for v in torch.nonzero(bad)[0])
            step = t if what == "states" else t + 1
            raise NonFiniteError(
                who,
                step,
                sorted(set(torch.nonzero(bad)[:, 0].tolist())),
                what=f"simulated {what} ({n} (trial, step) pair(s), first trial {b})",
                hint=hint or "the model's parameters or methods give NaN/inf there",
            )


def check_parameters(model, who: str = "") -> None:
    """Raise unless every learnable parameter of ``model`` is finite as the model uses it (a
    constrained one, e.g. ``psi = exp(original)``, after its constraint), naming the parameter
    and its value. One host read; filters call it once per call (an optimiser step may have
    pushed a parameter to NaN or overflowed its constraint)."""
    values = {}
    parametrized = getattr(model, "parametrizations", None)
    for name, p in model.named_parameters():
        if not p.requires_grad:
            continue
        if name.startswith("parametrizations."):
            label = name.split(".")[1]
            if parametrized is not None and label in parametrized and "." not in label:
                values[label] = getattr(model, label)
            continue
        values[name] = p
    if not values:
        return
    with torch.no_grad():
        flags = torch.stack([~torch.isfinite(v).all() for v in values.values()]).tolist()
    for (name, v), bad in zip(values.items(), flags):
        if bad:
            shown = v.detach().flatten()[:4].tolist()
            raise ArgumentError(
                f"{who + ': ' if who else ''}{type(model).__name__}'s learnable parameter {name!r} is "
                f"not finite (values {shown}{' ...' if v.numel() > 4 else ''}); an optimiser step "
                "diverged (lower the learning rate) or it was set so"
            )


#: :func:`check_shapes` evaluates the covariances where their dense batch holds at most this many
#: numbers, and :func:`check_covariances` checks a constant one of at most this many
COVARIANCE_CHECK_NUMBERS = 2**24
#: above this many numbers (m > 256) a declared scalar R is checked by its declared scale alone (below,
#: the matrix the model gives is checked too: cheap, and it catches a subclass whose R no longer
#: matches its parent's declaration)
DECLARED_CHECK_NUMBERS = 2**16


def check_covariances(model, who: str = "") -> None:
    """Raise unless the constant transition and measurement covariances of a Gaussian-form model
    (``transition_cov()``, ``measurement_cov()``; state-dependent ones are skipped) are symmetric
    positive semi-definite, naming the model, the covariance and, for a parameter of the model,
    its name. Filters call it once per call (a learnable covariance may leave the cone after an
    optimiser step; :mod:`torchflow.core.constraints` keeps one valid by construction). Per-trial values
    (:func:`torchflow.inference.per_trial_values`) are checked trial by trial, ``(B, k, k)``; the
    error names the first bad trial. A matrix of more than :data:`COVARIANCE_CHECK_NUMBERS` numbers
    (``k > 4096``) is not formed for the check (a model of ``d = 10^5`` whose filters never form
    it); a declared scalar R (``measurement_noise_scale``) of more than :data:`DECLARED_CHECK_NUMBERS`
    numbers is checked by its scale. A diagonal matrix is checked on its diagonal (no factorisation)."""
    params = {id(p): n for n, p in model.named_parameters()}
    structure = model.structure
    for what, name in (("transition covariance", "transition_cov"), ("measurement covariance", "measurement_cov")):
        fn = getattr(model, name, None)
        if fn is None:
            continue
        k = model.state_dim if name == "transition_cov" else (model.obs_dim or 0)
        scale = structure.measurement_noise_scale if structure.measurement_noise == "scalar" else None
        if (
            name == "measurement_cov"
            and scale is not None
            and k * k > DECLARED_CHECK_NUMBERS
            or k * k > COVARIANCE_CHECK_NUMBERS
        ):  # not formed for a check: a declared R = r I by its scale
            if name == "measurement_cov" and scale is not None and not scale >= 0:
                raise ArgumentError(
                    f"{who + ': ' if who else ''}{type(model).__name__}'s {what} ({scale:g} I, "
                    "declared) is not positive semi-definite"
                )
            continue
        try:
            C = fn()
        except (NotImplementedError, TypeError, RuntimeError, ValueError):
            continue  # state-dependent: no constant matrix to check
        if not isinstance(C, torch.Tensor):
            continue
        per_trial = C.dim() == 3 and bool(trial_names(model))  # (B, k, k): one per trial, each checked
        if C.dim() != 2 and not per_trial:
            continue
        letters = "(d, d)" if name == "transition_cov" else "(m, m)"
        if tuple(C.shape[-2:]) != (k, k):  # the method's mistake, named as check_shapes names it
            _expect(who or type(model).__name__, f"{type(model).__name__}.{name}", C, (*C.shape[:-2], k, k), letters)
        pname = params.get(id(C))
        label = f"{type(model).__name__}'s {what}" + (f" (parameter {pname!r})" if pname else "")
        if C.requires_grad and not pname:
            label += " (built from learnable parameters)"
        check_psd(f"{who + ': ' if who else ''}{label}", C.detach())


def _expect(
    who: str, method: str, out, shape: Tuple[int, ...], expected: str, broadcast_ok: bool = False, where: str = ""
) -> None:
    """Raise unless ``out`` is a tensor of ``shape`` (or, with ``broadcast_ok``, broadcastable to it
    with the same trailing dimensions); ``where`` says on which inputs."""
    if not isinstance(out, torch.Tensor):
        raise ArgumentTypeError(
            f"{who}: {method} returned {type(out).__name__}{where}; expected a tensor {expected} = {tuple(shape)}"
        )
    got = tuple(out.shape)
    if got == tuple(shape):
        return
    if broadcast_ok and len(got) >= 2 and got[-2:] == tuple(shape[-2:]):
        lead, want = got[:-2], tuple(shape[:-2])  # leading dims broadcast to the batch (plain ints: no torch call)
        if len(lead) <= len(want) and all(g in (1, w) for g, w in zip(reversed(lead), reversed(want))):
            return
    raise ArgumentError(f"{who}: {method} returned shape {got}{where}; expected {expected} = {tuple(shape)}")


def check_shapes(model, x: torch.Tensor, who: str, *, gaussian: Optional[bool] = None) -> None:
    """Evaluate the model's methods once at the states ``x (B, d)`` and raise if an output has the
    wrong shape, naming the method, the expected and the received shape.

    Checked: the core's samplers and densities (``sample_transition -> (B, d)``,
    ``transition_log_prob -> (B,)``, ``sample_measurement -> (B, m)``, ``measurement_log_prob ->
    (B,)``) and, for a Gaussian-form model (or ``gaussian=True``), ``transition_mean -> (B, d)``,
    ``measure -> (B, m)``, ``transition_cov`` and ``measurement_cov`` (``(d, d)``/``(m, m)`` or
    batched; only where the batch of dense matrices holds at most :data:`COVARIANCE_CHECK_NUMBERS`
    numbers). The same again on the particles' layout ``(b, N, d)`` (the first trials, with ``N``
    unlike ``B``, ``d`` and ``m``, so that a method that flattens, transposes or keeps the first row
    is caught where it would broadcast), and ``transition_mean``/``measure`` on one point ``(d,)``
    (what their Jacobians differentiate, under ``vmap``). Draws use a generator of their own (the
    caller's streams are not advanced); no gradient is recorded. Done once per model, dtype, device
    and batch size. A model whose parameters hold per-trial values
    (:func:`torchflow.inference.per_trial_values`) is checked again, on every trial's particles and
    not on a lone point."""
    if gaussian is None:
        gaussian = bool(getattr(model, "_gaussian", False))
    per_trial = trial_names(model)  # values per trial now: every trial, no lone point
    key = (x.dtype, x.device, x.shape[0], gaussian, per_trial)
    done = _checked.setdefault(model, set())
    if key in done:
        return
    B, d, m = x.shape[0], model.state_dim, model.obs_dim
    g = torch.Generator(device=x.device).manual_seed(0)
    b = B if per_trial else min(B, 2)
    N = next(n for n in itertools.count(3) if n not in (B, b, d, m))  # unlike every other size
    particles = x[:b].unsqueeze(1).expand(b, N, d)
    with torch.no_grad():
        _check_layout(model, who, x, "B", gaussian, g)
        _check_layout(model, who, particles, "B, N", gaussian, g, " on the particles' layout")
        if gaussian and not per_trial:  # one point: what jacobian() differentiates
            name = type(model).__name__
            _expect(who, f"{name}.transition_mean", model.transition_mean(x[0]), (d,), "(d,)", where=" on one point")
            _expect(who, f"{name}.measure", model.measure(x[0]), (m,), "(m,)", where=" on one point")
    done.add(key)


def _check_layout(model, who: str, x: torch.Tensor, lead: str, gaussian: bool, g, where: str = "") -> None:
    """:func:`check_shapes` at states ``x (*L, d)`` whose leading dims ``L`` are named ``lead``."""
    L, d, m = tuple(x.shape[:-1]), model.state_dim, model.obs_dim
    name = type(model).__name__

    def expect(method, out, tail, letters, broadcast_ok=False):
        shape = "(" + ", ".join([lead, *letters]) + (",)" if not letters and "," not in lead else ")")
        if broadcast_ok:
            shape = f"({', '.join(letters)}) or {shape}"
        _expect(who, f"{name}.{method}", out, (*L, *tail), shape, broadcast_ok, where)

    if gaussian:  # first: the core's defaults are built from these
        # the covariances where their dense form is small: a model of d = 10^5 coordinates is not
        # asked for the (B, d, d) matrices that the filters running it never form
        small = math.prod(L) * max(d, m or 0) ** 2 <= COVARIANCE_CHECK_NUMBERS
        expect("transition_mean", model.transition_mean(x), (d,), ["d"])
        if small:
            expect("transition_cov", model.transition_cov(x), (d, d), ["d", "d"], broadcast_ok=True)
        expect("measure", model.measure(x), (m,), ["m"])
        if small:
            expect("measurement_cov", model.measurement_cov(x), (m, m), ["m", "m"], broadcast_ok=True)
    x1 = model.sample_transition(x, g)
    expect("sample_transition", x1, (d,), ["d"])
    expect("transition_log_prob", model.transition_log_prob(x1, x), (), [])
    z = model.sample_measurement(x1, g)
    expect("sample_measurement", z, (m,), ["m"])
    expect("measurement_log_prob", model.measurement_log_prob(z, x1), (), [])
