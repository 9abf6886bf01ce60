"""Benchmark-suite plumbing (no timing claims): the harness (timing loop, writer, peer skip path,
filters by name), headline goals, statuses, the flop model and each benchmark on a micro or
``--quick`` configuration."""

import json
import math
import sys
import time

import numpy as np
import pytest
import torch

from experiments.benchmarks import (
    bench_acoustic,
    bench_float32,
    bench_flops,
    bench_foundation,
    bench_gaussian_sum,
    bench_gpu,
    bench_memory,
    bench_pfpf,
    bench_scaling,
    bench_streams,
    bench_sv,
    harness,
    run_all,
)
from torchflow.models import SensorNetwork


# ---- harness ---------------------------------------------------------------------------------
def test_time_calls_counts_warmups_repeats_and_budget():
    calls = []

    def sleepy():
        calls.append(1)
        time.sleep(0.01)
        return len(calls)

    t = harness.time_calls(sleepy, repeats=3, warmup=2)
    assert len(calls) == 5 and len(t.times) == 3 and t.result == 5
    assert 0.009 < t.min <= t.mean <= max(t.times) < 1.0
    calls.clear()
    t = harness.time_calls(sleepy, budget=0.035, max_repeats=50)
    assert sum(t.times) >= 0.035 > sum(t.times[:-1]) and len(t.times) >= 2  # until the budget is spent
    assert len(harness.time_calls(sleepy, budget=10.0, max_repeats=2).times) == 2
    assert len(harness.time_calls(sleepy, budget=0.0).times) == 1  # at least once
    for bad in (dict(repeats=0), dict(warmup=-1), dict(budget=-1.0)):
        with pytest.raises(ValueError, match="time_calls"):
            harness.time_calls(sleepy, **bad)


def test_writer_writes_table_rows_and_json(tmp_path, capsys):
    lines = harness.md_table(["a", "b"], [[1, harness.fmt(None)], ["x", harness.fmt(0.123456, "{:.2f}")]])
    assert lines == ["| a | b |", "|---|---|", "| 1 | - |", "| x | 0.12 |"]
    with pytest.raises(ValueError, match="row has 1 cells"):
        harness.md_table(["a", "b"], [[1]])
    assert harness.fmt(float("nan")) == "-" and harness.fmt(float("inf")) == "inf"
    assert [harness.met_cell(m) for m in (True, False, None)] == ["yes", "NO", "-"]
    res = {"markdown": "\n".join(lines) + "\n", "rows": [{"a": 1}], "args": {"quick": True}}
    md = harness.write_results(res, "demo", out=str(tmp_path / "r.json"))  # a .json --out: markdown beside it
    assert md == tmp_path / "r.md" and md.read_text() == res["markdown"]
    assert json.loads((tmp_path / "r.json").read_text()) == {"rows": [{"a": 1}], "args": {"quick": True}}
    assert harness.results_path("demo", quick=True).name == "results_demo_quick.md"
    assert "| x | 0.12 |" in capsys.readouterr().out


def test_machine_and_command():
    info = harness.machine(command="x")
    assert set(info) >= {
        "platform",
        "processor",
        "cpus",
        "python",
        "torch",
        "numpy",
        "torch_threads",
        "device",
        "load_start",
        "command",
    }
    info["load_end"] = harness.loadavg()
    line = harness.machine_line(info)
    assert line.startswith("Machine: ") and f"{info['cpus']} CPUs" in line and "at end" in line
    assert "numpy ?" in harness.machine_line({"platform": "p", "threads": 3})  # an older results file
    assert harness.command("bench_pfpf", ["--quick"]) == "python -m experiments.benchmarks.bench_pfpf --quick"


def test_peer_skip_path(monkeypatch):
    assert harness.peer("json") is json
    assert harness.peer("no_such_peer_library_xyz") is None
    assert harness.skipped("filterpy").startswith("skipped: filterpy not installed")
    monkeypatch.setitem(sys.modules, "filterpy", None)  # as if not installed
    monkeypatch.setitem(sys.modules, "particles", None)
    res = bench_foundation.run(["--quick"])
    assert [r["status"] for r in res["rows"]] == [harness.skipped("filterpy")] * 2 + [harness.skipped("particles")] * 2
    assert all(r["ratio"] is None and r["met"] is None for r in res["rows"])
    assert res["markdown"].count("skipped: filterpy not installed") == 4  # table and checks, KF and UKF
    assert "| Kalman filter vs filterpy | d=16, B=10, T=5 | skipped: filterpy" in res["markdown"]


