"""The learning command's bad inputs and faults: start values that are no argument of the model,
filters whose log-evidence is only an approximation, a diverging fit, parameters or a log-evidence
that stop being finite, an output folder that cannot be written. Tiny runs (2 tracks x 3 steps);
the stop signals and the shell's shared refusals are in tests/test_learn.py and tests/test_shell.py."""

import csv
import json
import os
import subprocess
import sys

import pytest

from tests.conftest import ROOT
from torchflow.app.learn import DIVERGENCE_GROWTH, _divergence

TINY = ["filter=[bpf]", "trials=2", "steps=3", "n_particles=50", "epochs=2", "reference=null", "plots=false"]


def _learn(tmp_path, *overrides, script=None, folder="out"):
    argv = [sys.executable, str(script or ROOT / "experiments" / "learn.py"), *overrides, f"hydra.run.dir={folder}"]
    return subprocess.run(
        argv,
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=300,
        env=dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1"),
    )


def _errors(text):
    return [ln for ln in text.splitlines() if ln.startswith("error:")]


def _lines(text):
    return [ln for ln in text.splitlines() if ln.strip()]


@pytest.mark.parametrize(
    "start, message",
    [
        (
            "start={psi: 5.0, sigma_w: 0.3, bogus: 1}",
            "error: start.bogus: expected an argument of AcousticTracking, got 'bogus'; its learnable "
            "parameters: psi, sigma_w",
        ),
        (
            "start.sigma=0.2",
            "error: start.sigma: expected an argument of AcousticTracking (did you mean start.sigma_w?), "
            "got 'sigma'; its learnable parameters: psi, sigma_w",
        ),
    ],
)
def test_a_start_value_that_is_no_argument_of_the_model_is_refused_in_one_line_naming_the_learnable_parameters(
    tmp_path, start, message
):
    r = _learn(tmp_path, *TINY, start)
    assert r.returncode == 2, r.stderr[-2000:]
    assert _lines(r.stderr) == [message]
    assert not (tmp_path / "out" / "learn.csv").exists()


def test_start_values_merge_into_the_default_and_a_default_key_the_model_lacks_is_named(tmp_path):
    """``start={psi: 4.0}`` merges (sigma_w stays 0.3); with another model the default start's keys
    are named with the way to replace them."""
    r = _learn(tmp_path, *TINY, "epochs=1", "start={psi: 4.0}")
    assert r.returncode == 0, r.stderr[-2000:]
    rows = {x["parameter"]: x for x in csv.DictReader(open(tmp_path / "out" / "learn.csv"))}
    assert rows["psi"]["start"] == "4" and rows["sigma_w"]["start"] == "0.3"
    r = _learn(
        tmp_path, *TINY, "model=linear_gaussian", "model.d=4", "learn=true", "start={alpha: 0.5}", folder="other"
    )
    assert r.returncode == 2 and len(_lines(r.stderr)) == 1, r.stderr[-2000:]
    assert "start.psi: expected an argument of SensorNetwork" in r.stderr
    assert (
        "psi, sigma_w are in learn.yaml's default start, which start={...} merges into: replace it with "
        "'~start' '+start={...}'" in r.stderr
    )


@pytest.mark.parametrize("selection", [["filter=[ledh]"], ["filter=[gspf]", "filter.gspf.particles_per_component=50"]])
def test_learning_through_a_filter_without_a_consistent_evidence_is_refused(tmp_path, selection):
    r = _learn(tmp_path, *TINY, *selection)
    assert r.returncode == 2, r.stderr[-2000:]
    (line,) = _lines(r.stderr)
    name = selection[0][len("filter=[") : -1]
    assert (
        line.startswith(f"error: filter: {name} (") and "reports a Gaussian approximation of the log-evidence" in line
    )
    assert "consistent: bpf, gpfis, lag1_pfpf, pfpf," in line and "pfpf_ledh" in line and " ledh," not in line
    assert "add allow_approximate_evidence=true" in line
    assert not (tmp_path / "out" / "learn.csv").exists()


def test_allow_approximate_evidence_learns_through_it_and_labels_the_results(tmp_path):
    r = _learn(tmp_path, *TINY, "filter=[ledh]", "n_particles=20", "epochs=1", "allow_approximate_evidence=true")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "warning: ledh: learning through an approximate log-evidence" in r.stderr
    rows = list(csv.DictReader(open(tmp_path / "out" / "learn.csv")))
    assert {x["note"] for x in rows} == {"approximate log-evidence"}
    assert json.loads((tmp_path / "out" / "learn.json").read_text())["approximate_evidence"] == ["ledh"]


def test_a_diverging_fit_is_warned_of_and_recorded(tmp_path):
    r = _learn(tmp_path, *TINY, "lr=100", "epochs=3")
    assert r.returncode == 0, r.stderr[-2000:]
    assert (
        "warning: bpf is diverging (epoch 1): psi grew from 5 to " in r.stderr and "a smaller lr (now 100)" in r.stderr
    )
    data = json.loads((tmp_path / "out" / "learn.json").read_text())
    assert data["diverged"]["bpf"]["epoch"] == 1 and data["diverged"]["bpf"]["reason"].startswith("psi grew")
    assert data["divergence_rule"] == {"growth": DIVERGENCE_GROWTH, "rises": 2}
    assert {x["note"] for x in csv.DictReader(open(tmp_path / "out" / "learn.csv"))} == {"diverging from epoch 1"}


