"""float32 vs float64: accuracy and speed of torchflow's filters in single precision on the
linear-Gaussian (Table I) and acoustic tracking (Table II, sigma_w = 0.1 and the stiff 0.001) tables.

    python -m experiments.benchmarks.bench_float32                 # LG 20 trials, acoustic 8 x 40

The data is simulated once in float64; ``run_experiment`` filters it in both precisions (scored in
float64) after an untimed 2 x 1 warm-up. ``SE``: the float64 metric's Monte Carlo standard error; ``z
= (float32 - float64) / SE``, positive = worse. Verdict: ``ok`` when no table metric is worse by more
than ``--se-k`` SE nor 0.1 % (1e-8 for relMSE log Z); ``breaks`` when float32 raised, needed more
non-finite repairs, gave an ESS outside [1, N], a metric 10x worse or at least max(3, trials / 2) more
lost tracks; else ``degraded`` (more than ``k sqrt(max(lost64, 1))`` more lost tracks too, or a
Kalman-type filter's first update off by more than 1e-3 of the true-state scale).
"""

from __future__ import annotations

import argparse
import math
from typing import Dict, List, Optional

import torch

import torchflow.app.runner as tfx
from torchflow.app.runner.plan import simulate
from torchflow.filters import KalmanFilter
from torchflow.models import AcousticTracking, SensorNetwork
from torchflow.models.base import Trajectory

from . import harness as h

NAMES = {
    "kf": "KF",
    "ekf": "EKF",
    "ukf": "UKF",
    "bpf": "BPF",
    "ledh": "PF-PF(LEDH)",
    "edh": "PF-PF(EDH)",
    "gromov": "PF-PF(Gromov)",
    "geodesic": "PF-PF(Geodesic)",
}
DETERMINISTIC = ("kf", "ekf", "ukf")
TABLES = ("lg", "acoustic0.1", "acoustic0.001")
DEFAULT_FILTERS = {"lg": "kf,ukf,bpf,ledh,edh,gromov", "acoustic": "ekf,bpf,ledh,gromov,edh"}
#: per table: the metrics the verdict reads, with +1 where larger is worse and -1 where smaller is
METRICS = {
    "lg": {"mse": 1, "log_evidence_relmse": 1, "ess": -1},
    "acoustic": {"omat": 1, "ospa": 1, "lost_rate": 1, "ess": -1},
}
REL_FLOOR, ABS_FLOOR, BREAK_RATIO, POINTWISE_TOL = 1e-3, {"log_evidence_relmse": 1e-8}, 10.0, 1e-3  # see above


_kind = lambda table: "lg" if table == "lg" else "acoustic"


def make_model(table: str, lg_d: int = 64):
    return SensorNetwork(d=lg_d) if table == "lg" else AcousticTracking(sigma_w=float(table[len("acoustic") :]))


def given_data(traj: Trajectory, mean: torch.Tensor, cov: torch.Tensor):
    """``run_experiment`` filters this data (cast to its dtype; true states: float64) instead of its own."""

    def simulate(model, trials, steps, inits_per_track, generator):
        if traj.observations.shape[:2] != (trials, steps):
            raise ValueError("given_data: trials/steps differ from the shared data")
        dt, dev = model.dtype, model.device
        return (
            Trajectory(traj.states.to(dev), traj.observations.to(device=dev, dtype=dt)),
            mean.to(device=dev, dtype=dt),
            cov.to(device=dev, dtype=dt),
        )

    return simulate


def _se(values: List[float]) -> Optional[float]:
    t = torch.tensor(values, dtype=torch.float64)
    t = t[torch.isfinite(t)]
    return float(t.std() / math.sqrt(t.numel())) if t.numel() >= 2 else None


