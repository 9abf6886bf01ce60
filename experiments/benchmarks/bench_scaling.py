"""Scaling benchmark: seconds per trial-step against N (``--ns``: particles, acoustic tracking), d
(``--ds``: the sensor network's dimension) and B (``--bs``: trials in one call), tables and
``results_scaling.png``. A point: an untimed 1 x 1 warm-up call, then trials x ``--steps`` timed until
``--time-budget`` seconds are spent (at least once), the best run / (trials x steps); N and d curves
call the filter's preferred chunk of trials within ``--memory-gb``. A point whose time extrapolated from
the smaller ones (linear, or the last log-log slope if steeper, at most 3) exceeds
``--max-point-seconds`` is skipped; one that raises is recorded (after an out-of-memory error the
larger points are skipped). The last row of a table is the log-log slope (the scaling exponent).

    python -m experiments.benchmarks.bench_scaling                      # full (~10-15 min, 2-core CPU)
"""

from __future__ import annotations

import argparse
import contextlib
import math
import time
from pathlib import Path
from typing import Dict, List, Optional

import torch

from torchflow.models import AcousticTracking, SensorNetwork

from . import harness as h

LABELS = {k: h.LABELS[k] for k in ("kf", "ekf", "bpf", "edh", "ledh", "gromov")}
CURVE_FILTERS = {
    "N": ("bpf", "edh", "ledh", "gromov"),
    "d": ("kf", "bpf", "edh", "ledh", "gromov"),
    "B": ("kf", "ekf", "bpf", "edh", "ledh", "gromov"),
}
MAX_REPEATS = 100
#: one colour and marker per filter, the same in every panel
STYLE = {
    "KF": ("tab:blue", "s"),
    "EKF": ("tab:cyan", "D"),
    "BPF": ("tab:orange", "o"),
    "PF-PF(EDH)": ("tab:green", "^"),
    "PF-PF(LEDH)": ("tab:red", "v"),
    "PF-PF(Gromov)": ("tab:purple", "P"),
}


def parse_args(argv=None) -> argparse.Namespace:
    a = h.options(
        __doc__,
        argv,
        dict(ns="100,300,1000", ds="16,36,64", bs="1,4,16", steps=2, trials=1, b_curve_n=100, time_budget=0.1),
        curves="N,d,B",
        ns="100,1000,10000,100000",
        ds="16,36,64,144,256,400",
        bs="1,4,16,64,256",
        filters="kf,ekf,bpf,edh,ledh,gromov",
        steps=3,
        trials=2,
        d_curve_n=200,
        b_curve_n=500,
        b_curve_lg_d=64,
        time_budget=0.5,
        max_point_seconds=60.0,
        memory_gb=4.0,
        dtype="float64",
        device="cpu",
        threads=None,
        seed=0,
        no_plot=False,
        quiet=False,
    )
    a.ns, a.ds, a.bs = (sorted(set(h.ints(getattr(a, k), "--" + k))) for k in ("ns", "ds", "bs"))
    a.curves = h.keys_option(a.curves, CURVE_FILTERS, "--curves")
    a.filters = h.keys_option(a.filters, LABELS)
    a.out = a.out or str(h.results_path("scaling", a.quick))
    return a


def _available_bytes(device: torch.device) -> Optional[int]:
    if device.type == "cuda":
        return torch.cuda.mem_get_info(device)[0]
    with contextlib.suppress(OSError):
        return next(
            (
                int(line.split()[1]) * 1024
                for line in Path("/proc/meminfo").read_text().splitlines()
                if line.startswith("MemAvailable:")
            ),
            None,
        )
    return None


def data_source(args, device, dtype):
    """``get(model, d, trials) -> (model, obs, mean, cov)``; data simulated once per size in float64 on CPU."""
    models, data = {}, {}

    def get(name: str, d: int, trials: int):
        make = (lambda: AcousticTracking()) if name == "acoustic" else (lambda: SensorNetwork(d=d))
        if (name, d) not in models:
            models[name, d] = make().to(device=device, dtype=dtype)
        if trials and ((name, d) not in data or data[name, d][0].shape[0] < trials):
            traj, mean, cov = h.simulate(make(), trials, args.steps, args.seed)
            data[name, d] = tuple(t.to(device=device, dtype=dtype) for t in (traj.observations, mean, cov))
        return (models[name, d],) + tuple(t[:trials] for t in data.get((name, d), ()))

    return get


