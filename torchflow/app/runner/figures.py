"""Pictures of a run (matplotlib is optional: :func:`pyplot`). Each ``*_figure`` takes ``plt`` and
returns a figure (``None``: nothing to draw); a filter keeps one colour everywhere (:func:`colours`).
The per-step figure's panels, labels and axes follow :data:`torchflow.core.metrics.REGISTRY`.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import List

from torchflow.app.runner.writers import save_figure
from torchflow.core import metrics

log = logging.getLogger("torchflow.app.runner")

COLOURS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"]


def pyplot():
    """``matplotlib.pyplot`` on the Agg back end, or ``None`` (with a note) when not installed."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        log.info("(matplotlib not installed: no plots; pip install matplotlib)")
        return None
    return plt


def colours(summary) -> dict:
    """``{filter: colour}`` in the order of the summary rows."""
    names = list(dict.fromkeys(r["filter"] for r in summary))
    return {n: COLOURS[i % len(COLOURS)] for i, n in enumerate(names)}


def _finish(fig, ax, title: str, **legend):
    ax.legend(fontsize=7, **(legend or {"loc": "upper left", "bbox_to_anchor": (1.01, 1)}))
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return fig


def per_step_keys(per_step) -> List[str]:
    """The per-step figure's panels: the registered metrics with ``plot=True`` that some per-step
    row holds, in registration order."""
    return [m.name for m in metrics.REGISTRY.values() if m.plot and any(m.name in r for r in per_step)]


def per_step_figure(plt, per_step, summary, title: str):
    """Per-step metric means, one panel per metric of :func:`per_step_keys` (y label: the metric's
    ``label``), one legend; a ``yscale="per_particle"`` metric (ESS) as a fraction of each filter's
    N (a log axis below 0.1); a panel names the filters that have no value there."""
    keys = per_step_keys(per_step)
    if not keys:
        return None
    colour, n_of = colours(summary), {r["filter"]: r.get("n_particles") for r in summary}
    fig, axes = plt.subplots(1, len(keys), figsize=(4.2 * len(keys), 3.6), squeeze=False)
    handles = {}
    for ax, key in zip(axes[0], keys):
        metric = metrics.REGISTRY[key]
        per_n = metric.yscale == "per_particle"
        missing = [n for n in colour if not any(r["filter"] == n and key in r for r in per_step)]
        for name in (n for n in colour if n not in missing):
            rows = [r for r in per_step if r["filter"] == name and key in r]
            y = [r[key] / n_of[name] if per_n else r[key] for r in rows]
            (handles[name],) = ax.plot([r["step"] for r in rows], y, color=colour[name], label=name)
        ax.set_xlabel("time step")
        ax.set_ylabel(metric.label)
        if per_n:
            Ns = sorted({n_of[n] for n in colour if n not in missing and n_of.get(n)})
            ax.set_ylabel(f"{metric.label} / N " + (f"(N = {Ns[0]})" if len(Ns) == 1 else "(each filter's N)"))
            fractions = [v for line in ax.get_lines() for v in line.get_ydata() if v > 0]
            low = bool(fractions) and min(fractions) < 0.1  # low ESS: a log axis keeps the curves apart
            ax.set_yscale("log" if low else "linear")
            ax.set_ylim(min(fractions) / 1.5 if low else 0, 1.05)
        if metric.yscale == "log":
            ax.set_yscale("log")
        if missing:
            ax.set_title("not defined for: " + ", ".join(missing), fontsize=7)
        ax.grid(alpha=0.3)
    named = [n for n in colour if n in handles]
    fig.legend(
        [handles[n] for n in named], named, loc="lower center", ncol=min(len(named), 6), fontsize=8, frameon=False
    )
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    return fig