def run_precision(table, keys, dtype, traj, mean, cov, a, ref_logz) -> Dict[str, dict]:
    """One ``run_experiment`` call in ``dtype`` on the shared data; per filter: the summary row,
    per-trial metric lists and (Kalman-type filters) the estimates and log Z of a direct call."""
    model = make_model(table, a.lg_d)
    n = a.particles_lg if table == "lg" else a.particles_acoustic
    counts = {"bpf": a.bpf_particles or n, "edh": a.edh_particles or n}
    filters = {
        NAMES[k]: h.make_filter(
            k,
            model,
            counts.get(k, n),
            name=NAMES[k],  # the BPF counts its repairs
            **(dict(nonfinite="recover") if k == "bpf" else {}),
        )
        for k in keys
    }
    dt = tfx.resolve_dtype(dtype)
    model.to(dtype=dt)
    for name, f in filters.items():  # untimed warm-up: 2 trials x 1 step in this dtype
        f.to(dtype=dt)
        try:
            with torch.no_grad():
                f(traj.observations[:2, :1].to(dt), mean[:2].to(dt), cov[:2].to(dt), torch.Generator().manual_seed(0))
        except Exception:
            pass
    res = tfx.run_experiment(  # the shared data, through the runner's simulator argument
        model,
        filters,
        simulator=given_data(traj, mean, cov),
        trials=a.trials,
        steps=a.steps,
        seed=a.seed,
        inits_per_track=1,
        chunk_size=None,
        memory_budget_gb=a.memory_gb,
        dtype=dtype,
        progress=False,
    )
    out = {}
    for key, (name, f) in zip(keys, filters.items()):
        row = next(r for r in res.summary if r["filter"] == name)
        trials = [r for r in res.per_trial if r["filter"] == name]
        per = {col: [r[col] for r in trials] for col in ("mse", "omat", "ospa", "ess") if trials and col in trials[0]}
        if trials and "lost" in trials[0]:
            per["lost_rate"] = [float(r["lost"]) for r in trials]
        if ref_logz is not None and f.estimates_evidence and trials:
            lz = torch.tensor([r["log_evidence"] for r in trials], dtype=torch.float64)
            per["log_evidence_relmse"] = (((lz - ref_logz) / ref_logz) ** 2).tolist()
        summ = {k: (sum(v) / len(v) if v else None) for k, v in per.items()}
        ess_vals = per.get("ess", []) + [r["ess"] for r in res.per_step if r["filter"] == name and "ess" in r]
        info = dict(
            summary=row,
            per_trial=per,
            metrics=summ,
            n_particles=getattr(f, "n_particles", None),
            state_scale=float(traj.states[:, 1:].abs().max()),  # ESS range: outside [1, N] if a step's is
            ess_range=(min(ess_vals), max(ess_vals)) if ess_vals else None,
        )
        if key in DETERMINISTIC and not row.get("error"):
            with torch.no_grad():
                r = f(traj.observations.to(dt), mean.to(dt), cov.to(dt))
            info["estimates"], info["log_evidence"] = r.estimates.double(), r.log_evidence.double()
        out[key] = info
    return out


def compare(table, key, r64, r32, k_se) -> dict:
    """One result row: both precisions' metrics, SE, z, times, repairs and the verdict."""
    s64, s32 = r64["summary"], r32["summary"]
    row = dict(
        table=table,
        key=key,
        filter=NAMES[key],
        n_particles=r64["n_particles"],
        trials=s64["trials"],
        steps=s64["steps"],
        **{
            f"{k}{b}": s.get(col)
            for k, col in (("error", "error"), ("sec_per_step",) * 2, ("repaired",) * 2, ("lost", "lost_tracks"))
            for b, s in (("64", s64), ("32", s32))
        },
        metrics={},
    )
    t64, t32 = row["sec_per_step64"], row["sec_per_step32"]
    row["speedup"] = t64 / t32 if t64 and t32 else None
    reasons, breaks = [], []
    for m, sign in METRICS[_kind(table)].items():
        v64, v32 = r64["metrics"].get(m), r32["metrics"].get(m)
        if v64 is None and v32 is None:
            continue
        se = _se(r64["per_trial"].get(m, []))
        d = None if v64 is None or v32 is None else v32 - v64
        rel = d / abs(v64) if d is not None and v64 not in (0, None) else None
        z = sign * d / se if d is not None and se else None
        if v64 is not None and v32 is not None and max(abs(v64), abs(v32)) <= ABS_FLOOR.get(m, -1.0):
            rel = z = None  # both at round-off level (the Kalman filters' relMSE of log Z)
        row["metrics"][m] = dict(f64=v64, f32=v32, se=se, rel=rel, z=z)
        if d is None or not math.isfinite(v32 if v32 is not None else float("nan")):
            if v64 is not None:
                breaks.append(f"{m} not finite in float32")
            continue
        if m != "lost_rate" and sign * d > max(k_se * (se or 0.0), REL_FLOOR * abs(v64), ABS_FLOOR.get(m, 0.0)):
            ten = (sign > 0 and v64 > 0 and v32 > BREAK_RATIO * v64) or (sign < 0 and v32 * BREAK_RATIO < v64)
            zs = f", z = {_z(z)}" if z is not None else ""  # (lost tracks: judged on the counts below)
            (breaks if ten else reasons).append(f"{m} {_g(v64)} -> {_g(v32)}{zs}")
    l64, l32 = row["lost64"] or 0, row["lost32"] or 0
    if l32 - l64 > k_se * math.sqrt(max(l64, 1)):  # more lost tracks than Monte Carlo noise explains
        (breaks if l32 - l64 >= max(3, row["trials"] / 2) else reasons).append(f"lost tracks {l64} -> {l32}")
    n = r32["n_particles"]
    if r32.get("ess_range") and n and not (1 - 1e-3 <= r32["ess_range"][0] and r32["ess_range"][1] <= n * (1 + 1e-3)):
        breaks.append(
            f"ESS outside [1, N] ({r32['ess_range'][0]:.3g} .. {r32['ess_range'][1]:.4g}): "
            "log-weights too large to normalise in float32"
        )
    if row["error32"] and not row["error64"]:
        breaks.insert(0, f"float32 raised: {row['error32'][:160]}")
    if (row["repaired32"] or 0) > (row["repaired64"] or 0):
        breaks.append(f"non-finite repairs {row['repaired64'] or 0} -> {row['repaired32']}")
    if key in DETERMINISTIC and "estimates" in r64 and "estimates" in r32:
        e64, e32 = r64["estimates"], r32["estimates"]
        scale = r64["state_scale"]  # max |true state|: a diverged filter's own estimates are no scale
        row["max_est_diff_rel"] = float((e32 - e64).abs().max()) / scale if scale > 0 else None
        row["max_est_diff"] = float((e32 - e64).abs().max())
        row["first_step_diff_rel"] = float((e32[:, 0] - e64[:, 0]).abs().max()) / scale if scale > 0 else None
        lz64, lz32 = r64["log_evidence"], r32["log_evidence"]
        row["max_logz_diff"] = float((lz32 - lz64).abs().max())
        row["max_logz_diff_rel"] = float(((lz32 - lz64).abs() / lz64.abs().clamp_min(1e-300)).max())
        if row["first_step_diff_rel"] is not None and row["first_step_diff_rel"] > POINTWISE_TOL:
            reasons.append(
                f"first-step estimates differ from float64's by {row['first_step_diff_rel']:.2g} x the "
                f"true-state scale (all steps: {row['max_est_diff_rel']:.2g}; log Z by "
                f"{row['max_logz_diff_rel']:.2g} relative)"
            )
    row["verdict"], row["reason"] = (
        ("n/a", f"float64 raised: {row['error64'][:160]}")
        if row["error64"]
        else ("breaks", "; ".join(breaks + reasons))
        if breaks
        else ("degraded", "; ".join(reasons))
        if reasons
        else ("ok", "")
    )
    return row


