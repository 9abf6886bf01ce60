"""The non-finite contract of every filter's forward pass and gradients, the model parameters'
checks, and user models whose methods return the wrong shape (:mod:`torchflow.filters.guards`,
:mod:`torchflow.models.contract`)."""

import warnings

import pytest
import torch
from torch import nn

import torchflow.filters as F
from torchflow.core.errors import ArgumentError, NonFiniteError, TorchflowError
from torchflow.models import AcousticTracking, GaussianStateSpaceModel, LinearGaussian, SensorNetwork

I2 = torch.eye(2, dtype=torch.float64)
ZERO2 = torch.zeros(2, dtype=torch.float64)


def lg(R=0.1):
    return LinearGaussian(0.9 * I2, 0.2 * I2, I2, R * I2, ZERO2, I2)


class UserModel(GaussianStateSpaceModel):
    """d = m = 2; ``bug`` plants one user mistake."""

    def __init__(self, bug=None, a=0.9):
        super().__init__()
        self.state_dim = self.obs_dim = 2
        self.bug = bug
        self.a = nn.Parameter(torch.tensor(a, dtype=torch.float64))
        self.register_buffer("Q", 0.2 * I2)
        self.register_buffer("R", 0.1 * I2)

    def transition_mean(self, x):
        if self.bug == "transition_mean_one_column":
            return 0.9 * x[..., :1]
        if self.bug == "parameter_gradient_trap":  # finite value, NaN gradient of a (a < 0)
            return torch.where(self.a > -10, self.a, self.a.sqrt()) * x
        return self.a * x

    def transition_cov(self, x=None):
        return self.Q

    def measure(self, x):
        if self.bug == "measure_one_column":
            return x[..., :1]
        if self.bug == "measure_summed":
            return x.sum(-1)
        if self.bug == "measure_nan":
            return x * float("nan")
        if self.bug == "state_gradient_trap":  # finite values, NaN gradient of x where x < 0
            return torch.where(x > -1e9, x, x.sqrt())
        return x

    def measurement_cov(self, x=None):
        return self.R

    def initial_state(self, batch_size, generator=None):
        return torch.zeros(batch_size, 2, dtype=torch.float64)

    def initial_belief(self, states0, generator=None):
        return states0.clone(), I2.expand(states0.shape[0], 2, 2).clone()


def observations(B=3, T=4, seed=0):
    return UserModel().simulate(B, T, torch.Generator().manual_seed(seed)).observations.detach()


FILTERS = {
    "ekf": lambda m: F.ExtendedKalmanFilter(m),
    "bpf": lambda m: F.BootstrapParticleFilter(m, n_particles=50),
    "pfpf": lambda m: F.ParticleFlowParticleFilter(m, n_particles=50),
}


def run(f, z, gen_seed=1):
    return f(z, ZERO2, I2, torch.Generator().manual_seed(gen_seed) if f.uses_randomness else None)


# ---- forward: estimates, log-evidence ---------------------------------------------------------


def test_kalman_filter_names_a_non_finite_log_evidence_increment():
    """An observation of 1e200 keeps the estimates finite (~1e198) but the log-evidence overflows to
    -inf: the call names the quantity, the step and the trial instead of returning -inf."""
    z = observations()
    z[0, 1, 0] = 1e200
    with pytest.raises(
        NonFiniteError,
        match=r"KalmanFilter: non-finite log-evidence increment at time step 2 "
        r"in trial\(s\) \[0\] \(an observation so far from its prediction",
    ) as info:
        F.KalmanFilter(lg())(z, ZERO2, I2)
    assert (info.value.step, info.value.trials, info.value.what) == (2, [0], "log-evidence increment")


@pytest.mark.parametrize("make", [F.BootstrapParticleFilter, F.ParticleFlowParticleFilter])
def test_particle_filters_refuse_a_singular_measurement_covariance(make):
    with pytest.raises(ArgumentError, match="measurement covariance is not positive definite"):
        run(make(lg(R=0.0), n_particles=50), observations())


def test_the_kalman_filter_still_runs_with_a_singular_measurement_covariance():
    out = F.KalmanFilter(lg(R=0.0))(observations(), ZERO2, I2)
    assert torch.isfinite(out.log_evidence).all()


@pytest.mark.parametrize("name", ["bpf", "pfpf"])
def test_a_measurement_that_is_nan_everywhere_is_an_error_not_a_minus_inf_evidence(name):
    with pytest.raises(NonFiniteError, match="no particle's weight carried the measurement at any of the 4 step"):
        run(FILTERS[name](UserModel("measure_nan")), observations())


