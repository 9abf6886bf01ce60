"""Hydra entry point: build a model and filters from ``configs/``, run them, write results.

    python experiments/run.py                                   # default acoustic comparison
    python experiments/run.py model=linear_gaussian filter=[kf,bpf] trials=100 steps=10 n_particles=200
    python experiments/run.py experiment=seed000_table1         # a paper table
    python experiments/run.py -m filter=[bpf] n_particles=100,1000   # sweep; one folder per job

Writes ``summary.csv``, ``per_step.csv``, ``per_trial.csv``, ``results.json`` and (with
matplotlib) ``per_step.png`` into Hydra's output folder and prints the summary table.
"""
from __future__ import annotations

import csv
import json
import os
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a source checkout too
CONFIGS = Path(__file__).resolve().parents[1] / "configs"

from torchflow.experiment import SUMMARY_COLUMNS, format_table, run_experiment  # noqa: E402
from torchflow import tuning  # noqa: E402


def _write_csv(path: Path, rows, columns=None):
    """Write ``rows`` to ``path`` atomically (a temporary file renamed): an interrupted write never
    leaves a truncated table."""
    columns = columns or sorted({k for r in rows for k in r}, key=lambda k: (k not in ("filter", "step", "trial"), k))
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=columns, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in columns})
    os.replace(tmp, path)


#: one colour per filter, the same on every panel and in the track picture
_COLOURS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
            "#bcbd22", "#17becf"]
_LABELS = {"omat": "OMAT (m)", "ospa": "OSPA (m)", "mse": "MSE", "ess": "ESS"}


def _matplotlib():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("(matplotlib not installed: no plots; pip install matplotlib)")
        return None
    return plt


def _colours(names):
    return {n: _COLOURS[i % len(_COLOURS)] for i, n in enumerate(names)}


def _plot(path: Path, per_step, summary, title: str):
    plt = _matplotlib()
    if plt is None:
        return
    fig = per_step_figure(plt, per_step, summary, title)
    if fig is not None:
        fig.savefig(path, dpi=110)
        plt.close(fig)


def per_step_figure(plt, per_step, summary, title: str):
    """Per-step metric means, one panel per metric; a filter keeps its colour on every panel and
    one legend lists them all. ESS is drawn as a fraction of each filter's N (filters of
    different N share the axis); a panel says which filters have no value there."""
    keys = [k for k in ("omat", "ospa", "mse", "ess") if any(k in r for r in per_step)]
    if not keys:
        return None
    names = list(dict.fromkeys(r["filter"] for r in summary))
    colour = _colours(names)
    n_of = {r["filter"]: r.get("n_particles") for r in summary}
    fig, axes = plt.subplots(1, len(keys), figsize=(4.2 * len(keys), 3.6), squeeze=False)
    handles = {}
    for ax, key in zip(axes[0], keys):
        missing = []
        for name in names:
            rows = [r for r in per_step if r["filter"] == name and key in r]
            if not rows:
                missing.append(name)
                continue
            y = [r[key] for r in rows]
            if key == "ess":
                y = [v / n_of[name] for v in y]
            (h,) = ax.plot([r["step"] for r in rows], y, color=colour[name], label=name)
            handles[name] = h
        ax.set_xlabel("time step")
        Ns = sorted({n_of[n] for n in names if n not in missing and n_of.get(n)})
        if key == "ess":
            ax.set_ylabel(f"ESS / N (N = {Ns[0]})" if len(Ns) == 1 else "ESS / N (each filter's N)")
            fractions = [v for line in ax.get_lines() for v in line.get_ydata() if v > 0]
            if fractions and min(fractions) < 0.1:  # low ESS: a log axis keeps the curves apart
                ax.set_yscale("log")
                ax.set_ylim(min(fractions) / 1.5, 1.05)
            else:
                ax.set_ylim(0, 1.05)
        else:
            ax.set_ylabel(_LABELS.get(key, key))
        if key == "mse":
            ax.set_yscale("log")
        if missing:
            ax.set_title("not defined for: " + ", ".join(missing), fontsize=7)
        ax.grid(alpha=0.3)
    fig.legend([handles[n] for n in names if n in handles], [n for n in names if n in handles],
               loc="lower center", ncol=min(len(handles), 6), fontsize=8, frameon=False)
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    return fig


