"""Bad input gets a clear error naming the argument, what it expects and what it received.

One case per kind of bad input that gave an unclear error or ran silently, through the Python
API and through the command line (one line on stderr, exit status 2, no traceback).
"""

import subprocess
import sys
from pathlib import Path

import pytest
import torch

from torchflow.app.runner import run_experiment
from torchflow.filters import BootstrapParticleFilter, KalmanFilter, ParticleFlowFilter, ParticleFlowParticleFilter
from torchflow.models import AcousticTracking, SensorNetwork

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def acoustic_data():
    model = AcousticTracking()
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(2, 3, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    return model, traj, mean, cov


@pytest.mark.parametrize(
    "args, match",
    [
        ((0, 3), r"AcousticTracking.simulate: batch_size: expected a positive integer, got 0 \(int\)"),
        ((-1, 3), r"batch_size: expected a positive integer, got -1 \(int\)"),
        ((2, 0), r"steps: expected a positive integer, got 0 \(int\)"),
        ((2.5, 3), r"batch_size: expected a positive integer, got 2.5 \(float\)"),
    ],
)
def test_simulate_counts(args, match):
    with pytest.raises(ValueError, match=match):
        AcousticTracking().simulate(*args, torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match=match.replace("AcousticTracking", "SensorNetwork")):
        SensorNetwork(d=4).simulate(*args, torch.Generator().manual_seed(0))


@pytest.mark.parametrize(
    "gen, match",
    [
        (
            0,
            r"generator: expected a torch.Generator, got int \(for a seed, pass torch.Generator\(\).manual_seed\(0\)\)",
        ),
        (None, r"generator: expected a torch.Generator, got NoneType"),
    ],
)
def test_simulate_generator(gen, match):
    with pytest.raises(TypeError, match=match):
        AcousticTracking().simulate(2, 3, gen)


def test_zero_time_steps(acoustic_data):
    model, traj, mean, cov = acoustic_data
    for f in (KalmanFilter(SensorNetwork(d=25)), BootstrapParticleFilter(model, n_particles=8)):
        obs = traj.observations[:, :0].to(f.model.dtype)
        m, c = (
            (mean, cov)
            if f.model is model
            else (torch.zeros(2, 25, dtype=torch.float64), torch.eye(25, dtype=torch.float64).expand(2, 25, 25))
        )
        with pytest.raises(
            ValueError,
            match=r"observations: expected \(B, T, m\) with at least one trial and one "
            r"time step, got \(2, 0, 25\)",
        ):
            f(obs, m, c, torch.Generator().manual_seed(0))


@pytest.mark.parametrize(
    "make",
    [
        lambda m: BootstrapParticleFilter(m, n_particles=8),
        lambda m: ParticleFlowParticleFilter(m, flow="ledh", n_particles=8),
        lambda m: ParticleFlowFilter(m, flow="edh", n_particles=8),
    ],
)
@pytest.mark.parametrize(
    "gen, match",
    [
        (
            3,
            r"generator: expected a torch.Generator or torchflow.core.random.TrialStreams, got int \(for a seed, pass "
            r"torch.Generator\(\).manual_seed\(3\)\)",
        ),
        (None, r"generator: expected a torch.Generator or torchflow.core.random.TrialStreams, got NoneType"),
    ],
)
def test_filter_generator(acoustic_data, make, gen, match):
    model, traj, mean, cov = acoustic_data
    with pytest.raises(TypeError, match=match):
        make(model)(traj.observations, mean, cov, gen)


def test_float16_model(acoustic_data):
    model, traj, mean, cov = acoustic_data
    f = BootstrapParticleFilter(model, n_particles=8)
    model.half()
    with pytest.raises(
        TypeError,
        match=r"BootstrapParticleFilter: the model is in torch.float16; filters and "
        r"simulation run in float32 or float64",
    ):
        f(traj.observations.half(), mean.half(), cov.half(), torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match=r"dtype: expected one of .*, got 'float16'"):
        run_experiment(SensorNetwork(d=4), {"kf": KalmanFilter(SensorNetwork(d=4))}, dtype="float16")


@pytest.mark.parametrize("value", [2.5, 2.7, True, "abc", 0, -3])
def test_n_particles_not_truncated(value):
    with pytest.raises(ValueError, match=rf"n_particles: expected a positive integer, got {value!r}"):
        BootstrapParticleFilter(SensorNetwork(d=4), n_particles=value)
    with pytest.raises(ValueError, match=rf"n_particles: expected a positive integer, got {value!r}"):
        ParticleFlowFilter(SensorNetwork(d=4), n_particles=value)


@pytest.mark.parametrize(
    "kw, match",
    [
        (
            dict(memory_budget_gb=0),
            r"memory_budget_gb: expected a positive number of GiB, or null/auto \(a share of the "
            r"memory free on the device\), got 0",
        ),
        (dict(memory_budget_gb=-1.0), r"memory_budget_gb: expected a positive number of GiB, or null/auto .*got -1.0"),
        (
            dict(memory_budget_gb="half"),
            r"memory_budget_gb: expected a positive number of GiB, or null/auto .*got 'half'",
        ),
        (dict(chunk_size=0), r"chunk_size: expected a positive integer \(or None: from memory_budget_gb\), got 0"),
        (dict(chunk_size=2.5), r"chunk_size: expected a positive integer .* got 2.5"),
        (dict(trials="abc"), r"trials: expected a positive integer, got 'abc' \(str\)"),
        (dict(steps=0), r"steps: expected a positive integer, got 0"),
        (dict(seed=-1), r"seed: expected an integer >= 0, got -1"),
        (dict(device="tpu"), r"device: expected 'cpu', 'cuda' or 'cuda:<index>', got 'tpu'"),
    ],
)
def test_runner_arguments(kw, match):
    model = SensorNetwork(d=4)
    with pytest.raises(ValueError, match=match):
        run_experiment(model, {"kf": KalmanFilter(model)}, progress=False, **kw)


def test_tiny_memory_budget_warns_with_the_plan():
    model = SensorNetwork(d=4)
    with pytest.warns(
        UserWarning,
        match=r"memory_budget_gb=1e-06: BootstrapParticleFilter runs one trial at a "
        r"time in blocks of \d+ of its 100 particles",
    ):
        res = run_experiment(
            model,
            {"bpf": BootstrapParticleFilter(model, n_particles=100)},
            trials=2,
            steps=2,
            memory_budget_gb=1e-6,
            progress=False,
        )
    assert res.config["particle_chunk"]["bpf"] >= 1


@pytest.mark.parametrize(
    "override, match",
    [
        ("device=tpu", "error: device: expected 'cpu', 'cuda' or 'cuda:<index>', got 'tpu'"),
        ("trials=abc", "error: trials: expected a positive integer, got 'abc' (str)"),
        ("filter=[nope]", "error: filter: unknown filter config 'nope'; available: bpf, bs, edh, ekf,"),
        ("n_particles=2.5", "error: filter.bpf: n_particles: expected a positive integer, got 2.5 (float)"),
        ("n_particles=True", "error: filter.bpf: n_particles: expected a positive integer, got True (bool)"),
        (
            "memory_budget_gb=0",
            "error: memory_budget_gb: expected a positive number of GiB, or null/auto (a share of the "
            "memory free on the device), got 0",
        ),
        ("chunk_size=0", "error: chunk_size: expected a positive integer (or None: from memory_budget_gb), got 0"),
        (
            "flow@filter.pfpf_ledh.flow=nope",
            "error: flow@filter.pfpf_ledh.flow: unknown flow config 'nope'; available:",
        ),
        ("tuning.points_per_call=-5", "error: tuning.points_per_call: expected an integer >= 0, got -5"),
    ],
)
def test_cli_one_line_errors(tmp_path, override, match):
    cmd = [
        sys.executable,
        str(ROOT / "experiments" / "run.py"),
        "model=linear_gaussian",
        "model.d=4",
        "filter=[bpf]",
        "trials=2",
        "steps=2",
        "n_particles=10",
        "progress=false",
        "plots=false",
        f"hydra.run.dir={tmp_path}/run",
        override,
    ]
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert out.returncode == 2, out.stderr[-2000:]
    assert match in out.stderr and "Traceback" not in out.stderr, out.stderr[-2000:]


def test_collect_on_a_single_run_folder(tmp_path):
    (tmp_path / "summary.csv").write_text("filter\nkf\n")
    out = subprocess.run(
        [sys.executable, str(ROOT / "experiments" / "collect.py"), str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2
    assert "holds no sweep jobs" in out.stderr and "single run" in out.stderr
    out = subprocess.run(
        [sys.executable, str(ROOT / "experiments" / "collect.py"), str(tmp_path / "nope")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2 and "not a directory" in out.stderr


# ---- found by the validation fuzz (tests/test_fuzz_validation.py) ----------------------------------


def _lg(dtype=torch.float64, d=2):
    from torchflow.models import LinearGaussian

    eye = torch.eye(d, dtype=torch.float64)
    return LinearGaussian(0.9 * eye, 0.2 * eye, eye, 0.1 * eye, torch.zeros(d, dtype=torch.float64), eye).to(dtype)


@pytest.mark.parametrize("n", [2**62, 10**30])
@pytest.mark.parametrize("streams", [False, True])
def test_a_particle_count_past_what_torch_can_count_is_an_out_of_memory_error_naming_the_filter(n, streams):
    from torchflow.core.random import TrialStreams

    f = BootstrapParticleFilter(_lg(), n_particles=8)
    gen = TrialStreams(0, 2) if streams else torch.Generator().manual_seed(0)
    with pytest.raises(MemoryError, match=rf"BootstrapParticleFilter: out of memory running 2 trials x {n} particles"):
        f(
            torch.zeros(2, 3, 2, dtype=torch.float64),
            torch.zeros(2, dtype=torch.float64),
            torch.eye(2, dtype=torch.float64),
            gen,
            n_particles=n,
        )


@pytest.mark.parametrize(
    "make",
    [
        lambda m: BootstrapParticleFilter(m, n_particles=8),
        lambda m: ParticleFlowParticleFilter(m, flow="ledh", n_particles=8),
        lambda m: ParticleFlowFilter(m, flow="edh", n_particles=8),
    ],
)
def test_a_known_initial_state_runs_in_float32(make):
    """A zero prior covariance (a known x_0) is valid: its factor is (nearly) zero, not NaN, in float32
    too (a subnormal jitter does not factor)."""
    model = _lg(torch.float32)
    z = torch.randn(2, 3, 2, generator=torch.Generator().manual_seed(0))
    out = make(model)(z, torch.zeros(2), torch.zeros(2, 2), torch.Generator().manual_seed(0))
    assert torch.isfinite(out.estimates).all() and torch.isfinite(out.log_evidence).all()


def test_a_negative_variance_is_refused_at_any_scale():
    """-1e-13 is not round-off in a matrix whose other entries are zero: refused by name, where it was
    accepted and then gave a NaN factor (a NonFiniteError naming the filter, not the argument)."""
    cov = torch.zeros(2, 2, dtype=torch.float64)
    cov[0, 0] = -1e-13
    with pytest.raises(ValueError, match=r"cov: covariance at batch index 0 \(trial\) is not positive semi-definite"):
        BootstrapParticleFilter(_lg(), n_particles=8)(
            torch.zeros(1, 2, 2, dtype=torch.float64),
            torch.zeros(2, dtype=torch.float64),
            cov,
            torch.Generator().manual_seed(0),
        )


def test_a_singular_float32_covariance_with_round_off_is_accepted():
    """A rank-one float32 prior whose computed eigenvalues are -1e-7 (float32 round-off) is a valid
    covariance; the filters factor it."""
    model = _lg(torch.float32, d=3)
    z = torch.randn(3, 2, 3, generator=torch.Generator().manual_seed(0))
    for f in (KalmanFilter(model), BootstrapParticleFilter(model, n_particles=8)):
        out = f(z, torch.zeros(3), torch.ones(3, 3), torch.Generator().manual_seed(0))
        assert torch.isfinite(out.estimates).all()


@pytest.mark.parametrize("n", ["8", True, 2.5, float("nan"), [8]])
def test_a_gaussian_sum_filter_refuses_a_particle_count_that_is_not_a_count(n):
    from torchflow.filters import GaussianParticleFilter

    f = GaussianParticleFilter(_lg(), n_particles=8)
    with pytest.raises(ValueError, match=r"n_particles: expected a positive integer"):
        f(
            torch.zeros(1, 2, 2, dtype=torch.float64),
            torch.zeros(2, dtype=torch.float64),
            torch.eye(2, dtype=torch.float64),
            torch.Generator().manual_seed(0),
            n_particles=n,
        )


_I2 = [[1.0, 0.0], [0.0, 1.0]]


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: _lg_args(F="abc"), r"F: expected a tensor, array or sequence of real numbers, got str"),
        (lambda: _lg_args(Q=None), r"Q: expected a tensor, array or sequence of real numbers, got NoneType"),
        (
            lambda: _lg_args(H=torch.eye(2, dtype=torch.complex128)),
            r"H: expected .* real numbers, got a torch.complex128",
        ),
        (
            lambda: _lg_args(F=[[float("nan"), 0.0], [0.0, 1.0]]),
            r"F: expected finite numbers, got 1 NaN/inf value\(s\)",
        ),
        (lambda: _lg_args(m0=[float("inf"), 0.0]), r"m0: expected finite numbers"),
        (lambda: _lg_args(F=torch.tensor(1.0)), r"F: expected a square matrix \(d, d\) with d >= 1, got \(\)"),
        (lambda: _lg_args(F=torch.zeros(0, 0)), r"F: expected a square matrix \(d, d\) with d >= 1, got \(0, 0\)"),
        (lambda: _lg_args(F=torch.eye(3)), r"H: expected \(m, d\) = \(\*, 3\) with m >= 1 and F's d, got \(2, 2\)"),
        (lambda: _lg_args(learnable=5), r"learnable: expected a bool or a subset of \['F', 'Q', 'H', 'R'\], got 5"),
        (lambda: _lg_args(learnable=None), r"learnable: expected a bool or a subset of .*, got None"),
        (
            lambda: AcousticTracking(learnable=5),
            r"learnable: expected a bool or a subset of \['psi', 'sigma_w'\], got 5",
        ),
        (lambda: AcousticTracking(prior_std=5.0), r"prior_std: expected 4 numbers \[px, py, vx, vy\], got \(\)"),
        (lambda: AcousticTracking(prior_std=None), r"prior_std: expected a tensor, array or sequence of real numbers"),
        (lambda: AcousticTracking(initial_state="abc"), r"initial_state: expected a tensor, array or sequence of real"),
        (lambda: AcousticTracking(initial_state=[float("nan")] * 16), r"initial_state: expected finite numbers"),
        (lambda: AcousticTracking(sensor_grid=float("nan")), r"sensor_grid: expected an integer >= 1, got nan"),
        (lambda: AcousticTracking(sigma_w=1e200), r"sigma_w: expected a noise scale whose square is a normal float64"),
        (
            lambda: SensorNetwork(d=4, sigma_z=1e200),
            r"sigma_z: expected a noise scale whose square is a finite float64",
        ),
    ],
)
def test_model_arguments_of_the_wrong_kind_are_named(make, match):
    """Strings, None, complex numbers, NaN, overflowing scales and non-collections are refused naming
    the argument (they raised a raw TypeError/ValueError/OverflowError, or were silently cast)."""
    from torchflow.core.errors import TorchflowError

    with pytest.raises(TorchflowError, match=match):
        make()


def _lg_args(**kw):
    from torchflow.models import LinearGaussian

    args = dict(F=_I2, Q=_I2, H=_I2, R=_I2)
    args.update(kw)
    return LinearGaussian(args.pop("F"), args.pop("Q"), args.pop("H"), args.pop("R"), **args)


def test_linear_gaussian_takes_lists_of_python_floats_in_float64_and_one_learnable_name():
    """A nested list keeps its float64 values (a rank-one P0 stays positive semi-definite), and
    ``learnable="F"`` is the one name, not its letters."""
    v = torch.tensor([[1.1], [-0.3], [2.7]], dtype=torch.float64)
    P0 = (v @ v.T).tolist()
    eye = torch.eye(3, dtype=torch.float64).tolist()
    from torchflow.models import LinearGaussian

    model = LinearGaussian(eye, eye, eye, eye, None, P0, learnable="F")
    assert torch.equal(model.P0, torch.tensor(P0, dtype=torch.float64)) and isinstance(model.F, torch.nn.Parameter)


def test_acoustic_targets_that_start_outside_the_field_are_refused_when_built():
    """With margin 0.49 the default targets start outside the field: the simulation could never keep
    them inside (it raised a RuntimeError after max_redraws rounds)."""
    with pytest.raises(
        ValueError,
        match=r"initial_state: expected target positions inside the field \[margin, "
        r"1 - margin\] \* area = \[19.6, 20.4\]\^2",
    ):
        AcousticTracking(margin=0.49)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(d=-4), r"d: expected a perfect square \(144, 400, ...\), got -4"),
        (dict(d="4"), r"d: expected a perfect square \(144, 400, ...\), got '4'"),
        (dict(d=4, gamma=1e200), r"gamma: the skewness 1e\+200 overflows the transition covariance"),
    ],
)
def test_skewed_t_dimension_and_an_overflowing_skewness_are_named(kw, match):
    from torchflow.models import SkewedTPoisson

    with pytest.raises(ValueError, match=match):
        SkewedTPoisson(**kw)


