"""Smoke test of experiments/benchmarks/bench_scaling.py on a micro configuration (a few seconds)."""
import importlib.util
import math
from pathlib import Path

_PATH = Path(__file__).resolve().parents[2] / "experiments" / "benchmarks" / "bench_scaling.py"


def _load():
    spec = importlib.util.spec_from_file_location("bench_scaling", _PATH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_bench_scaling_micro(tmp_path):
    bench = _load()
    assert math.isclose(bench.loglog_slope([(10, 2.0), (100, 20.0), (1000, 200.0)]), 1.0)
    res = bench.run(["--curves", "N,d,B", "--ns", "10,20", "--ds", "4,9", "--bs", "1,2", "--steps", "1",
                     "--trials", "1", "--time-budget", "0", "--d-curve-n", "10", "--b-curve-n", "10",
                     "--no-plot", "--quiet", "--out", str(tmp_path / "s.md")])
    rows = res["rows"]
    assert {r["curve"] for r in rows} == {"N", "d", "B"}
    assert len(rows) == 4 * 2 + 5 * 2 + 6 * 2
    assert all(r["status"] == "ok" and r["s_per_trial_step"] > 0 for r in rows), \
        [r["status"] for r in rows if r["status"] != "ok"]
    assert res["plot"] is None and "log-log slope" in res["markdown"] and "EKF (acoustic)" in res["markdown"]
    assert set(res["machine"]) >= {"platform", "cpus", "torch", "torch_threads", "load_start", "load_end"}

    # a point whose extrapolated time exceeds the cap is recorded as skipped, not dropped
    res = bench.run(["--curves", "N", "--ns", "10,20", "--filters", "bpf", "--steps", "1", "--trials", "1",
                     "--time-budget", "0", "--max-point-seconds", "0", "--no-plot", "--quiet",
                     "--out", str(tmp_path / "t.md")])
    assert [r["status"][:7] for r in res["rows"]] == ["ok", "skipped"]
    assert "skipped" in res["markdown"]
