"""Score a filter's chunks: the summary row, per-trial and per-step metrics; the result container."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

import torch

from torchflow.app.runner.plan import RunPlan, filter_chunk
from torchflow.core import metrics
from torchflow.core.errors import ArgumentError
from torchflow.filters.base import Filter
from torchflow.filters.kalman import KalmanFilter
from torchflow.models.base import StateSpaceModel, Trajectory

#: the first columns of the summary table
FIXED_COLUMNS = ("filter", "n_particles", "trials", "steps")
#: the runner's own summary columns (not per-step metrics), each group after the registered metric
#: it names (``None``: after every metric; a group whose metric is not registered comes before it)
RUN_COLUMNS = (
    ("omat", ("omat_kept_mean", "omat_kept_sd")),
    ("declared", ("underflows",)),
    (
        None,
        (
            "log_evidence",
            "log_evidence_se",
            "log_evidence_relmse",
            "lost_tracks",
            "lost_trials",
            "repaired",
            "sec_per_step",
            "warmup_sec",
            "path",
            "error",
        ),
    ),
)


def summary_columns() -> List[str]:
    """The summary table's columns now: :data:`FIXED_COLUMNS`, each metric of
    :data:`torchflow.core.metrics.REGISTRY` in registration order, and :data:`RUN_COLUMNS`."""
    after = {anchor: list(cols) for anchor, cols in RUN_COLUMNS}
    tail = after.pop(None, [])
    cols = list(FIXED_COLUMNS)
    for name, metric in metrics.REGISTRY.items():
        cols += [*metric.columns, *after.pop(name, [])]
    return cols + [c for group in after.values() for c in group] + tail


class _SummaryColumns(Sequence):
    """A live view of :func:`summary_columns` (a sequence of column names that follows the registry)."""

    def __len__(self):
        return len(summary_columns())

    def __getitem__(self, i):
        return summary_columns()[i]

    def __iter__(self):
        return iter(summary_columns())

    def __contains__(self, name):
        return name in summary_columns()

    def __eq__(self, other):
        return isinstance(other, (list, tuple, Sequence)) and list(other) == summary_columns()

    __hash__ = None

    def __add__(self, other):
        return summary_columns() + list(other)

    def __radd__(self, other):
        return list(other) + summary_columns()

    def __repr__(self):
        return repr(summary_columns())


#: the summary table's columns (:func:`summary_columns`, read on each use, so a metric
#: registered with :func:`torchflow.core.metrics.register` is a column of every table made after)
SUMMARY_COLUMNS: Sequence[str] = _SummaryColumns()


@dataclass
class ExperimentResult:
    """Tidy results.

    Attributes:
        summary: one dict per filter with :data:`SUMMARY_COLUMNS` (``None`` where undefined).
        per_trial: one dict per filter x trial: each registered metric that applies (built in: mse,
            omat, ospa, ess, g_eff; localisers: ospa, declared), log_evidence, lost (tracking
            models); localisers: underflows.
        per_step: one dict per filter x step with the registered metrics' means over trials.
        trajectory: the simulated data (CPU tensors); recorded data: ``states`` is ``None``.
        config: the run's settings (chunk sizes, particle chunks, seed, device, ...).
        examples: ``{filter: (T, d)}`` estimates of trial 0 (for the track picture; localisers: the
            declared sources ``(k, 3)``).
        interrupted: the run was stopped (Ctrl-C): the interrupted filter's row says so in ``error``;
            ``not_run``: the filters that did not start.
        failures: ``{filter: "chunk i of n (trials a..b)"}``: where each failed filter failed
            (its row's ``error`` says what; the traceback is in the ``torchflow.app.runner`` log).
        estimate_summary: ``{filter: (mean (T, d), sd (T, d))}``: at each step the mean over trials
            of the filter's estimates and their standard deviation over trials (the spread of the
            independent runs; 0 with one trial); filters of point estimates.
        recorded: the data were recorded (no true states: no metric that needs them).
        paths: ``{filter: {path: count}}``: the execution paths each filter's time steps took,
            summed over its chunks (:mod:`torchflow.core.paths`; the summary's ``path``
            column names them, most counted first).
        timings: wall seconds of the run's phases: ``plan`` (checks, moving to the device, the
            simulation or the recorded data), ``reference`` (the Kalman filter's reference
            log-evidence, where the model has one), ``filters`` (every filter's warm-up and
            chunks; their own compute is the summary's ``sec_per_step`` and ``warmup_sec``) and
            ``scoring``; the command line adds its own (start-up, writing, figures) in the log.
    """

    summary: List[dict]
    per_trial: List[dict]
    per_step: List[dict]
    trajectory: Optional[Trajectory] = None
    config: dict = field(default_factory=dict)
    examples: Dict[str, torch.Tensor] = field(default_factory=dict)
    interrupted: bool = False
    not_run: List[str] = field(default_factory=list)
    failures: Dict[str, str] = field(default_factory=dict)
    estimate_summary: Dict[str, Tuple[torch.Tensor, torch.Tensor]] = field(default_factory=dict)
    recorded: bool = False
    paths: Dict[str, Dict[str, int]] = field(default_factory=dict)
    timings: Dict[str, float] = field(default_factory=dict)

    @property
    def failed(self) -> List[str]:
        """Filters whose row has an error other than the interruption."""
        return [r["filter"] for r in self.summary if r.get("error") and not r["error"].startswith("interrupted")]


@dataclass
class Scorer:
    """The truth ``(n_run, T, d)`` (CPU float64; ``None``: recorded data) of a run's trial range
    from ``lo``, and the metric settings; ``reference_logz``: the Kalman filter's exact
    log-evidence (linear-Gaussian models)."""

    model: StateSpaceModel
    truth: Optional[torch.Tensor]
    lo: int
    ospa_cutoff: float = 40.0
    ospa_order: float = 1.0
    lost_threshold: float = 2.0
    burn_in: int = 0
    reference_logz: Optional[torch.Tensor] = None
    lost_rmse: Optional[float] = None

    @property
    def settings(self) -> Dict[str, float]:
        """The metric settings a :class:`~torchflow.core.metrics.MetricContext` carries."""
        return {
            "ospa_cutoff": self.ospa_cutoff,
            "ospa_order": self.ospa_order,
            "lost_threshold": self.lost_threshold,
            "burn_in": self.burn_in,
        }


def make_scorer(model: StateSpaceModel, plan: RunPlan, **settings) -> Scorer:
    """A :class:`Scorer` for ``plan``; on a linear-Gaussian model (rank 0) the Kalman filter's
    exact log-evidence is the reference of ``log_evidence_relmse``."""
    s = plan.settings
    states = plan.traj.states  # None: recorded data
    truth = None if states is None else states[s.lo : s.hi, 1:].double().cpu()  # chunks come back as CPU float64
    ref = None
    if plan.shard.is_main and model.structure.linear_dynamics and model.structure.linear_measurement:
        with torch.no_grad():
            kf = KalmanFilter(model, validate=False)
            c = filter_chunk(kf, s.n_run, s.chunk_size, s.memory_budget_gb)
            ref = (
                torch.cat(
                    [
                        kf(plan.traj.observations[a:b], plan.mean0[a:b], plan.cov0[a:b]).log_evidence
                        for a, b in plan.trial_chunks(c)
                    ]
                )
                .double()
                .cpu()
            )
    return Scorer(model, truth, s.lo, reference_logz=ref, **settings)


def _cat(chunks: List[dict], key: str) -> Optional[torch.Tensor]:
    return torch.cat([c[key] for c in chunks]) if key in chunks[0] else None


#: chunk entries that are not filter outputs of a :class:`~torchflow.core.metrics.MetricContext`
_NOT_OUTPUTS = ("start", "stop", "elapsed", "estimates", "estimate_mask", "std", "lost_at")


def lost_steps(chunks: List[dict]) -> torch.Tensor:
    """``(B,)`` long: the step at which each trial of the chunks went non-finite and was lost
    (:func:`~torchflow.app.runner.execute.run_chunk`), 0 for a kept trial."""
    return torch.cat(
        [c["lost_at"] if "lost_at" in c else torch.zeros(c["stop"] - c["start"], dtype=torch.long) for c in chunks]
    )


def context(sc: Scorer, f: Filter, chunks: List[dict]) -> metrics.MetricContext:
    """The :class:`~torchflow.core.metrics.MetricContext` of one filter's chunks (concatenated over
    trials); a lost trial's estimates (NaN) are zeros here: its metrics are computed, never reported."""
    est, lost = _cat(chunks, "estimates"), lost_steps(chunks) > 0
    if bool(lost.any()):
        est = est.clone()
        est[lost] = 0.0
    outputs = {
        k: _cat(chunks, k)
        for k, v in chunks[0].items()
        if k not in _NOT_OUTPUTS and isinstance(v, torch.Tensor) and all(k in c for c in chunks)
    }
    return metrics.MetricContext(
        model=sc.model,
        filter=f,
        estimates=est,
        truth=sc.truth,
        mask=_cat(chunks, "estimate_mask"),
        outputs=outputs,
        settings=sc.settings,
    )


