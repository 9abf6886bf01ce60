"""Acoustic tracking benchmark against Stone Soup: torchflow's Gromov flow filter, PF-PF(Gromov),
PF-PF(LEDH) and bootstrap PF beside Stone Soup's ``GromovFlowParticleUpdater`` and bootstrap
``ParticleUpdater``, N = 500 particles, same trajectories, one run on one machine.

    python -m experiments.benchmarks.bench_acoustic            # 20 trials x 10 steps (ours), peer 3 x 5
    python -m experiments.benchmarks.bench_acoustic --quick    # smoke test

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

Without Stone Soup installed its two rows read ``skipped: stonesoup not installed``.
"""
from __future__ import annotations

import numpy as np
import torch

from torchflow import metrics
from torchflow.models import AcousticTracking

from . import harness as h
from . import peer_stonesoup as ps

GOAL = 30.0
OURS = ("flow_gromov", "gromov", "ledh", "bpf")
PEERS = (("gromov", "GromovFlowParticleUpdater (Stone Soup)"), ("bootstrap", "ParticleUpdater bootstrap (Stone Soup)"))


def position_rmse(est: torch.Tensor, truth: torch.Tensor, model) -> float:
    """RMS over trials, steps and targets of the position error (metres)."""
    d = model.positions(est.double()) - model.positions(truth.double())
    return float(d.pow(2).sum(-1).mean().sqrt())


def time_ours(f, traj, mean, cov, seed):
    """Wall time of ``f`` over all trials in its preferred chunks after a 1-trial warm-up; returns
    ``(seconds, estimates, trials per call)``."""
    B = traj.observations.shape[0]
    chunk = f.preferred_chunk_trials() or B
    t = h.time_filter(f, traj.observations, mean, cov, chunk, h.streams(seed, f.stream_name),  # as the runner
                      warm_randomness=lambda s, e: torch.Generator().manual_seed(seed))
    return t.min, torch.cat([p.estimates for p in t.result]), min(chunk, B)


def peer_row(kind, label, model, traj, mean, cov, a) -> dict:
    """Stone Soup's ``kind`` filter over ``--peer-trials`` trajectories, one trial at a time."""
    times, errs, rmses, finite, completed, fails, omats = [], [], [], [], 0, [], []
    with h.blas_limit(a.peer_threads):
        for b in range(a.peer_trials):
            r = ps.run_on_model(kind, model, traj.states[b, : a.peer_steps + 1], traj.observations[b, : a.peer_steps],
                                mean[b], cov[b], n_particles=a.particles, seed=a.seed + b)
            times += list(r["step_times"])
            completed += r["steps_completed"]
            rmses.append(r["position_rmse"])
            est = torch.as_tensor(np.asarray(r["estimates"], dtype=np.float64))
            if est.numel():  # OMAT over the completed steps (inf where non-finite)
                tru = traj.states[b, 1: 1 + est.shape[0]]
                om = metrics.omat(model.positions(est.nan_to_num(1e300)).unsqueeze(0), model.positions(tru).unsqueeze(0))
                omats.append(float(om.mean()))
            finite.append(r["finite"])
            if r.get("error"):
                fails.append(f"trial {b}: step {r['steps_completed'] + 1} raised {r['error'][:160]}")
            errs.append(r.get("step_position_rmse"))
    per_ts = float(np.mean(times)) if times else float("nan")
    print(f"[peer] {label}: {per_ts:.4g} s/step over {completed} completed steps; failures: {fails}")
    return dict(name=label, side="peer", trials=a.peer_trials, steps=a.peer_steps, steps_completed=completed,
                per_ts=per_ts, finite=all(finite), position_rmse=float(np.nanmax(rmses)) if rmses else float("nan"),
                step_position_rmse=errs, failures=fails, chunk=1, omat=float(np.mean(omats)) if omats else None,
                stonesoup=ps.stonesoup_version())


