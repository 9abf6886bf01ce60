"""Input validation shared by models, filters and the experiment runner.

Every check raises ``ValueError``/``TypeError`` (never ``assert``, which ``python -O`` strips)
with a message naming the argument, what was expected and what arrived, in the style of
``torch.distributions``.
"""

from __future__ import annotations

import math
import numbers
import re
from typing import Optional, Sequence, Union

import numpy as np
import torch

from torchflow.core.errors import ArgumentError, ArgumentTypeError, NonFiniteError  # noqa: F401 (re-exported)

Dim = Union[int, None]


def check_tensor(
    name: str,
    x,
    shape: Sequence[Dim],
    letters: str,
    *,
    dtype: Optional[torch.dtype] = None,
    device: Optional[torch.device] = None,
) -> torch.Tensor:
    """Check that ``x`` is a tensor of the given shape (``None`` = any size) and dtype/device.

    Args:
        name: argument name used in the error message.
        x: the value to check.
        shape: expected sizes; ``None`` entries match anything.
        letters: the letters of the shape, e.g. ``"(B, T, m)"``.
        dtype, device: if given, ``x`` must match them.

    Returns:
        ``x`` unchanged.
    """
    if not isinstance(x, torch.Tensor):
        raise ArgumentTypeError(f"{name}: expected a torch.Tensor {letters}, got {type(x).__name__}")
    expected = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
    if x.dim() != len(shape) or any(s is not None and s != xs for s, xs in zip(shape, x.shape)):
        raise ArgumentError(f"{name}: expected {letters} = {expected}, got {tuple(x.shape)}")
    if dtype is not None and x.dtype != dtype:
        raise ArgumentTypeError(f"{name}: expected dtype {dtype} (the model's), got {x.dtype}")
    if device is not None and x.device.type != torch.device(device).type:
        raise ArgumentError(f"{name}: expected device {device} (the model's), got {x.device}")
    return x


def check_finite(name: str, x: torch.Tensor) -> torch.Tensor:
    """Raise if ``x`` holds NaN or inf, reporting how many and the first offending trial."""
    if x.is_floating_point() and x.numel() > 2**16 and bool(torch.isfinite(x.sum())):
        return x  # a sum is NaN or infinite if any term is: one reduction, no (x.shape) mask
    bad = ~torch.isfinite(x)
    if bool(bad.any()):
        n_bad = int(bad.sum())
        trials = torch.nonzero(bad.reshape(x.shape[0], -1).any(-1)).flatten().tolist() if x.dim() else []
        raise ArgumentError(f"{name}: {n_bad} non-finite value(s) (NaN/inf), in trial(s) {trials[:10]}")
    return x


def _off_diagonal(cov: torch.Tensor) -> torch.Tensor:
    """The off-diagonal entries of ``cov (..., k, k)`` as a view ``(..., k - 1, k)`` where possible (the
    flattened matrix after its first entry, read in rows of ``k + 1``: each row's last entry is a
    diagonal one), else a copy."""
    k = cov.shape[-1]
    if k < 2:
        return cov[..., :0, :0]
    flat = cov.reshape(*cov.shape[:-2], k * k)
    return flat[..., 1:].reshape(*cov.shape[:-2], k - 1, k + 1)[..., :k]


