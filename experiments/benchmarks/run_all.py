"""The whole benchmark suite in one command; each section is a module of this folder,
``python -m experiments.benchmarks.bench_<section>``, with its own options.

    pip install -e ".[bench]"                                   # filterpy, particles, stonesoup, matplotlib
    python -m experiments.benchmarks.run_all                    # everything (~20-25 min on 2 CPU cores)
    python -m experiments.benchmarks.run_all --only acoustic --merge   # rerun one section, keep the rest

Writes ``results_all[_quick].md``: a table of every goal, then each section's report (each section also
writes its own results files); a section that fails is reported and the others still run.
"""
from __future__ import annotations

import importlib
import json
import sys
import time
import traceback
from pathlib import Path

from . import harness as h

SECTIONS = ["foundation", "acoustic", "pfpf", "flops", "memory", "float32", "scaling", "streams", "gaussian_sum",
            "gradients", "ops"]


def _headline(results: dict) -> list:
    """Rows (benchmark, ours, peer, ratio, goal, met) of every goal the issue states."""
    rows = [(r["name"], r.get("setting", ""), r["per_ts_ours"], r["per_ts_peer"], r["ratio"], r.get("goal"),
             r.get("met")) for r in results.get("foundation", {}).get("rows", [])]
    ac = results.get("acoustic", {}).get("rows", [])
    peer = lambda test: next((r for r in ac if r["side"] == "peer" and test(r["name"]) and r.get("per_ts")), None)  # noqa: E731
    ref = peer(lambda n: n.startswith("GromovFlowParticleUpdater") and "repaired" in n)
    shipped = peer(lambda n: n.startswith("GromovFlowParticleUpdater") and "repaired" not in n)
    boot = peer(lambda n: n.startswith("ParticleUpdater"))
    for r in ac:
        if r["side"] == "ours" and ref is not None:
            rows.append((f"{r['name']} vs Stone Soup Gromov (repaired)", "acoustic N=500",
                         r["per_ts"], ref["per_ts"], r["vs_stonesoup_gromov"], r.get("goal"), r.get("met")))
        if r["side"] == "ours" and shipped is not None:
            rows.append((f"{r['name']} vs Stone Soup Gromov (shipped)", "acoustic N=500",
                         r["per_ts"], shipped["per_ts"], r.get("vs_stonesoup_gromov_shipped"), None, None))
        if r["name"].startswith("BPF") and boot is not None:
            rows.append(("BPF (torchflow) vs Stone Soup bootstrap", "acoustic N=500", r["per_ts"], boot["per_ts"],
                         r["vs_stonesoup_bootstrap"], None, None))
    return rows


def run(argv=None) -> dict:
    a = h.options(__doc__, argv, None, only=",".join(SECTIONS), skip="", merge=False)  # merge: saved sections too
    chosen = [s for s in a.only.split(",") if s and s not in a.skip.split(",")]
    for s in chosen:
        if s not in SECTIONS:
            raise SystemExit(f"--only/--skip: unknown section {s!r}; expected some of {SECTIONS}")
    results, failures, times = {}, {}, {}
    for s in chosen:
        t0 = time.perf_counter()
        print(f"=== {s} ===", flush=True)
        try:
            results[s] = importlib.import_module(f".bench_{s}", __package__).run(["--quick"] if a.quick else [])
            h.write_results(results[s], s, a.quick)
        except (Exception, SystemExit) as exc:  # a failing section must not lose the others' results
            failures[s] = "".join(traceback.format_exception_only(type(exc), exc)).strip()
            print(f"[{s}] FAILED: {failures[s]}", flush=True)
        times[s] = time.perf_counter() - t0
    if a.merge:  # re-running one section keeps the others' last results
        for s in SECTIONS:
            md = h.results_path(s, a.quick)
            if s not in results and s not in failures and md.exists() and md.with_suffix(".json").exists():
                saved = json.loads(md.with_suffix(".json").read_text())
                results[s] = dict(saved, markdown=md.read_text())
        chosen = [s for s in SECTIONS if s in results or s in failures]
    lines = ["# torchflow benchmark suite" + (" (--quick smoke test: sizes reduced)" if a.quick else ""), "",
             f"Command: `{h.command('run_all', argv)}`", "", "## Goals (same machine, same run)", ""]
    lines += h.md_table(
        ["benchmark", "setting", "ours s/trial-step", "peer s/trial-step", "ratio peer/ours", "goal", "met"],
        [[name, setting, h.fmt(ours, "{:.4g}"), h.fmt(peer, "{:.4g}"), h.fmt(ratio, "{:.1f}x"),
          h.fmt(goal, ">= {:.0f}x"), h.met_cell(met)]
         for name, setting, ours, peer, ratio, goal, met in _headline(results)])
    lines += ["", "Section times: " + ", ".join(f"{s} {t:.0f} s" for s, t in times.items())]
    lines += [f"- section **{s} FAILED**: `{msg[-400:]}`" for s, msg in failures.items()] + [""]
    for s in (s for s in chosen if s in results):
        lines += [results[s]["markdown"].replace("\n## ", "\n### "), ""]
        if results[s].get("plot"):  # the scaling curves
            lines += [f"![scaling curves]({Path(results[s]['plot']).name})", ""]
    md = "\n".join(lines) + "\n"
    out = h.results_path("all", a.quick, a.out)
    out.write_text(md)
    print(md)
    print(f"wrote {out}")
    return dict(results=results, failures=failures, markdown=md)


if __name__ == "__main__":
    res = run(sys.argv[1:])
    sys.exit(1 if res["failures"] else 0)
