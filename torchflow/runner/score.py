"""Score a filter's chunks: the summary row, per-trial and per-step metrics; the result container."""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import torch

from .. import metrics
from ..filters.base import Filter
from ..filters.kalman import KalmanFilter
from ..models.base import StateSpaceModel, Trajectory
from .plan import RunPlan, filter_chunk

SUMMARY_COLUMNS = [
    "filter", "n_particles", "trials", "steps", "mse", "omat", "omat_kept_mean", "omat_kept_sd",
    "ospa", "declared", "underflows", "ess", "g_eff", "log_evidence", "log_evidence_relmse", "lost_tracks", "repaired",
    "sec_per_step", "error",
]


@dataclass
class ExperimentResult:
    """Tidy results.

    Attributes:
        summary: one dict per filter with :data:`SUMMARY_COLUMNS` (``None`` where undefined).
        per_trial: one dict per filter x trial (mse, omat, ospa, ess, log_evidence, lost).
        per_step: one dict per filter x step with metric means over trials.
        trajectory: the simulated data (CPU tensors).
        config: the run's settings (chunk sizes, particle chunks, seed, device, ...).
        examples: ``{filter: (T, d)}`` estimates of trial 0 (for the track picture).
        interrupted: the run was stopped (Ctrl-C); the rows hold what finished, the interrupted
            filter's row says so in ``error``.
        not_run: filters that did not start because of the interruption.
        failures: ``{filter: "chunk i of n (trials a..b)"}``: where each failed filter failed
            (its row's ``error`` says what; the traceback is in the ``torchflow.runner`` log).
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

    @property
    def failed(self) -> List[str]:
        """Filters whose row has an error other than the interruption."""
        return [r["filter"] for r in self.summary if r.get("error") and not r["error"].startswith("interrupted")]


@dataclass
class Scorer:
    """The truth of a run's trial range and the metric settings."""

    model: StateSpaceModel
    truth: torch.Tensor  # (n_run, T, d) CPU float64
    lo: int
    ospa_cutoff: float = 40.0
    ospa_order: float = 1.0
    lost_threshold: float = 2.0
    reference_logz: Optional[torch.Tensor] = None

    @property
    def tracking(self) -> bool:
        return self.model.has_positions


def make_scorer(model: StateSpaceModel, plan: RunPlan, **settings) -> Scorer:
    """A :class:`Scorer` for ``plan``; on a linear-Gaussian model (rank 0) the Kalman filter's
    exact log-evidence is the reference of ``log_evidence_relmse``."""
    s = plan.settings
    truth = plan.traj.states[s.lo:s.hi, 1:].double().cpu()  # chunks come back as CPU float64 (any rank)
    ref = None
    if plan.shard.is_main and model.linear_dynamics and model.linear_measurement:
        with torch.no_grad():
            kf = KalmanFilter(model, validate=False)
            c = filter_chunk(kf, s.n_run, s.chunk_size, s.memory_budget_gb)
            ref = torch.cat([kf(plan.traj.observations[a:min(a + c, s.hi)], plan.mean0[a:min(a + c, s.hi)],
                                plan.cov0[a:min(a + c, s.hi)]).log_evidence
                             for a in range(s.lo, s.hi, c)]).double().cpu()
    return Scorer(model, truth, s.lo, reference_logz=ref, **settings)


def _cat(chunks: List[dict], key: str) -> Optional[torch.Tensor]:
    return torch.cat([c[key] for c in chunks]) if key in chunks[0] else None


def metric_columns(sc: Scorer, chunks: List[dict]) -> Dict[str, torch.Tensor]:
    """``{metric: (B, T)}`` of one filter's estimates."""
    est = _cat(chunks, "estimates")
    cols = {"mse": metrics.mse(est, sc.truth)}
    if sc.tracking:
        est_pos, true_pos = sc.model.positions(est), sc.model.positions(sc.truth)
        cols["omat"] = metrics.omat(est_pos, true_pos)
        cols["ospa"] = metrics.ospa(est_pos, true_pos, cutoff=sc.ospa_cutoff, order=sc.ospa_order)
    for key in ("ess", "g_eff"):
        if key in chunks[0]:
            cols[key] = _cat(chunks, key)
    return cols