def check_psd(name: str, cov: torch.Tensor, *, tol: float = 1e-10) -> torch.Tensor:
    """Raise if the batch of matrices ``cov (..., d, d)`` is not symmetric positive semi-definite.

    The tolerance is relative to each matrix's largest diagonal entry, and at least ``d`` machine
    epsilons of its dtype (float32 round-off): a matrix that passes factors under
    :func:`~torchflow.core.linalg.safe_cholesky`'s jitter. The error names the first offending batch
    index (the trial, for ``(B, d, d)`` inputs).
    """
    if cov.dim() < 2 or cov.shape[-1] != cov.shape[-2]:
        raise ArgumentError(f"{name}: expected square matrices (..., d, d), got {tuple(cov.shape)}")
    if cov.dim() == 3 and cov.shape[0] > 1 and (cov.stride(0) == 0 or bool((cov == cov[:1]).all())):
        check_psd(name, cov[:1], tol=tol)  # one prior shared by every trial: check it once
        return cov
    check_finite(name, cov.reshape(-1, *cov.shape[-2:]) if cov.dim() > 2 else cov.unsqueeze(0))
    tol = max(tol, cov.shape[-1] * torch.finfo(cov.dtype).eps) if cov.is_floating_point() else tol
    diag = cov.diagonal(dim1=-2, dim2=-1)
    scale = diag.abs().amax(-1)
    if not _off_diagonal(cov).any():
        # diagonal matrices (a declared Q = 0 or R = r I, a diagonal prior): their diagonal is their
        # spectrum, checked in O(d^2) instead of a factorisation
        bad_sym, eig_min = torch.zeros_like(scale, dtype=torch.bool), diag.amin(-1)
    else:
        asym = (cov - cov.transpose(-1, -2)).abs().amax((-1, -2))
        bad_sym = asym > 1e-8 * scale
        # fast path: Cholesky of cov + tol * scale * I succeeds for every PSD matrix
        eye = torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)
        _, info = torch.linalg.cholesky_ex(0.5 * (cov + cov.transpose(-1, -2)) + (tol * scale)[..., None, None] * eye)
        if not bool(bad_sym.any()) and not bool((info > 0).any()):
            return cov
        eig_min = torch.linalg.eigvalsh(0.5 * (cov + cov.transpose(-1, -2))).amin(-1)
    bad_psd = eig_min < -tol * scale
    bad = (bad_sym | bad_psd).reshape(-1)
    if bool(bad.any()):
        idx = int(torch.nonzero(bad)[0])
        why = (
            "not symmetric"
            if bool(bad_sym.reshape(-1)[idx])
            else (f"not positive semi-definite (smallest eigenvalue {float(eig_min.reshape(-1)[idx]):.3g})")
        )
        if cov.dim() == 2:
            raise ArgumentError(f"{name}: covariance is {why}")
        raise ArgumentError(f"{name}: covariance at batch index {idx} (trial) is {why}")
    return cov


