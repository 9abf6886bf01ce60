"""Bad input and faults around the run command: keys Hydra refuses, values its grammar cannot read,
selections, output folders (quoted, full), resuming, sweeps (overwrite, a stop on joblib) and
``collect.py``. Each fault gets one line that names what is wrong (exit status 2 for a setting) or a
warning, and nothing half done on disk. Subprocess runs are tiny (a few seconds each)."""
import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from torchflow.runner import ConfigError, shell
from torchflow.runner.config import check_selections

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "experiments" / "run.py"
TINY = ["model=linear_gaussian", "model.d=4", "trials=2", "steps=3", "n_particles=20", "progress=false", "plots=false"]


def _env():
    return dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")


def _run(cwd, *args, script=RUN):
    return subprocess.run([sys.executable, str(script), *args], capture_output=True, text=True, cwd=cwd, timeout=180,
                          env=_env())


def _lines(text):
    return [ln for ln in text.splitlines() if ln.strip()]


# ----------------------------------------------------------------------------------------------
# settings Hydra refuses or cannot read


def test_a_filter_selected_twice_is_refused_in_one_line_with_exit_2(capsys):
    from torchflow.cli import main

    with pytest.raises(SystemExit) as stop:
        main(["model=linear_gaussian", "filter=[bpf,kf,bpf]", "trials=4"])
    assert stop.value.code == 2
    assert _lines(capsys.readouterr().err) == [
        "error: filter: expected each filter config once, got bpf 2 times in [bpf,kf,bpf] (one row per config); "
        "select it once, and to compare settings of one filter, sweep them: -m filter.bpf.<key>=a,b"]


def test_a_sweep_over_lists_of_filters_is_not_refused():
    check_selections(["-m", "filter=[kf],[bpf,ekf]"])
    with pytest.raises(ConfigError, match=r"filter: unknown filter config 'bfp'"):
        check_selections(["-m", "filter=[kf],[bfp]"])
    with pytest.raises(ConfigError, match=r"got kf 2 times in \[kf,kf\]"):
        check_selections(["-m", "filter=[bpf],[kf,kf]"])


@pytest.mark.parametrize("trials, inits_per_track, warning, groups", [
    (4, 3, "inits_per_track=3 does not divide trials=4: the last trajectory is shared by 1 trial, the others by 3 "
           "(trials=6 keeps the groups equal)", [3, 1]),
    (4, 10, "inits_per_track=10 is more than trials=4: all 4 trials share one trajectory", [4]),
    (6, 3, None, [3, 3]),
])
def test_inits_per_track_that_leaves_unequal_groups_of_trials_warns(trials, inits_per_track, warning, groups):
    import warnings

    import torch

    from torchflow.models import SensorNetwork
    from torchflow.runner.execute import plan_run

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        plan = plan_run(SensorNetwork(d=4), {}, trials=trials, steps=2, seed=0, inits_per_track=inits_per_track)
    said = [str(w.message) for w in seen if "inits_per_track" in str(w.message)]
    assert said == [] if warning is None else (len(said) == 1 and said[0].startswith(warning)), said
    states = plan.traj.states  # the groups the warning describes are the trials that share a trajectory
    sizes, start = [], 0
    while start < trials:
        same = [torch.equal(states[start], states[i]) for i in range(start, trials)]
        sizes.append(same.index(False) if False in same else len(same))
        start += sizes[-1]
    assert sizes == groups


# ----------------------------------------------------------------------------------------------
# output folders and checkpoints


def test_resume_with_nothing_saved_says_so_and_computes_every_chunk(tmp_path, caplog):
    import torch
    from hydra import compose, initialize_config_dir

    from torchflow.cli import chunk_store

    with initialize_config_dir(str(ROOT / "configs"), version_base="1.3"):
        cfg = compose("config", ["model=linear_gaussian", "filter=[kf,bpf]", "resume=true",
                                 f"checkpoint_dir={tmp_path / 'ck'}"])
    labels = {"kf": "kf", "bpf": "bpf"}
    with caplog.at_level(logging.WARNING, logger="torchflow.cli"):
        store = chunk_store(cfg, labels)
    assert [r.getMessage() for r in caplog.records] == [
        f"resume=true: nothing is saved under {tmp_path / 'ck'} with these settings (a new folder, or settings other "
        "than the saved run's, which save under another key): every chunk is computed"]
    store.save("kf", 0, 2, {"estimates": torch.zeros(2, 3, 4)})
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="torchflow.cli"):
        chunk_store(cfg, labels)
    assert [r.getMessage() for r in caplog.records] == [
        f"resume=true: nothing is saved under {tmp_path / 'ck'} for bpf with these settings: their chunks are computed"]
    caplog.clear()
    cfg.resume = False
    with caplog.at_level(logging.WARNING, logger="torchflow.cli"):
        chunk_store(cfg, labels)
    assert caplog.records == []  # not resuming: nothing to say