def _plot_tracks(path: Path, model, trajectory, examples, summary, title: str):
    """Trial 0 of a tracking model: sensors, true tracks (start marked) and each filter's
    estimated tracks in the filter's colour."""
    plt = _matplotlib()
    if plt is None or not examples:
        return
    names = list(dict.fromkeys(r["filter"] for r in summary))
    colour = _colours(names)
    true_pos = model.positions(trajectory.states[0].to(model.dtype)).cpu()  # (T+1, C, 2)
    fig, ax = plt.subplots(figsize=(5.6, 5.6))
    sensors = getattr(model, "sensors", None)
    if sensors is not None:
        s = sensors.cpu()
        ax.scatter(s[:, 0], s[:, 1], marker="^", s=18, color="0.6", label="sensors")
    for c in range(true_pos.shape[1]):
        ax.plot(true_pos[:, c, 0], true_pos[:, c, 1], color="k", lw=2.2, label="truth" if c == 0 else None)
        ax.plot(true_pos[0, c, 0], true_pos[0, c, 1], "ko", ms=5)
    for name in names:
        if name not in examples:
            continue
        est = model.positions(examples[name].to(model.dtype)).cpu()  # (T, C, 2)
        for c in range(est.shape[1]):
            ax.plot(est[:, c, 0], est[:, c, 1], color=colour[name], lw=1.2, ls="--", label=name if c == 0 else None)
    area = getattr(model, "area", None)
    if area:
        ax.set_xlim(-0.03 * area, 1.03 * area)
        ax.set_ylim(-0.03 * area, 1.03 * area)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1))
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


_FLOW_NAMES = {"EDHFlow": "edh", "LEDHFlow": "ledh", "GeodesicFlow": "geodesic", "GromovFlow": "gromov",
               "OptimalDiffusionFlow": "osd"}


def flow_label(flow) -> str:
    """Config-style name of a flow: ``ledh``, ``gromov``; ``_global`` for a per-trial linearisation
    of a flow that is per particle by default."""
    name = _FLOW_NAMES.get(type(flow).__name__, type(flow).__name__)
    if name not in ("edh", "ledh") and getattr(flow, "points", "particle") != "particle":
        name += "_global"
    return name


def row_label(key: str, f) -> str:
    """A result row's label: the config key, plus the flow and linearisation points it really ran
    when an override made the key's name wrong (``pfpf_ledh`` run with
    ``flow@filter.pfpf_ledh.flow=edh`` -> ``pfpf_ledh[flow=edh]``; with
    ``filter.pfpf_ledh.points=global`` -> ``pfpf_ledh[points=global]``)."""
    flow = getattr(f, "flow", None)
    if hasattr(f, "method"):  # TDOA localisers: the key names the method
        return key
    if hasattr(f, "n_components"):  # Gaussian-sum filters: the seed's N* x G label, and a flow the key does not say
        tags = [f"{f.particles_per_component}x{f.n_components}"]
        fl = None if flow is None else flow_label(flow)
        if fl != ("ledh" if key.startswith("pf") else None):
            tags.append(f"flow={fl}")
        if getattr(f, "estimate", "mixture_mean") != "mixture_mean":
            tags.append(f"estimate={f.estimate}")
        return f"{key}[{','.join(tags)}]"
    if flow is None:
        return key
    fl = flow_label(flow)
    named = [n for n in sorted(set(_FLOW_NAMES.values()), key=len, reverse=True) if n in key.split("_")]
    expected = named[0] if named else "ledh"  # a key naming no flow (pfpf_clustered) runs LEDH by default
    tags = [] if fl == expected else [f"flow={fl}"]
    points = getattr(getattr(f, "points", None), "name", None)
    default_points = "clustered" if "clustered" in key.split("_") else flow.points
    if points is not None and points != default_points:
        tags.append(f"points={points}")
    return f"{key}[{','.join(tags)}]" if tags else key


