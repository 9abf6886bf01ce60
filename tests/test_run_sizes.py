"""Run sizes and the phase before the filters: the size check refuses a run that cannot fit in
memory before anything is simulated; allocation failures of the simulation name trials and steps;
a long simulation logs its progress; a stop request (SIGINT, SIGTERM, or set in Python) ends the
simulation within a time step."""

import datetime
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import torch

from torchflow.app.runner import STOP, ConfigError, RunStopped, plan_run, run_experiment
from torchflow.app.runner import plan as plan_module
from torchflow.app.runner.shell import LOCK_NAME
from torchflow.core import progress as _progress
from torchflow.filters import BootstrapParticleFilter, KalmanFilter
from torchflow.models import AcousticTracking, SensorNetwork, SkewedTPoisson

ROOT = Path(__file__).resolve().parents[1]
GIB = 2**30


class _NoSimulation(SensorNetwork):
    """A model whose simulation fails the test if the run gets that far."""

    def simulate(self, batch_size, steps, generator=None):
        raise AssertionError("simulated a run the size check should have refused")


def _available(monkeypatch, nbytes):
    monkeypatch.setattr(plan_module, "available_memory", lambda device: (int(nbytes), "available RAM"))


def test_a_run_that_cannot_fit_in_memory_is_refused_before_simulating(monkeypatch):
    _available(monkeypatch, 2 * GIB)
    model = _NoSimulation(d=4)
    with pytest.raises(
        ConfigError,
        match=r"^trials=1000000000, steps=5: the run needs about [\d,.]+ GiB of memory "
        r"\(simulated data [\d,.]+ GiB, filter chunks .*, results [\d,.]+ GiB\), "
        r"more than the 2 GiB available RAM; lower trials or steps \(the simulated "
        r"data alone needs [\d,.]+ GiB; trial_range",
    ):
        run_experiment(model, {"kf": KalmanFilter(model)}, trials=10**9, steps=5, progress=False)


def _estimate(model, filters, trials, steps, chunk):
    s = plan_module.check_settings(
        trials=trials,
        steps=steps,
        seed=0,
        inits_per_track=1,
        chunk_size=chunk,
        memory_budget_gb=4.0,
        device="cpu",
        dtype="float64",
        rng_backend="auto",
        trial_range=None,
    )
    return plan_module.estimate_memory(model, filters, s, dict.fromkeys(filters, chunk))


def test_results_that_cannot_fit_suggest_running_the_trials_in_parts(monkeypatch):
    model = _NoSimulation(d=4)
    filters = {"kf": KalmanFilter(model), "bpf": BootstrapParticleFilter(model, n_particles=10)}
    est = _estimate(model, filters, 10**6, 100, 1000)
    assert est.data < est.results
    _available(monkeypatch, (est.data + est.total) / 2)
    with pytest.raises(
        ConfigError,
        match=r"lower trials or steps, or run the trials in parts with "
        r"trial_range=\[start, stop\] \(each part keeps only its trials' results\)",
    ):
        run_experiment(model, filters, trials=10**6, steps=100, chunk_size=1000, progress=False)


def test_a_run_that_needs_most_of_the_available_memory_warns(monkeypatch):
    model = SensorNetwork(d=4)
    est = _estimate(model, {"kf": KalmanFilter(model)}, 2, 3, 2)
    _available(monkeypatch, 1.5 * est.total)
    with pytest.warns(
        UserWarning,
        match=r"^trials=2, steps=3: the run needs about [\d.]+ MiB of memory \(.*\), "
        r"67% of the [\d.]+ MiB available RAM; it may run out of memory",
    ):
        res = run_experiment(model, {"kf": KalmanFilter(model)}, trials=2, steps=3, chunk_size=2, progress=False)
    assert len(res.per_trial) == 2


def test_the_estimate_covers_the_simulated_data_and_priors():
    for model in (SensorNetwork(d=4), SkewedTPoisson(), AcousticTracking()):
        plan = plan_run(model, {}, trials=3, steps=7, seed=0, inits_per_track=1)
        est = plan_module.estimate_memory(model, {}, plan.settings, {})
        traj = sum(t.numel() * t.element_size() for t in (plan.traj.states, plan.traj.observations))
        assert traj + sum(t.numel() * t.element_size() for t in (plan.mean0, plan.cov0)) <= est.data, model
        assert est.filters == est.results == 0  # no filters: nothing else is kept
    assert model.simulation_bytes(3, 7) > 10 * traj  # the acoustic model's whole-trajectory temporaries


