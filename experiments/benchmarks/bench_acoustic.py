"""Acoustic tracking benchmark against Stone Soup: torchflow's Gromov flow filter, PF-PF(Gromov),
PF-PF(LEDH) and bootstrap PF beside Stone Soup's ``GromovFlowParticleUpdater`` and bootstrap
``ParticleUpdater``, N = 500 particles, same trajectories, one run on one machine.

    python experiments/benchmarks/bench_acoustic.py            # 20 trials x 10 steps (ours), peer 3 x 5
    python experiments/benchmarks/bench_acoustic.py --quick    # smoke test

Time per trial-step: ours = wall time of the filter calls (each filter in its preferred chunk of
trials, after an untimed 1-trial warm-up) / (trials x steps); Stone Soup = mean over the completed
steps of predict + update (see ``peer_stonesoup.py`` for its exact configuration, as shipped).
Stone Soup's Gromov updater diverges on this model as shipped (its particles blow up in the first
updates and a later update raises): its time is reported per completed step, with the failure.
Accuracy: OMAT (optimal-assignment position error, metres; mean over trials and steps) and the
position RMSE without assignment (which counts swapped target labels as errors). "Tracking" means
finite and mean OMAT <= 2 m (the tables' lost-track threshold); a goal is met only while tracking.

Goals (issue 5): PF-PF(LEDH) and PF-PF(Gromov) >= 30x faster per trial-step than Stone Soup's
Gromov updater at N = 500.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

_REPO = Path(__file__).resolve().parents[2]
for p in (str(_REPO), str(Path(__file__).resolve().parent)):
    if p not in sys.path:
        sys.path.insert(0, p)

import numpy as np  # noqa: E402
import torch  # noqa: E402

from _common import loadavg, write_results  # noqa: E402
from torchflow import metrics  # noqa: E402
from torchflow.random import TrialStreams  # noqa: E402
from torchflow.filters import BootstrapParticleFilter, ParticleFlowFilter, ParticleFlowParticleFilter  # noqa: E402
from torchflow.models import AcousticTracking  # noqa: E402

GOAL = 30.0


def position_rmse(est: torch.Tensor, truth: torch.Tensor, model) -> float:
    """RMS over trials, steps and targets of the position error (metres)."""
    d = model.positions(est.double()) - model.positions(truth.double())
    return float(d.pow(2).sum(-1).mean().sqrt())


def ours_filters(model, N):
    return {
        "Gromov flow (torchflow)": ParticleFlowFilter(model, flow="gromov", n_particles=N),
        "PF-PF(Gromov) (torchflow)": ParticleFlowParticleFilter(model, flow="gromov", n_particles=N),
        "PF-PF(LEDH) (torchflow)": ParticleFlowParticleFilter(model, flow="ledh", n_particles=N),
        "BPF (torchflow)": BootstrapParticleFilter(model, n_particles=N),
    }


def time_ours(f, traj, mean, cov, seed):
    B = traj.observations.shape[0]
    chunk = f.preferred_chunk_trials() or B
    with torch.no_grad():
        f(traj.observations[:1, :1], mean[:1], cov[:1], torch.Generator().manual_seed(seed))  # warm-up
        t0 = time.perf_counter()
        parts = [f(traj.observations[s:s + chunk], mean[s:s + chunk], cov[s:s + chunk],
                   TrialStreams(seed, range(s, min(s + chunk, B)), key=f.stream_name))  # as the runner
                 for s in range(0, B, chunk)]
        wall = time.perf_counter() - t0
    est = torch.cat([p.estimates for p in parts])
    return wall, est, min(chunk, B)


def run(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=20, help="trials for torchflow's filters")
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--particles", type=int, default=500)
    ap.add_argument("--peer-trials", type=int, default=3)
    ap.add_argument("--peer-steps", type=int, default=5)
    ap.add_argument("--sigma-w", type=float, default=0.1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--peer-threads", type=int, default=1, help="numpy BLAS threads for Stone Soup (0: default)")
    ap.add_argument("--no-peer", action="store_true", help="skip Stone Soup")
    ap.add_argument("--quick", action="store_true", help="4 trials x 3 steps, peer 1 x 2")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    if a.quick:
        a.trials, a.steps, a.peer_trials, a.peer_steps = 4, 3, 1, 2
    if a.threads:
        torch.set_num_threads(a.threads)
    load0 = loadavg()
    model = AcousticTracking(sigma_w=a.sigma_w)
    g = torch.Generator().manual_seed(a.seed)
    B = max(a.trials, a.peer_trials)
    traj = model.simulate(B, max(a.steps, a.peer_steps), g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    N = a.particles

    rows = []
    ours_traj = traj[: a.trials]
    ours_traj = type(traj)(ours_traj.states[:, : a.steps + 1], ours_traj.observations[:, : a.steps])
    for name, f in ours_filters(model, N).items():
        wall, est, chunk = time_ours(f, ours_traj, mean[: a.trials], cov[: a.trials], a.seed + 1)
        truth = ours_traj.states[:, 1:]
        om = metrics.omat(model.positions(est.double()), model.positions(truth.double()))
        rows.append(dict(name=name, side="ours", trials=a.trials, steps=a.steps, chunk=chunk,
                         per_ts=wall / (a.trials * a.steps), wall=wall, finite=bool(torch.isfinite(est).all()),
                         position_rmse=position_rmse(est, truth, model), omat=float(om.mean()), error=None))
        print(f"[ours] {name}: {rows[-1]['per_ts']:.4g} s/trial-step, RMSE {rows[-1]['position_rmse']:.3f} m")

    peer_note = None
    if not a.no_peer:
        import peer_stonesoup as ps
        from bench_foundation import blas_limit

        if not ps.stonesoup_available():
            peer_note = "stonesoup is not installed (pip install -e '.[bench]'): peer rows skipped"
        else:
            for kind, label in (("gromov", "GromovFlowParticleUpdater (Stone Soup)"),
                                ("bootstrap", "ParticleUpdater bootstrap (Stone Soup)")):
                times, errs, rmses, finite, completed, fails, omats = [], [], [], [], 0, [], []
                with blas_limit(a.peer_threads):
                    for b in range(a.peer_trials):
                        r = ps.run_on_model(kind, model, traj.states[b, : a.peer_steps + 1],
                                            traj.observations[b, : a.peer_steps], mean[b], cov[b],
                                            n_particles=N, seed=a.seed + b)
                        times += list(r["step_times"])
                        completed += r["steps_completed"]
                        rmses.append(r["position_rmse"])
                        est = torch.as_tensor(np.asarray(r["estimates"], dtype=np.float64))
                        if est.numel():  # OMAT over the completed steps (inf where non-finite)
                            tru = traj.states[b, 1: 1 + est.shape[0]]
                            om = metrics.omat(model.positions(est.nan_to_num(1e300)).unsqueeze(0),
                                              model.positions(tru).unsqueeze(0))
                            omats.append(float(om.mean()))
                        finite.append(r["finite"])
                        if r.get("error"):
                            fails.append(f"trial {b}: step {r['steps_completed'] + 1} raised {r['error'][:160]}")
                        errs.append(r.get("step_position_rmse"))
                per_ts = float(np.mean(times)) if times else float("nan")
                rows.append(dict(name=label, side="peer", trials=a.peer_trials, steps=a.peer_steps,
                                 steps_completed=completed, per_ts=per_ts, finite=all(finite),
                                 position_rmse=float(np.nanmax(rmses)) if rmses else float("nan"),
                                 step_position_rmse=errs, failures=fails, chunk=1,
                                 omat=float(np.mean(omats)) if omats else None,
                                 stonesoup=ps.stonesoup_version()))
                print(f"[peer] {label}: {per_ts:.4g} s/step over {completed} completed steps; failures: {fails}")
    ref = next((r for r in rows if r["name"].startswith("GromovFlowParticleUpdater")), None)
    boot = next((r for r in rows if r["name"].startswith("ParticleUpdater")), None)
    for r in rows:
        r["vs_stonesoup_gromov"] = ref["per_ts"] / r["per_ts"] if ref and r["side"] == "ours" else None
        r["vs_stonesoup_bootstrap"] = boot["per_ts"] / r["per_ts"] if boot and r["name"].startswith("BPF") else None
        goal = GOAL if r["name"].startswith(("PF-PF(LEDH)", "PF-PF(Gromov)")) and ref else None
        r["goal"] = goal
        r["met"] = (r["vs_stonesoup_gromov"] >= goal and status(r) == "tracking") if goal else None
    info = dict(platform=platform.platform(), cpus=os.cpu_count(), torch=torch.__version__,
                threads=torch.get_num_threads(), load_start=load0, load_end=loadavg(),
                command="python experiments/benchmarks/bench_acoustic.py" + (" " + " ".join(argv) if argv else ""),
                peer_note=peer_note)
    md = markdown(info, rows, a)
    return dict(machine=info, rows=rows, markdown=md, args=vars(a))


def _f(x, fmt="{:.3g}"):
    return "-" if x is None or (isinstance(x, float) and np.isnan(x)) else fmt.format(x)


def status(r, lost_m: float = 2.0) -> str:
    """``diverged`` (non-finite or position errors over 1 km; ``, then raised`` when a later step
    raised), ``tracking`` (mean OMAT <= ``lost_m``, the tables' lost-track threshold) or
    ``finite, tracks lost``."""
    if not r["finite"] or not r["position_rmse"] < 1e3:
        return "diverged, then raised" if r.get("failures") else "diverged"
    if r.get("failures"):
        return "raised"
    om = r.get("omat")
    if om is not None and om > lost_m:
        return "finite, tracks lost"
    return "tracking"


def markdown(info, rows, a) -> str:
    lines = [
        "## Acoustic tracking vs Stone Soup" + (" (--quick)" if a.quick else ""),
        "",
        f"Machine: {info['platform']}, {info['cpus']} CPUs, torch {info['torch']} ({info['threads']} threads); "
        f"Stone Soup with numpy BLAS threads {a.peer_threads or 'default'}. Load at start {info['load_start']}, "
        f"end {info['load_end']}.",
        f"Acoustic model sigma_w = {a.sigma_w}, N = {a.particles}; ours {a.trials} trials x {a.steps} steps "
        f"(float64, trials per call in the table), Stone Soup {a.peer_trials} trials x up to {a.peer_steps} steps "
        "(its time is the mean over completed steps).",
        f"Command: `{info['command']}`",
        "",
        "| filter | s / trial-step | Stone Soup Gromov time / ours | Stone Soup bootstrap time / ours | goal | met "
        "| position RMSE (m) | OMAT (m) | status | trials per call |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        goal = f">= {r['goal']:.0f}x" if r.get("goal") else "-"
        met = "-" if r.get("met") is None else ("yes" if r["met"] else "NO")
        lines.append(f"| {r['name']} | {_f(r['per_ts'], '{:.4g}')} | {_f(r.get('vs_stonesoup_gromov'), '{:.1f}x')} "
                     f"| {_f(r.get('vs_stonesoup_bootstrap'), '{:.1f}x')} | {goal} | {met} "
                     f"| {_f(r['position_rmse'], '{:.3g}')} | {_f(r.get('omat'), '{:.3g}')} | {status(r)} "
                     f"| {r.get('chunk', '-')} |")
    lines.append("")
    if info.get("peer_note"):
        lines.append(f"- {info['peer_note']}")
    for r in rows:
        if r["side"] == "peer":
            lines.append(f"- {r['name']} (stonesoup {r.get('stonesoup')}): {r['steps_completed']} of "
                         f"{r['trials'] * r['steps']} steps completed; worst position RMSE {_f(r['position_rmse'], '{:.3g}')} m.")
            for fmsg in r.get("failures", []):
                lines.append(f"  - {fmsg}")
            if r["name"].startswith("Gromov"):
                steps = [e for e in (r.get("step_position_rmse") or []) if e]
                if steps:
                    lines.append("  - per-step position RMSE (m) by trial: "
                                 + "; ".join(", ".join(_f(v, "{:.2g}") for v in e) for e in steps))
    lines.append("- Ratios are Stone Soup's time per step over ours per trial-step: both are the cost of "
                 "filtering one trajectory for one time step.")
    return "\n".join(lines) + "\n"


def main(argv=None):
    res = run(argv if argv is not None else sys.argv[1:])
    write_results(res, "acoustic", res["args"]["quick"], res["args"]["out"])


if __name__ == "__main__":
    main()
