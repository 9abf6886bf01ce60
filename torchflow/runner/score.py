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
    "sec_per_step", "warmup_sec", "error",
]


@dataclass
class ExperimentResult:
    """Tidy results.

    Attributes:
        summary: one dict per filter with :data:`SUMMARY_COLUMNS` (``None`` where undefined).
        per_trial: one dict per filter x trial (mse, omat, ospa, ess, log_evidence, lost; localisers:
            ospa, declared, underflows).
        per_step: one dict per filter x step with metric means over trials.
        trajectory: the simulated data (CPU tensors).
        config: the run's settings (chunk sizes, particle chunks, seed, device, ...).
        examples: ``{filter: (T, d)}`` estimates of trial 0 (for the track picture; localisers: the
            declared sources ``(k, 3)``).
        interrupted: the run was stopped (Ctrl-C): the interrupted filter's row says so in ``error``;
            ``not_run``: the filters that did not start.
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
    """The truth ``(n_run, T, d)`` (CPU float64) of a run's trial range from ``lo``, and the metric
    settings; ``reference_logz``: the Kalman filter's exact log-evidence (linear-Gaussian models)."""

    model: StateSpaceModel
    truth: torch.Tensor
    lo: int
    ospa_cutoff: float = 40.0
    ospa_order: float = 1.0
    lost_threshold: float = 2.0
    reference_logz: Optional[torch.Tensor] = None


def make_scorer(model: StateSpaceModel, plan: RunPlan, **settings) -> Scorer:
    """A :class:`Scorer` for ``plan``; on a linear-Gaussian model (rank 0) the Kalman filter's
    exact log-evidence is the reference of ``log_evidence_relmse``."""
    s = plan.settings
    truth = plan.traj.states[s.lo:s.hi, 1:].double().cpu()  # chunks come back as CPU float64 (any rank)
    ref = None
    if plan.shard.is_main and model.structure.linear_dynamics and model.structure.linear_measurement:
        with torch.no_grad():
            kf = KalmanFilter(model, validate=False)
            c = filter_chunk(kf, s.n_run, s.chunk_size, s.memory_budget_gb)
            ref = torch.cat([kf(plan.traj.observations[a:b], plan.mean0[a:b], plan.cov0[a:b]).log_evidence
                             for a, b in plan.trial_chunks(c)]).double().cpu()
    return Scorer(model, truth, s.lo, reference_logz=ref, **settings)


def _cat(chunks: List[dict], key: str) -> Optional[torch.Tensor]:
    return torch.cat([c[key] for c in chunks]) if key in chunks[0] else None


def _per_step(name: str, cols: Dict[str, torch.Tensor], steps: int) -> List[dict]:
    means = {k: v.mean(0) for k, v in cols.items()}
    return [{"filter": name, "step": t + 1, **{k: float(v[t]) for k, v in means.items()}} for t in range(steps)]


def score_sets(sc: Scorer, name: str, row: dict, chunks: List[dict], steps: int):
    """:func:`score_filter` of the localisers (sets ``estimates (B, T, K, 3)`` with ``estimate_mask``):
    OSPA and the declared count after each step, a trial's value the last step's; the measurements
    whose every weight underflowed (``underflow``) are counted and named in a warning."""
    est, mask, under = _cat(chunks, "estimates"), _cat(chunks, "estimate_mask"), _cat(chunks, "underflow")
    cols = {"ospa": metrics.ospa(est, sc.model.positions(sc.truth), cutoff=sc.ospa_cutoff, order=sc.ospa_order,
                                 X_mask=mask), "declared": mask.sum(-1).double()}
    lost = [f"run {b + sc.lo}, sensor {s}, measurement {m}" for b, s, m in torch.nonzero(under).tolist()]
    if lost:
        warnings.warn(f"{name}: every component's weight underflowed (measurement treated as clutter) at "
                      + "; ".join(lost), RuntimeWarning, stacklevel=2)
    counts = under.flatten(1).sum(1)
    per_trial = [{"filter": name, "trial": sc.lo + b, "ospa": float(cols["ospa"][b, -1]),
                  "declared": int(cols["declared"][b, -1]), "underflows": int(counts[b])} for b in range(est.shape[0])]
    row.update({k: float(v[:, -1].mean()) for k, v in cols.items()}, underflows=int(counts.sum()))
    return per_trial, _per_step(name, cols, steps), est[0, -1][mask[0, -1]]


def score_filter(sc: Scorer, f: Filter, name: str, row: dict, chunks: List[dict], steps: int):
    """``(per-trial rows, per-step rows, trial 0's estimates)`` of one filter; fills ``row``: metric
    means over trials and steps (MSE; OMAT, OSPA and lost tracks of tracking models; ESS, G_eff),
    the log-evidence and its error against the Kalman filter's, repairs."""
    if "estimate_mask" in chunks[0]:
        return score_sets(sc, name, row, chunks, steps)
    est, logz, n_run = _cat(chunks, "estimates"), _cat(chunks, "log_evidence"), sc.truth.shape[0]
    cols = {"mse": metrics.mse(est, sc.truth)}
    if sc.model.structure.has_positions:
        est_pos, true_pos = sc.model.positions(est), sc.model.positions(sc.truth)
        cols["omat"] = metrics.omat(est_pos, true_pos)
        cols["ospa"] = metrics.ospa(est_pos, true_pos, cutoff=sc.ospa_cutoff, order=sc.ospa_order)
    cols.update({k: _cat(chunks, k) for k in ("ess", "g_eff") if k in chunks[0]})
    if f.estimates_evidence:
        row["log_evidence"] = float(logz.mean())
        if sc.reference_logz is not None:
            row["log_evidence_relmse"] = float(metrics.log_evidence_relative_error(logz, sc.reference_logz).mean())
    if "n_repaired" in chunks[0]:
        row["repaired"] = int(_cat(chunks, "n_repaired").sum())
    row.update({k: float(v.mean()) for k, v in cols.items()})
    lost = None
    if sc.model.structure.has_positions:
        lost = metrics.lost_tracks(cols["omat"], threshold=sc.lost_threshold)
        kept = cols["omat"].mean(1)[~lost]
        row.update(lost_tracks=int(lost.sum()), omat_kept_mean=float(kept.mean()) if kept.numel() else None,
                   omat_kept_sd=float(kept.std()) if kept.numel() > 1 else None)
    per_trial = [{"filter": name, "trial": sc.lo + b, "log_evidence": float(logz[b]),
                  **{k: float(v[b].mean()) for k, v in cols.items()},
                  **({} if lost is None else {"lost": bool(lost[b])})} for b in range(n_run)]
    return per_trial, _per_step(name, cols, steps), chunks[0]["estimates"][0]


def format_table(summary: List[dict], columns: Optional[List[str]] = None) -> str:
    """Markdown table of the summary rows, dropping columns that are empty in every row."""
    cols = [c for c in columns or SUMMARY_COLUMNS if any(r.get(c) is not None for r in summary)]
    fmt = lambda v: "" if v is None else f"{v:.4g}" if isinstance(v, float) else str(v)  # noqa: E731
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    return "\n".join(lines + ["| " + " | ".join(fmt(r.get(c)) for c in cols) + " |" for r in summary])