def test_an_extended_kalman_filter_names_a_nan_measurement():
    with pytest.raises(NonFiniteError, match="non-finite estimate and log-evidence increment at time step 1"):
        run(FILTERS["ekf"](UserModel("measure_nan")), observations())


def test_steps_without_the_measurement_are_repaired_and_warned_not_silent():
    """One observation far in the tail leaves no particle with weight at that step: the filter carries
    its particles on (nonfinite="recover"), counts the step and warns naming step and trial."""
    z = observations()
    z[1, 2] = 1e200  # (z - x)^2 / R overflows: every log-weight -inf
    f = F.BootstrapParticleFilter(lg(R=1e-4), n_particles=20)
    with pytest.warns(
        RuntimeWarning,
        match=r"no particle's weight carried the measurement at 1 step\(s\) "
        r"\(first at time step 3\) in trial\(s\) \[1\]",
    ):
        out = run(f, z)
    assert out.log_evidence[1] == float("-inf") and torch.isfinite(out.log_evidence[[0, 2]]).all()
    assert int(out.n_repaired[1]) >= 1 and torch.isfinite(out.estimates).all()


def test_steps_without_the_measurement_are_an_error_with_nonfinite_raise():
    z = observations()
    z[1, 2] = 1e200  # (z - x)^2 / R overflows: every log-weight -inf
    f = F.BootstrapParticleFilter(lg(R=1e-4), n_particles=20, nonfinite="raise")
    with pytest.raises(NonFiniteError, match=r"at time step 3 in trial\(s\) \[1\]"):
        run(f, z)


def test_a_healthy_run_gives_no_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = run(FILTERS["bpf"](lg()), observations())
    assert torch.isfinite(out.log_evidence).all()


# ---- learnable parameters and their gradients -------------------------------------------------


def acoustic_data(model, seed=0):
    g = torch.Generator().manual_seed(seed)
    tr = model.simulate(2, 3, g)
    m0, P0 = model.initial_belief(tr.states[:, 0], g)
    return tr.observations.detach(), m0.detach(), P0.detach()


@pytest.mark.parametrize("name", ["ekf", "bpf", "pfpf"])
@pytest.mark.parametrize("value", [800.0, float("nan")])
def test_a_learnable_parameter_that_overflowed_is_named_before_filtering(name, value):
    model = AcousticTracking(learnable=["psi", "sigma_w"])
    z, m0, P0 = acoustic_data(model)
    with torch.no_grad():
        model.parametrizations.psi.original.fill_(value)  # psi = exp(800) = inf, or NaN
    f = FILTERS[name](model)
    with pytest.raises(ArgumentError, match=r"learnable parameter 'psi' is not finite \(values \[(inf|nan)\]\)"):
        f(z, m0, P0, torch.Generator().manual_seed(1) if f.uses_randomness else None)


def test_a_learnable_noise_scale_that_underflowed_is_named():
    model = AcousticTracking(learnable=["psi", "sigma_w"])
    z, m0, P0 = acoustic_data(model)
    with torch.no_grad():
        model.parametrizations.sigma_w.original.fill_(-800.0)  # sigma_w = exp(-800) = 0
    # m = 25 > d = 16: H P H^T + R is singular with R, so no filter has a measurement density
    with pytest.raises(
        ArgumentError,
        match=r"ExtendedKalmanFilter: the model's measurement covariance \(built from "
        r"learnable parameters\) is not positive definite \(smallest eigenvalue 0\); "
        r"with m = 25 measurements of d = 16 states",
    ):
        F.ExtendedKalmanFilter(model)(z, m0, P0)
    for make in (F.BootstrapParticleFilter, F.ParticleFlowParticleFilter):
        with pytest.raises(
            ArgumentError,
            match=r"measurement covariance \(built from learnable parameters\) is not "
            r"positive definite",
        ):
            make(model, n_particles=50)(z, m0, P0, torch.Generator().manual_seed(1))


def test_a_non_finite_gradient_names_the_step_and_trials_in_the_backward_pass():
    model = UserModel("state_gradient_trap")
    f = F.BootstrapParticleFilter(model, n_particles=50, resampling_gradient="stop_gradient")
    out = run(f, observations())
    assert torch.isfinite(out.log_evidence).all()  # the forward pass is finite
    with pytest.raises(
        NonFiniteError,
        match=r"BootstrapParticleFilter: non-finite gradient \(backward pass\) of the "
        r"step's computation at time step 4 in trial\(s\) \[0, 1, 2\]",
    ):
        out.log_evidence.sum().backward()