def run(argv=None) -> dict:
    ap = h.parser(__doc__, "4 trials x 3 steps, peer 1 x 2")
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
    a = ap.parse_args(argv)
    if a.quick:
        a.trials, a.steps, a.peer_trials, a.peer_steps = 4, 3, 1, 2
    with h.torch_threads(a.threads):
        info = h.machine(command=h.command("bench_acoustic", argv))
        model = AcousticTracking(sigma_w=a.sigma_w)
        traj, mean, cov = h.simulate(model, max(a.trials, a.peer_trials), max(a.steps, a.peer_steps), a.seed)
        ours_traj = type(traj)(traj.states[: a.trials, : a.steps + 1], traj.observations[: a.trials, : a.steps])
        truth = ours_traj.states[:, 1:]
        rows = []
        for key in OURS:
            f = h.make_filter(key, model, a.particles)
            wall, est, chunk = time_ours(f, ours_traj, mean[: a.trials], cov[: a.trials], a.seed + 1)
            om = metrics.omat(model.positions(est.double()), model.positions(truth.double()))
            rows.append(dict(name=f"{h.LABELS[key]} (torchflow)", side="ours", trials=a.trials, steps=a.steps,
                             chunk=chunk, per_ts=wall / (a.trials * a.steps), wall=wall,
                             finite=bool(torch.isfinite(est).all()), position_rmse=position_rmse(est, truth, model),
                             omat=float(om.mean()), error=None))
            print(f"[ours] {rows[-1]['name']}: {rows[-1]['per_ts']:.4g} s/trial-step, "
                  f"RMSE {rows[-1]['position_rmse']:.3f} m")
        if not a.no_peer:
            have = h.peer("stonesoup", "updater.particle") is not None
            for kind, label in PEERS:
                rows.append(peer_row(kind, label, model, traj, mean, cov, a) if have else
                            dict(name=label, side="peer", status=h.skipped("stonesoup"), per_ts=None))
        info["load_end"] = h.loadavg()
    timed = {kind: next((r for r in rows if r["name"] == label and r["per_ts"] is not None), None)
             for kind, label in PEERS}
    ref, boot = timed["gromov"], timed["bootstrap"]
    for r in rows:
        r["vs_stonesoup_gromov"] = ref["per_ts"] / r["per_ts"] if ref and r["side"] == "ours" else None
        r["vs_stonesoup_bootstrap"] = boot["per_ts"] / r["per_ts"] if boot and r["name"].startswith("BPF") else None
        goal = GOAL if r["name"].startswith(("PF-PF(LEDH)", "PF-PF(Gromov)")) and ref else None
        r["goal"] = goal
        r["met"] = (r["vs_stonesoup_gromov"] >= goal and status(r) == "tracking") if goal else None
    return dict(machine=info, rows=rows, markdown=markdown(info, rows, a), args=vars(a))


def status(r, lost_m: float = 2.0) -> str:
    """``skipped: ...`` (no peer library), ``diverged`` (non-finite or position errors over 1 km;
    ``, then raised`` when a later step raised), ``tracking`` (mean OMAT <= ``lost_m``, the tables'
    lost-track threshold) or ``finite, tracks lost``."""
    if r.get("status"):
        return r["status"]
    if not r["finite"] or not r["position_rmse"] < 1e3:
        return "diverged, then raised" if r.get("failures") else "diverged"
    if r.get("failures"):
        return "raised"
    om = r.get("omat")
    if om is not None and om > lost_m:
        return "finite, tracks lost"
    return "tracking"


def markdown(info, rows, a) -> str:
    lines = h.header("## Acoustic tracking vs Stone Soup", a.quick, info,
                     f"Stone Soup with numpy BLAS threads {a.peer_threads or 'default'}. Acoustic model sigma_w = "
                     f"{a.sigma_w}, N = {a.particles}; ours {a.trials} trials x {a.steps} steps (float64, trials per "
                     f"call in the table), Stone Soup {a.peer_trials} trials x up to {a.peer_steps} steps (its time "
                     "is the mean over completed steps).")
    lines += h.md_table(
        ["filter", "s / trial-step", "Stone Soup Gromov time / ours", "Stone Soup bootstrap time / ours", "goal",
         "met", "position RMSE (m)", "OMAT (m)", "status", "trials per call"],
        [[r["name"], h.fmt(r["per_ts"], "{:.4g}"), h.fmt(r.get("vs_stonesoup_gromov"), "{:.1f}x"),
          h.fmt(r.get("vs_stonesoup_bootstrap"), "{:.1f}x"), h.fmt(r.get("goal"), ">= {:.0f}x"),
          h.met_cell(r.get("met")), h.fmt(r.get("position_rmse")),
          h.fmt(r.get("omat")), status(r), r.get("chunk", "-")] for r in rows])
    lines.append("")
    for r in rows:
        if r["side"] == "peer" and not r.get("status"):
            lines.append(f"- {r['name']} (stonesoup {r.get('stonesoup')}): {r['steps_completed']} of "
                         f"{r['trials'] * r['steps']} steps completed; worst position RMSE "
                         f"{h.fmt(r['position_rmse'])} m.")
            lines += [f"  - {msg}" for msg in r.get("failures", [])]
            steps = [e for e in (r.get("step_position_rmse") or []) if e]
            if r["name"].startswith("Gromov") and steps:
                lines.append("  - per-step position RMSE (m) by trial: "
                             + "; ".join(", ".join(h.fmt(v, "{:.2g}") for v in e) for e in steps))
    lines.append("- Ratios are Stone Soup's time per step over ours per trial-step: both are the cost of "
                 "filtering one trajectory for one time step.")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    h.main(run, "acoustic")
