"""Hydra sweeps (any launcher): what happened to every job, from its folder (``error.txt``,
``results.json``); :class:`SweepReport` says it at the end, ``experiments/collect.py`` too.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, List, Optional

import yaml
from hydra.experimental.callback import Callback

from torchflow.app.runner.config import collect_command

#: the file a task's job writes last (``task=smooth``, ``task=pmmh``), read where it has no ``results.json``
TASK_RESULTS = ("smoothing.json", "pmmh.json")


def job_dirs(sweep_dir: Path) -> List[Path]:
    """A sweep's job folders (named by job number), in job order (none if ``sweep_dir`` is not a folder)."""
    return sorted((p for p in Path(sweep_dir).glob("*") if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name))


def job_status(job: Path) -> tuple:
    """``(state, message)``: ``failed`` (the last line of error.txt, or ``filter X failed: ...``),
    ``done``, ``interrupted`` (Ctrl-C or SIGTERM), ``missing`` (running, killed, never started) or
    ``damaged`` (a ``results.json`` that cannot be read: the message names it and why; it is written
    last and atomically, so the job's CSV files beside it are complete)."""
    err, res = Path(job) / "error.txt", Path(job) / "results.json"
    if err.exists():
        lines = [ln for ln in err.read_text().splitlines() if ln.strip()]
        return "failed", (lines[-1] if lines else "error")
    if not res.exists():  # a task's job: its own JSON file, written last (task=smooth, task=pmmh)
        res = next((Path(job) / n for n in TASK_RESULTS if (Path(job) / n).exists()), res)
    try:
        data = json.loads(res.read_text())
        if not isinstance(data, dict):
            raise ValueError(f"expected a JSON object, got {type(data).__name__}")
    except FileNotFoundError:  # not written (yet)
        return "missing", ""
    except (ValueError, OSError) as e:
        return "damaged", f"{res} is damaged ({type(e).__name__}: {e})"
    errors = {r["filter"]: r["error"] for r in data.get("summary", []) if r.get("error")}
    if data.get("interrupted") or (data.get("run") or {}).get("interrupted"):
        return "interrupted", ""
    return ("failed", "; ".join(f"filter {n} failed: {e}" for n, e in errors.items())) if errors else ("done", "")


def job_override_dict(job: Path) -> dict:
    """``{key: value}`` of one job's overrides (``.hydra/overrides.yaml``; ``experiment=`` left out)."""
    f = Path(job) / ".hydra" / "overrides.yaml"
    overrides = list(yaml.safe_load(f.read_text()) or []) if f.exists() else []
    return dict(o.split("=", 1) for o in overrides if "=" in o and not o.startswith("experiment="))


def varying_overrides(jobs: List[Path]) -> dict:
    """``{job name: {key: value}}`` of the overrides whose value differs between ``jobs``."""
    ov = {j.name: job_override_dict(j) for j in jobs}
    keys = list(dict.fromkeys(k for o in ov.values() for k in o))
    vary = [k for k in keys if len({o.get(k) for o in ov.values()}) > 1]
    return {n: {k: o[k] for k in vary if k in o} for n, o in ov.items()}


def describe_job(name: str, state: str, message: str, overrides: dict) -> str:
    """``job 1 (n_particles=-1) failed: error: ...`` / ``job 3 (...) has no results (...)``."""
    ov = " ".join(f"{k}={v}" for k, v in overrides.items())
    head = f"job {name}" + (f" ({ov})" if ov else "")
    if state == "failed":
        return f"{head} failed: {message}"
    if state == "interrupted":
        return f"{head} was interrupted (Ctrl-C or SIGTERM): rerun it with resume=true"
    if state == "task":  # finished, with a task's results (collect.py merges the run command's tables)
        return f"{head} ran a task: its results are {message} in its folder, not a summary.csv to merge"
    if state == "damaged":
        return (
            f"{head}: {message}; to write it again, rerun the job into its folder (its overrides are in "
            ".hydra/overrides.yaml there) with hydra.run.dir=<that folder> overwrite=true"
        )
    return f"{head} has no results (still running, killed, or never started)"


def report_sweep(sweep: Path, stopped_by: Optional[str] = None) -> dict:
    """Print (stderr) what happened to every job of ``sweep``: the counts, then each job that did not
    finish with its varying overrides, and how to merge what finished; the counts per state.
    ``stopped_by``: the stop request that ended the sweep (``Ctrl-C``, ``SIGTERM``)."""
    jobs = job_dirs(sweep)
    bad = {j.name: s for j, s in ((j, job_status(j)) for j in jobs) if s[0] != "done"}
    count = {k: sum(s[0] == k for s in bad.values()) for k in ("failed", "interrupted", "missing", "damaged")}
    damaged = f", {count['damaged']} with a damaged results.json" if count["damaged"] else ""
    stopped = f" (stopped by {stopped_by})" if stopped_by else ""
    print(
        f"sweep {sweep}{stopped}: {len(jobs)} jobs, {len(jobs) - len(bad)} finished, {count['failed']} failed, "
        f"{count['interrupted']} interrupted, {count['missing']} without results{damaged}",
        file=sys.stderr,
    )
    vary = varying_overrides(jobs)
    for n, (state, msg) in bad.items():
        print("  " + describe_job(n, state, msg, vary[n]), file=sys.stderr)
    if bad:
        print(f"  merge what finished: {collect_command(sweep)}", file=sys.stderr)
    return count


class SweepReport(Callback):
    """Hydra callback: after a multirun, :func:`report_sweep`; exit status 1 if a job failed. A sweep
    a stop request ended is reported by the command shell (with the command that goes on)."""

    def on_multirun_end(self, config: Any, **kwargs: Any) -> None:
        from torchflow.app.runner.execute import STOP

        if STOP.requested:
            return
        if report_sweep(Path(str(config.hydra.sweep.dir)))["failed"]:
            sys.exit(1)