def _values(ctx: metrics.MetricContext, name: str) -> Dict[str, tuple]:
    """``{metric: (values (B, T) float64, trial reduction, integer per-trial values, first step a
    trial's mean counts (burn-in), standard error column)}`` of every registered metric that
    applies; an error names the filter."""
    try:
        out = {}
        for m in metrics.applicable(ctx):
            v = m.evaluate(ctx)
            how = m.trial_reduction(ctx)
            out[m.name] = (
                v.double(),
                how,
                how == "last" and not v.is_floating_point(),
                m.first_step(ctx),
                m.standard_error,
            )
        return out
    except (RuntimeError, ValueError) as err:  # the metrics' own errors: add the filter's name
        if type(err) not in (RuntimeError, ValueError, ArgumentError):
            raise
        raise type(err)(f"filter {name}: {err}") from err


def _per_step(name: str, cols: Dict[str, tuple], steps: int) -> List[dict]:
    means = {k: c[0].mean(0) for k, c in cols.items()}
    return [{"filter": name, "step": t + 1, **{k: float(v[t]) for k, v in means.items()}} for t in range(steps)]


def _trial_values(v: torch.Tensor, how: str, start: int) -> torch.Tensor:
    """``(B,)``: each trial's last value, or its mean over the steps from ``start``."""
    return v[:, -1] if how == "last" else v[:, start:].mean(1)