def test_foundation_quick_with_peers():
    """Only where filterpy and particles are installed (``pip install -e ".[bench]"``)."""
    pytest.importorskip("filterpy")
    pytest.importorskip("particles")
    res = bench_foundation.run(["--quick", "--particles", "200", "--bpf-trials", "2", "--peer-trials", "1"])
    assert [r["name"] for r in res["rows"]] == [
        "Kalman filter vs filterpy",
        "UKF vs filterpy",
        "Bootstrap PF vs particles",
    ]
    assert all(r["per_ts_ours"] > 0 and r["per_ts_peer"] > 0 and "status" not in r for r in res["rows"])
    assert res["rows"][0]["max_abs_diff_estimates"] < 1e-8 and res["rows"][1]["max_abs_diff_estimates"] < 1e-6


def test_make_filter_by_name():
    model = SensorNetwork(d=4)
    assert type(harness.make_filter("kf", model)).__name__ == "KalmanFilter"
    f = harness.make_filter("pfpf_ledh", model, 7)
    assert type(f).__name__ == "ParticleFlowParticleFilter" and f.n_particles == 7
    assert type(harness.make_filter("flow_gromov", model, 5)).__name__ == "ParticleFlowFilter"
    assert (
        type(harness.make_filter("pfgspf", model, n_components=2, particles_per_component=6)).__name__
        == "ParticleFlowGaussianSumParticleFilter"
    )
    with pytest.raises(ValueError, match="unknown filter 'nope'"):
        harness.make_filter("nope", model)
    with pytest.raises(SystemExit, match="--filters: unknown"):
        harness.keys_option("kf,zz", ["kf"])


def test_filter_chunks_matches_one_call():
    model = SensorNetwork(d=4)
    traj, mean, cov = harness.simulate(model, 5, 3, 0)
    f = harness.make_filter("bpf", model, 20)
    whole = harness.filter_chunks(f, traj.observations, mean, cov, None, harness.streams(1, "bpf"))
    parts = harness.filter_chunks(f, traj.observations, mean, cov, 2, harness.streams(1, "bpf"))
    assert len(whole) == 1 and len(parts) == 3  # per-trial streams: chunking does not change the numbers
    assert torch.allclose(whole[0].estimates, torch.cat([p.estimates for p in parts]))


# ---- reports and goals -----------------------------------------------------------------------
def test_status_and_goal_flags():
    ok = dict(finite=True, position_rmse=3.0, omat=0.6)
    assert bench_acoustic.status(ok) == "tracking"
    assert bench_acoustic.status(dict(ok, omat=9.0)) == "finite, tracks lost"
    assert bench_acoustic.status(dict(finite=True, position_rmse=1e70)) == "diverged"
    assert bench_acoustic.status(dict(finite=False, position_rmse=float("nan"))) == "diverged"
    assert bench_acoustic.status(dict(finite=True, position_rmse=1e70, failures=["step 2"])) == "diverged, then raised"
    assert bench_acoustic.status(dict(status=harness.skipped("stonesoup"))).startswith("skipped")


