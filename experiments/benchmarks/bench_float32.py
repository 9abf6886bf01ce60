"""float32 vs float64: accuracy and speed of torchflow's filters in single precision on the
linear-Gaussian (Table I) and acoustic tracking (Table II, sigma_w = 0.1 and the stiff 0.001) tables.

    python -m experiments.benchmarks.bench_float32                 # LG 20 trials, acoustic 8 x 40
    python -m experiments.benchmarks.bench_float32 --tables lg --out /tmp/lg.md
    python -m experiments.benchmarks.bench_float32 --tables acoustic0.001 --filters ledh,gromov
    python -m experiments.benchmarks.bench_float32 --merge /tmp/lg.json /tmp/a1.json   # one report
    python -m experiments.benchmarks.bench_float32 --quick                 # smoke test (seconds)

How a table is run: the trajectories, observations and priors are simulated ONCE in float64 with
``torchflow.experiment``'s own simulator and seed; ``run_experiment`` is then called twice on that
same data, with ``dtype="float64"`` and ``dtype="float32"`` (the observations and priors are cast;
the true states stay float64 for scoring, and every metric is computed in float64). The runner's
simulator is swapped for the shared data during the call (``run_experiment`` itself simulates in
the run's dtype, and torch draws a different random stream per dtype, so two plain calls would score
the precisions on different trajectories). Everything else is the runner's: chunking, per-filter
seeds, the ``nonfinite`` repair counts and the timing. Each filter gets an untimed 2 trials x 1 step
warm-up in its dtype first. The filters' own random draws differ between the precisions (float64
CPU draws come from numpy's ziggurat, float32 ones from ``torch.randn``), so for the particle
filters float32 vs float64 is two independent Monte Carlo runs on the same data.

Metrics, as in the seed tables: LG: MSE of the estimates and the relative MSE of the log-evidence
``((log Z - log Z_KF) / log Z_KF)^2``, both precisions scored against the float64 Kalman filter's
exact log Z; acoustic: OMAT and OSPA (c = 40, p = 1) in metres and lost tracks (mean OMAT > 2 m);
ESS before resampling. ``SE`` is the Monte Carlo standard error across trials of the float64
metric (sd over trials / sqrt(trials)); ``z = (float32 - float64) / SE``, signed so that positive
is worse.

Verdict: ``ok`` when no table metric of float32 is worse than float64's by more than
``--se-k`` (2) SE, nor by more than 0.1 % of float64's value (1e-8 for the relative MSE of log Z):
the floors cover the deterministic filters, whose SE is zero. A band of 1 SE would flag about a
third of float64 re-runs with another seed, since the two precisions' Monte Carlo errors are
independent (and with few trials and heavy-tailed per-trial errors even 2 SE is optimistic: see
``--control``). Otherwise ``degraded`` (with the
metrics that moved), or ``breaks`` when float32 raised, went non-finite, needed non-finite
repairs float64 did not, reported an ESS outside [1, N] (log-weights it could not normalise), or a
table metric got 10x worse. Lost tracks are judged on counts: more than ``k sqrt(max(lost64, 1))``
extra lost tracks is ``degraded``, at least max(3, trials / 2) extra is ``breaks``.

For the Kalman-type filters (KF, EKF, UKF), which draw no random numbers, float32 is also compared
point by point with float64 on the same data: ``max|dx|/scale`` is the largest float32 - float64
difference of the estimates over the largest |true state| (a diverged filter's estimates are no
scale), ``max|d log Z|`` that of the log-evidence (and relative to |log Z|); when the estimates after the FIRST update already differ
by more than 1e-3 of the scale the filter is ``degraded`` even where its table metrics are not
(later steps are not judged: a filter that has lost the targets amplifies any perturbation).

``--control`` also re-runs the random filters in float64 with other filter seeds (same data) and
gives the verdict that float64 re-run would get against float64: the false-alarm check of the
verdict band.

Times are seconds per trial-step of the runner's timed filter calls (single-threaded if run with
``--threads 1``, the default here), after the warm-up; the machine's load is printed with them.
Particle counts default to the seed tables' N for the flow filters (LG 200, acoustic 500) and, for
a modest run, the same N for the bootstrap PF and PF-PF(EDH) (the paper uses 1e5 - 1e6 for those on
acoustic tracking): set ``--bpf-particles`` / ``--edh-particles``.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import time
from pathlib import Path
from typing import Dict, List, Optional

import torch

import torchflow.experiment as tfx
from torchflow.filters import KalmanFilter
from torchflow.models import AcousticTracking, SensorNetwork
from torchflow.models.base import Trajectory

from . import harness as h

NAMES = {"kf": "KF", "ekf": "EKF", "ukf": "UKF", "bpf": "BPF", "ledh": "PF-PF(LEDH)", "edh": "PF-PF(EDH)",
         "gromov": "PF-PF(Gromov)", "geodesic": "PF-PF(Geodesic)"}
DETERMINISTIC = ("kf", "ekf", "ukf")
TABLES = ("lg", "acoustic0.1", "acoustic0.001")
DEFAULT_FILTERS = {"lg": "kf,ukf,bpf,ledh,edh,gromov", "acoustic": "ekf,bpf,ledh,gromov,edh"}
#: per table: the metrics the verdict reads, with +1 where larger is worse and -1 where smaller is
METRICS = {
    "lg": {"mse": 1, "log_evidence_relmse": 1, "ess": -1},
    "acoustic": {"omat": 1, "ospa": 1, "lost_rate": 1, "ess": -1},
}
REL_FLOOR = 1e-3  # a float32 metric within 0.1 % of float64's is ok whatever the SE
#: absolute tolerances where float64's value may be exactly 0 (the KF's own relMSE of log Z)
ABS_FLOOR = {"log_evidence_relmse": 1e-8}
BREAK_RATIO = 10.0
#: a Kalman-type filter whose float32 estimates after the first update differ from float64's by more
#: than this fraction of their scale is degraded even when its table metrics are not (well-conditioned:
#: ~1e-6). Later steps are reported but not judged: a filter that has lost the targets is chaotic, so
#: any perturbation, round-off included, grows there.
POINTWISE_TOL = 1e-3


def _kind(table: str) -> str:
    return "lg" if table.partition(" [")[0] == "lg" else "acoustic"


def make_model(table: str, lg_d: int = 64):
    if table == "lg":
        return SensorNetwork(d=lg_d)
    if table.startswith("acoustic"):
        return AcousticTracking(sigma_w=float(table[len("acoustic"):]))
    raise ValueError(f"table: expected one of {TABLES}, got {table!r}")


def make_filter(key: str, model, n: int):
    # the BPF counts its repairs (as the PF-PFs do) instead of raising on the first -inf weight
    extra = dict(nonfinite="recover") if key == "bpf" else {}
    return h.make_filter(key, model, None if key in DETERMINISTIC else n, name=NAMES[key], **extra)


@contextlib.contextmanager
def given_data(traj: Trajectory, mean: torch.Tensor, cov: torch.Tensor):
    """Make ``run_experiment`` filter this float64 data (cast to the run's dtype) instead of
    simulating its own; the true states stay float64 (they are only used for scoring)."""
    orig = tfx._simulate

    def simulate(model, trials, steps, inits_per_track, generator):
        if traj.observations.shape[:2] != (trials, steps):
            raise ValueError("given_data: trials/steps differ from the shared data")
        dt, dev = model.dtype, model.device
        return (Trajectory(traj.states.to(dev), traj.observations.to(device=dev, dtype=dt)),
                mean.to(device=dev, dtype=dt), cov.to(device=dev, dtype=dt))

    tfx._simulate = simulate
    try:
        yield
    finally:
        tfx._simulate = orig


def _se(values: List[float]) -> Optional[float]:
    t = torch.tensor(values, dtype=torch.float64)
    t = t[torch.isfinite(t)]
    if t.numel() < 2:
        return None
    return float(t.std() / math.sqrt(t.numel()))


def run_precision(table, keys, dtype, traj, mean, cov, a, ref_logz) -> Dict[str, dict]:
    """One ``run_experiment`` call in ``dtype`` on the shared data; per filter: the summary row,
    per-trial metric lists and (Kalman-type filters) the estimates and log Z of a direct call."""
    model = make_model(table, a.lg_d)
    n = a.particles_lg if table == "lg" else a.particles_acoustic
    counts = {"bpf": a.bpf_particles or n, "edh": a.edh_particles or n}
    filters = {NAMES[k]: make_filter(k, model, counts.get(k, n)) for k in keys}
    dt = tfx.resolve_dtype(dtype)
    model.to(dtype=dt)
    for name, f in filters.items():  # untimed warm-up: 2 trials x 1 step in this dtype
        f.to(dtype=dt)
        try:
            with torch.no_grad():
                f(traj.observations[:2, :1].to(dt), mean[:2].to(dt), cov[:2].to(dt), torch.Generator().manual_seed(0))
        except Exception:  # noqa: BLE001  (the timed run reports it)
            pass
    with given_data(traj, mean, cov):
        res = tfx.run_experiment(model, filters, trials=a.trials, steps=a.steps, seed=a.seed,
                                 inits_per_track=1, chunk_size=None, memory_budget_gb=a.memory_gb,
                                 dtype=dtype, progress=False)
    out = {}
    for key, (name, f) in zip(keys, filters.items()):
        row = next(r for r in res.summary if r["filter"] == name)
        trials = [r for r in res.per_trial if r["filter"] == name]
        per = {}
        for col in ("mse", "omat", "ospa", "ess"):
            if trials and col in trials[0]:
                per[col] = [r[col] for r in trials]
        if trials and "lost" in trials[0]:
            per["lost_rate"] = [float(r["lost"]) for r in trials]
        if ref_logz is not None and f.estimates_evidence and trials:
            lz = torch.tensor([r["log_evidence"] for r in trials], dtype=torch.float64)
            per["log_evidence_relmse"] = (((lz - ref_logz) / ref_logz) ** 2).tolist()
        summ = {k: (sum(v) / len(v) if v else None) for k, v in per.items()}
        info = dict(summary=row, per_trial=per, metrics=summ, n_particles=getattr(f, "n_particles", None),
                    state_scale=float(traj.states[:, 1:].abs().max()),
                    ess_range=None)
        ess_vals = per.get("ess", []) + [r["ess"] for r in res.per_step if r["filter"] == name and "ess" in r]
        if ess_vals:  # means over steps / trials: outside [1, N] only if some step's ESS is
            info["ess_range"] = (min(ess_vals), max(ess_vals))
        if key in DETERMINISTIC and not row.get("error"):
            with torch.no_grad():
                r = f(traj.observations.to(dt), mean.to(dt), cov.to(dt))
            info["estimates"], info["log_evidence"] = r.estimates.double(), r.log_evidence.double()
        out[key] = info
    return out


def compare(table, key, r64, r32, k_se) -> dict:
    """One result row: both precisions' metrics, SE, z, times, repairs and the verdict."""
    s64, s32 = r64["summary"], r32["summary"]
    row = dict(table=table, key=key, filter=NAMES[key], n_particles=r64["n_particles"],
               trials=s64["trials"], steps=s64["steps"], error64=s64.get("error"), error32=s32.get("error"),
               sec_per_step64=s64.get("sec_per_step"), sec_per_step32=s32.get("sec_per_step"),
               repaired64=s64.get("repaired"), repaired32=s32.get("repaired"),
               lost64=s64.get("lost_tracks"), lost32=s32.get("lost_tracks"), metrics={})
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
        worse = sign * d
        tol = max(k_se * (se or 0.0), REL_FLOOR * abs(v64), ABS_FLOOR.get(m, 0.0))
        if worse > tol:
            zs = f", z = {_z(z)}" if z is not None else ""
            msg = f"{m} {_g(v64)} -> {_g(v32)}{zs}"
            if m == "lost_rate":
                continue  # judged on the counts below
            elif (sign > 0 and v64 > 0 and v32 > BREAK_RATIO * v64) or (sign < 0 and v32 * BREAK_RATIO < v64):
                breaks.append(msg)
            else:
                reasons.append(msg)
    l64, l32 = row["lost64"] or 0, row["lost32"] or 0
    if l32 - l64 > k_se * math.sqrt(max(l64, 1)):  # more lost tracks than Monte Carlo noise explains
        (breaks if l32 - l64 >= max(3, row["trials"] / 2) else reasons).append(f"lost tracks {l64} -> {l32}")
    n = r32["n_particles"]
    if r32.get("ess_range") and n and not (1 - 1e-3 <= r32["ess_range"][0] and r32["ess_range"][1] <= n * (1 + 1e-3)):
        breaks.append(f"ESS outside [1, N] ({r32['ess_range'][0]:.3g} .. {r32['ess_range'][1]:.4g}): "
                      "log-weights too large to normalise in float32")
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
            reasons.append(f"first-step estimates differ from float64's by {row['first_step_diff_rel']:.2g} x the "
                           f"true-state scale (all steps: {row['max_est_diff_rel']:.2g}; log Z by "
                           f"{row['max_logz_diff_rel']:.2g} relative)")
    if row["error64"]:
        row["verdict"], row["reason"] = "n/a", f"float64 raised: {row['error64'][:160]}"
    elif breaks:
        row["verdict"], row["reason"] = "breaks", "; ".join(breaks + reasons)
    elif reasons:
        row["verdict"], row["reason"] = "degraded", "; ".join(reasons)
    else:
        row["verdict"], row["reason"] = "ok", ""
    return row


def run_table(table: str, a) -> List[dict]:
    keys = h.keys_option(a.filters or DEFAULT_FILTERS[_kind(table)], NAMES)
    if table != "lg":
        keys = [k for k in keys if k != "kf"]  # the KF needs a linear-Gaussian model
    ta = argparse.Namespace(**vars(a))
    ta.trials = a.lg_trials if table == "lg" else a.acoustic_trials
    ta.steps = a.steps_lg if table == "lg" else a.steps_acoustic
    model64 = make_model(table, a.lg_d)
    gen = torch.Generator().manual_seed(int(a.seed))
    traj, mean, cov = tfx._simulate(model64, ta.trials, ta.steps, a.inits_per_track, gen)
    ref_logz = None
    if table == "lg":  # exact log Z: the float64 Kalman filter on the shared data
        with torch.no_grad():
            ref_logz = KalmanFilter(model64, validate=False)(traj.observations, mean, cov).log_evidence.double()
    res = {}
    for dtype in ("float64", "float32"):
        t0 = time.perf_counter()
        res[dtype] = run_precision(table, keys, dtype, traj, mean, cov, ta, ref_logz)
        if not a.quiet:
            print(f"[{table}] {dtype}: {time.perf_counter() - t0:.1f} s", flush=True)
    rows = [compare(table, k, res["float64"][k], res["float32"][k], a.se_k) for k in keys]
    if a.control:  # float64 again with other filter seeds: how often the verdict flags pure Monte Carlo noise
        random_keys = [k for k in keys if k not in DETERMINISTIC]
        ca = argparse.Namespace(**vars(ta))
        ca.seed = ta.seed + 1000
        t0 = time.perf_counter()
        ctrl = run_precision(table, random_keys, "float64", traj, mean, cov, ca, ref_logz) if random_keys else {}
        if not a.quiet:
            print(f"[{table}] float64 control: {time.perf_counter() - t0:.1f} s", flush=True)
        for r in rows:
            if r["key"] in ctrl:
                c = compare(table, r["key"], res["float64"][r["key"]], ctrl[r["key"]], a.se_k)
                r["control"] = dict(verdict=c["verdict"], reason=c["reason"],
                                    z={m: v["z"] for m, v in c["metrics"].items()},
                                    f64b={m: v["f32"] for m, v in c["metrics"].items()})
    for r in rows:
        r["inits_per_track"] = a.inits_per_track
        if not a.quiet:
            print(f"[{table}] {r['filter']}: {r['verdict']} {r['reason']}", flush=True)
    return rows


def _g(x, fmt="{:.3g}"):
    if x is None:
        return "-"
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    return fmt.format(x)


def _pct(x):
    if x is None:
        return "-"
    return f"{100 * x:+.1f}%" if abs(x) < 10 else f"{x:+.2g}x"


def _z(z):
    return f"{z:+.1f}" if abs(z) < 1e3 else f"{z:+.1e}"


_TITLES = {"lg": "Linear-Gaussian sensor network (Table I setting: d = 64, T = {steps})",
           "acoustic0.1": "Acoustic tracking, sigma_w = 0.1 (Table II setting, T = {steps})",
           "acoustic0.001": "Acoustic tracking, stiff sigma_w = 0.001 (T = {steps})"}
_LABEL = {"mse": "MSE", "log_evidence_relmse": "relMSE log Z", "omat": "OMAT (m)", "ospa": "OSPA (m)",
          "ess": "ESS", "lost_rate": "lost"}


def table_markdown(table: str, rows: List[dict]) -> List[str]:
    kind = _kind(table)
    r0 = rows[0]
    base, _, tag = table.partition(" [")  # a tagged variant of a table (e.g. a patched library)
    title = _TITLES.get(base, base).format(steps=r0["steps"]) + (f" [{tag}" if tag else "")
    out = [f"### {title}", "",
           f"{r0['trials']} trials (inits per track {r0.get('inits_per_track', 1)}), float64 and float32 on the "
           "same observations. Cells: float64 ± SE / float32 (relative change, z = change / SE, positive = "
           "worse).", ""]
    mets = [m for m in METRICS[kind] if m != "lost_rate"]
    head = ["filter", "N"] + [_LABEL[m] for m in mets]
    if kind == "acoustic":
        head.append("lost tracks f64 / f32")
    head += ["repairs f64 / f32", "s / trial-step f64", "f32", "f32 speed-up", "verdict"]
    ctrl = any(r.get("control") for r in rows)
    if ctrl:
        head.append("control: float64 re-run's verdict")
    def cell(v):
        if not v:
            return "-"
        se = f" ± {_g(v['se'], '{:.2g}')}" if v["se"] is not None else ""
        z = f", z {_z(v['z'])}" if v["z"] is not None else ""
        return f"{_g(v['f64'], '{:.4g}')}{se} / {_g(v['f32'], '{:.4g}')} ({_pct(v['rel'])}{z})"

    def verdict(r, bold=True):
        return (f"**{r['verdict']}**" if bold else r["verdict"]) + (f": {r['reason']}" if r["reason"] else "")

    out += h.md_table(head, [
        [r["filter"], _g(r["n_particles"], "{}")] + [cell(r["metrics"].get(m)) for m in mets]
        + ([f"{_g(r['lost64'], '{}')} / {_g(r['lost32'], '{}')}"] if kind == "acoustic" else [])
        + [f"{_g(r['repaired64'], '{}')} / {_g(r['repaired32'], '{}')}", _g(r["sec_per_step64"], "{:.3g}"),
           _g(r["sec_per_step32"], "{:.3g}"), _g(r["speedup"], "{:.2f}x"), verdict(r)]
        + ([verdict(r["control"], bold=False) if r.get("control") else "-"] if ctrl else []) for r in rows])
    det = [r for r in rows if r.get("max_est_diff_rel") is not None]
    if det:
        out += ["", "Kalman-type filters point by point (no random numbers; float32 - float64 on the same data):", ""]
        out += h.md_table(["filter", "first step: max abs(dx) / max abs(x_true)", "all steps: max abs(dx)",
                           "max abs(dx) / max abs(x_true)", "max abs(d log Z)", "max abs(d log Z) / abs(log Z)"],
                          [[r["filter"]] + [_g(r.get(k)) for k in ("first_step_diff_rel", "max_est_diff",
                                                                    "max_est_diff_rel", "max_logz_diff",
                                                                    "max_logz_diff_rel")] for r in det])
    out += [f"- {r['filter']}: float64 error: {r['error64'] or '-'}; float32 error: {r['error32'] or '-'}"
            for r in rows if r["error64"] or r["error32"]]
    return out + [""]


def markdown(info: dict, rows: List[dict], notes: Optional[List[str]] = None) -> str:
    lines = h.header("## float32 vs float64 accuracy", info.get("quick"), info,
                     f"Verdict: ok = no table metric worse by more than {info['se_k']} SE (or 0.1 %); degraded / "
                     "breaks otherwise (see the script's docstring).")
    for table in dict.fromkeys(r["table"] for r in rows):
        lines += table_markdown(table, [r for r in rows if r["table"] == table])
    for n in notes or []:
        lines.append(f"- {n}")
    return "\n".join(lines).rstrip() + "\n"


def build_parser():
    ap = h.parser(__doc__, "LG 3 trials, N 50; acoustic 2 trials x 4 steps, N 100")
    ap.add_argument("--tables", default=",".join(TABLES), help=f"comma-separated subset of {','.join(TABLES)}")
    ap.add_argument("--filters", default=None,
                    help=f"comma-separated subset of {','.join(NAMES)} for every table (default LG "
                         f"{DEFAULT_FILTERS['lg']}; acoustic {DEFAULT_FILTERS['acoustic']}); kf is skipped on acoustic")
    ap.add_argument("--lg-trials", type=int, default=20)
    ap.add_argument("--acoustic-trials", type=int, default=8)
    ap.add_argument("--steps-lg", type=int, default=10)
    ap.add_argument("--steps-acoustic", type=int, default=40)
    ap.add_argument("--lg-d", type=int, default=64)
    ap.add_argument("--particles-lg", type=int, default=200)
    ap.add_argument("--particles-acoustic", type=int, default=500)
    ap.add_argument("--bpf-particles", type=int, default=None, help="BPF N (default: the table's N)")
    ap.add_argument("--edh-particles", type=int, default=None, help="PF-PF(EDH) N (default: the table's N)")
    ap.add_argument("--inits-per-track", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--se-k", type=float, default=2.0, help="verdict band in standard errors (2)")
    ap.add_argument("--memory-gb", type=float, default=4.0)
    ap.add_argument("--threads", type=int, default=1, help="torch threads (default 1: single-thread numbers)")
    ap.add_argument("--control", action="store_true",
                    help="also re-run the random filters in float64 with other seeds (verdict false-alarm check)")
    ap.add_argument("--quiet", action="store_true")
    ap.add_argument("--merge", nargs="+", default=None, metavar="JSON",
                    help="combine the .json results of earlier runs into one report (runs nothing)")
    ap.add_argument("--note", action="append", default=[], help="a line added under the tables (repeatable)")
    return ap


def run(argv=None) -> dict:
    argv = list(argv or [])
    a = build_parser().parse_args(argv)
    if a.merge:
        parts = [json.loads(Path(p).read_text()) for p in a.merge]
        rows = [r for p in parts for r in p["rows"]]
        info = dict(parts[0]["machine"])
        info["command"] = "; ".join(p["machine"]["command"] for p in parts)
        info["load_start"] = [p["machine"]["load_start"] for p in parts]
        info["load_end"] = [p["machine"]["load_end"] for p in parts]
        notes = [n for p in parts for n in p.get("notes", [])] + list(a.note)
        return dict(machine=info, rows=rows, notes=notes, markdown=markdown(info, rows, notes), args=vars(a))
    if a.quick:
        a.lg_trials, a.acoustic_trials, a.steps_acoustic, a.particles_lg, a.particles_acoustic = 3, 2, 4, 50, 100
    tables = [t for t in a.tables.split(",") if t]
    for table in tables:
        if table not in TABLES and not table.startswith("acoustic"):
            raise SystemExit(f"--tables: unknown {table!r}; expected a subset of {','.join(TABLES)}")
    rows = []
    with h.torch_threads(a.threads):  # a suite runner's later sections keep their own thread count
        info = h.machine(se_k=a.se_k, quick=a.quick, command=h.command("bench_float32", argv))
        for table in tables:
            rows += run_table(table, a)
        info["load_end"] = h.loadavg()
    notes = list(a.note)
    return dict(machine=info, rows=rows, notes=notes, markdown=markdown(info, rows, notes), args=vars(a))


if __name__ == "__main__":
    h.main(run, "float32")
