"""Recorded observations: read a series from a file, check it against a model, and the filters'
prior without true states.

File formats (:func:`load_observations`):

* ``.csv`` (UTF-8 text, commas between columns): one row per time step; every numeric column is a
  measurement coordinate, in order, except a column named ``t`` or ``time`` (the observation times,
  which must step uniformly forwards). A header row is optional (a first row that is not all
  numbers is a header, and must hold names only); without one every column is a coordinate. A
  line starting with ``#`` is a comment, an empty line is skipped; a row of empty cells (``,``;
  ``""`` in a one-column file, as ``csv`` and pandas write it) is a step with nothing observed. An
  empty cell or ``nan`` is a coordinate not observed at that step (NaN).
* ``.npy``: a float array ``(T, m)`` (one series), ``(B, T, m)`` (B series) or ``(T,)`` (``m = 1``);
  no time column.
* ``.npz`` (``numpy.savez``; :func:`load_recording`): ``observations`` as the ``.npy`` array, and
  optionally ``states`` (``(T+1, d)`` or ``(B, T+1, d)``: the true states, ``states[..., 0, :]`` the
  initial state; with them the run is scored as a simulated one), ``prior_mean`` (``(d,)`` or
  ``(B, d)``) and ``prior_cov`` (``(d, d)`` or ``(B, d, d)``, symmetric positive semi-definite),
  given together. No other array: a misspelt name is refused, not ignored.

NaN marks a coordinate not observed and is passed through to the filters; an infinite value is
refused, naming its row and column.

The prior: the one given (the ``.npz`` file's ``prior_mean`` / ``prior_cov``, or the command line's
``prior.mean`` / ``prior.cov``: :func:`prior_from_spec`); else, with true states, the model's
``initial_belief`` at the true initial state (as in a simulation); else (:func:`declared_prior`) a
model's :meth:`initial_belief` takes the true initial
states (the runner draws the prior around them in simulations); recorded data have none, so the
filters start from the model's *declared* prior, ``model.declared_prior(batch_size) -> (mean (B, d),
cov (B, d, d))``, computed from the model's parameters (differentiably: a stationary prior of
learnable parameters follows them). The built-in models declare one (the linear-Gaussian model:
``N(m0, P0)``; the acoustic model: ``N(x0, diag(prior_std^2))``; the skewed-t Poisson model: its known
``x_0 = 0``); Lorenz-96's prior is drawn around the true state, so it has none and recorded data need
a prior passed explicitly (``run_experiment(..., prior=(mean, cov))``).
"""

from __future__ import annotations

import csv
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Tuple, Union

import numpy as np
import torch

from torchflow.core.covariances import DiagonalCovariance
from torchflow.core.errors import ArgumentError, ArgumentTypeError

__all__ = [
    "Recording",
    "load_recording",
    "prior_from_spec",
    "NPZ_ARRAYS",
    "load_observations",
    "read_recording",
    "check_observations",
    "check_time_step",
    "declared_prior",
    "TIME_COLUMNS",
]

#: names of the time column of a CSV file (case-insensitive)
TIME_COLUMNS = ("t", "time")
#: relative tolerance of the check of the time column's spacing against the model's ``dt``
DT_RTOL = 1e-6


