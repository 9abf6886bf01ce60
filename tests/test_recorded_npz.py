"""Recorded data with their truth and prior: a ``.npz`` file of ``observations`` and, optionally,
``states``, ``prior_mean`` and ``prior_cov``, and the prior on the command line."""

import csv

import numpy as np
import pytest
import torch

from tests.test_recorded_data import _command
from torchflow.app.data import load_recording, prior_from_spec
from torchflow.app.runner import ConfigError, plan_run, run_experiment
from torchflow.core.errors import ArgumentError
from torchflow.filters import BootstrapParticleFilter, EnsembleKalmanFilter, KalmanFilter
from torchflow.models import Lorenz96, SensorNetwork


def _save(path, **arrays):
    np.savez(path, **{k: (v.numpy() if isinstance(v, torch.Tensor) else v) for k, v in arrays.items()})
    return path


def test_a_simulation_saved_and_read_back_scores_the_same_numbers(tmp_path):
    """The runner's simulation written as a recording (observations, states, the trials' prior)
    and filtered from the file: every per-trial number is the simulation's."""
    model = SensorNetwork(d=4)
    filters = {"kf": KalmanFilter(model), "bpf": BootstrapParticleFilter(model, n_particles=50)}
    sim = run_experiment(model, filters, trials=3, steps=8, seed=4, progress=False)
    plan = plan_run(model, {}, trials=3, steps=8, seed=4)
    path = _save(
        tmp_path / "sim.npz",
        observations=plan.traj.observations,
        states=plan.traj.states,
        prior_mean=plan.mean0,
        prior_cov=plan.cov0,
    )
    rec = load_recording(path, model)
    assert rec.observations.shape == (3, 8, 4) and rec.states.shape == (3, 9, 4) and rec.prior[1].shape == (3, 4, 4)
    got = run_experiment(
        model, filters, observations=rec.observations, states=rec.states, prior=rec.prior, seed=4, progress=False
    )
    assert not got.recorded and got.summary[0]["rmse"] is not None
    assert [r["rmse"] for r in got.per_trial] == [r["rmse"] for r in sim.per_trial]
    assert [r["log_evidence"] for r in got.per_trial] == [r["log_evidence"] for r in sim.per_trial]


def test_lorenz96_with_states_and_no_prior_is_scored_from_a_prior_around_its_initial_state(tmp_path):
    """Lorenz-96 declares no prior: with the true states the prior is drawn around the initial
    state, as in a simulation; without states and without a prior the error says how to give one."""
    l96 = Lorenz96(d=8)
    traj = l96.simulate(1, 15, torch.Generator().manual_seed(0))
    rec = load_recording(_save(tmp_path / "a.npz", observations=traj.observations[0], states=traj.states[0]), l96)
    res = run_experiment(
        l96,
        {"enkf": EnsembleKalmanFilter(l96, n_particles=20)},
        observations=rec.observations,
        states=rec.states,
        trials=2,
        progress=False,
    )
    assert res.summary[0]["error"] is None and 0 < res.summary[0]["rmse"] < 3.0
    with pytest.raises(ConfigError, match="declares no prior.*prior.mean"):
        run_experiment(l96, {}, observations=rec.observations, progress=False)


@pytest.mark.parametrize(
    "arrays, message",
    [
        (
            {"obs": np.zeros((4, 4))},
            "expected arrays named observations, states, prior_mean, prior_cov in x.npz, got obs",
        ),
        ({"states": np.zeros((5, 4))}, "expected an array named observations in x.npz, got states"),
        ({"observations": np.zeros((4, 4)), "states": np.zeros((4, 4))}, "expected states of shape \\(5, 4\\)"),
        (
            {"observations": np.zeros((2, 4, 4)), "states": np.zeros((5, 4))},
            "expected states of shape \\(2, 5, 4\\)",
        ),
        ({"observations": np.zeros((4, 4)), "states": np.full((5, 4), np.nan)}, "expected finite states"),
        ({"observations": np.zeros((4, 4)), "prior_mean": np.zeros(4)}, "prior_mean without prior_cov"),
        (
            {"observations": np.zeros((4, 4)), "prior_mean": np.zeros(4), "prior_cov": -np.eye(4)},
            "prior cov: expected a positive semi-definite covariance",
        ),
        (
            {"observations": np.zeros((4, 4)), "prior_mean": np.zeros(3), "prior_cov": np.eye(4)},
            "prior mean: expected shape \\(4,\\) or \\(B, 4\\), got \\(3,\\)",
        ),
        (
            {"observations": np.zeros((4, 4)), "prior_mean": np.zeros(4), "prior_cov": np.triu(np.ones((4, 4)))},
            "expected a symmetric covariance",
        ),
        ({"observations": np.array(["a", "b"])}, "expected a numeric"),
    ],
)
def test_bad_recordings_are_refused_naming_the_array(tmp_path, arrays, message):
    path = _save(tmp_path / "x.npz", **arrays)
    with pytest.raises(ArgumentError, match=message):
        load_recording(path, SensorNetwork(d=4))


def test_a_file_that_is_not_an_npz_is_named(tmp_path):
    (tmp_path / "z.npz").write_text("1,2,3,4\n")
    with pytest.raises(ArgumentError, match="data: expected a NumPy .npz file \\(numpy.savez\\), could not read"):
        load_recording(tmp_path / "z.npz", SensorNetwork(d=4))


