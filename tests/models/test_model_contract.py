"""The model contract: a core of six methods that runs the bootstrap PF and the runner, the
Gaussian form the other filters need, the declared structure, and the first-call shape check."""

import math
import pathlib
import re

import pytest
import torch
from torch import nn

from torchflow.app.runner import run_experiment
from torchflow.core.linalg import standard_normal
from torchflow.filters import (
    BootstrapParticleFilter,
    ExtendedKalmanFilter,
    KalmanFilter,
    ParticleFlowGaussianParticleFilter,
    ParticleFlowGaussianSumParticleFilter,
    ParticleFlowParticleFilter,
)
from torchflow.models import GaussianStateSpaceModel, LinearGaussian, StateSpaceModel, Structure
from torchflow.models.structure import kernel_structure

ROOT = pathlib.Path(__file__).resolve().parents[2]
CORE = (
    "initial_state",
    "initial_belief",
    "sample_transition",
    "transition_log_prob",
    "sample_measurement",
    "measurement_log_prob",
)


class StochasticVolatility(StateSpaceModel):
    """``x_k = phi x_{k-1} + sigma v_k``, ``z_k | x_k ~ N(0, exp(x_k))``: the core alone."""

    state_dim = obs_dim = 1

    def __init__(self, phi=0.9, sigma=0.5):
        super().__init__()
        self.register_buffer("phi", torch.tensor(phi, dtype=torch.float64))
        self.register_buffer("sigma", torch.tensor(sigma, dtype=torch.float64))

    def _var0(self):
        return self.sigma**2 / (1 - self.phi**2)

    def initial_state(self, batch_size, generator=None):
        xi = standard_normal((batch_size, 1), dtype=self.dtype, device=self.device, generator=generator)
        return self._var0().sqrt() * xi

    def initial_belief(self, states0, generator=None):
        B = states0.shape[0]
        return states0.new_zeros(B, 1), self._var0() * states0.new_ones(B, 1, 1)

    def sample_transition(self, x, generator=None):
        return self.phi * x + self.sigma * standard_normal(x.shape, dtype=x.dtype, device=x.device, generator=generator)

    def transition_log_prob(self, x_next, x):
        r = (x_next - self.phi * x).squeeze(-1)
        return -0.5 * (math.log(2 * math.pi) + 2 * torch.log(self.sigma) + r * r / self.sigma**2)

    def sample_measurement(self, x, generator=None):
        return (x / 2).exp() * standard_normal(x.shape, dtype=x.dtype, device=x.device, generator=generator)

    def measurement_log_prob(self, z, x):
        z, x = z.squeeze(-1), x.squeeze(-1)
        return -0.5 * (math.log(2 * math.pi) + x + z * z * (-x).exp())


def _public(cls):
    return {n for n in dir(cls) if not n.startswith("_")} - {n for n in dir(nn.Module) if not n.startswith("_")}


def test_the_core_is_six_methods_and_the_model_class_at_most_fifteen_public_members():
    members = _public(StateSpaceModel)
    assert set(CORE) <= members
    assert len(members) <= 15, sorted(members)
    # what the core does not say (the Gaussian form, kernel hooks) lives elsewhere
    for name in (
        "transition_mean",
        "measure",
        "linearize_measurement",
        "bytes_per_point",
        "fused_measurement",
        "graph_safe",
        "linear_dynamics",
    ):
        assert name not in members


def test_a_core_only_model_runs_the_bootstrap_filter_and_the_runner():
    """The stochastic-volatility model with the six core methods: simulated by the core's
    :meth:`simulate`, filtered by the bootstrap PF (finite estimates and log-evidence), and run
    through the runner with per-trial streams."""
    model = StochasticVolatility()
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(4, 30, g)
    assert traj.states.shape == (4, 31, 1) and traj.observations.shape == (4, 30, 1)
    mean, cov = model.initial_belief(traj.states[:, 0])
    out = BootstrapParticleFilter(model, n_particles=200)(traj.observations, mean, cov, g)
    assert out.estimates.shape == (4, 30, 1) and torch.isfinite(out.log_evidence).all()
    # the filter tracks the log-volatility better than the prior mean 0 does
    err = (out.estimates - traj.states[:, 1:]).square().mean()
    assert err < traj.states[:, 1:].square().mean()
    res = run_experiment(
        model, {"bpf": BootstrapParticleFilter(model, n_particles=100)}, trials=3, steps=10, progress=False
    )
    assert res is not None and not res.failures


