"""Evaluation metrics for batched Bayesian filters, and the registry of the metrics the runner reports.

Conventions: ``B`` trials, ``T`` time steps, ``d`` state dimension, ``C``
targets, ``k`` position dimension (2 or 3), ``N`` particles. All functions are
batched over trials and time (no Python loops over either), work for float32
and float64 on any device, and return tensors on the input device.

Assignment problems (OMAT, OSPA) are solved exactly. For up to
``tuning.get().assignment_brute_force_max`` (7) items on the larger side this is done by brute force
over all injective maps expressed as tensor ops: a ``(P, m)`` index tensor
built with :func:`itertools.permutations` is used to gather the costs of every
assignment at once. For larger problems the code falls back to
:func:`scipy.optimize.linear_sum_assignment`, which loops in Python over the
``B * T`` problems (on CPU); the resulting assignment is then gathered from the
torch cost tensor, so the returned value keeps autograd information.

The metric registry
-------------------
:data:`REGISTRY` (``name -> Metric``, in registration order) lists the per-step metrics that
:func:`torchflow.app.runner.run_experiment` computes for every filter they apply to. A :class:`Metric`
is a function ``compute(ctx) -> (B, T)`` of a :class:`MetricContext` (the filter's estimates, the
truth, the model, the metric settings, the filter's other outputs such as ``ess``), a test
``applies(ctx) -> bool`` and how a trial's value is taken from its ``T`` values. Each registered
metric that applies gives

* the summary column ``name``: the mean over trials and steps (``reduce_trial="mean"``) or over
  trials of the last step's value (``"last"``); with ``standard_error=True`` also ``name_se``, the
  standard error of that mean over trials (the trials' values' sd / sqrt(B));
* the per-trial column ``name``: the trial's mean over steps, or its last step's value; a metric
  with ``burn_in=True`` averages only the steps after the run's ``burn_in`` setting (the first
  ``burn_in`` steps dropped: the data-assimilation convention, a filter's spin-up not scored);
* the per-step column ``name``: the mean over trials at each step, and a panel of ``per_step.png``
  (``plot=True``) with the y label ``label``.

The summary table's columns are ``filter, n_particles, trials, steps``, the registered metrics in
registration order, and the runner's own columns
(:data:`torchflow.app.runner.score.RUN_COLUMNS`). Built in: ``mse`` and ``rmse`` (both after burn-in; ``rmse`` with
its standard error ``rmse_se``), ``omat``, ``ospa``, ``declared``, ``ess``, ``g_eff``. A new metric is one function
and one :func:`register` call
(:func:`unregister` removes it; :func:`registered` registers for a ``with`` block)::

    >>> from torchflow.core import metrics
    >>> from torchflow.app.runner import run_experiment
    >>> from torchflow.filters import KalmanFilter
    >>> from torchflow.models import SensorNetwork
    >>> def max_abs_error(ctx):
    ...     "``(B, T)``: ``max_j |xhat[b, t, j] - x[b, t, j]|`` of point estimates ``(B, T, d)``."
    ...     return (ctx.estimates - ctx.truth).abs().amax(-1)
    >>> _ = metrics.register(metrics.Metric("max_abs", "max |error|", max_abs_error))
    >>> model = SensorNetwork(d=4)
    >>> res = run_experiment(model, {"kf": KalmanFilter(model)}, trials=3, steps=4, progress=False)
    >>> res.summary[0]["max_abs"] > 0, "max_abs" in res.per_trial[0], "max_abs" in res.per_step[0]
    (True, True, True)
    >>> _ = metrics.unregister("max_abs")

Scoring reads the filters' saved chunks, so a metric registered after a run with a checkpoint
store (``resume=true``) is computed from the stored estimates without filtering again; the
filter outputs a chunk keeps are :data:`torchflow.app.runner.checkpoint.CHUNK_FIELDS`.
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import math
import re
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Callable, Dict, Iterator, List, Mapping, Optional

import torch

from torchflow.core import tuning
from torchflow.core.checks import check_float_tensor, check_same_device, shape_str
from torchflow.core.errors import ArgumentError, ArgumentTypeError

__all__ = [
    "mse",
    "rmse",
    "omat",
    "ospa",
    "ess",
    "log_evidence_relative_error",
    "lost_tracks",
    "Metric",
    "MetricContext",
    "REGISTRY",
    "RESERVED_NAMES",
    "register",
    "unregister",
    "registered",
    "applicable",
]


def _check_pair(x, ref, name: str, ref_name: str, letters: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Raise unless ``x`` is a floating-point tensor shaped like ``ref`` on its device; both in their common dtype."""
    expected = f"{letters} matching {ref_name} {shape_str(ref.shape)}"
    check_float_tensor(x, name, expected)
    if x.shape != ref.shape:
        raise ArgumentError(f"{name}: expected {expected}, got {shape_str(x.shape)}")
    check_same_device(x, ref, name, ref_name)
    return _promote(x, ref)