def test_a_non_finite_parameter_gradient_is_named_when_every_step_gradient_is_finite():
    model = UserModel("parameter_gradient_trap", a=-0.5)
    out = run(F.BootstrapParticleFilter(model, n_particles=50, resampling_gradient="stop_gradient"), observations())
    with pytest.raises(NonFiniteError, match="non-finite gradient of the model parameter 'a'"):
        out.log_evidence.sum().backward()


def test_gradient_checks_can_be_turned_off():
    model = UserModel("state_gradient_trap")
    f = F.BootstrapParticleFilter(model, n_particles=50, resampling_gradient="stop_gradient")
    f.check_gradients = False
    run(f, observations()).log_evidence.sum().backward()
    assert not torch.isfinite(model.a.grad)


def test_healthy_gradients_pass_the_checks_unchanged():
    grads = []
    for check in (True, False):
        model = UserModel()
        f = F.BootstrapParticleFilter(model, n_particles=50, resampling_gradient="stop_gradient")
        f.check_gradients = check
        run(f, observations()).log_evidence.sum().backward()
        grads.append(model.a.grad.clone())
    assert torch.isfinite(grads[0]) and torch.equal(grads[0], grads[1])


# ---- model parameters and user models --------------------------------------------------------


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(sigma_w=float("nan")), "sigma_w: expected a finite number > 0, got nan"),
        (dict(sigma_w=1e-300), "sigma_w: expected a noise scale whose square is a normal float64"),
        (dict(psi=-5), "psi: expected a finite number > 0, got -5"),
        (dict(d0=-1), "d0: expected a finite number > 0, got -1"),
        (dict(true_noise_scale=-1), "true_noise_scale: expected a finite number > 0, got -1"),
        (dict(prior_std=(1.0, 1.0, -1.0, 1.0)), r"prior_std\[2\]: expected a finite number > 0"),
    ],
)
def test_acoustic_model_parameters_out_of_range_are_named(kw, match):
    with pytest.raises(ArgumentError, match=match):
        AcousticTracking(**kw)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(d=0), r"d: expected a perfect square >= 1"),
        (dict(d=5), r"d: expected a perfect square >= 1"),
        (dict(sigma_z=float("inf")), "sigma_z: expected a finite number > 0, got inf"),
        (dict(alpha1=-1.0), "alpha1: expected a finite number >= 0"),
        (dict(beta=0.0), "beta: expected a finite number > 0"),
    ],
)
def test_sensor_network_parameters_out_of_range_are_named(kw, match):
    with pytest.raises(ArgumentError, match=match):
        SensorNetwork(**kw)


@pytest.mark.parametrize(
    "bug, method, got, expected",
    [
        ("transition_mean_one_column", "transition_mean", r"\(3, 1\)", r"\(B, d\) = \(3, 2\)"),
        ("measure_one_column", "measure", r"\(3, 1\)", r"\(B, m\) = \(3, 2\)"),
        ("measure_summed", "measure", r"\(3,\)", r"\(B, m\) = \(3, 2\)"),
    ],
)
@pytest.mark.parametrize("name", ["ekf", "bpf", "pfpf"])
def test_a_user_model_method_of_the_wrong_shape_is_named_by_every_filter(name, bug, method, got, expected):
    with pytest.raises(ArgumentError, match=rf"UserModel\.{method} returned shape {got}; expected {expected}"):
        run(FILTERS[name](UserModel(bug)), observations())


@pytest.mark.parametrize(
    "bug, method", [("transition_mean_one_column", "transition_mean"), ("measure_one_column", "measure")]
)
def test_simulate_names_a_user_model_method_of_the_wrong_shape(bug, method):
    with pytest.raises(ArgumentError, match=rf"UserModel\.simulate: UserModel\.{method} returned shape \(2, 1\)"):
        UserModel(bug).simulate(2, 3, torch.Generator().manual_seed(0))


def test_simulate_names_non_finite_simulated_data_as_the_models():
    with pytest.raises(NonFiniteError, match=r"UserModel\.simulate: non-finite simulated observations"):
        UserModel("measure_nan").simulate(2, 3, torch.Generator().manual_seed(0))


def test_every_refusal_is_a_torchflow_error_and_a_builtin_one():
    with pytest.raises(TorchflowError):
        AcousticTracking(psi=-1)
    assert issubclass(ArgumentError, ValueError) and issubclass(NonFiniteError, FloatingPointError)