def test_the_builtin_stochastic_volatility_has_this_core():
    """The built-in model (mu = 0) draws and scores as the core-only class above: same simulated
    data from the same seed, same densities, and the bootstrap PF's same numbers."""
    from torchflow.models import StochasticVolatility as Builtin

    mine, builtin = StochasticVolatility(phi=0.9, sigma=0.5), Builtin(mu=0.0, rho=0.9, sigma=0.5)
    a, b = (
        mine.simulate(3, 20, torch.Generator().manual_seed(0)),
        builtin.simulate(3, 20, torch.Generator().manual_seed(0)),
    )
    assert torch.allclose(a.states, b.states) and torch.allclose(a.observations, b.observations)
    x, xn = a.states[:, :-1], a.states[:, 1:]
    assert torch.allclose(mine.transition_log_prob(xn, x), builtin.transition_log_prob(xn, x))
    assert torch.allclose(
        mine.measurement_log_prob(a.observations, xn), builtin.measurement_log_prob(a.observations, xn)
    )
    for m0, c0 in zip(mine.initial_belief(a.states[:, 0]), builtin.initial_belief(a.states[:, 0])):
        assert torch.allclose(m0, c0)
    mean, cov = mine.initial_belief(a.states[:, 0])
    r = [
        BootstrapParticleFilter(m, n_particles=50)(a.observations, mean, cov, torch.Generator().manual_seed(1))
        for m in (mine, builtin)
    ]
    assert torch.allclose(r[0].log_evidence, r[1].log_evidence)


def test_filters_that_need_the_gaussian_form_refuse_a_core_only_model_by_name():
    model = StochasticVolatility()
    for cls in (
        KalmanFilter,
        ExtendedKalmanFilter,
        ParticleFlowParticleFilter,
        ParticleFlowGaussianParticleFilter,
        ParticleFlowGaussianSumParticleFilter,
    ):
        with pytest.raises(TypeError, match="gives only the core.*Gaussian form"):
            cls(model)


class _WrongMeasure(GaussianStateSpaceModel):
    """m = 2 but ``measure`` returns ``(..., 1)``: the bootstrap PF's densities would broadcast."""

    state_dim, obs_dim = 2, 2
    structure = Structure(linear_dynamics=True)

    def __init__(self):
        super().__init__()
        self.register_buffer("F", 0.9 * torch.eye(2, dtype=torch.float64))

    def transition_matrix(self):
        return self.F

    def transition_cov(self, x=None):
        return 0.1 * torch.eye(2, dtype=torch.float64)

    def measure(self, x):
        return x.sum(-1, keepdim=True)

    def measurement_cov(self, x=None):
        return torch.eye(2, dtype=torch.float64)

    def initial_state(self, batch_size, generator=None):
        return torch.zeros(batch_size, 2, dtype=torch.float64)

    def initial_belief(self, states0, generator=None):
        return states0.clone(), torch.eye(2, dtype=torch.float64).expand(states0.shape[0], 2, 2).clone()


@pytest.mark.parametrize(
    "make",
    [
        lambda m: BootstrapParticleFilter(m, n_particles=8),
        ExtendedKalmanFilter,
        lambda m: ParticleFlowParticleFilter(m, n_particles=8),
    ],
    ids=["bpf", "ekf", "pfpf"],
)
def test_a_wrong_output_shape_names_the_method_expected_and_received(make):
    model = _WrongMeasure()
    obs = torch.zeros(2, 3, 2, dtype=torch.float64)
    mean, cov = model.initial_belief(torch.zeros(2, 2, dtype=torch.float64))
    with pytest.raises(
        ValueError, match=re.escape("_WrongMeasure.measure returned shape (2, 1); expected (B, m) = (2, 2)")
    ):
        make(model)(obs, mean, cov, torch.Generator().manual_seed(0))


