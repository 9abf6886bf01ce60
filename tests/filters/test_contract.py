"""One contract test over all filters, plus bad-input errors and reproducibility."""

import pytest
import torch
from conftest import cuda, random_lg

from torchflow.core.checks import NonFiniteError
from torchflow.core.random import TrialStreams
from torchflow.filters import (
    BootstrapParticleFilter,
    EnsembleKalmanFilter,
    EnsembleTransformKalmanFilter,
    ExtendedKalmanFilter,
    GaussianSumParticleFilter,
    KalmanFilter,
    KernelParticleFlowFilter,
    LagOneFlowFilter,
    LagOneFlowParticleFilter,
    LocalEnsembleTransformKalmanFilter,
    LocalLagOneFlowParticleFilter,
    LocalParticleFilter,
    ParticleFlowFilter,
    ParticleFlowParticleFilter,
    UnscentedKalmanFilter,
)
from torchflow.flows.schedules import ExponentialSchedule
from torchflow.models import AcousticTracking, Lorenz96, NeuralAcoustic, SensorNetwork, SkewedTPoisson

# (name, model factory, filter factory): every filter on every model it supports
CONFIGS = [
    ("kf-lg", lambda: random_lg(3, 2), lambda m: KalmanFilter(m)),
    ("ekf-lg", lambda: random_lg(3, 2), lambda m: ExtendedKalmanFilter(m)),
    ("ukf-lg", lambda: random_lg(3, 2), lambda m: UnscentedKalmanFilter(m)),
    ("bpf-lg", lambda: random_lg(3, 2), lambda m: BootstrapParticleFilter(m, n_particles=64)),
    ("ekf-acoustic", AcousticTracking, lambda m: ExtendedKalmanFilter(m)),
    ("ukf-acoustic", AcousticTracking, lambda m: UnscentedKalmanFilter(m)),
    ("bpf-acoustic", AcousticTracking, lambda m: BootstrapParticleFilter(m, n_particles=64)),
    ("enkf-lg", lambda: random_lg(3, 2), lambda m: EnsembleKalmanFilter(m, n_particles=64)),
    ("etkf-lg", lambda: random_lg(3, 2), lambda m: EnsembleTransformKalmanFilter(m, n_particles=64, inflation=1.1)),
    ("etkf-acoustic", AcousticTracking, lambda m: EnsembleTransformKalmanFilter(m, n_particles=64)),
    ("letkf-l96", lambda: Lorenz96(d=8), lambda m: LocalEnsembleTransformKalmanFilter(m, n_particles=64, radius=4.0)),
    ("kpff-lg", lambda: random_lg(3, 2), lambda m: KernelParticleFlowFilter(m, n_particles=64, flow_steps=5)),
    (
        "kpff-l96",
        lambda: Lorenz96(d=8),
        lambda m: KernelParticleFlowFilter(m, n_particles=64, radius=4.0, flow_steps=5),
    ),
    ("lpf-l96", lambda: Lorenz96(d=8), lambda m: LocalParticleFilter(m, n_particles=64, radius=4.0, jitter=0.1)),
    ("lag1_flow-lg", lambda: random_lg(3, 2), lambda m: LagOneFlowFilter(m, n_particles=64, flow_steps=5)),
    ("lag1_flow-l96", lambda: Lorenz96(d=8), lambda m: LagOneFlowFilter(m, n_particles=64, flow_steps=5)),
    (
        "lag1_flow_local-l96",
        lambda: Lorenz96(d=8),
        lambda m: LagOneFlowFilter(m, n_particles=64, radius=4.0, flow_steps=5),
    ),
    ("lag1_pfpf-lg", lambda: random_lg(3, 2), lambda m: LagOneFlowParticleFilter(m, n_particles=64, flow_steps=5)),
    ("lag1_pfpf-l96", lambda: Lorenz96(d=8), lambda m: LagOneFlowParticleFilter(m, n_particles=64, flow_steps=5)),
    (
        "lag1_pfpf_local-l96",
        lambda: Lorenz96(d=8),
        lambda m: LocalLagOneFlowParticleFilter(m, n_particles=64, radius=4.0, weight_radius=3.0, flow_steps=5),
    ),
]
_SCHED = ExponentialSchedule(8, 1.3)
for _flow in ("edh", "ledh", "geodesic", "gromov", "osd"):
    for _mname, _make_model in (("lg", lambda: random_lg(3, 2)), ("acoustic", AcousticTracking)):
        CONFIGS.append(
            (
                f"pfpf_{_flow}-{_mname}",
                _make_model,
                lambda m, fl=_flow: ParticleFlowParticleFilter(m, flow=fl, n_particles=64, schedule=_SCHED),
            )
        )
        CONFIGS.append(
            (
                f"{_flow}-{_mname}",
                _make_model,
                lambda m, fl=_flow: ParticleFlowFilter(m, flow=fl, n_particles=64, schedule=_SCHED),
            )
        )