def test_headline_collects_every_goal():
    results = {
        "foundation": {
            "rows": [
                dict(name="KF", setting="d=64", per_ts_ours=1e-6, per_ts_peer=1e-4, ratio=100.0, goal=50.0, met=True)
            ]
        },
        "acoustic": {
            "rows": [
                dict(
                    name="PF-PF(LEDH) (torchflow)",
                    side="ours",
                    per_ts=0.05,
                    vs_stonesoup_gromov=40.0,
                    vs_stonesoup_gromov_shipped=80.0,
                    goal=30.0,
                    met=True,
                    vs_stonesoup_bootstrap=None,
                ),
                dict(
                    name="BPF (torchflow)",
                    side="ours",
                    per_ts=0.001,
                    vs_stonesoup_gromov=2000.0,
                    vs_stonesoup_gromov_shipped=4000.0,
                    goal=None,
                    met=None,
                    vs_stonesoup_bootstrap=2.0,
                ),
                dict(name="GromovFlowParticleUpdater (Stone Soup)", side="peer", per_ts=4.0),
                dict(name="GromovFlowParticleUpdater (Stone Soup), square root repaired", side="peer", per_ts=2.0),
                dict(name="ParticleUpdater bootstrap (Stone Soup)", side="peer", per_ts=0.002),
            ]
        },
    }
    rows = run_all._headline(results)
    names = [r[0] for r in rows]
    assert names[0] == "KF" and "PF-PF(LEDH) (torchflow) vs Stone Soup Gromov (repaired)" in names
    assert "BPF (torchflow) vs Stone Soup bootstrap" in names
    ledh = rows[names.index("PF-PF(LEDH) (torchflow) vs Stone Soup Gromov (repaired)")]
    assert ledh[3] == 2.0 and ledh[4] == "40.0x" and ledh[5] == ">= 30x" and ledh[6] is True
    shipped = rows[names.index("PF-PF(LEDH) (torchflow) vs Stone Soup Gromov (shipped)")]
    assert shipped[3] == 4.0 and shipped[4] == "80.0x" and shipped[5] is None  # the goal is against the repaired one
    for r in results["acoustic"]["rows"][2:]:  # Stone Soup not installed: no peer columns to compare with
        r["per_ts"] = None
    assert [r[0] for r in run_all._headline(results)] == ["KF"]


def test_headline_has_the_cpu_goals():
    results = {
        "pfpf": {
            "rows": [
                dict(filter="PF-PF(LEDH)", N=500, sec_per_trial_step=0.07, vs_ledh=1.0),
                dict(filter="GPFIS", N=500, sec_per_trial_step=0.7, vs_ledh=10.0),
            ]
        },
        "flops": {
            "rows": [dict(name="PF-PF(LEDH), acoustic, N=500", gflops=3.0), dict(name="gemm_2048", gflops=100.0)]
        },
        "gaussian_sum": {"rows": [dict(key="pfgspf", filter="PFGSPF (200 x 5)", s_per_trial_step=1.5)]},
        "ops": {
            "rows": [
                dict(name="PF-PF(LEDH)", ops=4000, target=1000, met=False),
                dict(name="BPF", ops=130, target=None, met=None),
            ]
        },
    }
    rows = {r[0]: r for r in run_all._headline(results)}
    g = rows["GPFIS time / PF-PF(LEDH) time"]
    assert g[4] == "10.0x" and g[5] == "<= 5x" and g[6] is False
    share = rows["PF-PF(LEDH) GFLOP/s / large-GEMM GFLOP/s"]
    assert share[4] == "3.0%" and share[6] is False
    assert rows["PFGSPF (200 x 5) s/trial-step"][6] is True
    assert rows["PF-PF(LEDH) aten ops per time step"][5] == "<= 1000 ops" and len(rows) == 4  # no goal, no row


def test_pfpf_bench_runs_gpfis_on_its_trial_subset():
    res = bench_pfpf.run(
        ["--trials", "2", "--steps", "1", "--particles", "20", "--filters", "ledh,gpfis", "--gpfis-trials", "1"]
    )
    rows = {r["filter"]: r for r in res["rows"]}
    assert rows["GPFIS"]["trials"] == 1 and rows["PF-PF(LEDH)"]["trials"] == 2
    assert rows["GPFIS"]["goal"] == 5.0 and rows["GPFIS"]["met"] == (rows["GPFIS"]["vs_ledh"] <= 5)


