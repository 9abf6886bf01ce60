"""The one harness of the benchmarks: options, the timing loop, filters by name, the machine, peer
libraries and the results files. A benchmark module's ``run(argv)`` returns ``{"machine", "rows",
"markdown", "args", ...}``; ``python -m experiments.benchmarks.<module>`` also writes ``results_<name>.md``
and ``.json`` in ``results/`` (``--quick``: ``results_<name>_quick.*``; ``--out``: elsewhere).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import math
import os
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, List, Optional, Sequence

import torch

from torchflow.core.random import TrialStreams
from torchflow.filters import (
    GPFIS,
    BootstrapParticleFilter,
    ExtendedKalmanFilter,
    GaussianSumParticleFilter,
    KalmanFilter,
    ParticleFlowFilter,
    ParticleFlowGaussianSumParticleFilter,
    ParticleFlowParticleFilter,
    UnscentedKalmanFilter,
)

HERE = Path(__file__).resolve().parent
#: where the benchmarks' result files live, apart from the scripts
RESULTS = HERE / "results"


class CheckFailed(RuntimeError):
    """Ours and a peer disagree: the timing would not compare equal work (``main`` exits with it)."""


@dataclass
class Timing:
    """Seconds of each timed call (``min``, ``mean`` of them) and the last call's result."""

    times: List[float]
    result: Any = None

    min = property(lambda self: min(self.times))
    mean = property(lambda self: sum(self.times) / len(self.times))


def time_calls(
    fn: Callable[[], Any],
    repeats: int = 1,
    warmup: int = 0,
    budget: Optional[float] = None,
    max_repeats: int = 100,
    device=None,
) -> Timing:
    """Call ``fn()`` ``warmup`` times, then time it ``repeats`` times or, with ``budget``, until the timed
    calls add up to ``budget`` seconds (at least once, at most ``max_repeats`` times); the CUDA queue
    of ``device`` is synchronised before each clock read."""
    if int(repeats) < 1 or int(warmup) < 0 or int(max_repeats) < 1:
        raise ValueError(
            f"time_calls: expected repeats >= 1, warmup >= 0, max_repeats >= 1, got {repeats}, {warmup}, {max_repeats}"
        )
    if budget is not None and not budget >= 0:
        raise ValueError(f"time_calls: budget: expected seconds >= 0, got {budget}")
    cuda = device is not None and torch.device(device).type == "cuda"
    synchronize = (lambda: torch.cuda.synchronize(device)) if cuda else (lambda: None)
    for _ in range(int(warmup)):
        fn()
    synchronize()
    times: List[float] = []
    while True:
        t0 = time.perf_counter()
        out = fn()
        synchronize()
        times.append(time.perf_counter() - t0)
        if (len(times) >= repeats if budget is None else sum(times) >= budget) or len(times) >= max_repeats:
            return Timing(times, out)


def streams(seed: int, key) -> Callable[[int, int], TrialStreams]:
    """``(start, stop) -> TrialStreams(seed, range(start, stop), key)``: the runner's per-trial streams."""
    return lambda start, stop: TrialStreams(seed, range(start, stop), key=key)


def filter_chunks(f, obs, mean, cov, chunk: Optional[int], randomness: Callable[[int, int], Any]) -> list:
    """The results of ``f`` over all trials in calls of ``chunk`` trials (``None``: one call), under
    ``torch.no_grad()``; ``randomness(start, stop)`` gives each call its generator or streams."""
    B = obs.shape[0]
    chunk = chunk or B
    with torch.no_grad():
        return [
            f(obs[s : s + chunk], mean[s : s + chunk], cov[s : s + chunk], randomness(s, min(s + chunk, B)))
            for s in range(0, B, chunk)
        ]


