"""The whole benchmark suite in one command; each section is a module of this folder,
``python -m experiments.benchmarks.bench_<section>``, with its own options.

    pip install -e ".[bench]"                                   # filterpy, particles, stonesoup, matplotlib
    python -m experiments.benchmarks.run_all                    # everything (~20-25 min on 2 CPU cores)
    python -m experiments.benchmarks.run_all --only acoustic --merge   # rerun one section, keep the rest
    python -m experiments.benchmarks.run_all --device cuda      # the GPU goals (sections gpu, ops)

Writes ``results_all[_quick].md`` (``results_all_cuda[_quick].md`` with ``--device cuda``): a table of
every goal, then each section's report (each section also writes its own results files); a section
that fails is reported and the others still run.
"""

from __future__ import annotations

import importlib
import json
import sys
import time
import traceback
from pathlib import Path

from . import harness as h

SECTIONS = [
    "foundation",
    "acoustic",
    "pfpf",
    "flops",
    "memory",
    "float32",
    "scaling",
    "streams",
    "gaussian_sum",
    "gradients",
    "ops",
]
#: the sections of ``--device cuda`` (the op counts are counted on the CPU: they do not depend on the device)
CUDA_SECTIONS = ["gpu", "ops"]


def _x(ratio, spec="{:.1f}x"):
    return None if ratio is None else spec.format(ratio)


def _headline(results: dict) -> list:
    """Rows ``(benchmark, setting, ours, reference, ratio, goal, met)`` of every stated goal:
    ``ours``/``reference`` are seconds per trial-step unless the benchmark's name says otherwise,
    ``ratio`` and ``goal`` are text in the goal's own terms (peer/ours speed-up, share of a rate, ...)."""
    rows = [
        (
            r["name"],
            r.get("setting", ""),
            r["per_ts_ours"],
            r["per_ts_peer"],
            _x(r["ratio"]),
            _x(r.get("goal"), ">= {:.0f}x"),
            r.get("met"),
        )
        for r in results.get("foundation", {}).get("rows", [])
    ]
    ac = results.get("acoustic", {}).get("rows", [])
    peer = lambda test: next((r for r in ac if r["side"] == "peer" and test(r["name"]) and r.get("per_ts")), None)
    ref = peer(lambda n: n.startswith("GromovFlowParticleUpdater") and "repaired" in n)
    shipped = peer(lambda n: n.startswith("GromovFlowParticleUpdater") and "repaired" not in n)
    boot = peer(lambda n: n.startswith("ParticleUpdater"))
    for r in ac:
        if r["side"] == "ours" and ref is not None:
            rows.append(
                (
                    f"{r['name']} vs Stone Soup Gromov (repaired)",
                    "acoustic N=500",
                    r["per_ts"],
                    ref["per_ts"],
                    _x(r["vs_stonesoup_gromov"]),
                    _x(r.get("goal"), ">= {:.0f}x"),
                    r.get("met"),
                )
            )
        if r["side"] == "ours" and shipped is not None:
            rows.append(
                (
                    f"{r['name']} vs Stone Soup Gromov (shipped)",
                    "acoustic N=500",
                    r["per_ts"],
                    shipped["per_ts"],
                    _x(r.get("vs_stonesoup_gromov_shipped")),
                    None,
                    None,
                )
            )
        if r["name"].startswith("BPF") and boot is not None:
            rows.append(
                (
                    "BPF (torchflow) vs Stone Soup bootstrap",
                    "acoustic N=500",
                    r["per_ts"],
                    boot["per_ts"],
                    _x(r["vs_stonesoup_bootstrap"]),
                    None,
                    None,
                )
            )
    pf = {r["filter"]: r for r in results.get("pfpf", {}).get("rows", [])}
    if "GPFIS" in pf and pf["GPFIS"].get("vs_ledh") is not None:
        g, ledh = pf["GPFIS"], pf["PF-PF(LEDH)"]
        rows.append(
            (
                "GPFIS time / PF-PF(LEDH) time",
                f"acoustic N={g['N']}",
                g["sec_per_trial_step"],
                ledh["sec_per_trial_step"],
                _x(g["vs_ledh"]),
                "<= 5x",
                g["vs_ledh"] <= 5,
            )
        )
    fl = {r["name"]: r for r in results.get("flops", {}).get("rows", [])}
    ledh_fl = next((r for n, r in fl.items() if n.startswith("PF-PF(LEDH)")), None)
    if ledh_fl is not None and "gemm_2048" in fl:
        share = ledh_fl["gflops"] / fl["gemm_2048"]["gflops"]
        rows.append(
            (
                "PF-PF(LEDH) GFLOP/s / large-GEMM GFLOP/s",
                "acoustic N=500",
                ledh_fl["gflops"],
                fl["gemm_2048"]["gflops"],
                f"{100 * share:.1f}%",
                ">= 10%",
                share >= 0.10,
            )
        )
    gs = next((r for r in results.get("gaussian_sum", {}).get("rows", []) if r.get("key") == "pfgspf"), None)
    if gs is not None:
        rows.append(
            (
                f"{gs['filter']} s/trial-step",
                "skewed-t Poisson d=144",
                gs["s_per_trial_step"],
                None,
                None,
                "<= 2 s",
                gs["s_per_trial_step"] <= 2.0,
            )
        )
    for r in results.get("ops", {}).get("rows", []):
        if r.get("target") is not None:
            rows.append(
                (
                    f"{r['name']} aten ops per time step",
                    "acoustic B=4 N=100",
                    r["ops"],
                    None,
                    None,
                    f"<= {r['target']} ops",
                    r["met"],
                )
            )
    gpu = results.get("gpu", {})
    for r in gpu.get("rows", []):
        if r.get("goal") is not None:
            goal = f"< {r['goal']} s per call" if isinstance(r["goal"], float) else r["goal"]
            rows.append(
                (
                    r["name"],
                    f"{gpu.get('args', {}).get('device', '')}",
                    r.get("wall", r.get("per_ts")),
                    r.get("peer"),
                    None if r.get("ratio") is None else f"{r['ratio']:.2f}",
                    goal,
                    r.get("met"),
                )
            )
    return rows


