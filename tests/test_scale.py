"""Resumable runs (per-chunk files), torchrun sharding, sweeps on Hydra launchers,
Lightning DDP. The subprocess tests run the real command lines on 2 CPU processes (gloo)."""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from torchflow.app.runner import ChunkStore, Shard, fingerprint, run_experiment
from torchflow.filters import BootstrapParticleFilter, KalmanFilter
from torchflow.models import SensorNetwork

ROOT = Path(__file__).resolve().parents[1]
RUN = str(ROOT / "experiments" / "run.py")


class _StopAfter(BootstrapParticleFilter):
    """A bootstrap PF (it inherits the random streams) that is 'killed' when it starts its chunk number ``k``."""

    def __init__(self, *a, stop_at: int, **kw):
        super().__init__(*a, **kw)
        self.calls, self.stop_at = 0, stop_at

    def forward(self, *a, **kw):
        self.calls += 1
        if self.calls == self.stop_at:
            raise KeyboardInterrupt
        return super().forward(*a, **kw)


def _bpf_run(model, f, store=None, **kw):
    kw.setdefault("warmup", False)  # (the calls counted are the chunks')
    return run_experiment(
        model, {"bpf": f}, trials=10, steps=3, seed=4, chunk_size=1, progress=False, store=store, **kw
    )


def test_resume_computes_only_the_missing_chunks(tmp_path):
    """A 10-chunk run stopped at its 6th chunk saved 5; resuming loads those 5, computes 5 and
    gives the uninterrupted run's numbers (==)."""
    model = SensorNetwork(d=9)
    full = _bpf_run(model, BootstrapParticleFilter(model, n_particles=50))
    killed = _bpf_run(model, _StopAfter(model, n_particles=50, stop_at=6), ChunkStore(tmp_path, {"bpf": "k"}))
    assert killed.interrupted and killed.summary[0]["error"] == "interrupted after 5 of 10 trials"
    assert len(list((tmp_path / "k").glob("*.pt"))) == 5
    store = ChunkStore(tmp_path, {"bpf": "k"}, resume=True)
    f = _StopAfter(model, n_particles=50, stop_at=99)
    resumed = _bpf_run(model, f, store)
    assert store.loaded == {"bpf": 5} and store.computed == {"bpf": 5} and f.calls == 5
    assert resumed.per_trial == full.per_trial and resumed.per_step == full.per_step
    drop = lambda rows: [{k: v for k, v in r.items() if k != "sec_per_step"} for r in rows]
    assert drop(resumed.summary) == drop(full.summary)
    # without resume every chunk is computed again (and the files overwritten)
    again = ChunkStore(tmp_path, {"bpf": "k"})
    _bpf_run(model, BootstrapParticleFilter(model, n_particles=50), again)
    assert again.loaded == {} and again.computed == {"bpf": 10}


def test_resume_ignores_chunks_saved_with_other_settings(tmp_path):
    model = SensorNetwork(d=9)
    _bpf_run(model, BootstrapParticleFilter(model, n_particles=50), ChunkStore(tmp_path, {"bpf": "a"}))
    (tmp_path / "b").mkdir()
    for p in (tmp_path / "a").glob("*.pt"):  # files under the wrong key: their header says "a"
        (tmp_path / "b" / p.name).write_bytes(p.read_bytes())
    (tmp_path / "b" / "0000000-0000001.pt").write_bytes(b"not a torch file")
    store = ChunkStore(tmp_path, {"bpf": "b"}, resume=True)
    with pytest.warns(UserWarning, match="resume"):
        _bpf_run(model, BootstrapParticleFilter(model, n_particles=50), store)
    assert store.loaded == {} and store.computed == {"bpf": 10}


def test_fingerprint_and_bad_arguments():
    assert fingerprint({"a": 1, "b": [1, 2]}) == fingerprint({"b": [1, 2], "a": 1})
    assert fingerprint({"a": 1}) != fingerprint({"a": 2})
    with pytest.raises(ValueError, match="resume: expected True or False, got 'yes'"):
        ChunkStore("x", resume="yes")
    with pytest.raises(ValueError, match="rank: expected < world = 2, got 2"):
        Shard(rank=2, world=2)
    with pytest.raises(ValueError, match="world: expected an int >= 1, got 0"):
        Shard(rank=0, world=0)
    assert Shard(1, 3).mine(list(range(8))) == [1, 4, 7] and Shard().gather("x") == ["x"]