class UsageError(Exception):
    """A bad command line: printed as one line, exit status 2."""


def _reason(e: BaseException) -> str:
    """The message of the error that caused ``e`` (Hydra wraps constructor errors)."""
    from hydra.errors import InstantiationException

    if isinstance(e, InstantiationException):
        cause = e.__cause__ or e.__context__
        key = ""
        for line in str(e).splitlines():
            if line.startswith("full_key:"):
                key = line.split(":", 1)[1].strip() + ": "
        if cause is not None:
            return key + str(cause).strip("'\"")
    return str(e)


def _group_options(group: str):
    d = CONFIGS / group
    return sorted(p.stem for p in d.glob("*.yaml")) if d.is_dir() else None


def check_selections(argv) -> None:
    """Refuse unknown config names in group selections (``filter=[a,b]``, ``model=x``,
    ``flow@filter.pfpf_ledh.flow=edh``, sweeps ``filter=a,b``) with the list of valid names,
    before Hydra composes anything."""
    for arg in argv:
        if "=" not in arg or arg.startswith(("hydra.", "-")):
            continue
        lhs, rhs = arg.split("=", 1)
        group = lhs.lstrip("+~").split("@", 1)[0]
        if "." in group or "/" in group:
            continue
        options = _group_options(group)
        if options is None:
            continue
        values = [v.strip() for v in rhs.strip("[]").split(",") if v.strip()]
        if rhs.strip().startswith(("range(", "choice(", "glob(", "interval(")) or rhs.strip() in ("null", ""):
            continue
        unknown = [v for v in values if v not in options]
        if unknown:
            raise UsageError(f"{lhs}: unknown {group} config {', '.join(repr(u) for u in unknown)}; "
                             f"available: {', '.join(options)}")


def omat_box_figure(plt, per_trial, summary, title: str):
    """Per-trial time-averaged OMAT of every filter as a box at the filter's time per step (log
    axis): accuracy against cost, as seed 004's Fig. 5. ``None`` without OMAT."""
    names = [r["filter"] for r in summary if r.get("omat") is not None and r.get("sec_per_step")]
    if not names:
        return None
    colour = _colours([r["filter"] for r in summary])
    fig, ax = plt.subplots(figsize=(8.5, 4.2))
    for name in names:
        vals = [r["omat"] for r in per_trial if r["filter"] == name and "omat" in r]
        x = next(r["sec_per_step"] for r in summary if r["filter"] == name)
        bp = ax.boxplot([vals], positions=[x], widths=[x * 0.25], patch_artist=True, manage_ticks=False)
        for part in ("boxes", "medians", "whiskers", "caps", "fliers"):
            for artist in bp[part]:
                artist.set_color(colour[name])
        bp["boxes"][0].set_facecolor("none")
        bp["boxes"][0].set_label(name)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1))
    ax.set_xscale("log")
    ax.set_xlabel("seconds per trial-step (this run)")
    ax.set_ylabel("time-averaged OMAT per trial (m)")
    ax.grid(alpha=0.3)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return fig


def _write_results(out: Path, cfg, result, model) -> None:
    _write_csv(out / "summary.csv", result.summary, SUMMARY_COLUMNS)
    _write_csv(out / "per_step.csv", result.per_step)
    _write_csv(out / "per_trial.csv", result.per_trial)
    with open(out / "results.json", "w") as fh:
        json.dump({"config": OmegaConf.to_container(cfg, resolve=True), "run": result.config,
                   "summary": result.summary, "interrupted": result.interrupted, "not_run": result.not_run},
                  fh, indent=2)
    if cfg.get("plots", True) and result.per_step:
        model_name = cfg.model._target_.split(".")[-1]
        _plot(out / "per_step.png", result.per_step, result.summary, f"{model_name}, {cfg.trials} trials")
        if model.has_positions and result.trajectory is not None:
            _plot_tracks(out / "tracks.png", model, result.trajectory, result.examples, result.summary,
                         f"{model_name}: trial 0, true and estimated tracks")
            plt = _matplotlib()
            fig = omat_box_figure(plt, result.per_trial, result.summary,
                                  f"{model_name}: per-trial OMAT against time per step, {cfg.trials} trials")
            if fig is not None:
                fig.savefig(out / "omat_box.png", dpi=110)
                plt.close(fig)