def tracks_figure(plt, model, trajectory, examples, summary, title: str):
    """Trial 0 of a tracking model: sensors, true tracks (start marked) and each filter's estimates."""
    if not examples:
        return None
    colour = colours(summary)
    true_pos = model.positions(trajectory.states[0].to(model.dtype)).cpu()  # (T+1, C, 2)
    fig, ax = plt.subplots(figsize=(5.6, 5.6))
    if getattr(model, "sensors", None) is not None:
        ax.scatter(*model.sensors.cpu()[:, :2].T, marker="^", s=18, color="0.6", label="sensors")
    for c in range(true_pos.shape[1]):
        ax.plot(true_pos[:, c, 0], true_pos[:, c, 1], color="k", lw=2.2, label="truth" if c == 0 else None)
        ax.plot(true_pos[0, c, 0], true_pos[0, c, 1], "ko", ms=5)
    for name in (n for n in colour if n in examples):
        est = model.positions(examples[name].to(model.dtype)).cpu()  # (T, C, 2)
        for c in range(est.shape[1]):
            ax.plot(est[:, c, 0], est[:, c, 1], color=colour[name], lw=1.2, ls="--", label=name if c == 0 else None)
    if getattr(model, "area", None):
        ax.set_xlim(-0.03 * model.area, 1.03 * model.area)
        ax.set_ylim(-0.03 * model.area, 1.03 * model.area)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    return _finish(fig, ax, title)


def omat_box_figure(plt, per_trial, summary, title: str):
    """Per-trial time-averaged OMAT of every filter as a box at the filter's time per step (log
    axis): accuracy against cost, as Fig. 5 of Li & Coates' clustered PF-PF paper. ``None`` without OMAT."""
    rows = [r for r in summary if r.get("omat") is not None and r.get("sec_per_step")]
    if not rows:
        return None
    colour = colours(summary)
    fig, ax = plt.subplots(figsize=(8.5, 4.2))
    for row in rows:
        name, x = row["filter"], row["sec_per_step"]
        vals = [r["omat"] for r in per_trial if r["filter"] == name and "omat" in r]
        bp = ax.boxplot([vals], positions=[x], widths=[x * 0.25], patch_artist=True, manage_ticks=False)
        for part in ("boxes", "medians", "whiskers", "caps", "fliers"):
            for artist in bp[part]:
                artist.set_color(colour[name])
        bp["boxes"][0].set_facecolor("none")
        bp["boxes"][0].set_label(name)
    ax.set_xscale("log")
    ax.set_xlabel("seconds per trial-step (this run)")
    ax.set_ylabel("time-averaged OMAT per trial (m)")
    ax.grid(alpha=0.3)
    return _finish(fig, ax, title)


def scene_figure(plt, model, trajectory, examples, summary, title: str):
    """Run 0 of a 3-D localisation (:class:`~torchflow.models.TDOA3D`): receivers, true sources and
    each localiser's declared sources ``examples[name] (k, 3)`` in the filter's colour."""
    colour = colours(summary)
    fig = plt.figure(figsize=(6.5, 5.5))
    ax = fig.add_subplot(projection="3d")
    ax.scatter(*model.receivers.cpu().T, marker="s", s=40, c="k", label="receivers")
    ax.scatter(
        *model.positions(trajectory.states[0, 0]).cpu().T,
        marker="*",
        s=160,
        c="gold",
        edgecolors="k",
        label="true sources",
    )
    for i, (name, pos) in enumerate(examples.items()):
        mark = "o^vDs<>"[i % 7]
        if len(pos):
            ax.scatter(*pos.T, marker=mark, s=50, facecolors="none", edgecolors=colour[name], label=name)
        else:
            ax.scatter([], [], [], marker=mark, c=colour[name], label=f"{name} (none declared)")
    r = model.region
    ax.set_xlim(-r, r), ax.set_ylim(-r, r), ax.set_zlim(-r, r)
    ax.set_xlabel("x (m)"), ax.set_ylabel("y (m)"), ax.set_zlabel("z (m)")
    return _finish(fig, ax, title, loc="upper left")


#: state coordinates drawn by :func:`estimates_figure`
ESTIMATE_PANELS = 4


def estimates_figure(plt, estimate_summary, summary, title: str):
    """The first :data:`ESTIMATE_PANELS` state coordinates over time: each filter's filtered mean
    (averaged over trials) with a band of one filtering standard deviation (or, where a filter gives
    none, of the spread over trials); recorded data: no truth to draw. ``None`` without point
    estimates."""
    if not estimate_summary:
        return None
    colour = colours(summary)
    d = min(next(iter(estimate_summary.values()))[0].shape[-1], ESTIMATE_PANELS)
    fig, axes = plt.subplots(1, d, figsize=(4.2 * d, 3.4), squeeze=False)
    for j, ax in enumerate(axes[0]):
        for name, (mean, sd, spread) in estimate_summary.items():
            sd = spread if sd is None else sd
            steps = range(1, mean.shape[0] + 1)
            ax.plot(steps, mean[:, j], color=colour.get(name), label=name)
            ax.fill_between(steps, mean[:, j] - sd[:, j], mean[:, j] + sd[:, j], color=colour.get(name), alpha=0.2)
        ax.set_xlabel("time step")
        ax.set_ylabel(f"state coordinate {j}")
        ax.grid(alpha=0.3)
    axes[0][-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1))
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return fig