_TWO = [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]


@pytest.mark.parametrize(
    "kw, match",
    [
        (
            dict(receivers=_TWO, pairs=[(0.5, 1)]),
            r"pairs: expected pairs \(a, b\) of receiver indices, got \[\(0.5, 1\)\]",
        ),
        (dict(receivers=_TWO, pairs=[("a", 1)]), r"pairs: expected pairs \(a, b\) of receiver indices"),
        (dict(receivers=_TWO, pairs=5), r"pairs: expected pairs \(a, b\) of receiver indices, got 5"),
        (
            dict(receivers=[[0.0, 0.0, 0.0], [float("nan"), 1.0, 1.0]], pairs=[(0, 1)]),
            r"receivers: expected finite numbers",
        ),
        (dict(receivers="abc"), r"receivers: expected a tensor, array or sequence of real numbers, got str"),
        (dict(region="x"), r"region: expected a positive number, got 'x'"),
        (dict(region=0), r"region: expected a positive number, got 0"),
    ],
)
def test_tdoa_receivers_pairs_and_region_are_named(kw, match):
    from torchflow.core.errors import TorchflowError
    from torchflow.models import TDOA3D

    with pytest.raises(TorchflowError, match=match):
        TDOA3D(**kw)


def test_a_progress_that_is_not_callable_is_refused_before_the_first_step():
    with pytest.raises(TypeError, match=r"progress: expected a callable invoked after each step \(or None\), got bool"):
        KalmanFilter(_lg())(
            torch.zeros(1, 2, 2, dtype=torch.float64),
            torch.zeros(2, dtype=torch.float64),
            torch.eye(2, dtype=torch.float64),
            progress=True,
        )