def _read_csv(path: Path, name: str) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """``(values (T, m), times (T,) or None)`` of a CSV file (see the module docstring). Errors
    name the file's own line numbers (comment and blank lines counted)."""
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader, kept = csv.reader(fh), []
            for r in reader:
                blank = not r or (len(r) == 1 and r[0] != "" and not r[0].strip())  # '""': one empty cell
                if not blank and not r[0].lstrip().startswith("#"):  # ",,": a step with nothing observed
                    kept.append((reader.line_num, r))
    except UnicodeDecodeError as e:
        raise ArgumentError(
            f"{name}: expected a text CSV file (UTF-8), but {path} is not text (byte 0x{e.object[e.start]:02x} at "
            f"position {e.start}); a NumPy array must be saved as .npy"
        ) from None
    except csv.Error as e:
        raise ArgumentError(f"{name}: expected a CSV file, could not read {path} ({e})") from None
    if not kept:
        raise ArgumentError(f"{name}: expected a CSV file with one row per time step, got an empty file {path}")
    lines, rows = [n for n, _ in kept], [r for _, r in kept]
    for sep, word in ((";", "semicolons"), ("\t", "tabs"), ("|", "bars")):
        if len(rows[0]) == 1 and sep in rows[0][0] and all(len(r) == 1 for r in rows[:5]):
            raise ArgumentError(
                f"{name}: expected comma-separated columns, got {word} in {path} (line {lines[0]}: "
                f"{rows[0][0][:60]!r}); save the file with commas as separators"
            )

    def number(cell: str) -> Optional[float]:
        c = cell.strip()
        if c == "":
            return math.nan
        try:
            return float(c)
        except ValueError:
            return None

    header: Optional[List[str]] = None
    if any(number(c) is None for c in rows[0]):
        words = [c.strip() for c in rows[0] if number(c) is None]
        numbers = [c.strip() for c in rows[0] if c.strip() and number(c) is not None]
        # names and numbers in one row: a data row with a typo, or a header with a number; but a time
        # column's name beside numbered columns (pandas' integer column labels: time,0,1,2) is a header
        if numbers and not all(w.lower() in TIME_COLUMNS for w in words):
            raise ArgumentError(
                f"{name}: expected a header of column names or a row of numbers in line {lines[0]} of {path}, "
                f"got both ({', '.join(repr(c.strip()) for c in rows[0][:6])}); fix the cell that is not a "
                "number, or name every column"
            )
        header, rows, lines = [c.strip() for c in rows[0]], rows[1:], lines[1:]
    if not rows:
        raise ArgumentError(f"{name}: expected at least one row of numbers after the header of {path}, got none")
    width = len(header) if header is not None else len(rows[0])
    time_col = None
    if header is not None:
        found = [j for j, h in enumerate(header) if h.lower() in TIME_COLUMNS]
        if len(found) > 1:
            raise ArgumentError(
                f"{name}: expected at most one time column ({' or '.join(TIME_COLUMNS)}), got "
                f"{[header[j] for j in found]} in {path}"
            )
        time_col = found[0] if found else None
    values = np.empty((len(rows), width), dtype=np.float64)
    for i, row in enumerate(rows):
        if len(row) != width:
            raise ArgumentError(
                f"{name}: expected {width} columns in every row of {path}, got {len(row)} in line {lines[i]}"
            )
        for j, cell in enumerate(row):
            v = number(cell)
            if v is None:
                col = f"column {j + 1}" + (f" ({header[j]})" if header is not None else "")
                raise ArgumentError(
                    f"{name}: expected numbers (empty or nan: not observed), got {cell.strip()!r} in "
                    f"line {lines[i]}, {col} of {path}"
                )
            values[i, j] = v
    empty_tail = 0
    while empty_tail < len(rows) - 1 and all(not c.strip() for c in rows[-1 - empty_tail]):
        empty_tail += 1
    if empty_tail:  # kept (a step with nothing observed), but said: a spreadsheet's trailing empty rows look so
        warnings.warn(
            f"{name}: the last {empty_tail} row(s) of {path} (from line {lines[-empty_tail]}) hold only empty "
            "cells: they are steps with nothing observed; delete them if they are not",
            stacklevel=3,
        )
    if time_col is None:
        return values, None
    times = values[:, time_col]
    return np.delete(values, time_col, axis=1), times


