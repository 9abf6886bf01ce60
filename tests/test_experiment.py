"""The Monte Carlo runner and the Hydra command line."""
import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from torchflow.experiment import SUMMARY_COLUMNS, choose_chunk_size, format_table, run_experiment
from torchflow.filters import BootstrapParticleFilter, ExtendedKalmanFilter, Filter, KalmanFilter, UnscentedKalmanFilter
from torchflow.models import AcousticTracking, SensorNetwork

ROOT = Path(__file__).resolve().parents[1]


class _Broken(Filter):
    def init(self, mean, cov, n_particles=None, generator=None):
        raise RuntimeError("deliberately broken")


def test_runner_lg_rows_and_reference_evidence():
    model = SensorNetwork(d=16)
    filters = {"kf": KalmanFilter(model), "bpf": BootstrapParticleFilter(model, n_particles=100),
               "broken": _Broken(model)}
    seen = []
    res = run_experiment(model, filters, trials=6, steps=4, seed=3, progress=False,
                         on_filter_done=lambda rows: seen.append([r["filter"] for r in rows]))
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
    a = run_experiment(model, {"bpf": BootstrapParticleFilter(model, n_particles=50)}, trials=3, steps=3,
                       dtype="float32", progress=False)
    b = run_experiment(model, {"kf": KalmanFilter(model), "bpf": BootstrapParticleFilter(model, n_particles=50)},
                       trials=3, steps=3, dtype="float32", progress=False)
    assert a.config["dtype"] == "float32"
    assert a.summary[0]["mse"] == b.summary[1]["mse"]


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
    filters = {"pfpf_ledh": ParticleFlowParticleFilter(model, flow="ledh", n_particles=4000),
               "pfpf_edh": ParticleFlowParticleFilter(model, flow="edh", n_particles=4000),
               "ekf": ExtendedKalmanFilter(model)}
    res = run_experiment(model, filters, trials=5, steps=1, progress=False)
    assert res.config["chunk_size"] == {"pfpf_ledh": 2, "pfpf_edh": 5, "ekf": 5}


def _cli(tmp_path, *args):
    cmd = [sys.executable, str(ROOT / "experiments" / "run.py"), *args, "progress=false", "plots=false"]
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    return out


def test_cli_run_writes_results(tmp_path):
    out = _cli(tmp_path, "model=linear_gaussian", "model.d=16", "filter=[kf,bpf]", "trials=4", "steps=3",
               "n_particles=50", "seed=0", f"hydra.run.dir={tmp_path}/run")
    assert "| kf |" in out.stdout and "| bpf |" in out.stdout
    run = tmp_path / "run"
    with open(run / "summary.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["filter"] for r in rows] == ["kf", "bpf"]
    for col in ("filter", "n_particles", "trials", "steps", "mse", "omat", "ospa", "ess", "log_evidence",
                "lost_tracks", "sec_per_step"):
        assert col in rows[0]
    assert rows[0]["ess"] == "" and float(rows[1]["ess"]) > 0 and rows[1]["n_particles"] == "50"
    with open(run / "per_step.csv") as fh:
        assert len(list(csv.DictReader(fh))) == 2 * 3
    data = json.loads((run / "results.json").read_text())
    assert data["config"]["trials"] == 4 and len(data["summary"]) == 2


def test_cli_multirun_sweep_writes_one_folder_per_job(tmp_path):
    _cli(tmp_path, "-m", "model=linear_gaussian", "model.d=4", "filter=[kf]", "trials=2", "steps=2",
         "seed=0,1", f"hydra.sweep.dir={tmp_path}/sweep")
    jobs = sorted(p.name for p in (tmp_path / "sweep").iterdir() if p.is_dir())
    assert jobs == ["0", "1"]
    for j in jobs:
        assert (tmp_path / "sweep" / j / "summary.csv").exists()
    # the collector gathers both jobs with their overrides; a job without results is reported
    (tmp_path / "sweep" / "2").mkdir()
    out = subprocess.run([sys.executable, str(ROOT / "experiments" / "collect.py"), str(tmp_path / "sweep")],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("| ")]
    assert lines[0].startswith("| job | seed | filter") and len(lines) == 3
    assert "jobs without summary.csv" in out.stderr and "2" in out.stderr
    with open(tmp_path / "sweep" / "sweep_summary.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["job"], r["seed"], r["filter"]) for r in rows] == [("0", "0", "kf"), ("1", "1", "kf")]
