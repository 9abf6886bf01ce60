"""Result files of a run: CSV and JSON, written atomically (a temporary file renamed), so an
interrupted write never leaves a truncated table beside complete ones."""

from __future__ import annotations

import csv
import json
import os
import tempfile
from pathlib import Path
from typing import List, Mapping, Optional, Tuple

from torchflow.app.runner.score import summary_columns

#: the summary of the filters finished so far, rewritten after each filter while a run goes on and
#: removed once ``summary.csv`` is written: a run stopped before its end (a folder that became
#: read-only, a killed process) leaves this name, never a ``summary.csv`` that looks complete
PARTIAL_SUMMARY = "summary.partial.csv"
#: every file a run may write into its output folder (a reused folder is cleared of these)
RESULT_FILES = (
    "summary.csv",
    PARTIAL_SUMMARY,
    "per_step.csv",
    "per_trial.csv",
    "results.json",
    "error.txt",
    "estimates.csv",
    "per_step.png",
    "tracks.png",
    "omat_box.png",
    "scene.png",
    "estimates.png",
)
#: the files ``torchflow-learn`` writes into its output folder
LEARN_FILES = ("learn.csv", "learn.json", "curves.png")
#: the files of ``torchflow task=smooth`` and ``torchflow task=pmmh`` (:mod:`torchflow.app.tasks`)
SMOOTH_FILES = ("smoothed.csv", "smoothing.json", "smoothed.png")
PMMH_FILES = ("posterior.csv", "pmmh.json", "posterior.png", "traces.png")
#: every command's result files: a folder holding any of them holds an earlier run's results
ALL_RESULT_FILES = RESULT_FILES + LEARN_FILES + SMOOTH_FILES + PMMH_FILES


def _read_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


#: the process's umask, read once at import (reading it means setting it, which is process-wide:
#: not done per write while other threads may create files)
_UMASK = _read_umask()


def exclusive_temp(path: Path) -> Tuple[int, Path]:
    """``(descriptor, name)`` of a new temporary file beside ``path``, created exclusively (a random
    name opened with ``O_CREAT | O_EXCL``, mode 0600: :func:`tempfile.mkstemp`). In a folder others
    can write (a shared ``checkpoint_dir`` or output folder) no link planted at a guessable name is
    followed: the name is not guessable, and an existing entry of that name, a link included, makes
    the open fail instead of writing through it."""
    path = Path(path)
    fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    return fd, Path(name)


def replace_atomically(path: Path, write, binary: bool = False) -> Path:
    """Write ``path`` whole or not at all: ``write(file)`` into an :func:`exclusive_temp` file, then
    rename it over ``path`` (a rename replaces a link at ``path`` itself, it does not follow it)."""
    path = Path(path)
    fd, tmp = exclusive_temp(path)
    try:
        with os.fdopen(fd, "wb" if binary else "w", **({} if binary else {"newline": ""})) as fh:
            write(fh)
        os.chmod(tmp, 0o644 & ~_UMASK)  # mkstemp's 0600, widened as open() would have made it
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def save_figure(fig, path: Path, **kwargs) -> Path:
    """``fig.savefig`` into ``path`` through :func:`replace_atomically` (never through a link at
    ``path`` or a temporary name); the format follows the file's suffix."""
    path = Path(path)
    return replace_atomically(path, lambda fh: fig.savefig(fh, format=path.suffix.lstrip(".") or "png", **kwargs), True)


def write_csv(path: Path, rows: List[Mapping], columns: Optional[List[str]] = None) -> Path:
    """Write ``rows`` (``None`` as an empty cell) to ``path`` atomically; default columns: every key,
    ``filter``, ``step``, ``trial`` first, then the others sorted (so the per-step and per-trial
    files hold every registered metric that applied)."""
    columns = list(
        columns or sorted({k for r in rows for k in r}, key=lambda k: (k not in ("filter", "step", "trial"), k))
    )

    def write(fh):
        w = csv.DictWriter(fh, fieldnames=columns, extrasaction="ignore")
        w.writeheader()
        w.writerows({k: ("" if r.get(k) is None else r.get(k)) for k in columns} for r in rows)

    return replace_atomically(path, write)


def write_text(path: Path, text: str) -> Path:
    return replace_atomically(path, lambda fh: fh.write(text))


def estimate_rows(estimate_summary: Mapping) -> List[dict]:
    """The rows of ``estimates.csv``: per filter and step (1..T: the data's rows), for each state
    coordinate j = 0..d-1 ``mean_j`` (the filtered mean, averaged over trials), ``sd_j`` (the
    filtering law's standard deviation, averaged over trials) and ``spread_j`` (the standard
    deviation over trials of the filtered mean: the Monte Carlo spread of independent runs), from
    :attr:`~torchflow.app.runner.score.ExperimentResult.estimate_summary`."""
    rows = []
    for name, (mean, sd, spread) in estimate_summary.items():
        d = mean.shape[-1]
        for t in range(mean.shape[0]):
            rows.append(
                {
                    "filter": name,
                    "step": t + 1,
                    **{f"mean_{j}": float(mean[t, j]) for j in range(d)},
                    **{f"sd_{j}": None if sd is None else float(sd[t, j]) for j in range(d)},
                    **{f"spread_{j}": float(spread[t, j]) for j in range(d)},
                }
            )
    return rows


def write_estimates(path: Path, estimate_summary: Mapping) -> Path:
    """``estimates.csv`` (:func:`estimate_rows`; columns ``filter, step, mean_0..mean_{d-1},
    sd_0..sd_{d-1}, spread_0..spread_{d-1}``)."""
    d = max((v[0].shape[-1] for v in estimate_summary.values()), default=0)
    cols = ["filter", "step", *(f"{k}_{j}" for k in ("mean", "sd", "spread") for j in range(d))]
    return write_csv(path, estimate_rows(estimate_summary), cols)


def write_run(out: Path, result, config: Mapping) -> List[Path]:
    """``summary.csv`` (columns: :func:`~torchflow.app.runner.score.summary_columns`, which follow
    :data:`torchflow.core.metrics.REGISTRY`), ``per_step.csv``, ``per_trial.csv`` and ``results.json``
    of an :class:`~torchflow.app.runner.score.ExperimentResult`; ``config``: the settings to record.
    A run on recorded data also writes ``estimates.csv`` (:func:`write_estimates`). Once every file
    is written, the run's :data:`PARTIAL_SUMMARY` goes."""
    out = Path(out)
    extra = [write_estimates(out / "estimates.csv", result.estimate_summary)] if result.recorded else []
    written = extra + [
        write_csv(out / "summary.csv", result.summary, summary_columns()),
        write_csv(out / "per_step.csv", result.per_step),
        write_csv(out / "per_trial.csv", result.per_trial),
        write_text(
            out / "results.json",
            json.dumps(
                {
                    "config": dict(config),
                    "run": result.config,
                    "summary": result.summary,
                    "paths": getattr(result, "paths", {}),
                    "timings": {
                        k: None if v is None else round(v, 4) for k, v in getattr(result, "timings", {}).items()
                    },
                    "interrupted": result.interrupted,
                    "not_run": result.not_run,
                    "failed": {n: result.failures.get(n) for n in result.failed},
                },
                indent=2,
            ),
        ),
    ]
    (out / PARTIAL_SUMMARY).unlink(missing_ok=True)
    return written


def clear_results(out: Path, names=ALL_RESULT_FILES) -> None:
    """Remove the result files ``names`` (default: every command's, :data:`ALL_RESULT_FILES`) from ``out``."""
    for name in names:
        (Path(out) / name).unlink(missing_ok=True)
