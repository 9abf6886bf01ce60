"""Recorded observations: reading files, filtering them (runner, command line), learning on them."""

import csv
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from tests.conftest import ROOT
from torchflow.app.data import declared_prior, load_observations
from torchflow.app.runner import ConfigError, run_experiment
from torchflow.core.errors import ArgumentError
from torchflow.core.random import TrialStreams
from torchflow.filters import BootstrapParticleFilter, KalmanFilter
from torchflow.models import TDOA3D, AcousticTracking, LinearGaussian, Lorenz96, SensorNetwork, SkewedTPoisson

ONE = torch.ones(1, 1, dtype=torch.float64)


class StationaryAR(LinearGaussian):
    """AR(1) observed in noise whose prior is the stationary law ``N(0, q / (1 - phi^2))``: it moves
    with a learnable ``phi`` (``F``)."""

    def declared_prior(self, batch_size):
        var = self.Q / (1 - self.F**2)
        return self.m0.expand(batch_size, 1), var.expand(batch_size, 1, 1)


def _ar(phi, learn=False):
    return StationaryAR(
        phi * ONE,
        0.5 * ONE,
        ONE,
        0.3 * ONE,
        torch.zeros(1, dtype=torch.float64),
        ONE,
        learnable=["F"] if learn else False,
    )


def _series(model, T, seed=0):
    return model.simulate(1, T, torch.Generator().manual_seed(seed)).observations[0]  # (T, m)


def _write_csv(path, z, header=True, time_step=None):
    with open(path, "w") as fh:
        if header:
            fh.write(
                ",".join((["time"] if time_step is not None else []) + [f"z{j}" for j in range(z.shape[1])]) + "\n"
            )
        for t, row in enumerate(z.tolist()):
            cells = [repr(t * time_step)] if time_step is not None else []
            fh.write(",".join(cells + ["" if v != v else repr(v) for v in row]) + "\n")
    return path


# ---- files ---------------------------------------------------------------------------------------


def test_csv_and_npy_read_back_the_series(tmp_path):
    z = _series(SensorNetwork(d=4), 6).numpy()
    for header, dt in ((True, None), (False, None), (True, 0.5)):
        got = load_observations(_write_csv(tmp_path / "z.csv", z, header, dt))
        assert got.dtype == torch.float64 and torch.equal(got, torch.from_numpy(z))
    np.save(tmp_path / "z.npy", z)
    np.save(tmp_path / "zb.npy", np.stack([z, 2 * z]))
    assert torch.equal(load_observations(tmp_path / "z.npy"), torch.from_numpy(z))
    assert load_observations(tmp_path / "zb.npy").shape == (2, 6, 4)
    model = SensorNetwork(d=4).to(torch.float32)
    assert load_observations(tmp_path / "z.npy", model).dtype == torch.float32


def test_an_empty_cell_or_nan_is_not_observed_and_kept(tmp_path):
    z = _series(SensorNetwork(d=4), 5).numpy()
    z[1, 2] = np.nan
    path = _write_csv(tmp_path / "z.csv", z)  # an empty cell
    row = z[3].tolist()  # Python floats: their repr is what _write_csv wrote (numpy 2's repr is np.float64(...))
    text = path.read_text().replace(
        "\n" + ",".join(repr(v) for v in row), "\n" + ",".join(["nan"] + [repr(v) for v in row[1:]])
    )
    path.write_text(text)
    got = load_observations(path, SensorNetwork(d=4))
    assert torch.isnan(got[1, 2]) and torch.isnan(got[3, 0]) and int(torch.isnan(got).sum()) == 2


@pytest.mark.parametrize(
    "content, name, message",
    [
        (None, "missing.csv", "data: file not found"),
        ("z0,z1,z2,z3\n1,2,3\n", "z.csv", "expected 4 columns in every row"),
        ("z0,z1,z2,z3\n1,2,x,4\n", "z.csv", "got 'x' in line 2, column 3 (z2)"),
        ("1,2,3,inf\n", "z.csv", "got 1 infinite, the first at row 1, column 4"),
        ("1,2,3\n", "z.csv", "expected m = 4 measurement coordinates (columns) for SensorNetwork, got 3"),
        ("1,2,3,4\n", "z.txt", "expected a .csv, .npy or .npz file"),
        ("", "z.csv", "got an empty file"),
    ],
)
def test_bad_files_are_refused_naming_the_argument(tmp_path, content, name, message):
    path = tmp_path / name
    if content is not None:
        path.write_text(content)
    with pytest.raises(ArgumentError, match="^data") as e:
        load_observations(path, SensorNetwork(d=4))
    assert message in str(e.value)


