"""Comandur et al. (2022) Table 2 (d = 144) from per-trial files: the N* = 200 column against G, paired with G = 1,
and the G_eff-against-G and MSE-against-N_p figures (the seed's Figs 2 and 1, PFGSPF only) with the
paired fall of MSE from G = 1.

    python -m experiments.comandur2022_table2_report experiments/results/comandur2022_table2_gpu \
        --plot experiments/figures/comandur2022_table2_gpu.png

Reads ``per_trial_G<G>.csv`` (columns ``trial``, ``mse``, ``g_eff``; one row per run, written by
``experiments/run.py`` as ``per_trial.csv``) for every G found. Prints a Markdown table: per G the
runs, MSE mean (SE) +- sd, median, mean G_eff (SE), the paired difference to G = 1 on the runs both
have (SE over those runs), the paper's MSE +- sd and the distance in SEs. ``--trials a b`` keeps runs
a <= trial < b only (a common set for every G).

The SE of a mean is sd / sqrt(n); the runs are independent data sets (``inits_per_track`` = 1). The
paper's SE is its sd / sqrt(100) and is added in quadrature for the distance.
"""

from __future__ import annotations

import argparse
import csv
import math
import re
import statistics
import sys
from pathlib import Path

from experiments.trial_stats import mean_se

#: Comandur et al. (2022) Table 2, N* = 200: G -> (MSE, sd) over 100 runs (MODELS.md section 9)
PAPER = {
    1: (0.88, 0.32),
    2: (0.77, 0.26),
    3: (0.73, 0.24),
    4: (0.70, 0.26),
    5: (0.69, 0.25),
    7: (0.67, 0.24),
    10: (0.66, 0.23),
}
PAPER_RUNS = 100
PAPER_GEFF = {5: 3.5}  # the seed's text: average G_eff at G = 5 on this model


def read_runs(folder: Path, trials: tuple[int, int] | None = None) -> dict[int, dict[int, tuple[float, float]]]:
    """``{G: {trial: (mse, g_eff)}}`` from ``folder/per_trial_G<G>.csv``."""
    out: dict[int, dict[int, tuple[float, float]]] = {}
    for path in sorted(folder.glob("per_trial_G*.csv")):
        m = re.fullmatch(r"per_trial_G(\d+)\.csv", path.name)
        if not m:
            continue
        rows = {}
        with open(path) as fh:
            for r in csv.DictReader(fh):
                t = int(r["trial"])
                if trials is None or trials[0] <= t < trials[1]:
                    rows[t] = (float(r["mse"]), float(r["g_eff"]))
        if rows:
            out[int(m.group(1))] = rows
    if not out:
        raise SystemExit(f"{folder}: no per_trial_G<G>.csv with runs in range {trials}")
    return out


def mean_se_sd(v: list[float]) -> tuple[float, float, float]:
    """Mean, its standard error (``trial_stats.mean_se``: runs are independent) and the sample sd."""
    se = mean_se(v)
    return sum(v) / len(v), se, se * math.sqrt(len(v))


def table(runs: dict[int, dict[int, tuple[float, float]]]) -> list[dict]:
    """One row per G (ascending): statistics of MSE and G_eff and the paired difference to G = 1."""
    base = runs.get(1)
    rows = []
    for g in sorted(runs):
        r = runs[g]
        mse = [v[0] for v in r.values()]
        m, se, sd = mean_se_sd(mse)
        geff = mean_se_sd([v[1] for v in r.values()])
        row = dict(
            G=g,
            n=len(r),
            mse=m,
            se=se,
            sd=sd,
            median=statistics.median(mse),
            g_eff=geff[0],
            g_eff_se=geff[1],
            diff=None,
            diff_se=None,
            diff_n=0,
        )
        if base is not None and g != 1:
            common = sorted(set(r) & set(base))
            if len(common) > 1:
                d = mean_se_sd([r[t][0] - base[t][0] for t in common])
                row.update(diff=d[0], diff_se=d[1], diff_n=len(common))
        if g in PAPER:
            pm, psd = PAPER[g]
            row.update(paper=pm, paper_sd=psd, z=(m - pm) / math.hypot(se, psd / math.sqrt(PAPER_RUNS)))
        rows.append(row)
    return rows


def markdown(rows: list[dict]) -> str:
    lines = [
        "| N* x G | runs | MSE, mean (SE) +- sd | median | G_eff (SE) | minus G = 1, paired (SE), runs | "
        "paper (100 runs) | ours - paper, in SE |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        diff = "-" if r["diff"] is None else f"{r['diff']:+.3f} ({r['diff_se']:.3f}), {r['diff_n']}"
        paper = f"{r['paper']:.2f} +- {r['paper_sd']:.2f}" if "paper" in r else "-"
        z = f"{r['z']:+.1f}" if "z" in r else "-"
        lines.append(
            f"| 200 x {r['G']} | {r['n']} | {r['mse']:.3f} ({r['se']:.3f}) +- {r['sd']:.3f} | "
            f"{r['median']:.3f} | {r['g_eff']:.2f} ({r['g_eff_se']:.2f}) | {diff} | {paper} | {z} |"
        )
    return "\n".join(lines)


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    gs = [r["G"] for r in rows]
    fig, (a1, a3, a2) = plt.subplots(1, 3, figsize=(15, 4))
    a1.errorbar(
        [200 * g for g in gs],
        [r["mse"] for r in rows],
        yerr=[2 * r["se"] for r in rows],
        marker="o",
        capsize=3,
        label="ours, mean +- 2 SE",
    )
    pg = sorted(PAPER)
    a1.plot([200 * g for g in pg], [PAPER[g][0] for g in pg], "s--", label="Comandur et al. (2022) Table 2 (100 runs)")
    a1.set(xlabel="N_p = 200 G", ylabel="average MSE per dimension", title="PFGSPF, N* = 200, d = 144")
    a1.legend()
    paired = [r for r in rows if r["diff"] is not None]
    a3.axhline(0.0, color="grey", lw=0.8)
    a3.errorbar(
        [r["G"] for r in paired],
        [r["diff"] for r in paired],
        yerr=[2 * r["diff_se"] for r in paired],
        marker="o",
        capsize=3,
        label="ours, paired on the same runs, +- 2 SE",
    )
    a3.plot(pg[1:], [PAPER[g][0] - PAPER[1][0] for g in pg[1:]], "s--", label="Comandur et al. (2022) (unpaired)")
    a3.set(xlabel="G", ylabel="MSE(G) - MSE(G = 1)", title="the fall with G")
    a3.legend()
    a2.errorbar(
        gs,
        [r["g_eff"] for r in rows],
        yerr=[2 * r["g_eff_se"] for r in rows],
        marker="o",
        capsize=3,
        label="ours, mean +- 2 SE",
    )
    a2.plot(list(PAPER_GEFF), list(PAPER_GEFF.values()), "s", label="Comandur et al. (2022) (text, G = 5)")
    a2.plot(gs, gs, ":", color="grey", label="G_eff = G")
    a2.set(xlabel="G", ylabel="average G_eff", title="effective number of components")
    a2.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("folder", type=Path)
    p.add_argument("--trials", type=int, nargs=2, metavar=("START", "STOP"), default=None)
    p.add_argument("--plot", type=Path, default=None, help="write the two-panel figure here")
    a = p.parse_args(argv)
    rows = table(read_runs(a.folder, tuple(a.trials) if a.trials else None))
    print(markdown(rows))
    if a.plot:
        plot(rows, a.plot)
        print(f"figure: {a.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