for _flow in (None, "ledh"):  # GSPF and PFGSPF, G = 2 x 32 particles
    for _mname, _make_model in (("lg", lambda: random_lg(3, 2)), ("acoustic", AcousticTracking)):
        CONFIGS.append(
            (
                f"{'pf' if _flow else ''}gspf-{_mname}",
                _make_model,
                lambda m, fl=_flow: GaussianSumParticleFilter(
                    m, flow=fl, n_components=2, particles_per_component=32, schedule=_SCHED
                ),
            )
        )
# the declared diagonal measurement Jacobian (skewed-t dynamics, Poisson counts; d = 16 here)
CONFIGS.append(
    (
        "pfpf_ledh-skewed",
        lambda: SkewedTPoisson(d=16),
        lambda m: ParticleFlowParticleFilter(m, flow="ledh", n_particles=64, schedule=_SCHED),
    )
)
CONFIGS.append(
    (
        "pfgspf-skewed",
        lambda: SkewedTPoisson(d=16),
        lambda m: GaussianSumParticleFilter(
            m, flow="ledh", n_components=2, particles_per_component=32, schedule=_SCHED
        ),
    )
)
# a neural network in the measurement (the acoustic response as a small MLP; 2 targets, 9 sensors)
for _name, _make_filter in (
    ("bpf", lambda m: BootstrapParticleFilter(m, n_particles=64)),
    ("pfpf_ledh", lambda m: ParticleFlowParticleFilter(m, flow="ledh", n_particles=64, schedule=_SCHED)),
):
    CONFIGS.append((f"{_name}-neural", lambda: NeuralAcoustic(n_targets=2, sensor_grid=3), _make_filter))
IDS = [c[0] for c in CONFIGS]