def summary_row(sc: Scorer, f: Filter, row: dict, chunks: List[dict], cols: Dict[str, torch.Tensor],
                steps: int) -> Optional[torch.Tensor]:
    """Fill ``row`` from one filter's chunks; returns the lost-track flags (tracking models)."""
    n_run = sc.truth.shape[0]
    logz = _cat(chunks, "log_evidence")
    row["sec_per_step"] = sum(float(c["elapsed"]) for c in chunks) / (n_run * steps)
    if f.estimates_evidence:
        row["log_evidence"] = float(logz.mean())
    if "n_repaired" in chunks[0]:
        row["repaired"] = int(_cat(chunks, "n_repaired").sum())
    for k, v in cols.items():
        row[k] = float(v.mean())
    lost = None
    if sc.tracking:
        lost = metrics.lost_tracks(cols["omat"], threshold=sc.lost_threshold)
        row["lost_tracks"] = int(lost.sum())
        kept = cols["omat"].mean(1)[~lost]
        row["omat_kept_mean"] = float(kept.mean()) if kept.numel() else None
        row["omat_kept_sd"] = float(kept.std()) if kept.numel() > 1 else None
    if sc.reference_logz is not None and f.estimates_evidence:
        row["log_evidence_relmse"] = float(metrics.log_evidence_relative_error(logz, sc.reference_logz).mean())
    return lost


def score_sets(sc: Scorer, name: str, row: dict, chunks: List[dict], steps: int):
    """:func:`score_filter` of a filter whose estimates are sets (the localisers): ``estimates (B, T,
    K, 3)`` with ``estimate_mask``, scored by OSPA against the model's positions and the declared
    count after each step; a trial's value is the last step's (the answer of a localisation). The
    measurements whose every weight underflowed (``underflow``) are counted and named in a warning."""
    est, mask, under = _cat(chunks, "estimates"), _cat(chunks, "estimate_mask"), _cat(chunks, "underflow")
    truth = sc.model.positions(sc.truth)
    cols = {"ospa": metrics.ospa(est, truth, cutoff=sc.ospa_cutoff, order=sc.ospa_order, X_mask=mask),
            "declared": mask.sum(-1).double()}
    lost = [f"run {b + sc.lo}, sensor {s}, measurement {m}" for b, s, m in torch.nonzero(under).tolist()]
    if lost:
        warnings.warn(f"{name}: every component's weight underflowed (measurement treated as clutter) at "
                      + "; ".join(lost), RuntimeWarning, stacklevel=2)
    counts = under.flatten(1).sum(1)
    per_trial = [{"filter": name, "trial": sc.lo + b, "ospa": float(cols["ospa"][b, -1]),
                  "declared": int(cols["declared"][b, -1]), "underflows": int(counts[b])} for b in range(est.shape[0])]
    row.update({k: float(v[:, -1].mean()) for k, v in cols.items()}, underflows=int(counts.sum()),
               sec_per_step=sum(float(c["elapsed"]) for c in chunks) / (est.shape[0] * steps))
    per_step = [{"filter": name, "step": t + 1, **{k: float(v[:, t].mean()) for k, v in cols.items()}}
                for t in range(steps)]
    return per_trial, per_step, est[0, -1][mask[0, -1]]


def score_filter(sc: Scorer, f: Filter, name: str, row: dict, chunks: List[dict], steps: int):
    """``(per-trial rows, per-step rows, trial 0's estimates)`` of one filter; fills ``row``."""
    if "estimate_mask" in chunks[0]:
        return score_sets(sc, name, row, chunks, steps)
    cols = metric_columns(sc, chunks)
    lost = summary_row(sc, f, row, chunks, cols, steps)
    logz = _cat(chunks, "log_evidence")
    per_trial = []
    for b in range(sc.truth.shape[0]):
        r = {"filter": name, "trial": sc.lo + b, "log_evidence": float(logz[b])}
        r.update({k: float(v[b].mean()) for k, v in cols.items()})
        if lost is not None:
            r["lost"] = bool(lost[b])
        per_trial.append(r)
    means = {k: v.mean(0) for k, v in cols.items()}
    per_step = [{"filter": name, "step": t + 1, **{k: float(v[t]) for k, v in means.items()}} for t in range(steps)]
    return per_trial, per_step, chunks[0]["estimates"][0]


def format_table(summary: List[dict], columns: Optional[List[str]] = None) -> str:
    """Markdown table of the summary rows, dropping columns that are empty in every row."""
    columns = columns or SUMMARY_COLUMNS
    cols = [c for c in columns if any(r.get(c) is not None for r in summary)]

    def fmt(v):
        if v is None:
            return ""
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(fmt(r.get(c)) for c in cols) + " |" for r in summary]
    return "\n".join(lines)