def test_gpu_section_plumbing_on_the_cpu(tmp_path):
    """``run_all --device`` runs the GPU section (here on the CPU, quick sizes): its rows carry the
    speed goals, and the headline collects them."""
    res = run_all.run(["--device", "cpu", "--only", "gpu", "--quick", "--out", str(tmp_path / "all.md")])
    assert not res["failures"], res["failures"]
    rows = res["results"]["gpu"]["rows"]
    ledh = [r for r in rows if "wall" in r and r["name"].startswith("PF-PF(LEDH)")]
    assert [r["trials"] for r in ledh] == [2, 4] and all(r["wall"] > 0 and r["goal"] is None for r in ledh)
    gpfis = next(r for r in rows if r["name"].startswith("GPFIS / PF-PF(LEDH)"))
    assert gpfis["ratio"] > 0 and gpfis["met"] == (gpfis["ratio"] <= bench_gpu.GPFIS_GOAL)
    flat = next(r for r in rows if "cost per trial-step" in r["name"])
    assert flat["ratio"] == pytest.approx(ledh[1]["per_ts"] / ledh[0]["per_ts"]) and flat["met"] == (
        flat["ratio"] <= 1.05
    )
    if sys.version_info < (3, 12):  # PyDPF needs Python >= 3.12
        assert any(r["name"] == "BPF vs PyDPF" and r["status"].startswith("skipped") for r in rows)
    assert "| PF-PF(LEDH) cost per trial-step, 4 / 2 trials |" in (tmp_path / "all.md").read_text()
    assert bench_gpu.LEDH_GOALS[100] == 0.5 and "gpu" in run_all.CUDA_SECTIONS


def test_gpu_section_keeps_its_rows_when_the_peer_comparison_fails(tmp_path, monkeypatch):
    """A failing PyDPF comparison (on the H100 it once raised from a stub module) becomes a FAILED
    row; the PF-PF(LEDH) and GPFIS rows before it stay, with each first call's time."""

    def broken(*args, **kwargs):
        raise RuntimeError("peer broke")

    monkeypatch.setattr(bench_gpu.peer, "pydpf_available", lambda: True)
    monkeypatch.setattr(bench_gpu.peer, "compare", broken)
    res = bench_gpu.run(["--device", "cpu", "--quick", "--out", str(tmp_path / "gpu.md")])
    rows = res["rows"]
    bpf = next(r for r in rows if r["name"] == "BPF vs PyDPF")
    assert bpf["status"].startswith("FAILED: RuntimeError: peer broke") and bpf["met"] is False
    ledh = [r for r in rows if "wall" in r and r["name"].startswith("PF-PF(LEDH)")]
    assert len(ledh) == 2 and all(r["first"] > 0 for r in ledh)


def test_pydpf_stubs_can_be_made_twice():
    """The stand-ins for PyDPF's unused imports: a second call (the availability check, then the
    comparison) must not ask ``find_spec`` about the stub ("polars.__spec__ is None")."""
    from experiments.benchmarks import peer_pydpf_bpf as peer

    name = "torchflow_test_missing_module_xyz"
    try:
        peer._stub_missing(name)
        peer._stub_missing(name)
        assert sys.modules[name].Anything.__name__ == "Anything"
    finally:
        sys.modules.pop(name, None)


def test_flop_model_scales_with_particles_and_steps():
    f1 = bench_flops.ledh_flops_per_trial_step(500, 16, 8, 25, 4, 29)
    assert bench_flops.ledh_flops_per_trial_step(1000, 16, 8, 25, 4, 29) == pytest.approx(2 * f1)
    assert 1e8 < f1 < 1e9  # ~0.2 GFLOP per trial-step at N = 500


# ---- each benchmark, micro sizes -------------------------------------------------------------
def test_acoustic_bench_micro_with_and_without_peer(monkeypatch):
    res = bench_acoustic.run(["--trials", "2", "--steps", "2", "--particles", "30", "--no-peer"])
    ours = [r for r in res["rows"] if r["side"] == "ours"]
    assert len(ours) == len(res["rows"]) == 4 and all(r["per_ts"] > 0 and r["finite"] for r in ours)
    assert "| PF-PF(LEDH) (torchflow) |" in res["markdown"]
    monkeypatch.setattr(harness, "peer", lambda name, *subs: None)  # Stone Soup not installed
    res = bench_acoustic.run(["--trials", "1", "--steps", "1", "--particles", "10"])
    peers = [r for r in res["rows"] if r["side"] == "peer"]
    assert len(peers) == 3 and all(r["status"] == harness.skipped("stonesoup") for r in peers)
    assert all(r["vs_stonesoup_gromov"] is None and r["goal"] is None for r in res["rows"])
    assert "| GromovFlowParticleUpdater (Stone Soup) | - |" in res["markdown"]


