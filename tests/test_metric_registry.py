"""The metric registry (torchflow.core.metrics.REGISTRY): one registered function is a column of the
summary, per-trial and per-step rows, of the written files and a panel of the per-step figure."""

import csv
import doctest

import pytest
import torch

from torchflow.app.runner import SUMMARY_COLUMNS, figures, format_table, run_experiment, summary_columns, writers
from torchflow.app.runner.score import FIXED_COLUMNS, RUN_COLUMNS
from torchflow.core import metrics
from torchflow.filters import BootstrapParticleFilter, ExtendedKalmanFilter, KalmanFilter
from torchflow.models import AcousticTracking, SensorNetwork

#: the summary columns of the built-in metrics (the committed results files have this header)
BUILT_IN_COLUMNS = [
    "filter",
    "n_particles",
    "trials",
    "steps",
    "mse",
    "rmse",
    "rmse_se",
    "omat",
    "omat_kept_mean",
    "omat_kept_sd",
    "ospa",
    "declared",
    "underflows",
    "ess",
    "g_eff",
    "log_evidence",
    "log_evidence_se",
    "log_evidence_relmse",
    "lost_tracks",
    "lost_trials",
    "repaired",
    "sec_per_step",
    "warmup_sec",
    "path",
    "error",
]


def max_abs_error(ctx):
    """``(B, T)``: ``max_j |xhat[b, t, j] - x[b, t, j]|``."""
    return (ctx.estimates - ctx.truth).abs().amax(-1)


def first_target_x(ctx):
    """``(B, T)``: the first target's estimated x position (defined for tracking models only)."""
    return ctx.est_positions[..., 0, 0]


MAX_ABS = metrics.Metric("max_abs", "max |error|", max_abs_error)


@pytest.fixture
def clean_registry():
    """The registry restored as it was (the same metrics in the same order) after the test."""
    before = list(metrics.REGISTRY.values())
    yield
    for name in list(metrics.REGISTRY):
        metrics.unregister(name)
    for m in before:
        metrics.register(m)


def _run(model=None, steps=4):
    model = model or SensorNetwork(d=4)
    filters = {"kf": KalmanFilter(model), "bpf": BootstrapParticleFilter(model, n_particles=50)}
    return run_experiment(model, filters, trials=3, steps=steps, seed=5, progress=False)


def _read(path):
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    with open(path, newline="") as fh:
        return next(csv.reader(fh)), rows


def test_built_in_summary_columns_are_the_committed_files_header():
    assert summary_columns() == BUILT_IN_COLUMNS and list(SUMMARY_COLUMNS) == BUILT_IN_COLUMNS
    assert SUMMARY_COLUMNS == BUILT_IN_COLUMNS
    assert list(metrics.REGISTRY) == ["mse", "rmse", "omat", "ospa", "declared", "ess", "g_eff"]
    own = set(FIXED_COLUMNS) | {c for _, cols in RUN_COLUMNS for c in cols} | {"trial", "step", "lost"}
    assert own <= metrics.RESERVED_NAMES  # no metric can take a column the runner writes itself
    for m in metrics.REGISTRY.values():  # each built-in metric states its formula and shapes
        assert "(B, T)" in m.doc and "=" in m.doc, m.name


def test_a_registered_metric_is_in_every_row_file_and_figure(clean_registry, tmp_path):
    metrics.register(MAX_ABS)
    assert summary_columns() == BUILT_IN_COLUMNS[:15] + ["max_abs"] + BUILT_IN_COLUMNS[15:]
    assert "max_abs" in SUMMARY_COLUMNS  # the command line's partial summary.csv reads this
    res = _run()
    assert all(r["max_abs"] > 0 for r in res.summary) and all(set(r) == set(SUMMARY_COLUMNS) for r in res.summary)
    assert len(res.per_trial) == 6 and all(r["max_abs"] > 0 for r in res.per_trial)
    assert len(res.per_step) == 8 and all(r["max_abs"] > 0 for r in res.per_step)
    # the values: trial 0's mean over steps, and the summary's mean over trials and steps
    truth = res.trajectory.states[:, 1:].double()
    kf0 = (res.examples["kf"] - truth[0]).abs().amax(-1).mean()
    assert res.per_trial[0]["filter"] == "kf" and res.per_trial[0]["max_abs"] == pytest.approx(float(kf0), rel=1e-12)
    kf_trials = [r["max_abs"] for r in res.per_trial if r["filter"] == "kf"]
    assert res.summary[0]["max_abs"] == pytest.approx(sum(kf_trials) / 3, rel=1e-12)
    assert "max_abs" in format_table(res.summary).splitlines()[0]

    writers.write_run(tmp_path, res, {"trials": 3})
    header, rows = _read(tmp_path / "summary.csv")
    assert header == summary_columns() and all(float(r["max_abs"]) > 0 for r in rows)
    for name in ("per_trial.csv", "per_step.csv"):
        header, rows = _read(tmp_path / name)
        assert "max_abs" in header and all(float(r["max_abs"]) > 0 for r in rows), name

    assert figures.per_step_keys(res.per_step) == ["mse", "rmse", "ess", "max_abs"]
    plt = pytest.importorskip("matplotlib.pyplot")
    fig = figures.per_step_figure(plt, res.per_step, res.summary, "t")
    assert [ax.get_ylabel() for ax in fig.axes] == ["MSE", "RMSE", "ESS / N (N = 50)", "max |error|"]
    plt.close(fig)