def _summary(cols: Dict[str, tuple]) -> Dict[str, float]:
    """Summary values: the mean over trials (and steps from the burn-in on), or over trials of the
    last step's; ``name_se``: its standard error over trials where the metric asks for it."""
    out = {}
    for k, (v, how, _, start, se) in cols.items():
        per_trial = _trial_values(v, how, start)
        out[k] = float(per_trial.mean())
        if se:
            out[f"{k}_se"] = float(per_trial.std() / per_trial.numel() ** 0.5) if per_trial.numel() > 1 else None
    return out


def _trial(cols: Dict[str, tuple], b: int) -> dict:
    """Trial ``b``'s values: the mean over its steps (from the burn-in on), or its last step's (an
    int for counts)."""
    return {
        k: (int(v[b, -1]) if integer else float(v[b, -1])) if how == "last" else float(v[b, start:].mean())
        for k, (v, how, integer, start, _) in cols.items()
    }


def score_sets(sc: Scorer, ctx: metrics.MetricContext, name: str, row: dict, cols: Dict[str, tuple], steps: int):
    """:func:`score_filter` of the localisers (sets ``estimates (B, T, K, 3)`` with ``estimate_mask``):
    the registered metrics of sets (OSPA and the declared count after each step, a trial's value the
    last step's); the measurements whose every weight underflowed (``underflow``) are counted and
    named in a warning."""
    est, mask, under = ctx.estimates, ctx.mask, ctx.outputs.get("underflow")
    counts = None
    if under is not None:
        lost = [f"run {b + sc.lo}, sensor {s}, measurement {m}" for b, s, m in torch.nonzero(under).tolist()]
        if lost:
            warnings.warn(
                f"{name}: every component's weight underflowed (measurement treated as clutter) at " + "; ".join(lost),
                RuntimeWarning,
                stacklevel=2,
            )
        counts = under.flatten(1).sum(1)
    per_trial = [
        {
            "filter": name,
            "trial": sc.lo + b,
            **_trial(cols, b),
            **({} if counts is None else {"underflows": int(counts[b])}),
        }
        for b in range(est.shape[0])
    ]
    row.update(_summary(cols))
    if counts is not None:
        row["underflows"] = int(counts.sum())
    return per_trial, _per_step(name, cols, steps), est[0, -1][mask[0, -1]]