def test_memory_case_runs_in_its_own_process():
    res = bench_memory.run(["--cases", "bpf", "--particles-bpf", "3000", "--steps", "1", "--memory-gb", "0.002"])
    (row,) = res["rows"]
    assert "error" not in row, row
    assert row["particles"] == 3000 and row["particle_chunk"] is not None and row["particle_chunk"] < 3000
    assert row["peak_rss_gb"] > 0 and row["s_per_step"] > 0
    assert res["markdown"].count("\n| BPF | 3e+03 |") == 1


def test_pfpf_bench_micro():
    res = bench_pfpf.run(
        ["--trials", "3", "--steps", "1", "--particles", "10", "--filters", "bpf,ledh", "--chunk", "2"]
    )
    assert [r["filter"] for r in res["rows"]] == ["BPF", "PF-PF(LEDH)"]
    assert all(r["sec_per_trial_step"] > 0 and r["chunk"] == 2 and r["N"] == 10 for r in res["rows"])
    assert res["rows"][1]["vs_ledh"] == 1.0
    assert "| trials per call | s / trial-step | time / PF-PF(LEDH) |" in res["markdown"]
    with pytest.raises(SystemExit, match="--filters"):
        bench_pfpf.run(["--filters", "bpf,nope"])


def test_streams_bench_micro(monkeypatch):
    small = [c for c in bench_streams.cases(True) if c[0].startswith("BPF, LG d=64, N=200")]
    monkeypatch.setattr(bench_streams, "cases", lambda quick: [(n, m, f, 2, 2) for n, m, f, _, _ in small])
    res = bench_streams.run(["--repeats", "1", "--threads", "1"])
    (row,) = res["rows"]
    assert row["generator"] > 0 and row["streams"] > 0 and row["ratio"] == row["streams"] / row["generator"]
    assert len(res["draws"]) == 4 and all(d["generator_ns"] > 0 for d in res["draws"])
    assert "| BPF, LG d=64, N=200 | 2 x 2 |" in res["markdown"]


def test_float32_bench_micro():
    res = bench_float32.run(
        [
            "--tables",
            "lg",
            "--filters",
            "kf,bpf",
            "--lg-trials",
            "3",
            "--steps-lg",
            "2",
            "--lg-d",
            "4",
            "--particles-lg",
            "20",
            "--quiet",
        ]
    )
    kf, bpf = res["rows"]
    assert kf["filter"] == "KF" and kf["verdict"] == "ok" and kf["max_est_diff_rel"] < 1e-4  # round-off only
    assert kf["sec_per_step64"] > 0 and kf["sec_per_step32"] > 0 and bpf["sec_per_step64"] > 0
    assert bpf["n_particles"] == 20 and set(bpf["metrics"]) == {"mse", "log_evidence_relmse", "ess"}
    assert bpf["verdict"] in ("ok", "degraded", "breaks") and (bpf["verdict"] == "ok") == (bpf["reason"] == "")
    assert "| KF | - | " in res["markdown"] and "Kalman-type filters point by point" in res["markdown"]


def test_flops_bench_micro(monkeypatch):
    monkeypatch.setattr(
        bench_flops, "throughputs", lambda: dict(gemm_2048=100.0, bmm_16x8x8=10.0, bmm_gram_25x8=5.0, bmm_16x16x16=20.0)
    )
    res = bench_flops.run(["--particles", "20", "--trials", "2", "--steps", "1"])
    ledh = res["rows"][0]
    assert ledh["gflops"] == pytest.approx(ledh["gflop_per_trial_step"] / ledh["per_ts"])
    assert "| one 2048^3 GEMM (practical peak) | 100.00 | 100% |" in res["markdown"]
    assert "| batched 16x8 @ 8x8 (10^4 products; the flow's A = L (...) shape) | 10.00 | 10.0% |" in res["markdown"]