class _FakeShard(Shard):
    """Rank ``rank`` of ``world`` where gather hands rank 0 the other ranks' precomputed parts
    (ranks 1.. run first). ``broadcast`` of the stop decision: rank 0's own; a rank > 0 sees its
    own interruption (the case the tests build)."""

    parts: dict = {}

    def gather(self, obj):
        self.parts.setdefault(self.rank, []).append(obj)
        if self.rank:
            return None
        return [self.parts[r][len(self.parts[0]) - 1] for r in range(self.world)]

    def broadcast(self, obj):
        return obj if self.rank == 0 else self.parts[self.rank][-1][2]


def _sharded(model, filters, world, **kw):
    _FakeShard.parts = {}
    for r in range(1, world):
        assert run_experiment(model, filters(), progress=False, shard=_FakeShard(r, world), **kw) is None
    return run_experiment(model, filters(), progress=False, shard=_FakeShard(0, world), **kw)


def test_sharded_chunks_reassemble_to_the_single_process_run():
    """Ranks 1 and 2 of 3 run first and park their parts; rank 0 gathers them. With the same
    chunks every number equals the single-process run's (==); with the default chunking (capped
    at ceil(7 / 3) trials so every rank has work) the bootstrap PF is still identical and the
    Kalman filter equal to round-off (batched Cholesky blocks by batch size)."""
    model = SensorNetwork(d=9)
    filters = lambda: {"kf": KalmanFilter(model), "bpf": BootstrapParticleFilter(model, n_particles=40)}
    kw = dict(trials=7, steps=3, seed=1)
    pinned = run_experiment(model, filters(), progress=False, chunk_size=2, **kw)
    res = _sharded(model, filters, 3, chunk_size=2, **kw)
    assert res.per_trial == pinned.per_trial and res.per_step == pinned.per_step
    assert res.config["world_size"] == 3 and len(res.per_trial) == 14
    single = run_experiment(model, filters(), progress=False, **kw)
    res = _sharded(model, filters, 3, **kw)
    assert res.config["chunk_size"] == {"kf": 3, "bpf": 3} and single.config["chunk_size"] == {"kf": 7, "bpf": 7}
    bpf = lambda r: [x for x in r.per_trial if x["filter"] == "bpf"]
    assert bpf(res) == bpf(single)
    for a, b in zip(res.per_trial[:7], single.per_trial[:7]):
        assert a["mse"] == pytest.approx(b["mse"], rel=1e-12) and a["log_evidence"] == pytest.approx(b["log_evidence"])


def test_a_filter_failing_on_one_rank_fails_its_row_not_the_run():
    """Rank 1 raises inside the bootstrap PF: rank 0's row says so, the KF row is complete."""
    model = SensorNetwork(d=9)

    class Broken(BootstrapParticleFilter):
        def forward(self, obs, *a, **kw):
            if obs.shape[0] == 1:  # only rank 1 of 2 gets a 1-trial chunk (trials 2 of 3 -> chunks of 2)
                raise RuntimeError("boom")
            return super().forward(obs, *a, **kw)

    filters = lambda: {"bpf": Broken(model, n_particles=20), "kf": KalmanFilter(model)}
    res = _sharded(model, filters, 2, trials=3, steps=2, seed=0)
    assert res.summary[0]["error"] == "RuntimeError: boom" and res.summary[1]["error"] is None
    assert [r["filter"] for r in res.per_trial] == ["kf"] * 3