def score_filter(sc: Scorer, f: Filter, name: str, row: dict, chunks: List[dict], steps: int):
    """``(per-trial rows, per-step rows, trial 0's estimates)`` of one filter; fills ``row``: every
    registered metric that applies (:mod:`torchflow.core.metrics`; built in: MSE; OMAT and OSPA of
    tracking models; ESS, G_eff), the log-evidence and its error against the Kalman filter's, the
    lost tracks and the OMAT of the kept ones (tracking models), repairs."""
    ctx = context(sc, f, chunks)
    cols = _values(ctx, name)
    if ctx.kind == "sets":
        return score_sets(sc, ctx, name, row, cols, steps)
    logz, n_run = ctx.outputs.get("log_evidence"), ctx.estimates.shape[0]
    lost_at = lost_steps(chunks)
    lost = lost_at > 0
    if sc.lost_rmse is not None and "rmse" in cols:  # DAPPER's count: a trial whose RMSE is over a threshold
        v, how, _, start, _ = cols["rmse"]
        lost = lost | ~(_trial_values(v, how, start) <= sc.lost_rmse)  # NaN counts as over
    keep = ~lost
    kept = {k: (c[0][keep], *c[1:]) for k, c in cols.items()}  # every reported mean is over the kept trials
    n_kept = int(keep.sum())
    if f.estimates_evidence and n_kept:
        row["log_evidence"] = float(logz[keep].mean())
        if n_kept > 1:  # the standard error of the mean over trials
            row["log_evidence_se"] = float(logz[keep].std() / n_kept**0.5)
        if sc.reference_logz is not None:
            row["log_evidence_relmse"] = float(
                metrics.log_evidence_relative_error(logz[keep], sc.reference_logz[keep]).mean()
            )
    if "n_repaired" in ctx.outputs:
        row["repaired"] = int(ctx.outputs["n_repaired"][keep].sum())
    if n_kept:
        row.update(_summary(kept))
    row["lost_trials"] = n_run - n_kept
    lost_tracks = None
    if sc.model.structure.has_positions and sc.truth is not None:  # lost tracks: OMAT's, registered or not
        om = cols["omat"][0] if "omat" in cols else metrics.omat(ctx.est_positions, ctx.true_positions)
        lost_tracks = metrics.lost_tracks(om, threshold=sc.lost_threshold) & keep
        good = om.mean(1)[keep & ~lost_tracks]
        row.update(
            lost_tracks=int(lost_tracks.sum()),
            omat_kept_mean=float(good.mean()) if good.numel() else None,
            omat_kept_sd=float(good.std()) if good.numel() > 1 else None,
        )
    per_trial = [
        {
            "filter": name,
            "trial": sc.lo + b,
            **({} if logz is None else {"log_evidence": float(logz[b])}),
            **_trial(cols, b),
            **(dict.fromkeys([*([] if logz is None else ["log_evidence"]), *cols]) if lost_at[b] > 0 else {}),
            **({} if lost_tracks is None else {"lost": bool(lost_tracks[b])}),
            "lost_trial": bool(lost[b]),
            "lost_step": int(lost_at[b]),
        }
        for b in range(n_run)
    ]
    return per_trial, _per_step(name, kept if n_kept else cols, steps), chunks[0]["estimates"][0]


def estimate_spread(chunks: List[dict]) -> Optional[Tuple[torch.Tensor, Optional[torch.Tensor], torch.Tensor]]:
    """``(mean (T, d), sd (T, d), spread (T, d))`` of a filter's estimates over its trials (its
    chunks, concatenated): at each step the mean over trials of the filtered means, the mean over
    trials of the filtering law's standard deviation (``None`` where the chunks carry no ``std``)
    and the standard deviation over trials of the filtered means (the Monte Carlo spread between
    independent runs; 0 with one trial). ``None`` for sets (the localisers)."""
    if "estimate_mask" in chunks[0]:
        return None
    keep = lost_steps(chunks) == 0  # the lost trials (NaN) are left out
    if not bool(keep.any()):
        return None
    est = _cat(chunks, "estimates")[keep]  # (B, T, d) float64
    spread = est.std(0) if est.shape[0] > 1 else torch.zeros_like(est[0])
    sd = _cat(chunks, "std")[keep].mean(0) if all("std" in c for c in chunks) else None
    return est.mean(0), sd, spread


#: columns the printed table leaves out when they are 0 in every row (the CSV keeps them)
QUIET_ZERO = ("lost_trials",)


def format_table(summary: List[dict], columns: Optional[List[str]] = None) -> str:
    """Markdown table of the summary rows (default columns: :func:`summary_columns`), dropping
    columns that are empty in every row and the :data:`QUIET_ZERO` columns that are 0 in every row."""
    cols = [
        c
        for c in columns or summary_columns()
        if any(r.get(c) is not None for r in summary) and not (c in QUIET_ZERO and not any(r.get(c) for r in summary))
    ]
    fmt = lambda v: "" if v is None else f"{v:.4g}" if isinstance(v, float) else str(v)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    return "\n".join(lines + ["| " + " | ".join(fmt(r.get(c)) for c in cols) + " |" for r in summary])
