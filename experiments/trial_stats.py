"""Per-trial statistics of a run folder: quartiles of a per-trial metric with bootstrap standard
errors, and paired-bootstrap ratios of medians against a reference filter.

    python experiments/trial_stats.py outputs/li_coates_clustering/<run> --metric omat --reference pfpf_ledh

Reads ``per_trial.csv`` and ``summary.csv`` of one run; prints a Markdown table: Q1, median
(bootstrap SE), Q3, mean (SE), trials above ``--outlier`` and lost (the run's ``lost`` column),
seconds per trial-step and the time ratio to the reference; then each filter's median ratio to the
reference with a 95 % paired-bootstrap interval (the same trials resampled for both filters), and
the paired mean difference to the reference with its standard error.

``--against OTHER_RUN``: instead, each filter against the same filter of another run of the same
trials (e.g. one command under two arithmetic settings, ``tuning.fused_flows=0``): per metric the
paired mean difference with its SE and how many trials differ at all.

``--group K``: trials come in groups of K that share data (the runner's ``inits_per_track``: K
consecutive trials filter one trajectory from K initialisations). They are not independent, so
with K > 1 every standard error is taken over the group means (n / K of them) and the bootstrap
resamples whole groups; the plain per-trial SE would understate the error.
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


def group_means(v: np.ndarray, group: int) -> np.ndarray:
    """Means of consecutive groups of ``group`` trials (a last, shorter group is its own mean)."""
    return np.asarray([v[i : i + group].mean() for i in range(0, len(v), group)])


def mean_se(v: np.ndarray, group: int = 1) -> float:
    """Standard error of the mean of ``v`` when its trials come in groups of ``group`` sharing data:
    the spread of the group means over the square root of their number."""
    g = group_means(np.asarray(v, dtype=float), group)
    if len(g) < 2:
        return float("nan")
    return float(g.std(ddof=1) / np.sqrt(len(g)))


def trial_table(
    run: Path,
    metric: str = "omat",
    reference: str = "pfpf_ledh",
    outlier: float = 6.0,
    resamples: int = 5000,
    seed: int = 0,
    group: int = 1,
):
    """``(rows, ratios)``: per-filter statistics and paired median ratios and mean differences
    (see the module docstring); ``group``: trials per shared trajectory."""
    if group < 1:
        raise ValueError(f"group: expected a positive number of trials per trajectory, got {group}")
    per_trial = _read(run / "per_trial.csv")
    summary = {r["filter"]: r for r in _read(run / "summary.csv")}
    values, lost = {}, {}
    for r in per_trial:
        if r.get(metric, "") == "":  # a filter without this metric (the EKF's ESS): no row
            continue
        values.setdefault(r["filter"], []).append(float(r[metric]))
        lost.setdefault(r["filter"], []).append(r.get("lost") == "True")
    if not values:
        raise ValueError(f"metric: no filter of {run / 'per_trial.csv'} has a value of {metric!r}")
    n = len(next(iter(values.values())))
    uneven = {name: len(v) for name, v in values.items() if len(v) != n}
    if uneven:  # paired statistics need the same trials for every filter
        raise ValueError(f"per_trial.csv: expected {n} trials for every filter, got {uneven}")
    rng = np.random.default_rng(seed)
    n_groups = -(-n // group)
    # resample whole groups (trials sharing a trajectory move together); the last may be short
    pick = rng.integers(0, n_groups, size=(resamples, n_groups))
    idx = (pick[..., None] * group + np.arange(group)).reshape(resamples, -1)
    last = (n_groups - 1) * group  # a short last group fills its slots with its own trials again
    idx = np.where(idx < n, idx, last + (idx - last) % max(n - last, 1))
    ref_sec = float(summary[reference]["sec_per_step"]) if reference in summary else None
    rows, ratios = [], []
    for name, v in values.items():
        v = np.asarray(v)
        boot = np.median(v[idx], axis=1)
        sec = float(summary[name]["sec_per_step"])
        rows.append(
            dict(
                filter=name,
                q1=np.quantile(v, 0.25),
                median=np.median(v),
                median_se=boot.std(ddof=1),
                q3=np.quantile(v, 0.75),
                mean=v.mean(),
                mean_se=mean_se(v, group),
                outliers=int((v > outlier).sum()),
                lost=int(np.sum(lost[name])),
                sec=sec,
                time_ratio=sec / ref_sec if ref_sec else None,
            )
        )
        if reference in values and name != reference:
            ref = np.asarray(values[reference])
            ratio = np.median(v[idx], axis=1) / np.median(ref[idx], axis=1)
            ratios.append(
                dict(
                    filter=name,
                    ratio=np.median(v) / np.median(ref),
                    lo=np.quantile(ratio, 0.025),
                    hi=np.quantile(ratio, 0.975),
                    diff=float((v - ref).mean()),
                    diff_se=mean_se(v - ref, group),
                )
            )
    return rows, ratios


def paired_runs(run: Path, other: Path, metrics=("omat", "mse", "log_evidence", "ess"), group: int = 1):
    """Each filter of ``run`` against the same filter in ``other`` (the same trials, e.g. the same
    command under two arithmetic settings): per metric the mean of ``run`` minus ``other`` over the
    paired trials and its SE (over group means), and the trials whose value differs at all.
    Returns rows ``dict(filter, metric, n, mean, other_mean, diff, diff_se, changed)``."""
    if group < 1:
        raise ValueError(f"group: expected a positive number of trials per trajectory, got {group}")
    a, b = _read(run / "per_trial.csv"), _read(other / "per_trial.csv")
    key = lambda r: (r["filter"], int(r["trial"]))
    bmap = {key(r): r for r in b}
    rows = []
    for name in dict.fromkeys(r["filter"] for r in a):
        pairs = [(r, bmap[key(r)]) for r in a if r["filter"] == name and key(r) in bmap]
        if not pairs:
            raise ValueError(f"against: {other} has no trials of filter {name!r}")
        for m in metrics:
            if any(r.get(m, "") == "" or q.get(m, "") == "" for r, q in pairs):
                continue
            x = np.asarray([float(r[m]) for r, _ in pairs])
            y = np.asarray([float(q[m]) for _, q in pairs])
            rows.append(
                dict(
                    filter=name,
                    metric=m,
                    n=len(x),
                    mean=x.mean(),
                    other_mean=y.mean(),
                    diff=float((x - y).mean()),
                    diff_se=mean_se(x - y, group),
                    changed=int((x != y).sum()),
                )
            )
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a run folder with per_trial.csv and summary.csv")
    ap.add_argument("--metric", default="omat")
    ap.add_argument("--reference", default="pfpf_ledh")
    ap.add_argument("--outlier", type=float, default=6.0)
    ap.add_argument("--resamples", type=int, default=5000)
    ap.add_argument(
        "--group",
        type=int,
        default=1,
        help="trials per shared trajectory (the run's inits_per_track): SEs over group means",
    )
    ap.add_argument(
        "--against",
        type=Path,
        default=None,
        help="another run folder of the same trials: paired differences filter by filter",
    )
    args = ap.parse_args(argv)
    if args.against is not None:
        try:
            rows = paired_runs(args.run, args.against, group=args.group)
        except (ValueError, FileNotFoundError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        print(
            f"| filter | metric | trials | mean | mean in {args.against.name} | paired difference (SE) "
            "| trials that differ |"
        )
        print("|---|---|---|---|---|---|---|")
        for r in rows:
            print(
                f"| {r['filter']} | {r['metric']} | {r['n']} | {r['mean']:.4g} | {r['other_mean']:.4g} | "
                f"{r['diff']:+.3g} ({r['diff_se']:.3g}) | {r['changed']} |"
            )
        return 0
    for f in ("per_trial.csv", "summary.csv"):
        if not (args.run / f).is_file():
            print(f"error: run: {args.run} has no {f} (expected a run folder of experiments/run.py)", file=sys.stderr)
            return 2
    if args.group < 1:
        print(f"error: --group: expected a positive number of trials per trajectory, got {args.group}", file=sys.stderr)
        return 2
    try:
        rows, ratios = trial_table(
            args.run, args.metric, args.reference, args.outlier, args.resamples, group=args.group
        )
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(
        f"| filter | {args.metric} Q1 | median (bootstrap SE) | Q3 | mean (SE) | trials > {args.outlier:g} | lost "
        f"| s/trial-step | time vs {args.reference} |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        tr = f"{r['time_ratio']:.2f}" if r["time_ratio"] is not None else "-"
        print(
            f"| {r['filter']} | {r['q1']:.3f} | {r['median']:.3f} ({r['median_se']:.3f}) | {r['q3']:.3f} | "
            f"{r['mean']:.3f} ({r['mean_se']:.3f}) | {r['outliers']} | {r['lost']} | {r['sec']:.3g} | {tr} |"
        )
    if ratios:
        print(
            f"\n| filter | median ratio to {args.reference} | 95 % paired-bootstrap interval "
            f"| mean minus {args.reference}, paired (SE) |"
        )
        print("|---|---|---|---|")
        for r in ratios:
            print(
                f"| {r['filter']} | {r['ratio']:.3f} | {r['lo']:.3f}-{r['hi']:.3f} | {r['diff']:+.3f} "
                f"({r['diff_se']:.3f}) |"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