def smoothing_figure(plt, truth, results, title: str):
    """One trial's first :data:`ESTIMATE_PANELS` state coordinates over steps 0..T: the truth
    (``truth (T+1, d)``; ``None``: recorded data), and per filter (``results``: name -> ``mean``,
    ``sd``, ``filtered_mean``, ``filtered_sd``, each ``(T+1, d)``) the filtered mean (dashed) and
    the smoothed mean (solid), each with a band of +-2 standard deviations."""
    colour = colours([{"filter": n} for n in results])
    d = min(next(iter(results.values()))["mean"].shape[-1], ESTIMATE_PANELS)
    fig, axes = plt.subplots(1, d, figsize=(4.2 * d, 3.4), squeeze=False)
    for j, ax in enumerate(axes[0]):
        for name, r in results.items():
            steps = range(r["mean"].shape[0])
            for key, style, alpha, what in (("filtered", "--", 0.08, "filtered"), ("", "-", 0.2, "smoothed")):
                m = r[f"{key}_mean" if key else "mean"][:, j]
                sd = r[f"{key}_sd" if key else "sd"][:, j]
                ax.plot(steps, m, style, color=colour[name], lw=1.2, label=f"{name} {what}")
                ax.fill_between(steps, m - 2 * sd, m + 2 * sd, color=colour[name], alpha=alpha, lw=0)
        if truth is not None:
            ax.plot(range(truth.shape[0]), truth[:, j], color="black", lw=1.0, label="truth")
        ax.set_xlabel("time step")
        ax.set_ylabel(f"state coordinate {j}")
        ax.grid(alpha=0.3)
    axes[0][-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1))
    fig.suptitle(title + " (bands: +-2 sd)", fontsize=9)
    fig.tight_layout()
    return fig


def save_smoothing_figure(path: Path, truth, results, title: str) -> Path:
    """``smoothed.png`` (:func:`smoothing_figure`); matplotlib missing: nothing written."""
    plt = pyplot()
    if plt is None:
        return path
    fig = smoothing_figure(plt, truth, results, title)
    try:
        save_figure(fig, path, dpi=100)
    finally:
        plt.close(fig)
    return path


#: scalar parameter components drawn by the posterior figures
POSTERIOR_PANELS = 6


def scalar_series(draws):
    """``{component: (C, S)}`` of draws ``{parameter: (C, S, *shape)}``: a scalar parameter by its
    name (``rho``), a vector or matrix flattened, ``F_0, F_1, ...``."""
    out = {}
    for name, v in draws.items():
        flat = v.reshape(v.shape[0], v.shape[1], -1)
        out.update(
            {name: flat[..., 0]} if v.dim() == 2 else {f"{name}_{i}": flat[..., i] for i in range(flat.shape[-1])}
        )
    return out


def _include(ax, value: float, axis: str) -> None:
    """Widen ``ax``'s ``axis`` ("x" or "y") so that ``value`` (a truth line) sits inside, 5 % of
    the range in from the frame, not on it."""
    lo, hi = ax.get_xlim() if axis == "x" else ax.get_ylim()
    lo, hi = min(lo, value), max(hi, value)
    pad = 0.05 * (hi - lo or abs(value) or 1.0)
    lim = (min(lo, value - pad), max(hi, value + pad))
    (ax.set_xlim if axis == "x" else ax.set_ylim)(*lim)


