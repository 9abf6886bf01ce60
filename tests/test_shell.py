"""The command shell both commands run in (torchflow.app.runner.shell): unknown settings, stop signals,
the output folder's earlier results and lock file, the job environment. The subprocess tests use
tiny runs (a few seconds each, most of it Python's start-up)."""

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from torchflow.app.runner import ConfigError, shell
from torchflow.app.runner.config import close_keys

ROOT = Path(__file__).resolve().parents[1]
TINY = {
    "run": [
        "model=linear_gaussian",
        "model.d=4",
        "filter=[kf]",
        "trials=2",
        "steps=2",
        "progress=false",
        "plots=false",
        "checkpoint_dir=null",
    ],
    "learn": ["filter=[bpf]", "trials=2", "steps=3", "n_particles=20", "epochs=1", "reference=null", "plots=false"],
}
RESULT = {"run": "summary.csv", "learn": "learn.csv"}


def _argv(command, *args):
    start = ["-m", "torchflow"] if command == "run" else [str(ROOT / "experiments" / "learn.py")]
    return [sys.executable, *start, *args]


def _env():
    return dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")


def _cli(tmp_path, command, *args):
    return subprocess.run(_argv(command, *args), capture_output=True, text=True, cwd=tmp_path, timeout=120, env=_env())


def _lines(text):
    return [ln for ln in text.splitlines() if ln.strip()]


@pytest.mark.parametrize(
    "command, key, message",
    [
        ("learn", "+learning_rate=0.5", "error: learning_rate: unknown setting; did you mean lr?"),
        ("learn", "+bogus=1", "error: bogus: unknown setting"),
        ("run", "+n_particle=7", "error: n_particle: unknown setting; did you mean n_particles?"),
        ("run", "+bogus=1", "error: bogus: unknown setting"),
    ],
)
def test_unknown_key_is_refused_in_one_line_with_exit_2(tmp_path, command, key, message):
    r = _cli(tmp_path, command, *TINY[command], key, "hydra.run.dir=out")
    assert r.returncode == 2, r.stderr[-2000:]
    assert _lines(r.stderr) == [message]
    assert not (tmp_path / "out" / RESULT[command]).exists()


def test_close_keys_suggest_misspellings_and_abbreviations():
    known = ["lr", "lr_decay", "learn", "n_particles", "epochs", "trials"]
    assert close_keys("learning_rate", known) == ["lr"]
    assert close_keys("n_particle", known) == ["n_particles"]
    assert close_keys("np", known) == ["n_particles"]
    assert close_keys("bogus", known) == []


@pytest.mark.parametrize("command", ["run", "learn"])
@pytest.mark.parametrize("quoted", [False, True])
def test_earlier_results_are_refused_also_through_a_quoted_hydra_run_dir(tmp_path, command, quoted):
    """A folder holding results is refused in one line before Hydra writes into it (no .hydra, no log),
    whichever command wrote them; a Hydra-quoted path is read as Hydra resolves it (no folder named
    after the quotes is left behind)."""
    prev = tmp_path / "prev"
    prev.mkdir()
    (prev / RESULT["learn" if command == "run" else "run"]).write_text("earlier\n")  # the other command's
    given = f"'{prev}'" if quoted else "prev"
    r = _cli(tmp_path, command, *TINY[command], f"hydra.run.dir={given}")
    assert r.returncode == 2, r.stderr[-2000:]
    assert _lines(r.stderr) == [
        f"error: hydra.run.dir: {prev if quoted else 'prev'} already holds the results of a "
        f"run ({RESULT['learn' if command == 'run' else 'run']}); choose a new folder "
        "(hydra.run.dir=<new folder>) or add overwrite=true to replace them"
    ]
    assert sorted(p.name for p in prev.iterdir()) == [RESULT["learn" if command == "run" else "run"]]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["prev"]  # no junk folder


