"""Paired per-trial differences between two runs of the same trials (e.g. float32 against float64).

    python -m experiments.benchmarks.paired RUN_A RUN_B [--metrics omat,log_evidence]

Each argument is a run folder (or its ``per_trial.csv``). For every filter in both and every metric,
the trials present in both runs are paired and the mean of ``B - A`` is printed with its standard
error (``sd / sqrt(n)`` over the n pairs) and ``z = mean / SE``: a difference within about 2-3 SE of
zero is what two runs with equal statistics give. Trials share their random streams across runs of
one seed, so pairing removes most of the Monte Carlo noise that separates two independent runs.
Rows: a markdown table on stdout.
"""

from __future__ import annotations

import argparse
import csv
import math
from pathlib import Path
from typing import Dict, List, Sequence, Tuple


def read(path) -> Dict[Tuple[str, int], dict]:
    """``{(filter, trial): row}`` of a run folder's ``per_trial.csv`` (or that file)."""
    path = Path(path)
    path = path / "per_trial.csv" if path.is_dir() else path
    with path.open() as fh:
        return {(r["filter"], int(r["trial"])): r for r in csv.DictReader(fh)}


def paired(a: Dict, b: Dict, metrics: Sequence[str]) -> List[dict]:
    """One row per filter and metric: ``n`` pairs with finite values in both, ``mean_a``, ``mean_b``,
    the mean difference ``b - a``, its standard error and ``z``."""
    rows = []
    for name in sorted({k[0] for k in a} & {k[0] for k in b}):
        keys = sorted(k for k in a if k[0] == name and k in b)
        for m in metrics:
            pairs = []
            for k in keys:
                try:
                    x, y = float(a[k][m]), float(b[k][m])
                except (KeyError, TypeError, ValueError):
                    continue
                if math.isfinite(x) and math.isfinite(y):
                    pairs.append((x, y))
            n = len(pairs)
            if n == 0:
                continue
            d = [y - x for x, y in pairs]
            mean = sum(d) / n
            sd = math.sqrt(sum((v - mean) ** 2 for v in d) / (n - 1)) if n > 1 else float("nan")
            se = sd / math.sqrt(n)
            rows.append(
                dict(
                    filter=name,
                    metric=m,
                    n=n,
                    mean_a=sum(x for x, _ in pairs) / n,
                    mean_b=sum(y for _, y in pairs) / n,
                    diff=mean,
                    se=se,
                    z=mean / se if se > 0 else (0.0 if mean == 0 else float("inf")),
                )
            )
    return rows


def table(rows: List[dict], a_label: str = "A", b_label: str = "B") -> str:
    """The rows as a markdown table."""
    out = [
        f"| filter | metric | pairs | mean {a_label} | mean {b_label} | {b_label} - {a_label} | SE | z |",
        "|---|---|---|---|---|---|---|---|",
    ]
    out += [
        f"| {r['filter']} | {r['metric']} | {r['n']} | {r['mean_a']:.6g} | {r['mean_b']:.6g} | {r['diff']:+.3g} | "
        f"{r['se']:.3g} | {r['z']:+.2f} |"
        for r in rows
    ]
    return "\n".join(out)


def main(argv=None) -> str:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("a")
    p.add_argument("b")
    p.add_argument("--metrics", default="omat,log_evidence")
    p.add_argument("--labels", default="A,B", help="the two runs' names in the table's header")
    args = p.parse_args(argv)
    la, lb = args.labels.split(",")
    text = table(paired(read(args.a), read(args.b), args.metrics.split(",")), la, lb)
    print(text)
    return text


if __name__ == "__main__":
    main()