def test_run_all_runs_a_section_and_writes_both_reports(tmp_path, monkeypatch):
    monkeypatch.setattr(harness, "RESULTS", tmp_path)  # the sections' results files go here
    res = run_all.run(["--only", "gaussian_sum", "--quick"])
    assert not res["failures"] and list(res["results"]) == ["gaussian_sum"]
    assert (tmp_path / "results_gaussian_sum_quick.json").exists()
    assert "| PFGSPF (20 x 2) | 40 |" in (tmp_path / "results_all_quick.md").read_text()
    with pytest.raises(SystemExit, match="unknown section 'nope'"):
        run_all.run(["--only", "nope"])


def test_run_all_merge_reassembles_saved_sections(tmp_path):
    """``--merge`` with no section run rebuilds the report from the saved results files."""
    saved = [s for s in run_all.SECTIONS if harness.results_path(s).with_suffix(".json").exists()]
    if "foundation" not in saved:
        pytest.skip("no saved foundation results in this checkout")
    out = tmp_path / "all.md"
    res = run_all.run(["--only", "", "--merge", "--out", str(out)])
    assert not res["failures"] and set(res["results"]) == set(saved)
    text = out.read_text()
    assert "| Kalman filter vs filterpy |" in text and "## Foundation benchmarks" in text


def test_gaussian_sum_bench_micro():
    res = bench_gaussian_sum.run(["--quick"])
    assert [r["key"] for r in res["rows"]] == ["pfgspf", "pfpf_ledh", "gspf", "bpf"]
    assert all(r["s_per_trial_step"] > 0 and r["particles"] == 40 for r in res["rows"])
    assert res["rows"][1]["ratio_to_pfpf_ledh"] == 1.0 and "| PFGSPF (20 x 2) | 40 |" in res["markdown"]


def test_bench_scaling_micro(tmp_path):
    assert math.isclose(bench_scaling.loglog_slope([(10, 2.0), (100, 20.0), (1000, 200.0)]), 1.0)
    res = bench_scaling.run(
        [
            "--curves",
            "N,d,B",
            "--ns",
            "10,20",
            "--ds",
            "4,9",
            "--bs",
            "1,2",
            "--steps",
            "1",
            "--trials",
            "1",
            "--time-budget",
            "0",
            "--d-curve-n",
            "10",
            "--b-curve-n",
            "10",
            "--no-plot",
            "--quiet",
            "--out",
            str(tmp_path / "s.md"),
        ]
    )
    rows = res["rows"]
    assert {r["curve"] for r in rows} == {"N", "d", "B"}
    assert len(rows) == 4 * 2 + 5 * 2 + 6 * 2
    assert all(r["status"] == "ok" and r["s_per_trial_step"] > 0 and r["repeats"] == 1 for r in rows), [
        r["status"] for r in rows if r["status"] != "ok"
    ]
    assert res["plot"] is None and "log-log slope" in res["markdown"] and "EKF (acoustic)" in res["markdown"]
    assert set(res["machine"]) >= {"platform", "cpus", "torch", "torch_threads", "load_start", "load_end"}

    # a point whose extrapolated time exceeds the cap is recorded as skipped, not dropped
    res = bench_scaling.run(
        [
            "--curves",
            "N",
            "--ns",
            "10,20",
            "--filters",
            "bpf",
            "--steps",
            "1",
            "--trials",
            "1",
            "--time-budget",
            "0",
            "--max-point-seconds",
            "0",
            "--no-plot",
            "--quiet",
            "--out",
            str(tmp_path / "t.md"),
        ]
    )
    assert [r["status"][:7] for r in res["rows"]] == ["ok", "skipped"]
    assert "skipped" in res["markdown"]


