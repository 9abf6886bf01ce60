"""Acoustic tracking benchmark against Stone Soup: torchflow's Gromov flow filter, PF-PF(Gromov),
PF-PF(LEDH) and bootstrap PF beside Stone Soup's ``GromovFlowParticleUpdater`` and bootstrap
``ParticleUpdater`` (``peer_stonesoup.py``: their configuration, as shipped), N = 500, same trajectories.

    python -m experiments.benchmarks.bench_acoustic            # 20 trials x 10 steps (ours), peer 3 x 5

Time per trial-step: ours = wall time of the filter calls (each filter in its preferred chunk of
trials, after an untimed 1-trial warm-up) / (trials x steps); Stone Soup = mean over the completed
steps of predict + update (its Gromov updater diverges on this model and a later update raises).
Accuracy: OMAT (metres, mean over trials and steps) and the position RMSE without assignment.
Goals (issue 5): PF-PF(LEDH) and PF-PF(Gromov) >= 30x faster per trial-step than Stone Soup's Gromov
updater, met only while tracking (finite, mean OMAT <= 2 m). Without Stone Soup its rows are ``skipped``.
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


def omat(est: torch.Tensor, truth: torch.Tensor, model) -> float:
    """Mean OMAT (metres) of estimates ``(B, T, 16)`` against the true states."""
    return float(metrics.omat(model.positions(est.double()), model.positions(truth.double())).mean())


def peer_row(kind, label, model, traj, mean, cov, a) -> dict:
    """Stone Soup's ``kind`` filter over ``--peer-trials`` trajectories, one trial at a time."""
    times, rmses, finite, completed, fails, omats, steps = [], [], [], 0, [], [], []
    with h.blas_limit(a.peer_threads):
        for b in range(a.peer_trials):
            r = ps.run_on_model(kind, model, traj.states[b, : a.peer_steps + 1], traj.observations[b, : a.peer_steps],
                                mean[b], cov[b], n_particles=a.particles, seed=a.seed + b)
            times += r["step_times"]
            completed += r["steps_completed"]
            rmses.append(r["position_rmse"])
            est = torch.as_tensor(r["estimates"])
            if est.numel():  # OMAT over the completed steps (inf where non-finite)
                omats.append(omat(est.nan_to_num(1e300)[None], traj.states[b, 1: 1 + est.shape[0]][None], model))
            finite.append(r["finite"])
            if r["error"]:
                fails.append(f"trial {b}: step {r['steps_completed'] + 1} raised {r['error'][:160]}")
            steps.append(r["step_position_rmse"])
    per_ts = float(np.mean(times)) if times else float("nan")
    print(f"[peer] {label}: {per_ts:.4g} s/step over {completed} completed steps; failures: {fails}")
    return dict(name=label, side="peer", trials=a.peer_trials, steps=a.peer_steps, steps_completed=completed,
                per_ts=per_ts, finite=all(finite), position_rmse=float(np.nanmax(rmses)) if rmses else float("nan"),
                step_position_rmse=steps, failures=fails, chunk=1, omat=float(np.mean(omats)) if omats else None,
                stonesoup=ps.stonesoup_version())


