"""The ``torchflow`` command's smoothing and PMMH tasks (``task=smooth``, ``task=pmmh``:
:mod:`torchflow.app.tasks`): end to end on tiny configs through ``python -m torchflow`` (files, columns,
numbers that must hold), and their refusals (one line naming the key, exit status 2)."""

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from torchflow.app.runner.plan import ConfigError

ROOT = Path(__file__).resolve().parents[1]
SMOOTH = [
    "task=smooth",
    "model=linear_gaussian",
    "model.d=4",
    "trials=2",
    "steps=4",
    "n_particles=30",
    "smooth.n_paths=10",
    "progress=false",
    "checkpoint_dir=null",
]
SV_PRIORS = "+pmmh.priors={rho: {dist: Uniform, low: -1, high: 1}, sigma: {dist: Gamma, concentration: 1, rate: 1}}"
PMMH = [
    "task=pmmh",
    "model=stochastic_volatility",
    "filter=[bpf]",
    "steps=15",
    "n_particles=30",
    "pmmh.chains=2",
    "pmmh.iterations=8",
    "pmmh.adapt=4",
    "progress=false",
    "checkpoint_dir=null",
    SV_PRIORS,
]


def _torchflow(tmp_path, *args):
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    return subprocess.run(
        [sys.executable, "-m", "torchflow", *args, f"hydra.run.dir={tmp_path / 'out'}"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=180,
        env=env,
    )


def _rows(path):
    with open(path) as fh:
        return list(csv.DictReader(fh))


def test_smooth_task_writes_smoothed_means_summary_and_figure(tmp_path):
    r = _torchflow(tmp_path, *SMOOTH, "filter=[kf,bpf]")
    assert r.returncode == 0, r.stderr[-3000:]
    out = tmp_path / "out"
    rows = _rows(out / "smoothed.csv")
    per = ("truth", "filtered_mean", "filtered_sd", "smoothed_mean", "smoothed_sd")
    assert list(rows[0]) == ["filter", "method", "trial", "step", *(f"{k}_{j}" for k in per for j in range(4))]
    assert len(rows) == 2 * 2 * 5  # filters x trials x steps 0..T
    assert {(x["filter"], x["method"]) for x in rows} == {("kf", "rts"), ("bpf", "ffbsi")}
    kf = [x for x in rows if x["filter"] == "kf"]
    for x in kf:
        if x["step"] == "4":  # the RTS smoother equals the filter at the last step
            for j in range(4):
                assert float(x[f"smoothed_mean_{j}"]) == pytest.approx(float(x[f"filtered_mean_{j}"]), abs=1e-10)
                assert float(x[f"smoothed_sd_{j}"]) == pytest.approx(float(x[f"filtered_sd_{j}"]), abs=1e-10)
        if x["step"] == "2":  # and has a smaller variance before it
            assert all(float(x[f"smoothed_sd_{j}"]) < float(x[f"filtered_sd_{j}"]) for j in range(4))
    assert all(x["truth_0"] != "" and float(x["smoothed_sd_0"]) >= 0 for x in rows)
    summary = json.loads((out / "smoothing.json").read_text())
    by = {s["filter"]: s for s in summary["summary"]}
    assert by["kf"]["method"] == "rts" and by["bpf"]["n_paths"] == 10 and summary["run"]["trials"] == 2
    for s in by.values():
        assert s["rmse_filtered"] > 0 and s["rmse_smoothed"] > 0 and s["rmse_filtered_se"] is not None
        assert s["rmse_change"] == pytest.approx(s["rmse_smoothed"] - s["rmse_filtered"], abs=1e-9)
    assert (out / "smoothed.png").stat().st_size > 0
    assert "| kf | rts |" in r.stdout


def test_smooth_task_genealogy_on_recorded_data_has_no_truth(tmp_path):
    np.savetxt(tmp_path / "series.csv", np.random.default_rng(0).normal(size=(4, 4)), delimiter=",")
    r = _torchflow(tmp_path, *SMOOTH, "filter=[bpf]", "smooth.method=genealogy", "data=series.csv", "plots=false")
    assert r.returncode == 0, r.stderr[-3000:]
    rows = _rows(tmp_path / "out" / "smoothed.csv")
    assert len(rows) == 2 * 5 and {x["method"] for x in rows} == {"genealogy"}
    assert all(x["truth_0"] == "" for x in rows)
    summary = json.loads((tmp_path / "out" / "smoothing.json").read_text())["summary"][0]
    assert "rmse_smoothed" not in summary and summary["steps"] == 4
    assert not (tmp_path / "out" / "smoothed.png").exists()


@pytest.mark.parametrize(
    "args, message",
    [
        (["filter=[bpf]", "smooth.method=rts"], "smooth.method: 'rts' smooths the Kalman family"),
        (["filter=[kf]", "smooth.method=ffbsi"], "(filter.kf)"),
        (["filter=[enkf]"], "(filter.enkf)"),
        (["filter=[bpf]", "smooth.n_paths=0"], "smooth.n_paths: expected a positive number of paths, got 0"),
        (  # case S12: 1e8 paths failed in the allocator with a raw traceback
            ["filter=[bpf]", "smooth.n_paths=100000000", "memory_budget_gb=1"],
            "smooth.n_paths: 100000000 paths of 5 steps x d = 4 take 14.9 GiB per trial, more than memory_budget_gb = ",
        ),
        (["filter=[kf]", "task=smoothing"], "task: expected one of filter, smooth, pmmh, got 'smoothing'"),
        (["filter=[kf]", "resume=true"], "resume: expected false with task=smooth"),
    ],
)
def test_smooth_task_refuses_bad_settings_in_one_line(tmp_path, args, message):
    r = _torchflow(tmp_path, *SMOOTH, *args)
    assert r.returncode == 2 and message in r.stderr, (r.returncode, r.stderr[-2000:])
    assert "Traceback" not in r.stderr and not (tmp_path / "out" / "smoothed.csv").exists()


def test_pmmh_task_writes_draws_summary_and_figures(tmp_path):
    r = _torchflow(tmp_path, *PMMH)
    assert r.returncode == 0, r.stderr[-3000:]
    out = tmp_path / "out"
    rows = _rows(out / "posterior.csv")
    assert list(rows[0]) == ["filter", "chain", "iteration", "log_likelihood", "rho", "sigma"]
    assert [(x["chain"], x["iteration"]) for x in rows] == [(str(c), str(s)) for c in range(2) for s in range(1, 9)]
    assert all(-1 < float(x["rho"]) < 1 and float(x["sigma"]) > 0 for x in rows)
    res = json.loads((out / "pmmh.json").read_text())
    bpf = res["filters"]["bpf"]
    assert set(bpf["parameters"]) == {"rho", "sigma"} and len(bpf["acceptance"]) == 2
    rho = bpf["parameters"]["rho"]
    assert rho["truth"] == pytest.approx(0.9702) and rho["rhat"] > 0 and rho["ess"] > 0
    draws = np.array([float(x["rho"]) for x in rows])
    assert rho["mean"] == pytest.approx(draws.mean()) and rho["ess_per_sec"] == pytest.approx(
        rho["ess"] / bpf["seconds"]
    )
    assert res["priors"]["rho"] == {"dist": "Uniform", "low": -1, "high": 1} and res["run"]["series"].startswith(
        "trial 0"
    )
    assert (out / "posterior.png").stat().st_size > 0 and (out / "traces.png").stat().st_size > 0
    # 2 chains x 8 draws cannot have converged: the run says so, per parameter, and pmmh.json records it
    assert bpf["converged"] is False
    assert "bpf: rho: the chains have not converged (" in r.stderr and "ESS" in r.stderr


def test_pmmh_convergence_warnings_name_the_parameter_and_the_threshold():
    from torchflow.app.tasks import ESS_MIN, RHAT_MAX, convergence_warnings

    def summary(rhat, ess):
        return {"parameters": {"rho": {"rhat": rhat, "ess": ess}}}

    assert convergence_warnings("bpf", summary(1.01, 400.0)) == []
    (line,) = convergence_warnings("bpf", summary(1.2, 400.0))
    assert line.startswith("bpf: rho: the chains have not converged (R-hat 1.2 > 1.05)") and RHAT_MAX == 1.05
    (line,) = convergence_warnings("bpf", summary(1.01, 37.0))
    assert "(ESS 37 < 100)" in line and ESS_MIN == 100
    assert "R-hat nan > 1.05" in convergence_warnings("bpf", summary(float("nan"), 400.0))[0]


def test_pmmh_task_on_a_recorded_series_same_seed_same_draws(tmp_path):
    y = np.random.default_rng(1).normal(scale=0.6, size=(15, 1))
    np.savetxt(tmp_path / "returns.csv", y, delimiter=",")
    args = [*PMMH, "data=returns.csv", "plots=false", "pmmh.init={rho: 0.9, sigma: 0.2}"]
    first = _torchflow(tmp_path, *args)
    assert first.returncode == 0, first.stderr[-3000:]
    a = (tmp_path / "out" / "posterior.csv").read_text()
    res = json.loads((tmp_path / "out" / "pmmh.json").read_text())
    assert res["filters"]["bpf"]["parameters"]["rho"]["truth"] is None and res["run"]["series"] == "data"
    again = _torchflow(tmp_path, *args, "overwrite=true")
    assert again.returncode == 0 and (tmp_path / "out" / "posterior.csv").read_text() == a


@pytest.mark.parametrize(
    "args, message",
    [
        (
            ["+pmmh.priors.nu={dist: Normal, loc: 0, scale: 1}"],
            "pmmh.priors.nu: expected a per-trial parameter of StochasticVolatility (mu, rho, sigma), got 'nu'",
        ),
        (["filter=[ekf]"], "filter.ekf: task=pmmh needs a filter whose log-evidence estimates the likelihood"),
        (["pmmh.priors.rho.dist=Uniformm"], "pmmh.priors.rho.dist: expected a torch.distributions class"),
        (["pmmh.priors.rho.low=2"], "pmmh.priors.rho: Uniform(low=2, high=1) is refused by torch.distributions"),
        (["pmmh.iterations=2"], "pmmh.iterations: expected an integer >= 4, got 2"),
        (["pmmh.chain=3"], "pmmh.chain: unknown setting; did you mean pmmh.chains?"),
        (["pmmh.init={rho: 1.5, sigma: 0.2}"], "pmmh.init.rho: expected a value inside the support of its prior"),
        (  # case M10: a Normal on a standard deviation gave negative draws
            ["~pmmh.priors.sigma", "+pmmh.priors.sigma={dist: Normal, loc: 0.0, scale: 1.0}"],
            "pmmh.priors.sigma: Normal's support (Real()) reaches outside sigma's domain (GreaterThan(lower_bound=0",
        ),
    ],
)
def test_pmmh_task_refuses_bad_settings_in_one_line(tmp_path, args, message):
    r = _torchflow(tmp_path, *PMMH, *args)
    assert r.returncode == 2 and message in r.stderr, (r.returncode, r.stderr[-2000:])
    assert "Traceback" not in r.stderr and not (tmp_path / "out" / "posterior.csv").exists()


def _cfg(**pmmh):
    return OmegaConf.create({"pmmh": {"priors": {}, "init": None, **pmmh}})


def test_priors_from_config_shapes_models_and_constraints():
    from torchflow.app.tasks import prior_from_config, priors_from_config
    from torchflow.models import TDOA3D, StochasticVolatility

    p = prior_from_config("beta", {"dist": "Normal", "loc": [0.0, 1.0], "scale": 2.0})
    assert p.batch_shape == (2,) and p.loc.dtype == torch.float64
    sv = StochasticVolatility()
    priors = priors_from_config(_cfg(priors={"mu": {"dist": "Normal", "loc": 0, "scale": 2}}), sv)
    assert list(priors) == ["mu"] and float(priors["mu"].scale) == 2.0
    with pytest.raises(ConfigError, match=r"pmmh.priors.mu: expected a prior of mu's shape \(scalar\), got \(2,\)"):
        priors_from_config(_cfg(priors={"mu": {"dist": "Normal", "loc": [0, 1], "scale": 1}}), sv)
    with pytest.raises(ConfigError, match="pmmh.priors: expected a prior for at least one"):
        priors_from_config(_cfg(), sv)
    with pytest.raises(ConfigError, match="TDOA3D declares none"):
        priors_from_config(_cfg(priors={"speed": {"dist": "Gamma", "concentration": 1, "rate": 1}}), TDOA3D())
    with pytest.raises(ConfigError, match=r"pmmh.priors.rho: expected \{dist: <a torch.distributions class>"):
        prior_from_config("rho", {"low": -1, "high": 1})


def _pmmh_result():
    from torchflow.inference import PMMHResult

    g = torch.Generator().manual_seed(0)
    return PMMHResult(
        samples={"rho": torch.rand(3, 7, generator=g, dtype=torch.float64), "beta": torch.rand(3, 7, 2, generator=g)},
        log_likelihood=torch.randn(3, 7, generator=g),
        acceptance=torch.ones(3),
        scale=torch.ones(3),
        rhat={},
        ess={},
        seconds=1.0,
    )


def test_to_arviz_gives_the_draws_by_chain_and_draw():
    pytest.importorskip("arviz")
    from torchflow.inference import to_arviz

    res = _pmmh_result()
    data = to_arviz(res)
    assert data.posterior["rho"].shape == (3, 7) and data.posterior["beta"].shape == (3, 7, 2)
    assert np.allclose(data.posterior["rho"].values, res.samples["rho"].numpy())
    assert np.allclose(data.sample_stats["log_likelihood_estimate"].values, res.log_likelihood.numpy())


def test_to_arviz_without_arviz_names_the_extra(monkeypatch):
    from torchflow.inference import to_arviz

    monkeypatch.setitem(sys.modules, "arviz", None)  # as if not installed
    with pytest.raises(ImportError, match=r"torchflow\[arviz\]"):
        to_arviz(_pmmh_result())


def test_posterior_figures_keep_the_truth_inside_the_frame():
    """A truth outside every draw (rho's 0.97 against draws up to 0.5) is drawn inside the axes,
    not on their frame: the histogram's x range and the trace's y range are widened to hold it."""
    pytest.importorskip("matplotlib")
    from torchflow.app.runner import figures

    plt = figures.pyplot()
    draws = {"bpf": {"rho": torch.linspace(-0.5, 0.5, 40, dtype=torch.float64).reshape(2, 20)}}
    hist, trace = figures.posterior_figures(plt, draws, {"rho": torch.tensor(0.97, dtype=torch.float64)}, "t")
    try:
        lo, hi = hist.axes[0].get_xlim()
        assert hi > 0.97 + 0.01 and lo < -0.5
        lo, hi = trace.axes[0].get_ylim()
        assert hi > 0.97 + 0.01 and lo < -0.5
    finally:
        plt.close(hist)
        plt.close(trace)


def test_an_override_merged_into_another_prior_says_how_to_replace_it():
    """Case M03: ``pmmh.priors={sigma: {dist: Normal, ...}}`` over an experiment's Gamma merges the two
    (Normal with ``concentration`` and ``rate``); the error now says to delete the old prior first."""
    from torchflow.app.tasks import prior_from_config

    merged = {"dist": "Normal", "concentration": 1.0, "rate": 1.0, "loc": 0.0, "scale": 1.0}
    with pytest.raises(ConfigError, match="unexpected keyword") as err:
        prior_from_config("sigma", merged)
    assert "delete that one first: '~pmmh.priors.sigma' '+pmmh.priors.sigma={dist: Normal, ...}'" in str(err.value)
    with pytest.raises(ConfigError) as err:
        prior_from_config("rho", {"dist": "Uniform", "low": 2, "high": 1})
    assert "delete that one first" not in str(err.value)  # the hint only where arguments were merged in


def test_an_interrupted_pmmh_keeps_the_finished_filters_posteriors(tmp_path):
    """Case M17: Ctrl-C during the second filter's chains wrote nothing; now the first filter's
    posterior is written, the interrupted one is named, and the exit status is still 130."""
    code = (
        "import sys\n"
        "import torchflow.inference as inference\n"
        "real, calls = inference.pmmh, []\n"
        "def pmmh(*a, **k):\n"
        "    calls.append(1)\n"
        "    if len(calls) == 2:\n"
        "        raise KeyboardInterrupt\n"
        "    return real(*a, **k)\n"
        "inference.pmmh = pmmh\n"
        "from torchflow.app.cli import main\n"
        "sys.argv = ['torchflow', *sys.argv[1:]]\n"
        "main()\n"
    )
    args = [a for a in PMMH if not a.startswith("filter=")] + ["filter=[bpf,pfpf_ledh]", "plots=false"]
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    r = subprocess.run(
        [sys.executable, "-c", code, *args, f"hydra.run.dir={tmp_path / 'out'}"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=env,
        timeout=300,
    )
    assert r.returncode == 130, r.stderr[-2000:]
    assert "during pfpf_ledh's PMMH" in r.stderr and "the finished posteriors (bpf) are" in r.stderr
    rows = (tmp_path / "out" / "posterior.csv").read_text().splitlines()
    assert len(rows) > 1 and {row.split(",")[0] for row in rows[1:]} == {"bpf"}
    run = json.loads((tmp_path / "out" / "pmmh.json").read_text())["run"]
    assert run["interrupted"] == "pfpf_ledh" and run["not_run"] == ["pfpf_ledh"]


def test_smoothing_deterministic_dynamics_by_ffbsi_is_refused_in_one_line(tmp_path):
    """Case S10 on the command line: refused before any filter runs, naming the filter."""
    args = ["task=smooth", "model=lorenz96", "model.d=8", "filter=[bpf]", "trials=2", "steps=5", "n_particles=20"]
    r = _torchflow(tmp_path, *args, "progress=false", "checkpoint_dir=null")
    assert r.returncode == 2 and "transition covariance is not positive definite" in r.stderr, r.stderr[-2000:]
    assert "(filter.bpf)" in r.stderr and "Traceback" not in r.stderr
    ok = _torchflow(
        tmp_path, *args, "smooth.method=genealogy", "progress=false", "checkpoint_dir=null", "overwrite=true"
    )
    assert ok.returncode == 0 and (tmp_path / "out" / "smoothed.csv").exists(), ok.stderr[-2000:]