def test_an_allocation_failure_in_the_simulation_names_trials_and_steps(monkeypatch):
    class _Refused(SensorNetwork):
        def simulate(self, batch_size, steps, generator=None):
            raise RuntimeError(
                "[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate "
                "memory: you tried to allocate 512000000000 bytes. Error code 12"
            )

    model = _Refused(d=4)
    with pytest.raises(
        ConfigError,
        match=r"^trials=4, steps=5: the simulation ran out of memory \(one allocation "
        r"of 477 GiB\); lower trials or steps$",
    ):
        run_experiment(model, {"kf": KalmanFilter(model)}, trials=4, steps=5, progress=False)


def test_every_simulation_loop_over_time_reports_each_step():
    for model, steps in ((SensorNetwork(d=4), 9), (SkewedTPoisson(), 9), (AcousticTracking(), 9)):
        seen = []
        with _progress.watching(lambda done, total: seen.append((done, total))):
            model.simulate(2, steps, torch.Generator().manual_seed(0))
        assert seen[:steps] == [(k, steps) for k in range(1, steps + 1)], type(model).__name__


def test_a_stop_request_ends_the_simulation_at_its_next_step():
    model = SensorNetwork(d=1)
    timer = threading.Timer(0.3, lambda: setattr(STOP, "requested", True))  # a request without a signal
    try:
        timer.start()
        t0 = time.perf_counter()
        with pytest.raises(RunStopped, match=r"^stopped by Ctrl-C during the simulation; nothing was computed$"):
            run_experiment(model, {"kf": KalmanFilter(model)}, trials=1, steps=10**6, progress=False)
        assert time.perf_counter() - t0 < 1.3
    finally:
        timer.cancel()
        STOP.reset()


def test_a_signal_during_the_simulation_raises_at_once_in_process():
    model = SensorNetwork(d=1)
    before = signal.signal(signal.SIGINT, STOP.handler)
    timer = threading.Timer(0.3, lambda: os.kill(os.getpid(), signal.SIGINT))
    try:
        timer.start()
        t0 = time.perf_counter()
        with pytest.raises(RunStopped, match="^stopped by Ctrl-C during the simulation"):
            plan_run(model, {}, trials=1, steps=10**6, seed=0)
        assert time.perf_counter() - t0 < 1.3 and STOP.exit_code == 130
    finally:
        timer.cancel()
        signal.signal(signal.SIGINT, before)
        STOP.reset()


# ---- the command line ----------------------------------------------------------------------------


def _env():
    return dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")


def test_the_command_refuses_a_run_that_cannot_fit_in_one_line_with_exit_2(tmp_path):
    cmd = [
        sys.executable,
        str(ROOT / "experiments" / "run.py"),
        "model=linear_gaussian",
        "filter=[kf,bpf]",
        "trials=1000000000",
        "steps=5",
        "n_particles=100",
        "plots=false",
        f"hydra.run.dir={tmp_path}/run",
    ]
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=120, env=_env())
    assert out.returncode == 2, out.stderr[-2000:]
    lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: trials=1000000000, steps=5: the run needs about "), lines
    assert "more than the" in lines[0] and "lower trials or steps" in lines[0]


def _stamp(line: str) -> float:
    return datetime.datetime.strptime(line[1:24], "%Y-%m-%d %H:%M:%S,%f").timestamp()


def test_sigint_during_the_simulation_stops_within_a_second_with_exit_130(tmp_path):
    _stop_the_command_during_the_simulation(tmp_path, signal.SIGINT, 130, "Ctrl-C")


def test_sigterm_during_the_simulation_stops_within_a_second_with_exit_143(tmp_path):
    _stop_the_command_during_the_simulation(tmp_path, signal.SIGTERM, 143, "SIGTERM")


def _stop_the_command_during_the_simulation(tmp_path, signum, code, name):
    """Once the simulation has logged its progress, the signal: the stop is logged within a second
    (the process then exits after Python's own teardown) with the signal's exit status; nothing is
    written."""
    run = tmp_path / "run"
    cmd = [
        sys.executable,
        str(ROOT / "experiments" / "run.py"),
        "model=linear_gaussian",
        "model.d=1",
        "filter=[kf]",
        "trials=1",
        "steps=500000",
        "progress=false",
        "plots=false",
        "checkpoint_dir=null",
        f"hydra.run.dir={run}",
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path, env=_env())
    try:
        deadline = time.time() + 60
        while proc.poll() is None and time.time() < deadline and "simulating: " not in _text(run / "run.log"):
            time.sleep(0.05)
        assert proc.poll() is None, proc.communicate()[1][-2000:]
        sent = time.time()
        proc.send_signal(signum)
        out, err = proc.communicate(timeout=30)
        exited = time.time() - sent
    finally:
        proc.kill()
    assert proc.returncode == code, err[-2000:]
    message = f"stopped by {name} during the simulation; nothing was computed"
    assert [ln for ln in err.splitlines() if ln.strip()] == [message]
    logged = [ln for ln in _text(run / "run.log").splitlines() if message in ln]
    assert logged and _stamp(logged[0]) - sent < 1.0, (logged, sent)
    assert exited < 3.0, exited
    assert not (run / "summary.csv").exists() and not (run / LOCK_NAME).exists()
    assert "simulating: " in _text(run / "run.log") and "of 500,000 steps" in _text(run / "run.log")