def run(argv=None) -> dict:
    a = h.options(__doc__, argv, dict(trials=4, steps=3, peer_trials=1, peer_steps=2), trials=20, steps=10,
                  particles=500, peer_trials=3, peer_steps=5, sigma_w=0.1, seed=0, threads=None, peer_threads=1,
                  no_peer=False)  # peer_threads: numpy BLAS threads for Stone Soup (0: default)
    with h.session("bench_acoustic", argv, a.threads) as info:
        model = AcousticTracking(sigma_w=a.sigma_w)
        traj, mean, cov = h.simulate(model, max(a.trials, a.peer_trials), max(a.steps, a.peer_steps), a.seed)
        obs, truth = traj.observations[: a.trials, : a.steps], traj.states[: a.trials, 1: a.steps + 1]
        rows = []
        for key in OURS:
            f = h.make_filter(key, model, a.particles)
            chunk = f.preferred_chunk_trials() or a.trials
            t = h.time_filter(f, obs, mean[: a.trials], cov[: a.trials], chunk, h.streams(a.seed + 1, f.stream_name),
                              warm_randomness=lambda s, e: torch.Generator().manual_seed(a.seed + 1))  # as the runner
            est = torch.cat([p.estimates for p in t.result])
            d = model.positions(est.double()) - model.positions(truth.double())
            rows.append(dict(name=f"{h.LABELS[key]} (torchflow)", side="ours", trials=a.trials, steps=a.steps,
                             chunk=min(chunk, a.trials), per_ts=t.min / (a.trials * a.steps), wall=t.min,
                             finite=bool(torch.isfinite(est).all()), position_rmse=float(d.pow(2).sum(-1).mean().sqrt()),
                             omat=omat(est, truth, model), error=None))
            print(f"[ours] {rows[-1]['name']}: {rows[-1]['per_ts']:.4g} s/trial-step, "
                  f"RMSE {rows[-1]['position_rmse']:.3f} m")
        if not a.no_peer:
            have = h.peer("stonesoup", "updater.particle") is not None
            for kind, label in PEERS:
                rows.append(peer_row(kind, label, model, traj, mean, cov, a) if have else
                            dict(name=label, side="peer", status=h.skipped("stonesoup"), per_ts=None))
    ref, boot = (next((r for r in rows if r["name"] == label and r["per_ts"] is not None), None) for _, label in PEERS)
    for r in rows:
        r["vs_stonesoup_gromov"] = ref["per_ts"] / r["per_ts"] if ref and r["side"] == "ours" else None
        r["vs_stonesoup_bootstrap"] = boot["per_ts"] / r["per_ts"] if boot and r["name"].startswith("BPF") else None
        r["goal"] = GOAL if r["name"].startswith(("PF-PF(LEDH)", "PF-PF(Gromov)")) and ref else None
        r["met"] = (r["vs_stonesoup_gromov"] >= GOAL and status(r) == "tracking") if r["goal"] else None
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
    return "finite, tracks lost" if r.get("omat") is not None and r["omat"] > lost_m else "tracking"


def markdown(info, rows, a) -> str:
    notes = []
    for r in rows:
        if r["side"] == "peer" and not r.get("status"):
            notes.append(f"- {r['name']} (stonesoup {r.get('stonesoup')}): {r['steps_completed']} of "
                         f"{r['trials'] * r['steps']} steps completed; worst position RMSE "
                         f"{h.fmt(r['position_rmse'])} m.")
            notes += [f"  - {msg}" for msg in r.get("failures", [])]
            steps = [e for e in (r.get("step_position_rmse") or []) if e]
            if r["name"].startswith("Gromov") and steps:
                notes.append("  - per-step position RMSE (m) by trial: "
                             + "; ".join(", ".join(h.fmt(v, "{:.2g}") for v in e) for e in steps))
    return h.report(
        "## Acoustic tracking vs Stone Soup", a, info,
        [f"Stone Soup with numpy BLAS threads {a.peer_threads or 'default'}. Acoustic model sigma_w = {a.sigma_w}, "
         f"N = {a.particles}; ours {a.trials} trials x {a.steps} steps (float64, trials per call in the table), Stone "
         f"Soup {a.peer_trials} trials x up to {a.peer_steps} steps (its time is the mean over completed steps)."],
        ["filter", "s / trial-step", "Stone Soup Gromov time / ours", "Stone Soup bootstrap time / ours", "goal",
         "met", "position RMSE (m)", "OMAT (m)", "status", "trials per call"],
        [[r["name"], h.fmt(r["per_ts"], "{:.4g}"), h.fmt(r.get("vs_stonesoup_gromov"), "{:.1f}x"),
          h.fmt(r.get("vs_stonesoup_bootstrap"), "{:.1f}x"), h.fmt(r.get("goal"), ">= {:.0f}x"),
          h.met_cell(r.get("met")), h.fmt(r.get("position_rmse")), h.fmt(r.get("omat")), status(r),
          r.get("chunk", "-")] for r in rows],
        *notes, "- Ratios are Stone Soup's time per step over ours per trial-step: both are the cost of "
                "filtering one trajectory for one time step.")


if __name__ == "__main__":
    h.main(run, "acoustic")