def _promote(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    dtype = torch.promote_types(a.dtype, b.dtype)
    return a.to(dtype), b.to(dtype)


@functools.lru_cache(maxsize=64)
def _injective_maps(n: int, m: int, device: torch.device) -> torch.Tensor:
    """All injective maps {0..m-1} -> {0..n-1} as a ``(P, m)`` long tensor."""
    perms = list(itertools.permutations(range(n), m))
    return torch.tensor(perms, dtype=torch.long, device=device).reshape(len(perms), m)


def _min_assignment_cost(cost: torch.Tensor) -> torch.Tensor:
    """Minimal total cost over injective assignments of rows to columns.

    Args:
        cost: ``(..., m, n)`` cost matrices with ``m <= n``.

    Returns:
        ``(...)`` tensor: ``min_pi sum_i cost[..., i, pi(i)]`` over injective
        ``pi: {0..m-1} -> {0..n-1}``.
    """
    *batch, m, n = cost.shape
    if m == 0:
        return cost.new_zeros(batch)
    flat = cost.reshape(-1, m, n)
    rows = torch.arange(m, device=cost.device)
    knobs = tuning.get()
    if n <= knobs.assignment_brute_force_max:
        maps = _injective_maps(n, m, cost.device)  # (P, m)
        chunk = max(1, knobs.assignment_chunk_elems // (maps.shape[0] * m))
        # Chunking only bounds memory; each chunk is one batched tensor op.
        out = [
            flat[s : s + chunk][:, rows, maps].sum(-1).amin(-1)  # (chunk, P, m) -> (chunk,)
            for s in range(0, flat.shape[0], chunk)
        ]
        result = torch.cat(out) if out else flat.new_zeros(0)
        return result.reshape(batch)

    # Fallback: Python loop over the B*T problems with scipy (CPU).
    from scipy.optimize import linear_sum_assignment

    cost_np = torch.nan_to_num(flat.detach().to("cpu", torch.float64), nan=1e300, posinf=1e300, neginf=-1e300).numpy()
    cols = torch.empty(flat.shape[0], m, dtype=torch.long)
    for i in range(flat.shape[0]):
        r, c = linear_sum_assignment(cost_np[i])
        cols[i, torch.as_tensor(r)] = torch.as_tensor(c)
    cols = cols.to(cost.device)
    picked = flat.gather(-1, cols.unsqueeze(-1)).squeeze(-1)  # (BT, m)
    return picked.sum(-1).reshape(batch)


def _pairwise_dist(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Euclidean distances ``(..., m, k), (..., n, k) -> (..., m, n)``."""
    return torch.linalg.vector_norm(a.unsqueeze(-2) - b.unsqueeze(-3), dim=-1)


def mse(estimates: torch.Tensor, states: torch.Tensor) -> torch.Tensor:
    """Squared estimation error averaged over the state dimension.

    Args:
        estimates: ``(B, T, d)`` state estimates.
        states: ``(B, T, d)`` true states.

    Returns:
        ``(B, T)`` tensor ``mean_j (estimates[..., j] - states[..., j])**2``.
    """
    check_float_tensor(states, "states", "(B, T, d)", ndim=3)
    estimates, states = _check_pair(estimates, states, "estimates", "states", "(B, T, d)")
    if states.shape[-1] == 0:
        raise ArgumentError("states: expected (B, T, d) with d >= 1, got d = 0")
    return (estimates - states).square().mean(dim=-1)


def rmse(estimates: torch.Tensor, states: torch.Tensor) -> torch.Tensor:
    """Root-mean-square error over the state coordinates, per trial and step (the data-assimilation
    RMSE; its average over the steps after a burn-in is the usual score).

    Args:
        estimates: ``(B, T, d)`` state estimates.
        states: ``(B, T, d)`` true states.

    Returns:
        ``(B, T)`` tensor ``sqrt(mean_j (estimates[..., j] - states[..., j])**2)``.
    """
    return mse(estimates, states).sqrt()


def omat(est_positions: torch.Tensor, true_positions: torch.Tensor) -> torch.Tensor:
    """Optimal mass transfer (OMAT) error with ``p = 1`` (Li & Coates, omat.m).

    For each trial and step computes
    ``min_pi (1/C) sum_c ||true[c] - est[pi(c)]||_2`` over permutations ``pi``
    of the ``C`` targets (solved as in the module docstring; gradients flow).

    Args:
        est_positions: ``(B, T, C, k)`` estimated target positions, ``k`` in
            ``{2, 3}``.
        true_positions: ``(B, T, C, k)`` true target positions.

    Returns:
        ``(B, T)`` OMAT error (same units as the positions).
    """
    check_float_tensor(true_positions, "true_positions", "(B, T, C, k)", ndim=4)
    ref = shape_str(true_positions.shape)
    if true_positions.shape[-1] not in (2, 3):
        raise ArgumentError(f"true_positions: expected (B, T, C, k) with k in {{2, 3}}, got {ref}")
    if true_positions.shape[-2] == 0:
        raise ArgumentError(f"true_positions: expected (B, T, C, k) with C >= 1, got {ref}")
    est_positions, true_positions = _check_pair(
        est_positions, true_positions, "est_positions", "true_positions", "(B, T, C, k)"
    )
    dist = _pairwise_dist(true_positions, est_positions)  # (B, T, C, C)
    return _min_assignment_cost(dist) / true_positions.shape[-2]


def ospa(
    X: torch.Tensor,
    Y: torch.Tensor,
    cutoff: float = 40.0,
    order: float = 1.0,
    X_mask: Optional[torch.Tensor] = None,
    Y_mask: Optional[torch.Tensor] = None,
) -> torch.Tensor:
    """OSPA distance between point sets (Schuhmacher et al. 2008), of fixed or varying cardinality.

    With ``m = |X| <= n = |Y|`` (the sets are swapped otherwise),

    ``d = ((1/n) * (min_pi sum_{i<m} min(c, ||x_i - y_pi(i)||)**p + c**p * (n - m)))**(1/p)``

    where ``pi`` ranges over injective maps of the ``m`` items into the ``n``
    items (solved as in the module docstring). ``d = 0`` when ``m = n = 0``.

    Args:
        X: ``(B, T, m, k)`` first point set per trial and step.
        Y: ``(B, T, n, k)`` second point set per trial and step.
        cutoff: Cut-off ``c > 0``.
        order: Order ``p >= 1``.
        X_mask, Y_mask: optional ``(B, T, m)`` / ``(B, T, n)`` bool masks of the real items: sets
            whose cardinality varies over trials and steps (an unknown number of sources) are
            padded to ``m``/``n`` items. Padded items are matched as "absent": a real item paired
            with an absent one costs ``c^p``, two absent ones cost 0, so the minimal perfect
            matching of the padded ``K x K`` problem (``K = max(m, n)``) is the OSPA numerator of
            each problem, divided by its own ``max(|X|, |Y|)``, all in one batched call.
    """
    check_float_tensor(X, "X", "(B, T, m, k)", ndim=4)
    check_float_tensor(Y, "Y", f"(B, T, n, k) matching X {shape_str(X.shape)} in B, T, k", ndim=4)
    if Y.shape[:2] != X.shape[:2] or Y.shape[-1] != X.shape[-1]:
        raise ArgumentError(
            f"Y: expected (B, T, n, k) matching X {shape_str(X.shape)} in B, T, k, got {shape_str(Y.shape)}"
        )
    if X.shape[-1] == 0:
        raise ArgumentError(f"X: expected (B, T, m, k) with k >= 1, got {shape_str(X.shape)}")
    check_same_device(Y, X, "Y", "X")
    cutoff, order = float(cutoff), float(order)
    if not (math.isfinite(cutoff) and cutoff > 0):
        raise ArgumentError(f"cutoff: expected a finite float > 0, got {cutoff}")
    if not (math.isfinite(order) and order >= 1):
        raise ArgumentError(f"order: expected a finite float >= 1, got {order}")
    X, Y = _promote(X, Y)
    if X_mask is not None or Y_mask is not None:
        return _ospa_masked(X, Y, cutoff, order, X_mask, Y_mask)
    if X.shape[-2] > Y.shape[-2]:
        X, Y = Y, X
    m, n = X.shape[-2], Y.shape[-2]
    if n == 0:
        return X.new_zeros(X.shape[:2])
    cost = _pairwise_dist(X, Y).clamp(max=cutoff).pow(order)  # (B, T, m, n)
    total = _min_assignment_cost(cost) + cutoff**order * (n - m)
    return (total / n).pow(1.0 / order)


def _ospa_masked(X, Y, cutoff, order, X_mask, Y_mask) -> torch.Tensor:
    """OSPA of padded sets with masks of their real items (see :func:`ospa`)."""
    B, T, m = X.shape[:3]
    n = Y.shape[2]
    for name, mask, size, what in (("X_mask", X_mask, m, "m"), ("Y_mask", Y_mask, n, "n")):
        if mask is not None and (
            not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool or tuple(mask.shape) != (B, T, size)
        ):
            got = shape_str(mask.shape) if isinstance(mask, torch.Tensor) else type(mask).__name__
            raise ArgumentError(
                f"{name}: expected a bool tensor (B, T, {what}) = ({B}, {T}, {size}), got {got}"
                + (f" of {mask.dtype}" if isinstance(mask, torch.Tensor) else "")
            )
    xm = torch.ones(B, T, m, dtype=torch.bool, device=X.device) if X_mask is None else X_mask.to(X.device)
    ym = torch.ones(B, T, n, dtype=torch.bool, device=X.device) if Y_mask is None else Y_mask.to(X.device)
    K = max(m, n)
    if K == 0:
        return X.new_zeros(B, T)
    pad = lambda P, M, k: (
        torch.cat([P, P.new_zeros(B, T, K - k, P.shape[-1])], 2),
        torch.cat([M, M.new_zeros(B, T, K - k)], 2),
    )
    X, xm = pad(X, xm, m)
    Y, ym = pad(Y, ym, n)
    cp = cutoff**order
    real = _pairwise_dist(X, Y).clamp(max=cutoff).pow(order)  # (B, T, K, K)
    both = xm.unsqueeze(-1) & ym.unsqueeze(-2)
    one = xm.unsqueeze(-1) ^ ym.unsqueeze(-2)
    cost = torch.where(both, real, torch.where(one, torch.full_like(real, cp), torch.zeros_like(real)))
    total = _min_assignment_cost(cost)
    size = torch.maximum(xm.sum(-1), ym.sum(-1)).to(X.dtype)
    return torch.where(size > 0, (total / size.clamp_min(1)).pow(1.0 / order), torch.zeros_like(total))


def ess(log_weights: torch.Tensor) -> torch.Tensor:
    """Effective sample size ``1 / sum_i w_i**2`` of normalised weights.

    Computed in log space from unnormalised log-weights as
    ``exp(2 * logsumexp(lw) - logsumexp(2 * lw))``, so it is invariant to
    adding a constant to ``log_weights`` and does not overflow.

    Args:
        log_weights: ``(..., N)`` unnormalised log-weights (``-inf`` allowed
            for zero weights), ``N >= 1``.

    Returns:
        ``(...)`` effective sample size in ``[1, N]``.
    """
    check_float_tensor(log_weights, "log_weights", "(..., N)")
    if log_weights.dim() == 0 or log_weights.shape[-1] == 0:
        raise ArgumentError(f"log_weights: expected (..., N) with N >= 1, got {shape_str(log_weights.shape)}")
    lse = torch.logsumexp(log_weights, dim=-1)
    lse2 = torch.logsumexp(2.0 * log_weights, dim=-1)
    return torch.exp(2.0 * lse - lse2)


def log_evidence_relative_error(log_evidence: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """Relative squared error of log-evidence estimates per trial.

    Computes ``((log_evidence - reference) / reference)**2``. Its mean over
    trials is the "relative MSE of log Z" of Pal & Coates (2019), Table I.

    Args:
        log_evidence: ``(B,)`` estimated log marginal likelihoods ``log Zhat``.
        reference: ``(B,)`` reference (true) log marginal likelihoods ``log Z``.

    Returns:
        ``(B,)`` relative squared error.
    """
    check_float_tensor(reference, "reference", "(B,)", ndim=1)
    log_evidence, reference = _check_pair(log_evidence, reference, "log_evidence", "reference", "(B,)")
    return ((log_evidence - reference) / reference).square()


def lost_tracks(omat_per_step: torch.Tensor, threshold: float = 2.0) -> torch.Tensor:
    """Flags trials whose time-averaged OMAT error exceeds a threshold.

    Args:
        omat_per_step: ``(B, T)`` OMAT error per trial and step (e.g. from
            :func:`omat`), ``T >= 1``.
        threshold: Loss threshold (meters); a trial is lost when
            ``mean_t omat_per_step[b, t] > threshold`` (strict).

    Returns:
        ``(B,)`` boolean tensor, ``True`` for lost trials.
    """
    check_float_tensor(omat_per_step, "omat_per_step", "(B, T)", ndim=2)
    if omat_per_step.shape[1] == 0:
        raise ArgumentError(f"omat_per_step: expected (B, T) with T >= 1, got {shape_str(omat_per_step.shape)}")
    threshold = float(threshold)
    if not math.isfinite(threshold):
        raise ArgumentError(f"threshold: expected a finite float, got {threshold}")
    return omat_per_step.mean(dim=1) > threshold


# --------------------------------------------------------------------------- the metric registry


@dataclass(frozen=True, eq=False)
class MetricContext:
    """What a metric sees of one filter's scored trials (``B`` trials, ``T`` steps, CPU float64).

    Attributes:
        model: the model (``model.structure.has_positions``; ``model.positions(x)`` maps states
            ``(..., d)`` to target positions ``(..., C, k)``).
        filter: the filter scored (``n_particles``, ``estimates_evidence``, ...).
        estimates: point estimates ``(B, T, d)``, or for set estimators (the localisers) padded
            sets of positions ``(B, T, K, k)`` whose real items ``mask`` marks.
        truth: ``(B, T, d)`` true states; ``None`` on recorded data (the metrics that need them,
            ``needs_truth``, are left out).
        mask: ``None`` for point estimates; ``(B, T, K)`` bool for sets.
        outputs: the filter's other outputs over the ``B`` trials, those it produces of
            ``ess (B, T)``, ``g_eff (B, T)``, ``log_evidence (B,)``, ``n_repaired (B,)``,
            ``underflow (B, S, M)``.
        settings: the run's metric settings ``ospa_cutoff``, ``ospa_order``, ``lost_threshold``,
            ``burn_in``.
    """

    model: Any
    filter: Any
    estimates: torch.Tensor
    truth: Optional[torch.Tensor]
    mask: Optional[torch.Tensor] = None
    outputs: Mapping[str, torch.Tensor] = field(default_factory=dict)
    settings: Mapping[str, float] = field(default_factory=dict)

    @property
    def kind(self) -> str:
        """``"sets"`` (padded sets with a ``mask``) or ``"point"`` (one estimate per trial and step)."""
        return "point" if self.mask is None else "sets"

    @property
    def shape(self) -> tuple:
        """``(B, T)``: the shape every metric returns."""
        return tuple(self.estimates.shape[:2])

    @functools.cached_property
    def est_positions(self) -> torch.Tensor:
        """``(B, T, C, k)`` estimated positions (sets: the estimates ``(B, T, K, k)`` themselves)."""
        return self.estimates if self.mask is not None else self.model.positions(self.estimates)

    @functools.cached_property
    def true_positions(self) -> torch.Tensor:
        """``(B, T, C, k)`` true positions."""
        return self.model.positions(self.truth)


def point_estimates(ctx: MetricContext) -> bool:
    """``applies`` of a metric of point estimates ``(B, T, d)`` (the default)."""
    return ctx.kind == "point"


def tracking(ctx: MetricContext) -> bool:
    """``applies`` of a metric of target positions: point estimates of a model with positions."""
    return ctx.kind == "point" and bool(ctx.model.structure.has_positions)


def sets(ctx: MetricContext) -> bool:
    """``applies`` of a metric of the localisers' sets ``(B, T, K, k)``."""
    return ctx.kind == "sets"


_REDUCTIONS = (None, "mean", "last")
_YSCALES = ("linear", "log", "per_particle")
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
#: column names the runner writes itself (summary, per-trial and per-step files): no metric may take one
RESERVED_NAMES = frozenset(
    {
        "filter",
        "n_particles",
        "trials",
        "steps",
        "trial",
        "step",
        "lost",
        "omat_kept_mean",
        "omat_kept_sd",
        "underflows",
        "log_evidence",
        "log_evidence_se",
        "log_evidence_relmse",
        "lost_tracks",
        "lost_trials",
        "lost_trial",
        "lost_step",
        "repaired",
        "sec_per_step",
        "warmup_sec",
        "path",
        "error",
    }
)


def _expect(ok: bool, arg: str, what: str, got) -> None:
    if not ok:
        raise ArgumentTypeError(f"{arg}: expected {what}, got {got!r} ({type(got).__name__})")


@dataclass(frozen=True)
class Metric:
    """One per-step metric of the runner's tables (see the module docstring).

    Attributes:
        name: the column name (letters, digits, ``_``; not one of :data:`RESERVED_NAMES`).
        label: the per-step figure's y label (units included, e.g. ``"OMAT (m)"``).
        compute: ``compute(ctx: MetricContext) -> (B, T)`` tensor, the value per trial and step.
        applies: ``applies(ctx) -> bool``: whether the metric is defined for this filter and model
            (default :func:`point_estimates`); where it is not, its columns are empty.
        reduce_trial: a trial's value: ``"mean"`` over its steps, ``"last"`` step's, or ``None``:
            ``"mean"`` for point estimates, ``"last"`` for sets (a localiser's value is that of
            the sets it declares after the last measurement). The summary value is the mean of
            the ``B x T`` values (``"mean"``) or of the ``B`` last-step values (``"last"``); an
            integer or bool ``compute`` gives integer per-trial values with ``"last"``.
        higher_is_better: ``True`` for scores (ESS), ``False`` for errors; for readers of the table.
        plot: whether ``per_step.png`` has a panel of it.
        yscale: that panel's axis: ``"linear"``, ``"log"``, or ``"per_particle"``: the values
            divided by each filter's ``n_particles`` (a log axis when a fraction is below 0.1).
        needs_truth: whether ``compute`` reads the true states (``ctx.truth``, ``true_positions``);
            such a metric is left out on recorded data, which have none.
        burn_in: a trial's value (``reduce_trial="mean"``), hence the summary's, averages only the
            steps after the run's ``burn_in`` setting; the per-step values keep every step.
        standard_error: the summary also has the column ``name + "_se"``: the standard error of
            the summary value over trials (sd of the trials' values / sqrt(B); empty for B = 1).
    """

    name: str
    label: str
    compute: Callable[[MetricContext], torch.Tensor]
    applies: Callable[[MetricContext], bool] = point_estimates
    reduce_trial: Optional[str] = None
    higher_is_better: bool = False
    plot: bool = True
    yscale: str = "linear"
    needs_truth: bool = True
    burn_in: bool = False
    standard_error: bool = False

    def __post_init__(self):
        _expect(
            isinstance(self.name, str) and bool(_NAME.match(self.name)),
            "name",
            "a column name (letters, digits, _; not starting with a digit)",
            self.name,
        )
        if self.name in RESERVED_NAMES:
            raise ArgumentError(
                f"name: {self.name!r} is a column the runner writes itself; reserved: "
                f"{', '.join(sorted(RESERVED_NAMES))}"
            )
        _expect(isinstance(self.label, str), "label", "a string (the figure's y label)", self.label)
        _expect(callable(self.compute), "compute", "a callable compute(ctx) -> (B, T) tensor", self.compute)
        _expect(callable(self.applies), "applies", "a callable applies(ctx) -> bool", self.applies)
        if self.reduce_trial not in _REDUCTIONS:
            raise ArgumentError(f"reduce_trial: expected one of {list(_REDUCTIONS)}, got {self.reduce_trial!r}")
        for arg in ("higher_is_better", "plot", "needs_truth", "burn_in", "standard_error"):
            _expect(isinstance(getattr(self, arg), bool), arg, "a bool", getattr(self, arg))
        if self.yscale not in _YSCALES:
            raise ArgumentError(f"yscale: expected one of {list(_YSCALES)}, got {self.yscale!r}")

    @property
    def columns(self) -> tuple:
        """The metric's summary columns: ``name``, and ``name_se`` with ``standard_error``."""
        return (self.name, f"{self.name}_se") if self.standard_error else (self.name,)

    def first_step(self, ctx: MetricContext) -> int:
        """The first step a trial's mean counts: the run's ``burn_in`` for a ``burn_in`` metric, else 0."""
        return int(ctx.settings.get("burn_in", 0)) if self.burn_in else 0

    @property
    def doc(self) -> str:
        """The docstring of ``compute`` (its formula and shapes)."""
        return (self.compute.__doc__ or "").strip()

    def trial_reduction(self, ctx: MetricContext) -> str:
        """``"mean"`` or ``"last"`` for ``ctx`` (see ``reduce_trial``)."""
        return self.reduce_trial or ("last" if ctx.kind == "sets" else "mean")

    def evaluate(self, ctx: MetricContext) -> torch.Tensor:
        """``compute(ctx)``, checked to be a ``(B, T)`` tensor; an error names the metric."""
        try:
            value = self.compute(ctx)
        except Exception as err:
            raise RuntimeError(f"metric {self.name!r}: compute failed: {type(err).__name__}: {err}") from err
        if not isinstance(value, torch.Tensor) or tuple(value.shape) != ctx.shape:
            got = shape_str(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
            raise ArgumentError(
                f"metric {self.name!r}: compute returned {got}, expected (B, T) = {shape_str(ctx.shape)}"
            )
        return value.detach()


_REGISTRY: Dict[str, Metric] = {}
#: ``name -> Metric`` in registration order (a read-only view; change it with :func:`register`)
REGISTRY: Mapping[str, Metric] = MappingProxyType(_REGISTRY)


def register(metric: Metric, *, replace: bool = False) -> Metric:
    """Add ``metric`` to :data:`REGISTRY` (last; ``replace=True``: replace the metric of that
    name in its place) and return it."""
    _expect(isinstance(metric, Metric), "metric", "a torchflow.core.metrics.Metric", metric)
    _expect(isinstance(replace, bool), "replace", "a bool", replace)
    if metric.name in _REGISTRY and not replace:
        raise ArgumentError(
            f"metric: a metric named {metric.name!r} is already registered "
            f"(unregister({metric.name!r}) first, or register(..., replace=True))"
        )
    taken = {c for m in _REGISTRY.values() if m.name != metric.name for c in m.columns}
    clash = sorted(taken & set(metric.columns))
    if clash:
        raise ArgumentError(f"metric: {metric.name!r} would write the column {clash[0]!r}, another metric's")
    _REGISTRY[metric.name] = metric
    return metric


def unregister(name: str) -> Metric:
    """Remove the metric ``name`` from :data:`REGISTRY` and return it."""
    if name not in _REGISTRY:
        raise KeyError(f"name: no metric {name!r} is registered; registered: {', '.join(_REGISTRY)}")
    return _REGISTRY.pop(name)


@contextlib.contextmanager
def registered(*metrics: Metric) -> Iterator[None]:
    """Register ``metrics`` for a ``with`` block, then unregister them."""
    added = []
    try:
        for m in metrics:
            added.append(register(m).name)
        yield
    finally:
        for name in added:
            _REGISTRY.pop(name, None)


def applicable(ctx: MetricContext) -> List[Metric]:
    """The registered metrics that apply to ``ctx``, in registration order (without true states,
    ``ctx.truth is None``: those that do not need them)."""
    out = []
    for m in _REGISTRY.values():
        if ctx.truth is None and m.needs_truth:
            continue
        try:
            if m.applies(ctx):
                out.append(m)
        except Exception as err:
            raise RuntimeError(f"metric {m.name!r}: applies failed: {type(err).__name__}: {err}") from err
    return out


def _mse(ctx: MetricContext) -> torch.Tensor:
    """``(B, T)``: ``mse[b, t] = (1/d) sum_j (xhat[b, t, j] - x[b, t, j])**2`` of the point
    estimates ``xhat (B, T, d)`` against the true states ``x (B, T, d)`` (:func:`mse`)."""
    return mse(ctx.estimates, ctx.truth)


def _rmse(ctx: MetricContext) -> torch.Tensor:
    """``(B, T)``: ``rmse[b, t] = sqrt((1/d) sum_j (xhat[b, t, j] - x[b, t, j])**2)`` of the point
    estimates ``xhat (B, T, d)`` against the true states ``x (B, T, d)`` (:func:`rmse`); a trial's
    value is its mean over the steps after ``burn_in``."""
    return rmse(ctx.estimates, ctx.truth)


def _omat(ctx: MetricContext) -> torch.Tensor:
    """``(B, T)``: ``omat[b, t] = min_pi (1/C) sum_c ||p[b, t, c] - phat[b, t, pi(c)]||_2`` over
    permutations ``pi`` of the ``C`` targets, of the estimated and true positions
    ``phat, p (B, T, C, k)`` (:func:`omat`)."""
    return omat(ctx.est_positions, ctx.true_positions)


def _ospa(ctx: MetricContext) -> torch.Tensor:
    """``(B, T)``: the OSPA distance (cut-off ``c = ospa_cutoff``, order ``p = ospa_order``)
    between the estimated positions ``(B, T, C, k)`` (sets: the declared items of
    ``(B, T, K, k)``) and the true positions ``(B, T, C, k)``:
    ``((1/n) (min_pi sum_{i<m} min(c, ||x_i - y_pi(i)||)**p + c**p (n - m)))**(1/p)`` with
    ``m <= n`` the two sets' sizes (:func:`ospa`)."""
    return ospa(
        ctx.est_positions,
        ctx.true_positions,
        cutoff=ctx.settings.get("ospa_cutoff", 40.0),
        order=ctx.settings.get("ospa_order", 1.0),
        X_mask=ctx.mask,
    )


def _declared(ctx: MetricContext) -> torch.Tensor:
    """``(B, T)`` integer: ``declared[b, t] = sum_K mask[b, t, K]``, the number of sources a
    localiser declares after step ``t``."""
    return ctx.mask.sum(-1)


def _ess(ctx: MetricContext) -> torch.Tensor:
    """``(B, T)``: the filter's effective sample size before resampling,
    ``ess[b, t] = 1 / sum_i w[b, t, i]**2`` of its normalised weights ``w (B, T, N)`` (:func:`ess`)."""
    return ctx.outputs["ess"]


def _g_eff(ctx: MetricContext) -> torch.Tensor:
    """``(B, T)``: a Gaussian-sum filter's effective number of Gaussians,
    ``g_eff[b, t] = 1 / sum_g alpha[b, t, g]**2`` of its mixture weights ``alpha (B, T, G)``."""
    return ctx.outputs["g_eff"]


def _tracking_or_sets(ctx: MetricContext) -> bool:
    """Point estimates of a model with positions, or the localisers' sets."""
    return tracking(ctx) or sets(ctx)


def _has_ess(ctx: MetricContext) -> bool:
    return "ess" in ctx.outputs


def _has_g_eff(ctx: MetricContext) -> bool:
    return "g_eff" in ctx.outputs


for _m in (
    Metric("mse", "MSE", _mse, yscale="log", burn_in=True),
    Metric("rmse", "RMSE", _rmse, yscale="log", burn_in=True, standard_error=True),
    Metric("omat", "OMAT (m)", _omat, tracking),
    Metric("ospa", "OSPA (m)", _ospa, _tracking_or_sets),
    Metric("declared", "declared sources", _declared, sets, plot=False, needs_truth=False),
    Metric("ess", "ESS", _ess, _has_ess, higher_is_better=True, yscale="per_particle", needs_truth=False),
    Metric("g_eff", "G_eff", _g_eff, _has_g_eff, higher_is_better=True, plot=False, needs_truth=False),
):
    register(_m)
del _m