def _run(make_model, make_filter, dtype, device="cpu", B=3, T=4, seed=0, streams=False):
    model = make_model().to(device=device, dtype=dtype)
    f = make_filter(model)
    g = torch.Generator(device=device).manual_seed(seed)
    traj = model.simulate(B, T, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    run_gen = TrialStreams(seed, B, f.stream_name) if streams else g
    return f, model, f(traj.observations, mean, cov, run_gen, return_particles=True, return_covariances=True)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("name,make_model,make_filter", CONFIGS, ids=IDS)
def test_contract_shapes_dtype(name, make_model, make_filter, dtype):
    f, model, res = _run(make_model, make_filter, dtype)
    B, T, d = 3, 4, model.state_dim
    assert res.estimates.shape == (B, T, d) and res.estimates.dtype == dtype
    assert res.log_evidence.shape == (B,) and res.log_evidence_increments.shape == (B, T)
    assert torch.isfinite(res.estimates).all() and torch.isfinite(res.log_evidence).all()
    torch.testing.assert_close(res.log_evidence, res.log_evidence_increments.sum(1))
    if isinstance(f, ParticleFlowFilter):  # particles re-drawn each step, Gaussian belief
        assert res.ess is None and res.covariances.shape == (B, T, d, d)
    elif isinstance(f, GaussianSumParticleFilter):  # a mixture belief: ESS of the 64 draws, G_eff of 2
        assert res.ess.shape == (B, T) and res.ess.dtype == dtype
        assert ((res.ess >= 1 - 1e-4) & (res.ess <= 64 + 1e-3)).all()
        assert res.g_eff.shape == (B, T) and ((res.g_eff >= 1 - 1e-5) & (res.g_eff <= 2 + 1e-5)).all()
        assert res.particles is None and res.covariances is None
    elif f.uses_particles:
        assert res.ess.shape == (B, T) and res.ess.dtype == dtype
        assert ((res.ess >= 1 - 1e-4) & (res.ess <= 64 + 1e-3)).all()
        assert res.particles.shape == (B, T, 64, d)
        torch.testing.assert_close(res.log_weights.logsumexp(-1), torch.zeros(B, T, dtype=dtype), atol=1e-5, rtol=0)
    else:
        assert res.ess is None
        assert res.covariances.shape == (B, T, d, d)


@cuda
@pytest.mark.parametrize("name,make_model,make_filter", CONFIGS, ids=IDS)
def test_contract_cuda(name, make_model, make_filter):
    f, model, res = _run(make_model, make_filter, torch.float64, device="cuda")
    assert res.estimates.device.type == "cuda" and res.log_evidence.device.type == "cuda"
    # per-trial streams (counter-based Philox on the GPU) without a gradient, as the experiment
    # runner uses them: the deterministic flows' loop is then replayed from a CUDA graph
    with torch.no_grad():
        f, model, res = _run(make_model, make_filter, torch.float32, device="cuda", streams=True)
    assert res.estimates.device.type == "cuda" and torch.isfinite(res.estimates).all()


@pytest.mark.parametrize("name,make_model,make_filter", CONFIGS, ids=IDS)
def test_filter_built_before_the_model_moves(name, make_model, make_filter):
    """A filter built around a model that is then converted (dtype here; device on a GPU) works:
    filters keep no tensors of their own that miss the model's conversion."""
    model = make_model()
    f = make_filter(model)
    model.float()
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(2, 2, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    res = f(traj.observations, mean, cov, g)
    assert res.estimates.dtype == torch.float32 and torch.isfinite(res.estimates).all()


@pytest.mark.parametrize("name,make_model,make_filter", CONFIGS, ids=IDS)
@pytest.mark.parametrize("streams", [False, True], ids=["generator", "streams"])
def test_same_seed_same_numbers(name, make_model, make_filter, streams):
    _, _, a = _run(make_model, make_filter, torch.float64, seed=7, streams=streams)
    _, _, b = _run(make_model, make_filter, torch.float64, seed=7, streams=streams)
    assert torch.equal(a.estimates, b.estimates) and torch.equal(a.log_evidence, b.log_evidence)


def test_different_seed_different_particles():
    _, _, a = _run(lambda: random_lg(3, 2), lambda m: BootstrapParticleFilter(m, n_particles=64), torch.float64, seed=1)
    _, _, b = _run(lambda: random_lg(3, 2), lambda m: BootstrapParticleFilter(m, n_particles=64), torch.float64, seed=2)
    assert not torch.equal(a.estimates, b.estimates)


# ---- bad inputs -------------------------------------------------------------------------------
@pytest.fixture
def lg_setup():
    model = random_lg(3, 2)
    traj = model.simulate(4, 5, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0])
    return model, traj.observations, mean, cov


@pytest.mark.parametrize("make", [KalmanFilter, lambda m: BootstrapParticleFilter(m, n_particles=8)])
def test_wrong_observation_shape(lg_setup, make):
    model, obs, mean, cov = lg_setup
    with pytest.raises(ValueError, match=r"observations: expected \(B, T, m\) = \(\*, \*, 2\), got \(4, 5, 3\)"):
        make(model)(torch.zeros(4, 5, 3, dtype=torch.float64), mean, cov)
    with pytest.raises(ValueError, match="observations"):
        make(model)(obs[0], mean, cov)


def test_infinite_observations(lg_setup):
    """NaN means "not observed" (tests/filters/test_missing.py); an infinity is an error."""
    model, obs, mean, cov = lg_setup
    obs = obs.clone()
    obs[2, 3, 1] = float("inf")
    obs[1, 0, 0] = float("nan")
    with pytest.raises(ValueError, match=r"observations: 1 infinite value\(s\), in trial\(s\) \[2\] \(NaN marks"):
        KalmanFilter(model)(obs, mean, cov)


def test_prior_errors(lg_setup):
    model, obs, mean, cov = lg_setup
    kf = ExtendedKalmanFilter(model)
    bad = cov.clone()
    bad[1] = -torch.eye(3, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"cov: covariance at batch index 1 .* not positive semi-definite"):
        kf(obs, mean, bad)
    with pytest.raises(ValueError, match=r"mean: expected \(B, d\) = \(4, 3\), got \(4, 2\)"):
        kf(obs, mean[:, :2], cov)
    with pytest.raises(ValueError, match=r"cov: expected \(B, d, d\)"):
        kf(obs, mean, cov[:, :2])


def test_dtype_and_device_mismatch(lg_setup):
    model, obs, mean, cov = lg_setup
    with pytest.raises(TypeError, match=r"observations: expected dtype torch.float64 .*got torch.float32"):
        KalmanFilter(model)(obs.float(), mean, cov)
    with pytest.raises(TypeError, match=r"mean: dtype torch.float32 does not match the model's dtype torch.float64"):
        KalmanFilter(model)(obs, mean.float(), cov)
    if torch.cuda.is_available():
        with pytest.raises(ValueError, match="device"):
            KalmanFilter(model)(obs.cuda(), mean, cov)


def test_bad_constructor_arguments():
    model = random_lg(3, 2)
    with pytest.raises(ValueError, match="n_particles"):
        BootstrapParticleFilter(model, n_particles=0)
    with pytest.raises(ValueError, match="ess_threshold"):
        BootstrapParticleFilter(model, ess_threshold=2.0)
    with pytest.raises(ValueError, match="resampl"):
        BootstrapParticleFilter(model, resampling="bogus")
    with pytest.raises(ValueError, match="regularization"):
        BootstrapParticleFilter(model, regularization=[1.0, 2.0])
    with pytest.raises(TypeError, match="model"):
        ExtendedKalmanFilter("not a model")


class _NaNLikelihood(SensorNetwork):
    """A model whose likelihood turns NaN at the third step for trial 1 only."""

    calls = 0

    def measurement_log_prob(self, z, x):
        out = super().measurement_log_prob(z, x)
        type(self).calls += 1
        if type(self).calls == 3:
            out = out.clone()
            out[1] = float("nan")
        return out


def nan_likelihood_run():
    """``(model, traj, mean, cov)``: 3 trials x 5 steps of :class:`_NaNLikelihood` (its NaN counter reset)."""
    from torchflow.models.contract import check_shapes

    model = _NaNLikelihood(d=4)
    traj = model.simulate(3, 5, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0])
    check_shapes(model, mean, "test")  # the filters' first-call check, done here: it calls the counted density
    _NaNLikelihood.calls = 0
    return model, traj, mean, cov