def _run_localisation(cfg, model, localisers, out: Path) -> int:
    """Seed 002's scene: runs x localisers, OSPA per run, the table, CSVs and a 3-D picture of run 0."""
    from torchflow.localisation import LOCALISATION_COLUMNS, run_localisation, scene_figure

    bad = [k for k, f in localisers.items() if not hasattr(f, "method")]
    if bad:
        raise UsageError(f"filter: {', '.join(bad)} cannot run on the TDOA model; select localisers "
                         "(bs, pfi_d, pfi_s, pfi_os)")
    summary, per_run, data, examples = run_localisation(
        model, localisers, runs=cfg.trials, seed=cfg.seed, ospa_cutoff=float(cfg.metrics.ospa_cutoff),
        ospa_order=float(cfg.metrics.ospa_order), device=cfg.device, dtype=cfg.dtype,
        rng_backend=str(cfg.get("rng_backend", "auto")), progress=bool(cfg.progress),
        on_filter_done=lambda rows: _write_csv(out / "summary.csv", rows, LOCALISATION_COLUMNS))
    _write_csv(out / "summary.csv", summary, LOCALISATION_COLUMNS)
    _write_csv(out / "per_trial.csv", per_run)
    with open(out / "results.json", "w") as fh:
        json.dump({"config": OmegaConf.to_container(cfg, resolve=True), "summary": summary}, fh, indent=2)
    if cfg.get("plots", True):
        plt = _matplotlib()
        if plt is not None:
            fig = scene_figure(plt, model, data.sources[0], examples, "TDOA3D: run 0, true and declared sources")
            fig.savefig(out / "scene.png", dpi=110)
            plt.close(fig)
    print(f"\nTDOA3D: {cfg.trials} runs, seed {cfg.seed}, {cfg.device}/{cfg.dtype}, OSPA cut-off "
          f"{cfg.metrics.ospa_cutoff:g} m")
    print(format_table(summary, LOCALISATION_COLUMNS))
    for r in summary:
        if r.get("error"):
            print(f"!! {r['filter']} failed: {r['error']}", file=sys.stderr)
    print(f"results: {os.path.relpath(out)}")
    return 0


def _run(cfg: DictConfig) -> int:
    knobs = {k: v for k, v in (OmegaConf.to_container(cfg.get("tuning") or {}) or {}).items() if v is not None}
    with tuning.tuned(**knobs):
        return _run_tuned(cfg)


def _plain(v):
    return OmegaConf.to_container(v) if OmegaConf.is_config(v) else v


def _chunk_store(cfg: DictConfig, labels):
    """The run's :class:`~torchflow.checkpoint.ChunkStore` (``None`` with ``checkpoint_dir=null``):
    one folder per filter, named by a fingerprint of everything that changes its numbers."""
    import torch
    import torchflow
    from torchflow.checkpoint import ChunkStore, fingerprint

    root = cfg.get("checkpoint_dir")
    resume = cfg.get("resume", False)
    if not isinstance(resume, bool):
        raise UsageError(f"resume: expected true or false, got {resume!r}")
    if root is None:
        if resume:
            raise UsageError("resume=true needs checkpoint_dir (where the earlier run saved its chunks); it is null")
        return None
    common = {k: OmegaConf.to_container(cfg[k], resolve=True) if OmegaConf.is_config(cfg[k]) else cfg[k]
              for k in ("model", "trials", "steps", "seed", "inits_per_track", "device", "dtype", "rng_backend")}
    common["versions"] = {"torchflow": torchflow.__version__, "torch": torch.__version__}
    keys, settings = {}, {}
    for key, fcfg in cfg.filter.items():
        label = labels.get(key)
        if label is None:  # settings for a filter that is not selected
            continue
        s = dict(common, filter=OmegaConf.to_container(fcfg, resolve=True), label=label)
        keys[label] = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in label) + "-" + fingerprint(s)
        settings[label] = s
    return ChunkStore(Path(hydra.utils.to_absolute_path(str(root))), keys, resume=resume, settings=settings)