def test_bench_gradients_micro(tmp_path):
    """Rows for each estimator, the exact gradient's scale, positive costs; --estimators is checked."""
    from experiments.benchmarks import bench_gradients

    res = bench_gradients.run(
        [
            "--n",
            "30",
            "--trials",
            "2",
            "--reps",
            "3",
            "--steps",
            "3",
            "--filters",
            "bpf",
            "--estimators",
            "none,stop_gradient,ot",
            "--memory-n",
            "50",
            "--memory-trials",
            "2",
        ]
    )
    assert [r["estimator"] for r in res["rows"]] == ["none", "stop_gradient", "ot"]
    for r in res["rows"]:
        assert r["exact_norm"] > 0 and r["fwd"] > 0 and r["fwd_bwd"] > 0 and r["saved_mb"] > 0
        assert math.isfinite(r["bias"]) and math.isfinite(r["sd_run"])
    assert "| BPF | stop_gradient | 2 | 30 |" in res["markdown"]
    assert [m["checkpoint_steps"] for m in res["memory"]] == [False, True]
    assert all(m["peak_mb"] >= 0 and m["seconds"] > 0 for m in res["memory"])
    with pytest.raises(SystemExit, match="--estimators"):
        bench_gradients.run(["--estimators", "bogus"])


def test_bench_gradients_writes_the_peer_problem(tmp_path):
    """--write-problem: the model, data and the Kalman log-evidence and F-gradient for the PyDPF peer script."""
    from experiments.benchmarks import bench_gradients

    path = tmp_path / "p.pt"
    bench_gradients.run(["--write-problem", str(path), "--steps", "5", "--d", "3"])
    p = torch.load(path)
    assert p["F"].shape == (3, 3) and p["obs"].shape == (1, 5, 3) and p["grad_F"].shape == (3, 3)
    assert math.isfinite(float(p["log_z"])) and float(p["grad_F"].abs().sum()) > 0


def test_bench_ops_micro(tmp_path):
    """Every filter family gets a row; none synchronises on the CUDA path; the op targets are judged."""
    from experiments.benchmarks import bench_ops

    res = bench_ops.run(["--particles", "20", "--trials", "2", "--out", str(tmp_path / "ops.md")])
    names = [r["name"] for r in res["rows"]]
    assert {"BPF", "PF-PF(LEDH)", "PF-PF(Gromov)", "GPFIS", "UPF", "EKF"} <= set(names) and len(names) == 15
    assert all(r["syncs_cuda"] == 0 and 0 < r["compute_ops"] <= r["ops"] for r in res["rows"])
    ledh = next(r for r in res["rows"] if r["name"] == "PF-PF(LEDH)")
    assert ledh["target"] == 1000 and ledh["met"] == (ledh["ops"] <= 1000)
    assert "| PF-PF(LEDH) |" in res["markdown"]


def test_repaired_gromov_square_root():
    """The repaired Stone Soup peer's root satisfies ``B B^T = Q`` for the rank-deficient ``Q`` of the
    acoustic model (8 measured coordinates of 16), where the shipped ``cholesky_eps`` does not."""
    rng = np.random.default_rng(0)
    X = rng.standard_normal((16, 8))
    Q = X @ X.T  # rank 8
    B = bench_acoustic.psd_root(Q)
    assert np.allclose(B @ B.T, Q, atol=1e-10)
    ssp = pytest.importorskip("stonesoup.updater.particle")
    from stonesoup.functions import cholesky_eps

    U = cholesky_eps(Q)
    assert not np.allclose(U @ U.T, Q, atol=1e-3)  # the shipped root: the upper factor, pivots floored
    Repaired = bench_acoustic._classes()[-1]
    assert issubclass(Repaired, ssp.GromovFlowParticleUpdater)
    assert ssp.cholesky_eps is cholesky_eps  # patched only inside an update


def test_sv_quick(tmp_path):
    """The stochastic-volatility benchmark on a 20-step prefix: the exact row, ours (batched and one
    run per call), the flow rows, and the comparison with particles (whose dataset it reads); the
    CSV that experiments.data.gbpusd writes holds the same series."""
    pytest.importorskip("particles")
    res = bench_sv.run(
        [
            "--quick",
            "--steps",
            "20",
            "--ns",
            "100",
            "--single-runs",
            "1",
            "--flows",
            "ledh:20:2",
            "--flow-single",
            "0",
            "--out",
            str(tmp_path / "sv.md"),
        ]
    )
    names = [(r["name"], r["mode"]) for r in res["rows"]]
    assert names[0][0].startswith("exact") and res["T"] == 20
    assert ("ours BPF", "B = 4, one call") in names and ("ours BPF", "B = 1 per call") in names
    assert ("ours PF-PF(LEDH), log-squared form", "B = 2, one call") in names
    for r in res["rows"]:
        assert math.isfinite(r["mean"]) and r["sec_per_run"] > 0
    assert ("particles BPF", "1 run per call") in names and len(res["pairs"]) == 1
    from experiments.data import gbpusd

    y = np.loadtxt(gbpusd.write(tmp_path / "gbpusd.csv"), delimiter=",", skiprows=1)
    assert y.shape == (750,) and abs(y[0] + 0.23976372819901615) < 1e-15