def _read_npy(path: Path, name: str) -> np.ndarray:
    with open(path, "rb") as fh:
        magic = fh.read(6)
    if magic != b"\x93NUMPY":
        raise ArgumentError(
            f"{name}: expected a NumPy .npy file, but {path} does not start with NumPy's header "
            "(a CSV text file must end in .csv; an array saved with numpy.save ends in .npy)"
        )
    try:
        arr = np.load(path, allow_pickle=False)
    except ValueError as e:  # an object array (pickled), or not an .npy file
        raise ArgumentError(f"{name}: expected a numeric .npy array, could not read {path} ({e})") from None
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)) or np.issubdtype(
        arr.dtype, np.bool_
    ):
        raise ArgumentError(f"{name}: expected a numeric (float or integer) array in {path}, got dtype {arr.dtype}")
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim not in (2, 3):
        raise ArgumentError(f"{name}: expected an array (T, m), (B, T, m) or (T,) in {path}, got shape {arr.shape}")
    return arr.astype(np.float64)


#: the arrays a ``.npz`` recording may hold (``observations`` required)
NPZ_ARRAYS = ("observations", "states", "prior_mean", "prior_cov")


def _numeric(arr: np.ndarray, what: str) -> np.ndarray:
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)) or np.issubdtype(
        arr.dtype, np.bool_
    ):
        raise ArgumentError(f"{what}: expected a numeric (float or integer) array, got dtype {arr.dtype}")
    return arr.astype(np.float64)