def test_an_interrupt_on_one_rank_stops_every_rank():
    """Rank 1 is interrupted in the bootstrap PF: it stops, rank 0 stops too (no further
    filter), and rank 0's row says how many trials finished."""
    model = SensorNetwork(d=9)

    class Stopped(BootstrapParticleFilter):
        def forward(self, obs, *a, **kw):
            if obs.shape[0] == 1:  # rank 1's chunk
                raise KeyboardInterrupt
            return super().forward(obs, *a, **kw)

    filters = lambda: {
        "kf": KalmanFilter(model),
        "bpf": Stopped(model, n_particles=20),
        "kf2": KalmanFilter(model),
    }
    res = _sharded(model, filters, 2, trials=3, steps=2, seed=0, warmup=False)  # (a warm-up call has 1 trial too)
    assert res.interrupted and res.not_run == ["kf2"]
    assert res.summary[1]["error"] == "interrupted after 2 of 3 trials"


def test_a_signal_outside_a_chunk_waits_for_the_next_chunk():
    """STOP.handler (installed for SIGINT/SIGTERM by run.py) raises inside a chunk at once;
    outside one (here: while the runner reports a finished filter) it stops the run at the next
    chunk, after the finished filter is scored."""
    from torchflow.app.runner import STOP

    model = SensorNetwork(d=9)

    class Signalled(BootstrapParticleFilter):
        def forward(self, *a, **kw):
            STOP.handler(15, None)  # a SIGTERM arriving during the chunk
            raise AssertionError("not reached")

    try:
        res = run_experiment(model, {"bpf": Signalled(model, n_particles=20)}, trials=2, steps=2, progress=False)
        assert res.interrupted and res.summary[0]["error"] == "interrupted after 0 of 2 trials"
        STOP.reset()
        res = run_experiment(
            model,
            {"kf": KalmanFilter(model), "bpf": BootstrapParticleFilter(model, n_particles=20)},
            trials=2,
            steps=2,
            progress=False,
            on_filter_done=lambda rows: STOP.handler(15, None),
        )
        assert res.interrupted and res.summary[0]["error"] is None and len(res.per_trial) == 2
        assert res.summary[1]["error"] == "interrupted after 0 of 2 trials"
    finally:
        STOP.reset()


def _csv_rows(path, drop=("sec_per_step", "warmup_sec")):
    with open(path) as fh:
        return [{k: v for k, v in r.items() if k not in drop} for r in csv.DictReader(fh)]