def test_a_core_method_of_the_wrong_shape_is_named():
    class Flat(StochasticVolatility):
        def transition_log_prob(self, x_next, x):
            return super().transition_log_prob(x_next, x).unsqueeze(-1)  # (B, 1) instead of (B,)

    model = Flat()
    obs = torch.zeros(2, 3, 1, dtype=torch.float64)
    mean, cov = model.initial_belief(torch.zeros(2, 1, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"Flat\.transition_log_prob returned shape \(2, 1\); expected \(B,\)"):
        BootstrapParticleFilter(model, n_particles=8)(obs, mean, cov, torch.Generator().manual_seed(0))


def test_a_missing_core_method_is_named():
    class Half(StateSpaceModel):
        state_dim = obs_dim = 1

        def __init__(self):
            super().__init__()
            self.register_buffer("a", torch.zeros(()))

    with pytest.raises(NotImplementedError, match=r"Half\.sample_transition: not given"):
        Half().sample_transition(torch.zeros(2, 1))


def test_the_shape_check_draws_from_its_own_generator():
    """The check leaves the caller's stream where it was: the numbers of a filter do not depend on
    whether its model was checked before."""
    model = LinearGaussian(
        0.9 * torch.eye(2, dtype=torch.float64),
        torch.eye(2, dtype=torch.float64),
        torch.eye(2, dtype=torch.float64),
        torch.eye(2, dtype=torch.float64),
    )
    traj = model.simulate(3, 5, torch.Generator().manual_seed(1))
    mean, cov = model.initial_belief(traj.states[:, 0])
    f = BootstrapParticleFilter(model, n_particles=16)
    first = f(traj.observations, mean, cov, torch.Generator().manual_seed(2)).estimates  # checks the model
    again = f(traj.observations, mean, cov, torch.Generator().manual_seed(2)).estimates  # already checked
    assert torch.equal(first, again)


def test_kernel_declarations_hold_only_for_the_declaring_class():
    """graph_safe and the measurement form reach the kernel layer only where the model's own class
    declares its structure: a subclass may have changed a method."""
    from torchflow.models import AcousticTracking

    class Sub(AcousticTracking):
        pass

    class Declared(AcousticTracking):
        structure = AcousticTracking.structure

    assert kernel_structure(AcousticTracking()).graph_safe
    assert kernel_structure(AcousticTracking()).measurement_form is not None
    assert not kernel_structure(Sub()).graph_safe and kernel_structure(Sub()).measurement_form is None
    assert kernel_structure(Declared()).graph_safe
    assert Sub().structure.linear_dynamics  # the equations' declarations are inherited


def test_a_bad_structure_is_refused():
    with pytest.raises(ValueError, match="measurement_noise: expected one of"):
        Structure(measurement_noise="spherical")


def test_no_exact_class_dispatch_outside_the_kernel_selection():
    """Exact-class checks decide nothing outside torchflow.flows.select (which may ask whether a
    generator is a plain TrialStreams); what models import is checked with every other floor
    (tests/test_layers.py)."""
    pattern = re.compile(r"type\([^)]*\)\s+(is|in|==)\s")
    for path in (ROOT / "torchflow").rglob("*.py"):
        if path.relative_to(ROOT).as_posix() == "torchflow/flows/select.py":
            continue
        assert not pattern.search(path.read_text()), path


def test_check_covariances_skips_a_method_that_gives_no_tensor():
    """A user's model whose covariance method returns something other than a tensor (a number, a
    structured object) is left to the filters' own checks; ``check_covariances`` does not fail on it."""
    from torchflow.models import SensorNetwork
    from torchflow.models.contract import check_covariances

    class Scalar(SensorNetwork):
        def measurement_cov(self, x=None):
            return 0.5

    check_covariances(Scalar(d=4))  # no AttributeError