def test_a_time_column_must_step_by_the_model_s_dt(tmp_path):
    model = Lorenz96(d=4)  # dt = 0.05
    z = np.zeros((4, 4))
    assert load_observations(_write_csv(tmp_path / "ok.csv", z, time_step=0.05), model).shape == (4, 4)
    with pytest.raises(ArgumentError, match="steps are 0.1, but Lorenz96 assumes observations every dt = 0.05"):
        load_observations(_write_csv(tmp_path / "bad.csv", z, time_step=0.1), model)
    (tmp_path / "uneven.csv").write_text("t,a,b,c,d\n0,1,1,1,1\n0.05,1,1,1,1\n0.2,1,1,1,1\n")
    with pytest.raises(ArgumentError, match=r"uniform time step, got 0.05 and then 0.15 \(row 3"):
        load_observations(tmp_path / "uneven.csv", model)
    assert load_observations(
        _write_csv(tmp_path / "any.csv", np.zeros((3, 4)), time_step=0.3), SensorNetwork(d=4)
    ).shape == (3, 4)  # no dt: any times


# ---- the prior without true states ------------------------------------------------------------------


def test_every_built_in_model_s_prior_without_true_states():
    lg = SensorNetwork(d=4)
    mean, cov = declared_prior(lg, 3)
    assert torch.equal(mean, lg.m0.expand(3, -1)) and torch.equal(cov, lg.P0.expand(3, -1, -1))
    ac = AcousticTracking()
    mean, cov = declared_prior(ac, 2)
    assert torch.equal(mean, ac.x0.expand(2, -1)) and torch.equal(cov[0].diagonal(), ac.prior_std**2)
    st = SkewedTPoisson(d=4)
    mean, cov = declared_prior(st, 2)
    assert torch.equal(mean, torch.zeros(2, 4, dtype=torch.float64)) and cov.shape == (2, 4, 4)
    with pytest.raises(ArgumentError, match="Lorenz96 declares no prior without true states.*prior=\\(mean, cov\\)"):
        declared_prior(Lorenz96(d=4), 2)
    with pytest.raises(ConfigError, match="padded sets"):
        run_experiment(
            TDOA3D(), {}, observations=torch.zeros(5, TDOA3D().obs_dim or 1, dtype=torch.float64), progress=False
        )


# ---- the runner ---------------------------------------------------------------------------------


def test_each_trial_filters_the_recorded_series_with_its_own_stream():
    """(T, m): every trial filters the one series from the declared prior; the Kalman filter's
    log-evidence is that of the series, the bootstrap PF's trials are its own calls with the
    runner's per-trial streams; no metric that needs the truth, the log-evidence's standard error."""
    model = SensorNetwork(d=4)
    z = _series(model, 8)
    filters = {"kf": KalmanFilter(model), "bpf": BootstrapParticleFilter(model, n_particles=64)}
    res = run_experiment(model, filters, observations=z, trials=3, seed=4, progress=False)
    kf, bpf = res.summary
    assert kf["trials"] == bpf["trials"] == 3 and kf["steps"] == 8 and res.recorded
    assert all(r.get("mse") is None and r.get("omat") is None for r in res.summary) and bpf["ess"] > 0
    m0, P0 = model.declared_prior(1)
    exact = float(KalmanFilter(model)(z[None], m0, P0).log_evidence)
    assert kf["log_evidence"] == pytest.approx(exact, rel=1e-12) and kf["log_evidence_se"] == pytest.approx(0, abs=1e-9)
    B = 3
    direct = filters["bpf"](
        z.expand(B, -1, -1).contiguous(),
        m0.expand(B, -1),
        P0.expand(B, -1, -1),
        TrialStreams(4, range(B), key=filters["bpf"].stream_name),
    ).log_evidence
    per_trial = torch.tensor([r["log_evidence"] for r in res.per_trial if r["filter"] == "bpf"], dtype=torch.float64)
    assert torch.equal(per_trial, direct) and len(set(per_trial.tolist())) == B  # independent runs
    assert bpf["log_evidence_se"] == pytest.approx(float(direct.std() / B**0.5), rel=1e-12)
    mean, sd, spread = res.estimate_summary["bpf"]
    assert mean.shape == sd.shape == spread.shape == (8, 4) and bool((spread > 0).all())
    # the filtering sd is the filter's own: the Kalman filter's is its covariance's diagonal
    kf_mean, kf_sd, kf_spread = res.estimate_summary["kf"]
    kf_direct = KalmanFilter(model)(z[None], m0, P0, return_covariances=True)
    torch.testing.assert_close(kf_sd, kf_direct.covariances[0].diagonal(dim1=-2, dim2=-1).sqrt())
    assert float(kf_spread.abs().max()) == 0
    # the bootstrap PF's spread of the same law (64 particles, 3 runs: within 25 % on average)
    assert float(((sd - kf_sd) / kf_sd).abs().mean()) < 0.25
    assert res.trajectory.states is None and all("mse" not in r for r in res.per_step)


