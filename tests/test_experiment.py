"""The Monte Carlo runner and the Hydra command line."""

import csv
import json
import math
import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import torch

from torchflow.app.cli import row_label
from torchflow.app.runner import SUMMARY_COLUMNS, choose_chunk_size, figures, format_table, run_experiment
from torchflow.filters import BootstrapParticleFilter, ExtendedKalmanFilter, Filter, KalmanFilter, UnscentedKalmanFilter
from torchflow.models import AcousticTracking, SensorNetwork

ROOT = Path(__file__).resolve().parents[1]


class _Broken(Filter):
    def init(self, mean, cov, n_particles=None, generator=None):
        raise RuntimeError("deliberately broken")


def test_runner_lg_rows_and_reference_evidence():
    model = SensorNetwork(d=16)
    filters = {
        "kf": KalmanFilter(model),
        "bpf": BootstrapParticleFilter(model, n_particles=100),
        "broken": _Broken(model),
    }
    seen = []
    res = run_experiment(
        model,
        filters,
        trials=6,
        steps=4,
        seed=3,
        progress=False,
        on_filter_done=lambda rows: seen.append([r["filter"] for r in rows]),
    )
    assert seen == [["kf"], ["kf", "bpf"], ["kf", "bpf", "broken"]]
    rows = {r["filter"]: r for r in res.summary}
    assert set(rows) == {"kf", "bpf", "broken"}
    assert rows["kf"]["log_evidence_relmse"] == 0.0 and rows["kf"]["ess"] is None
    assert rows["bpf"]["ess"] is not None and rows["bpf"]["log_evidence_relmse"] > 0
    assert rows["bpf"]["mse"] > rows["kf"]["mse"]
    assert "deliberately broken" in rows["broken"]["error"] and rows["broken"]["mse"] is None
    assert all(set(SUMMARY_COLUMNS) == set(r) for r in res.summary)
    assert len(res.per_trial) == 2 * 6 and len(res.per_step) == 2 * 4
    table = format_table(res.summary)
    assert "| kf |" in table and "omat" not in table  # empty columns dropped


def test_runner_chunking_does_not_change_deterministic_filters():
    model = SensorNetwork(d=16)
    a = run_experiment(model, {"kf": KalmanFilter(model)}, trials=7, steps=3, progress=False)
    b = run_experiment(model, {"kf": KalmanFilter(model)}, trials=7, steps=3, chunk_size=3, progress=False)
    assert b.config["chunk_size"] == {"kf": 3}
    assert [r["mse"] for r in a.per_trial] == pytest.approx([r["mse"] for r in b.per_trial], abs=1e-12)


def test_runner_tracking_metrics_and_inits_per_track():
    model = AcousticTracking()
    filters = {"ekf": ExtendedKalmanFilter(model), "ukf": UnscentedKalmanFilter(model)}
    res = run_experiment(model, filters, trials=6, steps=5, inits_per_track=3, progress=False)
    # trials 0-2 share a trajectory, 3-5 another
    assert torch.equal(res.trajectory.observations[0], res.trajectory.observations[2])
    assert not torch.equal(res.trajectory.observations[0], res.trajectory.observations[3])
    for r in res.summary:
        assert r["omat"] is not None and r["ospa"] is not None and r["lost_tracks"] is not None
        assert r["ospa"] <= r["omat"] + 1e-9  # the cutoff can only lower the distance
    assert {"omat", "ospa", "mse"} <= set(res.per_step[0])


def test_runner_float32_and_filter_seeds_independent_of_other_filters():
    model = SensorNetwork(d=16)
    a = run_experiment(
        model,
        {"bpf": BootstrapParticleFilter(model, n_particles=50)},
        trials=3,
        steps=3,
        dtype="float32",
        progress=False,
    )
    b = run_experiment(
        model,
        {"kf": KalmanFilter(model), "bpf": BootstrapParticleFilter(model, n_particles=50)},
        trials=3,
        steps=3,
        dtype="float32",
        progress=False,
    )
    assert a.config["dtype"] == "float32"
    assert a.summary[0]["mse"] == b.summary[1]["mse"]


def test_runner_warmup_is_untimed_and_moves_no_number():
    """``warmup=True`` (on a GPU: ``"auto"``) makes one untimed call per filter on its first trial
    and reports its seconds as ``warmup_sec``; every trial's numbers stay those of a run without it
    (each trial draws from its own stream). ``"auto"`` on the CPU warms up the filters that take a
    Numba kernel (a flow's, or the particle filters' weighting kernel: their first call compiles or
    loads it), not the others (a jittered resampler is not the kernel's); a bad value is refused."""
    from torchflow.filters import ParticleFlowParticleFilter
    from torchflow.flows.kernels import steps

    model = AcousticTracking()
    filters = lambda: {
        "bpf": BootstrapParticleFilter(model, n_particles=40),
        "jittered": BootstrapParticleFilter(model, n_particles=40, regularization=0.01),
        "ledh": ParticleFlowParticleFilter(model, flow="ledh", n_particles=20),
    }
    plain = run_experiment(model, filters(), trials=3, steps=3, progress=False, warmup=False)
    warm = run_experiment(model, filters(), trials=3, steps=3, progress=False, warmup=True)
    auto = run_experiment(model, filters(), trials=3, steps=3, progress=False)
    assert all(r["warmup_sec"] is None for r in plain.summary)
    assert all(r["warmup_sec"] > 0 for r in warm.summary)
    warmed = {r["filter"]: r["warmup_sec"] is not None for r in auto.summary}
    assert warmed == {"bpf": steps.weights_available(), "jittered": False, "ledh": steps.numba_available()}
    drop = lambda rows: [{k: v for k, v in r.items() if k not in ("sec_per_step", "warmup_sec")} for r in rows]
    assert drop(warm.per_trial) == drop(plain.per_trial) and drop(warm.summary) == drop(plain.summary)
    with pytest.raises(ValueError, match="warmup"):
        run_experiment(model, filters(), trials=1, steps=2, progress=False, warmup="yes")