def test_a_particle_count_is_checked_by_a_filter_without_particles():
    """A Kalman filter has no particles and ignores a valid count; a value that is no count is refused
    as by the particle filters (it was silently ignored)."""
    f, args = (
        KalmanFilter(_lg()),
        (
            torch.zeros(1, 2, 2, dtype=torch.float64),
            torch.zeros(2, dtype=torch.float64),
            torch.eye(2, dtype=torch.float64),
        ),
    )
    assert torch.equal(f(*args, n_particles=10).estimates, f(*args).estimates)
    with pytest.raises(ValueError, match=r"n_particles: expected a positive integer, got 'abc' \(str\)"):
        f(*args, n_particles="abc")


def test_a_model_on_the_meta_device_is_named():
    """Meta tensors have no values: a filter or a simulation named it as a raw RuntimeError from the
    first host read."""
    model = _lg().to("meta")
    with pytest.raises(ValueError, match=r"KalmanFilter: the model is on the meta device"):
        KalmanFilter(model)(
            torch.zeros(1, 2, 2, device="meta", dtype=torch.float64),
            torch.zeros(2, device="meta", dtype=torch.float64),
            torch.eye(2, device="meta", dtype=torch.float64),
        )
    with pytest.raises(ValueError, match=r"LinearGaussian.simulate: the model is on the meta device"):
        model.simulate(1, 2, torch.Generator().manual_seed(0))


def test_stacking_returned_particles_out_of_memory_names_the_filter(monkeypatch):
    """``return_particles=True`` stacks ``(B, T, N, d)`` after the last step, outside the steps' own
    out-of-memory report: an allocator's failure there is the same MemoryError naming the filter."""
    from torchflow.filters import base

    def fail(self, state):
        raise RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried to allocate 8000000000000 bytes.")

    monkeypatch.setattr(base._Trace, "result", fail)
    f = BootstrapParticleFilter(_lg(), n_particles=8)
    with pytest.raises(
        MemoryError,
        match=r"BootstrapParticleFilter: out of memory running 1 trials x 8 particles "
        r"\(one allocation of 7.45e\+03 GiB\)",
    ):
        f(
            torch.zeros(1, 2, 2, dtype=torch.float64),
            torch.zeros(2, dtype=torch.float64),
            torch.eye(2, dtype=torch.float64),
            torch.Generator().manual_seed(0),
            return_particles=True,
        )