def test_sv_pmmh_quick(tmp_path):
    """The PMMH benchmark at toy size: both samplers' rows, finite posterior summaries."""
    pytest.importorskip("particles")
    from experiments.benchmarks import bench_sv_pmmh

    bench_sv_pmmh.main(
        [
            "--steps",
            "20",
            "--iterations",
            "6",
            "--adapt",
            "3",
            "--chains",
            "2",
            "--particles",
            "30",
            "--out",
            str(tmp_path / "pmmh"),
        ]
    )
    rows = json.loads((tmp_path / "pmmh.json").read_text())["rows"]
    assert [r["sampler"].split()[0] for r in rows] == ["torchflow", "particles"]
    assert all(math.isfinite(r[k]["mean"]) and r[k]["ess"] > 0 for r in rows for k in ("mu", "rho", "sigma"))


def test_paired_differences_of_two_runs(tmp_path):
    """``paired`` pairs the trials both runs have, per filter and metric, and reports the mean
    difference with its standard error; a run against itself differs by exactly 0, and a shift of
    every trial by c gives c with SE 0 (z infinite)."""
    from experiments.benchmarks import paired

    def write(name, rows):
        d = tmp_path / name
        d.mkdir()
        lines = ["filter,trial,omat,log_evidence"] + [f"{f},{t},{o},{l}" for f, t, o, l in rows]
        (d / "per_trial.csv").write_text("\n".join(lines) + "\n")
        return d

    a = write("a", [("bpf", 0, 1.0, -5.0), ("bpf", 1, 3.0, -7.0), ("bpf", 2, 2.0, "nan"), ("ledh", 0, 0.5, 1.0)])
    b = write("b", [("bpf", 0, 1.5, -4.0), ("bpf", 1, 3.5, -8.0), ("bpf", 3, 9.0, 0.0), ("ledh", 0, 0.5, 1.0)])
    same = paired.paired(paired.read(a), paired.read(a), ["omat"])
    assert [(r["filter"], r["n"], r["diff"]) for r in same] == [("bpf", 3, 0.0), ("ledh", 1, 0.0)]
    rows = {
        (r["filter"], r["metric"]): r for r in paired.paired(paired.read(a), paired.read(b), ["omat", "log_evidence"])
    }
    om = rows["bpf", "omat"]
    assert om["n"] == 2 and om["diff"] == 0.5 and om["se"] == 0.0 and om["z"] == math.inf
    le = rows["bpf", "log_evidence"]  # trial 2 has no finite value in a; trial 3 is not in a
    assert le["n"] == 2 and le["diff"] == 0.0 and math.isclose(le["se"], 1.0)
    assert "| bpf | omat | 2 |" in paired.table(list(rows.values()))


def test_the_before_after_benchmark_covers_every_family_and_runs(capsys):
    """bench_before_after times the particle, flow, Gaussian-sum, ensemble, data-assimilation and TDOA
    families; one case runs here (a localised weighted lag-one flow: 4 trials x 50 steps)."""
    from experiments.benchmarks import bench_before_after

    names = set(bench_before_after.cases())
    assert {"bpf", "pfpf_ledh", "gpfis", "pfgspf", "letkf", "lag1_flow", "lag1_pfpf_local", "kpff", "pfi_d"} <= names
    bench_before_after.main(["now", "lag1_pfpf_local", "--repeats", "1", "--threads", "1"])
    out = capsys.readouterr().out
    assert "now lag1_pfpf_local median s/trial-step" in out and '{"now": {"lag1_pfpf_local": [' in out