def test_overwrite_true_replaces_the_earlier_results_of_learning(tmp_path):
    prev = tmp_path / "prev"
    prev.mkdir()
    (prev / "learn.csv").write_text("earlier\n")
    (prev / "curves.png").write_text("earlier\n")
    r = _cli(tmp_path, "learn", *TINY["learn"], "hydra.run.dir=prev", "overwrite=true")
    assert r.returncode == 0, r.stderr[-2000:]
    assert (prev / "learn.csv").read_text().startswith("filter,parameter")
    assert not (prev / "curves.png").exists()  # plots=false: the old figure is gone, not left beside new numbers


@pytest.mark.parametrize("command", ["run", "learn"])
def test_a_folder_whose_lock_a_live_process_holds_is_refused(tmp_path, command):
    out = tmp_path / "out"
    out.mkdir()
    lock = out / shell.LOCK_NAME
    lock.write_text(f"{os.getpid()}\n{socket.gethostname()}\npytest\n")  # this test process: alive
    r = _cli(tmp_path, command, *TINY[command], "hydra.run.dir=out")
    assert r.returncode == 2, r.stderr[-2000:]
    assert _lines(r.stderr) == [
        f"error: hydra.run.dir: {out} is in use by a running torchflow command (pid "
        f"{os.getpid()}, pytest; lock file {lock}); wait for it to finish or choose another "
        "folder (hydra.run.dir=<new folder>)"
    ]
    assert lock.read_text().startswith(f"{os.getpid()}\n")  # still the holder's
    assert sorted(p.name for p in out.iterdir()) == [shell.LOCK_NAME]


@pytest.mark.parametrize("command", ["run", "learn"])
def test_a_stale_lock_is_taken_over_with_a_warning_and_removed_at_exit(tmp_path, command):
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()  # reaped: its pid names no process
    out = tmp_path / "out"
    out.mkdir()
    (out / shell.LOCK_NAME).write_text(f"{gone.pid}\n{socket.gethostname()}\ntorchflow\n")
    r = _cli(tmp_path, command, *TINY[command], "hydra.run.dir=out")
    assert r.returncode == 0, r.stderr[-2000:]
    assert (
        f"warning: hydra.run.dir: took over the stale lock {out / shell.LOCK_NAME} of a run that is gone "
        f"(pid {gone.pid})" in r.stderr
    )
    assert (out / RESULT[command]).exists() and not (out / shell.LOCK_NAME).exists()


@pytest.mark.parametrize("command", ["run", "learn"])
def test_two_runs_started_at_once_into_one_folder_do_not_both_succeed(tmp_path, command):
    """Two seeds into one folder (the run command: and one checkpoint_dir): one goes on, the other is
    refused in one line, and the folder's .hydra/config.yaml is the results' run."""
    shared = ["checkpoint_dir=ck"] if command == "run" else []
    procs = [
        subprocess.Popen(
            _argv(command, *TINY[command], *shared, f"seed={seed}", "hydra.run.dir=out"),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            cwd=tmp_path,
            env=_env(),
        )
        for seed in (0, 1)
    ]
    errs = [p.communicate(timeout=120)[1] for p in procs]
    codes = [p.returncode for p in procs]
    assert sorted(codes) == [0, 2], (codes, errs)
    refused = _lines(errs[codes.index(2)])
    assert len(refused) == 1 and (
        "is in use by a running torchflow command" in refused[0] or "already holds the results of a run" in refused[0]
    ), refused
    out = tmp_path / "out"
    assert (out / RESULT[command]).exists() and not (out / shell.LOCK_NAME).exists()
    assert yaml.safe_load((out / ".hydra" / "config.yaml").read_text())["seed"] == codes.index(0)
    if command == "run":
        assert json.loads((out / "results.json").read_text())["config"]["seed"] == codes.index(0)
        assert len(list((tmp_path / "ck").glob("kf-*"))) == 1  # the refused run saved nothing


def _foreign_lock(folder, pid, mtime=None):
    path = folder / shell.LOCK_NAME
    path.write_text(f"{pid}\n{socket.gethostname()}\nother\n")
    if mtime is not None:
        os.utime(path, (mtime, mtime))
    return path


