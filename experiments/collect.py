"""Collect a Hydra sweep: one table of every job's ``summary.csv`` beside the job's overrides.

    python experiments/collect.py multirun/<label>/<time> [--columns omat,ospa,ess,sec_per_step]
    python experiments/collect.py multirun/<label>/<time> --plot filter.pfgspf.n_components:g_eff

Prints a markdown table (the overrides that vary between jobs, then every summary column some job
filled, or those ``--columns`` names), writes
``sweep_summary.csv`` into the sweep directory and lists the jobs that failed or have no results
(any Hydra launcher). ``--plot X:Y[:GROUP]`` also draws Y against X, one line per value of GROUP
(default: the other varying overrides and the filter), +-1 standard error over the job's trials,
into ``<sweep_dir>/<Y>_vs_<X>.png``.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import sys
from pathlib import Path

from torchflow.app.runner import SUMMARY_COLUMNS
from torchflow.app.runner.figures import pyplot
from torchflow.app.runner.sweep import (
    TASK_RESULTS,
    describe_job,
    job_dirs,
    job_override_dict,
    job_status,
    varying_overrides,
)
from torchflow.app.runner.writers import write_csv


def collect(sweep_dir: Path, columns=None):
    """Rows ``{overrides..., filter, columns...}`` of every finished job under ``sweep_dir`` (a job whose
    ``results.json`` is damaged: its CSV files, written before it), the columns, and the jobs without
    (complete) results: ``{"name", "state" ("failed" | "interrupted" | "missing" | "damaged"), "message",
    "overrides"}`` (overrides that vary between jobs)."""
    rows, missing, keys, summary_cols = [], [], [], []
    vary = varying_overrides(job_dirs(sweep_dir))
    for job in job_dirs(sweep_dir):
        ov = job_override_dict(job)
        keys += [k for k in ov if k not in keys]
        state, message = job_status(job)
        summary = job / "summary.csv"
        # a damaged results.json was written last, after the complete CSV files: they are merged
        merged = state in ("done", "failed", "damaged") and summary.exists() and (job / "results.json").exists()
        if state == "damaged":
            message += (
                "; its summary.csv and per_trial.csv, written before it, are merged"
                if merged
                else "; it has no summary.csv to merge"
            )
        if state != "done" or not summary.exists():
            task = next((n for n in TASK_RESULTS if (job / n).exists()), None)
            if state == "done" and task is not None:  # a finished task=smooth / task=pmmh job: not a run's table
                state, message = "task", task
            missing.append(
                {
                    "name": job.name,
                    "state": "missing" if state == "done" else state,
                    "message": message,
                    "overrides": vary[job.name],
                }
            )
        if not merged:
            continue  # a running job's partial summary.csv is not merged
        se = _trial_standard_errors(job / "per_trial.csv")
        with open(summary) as fh:
            header = next(csv.reader(fh), [])
            summary_cols += [c for c in header if c not in summary_cols]
            fh.seek(0)
            rows += [
                {"job": job.name, **ov, **r, **{f"{k}_se": v for k, v in se.get(r.get("filter"), {}).items()}}
                for r in csv.DictReader(fh)
            ]
    # overrides shared by every job describe the sweep, not a row: keep only those that vary
    keys = [k for k in keys if len({r.get(k) for r in rows}) > 1]
    # by default every summary column that some job filled, in the summary's order
    shown = columns or [c for c in summary_cols if c not in ("filter", "n_particles", "trials", "error")]
    cols = ["job", *keys, "filter", "n_particles", "trials", *shown, "error"]
    cols = list(
        dict.fromkeys(
            c for c in cols if any(c in r for r in rows) and (c in ("job", *keys) or any(r.get(c) for r in rows))
        )
    )
    return rows, cols, missing


def _se(xs) -> float:
    m = sum(xs) / len(xs)
    return (sum((x - m) ** 2 for x in xs) / (len(xs) - 1) / len(xs)) ** 0.5


def _trial_standard_errors(path: Path) -> dict:
    """``{filter: {column: standard error of the mean over trials}}`` from a job's ``per_trial.csv``."""
    per = {}
    with open(path) if path.exists() else contextlib.nullcontext([]) as fh:
        for r in csv.DictReader(fh):
            for k, v in r.items():
                with contextlib.suppress(TypeError, ValueError):
                    per.setdefault(r["filter"], {}).setdefault(k, []).append(float(v))
    return {f: {k: _se(xs) for k, xs in cols.items() if len(xs) > 1 and k != "trial"} for f, cols in per.items()}