def test_warm_up_covers_every_chunk_shape_on_a_gpu(monkeypatch, caplog):
    """On a GPU the warm-up calls the filter once per distinct chunk size (two steps each), so that
    no CUDA graph capture or shape-specialised compilation lands in a timed chunk; on the CPU one
    call on one trial. Each says what it does in the log."""
    import logging
    import types

    from torchflow.app.runner import execute

    calls = []
    monkeypatch.setattr(
        execute, "_timed_call", lambda f, name, plan, s, e, steps=None: calls.append((s, e, steps)) or (None, 0.5)
    )
    chunks = [(0, 20), (20, 40), (40, 50)]
    for device, want in (("cuda", [(0, 20, 2), (0, 10, 2)]), ("cpu", [(0, 1, 2)])):
        calls.clear()
        plan = types.SimpleNamespace(settings=types.SimpleNamespace(device=torch.device(device)))
        with caplog.at_level(logging.INFO, logger="torchflow.app.runner"):
            seconds = execute.warm_up(BootstrapParticleFilter(SensorNetwork(d=4)), "ledh", plan, chunks)
        assert calls == want and seconds == 0.5 * len(want)
        assert "ledh: warming up on " + "/".join(str(e - s) for s, e, _ in want) in caplog.text


def test_a_localiser_warms_up_on_its_whole_data():
    """A one-shot localiser has no time axis to cut to two steps: its warm-up (on a GPU by default)
    runs one trial's whole data and moves no number."""
    from torchflow.models import TDOA3D
    from torchflow.tdoa import BootstrapLocaliser

    model = TDOA3D()
    runs = {
        w: run_experiment(
            model, {"bs": BootstrapLocaliser(model, n_particles=2000)}, trials=1, progress=False, warmup=w
        )
        for w in (False, True)
    }
    assert runs[True].summary[0]["error"] is None and runs[True].summary[0]["warmup_sec"] > 0
    drop = lambda rows: [{k: v for k, v in r.items() if k not in ("sec_per_step", "warmup_sec")} for r in rows]
    assert drop(runs[True].per_trial) == drop(runs[False].per_trial)


def test_runner_errors():
    model = SensorNetwork(d=16)
    with pytest.raises(ValueError, match="dtype"):
        run_experiment(model, {"kf": KalmanFilter(model)}, dtype="float16", progress=False)
    with pytest.raises(ValueError, match="different model"):
        run_experiment(model, {"kf": KalmanFilter(SensorNetwork(d=16))}, progress=False)
    assert choose_chunk_size({"kf": KalmanFilter(model)}, 10, 1e-9) == 1


def test_runner_caps_local_flow_chunks():
    from torchflow.filters import ParticleFlowParticleFilter

    model = AcousticTracking()
    filters = {
        "pfpf_ledh": ParticleFlowParticleFilter(model, flow="ledh", n_particles=4000),
        "pfpf_edh": ParticleFlowParticleFilter(model, flow="edh", n_particles=4000),
        "ekf": ExtendedKalmanFilter(model),
    }
    res = run_experiment(model, filters, trials=5, steps=1, progress=False)
    assert res.config["chunk_size"] == {"pfpf_ledh": 2, "pfpf_edh": 5, "ekf": 5}


def _cli(tmp_path, *args):
    cmd = [sys.executable, str(ROOT / "experiments" / "run.py"), *args, "progress=false", "plots=false"]
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    return out


def _not_the_default_threads():
    """A thread count a command would not use unprompted (its default: OMP_NUM_THREADS, one under
    pytest-xdist, else the usable cores), so that a run using it shows the knob reached torch."""
    return 2 if os.environ.get("OMP_NUM_THREADS") == "1" else 1