def _read_npz(path: Path, name: str) -> dict:
    """The arrays of a ``.npz`` recording (:data:`NPZ_ARRAYS`), float64; the observations
    ``(T, m)`` or ``(B, T, m)`` (``(T,)``: ``m = 1``)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (ValueError, OSError) as e:  # not a zip of arrays, or an object (pickled) array
        raise ArgumentError(f"{name}: expected a NumPy .npz file (numpy.savez), could not read {path} ({e})") from None
    unknown = sorted(set(arrays) - set(NPZ_ARRAYS))
    if unknown:
        raise ArgumentError(
            f"{name}: expected arrays named {', '.join(NPZ_ARRAYS)} in {path.name}, got {', '.join(unknown)} too "
            "(numpy.savez(path, observations=yy, states=xx, ...) names them)"
        )
    if "observations" not in arrays:
        raise ArgumentError(
            f"{name}: expected an array named observations in {path.name}, got {', '.join(sorted(arrays)) or 'none'}"
        )
    out = {k: _numeric(v, f"{name} ({path.name}: {k})") for k, v in arrays.items()}
    obs = out["observations"]
    if obs.ndim == 1:
        out["observations"] = obs = obs[:, None]
    if obs.ndim not in (2, 3):
        raise ArgumentError(
            f"{name}: expected observations (T, m), (B, T, m) or (T,) in {path.name}, got shape {obs.shape}"
        )
    return out


def read_recording(path: Union[str, Path], *, name: str = "data") -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """``(observations, times)`` of a ``.csv``, ``.npy`` or ``.npz`` file (the module docstring's
    formats): observations ``(T, m)`` or ``(B, T, m)`` float64 (NaN: not observed), the CSV time
    column ``(T,)`` or ``None``. ``name``: the argument named in errors."""
    p = _regular_file(path, name)
    suffix = p.suffix.lower()
    if suffix == ".csv":
        return _read_csv(p, name)
    if suffix == ".npy":
        return _read_npy(p, name), None
    if suffix == ".npz":
        return _read_npz(p, name)["observations"], None
    raise ArgumentError(f"{name}: expected a .csv, .npy or .npz file, got {p.name!r}")


def _regular_file(path, name: str) -> Path:
    if not isinstance(path, (str, Path)):
        raise ArgumentTypeError(f"{name}: expected the path of a .csv, .npy or .npz file, got {type(path).__name__}")
    p = Path(path).expanduser()
    if not p.exists():
        raise ArgumentError(f"{name}: file not found: {p}")
    if not p.is_file():  # reading a pipe or a device would block or never end
        kind = "a folder" if p.is_dir() else "a named pipe" if p.is_fifo() else "a device or socket"
        raise ArgumentError(f"{name}: expected a regular .csv, .npy or .npz file, got {kind}: {p}")
    return p


def check_observations(
    observations, model=None, *, name: str = "observations", require_observed: bool = True
) -> torch.Tensor:
    """``observations`` ``(T, m)`` or ``(B, T, m)`` checked: a floating-point tensor (an array is
    converted), at least one step, ``m`` equal to ``model.obs_dim`` where a model is given, no
    infinite value and none whose square overflows (NaN: not observed, kept), and, with
    ``require_observed``, at least one observed value in every series; on the model's dtype and
    device where given."""
    if isinstance(observations, np.ndarray):
        observations = torch.from_numpy(np.asarray(observations, dtype=np.float64))
    if not isinstance(observations, torch.Tensor):
        raise ArgumentTypeError(f"{name}: expected a tensor (T, m) or (B, T, m), got {type(observations).__name__}")
    if not observations.is_floating_point():
        raise ArgumentTypeError(f"{name}: expected a floating-point tensor, got {observations.dtype}")
    if observations.dim() not in (2, 3) or observations.shape[-2] == 0 or observations.shape[0] == 0:
        raise ArgumentError(
            f"{name}: expected (T, m) or (B, T, m) with at least one time step, got {tuple(observations.shape)}"
        )
    if model is not None:
        m = model.obs_dim
        if model.structure.padded_measurements:
            raise ArgumentError(
                f"{name}: {type(model).__name__}'s measurements are padded sets with a mask; "
                "recorded data are series (T, m) of a model with a fixed measurement dimension"
            )
        if observations.shape[-1] != m:
            raise ArgumentError(
                f"{name}: expected m = {m} measurement coordinates (columns) for "
                f"{type(model).__name__}, got {observations.shape[-1]} (shape "
                f"{tuple(observations.shape)}; a CSV time column named t or time is not counted)"
            )
        observations = observations.to(dtype=model.dtype, device=model.device)

    def at(where) -> str:
        return f"row {where[-2] + 1}, column {where[-1] + 1}" + (f" of series {where[0]}" if len(where) == 3 else "")

    inf = torch.isinf(observations)
    if bool(inf.any()):
        raise ArgumentError(
            f"{name}: expected finite values (NaN: not observed), got {int(inf.sum())} infinite, the first at "
            f"{at(torch.nonzero(inf)[0].tolist())}"
        )
    limit = math.sqrt(torch.finfo(observations.dtype).max)  # a square beyond it overflows
    huge = observations.abs() > limit
    if bool(huge.any()):
        first = torch.nonzero(huge)[0].tolist()
        raise ArgumentError(
            f"{name}: expected values below {limit:.3g} in magnitude ({observations.dtype}: their squares "
            f"overflow), got {float(observations[tuple(first)]):.3g} at {at(first)}; rescale the series"
        )
    if require_observed:
        empty = torch.isnan(observations).flatten(-2).all(-1).reshape(-1)
        if bool(empty.any()):
            which = torch.nonzero(empty).squeeze(1).tolist()
            what = "the series" if observations.dim() == 2 else f"series {which[:10]}"
            raise ArgumentError(
                f"{name}: {what} hold{'s' if len(which) == 1 else ''} no observation (every value is NaN): "
                "there is nothing to filter"
            )
    return observations


def check_time_step(times: Optional[np.ndarray], model, *, name: str = "data") -> None:
    """The file's time column (``times``; ``None``: none) must be finite and step forwards
    uniformly (relative tolerance :data:`DT_RTOL`): filters assume one step between rows. Where
    ``model`` has a scalar time step ``dt``, the step must also equal it. Errors name the first
    bad row."""
    if times is None or len(times) < 2:
        return
    bad = np.nonzero(~np.isfinite(times))[0]
    if len(bad):
        raise ArgumentError(
            f"{name}: expected finite observation times in the time column, got {times[bad[0]]} in row {bad[0] + 1}"
        )
    steps = np.diff(times)
    dt = getattr(model, "dt", None) if model is not None else None
    if isinstance(dt, torch.Tensor):
        dt = float(dt) if dt.numel() == 1 else None
    dt = float(dt) if isinstance(dt, (int, float)) else None
    scale = abs(dt) if dt else max(abs(float(steps[0])), 1e-300)
    tol = DT_RTOL * scale
    back = np.nonzero(steps <= 0)[0]
    if len(back):
        i = int(back[0])
        raise ArgumentError(
            f"{name}: expected observation times that increase row by row, got {times[i + 1]:g} after "
            f"{times[i]:g} in row {i + 2} of the time column"
        )
    uneven = np.nonzero(np.abs(steps - steps[0]) > tol)[0]
    if len(uneven):
        i = int(uneven[0])
        raise ArgumentError(
            f"{name}: expected a uniform time step, got {steps[0]:g} and then {steps[i]:g} (row {i + 2} of the "
            "time column); a varying time step is not supported: resample the series"
        )
    if dt is not None and abs(steps[0] - dt) > tol:
        raise ArgumentError(
            f"{name}: the time column's steps are {steps[0]:g}, but {type(model).__name__} assumes "
            f"observations every dt = {dt:g} (set the model's dt, e.g. model.dt={steps[0]:g}, or "
            "resample the series)"
        )


def load_observations(path: Union[str, Path], model=None, *, name: str = "data") -> torch.Tensor:
    """Recorded observations from a ``.csv`` or ``.npy`` file (formats in the module docstring),
    as a float64 tensor ``(T, m)`` (``(B, T, m)`` for a 3-D ``.npy``): NaN where not observed.

    With ``model``: the column count must be its ``m``, the tensor comes on its dtype and device,
    and a CSV time column must step by its ``dt`` where it has one (:func:`check_time_step`).
    Errors name ``name`` (the command line's setting, ``data``), the file and what is wrong: a file
    not found, a wrong column count, a non-numeric cell (its line and column), an infinite value."""
    values, times = read_recording(path, name=name)
    obs = check_observations(torch.from_numpy(values), model, name=f"{name} ({Path(path).name})")
    check_time_step(times, model, name=name)
    return obs


@dataclass
class Recording:
    """A recording (:func:`load_recording`): ``observations`` ``(T, m)`` or ``(B, T, m)`` (NaN: not
    observed); ``states`` ``(T+1, d)`` or ``(B, T+1, d)`` (the truth, ``states[..., 0, :]`` the
    initial state) or ``None``; the prior ``prior_mean`` ``(d,)`` / ``(B, d)`` and ``prior_cov``
    ``(d, d)`` / ``(B, d, d)``, or ``None``. Tensors on the model's dtype and device."""

    observations: torch.Tensor
    states: Optional[torch.Tensor] = None
    prior_mean: Optional[torch.Tensor] = None
    prior_cov: Optional[torch.Tensor] = None

    @property
    def prior(self) -> Optional[Tuple[torch.Tensor, torch.Tensor]]:
        return None if self.prior_mean is None else (self.prior_mean, self.prior_cov)


def _positive_definite(cov: torch.Tensor, what: str) -> None:
    if not bool(torch.isfinite(cov).all()):
        raise ArgumentError(f"{what}: expected finite values, got NaN or infinite entries")
    asym = (cov - cov.transpose(-1, -2)).abs().amax()
    if float(asym) > 1e-10 * max(float(cov.abs().amax()), 1e-300):
        raise ArgumentError(f"{what}: expected a symmetric covariance, got entries that differ by {float(asym):.3g}")
    low = float(torch.linalg.eigvalsh(cov).amin())  # a known state (a zero covariance) is a prior too
    if low < -1e-10 * max(float(cov.abs().amax()), 1e-300):
        raise ArgumentError(f"{what}: expected a positive semi-definite covariance, got an eigenvalue {low:.3g}")


def check_prior(mean, cov, d: int, *, name: str = "prior") -> Tuple[torch.Tensor, torch.Tensor]:
    """``(mean (d,) or (B, d), cov (d, d) or (B, d, d))`` checked: finite, the state dimension
    ``d``, the covariance symmetric positive semi-definite; float64 tensors. Errors name ``name``."""
    mean = torch.as_tensor(mean, dtype=torch.float64)
    cov = torch.as_tensor(cov, dtype=torch.float64)
    if mean.dim() not in (1, 2) or mean.shape[-1] != d:
        raise ArgumentError(f"{name} mean: expected shape ({d},) or (B, {d}), got {tuple(mean.shape)}")
    if not bool(torch.isfinite(mean).all()):
        raise ArgumentError(f"{name} mean: expected finite values, got NaN or infinite entries")
    if cov.dim() not in (2, 3) or tuple(cov.shape[-2:]) != (d, d):
        raise ArgumentError(f"{name} cov: expected shape ({d}, {d}) or (B, {d}, {d}), got {tuple(cov.shape)}")
    if mean.dim() == 2 and cov.dim() == 3 and mean.shape[0] != cov.shape[0]:
        raise ArgumentError(f"{name}: mean and cov give {mean.shape[0]} and {cov.shape[0]} trials; expected the same")
    _positive_definite(cov, f"{name} cov")
    return mean, cov


def prior_from_spec(mean, cov, d: int, *, name: str = "prior") -> Tuple[torch.Tensor, torch.Tensor]:
    """The prior of the command line (``prior.mean``, ``prior.cov``): ``mean`` a number (every
    coordinate) or ``d`` numbers; ``cov`` a number (times the identity), ``d`` variances or a
    ``d x d`` nested list. ``((d,), (d, d))`` float64, checked (:func:`check_prior`)."""

    def numbers(v, what):
        try:
            t = torch.as_tensor(v, dtype=torch.float64)
        except (TypeError, ValueError, RuntimeError):
            raise ArgumentError(f"{name}.{what}: expected numbers, got {v!r}") from None
        return t

    m, c = numbers(mean, "mean"), numbers(cov, "cov")
    if m.dim() == 0:
        m = m.expand(d).clone()
    if m.dim() != 1 or m.shape[0] != d:
        raise ArgumentError(f"{name}.mean: expected a number or {d} numbers (the state dimension), got {mean!r}")
    if c.dim() == 0:
        c = c * torch.eye(d, dtype=torch.float64)
    elif c.dim() == 1 and c.shape[0] == d:
        c = torch.diag(c)
    elif c.dim() != 2 or tuple(c.shape) != (d, d):
        raise ArgumentError(
            f"{name}.cov: expected a number (times the identity), {d} variances or a {d} x {d} list, got shape "
            f"{tuple(c.shape)}"
        )
    return check_prior(m, c, d, name=name)


def load_recording(path: Union[str, Path], model=None, *, name: str = "data") -> Recording:
    """A recording from a ``.csv``, ``.npy`` or ``.npz`` file (the module docstring's formats):
    the observations as :func:`load_observations` reads them and, from a ``.npz`` file, the true
    ``states`` and the prior where it holds them. With ``model``: every array is checked against its
    dimensions (``states`` ``(T+1, d)`` with the observations ``(T, m)``, ``(B, T+1, d)`` with
    ``(B, T, m)``; finite; the prior as :func:`check_prior`) and comes on its dtype and device."""
    p = _regular_file(path, name)
    if p.suffix.lower() != ".npz":
        return Recording(load_observations(p, model, name=name))
    arrays = _read_npz(p, name)
    where = f"{name} ({p.name})"
    obs = check_observations(torch.from_numpy(arrays["observations"]), model, name=where)
    rec = Recording(obs)
    to = (lambda t: t.to(dtype=model.dtype, device=model.device)) if model is not None else (lambda t: t)
    if "states" in arrays:
        x = torch.from_numpy(arrays["states"])
        T = obs.shape[-2]
        d = model.state_dim if model is not None else x.shape[-1]
        want = (T + 1, d) if obs.dim() == 2 else (obs.shape[0], T + 1, d)
        if tuple(x.shape) != want:
            raise ArgumentError(
                f"{where}: expected states of shape {want} (T + 1 rows: the initial state, then one per observation "
                f"row; d = {d}), got {tuple(x.shape)}"
            )
        if not bool(torch.isfinite(x).all()):
            bad = torch.nonzero(~torch.isfinite(x))[0].tolist()
            raise ArgumentError(f"{where}: expected finite states, got a NaN or infinite value at index {bad}")
        rec.states = to(x)
    given = [k for k in ("prior_mean", "prior_cov") if k in arrays]
    if len(given) == 1:
        other = "prior_cov" if given[0] == "prior_mean" else "prior_mean"
        raise ArgumentError(f"{where}: expected prior_mean and prior_cov together, got {given[0]} without {other}")
    if given:
        d = model.state_dim if model is not None else arrays["prior_mean"].shape[-1]
        mean, cov = check_prior(arrays["prior_mean"], arrays["prior_cov"], d, name=f"{where}: prior")
        if obs.dim() == 3:
            for t, what in ((mean, "prior_mean"), (cov, "prior_cov")):
                if t.dim() == (3 if what == "prior_cov" else 2) and t.shape[0] != obs.shape[0]:
                    raise ArgumentError(
                        f"{where}: {what} holds {t.shape[0]} trials, the observations {obs.shape[0]} series"
                    )
        rec.prior_mean, rec.prior_cov = to(mean), to(cov)
    return rec


def declared_prior(model, batch_size: int) -> Tuple[torch.Tensor, torch.Tensor]:
    """The filters' prior without true states: ``model.declared_prior(batch_size)``, checked to be
    ``(mean (B, d), cov (B, d, d))``. Call it where the parameters may have changed (each optimiser
    step): it is computed from them, and differentiable where they are. A model without one raises
    an error saying how to give it (or to pass a prior explicitly)."""
    from torchflow.models.base import StateSpaceModel

    fn = getattr(model, "declared_prior", None)
    if fn is None or getattr(type(model), "declared_prior", None) is StateSpaceModel.declared_prior:
        raise ArgumentError(
            f"model: {type(model).__name__} declares no prior without true states (its initial_belief needs them); "
            "recorded data need one: give the model a method declared_prior(batch_size) -> (mean (B, d), cov (B, "
            "d, d)), "
            "or give the prior: on the command line prior.mean=<number or d numbers> prior.cov=<number, d variances "
            "or d x d>, in a .npz recording as prior_mean and prior_cov (with its true states the prior is drawn "
            "around the initial state, as in a simulation), or run_experiment(..., prior=(mean, cov))"
        )
    mean, cov = fn(batch_size)
    d = model.state_dim
    kind = DiagonalCovariance if model.structure.prior_covariance == "diagonal" else torch.Tensor
    if not (
        isinstance(mean, torch.Tensor)
        and isinstance(cov, kind)
        and tuple(mean.shape) == (batch_size, d)
        and tuple(cov.shape) == (batch_size, d, d)
    ):
        got = tuple(getattr(mean, "shape", ())), tuple(getattr(cov, "shape", ()))
        form = (
            "a DiagonalCovariance of variances (B, d), as the model declares a diagonal prior"
            if kind is DiagonalCovariance
            else "a tensor"
        )
        raise ArgumentError(
            f"{type(model).__name__}.declared_prior: expected (mean (B, d), cov (B, d, d)) = "
            f"(({batch_size}, {d}), ({batch_size}, {d}, {d})), cov {form}; got {got}"
            + ("" if isinstance(cov, kind) else f" ({type(cov).__name__})")
        )
    return mean, cov