def test_unregistering_removes_the_metric_everywhere(clean_registry, tmp_path):
    metrics.register(MAX_ABS)
    assert metrics.unregister("max_abs") is MAX_ABS
    assert "max_abs" not in metrics.REGISTRY and summary_columns() == BUILT_IN_COLUMNS
    res = _run()
    assert not any("max_abs" in r for r in res.summary + res.per_trial + res.per_step)
    writers.write_run(tmp_path, res, {})
    for name in ("summary.csv", "per_trial.csv", "per_step.csv"):
        assert "max_abs" not in _read(tmp_path / name)[0], name
    assert "max_abs" not in figures.per_step_keys(res.per_step)
    # a built-in metric goes too; the runner's own columns stay (a group after it moves to the end)
    metrics.unregister("mse")
    assert "mse" not in summary_columns() and "log_evidence" in summary_columns()
    res = _run()
    assert all("mse" not in r for r in res.summary + res.per_trial + res.per_step)
    metrics.unregister("omat")
    cols = summary_columns()
    assert "omat" not in cols and cols.index("omat_kept_mean") == cols.index("g_eff") + 1


def test_a_metric_that_does_not_apply_is_absent(clean_registry):
    """A metric of target positions on a model without positions: an empty summary column, no
    per-trial or per-step value, no panel; on a tracking model it is there."""
    metrics.register(metrics.Metric("first_x", "x of target 1 (m)", first_target_x, metrics.tracking))
    res = _run()
    assert all(r["first_x"] is None for r in res.summary)
    assert not any("first_x" in r for r in res.per_trial + res.per_step)
    assert "first_x" not in format_table(res.summary) and "first_x" not in figures.per_step_keys(res.per_step)
    model = AcousticTracking()
    res = run_experiment(model, {"ekf": ExtendedKalmanFilter(model)}, trials=2, steps=3, progress=False)
    assert res.summary[0]["first_x"] is not None and all("first_x" in r for r in res.per_trial + res.per_step)
    assert "first_x" in figures.per_step_keys(res.per_step)


def test_last_step_reduction_and_integer_counts(clean_registry):
    def over_one(ctx):
        """``(B, T)`` integer: ``sum_j [|xhat[b, t, j] - x[b, t, j]| > 1]``."""
        return ((ctx.estimates - ctx.truth).abs() > 1).sum(-1)

    metrics.register(metrics.Metric("over_one", "components off by > 1", over_one, reduce_trial="last"))
    res = _run(steps=3)
    truth = res.trajectory.states[:, 1:].double()
    want = int(((res.examples["kf"] - truth[0]).abs() > 1).sum(-1)[-1])
    got = res.per_trial[0]["over_one"]
    assert isinstance(got, int) and got == want
    kf = [r["over_one"] for r in res.per_trial if r["filter"] == "kf"]
    assert res.summary[0]["over_one"] == pytest.approx(sum(kf) / 3)