def test_a_batch_of_series_is_one_trial_each_and_sizes_are_checked():
    model = SensorNetwork(d=4)
    z = model.simulate(2, 5, torch.Generator().manual_seed(1)).observations  # (2, 5, 4)
    res = run_experiment(model, {"kf": KalmanFilter(model)}, observations=z, progress=False)
    m0, P0 = model.declared_prior(2)
    assert res.summary[0]["trials"] == 2
    assert [r["log_evidence"] for r in res.per_trial] == pytest.approx(
        KalmanFilter(model)(z, m0, P0).log_evidence.tolist(), rel=1e-12
    )
    for kw, message in (
        ({"trials": 3}, "trials: expected the number of recorded series B = 2"),
        ({"steps": 4}, "steps: expected the recorded series' length T = 5"),
        ({"inits_per_track": 2}, "inits_per_track: expected 1 with recorded data"),
        ({"simulator": lambda *a: None}, "give observations or simulator, not both"),
    ):
        with pytest.raises(ConfigError, match=message):
            run_experiment(model, {"kf": KalmanFilter(model)}, observations=z, progress=False, **kw)
    with pytest.raises(ConfigError, match="expected m = 4"):
        run_experiment(model, {}, observations=z[..., :3], progress=False)


def test_a_model_without_a_declared_prior_takes_one_given():
    from torchflow.filters import ExtendedKalmanFilter

    l96 = Lorenz96(d=8)
    z = _series(l96, 5)
    with pytest.raises(ConfigError, match="declares no prior"):
        run_experiment(l96, {"ekf": ExtendedKalmanFilter(l96)}, observations=z, progress=False)
    prior = (torch.full((8,), 8.0, dtype=torch.float64), 4.0 * torch.eye(8, dtype=torch.float64))
    res = run_experiment(l96, {"ekf": ExtendedKalmanFilter(l96)}, observations=z, prior=prior, trials=2, progress=False)
    assert res.summary[0]["error"] is None and res.summary[0]["log_evidence"] < 0
    with pytest.raises(ConfigError, match="prior: expected \\(mean, cov\\)"):
        run_experiment(l96, {}, observations=z, prior=(prior[0][:3], prior[1]), progress=False)


def test_a_series_with_unobserved_coordinates_is_filtered():
    model = SensorNetwork(d=4)
    z = _series(model, 6).clone()
    z[2, 1] = float("nan")
    res = run_experiment(
        model,
        {"kf": KalmanFilter(model), "bpf": BootstrapParticleFilter(model, n_particles=32)},
        observations=z,
        trials=2,
        progress=False,
    )
    assert all(r["error"] is None and np.isfinite(r["log_evidence"]) for r in res.summary)
    # the gap reaches the filters as a gap: the runner's Kalman evidence is that of the series with
    # the coordinate unobserved, not of one with a zero there
    mean, cov = declared_prior(model, 1)
    with torch.no_grad():
        gap = float(KalmanFilter(model)(z.unsqueeze(0), mean, cov).log_evidence)
        zero = float(KalmanFilter(model)(torch.nan_to_num(z).unsqueeze(0), mean, cov).log_evidence)
    kf = next(r for r in res.summary if r["filter"] == "kf")["log_evidence"]
    assert kf == pytest.approx(gap, rel=1e-9, abs=1e-9) and abs(zero - gap) > 1e-3, (kf, gap, zero)


# ---- the command lines ----------------------------------------------------------------------------