def test_cli_run_writes_results(tmp_path):
    out = _cli(
        tmp_path,
        "model=linear_gaussian",
        "model.d=16",
        "filter=[kf,bpf]",
        "trials=4",
        "steps=3",
        "n_particles=50",
        "seed=0",
        f"hydra.run.dir={tmp_path}/run",
        "tuning.cache_bytes_per_call=4096",
        f"threads={_not_the_default_threads()}",
    )
    assert "| kf |" in out.stdout and "| bpf |" in out.stdout
    assert "(the columns: docs/guide/command-line.md#the-summary-columns)" in out.stdout  # under the table
    run = tmp_path / "run"
    with open(run / "summary.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["filter"] for r in rows] == ["kf", "bpf"]
    for col in (
        "filter",
        "n_particles",
        "trials",
        "steps",
        "mse",
        "omat",
        "ospa",
        "ess",
        "log_evidence",
        "lost_tracks",
        "sec_per_step",
    ):
        assert col in rows[0]
    assert rows[0]["ess"] == "" and float(rows[1]["ess"]) > 0 and rows[1]["n_particles"] == "50"
    with open(run / "per_step.csv") as fh:
        assert len(list(csv.DictReader(fh))) == 2 * 3
    data = json.loads((run / "results.json").read_text())
    assert data["config"]["trials"] == 4 and len(data["summary"]) == 2
    # the speed knob reached the runner: one trial per chunk (4096 bytes < one 50 x 16 state)
    assert data["config"]["tuning"]["cache_bytes_per_call"] == 4096 and data["run"]["chunk_size"]["bpf"] == 1
    assert data["run"]["threads"] == _not_the_default_threads()  # the threads knob reached torch


def test_job_threads(monkeypatch):
    """threads: given; else OMP_NUM_THREADS's (torch follows it: None); else the usable cores (outside a
    sweep, one job); a bad value is one line."""
    import os

    from torchflow.app.cli import job_threads
    from torchflow.app.runner import ConfigError

    assert job_threads(3) == 3
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert job_threads(None) is None
    monkeypatch.delenv("OMP_NUM_THREADS")
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assert job_threads(None) == cores
    for bad in (0, -2, 1.5, True, "4"):
        with pytest.raises(ConfigError, match="threads: expected a positive number of threads or null"):
            job_threads(bad)


def test_cli_multirun_sweep_writes_one_folder_per_job(tmp_path):
    _cli(
        tmp_path,
        "-m",
        "model=linear_gaussian",
        "model.d=4",
        "filter=[kf]",
        "trials=2",
        "steps=2",
        "seed=0,1",
        f"hydra.sweep.dir={tmp_path}/sweep",
    )
    jobs = sorted(p.name for p in (tmp_path / "sweep").iterdir() if p.is_dir())
    assert jobs == ["0", "1"]
    for j in jobs:
        assert (tmp_path / "sweep" / j / "summary.csv").exists()
    # the collector gathers both jobs with their overrides; a job without results is reported
    (tmp_path / "sweep" / "2").mkdir()
    out = subprocess.run(
        [sys.executable, str(ROOT / "experiments" / "collect.py"), str(tmp_path / "sweep")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("| ")]
    assert lines[0].startswith("| job | seed | filter") and len(lines) == 3
    assert "job 2 has no results (still running, killed, or never started)" in out.stdout
    with open(tmp_path / "sweep" / "sweep_summary.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["job"], r["seed"], r["filter"]) for r in rows] == [("0", "0", "kf"), ("1", "1", "kf")]
    # --plot: Y against X with standard-error bars from each job's per-trial file; a wrong column is refused
    from experiments.collect import collect

    got, cols, _ = collect(tmp_path / "sweep")
    # every summary column a job filled, in the summary's order: rmse and log_evidence among them, empty ones not
    summary_header = next(csv.reader(open(tmp_path / "sweep" / "0" / "summary.csv")))
    filled = [c for c in summary_header if c not in ("filter", "n_particles", "trials") and got[0].get(c)]
    assert cols == ["job", "seed", "filter", "trials", *filled] and {"rmse", "log_evidence", "mse"} <= set(cols)
    assert "omat" not in cols  # empty for this model
    per = list(csv.DictReader(open(tmp_path / "sweep" / "0" / "per_trial.csv")))
    mses = [float(r["mse"]) for r in per]
    se = (sum((m - sum(mses) / 2) ** 2 for m in mses) / 1 / 2) ** 0.5
    assert abs(float(got[0]["mse_se"]) - se) < 1e-12
    cmd = [sys.executable, str(ROOT / "experiments" / "collect.py"), str(tmp_path / "sweep")]
    out = subprocess.run(cmd + ["--plot", "seed:mse"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "sweep" / "mse_vs_seed.png").exists()
    out = subprocess.run(cmd + ["--plot", "seed:nope"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "no column 'nope'" in out.stderr


def test_per_step_plot_keeps_one_colour_per_filter_and_scales_ess_by_n():
    plt = pytest.importorskip("matplotlib.pyplot")
    model = AcousticTracking()
    filters = {
        "ekf": ExtendedKalmanFilter(model),
        "ukf": UnscentedKalmanFilter(model),
        "bpf": BootstrapParticleFilter(model, n_particles=40),
    }
    res = run_experiment(model, filters, trials=2, steps=3, progress=False)
    fig = figures.per_step_figure(plt, res.per_step, res.summary, "t")
    colours = {}
    for ax in fig.axes:
        for line in ax.get_lines():
            colours.setdefault(line.get_label(), set()).add(line.get_color())
    assert set(colours) == {"ekf", "ukf", "bpf"}
    assert all(len(c) == 1 for c in colours.values())  # the same colour on every panel
    assert len({next(iter(c)) for c in colours.values()}) == 3  # and different filters differ
    ess_ax = [ax for ax in fig.axes if "ESS" in ax.get_ylabel()][0]
    assert ess_ax.get_ylabel() == "ESS / N (N = 40)"
    assert [ln.get_label() for ln in ess_ax.get_lines()] == ["bpf"]
    assert "ekf, ukf" in ess_ax.get_title()
    y = ess_ax.get_lines()[0].get_ydata()
    assert (y > 0).all() and (y <= 1).all()
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["ekf", "ukf", "bpf"]
    plt.close(fig)


def test_row_label_names_the_flow_that_ran():
    from torchflow.filters import ParticleFlowFilter, ParticleFlowParticleFilter

    model = SensorNetwork(d=4)
    assert row_label("pfpf_ledh", ParticleFlowParticleFilter(model, flow="edh")) == "pfpf_ledh[flow=edh]"
    assert row_label("pfpf_ledh", ParticleFlowParticleFilter(model, flow="ledh")) == "pfpf_ledh"
    assert row_label("gromov", ParticleFlowFilter(model, flow="gromov")) == "gromov"
    assert row_label("bpf", BootstrapParticleFilter(model)) == "bpf"
    from torchflow.filters import ClusteredParticleFlowParticleFilter

    assert row_label("pfpf_clustered", ClusteredParticleFlowParticleFilter(model)) == "pfpf_clustered"
    assert row_label("pfpf_clustered_k30", ClusteredParticleFlowParticleFilter(model)) == "pfpf_clustered_k30"
    assert (
        row_label("pfpf_clustered", ClusteredParticleFlowParticleFilter(model, flow="geodesic"))
        == "pfpf_clustered[flow=geodesic]"
    )


def test_runner_keeps_finished_filters_on_interrupt():
    class _Interrupt(Filter):
        def init(self, mean, cov, n_particles=None, generator=None):
            raise KeyboardInterrupt

    model = SensorNetwork(d=4)
    res = run_experiment(
        model,
        {"kf": KalmanFilter(model), "stop": _Interrupt(model), "bpf": BootstrapParticleFilter(model, n_particles=10)},
        trials=3,
        steps=2,
        progress=False,
    )
    assert res.interrupted and res.not_run == ["bpf"]
    assert [r["filter"] for r in res.summary] == ["kf", "stop"]
    assert res.summary[1]["error"] == "interrupted after 0 of 3 trials"
    assert len(res.per_trial) == 3 and res.examples["kf"].shape == (2, 4)


def test_cli_ctrl_c_writes_finished_results(tmp_path):
    """SIGINT while the second filter runs: exit 130, one line, every file for the first filter."""
    import signal
    import time

    cmd = [
        sys.executable,
        str(ROOT / "experiments" / "run.py"),
        "model=linear_gaussian",
        "filter=[kf,bpf]",
        "trials=200",
        "steps=200",
        "n_particles=20000",
        "progress=false",
        f"hydra.run.dir={tmp_path}/run",
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    summary, partial = tmp_path / "run" / "summary.csv", tmp_path / "run" / "summary.partial.csv"
    deadline = time.time() + 120
    while not partial.exists() and time.time() < deadline and proc.poll() is None:  # the first filter is done
        time.sleep(0.2)
    assert partial.exists(), proc.communicate()[1][-2000:]
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-2000:]
    assert "Traceback" not in err and "interrupted by Ctrl-C" in err and "resume=true" in err
    for name in ("summary.csv", "per_step.csv", "per_trial.csv", "results.json"):
        assert (tmp_path / "run" / name).exists(), name
    assert not partial.exists()  # the interrupted run's own summary.csv replaces it
    rows = list(csv.DictReader(open(summary)))
    assert [r["filter"] for r in rows] == ["kf", "bpf"] and rows[1]["error"].startswith("interrupted after")
    assert json.loads((tmp_path / "run" / "results.json").read_text())["interrupted"] is True


def test_omat_box_figure_one_box_per_filter():
    plt = pytest.importorskip("matplotlib.pyplot")
    model = AcousticTracking()
    filters = {"ekf": ExtendedKalmanFilter(model), "bpf": BootstrapParticleFilter(model, n_particles=40)}
    res = run_experiment(model, filters, trials=3, steps=2, progress=False)
    fig = figures.omat_box_figure(plt, res.per_trial, res.summary, "t")
    ax = fig.axes[0]
    assert ax.get_xscale() == "log" and [t.get_text() for t in ax.get_legend().get_texts()] == ["ekf", "bpf"]
    plt.close(fig)


def test_row_label_names_overridden_points():
    from torchflow.filters import ParticleFlowParticleFilter

    model = SensorNetwork(d=4)
    assert (
        row_label("pfpf_ledh", ParticleFlowParticleFilter(model, flow="ledh", points="global"))
        == "pfpf_ledh[points=global]"
    )
    assert (
        row_label("pfpf_edh", ParticleFlowParticleFilter(model, flow="ledh", points="particle"))
        == "pfpf_edh[flow=ledh]"
    )
    assert (
        row_label("pfpf_edh", ParticleFlowParticleFilter(model, flow="edh", points="clustered"))
        == "pfpf_edh[points=clustered]"
    )


def test_row_label_of_gaussian_sum_filters_says_n_star_x_g_and_an_unnamed_flow():
    from torchflow.filters import GaussianSumParticleFilter, ParticleFlowGaussianSumParticleFilter

    model = SensorNetwork(d=4)
    gs = GaussianSumParticleFilter
    assert (
        row_label("pfgspf", ParticleFlowGaussianSumParticleFilter(model, n_components=3, particles_per_component=50))
        == "pfgspf[50x3]"
    )
    assert row_label("gspf", gs(model, n_components=2, particles_per_component=10)) == "gspf[10x2]"
    assert row_label("gspf", gs(model, particles_per_component=10, flow="ledh")) == "gspf[10x1,flow=ledh]"
    assert row_label("pfgspf", gs(model, particles_per_component=10, flow="edh")) == "pfgspf[10x1,flow=edh]"


def test_trial_stats_quartiles_and_paired_ratios(tmp_path):
    """experiments/trial_stats.py on a hand-made run: medians, the lost count and the paired ratio."""
    from experiments.trial_stats import main, trial_table

    ref = [1.0, 2.0, 3.0, 4.0, 5.0]
    other = [2 * v for v in ref]
    with open(tmp_path / "per_trial.csv", "w") as fh:
        fh.write("filter,trial,omat,lost\n")
        for name, vals in (("pfpf_ledh", ref), ("clustered", other)):
            for b, v in enumerate(vals):
                fh.write(f"{name},{b},{v},{v > 4}\n")
    with open(tmp_path / "summary.csv", "w") as fh:
        fh.write("filter,sec_per_step\npfpf_ledh,0.2\nclustered,0.05\n")
    rows, ratios = trial_table(tmp_path, resamples=200)
    by = {r["filter"]: r for r in rows}
    assert by["pfpf_ledh"]["median"] == 3.0 and by["clustered"]["median"] == 6.0
    assert by["pfpf_ledh"]["lost"] == 1 and by["clustered"]["lost"] == 3
    assert by["clustered"]["time_ratio"] == 0.25
    # every paired resample doubles the median exactly
    assert ratios[0]["ratio"] == 2.0 and ratios[0]["lo"] == 2.0 and ratios[0]["hi"] == 2.0
    assert main([str(tmp_path / "nope")]) == 2


def test_trial_stats_groups_trials_that_share_a_trajectory(tmp_path):
    """--group K: the mean's SE and the paired difference's SE come from the K-trial group means,
    the bootstrap resamples whole groups, and a filter without the metric has no row."""
    from experiments.trial_stats import main, mean_se, trial_table

    # two trajectories x 3 initialisations: trials agree within a trajectory, differ between them
    ref = [1.0, 1.1, 0.9, 3.0, 3.1, 2.9]
    other = [v + d for v, d in zip(ref, [0.5, 0.5, 0.5, 1.5, 1.5, 1.5])]
    with open(tmp_path / "per_trial.csv", "w") as fh:
        fh.write("filter,trial,ospa,ess,lost\n")
        for name, vals in (("pfpf_ledh", ref), ("gromov", other), ("ekf", ref)):
            for b, v in enumerate(vals):
                fh.write(f"{name},{b},{v},{'' if name == 'ekf' else 10 + b},False\n")
    with open(tmp_path / "summary.csv", "w") as fh:
        fh.write("filter,sec_per_step\npfpf_ledh,0.2\ngromov,0.1\nekf,0.001\n")
    rows, ratios = trial_table(tmp_path, metric="ospa", resamples=200, group=3)
    by = {r["filter"]: r for r in rows}
    # group means 1.0 and 3.0: SE = sd(1, 3) / sqrt(2) = 1.0; the per-trial SE would be 0.45
    assert by["pfpf_ledh"]["mean_se"] == pytest.approx(1.0)
    assert mean_se(ref, 1) == pytest.approx(0.4487, abs=1e-4)
    (g,) = [r for r in ratios if r["filter"] == "gromov"]
    assert g["diff"] == pytest.approx(1.0) and g["diff_se"] == pytest.approx(0.5)
    # resampling whole groups: every bootstrap median is a median of trials 0-2 and/or 3-5
    assert 0.0 < by["pfpf_ledh"]["median_se"] < 2.0
    rows, _ = trial_table(tmp_path, metric="ess", resamples=50, group=3)
    assert {r["filter"] for r in rows} == {"pfpf_ledh", "gromov"}
    # a short last group (5 trials in groups of 2) is its own group
    assert mean_se([1.0, 1.0, 3.0, 3.0, 5.0], 2) == pytest.approx(1.1547, abs=1e-4)
    with pytest.raises(ValueError, match="group"):
        trial_table(tmp_path, group=0)
    assert main([str(tmp_path), "--metric", "ospa", "--group", "0"]) == 2
    assert main([str(tmp_path), "--metric", "nope"]) == 2  # no filter has it: one line, exit 2


def test_trial_stats_pairs_a_filter_across_two_runs(tmp_path):
    """--against: each filter against itself in another run of the same trials (two arithmetic
    settings): paired mean difference, its SE over group means, and the count of trials that differ."""
    from experiments.trial_stats import main, paired_runs

    a, b = tmp_path / "a", tmp_path / "b"
    for run, shift in ((a, [0.0, 0.0, 0.2, 0.4]), (b, [0.0] * 4)):
        run.mkdir()
        with open(run / "per_trial.csv", "w") as fh:
            fh.write("filter,trial,omat,ess\n")
            for t, s in enumerate(shift):
                fh.write(f"pfpf_ledh,{t},{1.0 + t + s},{'' if run is b and t == 0 else 5.0}\n")
        (run / "summary.csv").write_text("filter,sec_per_step\npfpf_ledh,0.1\n")
    rows = paired_runs(a, b, group=2)
    (om,) = [r for r in rows if r["metric"] == "omat"]
    assert om["diff"] == pytest.approx(0.15) and om["changed"] == 2 and om["n"] == 4
    assert om["diff_se"] == pytest.approx(0.15)  # group means of the differences 0 and 0.3: sd 0.212 / sqrt 2
    assert not [r for r in rows if r["metric"] == "ess"]  # a missing value in one run: no row
    assert main([str(a), "--against", str(b)]) == 0
    assert main([str(a), "--against", str(tmp_path / "nope")]) == 2


def test_cli_tdoa_runs_localisers_and_refuses_filters(tmp_path):
    """model=tdoa runs Zhang et al.'s (2024) localisers (table, per-run CSV, OSPA within [0, cut-off]) and
    refuses a state-space filter with a one-line error."""
    out = _cli(
        tmp_path,
        "model=tdoa",
        "filter=[pfi_s,bs]",
        "trials=2",
        "filter.pfi_s.n_components=5",
        "filter.pfi_s.samples_per_component=20",
        "filter.bs.n_particles=500",
        f"hydra.run.dir={tmp_path}/t",
    )
    assert "| pfi_s |" in out.stdout and "| bs |" in out.stdout
    rows = list(csv.DictReader(open(tmp_path / "t" / "per_trial.csv")))
    assert len(rows) == 4 and all(0 <= float(r["ospa"]) <= 40 for r in rows)
    assert (tmp_path / "t" / "summary.csv").exists() and (tmp_path / "t" / "per_step.csv").exists()
    cmd = [
        sys.executable,
        str(ROOT / "experiments" / "run.py"),
        "model=tdoa",
        "filter=[bpf]",
        "progress=false",
        f"hydra.run.dir={tmp_path}/u",
    ]
    bad = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert bad.returncode == 2 and "filter.bpf: BootstrapParticleFilter cannot run on TDOA3D" in bad.stderr


def test_trial_range_reruns_rows_of_a_longer_run():
    """trial_range=[2, 5] of a 6-trial run: the same data and draws as trials 2-4 of the whole run."""
    from torchflow.models import SensorNetwork

    model = SensorNetwork(d=9)
    make = lambda: {"bpf": BootstrapParticleFilter(model, n_particles=30)}
    full = run_experiment(model, make(), trials=6, steps=3, seed=3, progress=False)
    part = run_experiment(model, make(), trials=6, steps=3, seed=3, progress=False, trial_range=[2, 5])
    assert part.per_trial == full.per_trial[2:5] and part.summary[0]["trials"] == 3
    assert part.config["trial_range"] == [2, 5] and part.trajectory.states.shape[0] == 3
    # the Kalman reference of a linear model covers exactly the range, for any chunking
    kw = dict(trials=6, steps=3, seed=3, progress=False)
    whole = run_experiment(model, {"kf": KalmanFilter(model)}, **kw)
    sub = run_experiment(model, {"kf": KalmanFilter(model)}, chunk_size=2, trial_range=[0, 3], **kw)
    assert [r["trial"] for r in sub.per_trial] == [0, 1, 2] and sub.summary[0]["log_evidence_relmse"] is not None
    for a, b in zip(sub.per_trial, whole.per_trial):
        assert a["mse"] == pytest.approx(b["mse"], rel=1e-12) and a["log_evidence"] == pytest.approx(b["log_evidence"])
    for bad in ([3, 3], [0, 7], [-1, 2], [1.5, 3], "ab", 4):
        with pytest.raises(
            ValueError, match=r"trial_range: expected \[start, stop\] with 0 <= start < stop <= trials = 6"
        ):
            run_experiment(model, make(), trials=6, steps=3, progress=False, trial_range=bad)


def test_comandur2022_table2_report_pairs_runs_with_g1(tmp_path, capsys):
    """experiments/comandur2022_table2_report.py: per-G statistics, the paired difference to G = 1 on the
    runs both have (its SE from the per-run differences), --trials, and the distance to the paper."""
    from experiments.comandur2022_table2_report import PAPER, main, read_runs, table

    g1 = {0: 1.0, 1: 2.0, 2: 3.0, 3: 4.0}
    g5 = {0: 0.9, 1: 1.7, 2: 2.9, 5: 9.0}  # run 3 missing, run 5 has no G = 1 partner
    for g, runs in ((1, g1), (5, g5)):
        with open(tmp_path / f"per_trial_G{g}.csv", "w") as fh:
            fh.write("filter,trial,ess,g_eff,log_evidence,mse\n")
            for t, v in runs.items():
                fh.write(f"pfgspf,{t},1,{1 + 0.5 * (g > 1) * t},0,{v}\n")
    rows = {r["G"]: r for r in table(read_runs(tmp_path))}
    assert rows[1]["n"] == 4 and rows[1]["mse"] == pytest.approx(2.5) and rows[1]["median"] == pytest.approx(2.5)
    assert rows[1]["se"] == pytest.approx(math.sqrt(5 / 3) / 2)
    # paired on runs 0-2: differences -0.1, -0.3, -0.1
    assert rows[5]["diff_n"] == 3 and rows[5]["diff"] == pytest.approx(-0.5 / 3)
    assert rows[5]["diff_se"] == pytest.approx(math.sqrt((2 * (0.2 / 3) ** 2 + (0.4 / 3) ** 2) / 2) / math.sqrt(3))
    assert rows[5]["g_eff"] == pytest.approx(1 + 0.5 * (0 + 1 + 2 + 5) / 4)
    pm, psd = PAPER[5]
    assert rows[5]["z"] == pytest.approx((rows[5]["mse"] - pm) / math.hypot(rows[5]["se"], psd / 10))
    kept = {r["G"]: r for r in table(read_runs(tmp_path, (0, 2)))}
    assert kept[5]["n"] == 2 and kept[5]["diff"] == pytest.approx(-0.2)
    assert main([str(tmp_path), "--trials", "0", "3"]) == 0
    assert "| 200 x 5 | 3 |" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="no per_trial_G"):
        read_runs(tmp_path, (10, 20))


def test_comandur2022_geff_diagnostic_runs_and_pooled_fit_is_shared(capsys):
    """experiments/comandur2022_geff_diagnostic.py: the spy sees the filter's log-weights (so its numbers
    are the filter's), and the pooled control gives every component the same predictive fit."""
    from experiments.comandur2022_geff_diagnostic import PooledFit, main, run
    from torchflow.models import SkewedTPoisson

    own = run(d=4, G=3, n_star=20, trials=2, steps=3, seed=1)
    assert 1.0 <= own["g_eff"] <= 3.0 and 1.0 <= own["ess_j"] <= 20.0 and own["sd_c"] > 0
    model = SkewedTPoisson(d=4).double()
    f = PooledFit(model, n_components=3, particles_per_component=20)
    mean, cov = model.initial_belief(torch.zeros(2, 4, dtype=torch.float64))
    state = f.init(mean, cov, generator=torch.Generator().manual_seed(0))
    _, eta0, mu, L = f.draw(state, torch.Generator().manual_seed(0))
    assert torch.equal(mu[:, 0], mu[:, 2]) and torch.equal(L[:, 0], L[:, 1])
    assert torch.allclose(mu[:, 0], eta0.reshape(2, 60, 4).mean(1))
    assert main(["--d", "4", "--G", "2", "--n-star", "10", "--trials", "1", "--steps", "2", "--fit", "both"]) == 0
    out = capsys.readouterr().out
    assert "| 10 | own |" in out and "| 10 | pooled |" in out


def test_zhang2024_proposal_quality_measures_what_it_says(capsys):
    """experiments/zhang2024_proposal_quality.py: a near-linear case (prior sd 5 m) gives the Gromov
    flow an almost exact proposal (ESS fraction near 1), the explicit Euler step (`start`) of
    EDH overshoots on the coarse (2, 1e-4) grid from the 200 m birth components while the step at
    lambda_l never amplifies, and the command prints both stages."""
    from experiments.zhang2024_proposal_quality import amplification, evaluate, main, make_flow, scenes
    from torchflow.flows.schedules import GeometricSchedule
    from torchflow.models import TDOA3D

    model = TDOA3D()
    gen = torch.Generator().manual_seed(3)
    st = scenes(model, 2, gen)
    coarse = GeometricSchedule(1e-4, 2.0)
    edh = make_flow("pfi_d", None, "-")
    assert float(amplification(edh, model, st["birth"], coarse, "start").max()) > 2.0
    assert float(amplification(edh, model, st["birth"], coarse, "end").max()) <= 1.0 + 1e-9
    near = dict(st["legacy"])
    near["L"] = 5.0 * torch.eye(3, dtype=torch.float64).expand(2, 3, 3)
    near["mean"] = near["mean"] * 0.0 + torch.tensor([100.0, -50.0, 20.0], dtype=torch.float64)
    near["z"] = model.measure(near["mean"] + 2.0, near["sensor"])
    log_ref = torch.zeros(2, dtype=torch.float64)
    good = evaluate(model, near, make_flow("pfi_s", None, "-"), GeometricSchedule(1e-5, 1.5), "end", 400, log_ref, gen)
    assert good["ess"] > 0.95 and good["deg"] == 0.0
    assert main(["--scenes", "1", "--n-samples", "20", "--reference", "50"]) == 0
    out = capsys.readouterr().out
    assert "## birth components (125 rows)" in out and "## legacy components (1 rows)" in out
    assert "| pfi_os a=0.01 | literal_shift |" in out


# --- what a user meets: the faults of the runner, the registry and the harness, as a user sees them ---

_BROKEN = """
from torchflow.filters import KalmanFilter


class Broken(KalmanFilter):
    def forward(self, *a, **kw):
        raise RuntimeError("deliberately broken")


class BadInit(KalmanFilter):
    def __init__(self, *a, **kw):
        raise KeyError("a bug in a constructor")
"""


def _tf(tmp_path, *args, env=None, script=None):
    """The command line in a subprocess (no assertion on the exit status)."""
    env = dict(os.environ if env is None else env, PYTHONPATH=os.pathsep.join([str(ROOT), str(tmp_path)]))
    cmd = [sys.executable, *([str(script)] if script else ["-m", "torchflow"]), *args, "progress=false"]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=300, env=env)


_LG = ["model=linear_gaussian", "model.d=4", "trials=2", "steps=3", "n_particles=20"]


def test_cli_unwritable_checkpoint_dir_warns_once_and_keeps_the_results(tmp_path):
    (tmp_path / "a_file").write_text("")
    out = _tf(
        tmp_path,
        *_LG,
        "filter=[kf,bpf]",
        "chunk_size=1",
        f"checkpoint_dir={tmp_path}/a_file/ckpt",
        "plots=false",
        "hydra.run.dir=run",
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stderr.count("checkpoint_dir: cannot save chunks under") == 1 and "Traceback" not in out.stderr
    rows = list(csv.DictReader(open(tmp_path / "run" / "summary.csv")))
    assert [r["filter"] for r in rows] == ["kf", "bpf"] and all(r["mse"] and not r["error"] for r in rows)
    assert "cannot save chunks" in (tmp_path / "run" / "run.log").read_text()


def test_cli_a_failed_filter_fails_the_run_the_sweep_and_shows_in_collect(tmp_path):
    (tmp_path / "broken_filter.py").write_text(_BROKEN)
    broken = "+filter.broken._target_=broken_filter.Broken"
    out = _tf(tmp_path, *_LG, "filter=[kf]", broken, "plots=false", "checkpoint_dir=null", "hydra.run.dir=run")
    assert out.returncode == 1 and "| kf |" in out.stdout
    assert "!! broken failed in chunk 1 of 1 (trials 0..1): RuntimeError: deliberately broken" in out.stderr
    log = (tmp_path / "run" / "run.log").read_text()
    assert "Traceback" in log and "deliberately broken" in log and "SensorNetwork" in log
    sweep = _tf(
        tmp_path,
        "-m",
        *_LG,
        "filter=[kf]",
        broken,
        "seed=0,1",
        "plots=false",
        "checkpoint_dir=null",
        "hydra.sweep.dir=sweep",
    )
    assert sweep.returncode == 1 and "2 jobs, 0 finished, 2 failed" in sweep.stderr, sweep.stderr[-3000:]
    assert "filter broken failed: RuntimeError: deliberately broken" in sweep.stderr
    col = subprocess.run(
        [sys.executable, str(ROOT / "experiments" / "collect.py"), str(tmp_path / "sweep")],
        capture_output=True,
        text=True,
        timeout=120,
        env=dict(os.environ, PYTHONPATH=str(ROOT)),
    )
    table = [ln for ln in col.stdout.splitlines() if ln.startswith("| ")]
    assert table[0].endswith("| error |")
    assert sum("deliberately broken" in ln for ln in table) == 2 and sum("| kf |" in ln for ln in table) == 2
    # a bad value in one job of a sweep fails that job at its start, the other finishes
    bad = _tf(
        tmp_path,
        "-m",
        *_LG,
        "filter=[kf]",
        "rng_backend=auto,bogus",
        "plots=false",
        "checkpoint_dir=null",
        "hydra.sweep.dir=sweep2",
    )
    assert bad.returncode == 1 and "2 jobs, 1 finished, 1 failed" in bad.stderr, bad.stderr[-3000:]
    assert "rng_backend: expected one of auto, numpy, philox, got 'bogus'" in bad.stderr


def test_cli_configuration_errors_are_one_line_and_bugs_keep_their_traceback(tmp_path):
    (tmp_path / "broken_filter.py").write_text(_BROKEN)
    out = _tf(tmp_path, *_LG, "filter=[kf]", "+n_particle=7", "hydra.run.dir=a")
    assert out.returncode == 2 and "error: n_particle: unknown setting; did you mean n_particles?" in out.stderr
    assert "Traceback" not in out.stderr
    bug = _tf(tmp_path, *_LG, "filter=[kf]", "+filter.bad._target_=broken_filter.BadInit", "hydra.run.dir=b")
    assert bug.returncode == 1 and "Traceback" in bug.stderr and "a bug in a constructor" in bug.stderr
    assert "Traceback" in (tmp_path / "b" / "run.log").read_text()


def test_check_config_refuses_values_that_mean_nothing():
    from hydra import compose, initialize_config_dir

    from torchflow.app.runner import ConfigError
    from torchflow.app.runner.config import check_config

    cases = {
        "plots=no": "plots: expected true or false, got 'no'",
        "metrics.lost_threshold=-1": "metrics.lost_threshold: expected a positive number of metres, got -1",
        "metrics.ospa_cutoff=0": "metrics.ospa_cutoff: expected a positive number, got 0",
        f"seed={2**70}": "seed: expected an integer in [0, 2**63), got 1180591620717411303424",
        "rng_backend=bogus": "rng_backend: expected one of auto, numpy, philox, got 'bogus'",
        "+metrics.lost_treshold=3": (
            "metrics.lost_treshold: unknown setting; did you mean metrics.lost_threshold or metrics.lost_rmse?"
        ),
        "+n_particle=7": "n_particle: unknown setting; did you mean n_particles?",
    }
    with initialize_config_dir(str(ROOT / "configs"), version_base="1.3"):
        check_config(compose("config"), {})
        check_config(compose("config", ["experiment=comandur2022_table2"]), {"experiment": "comandur2022_table2"})
        for override, message in cases.items():
            with pytest.raises(ConfigError, match=re.escape(message)):
                check_config(compose("config", [override]), {})


def test_cli_reused_output_folder_is_refused_or_cleared(tmp_path):
    first = _tf(tmp_path, *_LG, "filter=[kf]", "checkpoint_dir=null", "hydra.run.dir=run")
    assert first.returncode == 0 and (tmp_path / "run" / "per_step.png").exists(), first.stderr[-2000:]
    again = _tf(tmp_path, *_LG, "filter=[kf]", "checkpoint_dir=null", "hydra.run.dir=run")
    assert again.returncode == 2 and "Traceback" not in again.stderr
    assert "error: hydra.run.dir: run already holds the results of a run (summary.csv" in again.stderr
    assert "overwrite=true" in again.stderr
    over = _tf(
        tmp_path, *_LG, "filter=[kf]", "checkpoint_dir=null", "plots=false", "overwrite=true", "hydra.run.dir=run"
    )
    assert over.returncode == 0 and not (tmp_path / "run" / "per_step.png").exists()
    assert (tmp_path / "run" / "summary.csv").exists()


def test_cli_unwritable_output_folder_and_full_disk_are_one_line(tmp_path):
    (tmp_path / "a_file").write_text("")
    ro = _tf(tmp_path, *_LG, "filter=[kf]", "hydra.run.dir=a_file/run")
    assert ro.returncode == 2 and "Traceback" not in ro.stderr
    assert "error: hydra.run.dir: cannot write into" in ro.stderr and "NotADirectoryError" in ro.stderr
    shim = tmp_path / "full_disk.py"
    shim.write_text(
        "import errno\nimport torchflow.app.runner.writers as w\n\n\ndef full(*a, **k):\n"
        "    raise OSError(errno.ENOSPC, 'No space left on device')\n\n\nw.write_csv = full\n"
        "from torchflow.app.cli import main\nmain()\n"
    )
    out = _tf(tmp_path, *_LG, "filter=[kf]", "checkpoint_dir=null", "plots=false", "hydra.run.dir=full", script=shim)
    assert out.returncode == 1 and "| kf |" in out.stdout and "Traceback" not in out.stderr
    errors = [ln for ln in out.stderr.splitlines() if ln.startswith("error:")]
    assert errors == [
        f"error: cannot write summary.partial.csv into {tmp_path / 'full'} (OSError: No space left on device)"
    ]


def test_a_folder_that_turns_read_only_mid_run_leaves_a_summary_marked_partial(tmp_path):
    """F01: the summary written after each filter is ``summary.partial.csv``; ``summary.csv`` is
    written only with the run's other files, after which the partial one goes. A folder that stops
    taking writes after the first filter (here: every write after the first fails) keeps the
    finished filter's row under the partial name and no ``summary.csv`` that looks complete."""
    shim = tmp_path / "read_only_later.py"
    shim.write_text(
        "import errno\nimport torchflow.app.runner.writers as w\n\nreal, calls = w.write_csv, []\n\n\n"
        "def later(*a, **k):\n    calls.append(a[0])\n    if len(calls) > 1:\n"
        "        raise PermissionError(errno.EPERM, 'Operation not permitted')\n    return real(*a, **k)\n\n\n"
        "w.write_csv = later\nfrom torchflow.app.cli import main\nmain()\n"
    )
    args = (*_LG, "filter=[kf,bpf]", "checkpoint_dir=null", "plots=false")
    out = _tf(tmp_path, *args, "hydra.run.dir=ro", script=shim)
    assert out.returncode == 1 and "Traceback" not in out.stderr
    assert f"error: cannot write summary.partial.csv into {tmp_path / 'ro'} (PermissionError" in out.stderr
    assert not (tmp_path / "ro" / "summary.csv").exists()
    with open(tmp_path / "ro" / "summary.partial.csv") as fh:
        assert [r["filter"] for r in csv.DictReader(fh)] == ["kf"]
    done = _tf(tmp_path, *args, "hydra.run.dir=ok")  # a run that ends leaves no partial summary
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "ok" / "summary.csv").exists() and not (tmp_path / "ok" / "summary.partial.csv").exists()


def test_resume_command_of_a_run_a_sweep_and_torchrun():
    from torchflow.app.runner.config import resume_command

    assert (
        resume_command("torchflow", ["-m", "seed=0,1", "filter=[kf]", "resume=false"], {})
        == "torchflow -m seed=0,1 'filter=[kf]' resume=true"
    )
    assert resume_command("python -m torchflow", ["trials=4"], {}) == "python -m torchflow trials=4 resume=true"
    env = {"WORLD_SIZE": "4", "LOCAL_WORLD_SIZE": "2"}
    assert (
        resume_command("python experiments/run.py", ["trials=4"], env)
        == "torchrun --nproc_per_node=2 --nnodes=2 experiments/run.py trials=4 resume=true"
    )
    assert (
        resume_command("torchflow", [], {"WORLD_SIZE": "2"}) == "torchrun --nproc_per_node=2 -m torchflow resume=true"
    )


class _Counting(BootstrapParticleFilter):
    """A bootstrap PF that records the trials of every chunk it computes."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.seen = []

    def forward(self, obs, *a, **kw):
        self.seen.append(obs.shape[0])
        return super().forward(obs, *a, **kw)


def _store_run(model, store, **kw):
    f = _Counting(model, n_particles=30)
    kw.setdefault("warmup", False)  # (the calls counted are the chunks')
    res = run_experiment(model, {"bpf": f}, trials=6, steps=3, seed=2, progress=False, store=store, **kw)
    return res, f


def test_the_warm_up_is_made_only_before_a_chunk_is_computed(tmp_path):
    """Resuming a run whose chunks are all saved computes nothing, not even the warm-up; with one
    chunk lost, the warm-up (one trial) comes before it."""
    from torchflow.app.runner import ChunkStore

    model = SensorNetwork(d=4)
    _store_run(model, ChunkStore(tmp_path, {"bpf": "k"}), chunk_size=3)
    res, f = _store_run(model, ChunkStore(tmp_path, {"bpf": "k"}, resume=True), chunk_size=3, warmup=True)
    assert f.seen == [] and res.summary[0]["warmup_sec"] is None
    (tmp_path / "k" / "0000003-0000006.pt").unlink()
    res, f = _store_run(model, ChunkStore(tmp_path, {"bpf": "k"}, resume=True), chunk_size=3, warmup=True)
    assert f.seen == [1, 3] and res.summary[0]["warmup_sec"] > 0


def test_a_damaged_chunk_file_is_recomputed_with_a_warning(tmp_path):
    from torchflow.app.runner import ChunkStore

    model = SensorNetwork(d=4)
    full, _ = _store_run(model, ChunkStore(tmp_path, {"bpf": "k"}), chunk_size=3)
    path = tmp_path / "k" / "0000000-0000003.pt"
    saved = torch.load(path, weights_only=True)
    raw, needle = bytearray(path.read_bytes()), saved["estimates"].numpy().tobytes()
    at = raw.find(needle)
    assert at > 0
    raw[at + 5] ^= 0x10  # one flipped bit inside the estimates: the file still loads
    path.write_bytes(bytes(raw))
    assert not torch.equal(torch.load(path, weights_only=True)["estimates"], saved["estimates"])
    store = ChunkStore(tmp_path, {"bpf": "k"}, resume=True)
    with pytest.warns(UserWarning, match="damaged"):
        res, f = _store_run(model, store, chunk_size=3)
    assert f.seen == [3] and store.loaded == {"bpf": 1}
    assert res.per_trial == full.per_trial


def test_resume_with_another_chunk_size_reuses_the_saved_trials(tmp_path):
    from torchflow.app.runner import ChunkStore

    model = SensorNetwork(d=4)
    full, _ = _store_run(model, ChunkStore(tmp_path, {"bpf": "k"}), chunk_size=2)
    store = ChunkStore(tmp_path, {"bpf": "k"}, resume=True)
    res, f = _store_run(model, store, chunk_size=3)
    assert f.seen == [] and store.reused_trials == {"bpf": 6} and res.per_trial == full.per_trial
    assert store.computed == {}  # Q84: chunks put together from saved trials are not 'computed'
    (tmp_path / "k" / "0000002-0000004.pt").unlink()  # trials 2, 3 lost: only they are computed
    for p in (tmp_path / "k").glob("0000000-0000003.pt"):
        p.unlink()
    (tmp_path / "k" / "0000003-0000006.pt").unlink()
    store = ChunkStore(tmp_path, {"bpf": "k"}, resume=True)
    res, f = _store_run(model, store, chunk_size=3)
    assert sorted(f.seen) == [1, 1] and store.reused_trials == {"bpf": 4} and res.per_trial == full.per_trial


def test_a_store_that_cannot_write_warns_once_and_the_results_stay():
    from torchflow.app.runner import ChunkStore

    model = SensorNetwork(d=4)
    store = ChunkStore(Path(__file__), {"bpf": "k"})  # a file: no folder can be made under it
    with pytest.warns(UserWarning, match="cannot save chunks") as seen:
        res, _ = _store_run(model, store, chunk_size=1)
    assert len([w for w in seen if "cannot save" in str(w.message)]) == 1
    assert len(res.per_trial) == 6 and res.summary[0]["error"] is None and store.computed == {}


def test_explicit_chunk_over_the_memory_budget_warns():
    """An explicit chunk_size is used as given, but one whose estimate exceeds memory_budget_gb says so
    (a GPU run with chunk_size=100 and 1e6 particles asked for 80 GB in one tensor)."""
    from torchflow.app.runner.plan import filter_chunk
    from torchflow.filters import BootstrapParticleFilter
    from torchflow.models import AcousticTracking

    f = BootstrapParticleFilter(AcousticTracking(), n_particles=1_000_000)
    with pytest.warns(UserWarning, match=r"chunk_size=100: .* GiB per chunk of 100 trials, over memory_budget_gb=100"):
        assert filter_chunk(f, 500, 100, 100.0) == 100
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert filter_chunk(f, 500, 2, 100.0) == 2