def _extrapolate(history: List[tuple], x: int) -> Optional[float]:
    """Seconds of one timed run at ``x`` from the ok points ``[(x, run_seconds), ...]`` (see above)."""
    if not history:
        return None
    (x0, t0), (x1, t1) = history[-2:] if len(history) >= 2 else (history[-1], history[-1])
    q = min(3.0, max(1.0, math.log(t1 / t0) / math.log(x1 / x0))) if x1 != x0 and t0 > 0 and t1 > 0 else 1.0
    return t1 * (x / x1) ** q


def curve_points(curve: str, args):
    """``(filter key, model name, x, N, d, trials)`` of one curve, filter-major."""
    for key in (k for k in CURVE_FILTERS[curve] if k in args.filters):
        for x in {"N": args.ns, "d": args.ds, "B": args.bs}[curve]:
            if curve == "N":
                yield key, "acoustic", x, x, 16, args.trials
            elif curve == "d":
                yield key, "lg", x, (None if key == "kf" else args.d_curve_n), x, args.trials
            elif key == "kf":
                yield key, "lg", x, None, args.b_curve_lg_d, x
            else:
                yield key, "acoustic", x, (None if key == "ekf" else args.b_curve_n), 16, x


def run_curve(curve: str, args, data, device, log) -> List[dict]:
    rows: List[dict] = []
    history: Dict[str, List[tuple]] = {}  # filter -> its ok points (x, seconds of one timed run)
    oom: Dict[str, bool] = {}
    budget = int(args.memory_gb * 2**30)
    for key, mname, x, N, d, trials in curve_points(curve, args):
        label = LABELS[key]
        row = {
            "curve": curve,
            "filter": label,
            "model": "acoustic" if mname == "acoustic" else "sensor network",
            "N": N,
            "d": d,
            "B": trials,
            "trials": trials,
            "steps": args.steps,
            "s_per_trial_step": None,
            "status": "ok",
        }
        rows.append(row)
        hist = history.setdefault(key, [])
        try:
            model = data(mname, d, 0)[0]
            filt = h.make_filter(key, model, N)
            per_trial = filt.bytes_per_trial(N)
            fit = max(1, budget // max(per_trial, 1))
            chunk = min(trials, fit) if curve == "B" else min(trials, fit, filt.preferred_chunk_trials(N) or trials)
            row["B"] = chunk  # trials per call
            run_est = _extrapolate(hist, x)
            if run_est is not None:  # the warm-up call filters 1 trial x 1 step
                row["est_point_s"] = run_est * (1 + 1 / (trials * args.steps))
            avail = _available_bytes(device)
            if oom.get(key):
                row["status"] = "skipped: a smaller point of this filter ran out of memory"
            elif run_est is not None and row["est_point_s"] > args.max_point_seconds:
                row["status"] = (
                    f"skipped: estimated {row['est_point_s']:.0f} s > --max-point-seconds {args.max_point_seconds:g}"
                )
            elif avail is not None and per_trial > avail:
                row["status"] = (
                    f"skipped: estimated {per_trial / 2**30:.1f} GB per trial > {avail / 2**30:.1f} GB available"
                )
            if row["status"] != "ok":
                continue
            _, obs, mean, cov = data(mname, d, trials)
            t0 = time.perf_counter()
            g = torch.Generator(device=device).manual_seed(args.seed)  # one generator for every call
            t = h.time_filter(
                filt,
                obs,
                mean,
                cov,
                chunk,
                lambda start, stop: g,
                budget=args.time_budget,
                max_repeats=MAX_REPEATS,
                device=device,
            )
            row["point_s"] = time.perf_counter() - t0
            row["s_per_trial_step"] = t.min / (trials * args.steps)
            row["mean_s_per_trial_step"] = t.mean / (trials * args.steps)
            row["repeats"] = len(t.times)
            hist.append((x, t.min))
            log(
                f"[{curve}] {label:14s} x={x:<7d} {row['s_per_trial_step']:.3g} s/trial-step "
                f"({row['repeats']} run(s), {chunk} trials/call, point {row['point_s']:.1f} s)"
            )
        except Exception as exc:
            row["status"] = f"error: {type(exc).__name__}: {' '.join(str(exc).split())[:200]}"
            oom[key] = (
                oom.get(key)
                or isinstance(exc, MemoryError)
                or "out of memory" in str(exc).lower()
                or type(exc).__name__ == "OutOfMemoryError"
            )
        finally:
            if row["status"] != "ok":
                log(f"[{curve}] {label:14s} x={x:<7d} {row['status']}")
            if device.type == "cuda":
                torch.cuda.empty_cache()
    return rows


_xkey = {"N": "N", "d": "d", "B": "trials"}.get  # the row item a curve's x is


def _column(row: dict, curve: str) -> str:
    return (
        {"KF": "KF (sensor net)", "EKF": "EKF (acoustic)"}.get(row["filter"], row["filter"])
        if curve == "B"
        else row["filter"]
    )


def loglog_slope(points: List[tuple]) -> Optional[float]:
    """Least-squares slope of log(y) on log(x) (None with fewer than two distinct x)."""
    pts = [(math.log(x), math.log(y)) for x, y in points if x > 0 and y and y > 0]
    if len({p[0] for p in pts}) < 2:
        return None
    mx, my = (sum(p[i] for p in pts) / len(pts) for i in (0, 1))
    return sum((p[0] - mx) * (p[1] - my) for p in pts) / sum((p[0] - mx) ** 2 for p in pts)


def points(rows: List[dict], curve: str) -> Dict[str, list]:
    """Column -> its sorted ok points ``(x, s_per_trial_step)`` on ``curve``."""
    cols: Dict[str, list] = {}
    for r in rows:
        if r["curve"] == curve:
            cols.setdefault(_column(r, curve), []).extend(
                [(r[_xkey(curve)], r["s_per_trial_step"])] if r["status"] == "ok" else []
            )
    return {c: sorted(p) for c, p in cols.items()}


def _cell(r: Optional[dict]) -> str:
    if r is None or r["status"] == "ok":
        return "-" if r is None else f"{r['s_per_trial_step']:.3g}"
    est = r.get("est_point_s") if "estimated" in r["status"] and "GB" not in r["status"] else None
    return ("skipped" + (f" (est. {est:.0f} s)" if est else "")) if r["status"].startswith("skipped") else "error"


HEADINGS = {
    "N": "particle count N\n\nAcoustic tracking (d = 16, m = 25), {a.trials} trial(s) x {a.steps} steps per point.",
    "d": "state dimension d\n\nLinear-Gaussian sensor network `SensorNetwork(d=d)` (m = d), particle filters at "
    "N = {a.d_curve_n}, {a.trials} trial(s) x {a.steps} steps per point.",
    "B": "trials per call B\n\nAll B trials in one call, {a.steps} steps. BPF and PF-PFs: acoustic tracking, N = "
    "{a.b_curve_n}. KF (sensor net): the exact Kalman filter on `SensorNetwork(d={a.b_curve_lg_d})`. EKF "
    "(acoustic): the extended Kalman filter stands in as the Gaussian filter on the nonlinear acoustic model, "
    "where the KF does not apply.",
}


def markdown(rows: List[dict], a, info: dict) -> str:
    out = h.header("## Scaling benchmark: seconds per trial-step", False, info, f"{a.dtype}.") + [
        "Each cell is seconds per trial-step = best timed run / (trials x steps), after one untimed "
        "warm-up call (1 trial x 1 step, same N), under `torch.no_grad()`; runs are repeated until "
        f"they add up to {a.time_budget:g} s (at least once). N and d curves: trials split into calls of "
        "the filter's preferred size (local flows ~1e4 particles per call) within "
        f"{a.memory_gb:g} GB. A point is skipped when its time extrapolated from the smaller points "
        f"(linear, or the last log-log slope if steeper) exceeds {a.max_point_seconds:g} s. "
        "The last row of each table is the least-squares log-log slope over the timed points "
        "(the scaling exponent of the time per trial-step).",
        "",
    ]
    for curve in a.curves:
        cr = [r for r in rows if r["curve"] == curve]
        if not cr:
            continue
        xk = _xkey(curve)
        cols = list(dict.fromkeys(_column(r, curve) for r in cr))
        xs = sorted({r[xk] for r in cr})
        cell = {(r[xk], _column(r, curve)): r for r in cr}
        sl = {c: loglog_slope(p) for c, p in points(rows, curve).items()}
        out += ["### Seconds per trial-step vs " + HEADINGS[curve].format(a=a), ""] + h.md_table(
            [curve] + cols,
            [[x] + [_cell(cell.get((x, c))) for c in cols] for x in xs]
            + [["**log-log slope**"] + [f"**{sl[c]:.2f}**" if sl.get(c) is not None else "n/a" for c in cols]],
        )
        notes = [
            f"- {c} at {curve} = {x}: {cell[(x, c)]['status']}"
            for x in xs
            for c in cols
            if (x, c) in cell and cell[(x, c)]["status"] != "ok"
        ]
        out += ([""] + notes if notes else []) + [""]
    return "\n".join(out)


def plot(rows: List[dict], a, path: Path) -> Optional[str]:
    if h.peer("matplotlib") is None:
        print("(matplotlib not installed: no plot)")
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    curves = [c for c in a.curves if any(r["curve"] == c for r in rows)]
    if not curves:
        return None
    fig, axes = plt.subplots(1, len(curves), figsize=(5.2 * len(curves), 4.2), squeeze=False)
    for ax, curve in zip(axes[0], curves):
        for c, pts in points(rows, curve).items():
            if pts:
                sl = loglog_slope(pts)
                color, marker = STYLE.get(c.split(" ")[0], (None, "o"))
                ax.plot(
                    *zip(*pts),
                    marker=marker,
                    linestyle="-",
                    color=color,
                    label=c + (f" (slope {sl:.2f})" if sl is not None else ""),
                )
        ax.set(xscale="log", yscale="log", xlabel=HEADINGS[curve].partition("\n")[0], ylabel="seconds per trial-step")
        xs = sorted({r[_xkey(curve)] for r in rows if r["curve"] == curve})
        ax.set_xticks(xs)
        ax.set_xticklabels(
            [
                f"{x:g}" if x < 1e4 else f"1e{round(math.log10(x))}" if math.log10(x).is_integer() else f"{x:.0e}"
                for x in xs
            ]
        )
        ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
        ax.set_title(
            {
                "N": "acoustic tracking",
                "d": f"sensor network, N = {a.d_curve_n}",
                "B": f"acoustic N = {a.b_curve_n} / sensor net d = {a.b_curve_lg_d}",
            }[curve],
            fontsize=10,
        )
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(
        f"torchflow scaling ({a.device}, {a.dtype}, {a.threads or torch.get_num_threads()} threads)", fontsize=11
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return str(path)


def run(argv=None) -> dict:
    """``{"machine", "rows", "markdown", "plot", "args"}``; draws the PNG unless ``--no-plot``."""
    a = parse_args(argv)
    device = torch.device(a.device)
    log = (lambda s: None) if a.quiet else (lambda s: print(s, flush=True))
    with h.session("bench_scaling", argv, a.threads, device) as info:
        data = data_source(a, device, getattr(torch, a.dtype))
        t0 = time.perf_counter()
        rows = [r for curve in a.curves for r in run_curve(curve, a, data, device, log)]
        info["total_s"] = round(time.perf_counter() - t0, 1)
    md = markdown(rows, a, info)
    png = None if a.no_plot else plot(rows, a, Path(a.out).with_suffix(".png"))
    return {"machine": info, "rows": rows, "markdown": md, "plot": png, "args": vars(a)}


if __name__ == "__main__":
    h.main(run, "scaling")
