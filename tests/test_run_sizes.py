"""Run sizes: the size check refuses a run that cannot fit in memory before anything is simulated;
allocation failures of the simulation name trials and steps."""
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from torchflow import _progress
from torchflow.experiment import run_experiment
from torchflow.filters import BootstrapParticleFilter, KalmanFilter
from torchflow.models import AcousticTracking, SensorNetwork, SkewedTPoisson
from torchflow.runner import ConfigError, plan_run
from torchflow.runner import plan as plan_module

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
    with pytest.raises(ConfigError, match=r"^trials=1000000000, steps=5: the run needs about [\d,.]+ GiB of memory "
                                          r"\(simulated data [\d,.]+ GiB, filter chunks .*, results [\d,.]+ GiB\), "
                                          r"more than the 2 GiB available RAM; lower trials or steps \(the simulated "
                                          r"data alone needs [\d,.]+ GiB; trial_range"):
        run_experiment(model, {"kf": KalmanFilter(model)}, trials=10**9, steps=5, progress=False)


def _estimate(model, filters, trials, steps, chunk):
    s = plan_module.check_settings(trials=trials, steps=steps, seed=0, inits_per_track=1, chunk_size=chunk,
                                   memory_budget_gb=4.0, device="cpu", dtype="float64", rng_backend="auto",
                                   trial_range=None)
    return plan_module.estimate_memory(model, filters, s, dict.fromkeys(filters, chunk))


def test_results_that_cannot_fit_suggest_running_the_trials_in_parts(monkeypatch):
    model = _NoSimulation(d=4)
    filters = {"kf": KalmanFilter(model), "bpf": BootstrapParticleFilter(model, n_particles=10)}
    est = _estimate(model, filters, 10**6, 100, 1000)
    assert est.data < est.results
    _available(monkeypatch, (est.data + est.total) / 2)
    with pytest.raises(ConfigError, match=r"lower trials or steps, or run the trials in parts with "
                                          r"trial_range=\[start, stop\] \(each part keeps only its trials' results\)"):
        run_experiment(model, filters, trials=10**6, steps=100, chunk_size=1000, progress=False)


def test_a_run_that_needs_most_of_the_available_memory_warns(monkeypatch):
    model = SensorNetwork(d=4)
    est = _estimate(model, {"kf": KalmanFilter(model)}, 2, 3, 2)
    _available(monkeypatch, 1.5 * est.total)
    with pytest.warns(UserWarning, match=r"^trials=2, steps=3: the run needs about [\d.]+ MiB of memory \(.*\), "
                                         r"67% of the [\d.]+ MiB available RAM; it may run out of memory"):
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
            raise RuntimeError("[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate "
                               "memory: you tried to allocate 512000000000 bytes. Error code 12")

    model = _Refused(d=4)
    with pytest.raises(ConfigError, match=r"^trials=4, steps=5: the simulation ran out of memory \(one allocation "
                                          r"of 477 GiB\); lower trials or steps$"):
        run_experiment(model, {"kf": KalmanFilter(model)}, trials=4, steps=5, progress=False)


def test_every_simulation_loop_over_time_reports_each_step():
    for model, steps in ((SensorNetwork(d=4), 9), (SkewedTPoisson(), 9), (AcousticTracking(), 9)):
        seen = []
        with _progress.watching(lambda done, total: seen.append((done, total))):
            model.simulate(2, steps, torch.Generator().manual_seed(0))
        assert seen[:steps] == [(k, steps) for k in range(1, steps + 1)], type(model).__name__


# ---- the command line ----------------------------------------------------------------------------


def _env():
    return dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")


def test_the_command_refuses_a_run_that_cannot_fit_in_one_line_with_exit_2(tmp_path):
    cmd = [sys.executable, str(ROOT / "experiments" / "run.py"), "model=linear_gaussian", "filter=[kf,bpf]",
           "trials=1000000000", "steps=5", "n_particles=100", "plots=false", f"hydra.run.dir={tmp_path}/run"]
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=120, env=_env())
    assert out.returncode == 2, out.stderr[-2000:]
    lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: trials=1000000000, steps=5: the run needs about "), lines
    assert "more than the" in lines[0] and "lower trials or steps" in lines[0]