def as_real_tensor(name: str, x, *, finite: bool = True, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """``x`` (a tensor, array or nested sequence of real numbers) as a ``dtype`` tensor: an
    :class:`ArgumentTypeError` naming ``name`` for anything else (a string, ``None``, complex numbers,
    whose imaginary part a cast would drop), and with ``finite`` an :class:`ArgumentError` for NaN/inf."""
    t = x if isinstance(x, torch.Tensor) else None
    if t is None:  # through numpy: Python floats stay float64 (torch.as_tensor would round them to float32)
        try:
            a = np.asarray(x)
            t = torch.as_tensor(a) if a.dtype.kind in "biuf" else None  # bool, int, float: not str, object, complex
        except (TypeError, ValueError, RuntimeError):
            pass
    if t is None or t.is_complex() or t.device.type == "meta":
        what = type(x).__name__ if t is None else f"a {t.dtype} tensor on {t.device}"
        raise ArgumentTypeError(f"{name}: expected a tensor, array or sequence of real numbers, got {what}")
    t = t.to(dtype)
    if finite and not bool(torch.isfinite(t).all()):
        raise ArgumentError(f"{name}: expected finite numbers, got {int((~torch.isfinite(t)).sum())} NaN/inf value(s)")
    return t


def check_learnable(learnable, names: Sequence[str]) -> set:
    """The set of parameter names to learn: ``True`` (all of ``names``), ``False`` (none), one name or
    a collection of names; an :class:`ArgumentError` for anything else."""
    if isinstance(learnable, bool):
        return set(names) if learnable else set()
    try:
        learn = {learnable} if isinstance(learnable, str) else set(learnable)
    except TypeError:
        learn = None
    if learn is None or not learn <= set(names):
        raise ArgumentError(f"learnable: expected a bool or a subset of {list(names)}, got {learnable!r}")
    return learn


def check_same(name: str, x: torch.Tensor, ref: torch.Tensor, ref_name: str = "the model") -> None:
    """Raise if ``x`` and ``ref`` differ in dtype or device (names both sides)."""
    if x.dtype != ref.dtype:
        raise ArgumentTypeError(f"{name}: dtype {x.dtype} does not match {ref_name}'s dtype {ref.dtype}")
    if x.device != ref.device:
        raise ArgumentError(f"{name}: device {x.device} does not match {ref_name}'s device {ref.device}")


def check_count(name: str, value, *, minimum: int = 1, hint: str = "") -> int:
    """An integer ``>= minimum`` (a bool, a fractional float or a string is refused, not truncated)."""
    ok = (isinstance(value, numbers.Integral) and not isinstance(value, bool)) or (
        isinstance(value, float) and value.is_integer()
    )
    if not ok or int(value) < minimum:
        what = "a positive integer" if minimum == 1 else f"an integer >= {minimum}"
        raise ArgumentError(f"{name}: expected {what}{hint}, got {value!r} ({type(value).__name__})")
    return int(value)


def allocation_failure(err: BaseException) -> Optional[str]:
    """``None`` unless ``err`` is an allocator's out-of-memory error (torch's CPU or CUDA allocator,
    Python's ``MemoryError``); then what it asked for, e.g. ``" (one allocation of 477 GiB)"``, or ``""``."""
    text = str(err)
    if not (
        isinstance(err, (torch.OutOfMemoryError, MemoryError))
        or "can't allocate memory" in text
        or "out of memory" in text.lower()
    ):
        return None
    asked = re.search(r"allocate (\d+) bytes|allocate ([\d.]+ [KMGT]iB)", text)
    if asked is None:
        return ""
    return (
        f" (one allocation of {int(asked.group(1)) / 2**30:.3g} GiB)"
        if asked.group(1)
        else f" (one allocation of {asked.group(2)})"
    )


def check_choice(name: str, value, choices):
    """``value`` if it is one of ``choices``, else a ValueError naming them."""
    if value not in choices:
        raise ArgumentError(f"{name}: expected one of {tuple(choices)}, got {value!r}")
    return value


def check_number(name: str, v, ok=None, what: str = "a finite number", *, integer: bool = False) -> float:
    """``float(v)`` (``int(v)`` if ``integer``) if ``v`` is a finite real number (not a bool) with
    ``ok(v)``; else an :class:`ArgumentError` naming ``name``, ``what`` was expected and ``v``.

    NaN and infinities are refused whatever ``ok`` says (``nan <= 0`` is False, so a bare
    comparison lets NaN through)."""
    real = isinstance(v, numbers.Real) and not isinstance(v, bool)
    if integer:
        real = real and math.isfinite(float(v)) and float(v) == int(v)
    if not real or not math.isfinite(float(v)) or (ok is not None and not ok(v)):
        raise ArgumentError(f"{name}: expected {what}, got {v!r}")
    return int(v) if integer else float(v)


def check_positive(name: str, v) -> float:
    """A finite number > 0 (see :func:`check_number`)."""
    return check_number(name, v, lambda x: x > 0, "a finite number > 0")


def check_nonnegative(name: str, v) -> float:
    """A finite number >= 0 (see :func:`check_number`)."""
    return check_number(name, v, lambda x: x >= 0, "a finite number >= 0")


def shape_str(shape) -> str:
    """``(2, 3)``; a 1-d shape as ``(5,)``."""
    return "(" + ", ".join(str(int(s)) for s in shape) + ")" if len(shape) != 1 else f"({int(shape[0])},)"


def check_float_tensor(x, name: str, expected: str, ndim: Optional[int] = None) -> torch.Tensor:
    """Raise unless ``x`` is a floating-point tensor (with ``ndim`` dimensions if given);
    ``expected`` is the shape in letters, e.g. ``"(B, N)"``."""
    if not isinstance(x, torch.Tensor):
        raise ArgumentError(f"{name}: expected a torch.Tensor of shape {expected}, got {type(x).__name__}")
    if ndim is not None and x.dim() != ndim:
        raise ArgumentError(f"{name}: expected shape {expected}, got {shape_str(x.shape)}")
    if not torch.is_floating_point(x):
        raise ArgumentError(f"{name}: expected a floating-point tensor of shape {expected}, got dtype {x.dtype}")
    return x


def check_same_device(a: torch.Tensor, b: torch.Tensor, name_a: str, name_b: str) -> None:
    """Raise unless ``a`` is on ``b``'s device."""
    if a.device != b.device:
        raise ArgumentError(f"{name_a}: expected a tensor on the same device as {name_b} ({b.device}), got {a.device}")