def _env():
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONWARNINGS="ignore")
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def test_cli_sigterm_then_resume_gives_the_uninterrupted_files(tmp_path):
    """End to end: a 10-chunk run killed (SIGTERM) after 5 chunks; ``resume=true``
    computes only the missing chunks and writes the uninterrupted run's files."""
    args = [
        "model=linear_gaussian",
        "model.d=16",
        "filter=[bpf]",
        "trials=10",
        "steps=40",
        "n_particles=20000",
        "chunk_size=1",
        "seed=3",
        "progress=false",
        "plots=false",
        f"checkpoint_dir={tmp_path}/ckpt",
    ]
    full = subprocess.run(
        [sys.executable, RUN, *args, f"hydra.run.dir={tmp_path}/full", "checkpoint_dir=null"],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=300,
    )
    assert full.returncode == 0, full.stderr[-2000:]
    proc = subprocess.Popen(
        [sys.executable, RUN, *args, f"hydra.run.dir={tmp_path}/killed"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
    )
    deadline = time.time() + 240
    files = lambda: list((tmp_path / "ckpt").glob("*/*.pt"))
    while len(files()) < 5 and time.time() < deadline and proc.poll() is None:
        time.sleep(0.01)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    saved = len(files())
    assert proc.returncode == 143 and "Traceback" not in err, err[-2000:]  # 128 + SIGTERM (torchflow.app.runner.shell)
    assert 5 <= saved < 10 and "resume=true" in err, err[-2000:]
    res = subprocess.run(
        [sys.executable, RUN, *args, f"hydra.run.dir={tmp_path}/resumed", "resume=true"],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=300,
    )
    assert res.returncode == 0, res.stderr[-2000:]
    assert f"resumed: {saved} saved chunks read" in res.stdout and f"{10 - saved} chunks computed" in res.stdout
    for name in ("per_trial.csv", "per_step.csv"):
        assert (tmp_path / "resumed" / name).read_bytes() == (tmp_path / "full" / name).read_bytes(), name
    assert _csv_rows(tmp_path / "resumed" / "summary.csv") == _csv_rows(tmp_path / "full" / "summary.csv")


def test_cli_resume_needs_a_checkpoint_dir(tmp_path):
    out = subprocess.run(
        [
            sys.executable,
            RUN,
            "model=linear_gaussian",
            "filter=[kf]",
            "trials=2",
            "steps=2",
            "resume=true",
            "checkpoint_dir=null",
            f"hydra.run.dir={tmp_path}",
        ],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=120,
    )
    assert out.returncode == 2 and "resume=true needs checkpoint_dir" in out.stderr


def test_torchrun_two_processes_give_byte_identical_per_trial_csv(tmp_path):
    """End to end: the same command on 1 and on 2 torchrun processes (gloo)."""
    args = [
        "model=linear_gaussian",
        "filter=[bpf]",
        "trials=40",
        "steps=10",
        "n_particles=200",
        "seed=0",
        "progress=false",
        "plots=false",
        "checkpoint_dir=null",
    ]
    one = subprocess.run(
        [sys.executable, RUN, *args, f"hydra.run.dir={tmp_path}/one"],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=300,
    )
    assert one.returncode == 0, one.stderr[-2000:]
    two = subprocess.run(
        [
            sys.executable,
            "-m",
            "torch.distributed.run",
            "--standalone",
            "--nproc_per_node=2",
            RUN,
            *args,
            f"hydra.run.dir={tmp_path}/two",
        ],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=300,
    )
    assert two.returncode == 0, two.stderr[-3000:]
    assert two.stdout.count("| bpf |") == 1  # rank 0 alone prints and writes
    assert (tmp_path / "two" / "per_trial.csv").read_bytes() == (tmp_path / "one" / "per_trial.csv").read_bytes()
    assert _csv_rows(tmp_path / "two" / "summary.csv") == _csv_rows(tmp_path / "one" / "summary.csv")
    import json

    run = json.loads((tmp_path / "two" / "results.json").read_text())["run"]
    assert run["chunk_size"] == {"bpf": 20} and run["world_size"] == 2


def _sweep(tmp_path, launcher=None, values="10,-1,20"):
    cmd = [
        sys.executable,
        RUN,
        "-m",
        "model=linear_gaussian",
        "model.d=4",
        "filter=[bpf]",
        "trials=2",
        "steps=2",
        f"n_particles={values}",
        "progress=false",
        "plots=false",
        "checkpoint_dir=null",
        f"hydra.sweep.dir={tmp_path}/sweep",
    ]
    if launcher:
        cmd.append(f"hydra/launcher={launcher}")
    return subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=400, cwd=tmp_path)


def _collect(sweep_dir):
    return subprocess.run(
        [sys.executable, str(ROOT / "experiments" / "collect.py"), str(sweep_dir)],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=120,
    )


@pytest.mark.parametrize(
    "launcher",
    [None, pytest.param("joblib", marks=pytest.mark.slow), pytest.param("submitit_local", marks=pytest.mark.slow)],
)  # the parallel launchers: 14 s each, second tier
def test_sweep_with_a_failing_job_keeps_the_others_and_names_it(tmp_path, launcher):
    """Job 1 (n_particles=-1) fails: jobs 0 and 2 still run, the sweep ends with status 1 and
    names job 1 with its overrides; collect.py merges the two results and names the failure."""
    plugin = {
        "joblib": "hydra_plugins.hydra_joblib_launcher",
        "submitit_local": "hydra_plugins.hydra_submitit_launcher",
    }.get(launcher)
    if plugin and importlib.util.find_spec(plugin) is None:
        pytest.skip(f"{launcher} launcher not installed (pip install -e '.[cluster]')")
    out = _sweep(tmp_path, launcher)
    assert out.returncode == 1, out.stderr[-3000:]
    assert "3 jobs, 2 finished, 1 failed, 0 interrupted" in out.stderr and "job 1 (" in out.stderr, out.stderr[-3000:]
    assert "job 1 (n_particles=-1) failed: error: filter.bpf: n_particles" in out.stderr
    sweep = tmp_path / "sweep"
    for j in ("0", "2"):
        assert (sweep / j / "summary.csv").exists(), j
    col = _collect(sweep)
    assert col.returncode == 0, col.stderr
    rows = [ln for ln in col.stdout.splitlines() if "| bpf |" in ln]
    assert len(rows) == 2 and "| 10 |" in rows[0] and "| 20 |" in rows[1]
    assert "job 1 (n_particles=-1) failed: error: filter.bpf: n_particles" in col.stdout + col.stderr