def test_non_finite_error_names_filter_step_trial():
    model, traj, mean, cov = nan_likelihood_run()
    f = BootstrapParticleFilter(model, n_particles=16, nonfinite="raise", name="bpf-test")
    with pytest.raises(
        NonFiniteError,
        match=r"bpf-test: non-finite particles or weights (and log-evidence increment )?at time step 3 "
        r"in trial\(s\) \[1\]",
    ) as e:
        f(traj.observations, mean, cov, torch.Generator().manual_seed(0))
    assert e.value.step == 3 and e.value.trials == [1]


def test_trace_finds_the_first_bad_step_per_trial():
    """The first non-finite step is found once from the stacked estimates, invalid flags and
    log-evidence increments: per trial the earliest bad step (1-based), 0 where none, and which
    quantities were bad then; a -inf increment of a recovering particle filter is a step without
    the measurement (counted), not an error."""
    from types import SimpleNamespace

    from torchflow.filters import guards
    from torchflow.filters.base import _Trace

    tr = _Trace(3, "cpu", False, False)
    nan, inf = float("nan"), float("inf")
    ests = [
        torch.tensor([[0.0], [0.0], [0.0]]),
        torch.tensor([[0.0], [nan], [0.0]]),
        torch.tensor([[0.0], [nan], [0.0]]),
    ]
    invs = [None, torch.tensor([False, False, False]), torch.tensor([True, True, False])]
    incs = [torch.zeros(3), torch.zeros(3), torch.tensor([0.0, 0.0, -inf])]
    for t, (e, i, c) in enumerate(zip(ests, invs, incs)):
        tr.add(SimpleNamespace(estimate=e, invalid=i, log_evidence_increment=c, ess=None), t)
    table = guards.first_steps(tr.estimates(), tr.invalid_steps(), tr.increments(), recover=True).tolist()
    # [first bad step, estimate bad, invalid, increment bad, first dead step, dead steps]
    assert table == [[3, 0, 1, 0, 0, 0], [2, 1, 0, 0, 0, 0], [0, 0, 0, 0, 3, 1]]
    with pytest.raises(NonFiniteError, match=r"non-finite estimate at time step 2 in trial\(s\) \[1\]"):
        guards.raise_first("KalmanFilter", table)
    strict = guards.first_steps(tr.estimates(), tr.invalid_steps(), tr.increments(), recover=False).tolist()
    assert strict[2][:4] == [3, 0, 0, 1]  # without recovery, the -inf increment is the error