def time_filter(
    f, obs, mean, cov, chunk: Optional[int], randomness, warm=(1, 1), warm_randomness=None, **timing
) -> Timing:
    """An untimed call on the first ``warm = (trials, steps)``, then :func:`time_calls` (``timing``) of
    :func:`filter_chunks` (``warm_randomness``: the warm-up's randomness)."""
    b, k = warm
    filter_chunks(f, obs[:b, :k], mean[:b], cov[:b], None, warm_randomness or randomness)
    return time_calls(lambda: filter_chunks(f, obs, mean, cov, chunk, randomness), **timing)


def simulate(model, trials: int, steps: int, seed: int):
    """``(trajectory, prior mean, prior covariance)`` drawn with one generator seeded ``seed``."""
    g = torch.Generator().manual_seed(int(seed))
    traj = model.simulate(trials, steps, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    return traj, mean, cov


@contextlib.contextmanager
def torch_threads(n: Optional[int]):
    """Run with ``n`` torch threads (``None`` / 0: unchanged), then restore the previous count."""
    before = torch.get_num_threads()
    if n:
        torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(before)


def blas_limit(n_threads: int):
    """Context manager limiting numpy/scipy BLAS threads (not torch's) to ``n_threads`` (0: default)."""
    tpc = peer("threadpoolctl") if n_threads > 0 else None
    if tpc is None and n_threads > 0:
        print("  (threadpoolctl not installed: peer BLAS threads left at their default)")
    return contextlib.nullcontext() if tpc is None else tpc.threadpool_limits(limits=n_threads, user_api="blas")


def blas_threads() -> str:
    """``"openblas:1,..."``: numpy/scipy's BLAS libraries and their thread counts now."""
    tpc = peer("threadpoolctl")
    infos = (
        []
        if tpc is None
        else [f"{i['internal_api']}:{i['num_threads']}" for i in tpc.threadpool_info() if i["user_api"] == "blas"]
    )
    return ",".join(infos) or "?"


def loadavg() -> Optional[list]:
    """1/5/15-minute load average (rounded), or None where the OS has none."""
    with contextlib.suppress(OSError, AttributeError):
        return [round(x, 2) for x in os.getloadavg()]
    return None


def _cpu_name() -> str:
    with contextlib.suppress(OSError, StopIteration):
        return next(
            line.split(":", 1)[1].strip()
            for line in Path("/proc/cpuinfo").read_text().splitlines()
            if line.startswith("model name")
        )
    return platform.processor() or platform.machine() or "unknown CPU"


def machine(device=None, **extra) -> dict:
    """The machine a benchmark runs on, the load average now (``load_start``) and the ``extra`` items."""
    import numpy as np

    device = torch.device(device or "cpu")
    info = dict(
        platform=platform.platform(),
        processor=_cpu_name(),
        cpus=os.cpu_count(),
        python=platform.python_version(),
        torch=torch.__version__,
        numpy=np.__version__,
        torch_threads=torch.get_num_threads(),
        device=str(device),
        load_start=loadavg(),
    )
    with contextlib.suppress(ValueError, OSError, AttributeError):
        info["mem_total_gb"] = round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)
    if device.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(device)
    info.update(extra)
    return info


def machine_line(info: dict) -> str:
    """``Machine: ...`` line of a report, with the load at start and end (items missing: ``?``)."""
    get = lambda k: info.get(k, "?")
    gpu = f", GPU {info['gpu']}" if info.get("gpu") else ""
    mem = f", {info['mem_total_gb']} GiB RAM" if info.get("mem_total_gb") else ""
    threads = info.get("torch_threads", info.get("threads", "?"))
    return (
        f"Machine: {get('platform')}, {get('processor')}, {get('cpus')} CPUs{mem}; python {get('python')}, "
        f"torch {get('torch')} ({threads} threads), numpy {get('numpy')}; device {get('device')}{gpu}. "
        f"Load average (1/5/15 min) at start {info.get('load_start')}, at end {info.get('load_end')}."
    )


def header(title: str, quick: bool, info: dict, *lines: str) -> List[str]:
    """Opening lines of a report: the title, the machine, ``lines`` and the command."""
    return [
        title + (" (--quick)" if quick else ""),
        "",
        machine_line(info),
        *lines,
        f"Command: `{info['command']}`",
        "",
    ]


