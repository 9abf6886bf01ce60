"""Benchmark-suite plumbing (no timing claims): headline goals, statuses, the flop model, the
acoustic bench on a micro configuration and one memory-budget case in its own process."""
import sys
from pathlib import Path

import pytest

_BENCH = Path(__file__).resolve().parents[2] / "experiments" / "benchmarks"
sys.path.insert(0, str(_BENCH))

import bench_acoustic  # noqa: E402
import bench_flops  # noqa: E402
import bench_memory  # noqa: E402
import run_all  # noqa: E402


def test_status_and_goal_flags():
    ok = dict(finite=True, position_rmse=3.0, omat=0.6)
    assert bench_acoustic.status(ok) == "tracking"
    assert bench_acoustic.status(dict(ok, omat=9.0)) == "finite, tracks lost"
    assert bench_acoustic.status(dict(finite=True, position_rmse=1e70)) == "diverged"
    assert bench_acoustic.status(dict(finite=False, position_rmse=float("nan"))) == "diverged"
    assert bench_acoustic.status(dict(finite=True, position_rmse=1e70, failures=["step 2"])) == "diverged, then raised"


def test_headline_collects_every_goal():
    results = {
        "foundation": {"rows": [dict(name="KF", setting="d=64", per_ts_ours=1e-6, per_ts_peer=1e-4, ratio=100.0,
                                     goal=50.0, met=True)]},
        "acoustic": {"rows": [
            dict(name="PF-PF(LEDH) (torchflow)", side="ours", per_ts=0.05, vs_stonesoup_gromov=80.0, goal=30.0,
                 met=True, vs_stonesoup_bootstrap=None),
            dict(name="BPF (torchflow)", side="ours", per_ts=0.001, vs_stonesoup_gromov=4000.0, goal=None,
                 met=None, vs_stonesoup_bootstrap=2.0),
            dict(name="GromovFlowParticleUpdater (Stone Soup)", side="peer", per_ts=4.0),
            dict(name="ParticleUpdater bootstrap (Stone Soup)", side="peer", per_ts=0.002)]},
    }
    rows = run_all._headline(results)
    names = [r[0] for r in rows]
    assert names[0] == "KF" and "PF-PF(LEDH) (torchflow) vs Stone Soup Gromov" in names
    assert "BPF (torchflow) vs Stone Soup bootstrap" in names
    ledh = rows[names.index("PF-PF(LEDH) (torchflow) vs Stone Soup Gromov")]
    assert ledh[4] == 80.0 and ledh[5] == 30.0 and ledh[6] is True


def test_flop_model_scales_with_particles_and_steps():
    f1 = bench_flops.ledh_flops_per_trial_step(500, 16, 8, 25, 4, 29)
    assert bench_flops.ledh_flops_per_trial_step(1000, 16, 8, 25, 4, 29) == pytest.approx(2 * f1)
    assert 1e8 < f1 < 1e9  # ~0.2 GFLOP per trial-step at N = 500


def test_acoustic_bench_micro_without_peer():
    res = bench_acoustic.run(["--trials", "2", "--steps", "2", "--particles", "30", "--no-peer"])
    ours = [r for r in res["rows"] if r["side"] == "ours"]
    assert len(ours) == 4 and all(r["per_ts"] > 0 and r["finite"] for r in ours)
    assert "| PF-PF(LEDH) (torchflow) |" in res["markdown"]


def test_memory_case_runs_in_its_own_process():
    res = bench_memory.run(["--cases", "bpf", "--particles-bpf", "3000", "--steps", "1", "--memory-gb", "0.002"])
    (row,) = res["rows"]
    assert "error" not in row, row
    assert row["particles"] == 3000 and row["particle_chunk"] is not None and row["particle_chunk"] < 3000
    assert row["peak_rss_gb"] > 0 and row["s_per_step"] > 0


def test_run_all_merge_reassembles_saved_sections(tmp_path):
    """``--merge`` with no section run rebuilds the report from the saved results files."""
    saved = [s for s in run_all.SECTIONS if (_BENCH / f"results_{s}.json").exists()]
    if "foundation" not in saved:
        pytest.skip("no saved foundation results in this checkout")
    out = tmp_path / "all.md"
    res = run_all.run(["--only", "", "--merge", "--out", str(out)])
    assert not res["failures"] and set(res["results"]) == set(saved)
    text = out.read_text()
    assert "| Kalman filter vs filterpy |" in text and "## Foundation benchmarks" in text


def test_gaussian_sum_bench_micro():
    import bench_gaussian_sum

    res = bench_gaussian_sum.run(["--quick"])
    assert [r["key"] for r in res["rows"]] == ["pfgspf", "pfpf_ledh", "gspf", "bpf"]
    assert all(r["s_per_trial_step"] > 0 and r["particles"] == 40 for r in res["rows"])
    assert res["rows"][1]["ratio_to_pfpf_ledh"] == 1.0 and "| PFGSPF (20 x 2) | 40 |" in res["markdown"]