def posterior_figures(plt, draws, truth, title: str):
    """``(histograms, traces)`` of PMMH draws (``draws``: filter -> parameter -> ``(C, S, ...)``),
    the first :data:`POSTERIOR_PANELS` scalar components: a histogram of all chains' draws per
    filter with the truth (``truth``: parameter -> value; ``None``: unknown) as a vertical line;
    trace plots, one row per filter, one line per chain."""
    series = {f: scalar_series(d) for f, d in draws.items()}
    names = list(dict.fromkeys(n for s in series.values() for n in s))[:POSTERIOR_PANELS]
    true = {} if truth is None else scalar_series({k: v.reshape(1, 1, *v.shape) for k, v in truth.items()})
    colour = colours([{"filter": f} for f in draws])
    hist, axes = plt.subplots(1, len(names), figsize=(3.6 * len(names), 3.0), squeeze=False)
    for ax, n in zip(axes[0], names):
        for f, s in series.items():
            if n in s:
                ax.hist(s[n].reshape(-1).numpy(), bins=40, density=True, alpha=0.45, color=colour[f], label=f)
        if n in true:
            ax.axvline(float(true[n].reshape(-1)[0]), color="black", lw=1.2, label="truth")
            _include(ax, float(true[n].reshape(-1)[0]), "x")
        ax.set_xlabel(n)
        ax.set_ylabel("posterior density")
    axes[0][-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1))
    hist.suptitle(title, fontsize=9)
    hist.tight_layout()
    trace, taxes = plt.subplots(len(series), len(names), figsize=(3.6 * len(names), 2.4 * len(series)), squeeze=False)
    for row, (f, s) in zip(taxes, series.items()):
        for ax, n in zip(row, names):
            if n in s:
                for c in range(s[n].shape[0]):
                    ax.plot(range(1, s[n].shape[1] + 1), s[n][c].numpy(), lw=0.6, alpha=0.8)
            if n in true:
                ax.axhline(float(true[n].reshape(-1)[0]), color="black", lw=1.0)
                _include(ax, float(true[n].reshape(-1)[0]), "y")
            ax.set_title(f"{f}: {n}", fontsize=8)
            ax.set_xlabel("iteration (after adaptation)")
    trace.suptitle(title + ", one line per chain", fontsize=9)
    trace.tight_layout()
    return hist, trace


def save_posterior_figures(out: Path, draws, truth, title: str) -> List[Path]:
    """``posterior.png`` and ``traces.png`` (:func:`posterior_figures`) in ``out``."""
    plt = pyplot()
    if plt is None:
        return []
    paths = []
    for name, fig in zip(("posterior.png", "traces.png"), posterior_figures(plt, draws, truth, title)):
        try:
            save_figure(fig, Path(out) / name, dpi=100, bbox_inches="tight")  # the legend beside the last panel
        finally:
            plt.close(fig)
        paths.append(Path(out) / name)
    return paths


def save_run_figures(out: Path, model, result, model_name: str) -> List[Path]:
    """``per_step.png``, and for tracking models ``tracks.png`` and ``omat_box.png``, for 3-D
    localisation (a model with receivers) ``scene.png``, of a run; on recorded data (no truth)
    ``per_step.png`` (the ESS) and ``estimates.png`` (:func:`estimates_figure`); the paths written."""
    plt = pyplot()
    if plt is None or not result.per_step:
        return []
    n, res, paths = result.config.get("trials", len({r["trial"] for r in result.per_trial})), result, []
    figs = {"per_step.png": lambda: per_step_figure(plt, res.per_step, res.summary, f"{model_name}, {n} trials")}
    truth = res.trajectory is not None and res.trajectory.states is not None
    if res.recorded:
        figs["estimates.png"] = lambda: estimates_figure(
            plt, res.estimate_summary, res.summary, f"{model_name}: recorded data, mean and spread over {n} trials"
        )
    if hasattr(model, "receivers") and truth:
        figs["scene.png"] = lambda: scene_figure(
            plt, model, res.trajectory, res.examples, res.summary, f"{model_name}: run 0, true and declared sources"
        )
    elif model.structure.has_positions and truth:
        figs["tracks.png"] = lambda: tracks_figure(
            plt, model, res.trajectory, res.examples, res.summary, f"{model_name}: trial 0, true and estimated tracks"
        )
        figs["omat_box.png"] = lambda: omat_box_figure(
            plt, res.per_trial, res.summary, f"{model_name}: per-trial OMAT against time per step, {n} trials"
        )
    for name, draw in figs.items():
        fig = draw()
        if fig is not None:
            try:
                save_figure(fig, Path(out) / name, dpi=110, bbox_inches="tight" if name == "tracks.png" else None)
            finally:
                plt.close(fig)
            paths.append(Path(out) / name)
    return paths