command = lambda name, argv: " ".join(["python -m experiments.benchmarks." + name, *map(str, argv or [])])


def peer(name: str, *submodules: str):
    """The peer library ``name`` (``submodules`` imported too), ``None`` when it is not installed."""
    try:
        mod = importlib.import_module(name)
        for sub in submodules:
            importlib.import_module(f"{name}.{sub}")
    except ModuleNotFoundError as exc:
        if exc.name is None or exc.name.split(".")[0] != name:
            raise  # the peer is there but one of its own dependencies is missing: say so
        return None
    return mod


def skipped(name: str) -> str:
    """Status of a row whose peer library is not installed."""
    return f"skipped: {name} not installed (pip install -e '.[bench]')"


FLOWS = {"ledh": "LEDH", "edh": "EDH", "gromov": "Gromov", "geodesic": "Geodesic", "osd": "OSD"}
LABELS = {
    "kf": "KF",
    "ekf": "EKF",
    "ukf": "UKF",
    "bpf": "BPF",
    "pfgspf": "PFGSPF",
    "gspf": "GSPF",
    "gpfis": "GPFIS",
    **{f: f"PF-PF({n})" for f, n in FLOWS.items()},
    **{f"flow_{f}": f"{n} flow" for f, n in FLOWS.items()},
}
#: key -> (class, constructor settings, whether it takes ``n_particles``)
FILTERS = {
    "kf": (KalmanFilter, {}, False),
    "ekf": (ExtendedKalmanFilter, {}, False),
    "ukf": (UnscentedKalmanFilter, {}, False),
    "bpf": (BootstrapParticleFilter, {}, True),
    "gpfis": (GPFIS, {}, True),
    "gspf": (GaussianSumParticleFilter, {}, False),
    "pfgspf": (ParticleFlowGaussianSumParticleFilter, {}, False),
    **{f: (ParticleFlowParticleFilter, dict(flow=f), True) for f in FLOWS},
    **{f"flow_{f}": (ParticleFlowFilter, dict(flow=f), True) for f in FLOWS},
}


def make_filter(key: str, model, n_particles: Optional[int] = None, **kw):
    """The filter :data:`FILTERS` calls ``key`` (``pfpf_<flow>``: ``<flow>``); ``kw`` go to its constructor."""
    if str(key).removeprefix("pfpf_") not in FILTERS:
        raise ValueError(f"make_filter: unknown filter {key!r}; expected one of {', '.join(LABELS)}")
    cls, settings, particles = FILTERS[str(key).removeprefix("pfpf_")]
    n = dict(n_particles=int(n_particles)) if particles and n_particles is not None else {}
    return cls(model, **settings, **n, **kw)


def keys_option(text: str, allowed: Iterable[str], option: str = "--filters") -> List[str]:
    """Comma list of names, each one of ``allowed`` (else ``SystemExit`` naming the option)."""
    allowed, keys = list(allowed), [k.strip() for k in str(text).split(",") if k.strip()]
    bad = [k for k in keys if k not in allowed]
    if bad or not keys:
        raise SystemExit(f"{option}: unknown {bad or keys!r}; expected a subset of {','.join(allowed)}")
    return keys


def _value(text: str):
    """An option's value: an int, else a float, else the text."""
    for cast in (int, float):
        with contextlib.suppress(ValueError):
            return cast(text)
    return text


