"""Collect a Hydra sweep: one table of every job's ``summary.csv`` beside the job's overrides.

    python experiments/collect.py multirun/<label>/<time> [--columns omat,ospa,ess,sec_per_step]

Prints a markdown table (columns: the overrides that vary between jobs, then the summary columns)
and writes ``sweep_summary.csv`` into the sweep directory. Jobs that failed
or are still running (no ``summary.csv``) are listed, not dropped silently.
"""
from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import yaml

DEFAULT_COLUMNS = ["mse", "omat", "ospa", "ess", "log_evidence_relmse", "lost_tracks", "repaired", "sec_per_step"]


def collect(sweep_dir: Path, columns=None):
    """Rows ``{overrides..., filter, columns...}`` of every job under ``sweep_dir`` and the list of
    job directories without results."""
    rows, missing, keys = [], [], []
    jobs = sorted((p for p in sweep_dir.iterdir() if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name))
    for job in jobs:
        ov_file = job / ".hydra" / "overrides.yaml"
        overrides = yaml.safe_load(ov_file.read_text()) if ov_file.exists() else []
        ov = dict(o.split("=", 1) for o in overrides if "=" in o and not o.startswith("experiment="))
        keys += [k for k in ov if k not in keys]
        summary = job / "summary.csv"
        if not summary.exists():
            missing.append(job.name)
            continue
        with open(summary) as fh:
            for r in csv.DictReader(fh):
                rows.append({"job": job.name, **ov, **r})
    # overrides shared by every job describe the sweep, not a row: keep only those that vary
    keys = [k for k in keys if len({r.get(k) for r in rows}) > 1]
    cols = ["job", *keys, "filter", "n_particles", "trials", *(columns or DEFAULT_COLUMNS)]
    cols = list(dict.fromkeys(c for c in cols if any(c in r for r in rows)))
    return rows, cols, missing


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
    args = ap.parse_args(argv)
    if not args.sweep_dir.is_dir():
        print(f"error: sweep_dir: expected a sweep folder (multirun/<label>/<time>), got {args.sweep_dir}, "
              "which is not a directory", file=sys.stderr)
        sys.exit(2)
    rows, cols, missing = collect(args.sweep_dir, args.columns.split(",") if args.columns else None)
    if not rows and not missing:
        hint = (" (it is a single run: its table is summary.csv there)" if (args.sweep_dir / "summary.csv").exists()
                else "")
        print(f"error: sweep_dir: {args.sweep_dir} holds no sweep jobs (numbered folders 0, 1, ... written by "
              f"`run.py -m`){hint}", file=sys.stderr)
        sys.exit(2)
    if not rows:
        print(f"error: sweep_dir: no job in {args.sweep_dir} has a summary.csv yet (failed or running: "
              f"{', '.join(missing)})", file=sys.stderr)
        sys.exit(2)
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        print("| " + " | ".join(_fmt(r.get(c)) for c in cols) + " |")
    with open(args.sweep_dir / "sweep_summary.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    if missing:
        print(f"jobs without summary.csv (failed or running): {', '.join(missing)}", file=sys.stderr)


if __name__ == "__main__":
    main()
