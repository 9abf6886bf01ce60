"""Per-trial statistics of a run folder: quartiles of a per-trial metric with bootstrap standard
errors, and paired-bootstrap ratios of medians against a reference filter.

    python experiments/trial_stats.py outputs/seed004_clustering/<run> --metric omat --reference pfpf_ledh

Reads ``per_trial.csv`` and ``summary.csv`` of one run; prints a Markdown table: Q1, median
(bootstrap SE), Q3, mean (SE), trials above ``--outlier`` and lost (the run's ``lost`` column),
seconds per trial-step and the time ratio to the reference; then each filter's median ratio to the
reference with a 95 % paired-bootstrap interval (the same trials resampled for both filters).
"""
from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np


def _read(path: Path):
    with open(path) as fh:
        return list(csv.DictReader(fh))


def trial_table(run: Path, metric: str = "omat", reference: str = "pfpf_ledh", outlier: float = 6.0,
                resamples: int = 5000, seed: int = 0):
    """``(rows, ratios)``: per-filter statistics and paired median ratios (see the module docstring)."""
    per_trial = _read(run / "per_trial.csv")
    summary = {r["filter"]: r for r in _read(run / "summary.csv")}
    values, lost = {}, {}
    for r in per_trial:
        values.setdefault(r["filter"], []).append(float(r[metric]))
        lost.setdefault(r["filter"], []).append(r.get("lost") == "True")
    rng = np.random.default_rng(seed)
    n = len(next(iter(values.values())))
    idx = rng.integers(0, n, size=(resamples, n))
    ref_sec = float(summary[reference]["sec_per_step"]) if reference in summary else None
    rows, ratios = [], []
    for name, v in values.items():
        v = np.asarray(v)
        boot = np.median(v[idx], axis=1)
        sec = float(summary[name]["sec_per_step"])
        rows.append(dict(filter=name, q1=np.quantile(v, 0.25), median=np.median(v), median_se=boot.std(ddof=1),
                         q3=np.quantile(v, 0.75), mean=v.mean(), mean_se=v.std(ddof=1) / np.sqrt(n),
                         outliers=int((v > outlier).sum()), lost=int(np.sum(lost[name])), sec=sec,
                         time_ratio=sec / ref_sec if ref_sec else None))
        if reference in values and name != reference:
            ref = np.asarray(values[reference])
            ratio = np.median(v[idx], axis=1) / np.median(ref[idx], axis=1)
            ratios.append(dict(filter=name, ratio=np.median(v) / np.median(ref),
                               lo=np.quantile(ratio, 0.025), hi=np.quantile(ratio, 0.975)))
    return rows, ratios


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a run folder with per_trial.csv and summary.csv")
    ap.add_argument("--metric", default="omat")
    ap.add_argument("--reference", default="pfpf_ledh")
    ap.add_argument("--outlier", type=float, default=6.0)
    ap.add_argument("--resamples", type=int, default=5000)
    args = ap.parse_args(argv)
    for f in ("per_trial.csv", "summary.csv"):
        if not (args.run / f).is_file():
            print(f"error: run: {args.run} has no {f} (expected a run folder of experiments/run.py)", file=sys.stderr)
            return 2
    rows, ratios = trial_table(args.run, args.metric, args.reference, args.outlier, args.resamples)
    print(f"| filter | {args.metric} Q1 | median (bootstrap SE) | Q3 | mean (SE) | trials > {args.outlier:g} | lost "
          f"| s/trial-step | time vs {args.reference} |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        tr = f"{r['time_ratio']:.2f}" if r["time_ratio"] is not None else "-"
        print(f"| {r['filter']} | {r['q1']:.3f} | {r['median']:.3f} ({r['median_se']:.3f}) | {r['q3']:.3f} | "
              f"{r['mean']:.3f} ({r['mean_se']:.3f}) | {r['outliers']} | {r['lost']} | {r['sec']:.3g} | {tr} |")
    if ratios:
        print(f"\n| filter | median ratio to {args.reference} | 95 % paired-bootstrap interval |")
        print("|---|---|---|")
        for r in ratios:
            print(f"| {r['filter']} | {r['ratio']:.3f} | {r['lo']:.3f}-{r['hi']:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