def _resume_command() -> str:
    """The command line of this run with ``resume=true`` (under torchrun: the same number of
    processes, so the chunks are the same)."""
    import shlex

    overrides = [o for o in HydraConfig.get().overrides.task if not o.startswith("resume=")]
    world = int(os.environ.get("WORLD_SIZE", "1"))
    head = (["python experiments/run.py"] if world == 1 else
            [f"torchrun --nproc_per_node={os.environ.get('LOCAL_WORLD_SIZE', world)}"
             + (f" --nnodes={world // int(os.environ['LOCAL_WORLD_SIZE'])}" if os.environ.get("LOCAL_WORLD_SIZE")
                and world != int(os.environ["LOCAL_WORLD_SIZE"]) else ""), "experiments/run.py"])
    return " ".join([*head, *(shlex.quote(o) for o in overrides), "resume=true"])


def _run_tuned(cfg: DictConfig) -> int:
    from torchflow.distributed import Shard

    out = Path(HydraConfig.get().runtime.output_dir)
    shard = Shard.from_env(str(cfg.device), timeout_minutes=float(cfg.get("dist_timeout_min", 720)))
    try:
        return _run_sharded(cfg, out, shard)
    finally:
        shard.close()


def _run_sharded(cfg: DictConfig, out: Path, shard) -> int:
    if shard.is_main:
        out.mkdir(parents=True, exist_ok=True)
    if not cfg.get("filter"):
        raise UsageError("filter: select at least one filter, e.g. filter=[kf,bpf]; available: "
                         + ", ".join(_group_options("filter")))
    model = instantiate(cfg.model)
    filters, labels = {}, {}  # labels: config key -> row label
    for key, fcfg in cfg.filter.items():
        if "_target_" not in fcfg:  # e.g. an experiment's per-filter setting for a filter not selected
            print(f"(filter.{key}: settings given but the filter is not selected; skipped)", file=sys.stderr)
            continue
        f = instantiate(fcfg, model=model, name=key)
        label = row_label(key, f)
        f.name = label
        labels[key] = label
        filters[label] = f
    from torchflow.models import TDOA3D

    if isinstance(model, TDOA3D):
        if shard.world > 1 or cfg.get("resume"):
            raise UsageError("resume=true and torchrun apply to filter runs, not to the TDOA localisers")
        return _run_localisation(cfg, model, filters, out)
    store = _chunk_store(cfg, labels)
    result = run_experiment(
        model,
        filters,
        trials=cfg.trials,
        steps=cfg.steps,
        seed=cfg.seed,
        inits_per_track=cfg.inits_per_track,
        chunk_size=cfg.chunk_size,
        memory_budget_gb=cfg.memory_budget_gb,
        device=shard.device(cfg.device),
        dtype=cfg.dtype,
        ospa_cutoff=float(cfg.metrics.ospa_cutoff),
        ospa_order=float(cfg.metrics.ospa_order),
        lost_threshold=float(cfg.metrics.lost_threshold),
        progress=bool(cfg.progress),
        rng_backend=str(cfg.get("rng_backend", "auto")),
        on_filter_done=lambda rows: _write_csv(out / "summary.csv", rows, SUMMARY_COLUMNS),  # partial results
        store=store,
        shard=shard,
        trial_range=_plain(cfg.get("trial_range")),
    )
    if result is None:  # a rank other than 0 of a torchrun run: rank 0 writes the files
        return 0
    _write_results(out, cfg, result, model)
    model_name = cfg.model._target_.split(".")[-1]
    if store is not None and store.loaded:
        print(f"resumed: {sum(store.loaded.values())} chunks loaded from {store.root}, "
              f"{sum(store.computed.values())} computed")
    lo, hi = result.config["trial_range"]
    which = f"{cfg.trials} trials" if (lo, hi) == (0, cfg.trials) else f"trials {lo}..{hi - 1} of {cfg.trials}"
    print(f"\n{model_name}: {which} x {cfg.steps} steps, seed {cfg.seed}, {cfg.device}/{cfg.dtype}")
    print(format_table(result.summary))
    for r in result.summary:
        if r.get("error"):
            print(f"!! {r['filter']} failed: {r['error']}", file=sys.stderr)
    print(f"results: {os.path.relpath(out)}")
    if result.interrupted:
        skipped = f"; not run: {', '.join(result.not_run)}" if result.not_run else ""
        print(f"interrupted (Ctrl-C or SIGTERM): the results of the filters that finished are written{skipped}",
              file=sys.stderr)
        if store is not None:
            print(f"the finished chunks are saved under {store.root}; go on with\n  {_resume_command()}",
                  file=sys.stderr)
        return 130
    return 0