def test_the_divergence_rule_flags_growth_and_a_rising_loss_but_not_a_noisy_descent():
    start = {"psi": [5.0]}

    def history(loss, psi):
        return {"nll_per_step": loss, "psi": [[p] for p in psi]}

    assert _divergence(history([3.0, 2.0, 2.1, 1.9, 2.0], [5, 7, 9, 10, 10]), start) is None  # noisy descent
    assert _divergence(history([3.0, 3.1, 3.2], [5, 5, 5]), start) is None  # rises within 10% of the first epoch
    assert _divergence(history([3.0, 3.5, 4.0], [5, 5, 5]), start).startswith(
        "the negative log-evidence per step rose in each of the last 2 epochs, from 3 (epoch 1) to 4"
    )
    assert _divergence(history([3.0], [5000]), start) is None and "psi grew from 5 to 5001" in _divergence(
        history([3.0], [5001]), start
    )
    assert "psi grew" in _divergence(history([3.0], [1001]), {"psi": [0.0]})  # a zero start counts as 1


@pytest.mark.parametrize(
    "lr, message, finished",
    [
        (
            "1000",
            "error: bpf: non-finite psi, sigma_w after the optimiser step of epoch 1; learn.csv and learn.json "
            "hold the epochs that finished (bpf: 0 of 4 epochs)",
            0,
        ),
        (
            "300",
            "error: bpf: in epoch 3 the learned parameters (psi 6.475e+140, sigma_w 3.222e+225) give a model the "
            "filter refuses (bpf: ParametrizedAcousticTracking's measurement covariance (built from learnable "
            "parameters): 625 non-finite value(s)",
            2,
        ),
    ],
)
def test_parameters_that_stop_being_finite_end_the_fit_in_one_line_and_the_finished_epochs_are_written(
    tmp_path, lr, message, finished
):
    r = _learn(tmp_path, *TINY, f"lr={lr}", "epochs=4")
    assert r.returncode == 1, r.stderr[-2000:]
    (line,) = _errors(r.stderr)
    assert line.startswith(message[: message.index(";") if finished == 0 else len(message)]), line
    assert line.endswith(f"learn.csv and learn.json hold the epochs that finished (bpf: {finished} of 4 epochs)")
    assert "Traceback" not in r.stderr
    data = json.loads((tmp_path / "out" / "learn.json").read_text())
    assert data["failed"]["bpf"]["epoch"] == finished + 1
    assert len(data["history"].get("bpf", {"epoch": []})["epoch"]) == finished
    rows = list(csv.DictReader(open(tmp_path / "out" / "learn.csv")))
    assert len(rows) == (2 if finished else 0) and all(x["epochs"] == str(finished) for x in rows)


def test_a_non_finite_log_evidence_during_learning_ends_the_fit_naming_the_filter_quantity_and_epoch(tmp_path):
    """The filter's own NonFiniteError (here raised by the second epoch's forward pass) gets the epoch;
    the other filters go on; the finished epochs are written; exit status 1."""
    shim = tmp_path / "faulty.py"
    shim.write_text(
        "from torchflow.core.errors import NonFiniteError\nfrom torchflow.filters import BootstrapParticleFilter\n"
        "calls = [0]\nforward = BootstrapParticleFilter.forward\n\n\n"
        "def faulty(self, *a, **k):\n    calls[0] += 1\n    if calls[0] == 2:\n"
        "        raise NonFiniteError(self.name, 3, [1], 'log-evidence increment')\n    return forward(self, *a, "
        "**k)\n\n\n"
        "BootstrapParticleFilter.forward = faulty\nfrom torchflow.app.learn import main\nmain()\n"
    )
    r = _learn(tmp_path, *TINY, "epochs=3", "reference=ekf", script=shim)
    assert r.returncode == 1, r.stderr[-2000:]
    assert _errors(r.stderr) == [
        "error: bpf: non-finite log-evidence increment in epoch 2 at time step 3 in trial(s) "
        "[1]; learn.csv and learn.json hold the epochs that finished (bpf: 1 of 3 epochs, "
        "ekf: 3 of 3 epochs)"
    ]
    rows = list(csv.DictReader(open(tmp_path / "out" / "learn.csv")))
    assert [(x["filter"], x["epochs"], x["note"]) for x in rows] == [
        ("bpf", "1", "failed in epoch 2"),
        ("bpf", "1", "failed in epoch 2"),
        ("ekf", "3", ""),
        ("ekf", "3", ""),
    ]


def test_an_unwritable_output_folder_is_refused_in_one_line_before_learning(tmp_path):
    (tmp_path / "a_file").write_text("")
    r = _learn(tmp_path, *TINY, folder="a_file/learn")
    assert r.returncode == 2, r.stderr[-2000:]
    assert _lines(r.stderr) == [
        f"error: hydra.run.dir: cannot write into {tmp_path / 'a_file' / 'learn'} "
        "(NotADirectoryError: Not a directory); choose a writable folder with hydra.run.dir=<folder>"
    ]


def test_a_model_without_learnable_parameters_is_named_with_the_models_that_have_them(tmp_path):
    """Q63: Lorenz-96 takes no ``learnable=``; the refusal says so and lists the models
    torchflow-learn fits, instead of relaying the constructor's unexpected-keyword error."""
    r = _learn(
        tmp_path,
        "model=lorenz96",
        "model.d=8",
        "filter=[bpf]",
        "trials=2",
        "steps=5",
        "epochs=1",
        "reference=null",
        "~start",
        "learn=[forcing]",
    )
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert _errors(r.stderr) == [
        "error: model: Lorenz96 has no learnable parameters (it takes no learnable=...), so torchflow-learn "
        "cannot fit it; the models it fits: acoustic, linear_gaussian, stochastic_volatility"
    ]