def run(argv=None) -> dict:
    a = h.options(__doc__, argv, None, only=None, skip="", merge=False, device="cpu")  # merge: saved sections too
    cuda = str(a.device).startswith("cuda")
    sections = CUDA_SECTIONS if cuda else SECTIONS
    chosen = [
        s
        for s in (",".join(sections) if a.only is None else str(a.only)).split(",")
        if s and s not in a.skip.split(",")
    ]
    for s in chosen:
        if s not in SECTIONS + CUDA_SECTIONS:
            raise SystemExit(f"--only/--skip: unknown section {s!r}; expected some of {SECTIONS + ['gpu']}")
    results, failures, times = {}, {}, {}
    for s in chosen:
        t0 = time.perf_counter()
        print(f"=== {s} ===", flush=True)
        try:
            args = (["--quick"] if a.quick else []) + (["--device", str(a.device)] if s == "gpu" else [])
            results[s] = importlib.import_module(f".bench_{s}", __package__).run(args)
            h.write_results(results[s], s, a.quick)
        except (Exception, SystemExit) as exc:  # a failing section must not lose the others' results
            failures[s] = "".join(traceback.format_exception_only(type(exc), exc)).strip()
            print(f"[{s}] FAILED: {failures[s]}", flush=True)
        times[s] = time.perf_counter() - t0
    if a.merge:  # re-running one section keeps the others' last results
        for s in sections:
            md = h.results_path(s, a.quick)
            if s not in results and s not in failures and md.exists() and md.with_suffix(".json").exists():
                saved = json.loads(md.with_suffix(".json").read_text())
                results[s] = dict(saved, markdown=md.read_text())
        chosen = [s for s in sections if s in results or s in failures]
    lines = [
        "# torchflow benchmark suite" + (" (--quick smoke test: sizes reduced)" if a.quick else ""),
        "",
        f"Command: `{h.command('run_all', argv)}`",
        "",
        "## Goals (same machine, same run)",
        "",
    ]
    lines += h.md_table(
        ["benchmark", "setting", "ours", "reference", "ratio", "goal", "met"],
        [
            [
                name,
                setting,
                h.fmt(ours, "{:.4g}"),
                h.fmt(peer, "{:.4g}"),
                h.fmt(ratio, "{}"),
                h.fmt(goal, "{}"),
                h.met_cell(met),
            ]
            for name, setting, ours, peer, ratio, goal, met in _headline(results)
        ],
    )
    lines += [
        "",
        "`ours` and `reference` are seconds per trial-step (a peer's, or PF-PF(LEDH)'s for GPFIS), "
        "GFLOP/s for the GEMM share, aten ops for the op counts, seconds per call for the GPU rows of "
        "PF-PF(LEDH); `ratio` is in the goal's terms (reference / ours for a peer, GPFIS / LEDH, the share "
        "of the large-GEMM rate, the cost per trial-step of the most trials over the fewest).",
    ]
    lines += ["", "Section times: " + ", ".join(f"{s} {t:.0f} s" for s, t in times.items())]
    lines += [f"- section **{s} FAILED**: `{msg[-400:]}`" for s, msg in failures.items()] + [""]
    for s in (s for s in chosen if s in results):
        lines += [results[s]["markdown"].replace("\n## ", "\n### "), ""]
        if results[s].get("plot"):  # the scaling curves
            lines += [f"![scaling curves]({Path(results[s]['plot']).name})", ""]
    md = "\n".join(lines) + "\n"
    out = h.results_path("all_cuda" if cuda else "all", a.quick, a.out)
    out.write_text(md)
    print(md)
    print(f"wrote {out}")
    return dict(results=results, failures=failures, markdown=md)


if __name__ == "__main__":
    res = run(sys.argv[1:])
    sys.exit(1 if res["failures"] else 0)