def plot(rows, keys, spec: str, out_dir: Path) -> Path:
    """Draw ``Y`` against ``X`` (``spec = "X:Y[:GROUP]"``), one line per group, +-1 SE bars."""
    parts = spec.split(":")
    if len(parts) not in (2, 3):
        raise ValueError(f"--plot: expected X:Y or X:Y:GROUP, got {spec!r}")
    x, y = parts[:2]
    for name in (x, y):
        if not any(name in r for r in rows):
            raise ValueError(f"--plot: no column {name!r}; columns: {sorted({k for r in rows for k in r})}")
    group = [parts[2]] if len(parts) == 3 else [k for k in [*keys, "filter"] if k != x]
    plt = pyplot()
    if plt is None:
        raise ValueError("--plot: needs matplotlib (pip install matplotlib)")
    lines = {}
    for r in rows:
        if r.get(x) in (None, "") or r.get(y) in (None, ""):
            continue
        label = ", ".join(f"{r.get(g)}" for g in group)
        lines.setdefault(label, []).append((float(r[x]), float(r[y]), float(r.get(f"{y}_se") or 0.0)))
    fig, ax = plt.subplots(figsize=(6, 4))
    for label, pts in lines.items():
        pts.sort()
        ax.errorbar(
            [p[0] for p in pts], [p[1] for p in pts], yerr=[p[2] for p in pts], marker="o", capsize=3, label=label
        )
    ax.set_xlabel(x)
    ax.set_ylabel(y + " (mean +- 1 SE over trials)")
    ax.legend(fontsize=8, title=", ".join(group))
    fig.tight_layout()
    path = out_dir / f"{y}_vs_{x.split('.')[-1]}.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _fmt(v):
    try:
        f = float(v)
    except (TypeError, ValueError):
        return "" if v is None else str(v)
    return f"{f:.4g}"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sweep_dir", type=Path)
    ap.add_argument("--columns", default=None, help="comma-separated summary columns")
    ap.add_argument("--plot", default=None, help="X:Y[:GROUP]: draw Y against X (needs matplotlib)")
    args = ap.parse_args(argv)
    if not args.sweep_dir.is_dir():
        print(
            f"error: sweep_dir: expected a sweep folder (multirun/<label>/<time>), got {args.sweep_dir}, "
            "which is not a directory",
            file=sys.stderr,
        )
        sys.exit(2)
    rows, cols, missing = collect(args.sweep_dir, args.columns.split(",") if args.columns else None)
    if not rows and not missing:
        hint = (
            " (it is a single run: its table is summary.csv there)" if (args.sweep_dir / "summary.csv").exists() else ""
        )
        print(
            f"error: sweep_dir: {args.sweep_dir} holds no sweep jobs (numbered folders 0, 1, ... written by "
            f"`run.py -m`){hint}",
            file=sys.stderr,
        )
        sys.exit(2)
    tasks = sorted({n for j in job_dirs(args.sweep_dir) for n in TASK_RESULTS if (j / n).exists()})
    if not rows and tasks:
        print(
            f"error: sweep_dir: the jobs of {args.sweep_dir} ran a task (their results are {', '.join(tasks)} "
            "in each job folder); collect.py merges the run command's summary.csv of each job",
            file=sys.stderr,
        )
        sys.exit(2)
    if not rows:
        print(f"error: sweep_dir: no job in {args.sweep_dir} has results yet:", file=sys.stderr)
        for m in missing:
            print("  " + describe_job(**m), file=sys.stderr)
        sys.exit(2)
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        print("| " + " | ".join(_fmt(r.get(c)) for c in cols) + " |")
    write_csv(args.sweep_dir / "sweep_summary.csv", rows, cols)
    if args.plot:
        varying = [
            c
            for c in cols
            if c not in ("job", "filter", "n_particles", "trials")
            and c not in set(SUMMARY_COLUMNS)  # a metric, not a setting that varies
            and not c.endswith("_se")
            and c not in (args.columns.split(",") if args.columns else [])
        ]
        try:
            print(f"wrote {plot(rows, varying, args.plot, args.sweep_dir)}")
        except ValueError as e:
            print(f"error: {e}", file=sys.stderr)
            sys.exit(2)
    for m in missing:  # listed, not dropped silently
        print(describe_job(**m))


if __name__ == "__main__":
    main()