def _text(path: Path) -> str:
    try:
        return path.read_text()
    except OSError:
        return ""


def test_a_stop_during_the_learning_commands_simulation_says_nothing_was_fitted(monkeypatch, caplog):
    """The learning command ends a stop before its first fit as the run command does: the stop's own
    line and 128 + the signal, not the shell's generic 'outside the job's safe points'."""
    import torchflow.app.learn as learn_module

    def stopped(*args, **kwargs):
        STOP.handler(signal.SIGTERM, None)
        raise RunStopped("stopped by SIGTERM during the simulation; nothing was computed")

    monkeypatch.setattr(learn_module, "learn", stopped)
    try:
        with caplog.at_level("WARNING", logger="torchflow"):
            assert learn_module._job(None, None, None) == 143
        assert "stopped by SIGTERM during the simulation; nothing was computed" in caplog.text
    finally:
        STOP.reset()


def test_the_default_memory_budget_is_a_share_of_the_free_memory(monkeypatch):
    """``memory_budget_gb`` unset (``None`` or ``"auto"``): MEMORY_BUDGET_SHARE of what the device
    has free when the run is planned, rounded down to a power of two GiB (stable chunks while the
    free memory moves a little), which sizes the chunks and is recorded with where it came from; a
    given budget is recorded as given."""
    from torchflow.app.runner.plan import MEMORY_BUDGET_SHARE

    model = SensorNetwork(d=4)
    f = BootstrapParticleFilter(model, n_particles=50)
    for given, free, budget in ((None, 10, 4.0), ("auto", 12, 4.0), (None, 3, 1.0)):  # 40%, down to a power of 2
        _available(monkeypatch, free * GIB)
        res = run_experiment(model, {"bpf": f}, trials=3, steps=2, memory_budget_gb=given, progress=False)
        assert MEMORY_BUDGET_SHARE == 0.4 and res.config["memory_budget_gb"] == budget
        assert res.config["memory_budget"] == f"40% of the {free} GiB available RAM, rounded down to a power of two"
    # the chunks follow the budget: a machine with almost nothing free runs one trial per chunk
    per_trial = f.bytes_per_trial()
    _available(monkeypatch, 1.5 * per_trial / MEMORY_BUDGET_SHARE)
    res = run_experiment(model, {"bpf": f}, trials=3, steps=2, progress=False)
    assert res.config["chunk_size"] == {"bpf": 1}
    res = run_experiment(model, {"bpf": f}, trials=3, steps=2, memory_budget_gb=4.0, progress=False)
    assert res.config["memory_budget_gb"] == 4.0 and res.config["memory_budget"] == "given"


def test_a_budget_below_one_trial_of_a_filter_that_cannot_split_it_is_warned_and_recorded():
    """Q79: ``memory_budget_gb=1e-9`` ran the ETKF silently (one trial is kilobytes and an ensemble
    filter has no particle blocks) and results.json recorded the budget as 0.0."""
    from torchflow.filters import EnsembleTransformKalmanFilter
    from torchflow.models import Lorenz96

    model = Lorenz96(d=8)
    f = EnsembleTransformKalmanFilter(model, n_particles=10)
    with pytest.warns(
        UserWarning,
        match=r"memory_budget_gb=1e-09: one trial of EnsembleTransformKalmanFilter is estimated at .* over the budget",
    ):
        res = run_experiment(model, {"etkf": f}, trials=2, steps=2, memory_budget_gb=1e-9, progress=False)
    assert res.config["memory_budget_gb"] == 1e-9 and res.config["chunk_size"] == {"etkf": 1}


def test_a_given_local_chunk_is_not_called_no_smaller_unit_of_work():
    """The one-trial budget warning is for filters with nothing smaller to run; a LETKF given its own
    ``local_chunk`` has a smaller unit (the user's), so the warning does not claim otherwise."""
    import warnings

    from torchflow.filters import LocalEnsembleTransformKalmanFilter
    from torchflow.models import Lorenz96

    model = Lorenz96(d=8)
    f = LocalEnsembleTransformKalmanFilter(model, n_particles=10, radius=3.0, local_chunk=2)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        run_experiment(model, {"letkf": f}, trials=2, steps=2, memory_budget_gb=1e-9, progress=False)
    assert not [w for w in seen if "no smaller unit of work" in str(w.message)]