def test_parallel_launchers_keep_every_job_in_the_announced_sweep_folder(tmp_path):
    """Without hydra.sweep.dir, the joblib workers resolve the default folder (which names the
    process) to the main process's value: one sweep folder with jobs 0, 1, 2."""
    if importlib.util.find_spec("hydra_plugins.hydra_joblib_launcher") is None:
        pytest.skip("joblib launcher not installed (pip install -e '.[cluster]')")
    env = {k: v for k, v in _env().items() if k != "OMP_NUM_THREADS"}  # threads=null divides the cores
    out = subprocess.run(
        [
            sys.executable,
            RUN,
            "-m",
            "hydra/launcher=joblib",
            "hydra.launcher.n_jobs=2",
            "model=linear_gaussian",
            "model.d=4",
            "filter=[kf]",
            "trials=2",
            "steps=2",
            "seed=0,1,2",
            "progress=false",
            "plots=false",
            "checkpoint_dir=null",
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
        cwd=tmp_path,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    sweeps = list((tmp_path / "multirun" / "default").iterdir())
    assert len(sweeps) == 1 and sorted(p.name for p in sweeps[0].iterdir() if p.is_dir()) == ["0", "1", "2"]
    assert "3 jobs, 3 finished" in out.stderr
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    for j in ("0", "1", "2"):  # two jobs at once share the cores: threads=null gives each half
        assert json.loads((sweeps[0] / j / "results.json").read_text())["run"]["threads"] == max(1, cores // 2)


@pytest.mark.slow  # 19 s: two processes
def test_lightning_ddp_gradients_equal_single_process(tmp_path):
    """Trainer(strategy="ddp") on 2 CPU processes (gloo): after one step on 8 trials the
    gradients of the model's parameters equal those of one process on the same 8 trials."""
    script = ROOT / "tests" / "ddp_train.py"
    outs = {}
    for devices in (1, 2):
        out = subprocess.run(
            [sys.executable, str(script), str(devices), str(tmp_path / f"grad{devices}.pt")],
            capture_output=True,
            text=True,
            env=_env(),
            timeout=300,
            cwd=tmp_path,
        )
        assert out.returncode == 0, out.stderr[-3000:]
        outs[devices] = torch.load(tmp_path / f"grad{devices}.pt")
    assert outs[2]["world"] == 2 and outs[1]["world"] == 1
    seen = outs[2]["trials_seen"]  # the distributed sampler deals 4 of the 8 trials to each rank
    assert len(seen) == 2 and sorted(seen[0] + seen[1]) == list(range(8)) and len(seen[0]) == 4
    for k, g in outs[1]["grads"].items():
        assert torch.isfinite(g).all() and g.abs().sum() > 0, k
        torch.testing.assert_close(outs[2]["grads"][k], g, rtol=1e-10, atol=1e-12)


def test_chunk_header_must_repeat_the_run_settings(tmp_path):
    """A caller's fixed key with another seed: the header's settings differ, the chunk is recomputed."""
    store = ChunkStore(tmp_path, {"f": "k"}, resume=True)
    chunk = {"estimates": torch.zeros(2, 3, 4), "log_evidence": torch.zeros(2), "elapsed": 0.1}
    store.save("f", 0, 2, chunk, {"seed": 1})
    assert store.load("f", 0, 2, 3, {"seed": 1})["start"] == 0
    with pytest.warns(UserWarning, match="other settings"):
        assert store.load("f", 0, 2, 3, {"seed": 2}) is None
    with pytest.warns(UserWarning, match="other settings"):
        assert store.load("f", 0, 2, 4, {"seed": 1}) is None  # other steps