def _command(script, tmp_path, *args):
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    return subprocess.run(
        [sys.executable, str(ROOT / "experiments" / script), *args, f"hydra.run.dir={tmp_path / 'out'}"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=300,
        env=env,
    )


def test_the_run_command_filters_a_csv(tmp_path):
    z = _series(SensorNetwork(d=4), 6).numpy()
    _write_csv(tmp_path / "z.csv", z, time_step=1.0)
    r = _command(
        "run.py",
        tmp_path,
        "model=linear_gaussian",
        "model.d=4",
        "filter=[kf,bpf]",
        "n_particles=30",
        "trials=3",
        "data=z.csv",
        "progress=false",
        "checkpoint_dir=null",
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert "recorded data (no true states): mse, rmse, omat, ospa left out" in r.stdout
    out = tmp_path / "out"
    rows = list(csv.DictReader(open(out / "summary.csv")))
    assert [x["filter"] for x in rows] == ["kf", "bpf"] and all(x["mse"] == "" and x["trials"] == "3" for x in rows)
    assert rows[1]["log_evidence_se"] != "" and float(rows[1]["ess"]) > 0 and rows[0]["steps"] == "6"
    est = list(csv.DictReader(open(out / "estimates.csv")))
    assert len(est) == 2 * 6 and list(est[0])[:3] == ["filter", "step", "mean_0"] and "sd_3" in est[0]
    assert (out / "estimates.png").exists() and (out / "per_step.png").exists() and not (out / "tracks.png").exists()
    assert json.loads((out / "results.json").read_text())["config"]["data"] == "z.csv"
    bad = _command(
        "run.py", tmp_path, "model=linear_gaussian", "model.d=16", "filter=[kf]", "data=z.csv", "overwrite=true"
    )
    assert bad.returncode == 2 and "error: data (z.csv): expected m = 16 measurement coordinates" in bad.stderr
    assert "Traceback" not in bad.stderr


# ---- learning ---------------------------------------------------------------------------------------


def _fit(filt, model, obs, epochs, **kw):
    import pytorch_lightning as pl
    from torch.utils.data import DataLoader

    from torchflow.app.lightning import FilterLightningModule, TrajectoryDataset

    module = FilterLightningModule(filt, lr=0.05, betas=(0.5, 0.9), lr_decay=0.95, **kw)
    trainer = pl.Trainer(
        max_epochs=epochs,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    trainer.fit(module, DataLoader(TrajectoryDataset(obs), batch_size=obs.shape[0]))  # no states, no prior
    return float(model.F.detach())


def _kalman_mle(obs, stationary=True):
    from scipy.optimize import minimize_scalar

    def nll(phi):
        m = _ar(phi)
        mean, cov = m.declared_prior(1) if stationary else (m.m0[None], m.P0[None])
        return -float(KalmanFilter(m)(obs[None], mean, cov).log_evidence)

    return minimize_scalar(nll, bounds=(0.0, 0.99), method="bounded", options={"xatol": 1e-9}).x


def test_learning_on_a_recorded_series_reaches_the_kalman_mle_with_a_prior_that_moves_with_the_parameter():
    """A 20-step AR(1) series (phi = 0.8) passed as data, no states: the Kalman filter fitted through
    the Lightning module (prior: the stationary law of the current phi, recomputed each step) ends at
    the Kalman MLE under that prior (0.5724), not at the MLE under the fixed prior N(0, 1) (0.5798):
    the prior is differentiated through. The bootstrap PF (N = 100, 16 runs on the series, default
    stop-gradient resampling) from phi = 0.2 ends within 0.03 of it: over 6 seeds its end points had
    mean 0.5678 and standard deviation 0.0067 (1 thread), so 0.03 is the offset plus 4 standard deviations."""
    obs = _series(_ar(0.8), 20)
    mle, mle_fixed = _kalman_mle(obs), _kalman_mle(obs, stationary=False)
    assert abs(mle - mle_fixed) > 0.005
    kf_model = _ar(0.5, learn=True)
    assert _fit(KalmanFilter(kf_model), kf_model, obs[None], 100) == pytest.approx(mle, abs=1e-5)
    pf_model = _ar(0.2, learn=True)
    fitted = _fit(BootstrapParticleFilter(pf_model, n_particles=100), pf_model, obs.expand(16, -1, -1), 60)
    assert abs(fitted - mle) < 0.03, (fitted, mle)


def test_the_learn_command_fits_a_csv(tmp_path):
    z = _series(SensorNetwork(d=4), 8).numpy()
    np.savetxt(tmp_path / "z.csv", z, delimiter=",")
    r = _command(
        "learn.py",
        tmp_path,
        "model=linear_gaussian",
        "model.d=4",
        "learn=[F]",
        "~start",
        "+start={alpha: 0.5}",
        "filter=[bpf]",
        "reference=kf",
        "data=z.csv",
        "epochs=2",
        "trials=2",
        "n_particles=20",
        "plots=false",
    )
    assert r.returncode == 0, r.stderr[-3000:]
    rows = list(csv.DictReader(open(tmp_path / "out" / "learn.csv")))
    assert [(x["filter"], x["parameter"]) for x in rows] == [("bpf", "F"), ("kf", "F")]
    assert rows[0]["truth"] == "" and rows[0]["reference"] != "" and rows[0]["epochs"] == "2"
    run = json.loads((tmp_path / "out" / "learn.json").read_text())["run"]
    assert run["data"] == "z.csv" and run["trials"] == 2 and run["steps"] == 8 and len(run["data_sha256"]) == 64


# ---- files that cannot be right, or cannot be read (issue cases D07-D37) ----------------------------


def test_a_time_column_must_step_forwards_uniformly_even_without_a_model_dt(tmp_path):
    """Cases D26, D27: a model without ``dt`` used to take any times, the column dropped unread."""
    lg = SensorNetwork(d=4)
    cases = {
        "uneven": ("0,.1,.2,.5", r"uniform time step, got 0.1 and then 0.3 \(row 4"),
        "decreasing": ("0.3,0.2,0.1,0", r"increase row by row, got 0.2 after 0.3 in row 2"),
        "constant": ("0,0,0,0", r"increase row by row, got 0 after 0 in row 2"),
    }
    for name, (times, message) in cases.items():
        rows = "".join(f"{t},1,2,3,4\n" for t in times.split(","))
        (tmp_path / f"{name}.csv").write_text("time,a,b,c,d\n" + rows)
        with pytest.raises(ArgumentError, match=message):
            load_observations(tmp_path / f"{name}.csv", lg)
    (tmp_path / "even.csv").write_text("time,a,b,c,d\n0,1,2,3,4\n0.5,1,2,3,4\n1.0,1,2,3,4\n")
    assert load_observations(tmp_path / "even.csv", lg).shape == (3, 4)


def test_a_series_with_no_observation_is_refused(tmp_path):
    """Case D09: an all-NaN file gave log-evidence 0 and a normal-looking table."""
    lg = SensorNetwork(d=4)
    (tmp_path / "allnan.csv").write_text("a,b,c,d\nnan,nan,nan,nan\n,,,\n")
    with pytest.raises(ArgumentError, match=r"the series holds no observation \(every value is NaN\)"):
        load_observations(tmp_path / "allnan.csv", lg)
    arr = np.full((3, 4, 4), np.nan)
    arr[0, 1, 0] = 1.0  # series 0 has one value; 1 and 2 none
    np.save(tmp_path / "allnan.npy", arr)
    with pytest.raises(ArgumentError, match=r"series \[1, 2\] hold no observation"):
        load_observations(tmp_path / "allnan.npy", lg)


def test_a_value_whose_square_overflows_is_refused_naming_its_cell(tmp_path):
    """Cases D07, D07b: a 1e308 cell stopped the run in the hidden Kalman reference, blamed on it."""
    (tmp_path / "huge.csv").write_text("a,b,c,d\n1,2,3,4\n3,1e308,1,1\n")
    with pytest.raises(ArgumentError, match=r"values below 1.34e\+154 .* got 1e\+308 at row 2, column 2"):
        load_observations(tmp_path / "huge.csv", SensorNetwork(d=4))


def test_files_that_are_not_what_their_name_says_get_one_clear_line(tmp_path):
    """Cases D20 (semicolons), D21 (bytes), D23 (CSV text named .npy), D35 (a comment line)."""
    lg = SensorNetwork(d=4)
    (tmp_path / "semi.csv").write_text("1.0;2.0;3.0;4.0\n3.0;4.0;5.0;6.0\n")
    with pytest.raises(ArgumentError, match="expected comma-separated columns, got semicolons"):
        load_observations(tmp_path / "semi.csv", lg)
    (tmp_path / "bytes.csv").write_bytes(bytes(range(256)) * 4)
    with pytest.raises(ArgumentError, match=r"expected a text CSV file \(UTF-8\), but .* is not text"):
        load_observations(tmp_path / "bytes.csv", lg)
    (tmp_path / "text.npy").write_text("1,2,3,4\n3,4,5,6\n")
    with pytest.raises(ArgumentError, match="does not start with NumPy's header") as err:
        load_observations(tmp_path / "text.npy", lg)
    assert "pickle" not in str(err.value)
    (tmp_path / "comment.csv").write_text("# recorded 2024\na,b,c,d\n1,2,3,4\n3,4,5,6\n")
    torch.testing.assert_close(
        load_observations(tmp_path / "comment.csv", lg),
        torch.tensor([[1.0, 2.0, 3.0, 4.0], [3.0, 4.0, 5.0, 6.0]], dtype=torch.float64),
    )


def test_a_home_folder_path_is_expanded(tmp_path, monkeypatch):
    """Case D37: ``~/file.csv`` was joined onto the working folder."""
    monkeypatch.setenv("HOME", str(tmp_path))
    (tmp_path / "good.csv").write_text("a,b,c,d\n1,2,3,4\n")
    assert load_observations("~/good.csv", SensorNetwork(d=4)).shape == (1, 4)


def test_the_command_line_s_recorded_data_keep_their_gaps(tmp_path):
    """What the command line reads (``data=<file>``) reaches the runner with NaN where a cell is
    empty: a loader or runner that filled gaps with zeros fails here, not only on finite checks."""
    from omegaconf import OmegaConf

    from torchflow.app.runner.config import recorded_data

    model = SensorNetwork(d=4)
    z = np.arange(12.0).reshape(3, 4)
    z[1, 2] = np.nan
    path = _write_csv(tmp_path / "gaps.csv", z)
    rec = recorded_data(OmegaConf.create({"data": str(path), "trials": 2, "steps": 3}), model)
    obs, steps = rec.observations, rec.steps
    assert steps == 3 and rec.states is None and rec.prior is None
    assert torch.isnan(obs[1, 2]) and int(torch.isnan(obs).sum()) == 1
    torch.testing.assert_close(torch.nan_to_num(obs), torch.nan_to_num(torch.from_numpy(z)))


def test_a_pipe_a_device_or_a_folder_is_named_as_such_not_as_missing(tmp_path):
    """Q86: a named pipe (reading it would block) or a link to a device is not a regular file;
    the message says what it is rather than 'file not found'."""
    os.mkfifo(tmp_path / "fifo.csv")
    (tmp_path / "zero.npy").symlink_to("/dev/zero")
    (tmp_path / "folder.csv").mkdir()
    for name, kind in (("fifo.csv", "a named pipe"), ("zero.npy", "a device or socket"), ("folder.csv", "a folder")):
        with pytest.raises(ArgumentError, match=f"^data: expected a regular .csv, .npy or .npz file, got {kind}: "):
            load_observations(tmp_path / name, SensorNetwork(d=4))


def test_a_pandas_header_of_numbered_columns_beside_a_time_column_is_a_header(tmp_path):
    """pandas writes integer column labels with a named time index as ``time,0,1,2,3``: a header
    (names of the time column beside numbers), read as before; a first row mixing other names and
    numbers is refused (a data row with a typo, or a header with a number)."""
    (tmp_path / "pd.csv").write_text("time,0,1,2,3\n0.0,1,2,3,4\n0.5,5,6,7,8\n")
    got = load_observations(tmp_path / "pd.csv", SensorNetwork(d=4))
    assert got.tolist() == [[1.0, 2.0, 3.0, 4.0], [5.0, 6.0, 7.0, 8.0]]
    (tmp_path / "typo.csv").write_text("1,2,x,4\n5,6,7,8\n")
    with pytest.raises(ArgumentError, match="header of column names or a row of numbers in line 1"):
        load_observations(tmp_path / "typo.csv", SensorNetwork(d=4))


def test_trailing_rows_of_empty_cells_are_steps_with_a_warning(tmp_path):
    """A row of empty cells is a step with nothing observed; trailing ones (a spreadsheet's
    habit) are kept, with a warning naming them."""
    (tmp_path / "xl.csv").write_text("1,2,3,4\n,,,\n5,6,7,8\n,,,\n,,,\n")
    with pytest.warns(UserWarning, match=r"the last 2 row\(s\) of .*xl.csv \(from line 4\) hold only empty cells"):
        got = load_observations(tmp_path / "xl.csv", SensorNetwork(d=4))
    assert got.shape == (5, 4) and torch.isnan(got[1]).all() and torch.isnan(got[3:]).all()