def test_bad_registrations_name_the_argument(clean_registry):
    with pytest.raises(ValueError, match=r"^metric: a metric named 'mse' is already registered"):
        metrics.register(metrics.Metric("mse", "MSE", max_abs_error))
    with pytest.raises(TypeError, match=r"^compute: expected a callable"):
        metrics.Metric("toy", "toy", compute=3.0)
    with pytest.raises(TypeError, match=r"^applies: expected a callable"):
        metrics.Metric("toy", "toy", max_abs_error, applies="tracking")
    with pytest.raises(TypeError, match=r"^metric: expected a torchflow.core.metrics.Metric"):
        metrics.register(max_abs_error)
    with pytest.raises(TypeError, match=r"^name: expected a column name"):
        metrics.Metric("max abs", "toy", max_abs_error)
    with pytest.raises(ValueError, match=r"^name: 'error' is a column the runner writes itself"):
        metrics.Metric("error", "toy", max_abs_error)
    with pytest.raises(ValueError, match=r"^reduce_trial: expected one of \[None, 'mean', 'last'\], got 'max'"):
        metrics.Metric("toy", "toy", max_abs_error, reduce_trial="max")
    with pytest.raises(ValueError, match=r"^yscale: expected one of"):
        metrics.Metric("toy", "toy", max_abs_error, yscale="symlog")
    with pytest.raises(ValueError, match=r"^metric: 'rmse_se' would write the column 'rmse_se', another metric's"):
        metrics.register(metrics.Metric("rmse_se", "toy", max_abs_error))
    with pytest.raises(TypeError, match=r"^burn_in: expected a bool"):
        metrics.Metric("toy", "toy", max_abs_error, burn_in=3)
    with pytest.raises(KeyError, match=r"name: no metric 'nope' is registered"):
        metrics.unregister("nope")
    assert list(metrics.REGISTRY) == ["mse", "rmse", "omat", "ospa", "declared", "ess", "g_eff"]
    with pytest.raises(TypeError):
        metrics.REGISTRY["toy"] = MAX_ABS  # a read-only view: register() checks


def test_a_metric_of_the_wrong_shape_names_itself_and_the_filter(clean_registry):
    metrics.register(metrics.Metric("per_trial_only", "bad", lambda ctx: ctx.estimates[:, 0, 0]))
    with pytest.raises(
        ValueError,
        match=r"filter kf: metric 'per_trial_only': compute returned \(3,\), "
        r"expected \(B, T\) = \(3, 4\)",
    ):
        _run()


def test_registered_is_temporary_and_the_module_example_runs(clean_registry):
    with metrics.registered(MAX_ABS):
        assert "max_abs" in summary_columns()
    assert "max_abs" not in metrics.REGISTRY
    result = doctest.testmod(metrics, optionflags=doctest.ELLIPSIS)
    assert result.attempted >= 5 and result.failed == 0
    assert "max_abs" not in metrics.REGISTRY


def test_rmse_after_burn_in_with_standard_errors(tmp_path):
    """``rmse``: per trial, sqrt(mean over coordinates of the squared error) per step, averaged over
    the steps after ``burn_in`` (``mse`` over the same steps); the summary is the mean over trials
    with its standard error; the per-step rows keep every step; ``burn_in`` must leave a step."""
    model = SensorNetwork(d=4)
    kw = dict(trials=4, steps=6, seed=5, progress=False)
    res = run_experiment(model, {"kf": KalmanFilter(model)}, burn_in=2, **kw)
    est = res.examples["kf"].unsqueeze(0)  # trial 0
    truth = res.trajectory.states[:, 1:].double()
    step_rmse = (est[0] - truth[0]).square().mean(-1).sqrt()  # (T,)
    assert res.per_trial[0]["rmse"] == pytest.approx(float(step_rmse[2:].mean()), rel=1e-12)
    assert res.per_trial[0]["mse"] == pytest.approx(float(step_rmse[2:].square().mean()), rel=1e-12)  # same steps
    trials = torch.tensor([r["rmse"] for r in res.per_trial], dtype=torch.float64)
    assert res.summary[0]["rmse"] == pytest.approx(float(trials.mean()), rel=1e-12)
    assert res.summary[0]["rmse_se"] == pytest.approx(float(trials.std() / 2), rel=1e-12)
    assert len([r for r in res.per_step if "rmse" in r]) == 6
    assert "rmse_se" in format_table(res.summary).splitlines()[0]
    whole = run_experiment(model, {"kf": KalmanFilter(model)}, **kw)
    assert whole.per_trial[0]["rmse"] == pytest.approx(float(step_rmse.mean()), rel=1e-12)
    one = run_experiment(model, {"kf": KalmanFilter(model)}, **{**kw, "trials": 1})
    assert one.summary[0]["rmse_se"] is None
    for bad in (6, -1, 1.5, True):
        with pytest.raises(ValueError, match=r"metrics.burn_in: expected an integer in \[0, steps = 6\)"):
            run_experiment(model, {"kf": KalmanFilter(model)}, burn_in=bad, **kw)