def test_output_lock_is_exclusive_reentrant_and_released_only_by_its_holder(tmp_path):
    lock = shell.OutputLock(tmp_path).acquire()
    path = tmp_path / shell.LOCK_NAME
    assert lock.held and path.read_text().splitlines()[0] == str(os.getpid())
    assert shell.OutputLock(tmp_path).acquire().held  # the same process: its own lock
    lock.release()
    assert not path.exists()
    _foreign_lock(tmp_path, os.getppid())  # a live process (this one's parent)
    with pytest.raises(ConfigError, match=f"is in use by a running torchflow command \\(pid {os.getppid()}"):
        shell.OutputLock(tmp_path).acquire()
    lock = shell.OutputLock(tmp_path)
    lock.held = True  # a holder whose lock another process replaced does not remove that one
    lock.release()
    assert path.exists()


def test_stale_locks_are_taken_over_dead_pid_and_reused_pid(tmp_path):
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    _foreign_lock(tmp_path, gone.pid)
    lock = shell.OutputLock(tmp_path).acquire()
    assert lock.took_over["pid"] == gone.pid and "took over the stale lock" in lock.takeover_message()
    lock.release()
    if not Path("/proc/self/stat").exists():
        pytest.skip("no /proc: a reused process id cannot be told")
    _foreign_lock(tmp_path, os.getppid(), mtime=time.time() - 10 * 365 * 86400)  # written before that process began
    lock = shell.OutputLock(tmp_path).acquire()
    assert lock.took_over["pid"] == os.getppid()
    lock.release()


def test_earlier_results_of_a_sweep_and_of_either_command(tmp_path):
    assert shell.earlier_results(tmp_path / "missing") == []
    (tmp_path / "learn.json").write_text("{}")
    (tmp_path / "run.log").write_text("")  # a log alone is no result
    assert shell.earlier_results(tmp_path) == ["learn.json"]
    (tmp_path / "3").mkdir()
    (tmp_path / "3" / "results.json").write_text("{}")
    assert shell.earlier_results(tmp_path, sweep=True) == ["3/results.json"]
    with pytest.raises(ConfigError, match="already holds the results of a run"):
        shell.guard_output_folder(tmp_path)
    shell.guard_output_folder(tmp_path, replace=True).release()
    assert not (tmp_path / shell.LOCK_NAME).exists()


def test_job_environment_sets_threads_and_knobs_and_refuses_bad_ones():
    import torch
    from omegaconf import OmegaConf

    from torchflow.core import tuning

    before = torch.get_num_threads(), tuning.as_dict()
    n = 2 if before[0] == 1 else 1  # a count other than this process's, so that setting it shows
    cfg = OmegaConf.create({"device": "cpu", "dtype": "float32", "threads": n, "tuning": {"points_per_call": 123}})
    with shell.job_environment(cfg) as env:
        assert (env.device.type, env.dtype, env.threads) == ("cpu", torch.float32, n)
        assert tuning.get().points_per_call == 123 and torch.get_num_threads() == n
    assert (torch.get_num_threads(), tuning.as_dict()) == before
    for bad, message in [
        ({"dtype": "float16"}, "dtype: expected one of"),
        ({"threads": 0}, "threads: expected"),
        ({"tuning": {"points_per_cal": 1}}, "unknown knob"),
        ({"device": "tpu"}, "device: expected"),
    ]:
        with pytest.raises(ConfigError, match=message):
            with shell.job_environment(OmegaConf.create({"device": "cpu", **bad})):
                pass


def test_stop_request_exit_codes_follow_the_signal():
    from torchflow.app.runner import STOP

    try:
        STOP.reset()
        STOP.handler(signal.SIGTERM, None)
        STOP.handler(signal.SIGINT, None)  # the first signal counts
        assert STOP.requested and STOP.exit_code == 143 and STOP.name == "SIGTERM"
        STOP.reset()
        STOP.handler(signal.SIGINT, None)
        assert STOP.exit_code == 130 and STOP.name == "Ctrl-C"
    finally:
        STOP.reset()