def test_the_command_line_s_prior_forms():
    m, c = prior_from_spec(2.0, 3.0, 3)
    assert m.tolist() == [2.0] * 3 and c.tolist() == (3.0 * torch.eye(3, dtype=torch.float64)).tolist()
    m, c = prior_from_spec([1, 2, 3], [1, 2, 3], 3)
    assert m.tolist() == [1.0, 2.0, 3.0] and c.diagonal().tolist() == [1.0, 2.0, 3.0] and c[0, 1] == 0
    full = [[2.0, 0.5], [0.5, 1.0]]
    assert prior_from_spec(0, full, 2)[1].tolist() == full
    for mean, cov, message in (
        ([1, 2], 1.0, "prior.mean: expected a number or 3 numbers"),
        (0, [1, 2], "prior.cov: expected a number \\(times the identity\\), 3 variances"),
        (0, -1.0, "positive semi-definite"),
        ("x", 1.0, "prior.mean: expected numbers"),
    ):
        with pytest.raises(ArgumentError, match=message):
            prior_from_spec(mean, cov, 3)


def test_the_command_line_filters_lorenz96_from_a_dapper_user_s_arrays(tmp_path):
    """The guide's example: a DAPPER user's ``xx`` (truth from time 0) and ``yy`` (one row per
    observation) saved with ``numpy.savez``; with the truth the run is scored (and its lost trials
    written), without it the prior comes from the command line and the summary has no RMSE."""
    l96 = Lorenz96(d=8)
    traj = l96.simulate(1, 12, torch.Generator().manual_seed(3))
    xx, yy = traj.states[0].numpy(), traj.observations[0].numpy()
    np.savez(tmp_path / "scored.npz", observations=yy, states=xx)
    np.savez(tmp_path / "bare.npz", observations=yy)
    common = ["model=lorenz96", "model.d=8", "filter=[enkf]", "n_particles=20", "trials=2", "progress=false"]
    common += ["plots=false", "checkpoint_dir=null"]
    # scored from the file's states; a threshold no trial meets loses both (summary.csv counts them,
    # per_trial.csv names them and keeps their RMSE)
    r = _command("run.py", tmp_path, *common, "data=scored.npz", "metrics.lost_rmse=1e-6")
    assert r.returncode == 0, r.stderr[-3000:]
    row = next(csv.DictReader(open(tmp_path / "out" / "summary.csv")))
    assert row["lost_trials"] == "2" and row["rmse"] == "" and row["trials"] == "2"
    per = list(csv.DictReader(open(tmp_path / "out" / "per_trial.csv")))
    assert [p["lost_trial"] for p in per] == ["True"] * 2 and all(float(p["rmse"]) > 1e-6 for p in per)
    assert [p["lost_step"] for p in per] == ["0", "0"]
    r = _command("run.py", tmp_path, *common, "data=bare.npz", "prior.mean=3.0", "prior.cov=1.0", "overwrite=true")
    assert r.returncode == 0, r.stderr[-3000:]
    row = next(csv.DictReader(open(tmp_path / "out" / "summary.csv")))
    assert row["rmse"] == "" and float(row["ess"]) > 0


def test_the_command_line_s_prior_is_read_over_the_file_s_and_refused_without_data(tmp_path):
    """``prior.mean`` / ``prior.cov`` (:func:`recorded_data`): each over the file's; one alone with
    none in the file, or either without ``data=``, is a one-line error."""
    from omegaconf import OmegaConf

    from torchflow.app.runner.config import recorded_data

    l96 = Lorenz96(d=4)
    traj = l96.simulate(1, 5, torch.Generator().manual_seed(0))
    yy = traj.observations[0].numpy()
    np.savez(tmp_path / "bare.npz", observations=yy)
    np.savez(tmp_path / "prior.npz", observations=yy, prior_mean=np.ones(4), prior_cov=2 * np.eye(4))

    def read(name, **prior):
        cfg = {"data": str(tmp_path / name) if name else None, "trials": 2, "steps": 5, "prior": prior}
        return recorded_data(OmegaConf.create(cfg), l96)

    assert read("bare.npz").prior is None and read("prior.npz").prior[0].tolist() == [1.0] * 4
    m, c = read("prior.npz", mean=[0, 1, 2, 3]).prior  # the mean from the command line, the cov from the file
    assert m.tolist() == [0.0, 1.0, 2.0, 3.0] and c.diagonal().tolist() == [2.0] * 4
    m, c = read("bare.npz", mean=3.0, cov=[1, 2, 3, 4]).prior
    assert m.tolist() == [3.0] * 4 and c.diagonal().tolist() == [1.0, 2.0, 3.0, 4.0]
    with pytest.raises(ConfigError, match="prior.cov: expected it with prior.mean, got null"):
        read("bare.npz", mean=3.0)
    with pytest.raises(ConfigError, match="prior.mean: expected null without data="):
        read(None, mean=3.0)
    with pytest.raises(ConfigError, match="prior.mean: expected a number or 4 numbers"):
        read("bare.npz", mean=[1, 2], cov=1.0)


def test_the_guide_s_dapper_user_example_runs(tmp_path, monkeypatch, capsys):
    """The data-assimilation guide's example of a DAPPER user's arrays, as printed there."""
    import re

    from tests.conftest import ROOT

    guide = (ROOT / "docs" / "guide" / "data-assimilation.md").read_text()
    block = next(b for b in re.findall(r"```python\n(.*?)```", guide, re.S) if "load_recording" in b)
    monkeypatch.chdir(tmp_path)
    exec(compile(block, "data-assimilation.md", "exec"), {})
    rmse, lost = capsys.readouterr().out.split()
    assert 0 < float(rmse) < 1.5 and lost == "0" and (tmp_path / "l96.npz").exists()