def _multirun() -> bool:
    from hydra.types import RunMode

    return HydraConfig.get().mode == RunMode.MULTIRUN


def _record_failure(message: str) -> None:
    """A failed sweep job leaves ``error.txt`` in its folder (collect.py and the end-of-sweep
    report name it) instead of stopping the sweep."""
    out = Path(HydraConfig.get().runtime.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "error.txt").write_text(message.rstrip() + "\n")


@hydra.main(config_path="../configs", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    """Run one job; a bad setting or an interruption ends it with one line, not a traceback. In
    a sweep (``-m``) a failing job records its error and the sweep goes on with the next job."""
    import signal
    import traceback

    from torchflow.experiment import STOP

    STOP.reset()
    try:  # Ctrl-C and SIGTERM (kill, a scheduler's time limit) stop at once inside a chunk, else at the next one
        signal.signal(signal.SIGINT, STOP.handler)
        signal.signal(signal.SIGTERM, STOP.handler)
    except ValueError:  # not the main thread (some launchers): Python's own Ctrl-C handling only
        pass
    try:
        code = _run(cfg)
    except KeyboardInterrupt:
        print("interrupted outside a filter run: only summary.csv (rows of the filters that "
              "finished, if any) was written", file=sys.stderr)
        code = 130
    except Exception as e:  # noqa: BLE001 - configuration errors: name the setting, no traceback
        from hydra.errors import InstantiationException
        from omegaconf.errors import OmegaConfBaseException

        config_error = isinstance(e, (ValueError, TypeError, UsageError, InstantiationException, OmegaConfBaseException))
        if _multirun():
            _record_failure(f"error: {_reason(e)}" if config_error else traceback.format_exc())
            print(f"error: {_reason(e)} (job failed; the sweep goes on)", file=sys.stderr)
            return
        if not config_error:
            raise
        print(f"error: {_reason(e)}", file=sys.stderr)
        code = 2
    if code:
        sys.exit(code)


def _pid_resolver() -> str:
    return str(os.getpid())


# cached: a launcher that resolves the sweep folder again in each worker (joblib, submitit) gets
# the main process's value, so every job lands in the one announced folder
OmegaConf.register_new_resolver("tf_pid", _pid_resolver, replace=True, use_cache=True)

def _quiet_rank_overrides(argv):
    """Ranks other than 0 of a ``torchrun`` run write no Hydra folder or log (rank 0 does)."""
    if int(os.environ.get("RANK", "0")) == 0:
        return argv
    if any(a in ("-m", "--multirun") for a in argv):
        raise UsageError("torchrun runs one job; run a sweep (-m) on a Hydra launcher instead")
    import tempfile

    return [*argv, f"hydra.run.dir={tempfile.gettempdir()}/torchflow-rank{os.environ['RANK']}-{os.getppid()}",
            "hydra.output_subdir=null", "hydra/job_logging=disabled", "hydra/hydra_logging=disabled"]


if __name__ == "__main__":
    try:
        check_selections(sys.argv[1:])
        sys.argv[1:] = _quiet_rank_overrides(sys.argv[1:])
    except UsageError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    main()