def run_table(table: str, a) -> List[dict]:
    keys = h.keys_option(a.filters or DEFAULT_FILTERS[_kind(table)], NAMES)
    if table != "lg":
        keys = [k for k in keys if k != "kf"]  # the KF needs a linear-Gaussian model
    ta = argparse.Namespace(
        **vars(a),
        trials=a.lg_trials if table == "lg" else a.acoustic_trials,
        steps=a.steps_lg if table == "lg" else a.steps_acoustic,
    )
    model64 = make_model(table, a.lg_d)
    gen = torch.Generator().manual_seed(int(a.seed))
    traj, mean, cov = simulate(model64, ta.trials, ta.steps, 1, gen)
    ref_logz = None
    if table == "lg":  # exact log Z: the float64 Kalman filter on the shared data
        with torch.no_grad():
            ref_logz = KalmanFilter(model64, validate=False)(traj.observations, mean, cov).log_evidence.double()
    res = {dtype: run_precision(table, keys, dtype, traj, mean, cov, ta, ref_logz) for dtype in ("float64", "float32")}
    rows = [compare(table, k, res["float64"][k], res["float32"][k], a.se_k) for k in keys]
    for r in rows:
        r["inits_per_track"] = 1
        if not a.quiet:
            print(f"[{table}] {r['filter']}: {r['verdict']} {r['reason']}", flush=True)
    return rows


# cells: a number (non-finite as text), a relative change, a z score
_g = lambda x, f="{:.3g}": (
    "-" if x is None else str(x) if isinstance(x, float) and not math.isfinite(x) else f.format(x)
)
_pct = lambda x: "-" if x is None else f"{100 * x:+.1f}%" if abs(x) < 10 else f"{x:+.2g}x"
_z = lambda z: f"{z:+.1f}" if abs(z) < 1e3 else f"{z:+.1e}"


_TITLES = {
    "lg": "Linear-Gaussian sensor network (Table I setting: d = 64, T = {steps})",
    "acoustic0.1": "Acoustic tracking, sigma_w = 0.1 (Table II setting, T = {steps})",
    "acoustic0.001": "Acoustic tracking, stiff sigma_w = 0.001 (T = {steps})",
}
_LABEL = {
    "mse": "MSE",
    "log_evidence_relmse": "relMSE log Z",
    "omat": "OMAT (m)",
    "ospa": "OSPA (m)",
    "ess": "ESS",
    "lost_rate": "lost",
}