def options(doc: str, argv: Optional[Sequence[str]], quick: Optional[dict] = None, **defaults) -> argparse.Namespace:
    """A benchmark's options from ``argv``: ``--quick``, ``--out`` and ``--<name>`` per item of
    ``defaults`` (``False``: a flag; else an int, float or text); with ``--quick``, ``quick``'s items
    replace the defaults of options not given."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help=f"smoke test: {quick}")
    ap.add_argument("--out", default=None, help="results file (.md or .json; the other is written beside it)")
    for k, v in defaults.items():
        name = "--" + k.replace("_", "-")
        if v is False:
            ap.add_argument(name, action="store_true")
        else:
            ap.add_argument(name, type=_value, default=None, help=f"default {v}")
    a = ap.parse_args(argv)
    for k, v in defaults.items():
        if getattr(a, k) is None:
            setattr(a, k, (quick or {}).get(k, v) if a.quick else v)
    return a


def ints(text, option: str) -> List[int]:
    """``"200,1e4"`` (or one number) -> ``[200, 10000]``, each >= 1 (else ``SystemExit`` naming the option)."""
    try:
        vals = [int(float(v)) for v in str(text).split(",") if v.strip()]
    except ValueError:
        raise SystemExit(f"{option}: expected comma-separated integers, got {text!r}") from None
    if not vals or min(vals) < 1:
        raise SystemExit(f"{option}: expected positive integers, got {text!r}")
    return vals


@contextlib.contextmanager
def session(name: str, argv, threads: Optional[int] = None, device=None, **extra):
    """Run with ``threads`` torch threads; yields the :func:`machine` (``load_end`` set on exit)."""
    with torch_threads(threads):
        info = machine(device, command=command(name, argv), **extra)
        yield info
        info["load_end"] = loadavg()


def report(
    title: str, a, info: dict, intro: Sequence[str], head: Sequence[str], rows: Iterable[Sequence], *more: str
) -> str:
    """Markdown of a run: :func:`header` (``intro`` its lines), the table, then ``more`` lines."""
    lines = header(title, a.quick, info, *intro) + md_table(head, rows) + ([""] if more else []) + list(more)
    return "\n".join(lines) + "\n"


def fmt(x, spec: str = "{:.3g}") -> str:
    """``spec.format(x)``, ``-`` for None or nan (an infinity prints as ``inf``)."""
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    return str(x) if isinstance(x, float) and math.isinf(x) else spec.format(x)


def met_cell(met: Optional[bool]) -> str:
    """A goal's ``met`` cell: ``yes``, ``NO`` or ``-`` (no goal)."""
    return "-" if met is None else ("yes" if met else "NO")


def md_table(head: Sequence[str], rows: Iterable[Sequence]) -> List[str]:
    """Lines of a markdown table; every row must have one cell per column."""
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        if len(r) != len(head):
            raise ValueError(f"md_table: row has {len(r)} cells, the header {len(head)}: {list(r)!r}")
        out.append("| " + " | ".join(str(c) for c in r) + " |")
    return out


def results_path(name: str, quick: bool = False, out: Optional[str] = None) -> Path:
    """Markdown path of a run: ``out`` or ``results_<name>[_quick].md`` in :data:`RESULTS`."""
    return Path(out) if out else RESULTS / (f"results_{name}_quick.md" if quick else f"results_{name}.md")


def write_results(res: dict, name: str, quick: bool = False, out: Optional[str] = None) -> Path:
    """Write and print ``res["markdown"]`` (:func:`results_path`) and the rest of ``res`` as JSON beside it."""
    path = results_path(name, quick, out)
    md = path.with_suffix(".md") if path.suffix == ".json" else path
    md.parent.mkdir(parents=True, exist_ok=True)
    md.write_text(res["markdown"])
    md.with_suffix(".json").write_text(
        json.dumps({k: v for k, v in res.items() if k != "markdown"}, indent=1, default=str)
    )
    print(res["markdown"])
    print(f"wrote {md} and {md.with_suffix('.json')}")
    return md


def main(run: Callable[[list], dict], name: str, argv: Optional[Sequence[str]] = None) -> dict:
    """Command-line entry of a benchmark: ``run(argv)``, then its results files."""
    try:
        res = run(list(sys.argv[1:] if argv is None else argv))
    except CheckFailed as exc:
        raise SystemExit(str(exc)) from None
    args = res.get("args", {})
    write_results(res, name, bool(args.get("quick")), args.get("out"))
    return res