def test_both_configs_carry_every_speed_knob_and_the_output_guard():
    from torchflow.core import tuning

    for name in ("config", "learn"):
        cfg = yaml.safe_load((ROOT / "configs" / f"{name}.yaml").read_text())
        assert set(cfg["tuning"]) == set(tuning.as_dict()), name
        assert cfg["hydra"]["callbacks"]["output_guard"]["_target_"] == "torchflow.app.runner.shell.OutputGuard", name
        assert {"device", "dtype", "threads", "seed", "inits_per_track", "overwrite"} <= set(cfg), name


def test_sigterm_during_a_run_writes_the_finished_filters_and_exits_143(tmp_path):
    """The run command agrees with learning: SIGTERM is 143 (Ctrl-C 130: test_experiment)."""
    cmd = _argv(
        "run",
        "model=linear_gaussian",
        "filter=[kf,bpf]",
        "trials=200",
        "steps=200",
        "n_particles=20000",
        "progress=false",
        "plots=false",
        "checkpoint_dir=null",
        "hydra.run.dir=run",
    )
    with open(tmp_path / "err.txt", "w") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, cwd=tmp_path, env=_env())
        summary = tmp_path / "run" / "summary.partial.csv"  # the first filter is done
        deadline = time.time() + 60
        while not summary.exists() and time.time() < deadline and proc.poll() is None:
            time.sleep(0.1)
        assert summary.exists(), (tmp_path / "err.txt").read_text()[-2000:]
        assert (tmp_path / "run" / shell.LOCK_NAME).exists()
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)
    text = (tmp_path / "err.txt").read_text()
    assert proc.returncode == 143, text[-2000:]
    assert "interrupted by SIGTERM" in text and "Traceback" not in text
    assert json.loads((tmp_path / "run" / "results.json").read_text())["interrupted"] is True
    assert not (tmp_path / "run" / shell.LOCK_NAME).exists()


def test_a_run_says_where_its_wall_time_went(tmp_path):
    """The run command logs its wall seconds by phase (start-up, data, filters, scoring, writing,
    figures) and the memory budget it chose; results.json keeps the phases up to the filters'
    scoring. The phases add up to no more than the process's age."""
    r = _cli(
        tmp_path,
        "run",
        "model=linear_gaussian",
        "filter=[kf,bpf]",
        "trials=2",
        "steps=3",
        "n_particles=50",
        "progress=false",
        "plots=true",
        "hydra.run.dir=run",
    )
    assert r.returncode == 0, r.stderr[-2000:]
    log = (tmp_path / "run" / "run.log").read_text()
    line = next(ln for ln in log.splitlines() if "wall seconds:" in ln)
    found = dict(re.findall(r"(start-up|data|reference|filters|scoring|writing|figures) ([\d.]+)", line))
    assert set(found) == {"start-up", "data", "reference", "filters", "scoring", "writing", "figures"}, line
    total = float(re.search(r"; ([\d.]+) since the process started", line).group(1))
    assert sum(map(float, found.values())) <= total + 0.05 and float(found["start-up"]) > 0
    assert re.search(r"memory budget [\d.]+ GiB \(40% of the [\d.,]+ [MG]iB ", log), log[-2000:]
    timings = json.loads((tmp_path / "run" / "results.json").read_text())["timings"]
    assert set(timings) == {"startup", "plan", "reference", "filters", "scoring"} and timings["filters"] > 0


def test_a_run_whose_start_up_cannot_be_read_still_writes_its_results(tmp_path):
    """Where the process's age cannot be read (no ``/proc``), ``startup`` is ``None``: results.json
    records it as null and the log line leaves it out (no crash after the filters ran)."""
    from torchflow.app import cli
    from torchflow.app.runner import run_experiment, writers
    from torchflow.filters import KalmanFilter
    from torchflow.models import SensorNetwork

    model = SensorNetwork(d=4)
    res = run_experiment(model, {"kf": KalmanFilter(model)}, trials=2, steps=2, progress=False)
    res.timings = {"startup": None, **res.timings}
    writers.write_run(tmp_path, res, {})
    assert json.loads((tmp_path / "results.json").read_text())["timings"]["startup"] is None
    line = cli._timings_line(res.timings, None)
    assert line.startswith("wall seconds: data ") and "start-up" not in line