def table_markdown(table: str, rows: List[dict]) -> List[str]:
    kind = _kind(table)
    r0 = rows[0]
    out = [
        f"### {_TITLES.get(table, table).format(steps=r0['steps'])}",
        "",
        f"{r0['trials']} trials (inits per track {r0.get('inits_per_track', 1)}), float64 and float32 on the "
        "same observations. Cells: float64 ± SE / float32 (relative change, z = change / SE, positive = "
        "worse).",
        "",
    ]
    mets = [m for m in METRICS[kind] if m != "lost_rate"]
    head = (
        ["filter", "N"]
        + [_LABEL[m] for m in mets]
        + ["lost tracks f64 / f32"] * (kind == "acoustic")
        + ["repairs f64 / f32", "s / trial-step f64", "f32", "f32 speed-up", "verdict"]
    )

    def cell(v):
        if not v:
            return "-"
        se = f" ± {_g(v['se'], '{:.2g}')}" if v["se"] is not None else ""
        z = f", z {_z(v['z'])}" if v["z"] is not None else ""
        return f"{_g(v['f64'], '{:.4g}')}{se} / {_g(v['f32'], '{:.4g}')} ({_pct(v['rel'])}{z})"

    out += h.md_table(
        head,
        [
            [r["filter"], _g(r["n_particles"], "{}")]
            + [cell(r["metrics"].get(m)) for m in mets]
            + ([f"{_g(r['lost64'], '{}')} / {_g(r['lost32'], '{}')}"] if kind == "acoustic" else [])
            + [
                f"{_g(r['repaired64'], '{}')} / {_g(r['repaired32'], '{}')}",
                _g(r["sec_per_step64"], "{:.3g}"),
                _g(r["sec_per_step32"], "{:.3g}"),
                _g(r["speedup"], "{:.2f}x"),
                f"**{r['verdict']}**" + (f": {r['reason']}" if r["reason"] else ""),
            ]
            for r in rows
        ],
    )
    det = [r for r in rows if r.get("max_est_diff_rel") is not None]
    if det:
        out += ["", "Kalman-type filters point by point (no random numbers; float32 - float64 on the same data):", ""]
        out += h.md_table(
            [
                "filter",
                "first step: max abs(dx) / max abs(x_true)",
                "all steps: max abs(dx)",
                "max abs(dx) / max abs(x_true)",
                "max abs(d log Z)",
                "max abs(d log Z) / abs(log Z)",
            ],
            [
                [r["filter"]]
                + [
                    _g(r.get(k))
                    for k in (
                        "first_step_diff_rel",
                        "max_est_diff",
                        "max_est_diff_rel",
                        "max_logz_diff",
                        "max_logz_diff_rel",
                    )
                ]
                for r in det
            ],
        )
    out += [
        f"- {r['filter']}: float64 error: {r['error64'] or '-'}; float32 error: {r['error32'] or '-'}"
        for r in rows
        if r["error64"] or r["error32"]
    ]
    return out + [""]


def markdown(info: dict, rows: List[dict]) -> str:
    lines = h.header(
        "## float32 vs float64 accuracy",
        info.get("quick"),
        info,
        f"Verdict: ok = no table metric worse by more than {info['se_k']} SE (or 0.1 %); degraded / "
        "breaks otherwise (see the script's docstring).",
    )
    for table in dict.fromkeys(r["table"] for r in rows):
        lines += table_markdown(table, [r for r in rows if r["table"] == table])
    return "\n".join(lines).rstrip() + "\n"


def run(argv=None) -> dict:
    argv = list(argv or [])
    a = h.options(
        __doc__,
        argv,
        dict(lg_trials=3, acoustic_trials=2, steps_acoustic=4, particles_lg=50, particles_acoustic=100),
        tables=",".join(TABLES),
        filters=None,
        lg_trials=20,
        acoustic_trials=8,
        steps_lg=10,
        steps_acoustic=40,
        lg_d=64,
        particles_lg=200,
        particles_acoustic=500,
        bpf_particles=None,
        edh_particles=None,
        seed=0,
        se_k=2.0,
        memory_gb=4.0,
        threads=1,
        quiet=False,
    )
    with h.session("bench_float32", argv, a.threads, se_k=a.se_k, quick=a.quick) as info:
        rows = [r for table in a.tables.split(",") if table for r in run_table(table, a)]  # lg, acoustic<sigma_w>
    return dict(machine=info, rows=rows, notes=[], markdown=markdown(info, rows), args=vars(a))


if __name__ == "__main__":
    h.main(run, "float32")
