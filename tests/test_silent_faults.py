"""Bad input and faults that ran silently wrong or gave unclear errors (singular or mis-shaped
covariances, all-invalid weights, bad schedules, learned covariances that left the cone, memory
limits, a stop signal during a long flow step): one test per case, named after it."""

import pytest
import torch

from torchflow.app.runner import run_experiment
from torchflow.filters import BootstrapParticleFilter, KalmanFilter, ParticleFlowFilter, ParticleFlowParticleFilter
from torchflow.flows import LEDHFlow, integrate_flow
from torchflow.flows.schedules import ExponentialSchedule, LambdaSchedule, UniformSchedule, resolve_schedule
from torchflow.models import SensorNetwork
from torchflow.models.contract import check_covariances


def _singular_q_model():
    """The command ``model=linear_gaussian model.d=4 model.alpha0=0 model.alpha1=0
    model.prior_var=1``: Q = 0."""
    return SensorNetwork(d=4, alpha0=0.0, alpha1=0.0, prior_var=1.0)


def test_pfpf_singular_transition_covariance_is_a_clear_error():
    model = _singular_q_model()
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(2, 3, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    f = ParticleFlowParticleFilter(model, flow="ledh", n_particles=20)
    with pytest.raises(
        ValueError,
        match=r"ParticleFlowParticleFilter: the model's transition covariance is not positive definite "
        r"\(smallest eigenvalue 0\); this filter weighs particles by the transition density",
    ):
        f(traj.observations, mean, cov, g)
    # the filters that do not weigh by the transition density still run
    for ok in (
        BootstrapParticleFilter(model, n_particles=20),
        ParticleFlowFilter(model, n_particles=20),
        KalmanFilter(model),
    ):
        res = ok(traj.observations, mean, cov, g)
        assert torch.isfinite(res.estimates).all()


def test_pfpf_singular_transition_covariance_in_the_runner_keeps_the_kf_row():
    """Through the runner the PF-PF's row carries the error, the KF's row its numbers."""
    model = _singular_q_model()
    res = run_experiment(
        model,
        {"kf": KalmanFilter(model), "pfpf_ledh": ParticleFlowParticleFilter(model, n_particles=20)},
        trials=2,
        steps=3,
        progress=False,
    )
    rows = {r["filter"]: r for r in res.summary}
    assert rows["kf"].get("error") in (None, "") and rows["kf"]["mse"] is not None
    assert "transition covariance is not positive definite" in rows["pfpf_ledh"]["error"]


def test_all_invalid_weights_report_zero_ess_not_a_full_one():
    """A step where no particle has positive weight keeps the previous weights to go on, but its
    ESS is 0 (it used to be reported as N: 50 of 50)."""
    model = SensorNetwork(d=4)
    f = BootstrapParticleFilter(model, n_particles=8)
    B, N, d = 2, 8, 4
    x = torch.randn(B, N, d, dtype=torch.float64)
    prev = torch.full((B, N), -torch.log(torch.tensor(float(N))), dtype=torch.float64)
    inc = torch.zeros(B, N, dtype=torch.float64)
    inc[0] = float("-inf")  # trial 0: every weight invalid
    st = f.weight_and_resample(x, prev, inc, torch.Generator().manual_seed(0), 0)
    assert st.ess[0].item() == 0.0 and st.ess[1].item() == pytest.approx(N)
    assert st.log_evidence_increment[0].item() == float("-inf") and st.n_repaired[0].item() == 1


class _Custom(LambdaSchedule):
    def __init__(self, eps):
        self.eps, self.n_steps = list(eps), len(eps)

    def step_sizes(self):
        return torch.tensor(self.eps, dtype=torch.float64)


@pytest.mark.parametrize(
    "eps, match",
    [
        ([0.5, -0.1, 0.6], r"_Custom.step_sizes\(\): expected finite steps > 0, got smallest -0.1"),
        ([0.1, 0.1], r"_Custom.step_sizes\(\): expected steps summing to 1 \(lambda from 0 to 1\), got a sum of 0.2"),
        ([0.5, float("nan"), 0.5], r"expected finite steps > 0"),
    ],
)
def test_custom_schedule_with_bad_steps_is_refused(eps, match):
    model = SensorNetwork(d=4)
    with pytest.raises(ValueError, match=match):
        ParticleFlowParticleFilter(model, n_particles=10, schedule=_Custom(eps))
    x = torch.zeros(1, 3, 4, dtype=torch.float64)
    from torchflow.flows import FlowPrior

    with pytest.raises(ValueError, match=match):
        integrate_flow(
            LEDHFlow(),
            model,
            x,
            torch.zeros(1, 4, dtype=torch.float64),
            FlowPrior(x, torch.eye(4, dtype=torch.float64).expand(1, 3, 4, 4)),
            _Custom(eps),
        )


def test_exponential_schedule_with_fractional_steps_is_refused():
    with pytest.raises(ValueError, match=r"n_steps: expected a positive integer, got 2.7 \(float\)"):
        ExponentialSchedule(2.7)


def test_schedule_given_by_name():
    """``schedule="uniform"`` (a string) used to be accepted and fail at the first call with
    ``'str' object has no attribute 'steps'``: names now select a schedule, other values are refused."""
    model = SensorNetwork(d=4)
    f = ParticleFlowParticleFilter(model, n_particles=10, schedule="uniform")
    assert isinstance(f.proposal.schedule, UniformSchedule) and f.proposal.schedule.n_steps == 29
    with pytest.raises(
        ValueError,
        match=r"schedule: expected a LambdaSchedule or one of \('exponential', 'uniform', "
        r"'geometric'\), got 'unifrom'",
    ):
        ParticleFlowParticleFilter(model, n_particles=10, schedule="unifrom")
    with pytest.raises(TypeError, match=r"schedule: expected a LambdaSchedule .* got list"):
        resolve_schedule([0.5, 0.5])


def _lg_data(B=3, d=4):
    model = SensorNetwork(d=d)
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(B, 3, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    return model, traj, mean, cov, g


def test_covariance_passed_as_trial_variances_names_the_shape_given():
    model, traj, mean, cov, g = _lg_data(B=3)
    with pytest.raises(
        ValueError,
        match=r"cov: expected \(d, d\) = \(4, 4\) shared by every trial or \(B, d, d\), "
        r"got \(3, 4\) \(per-trial variances \(B, d\) are torch.diag_embed",
    ):
        KalmanFilter(model)(traj.observations, mean, torch.ones(3, 4, dtype=torch.float64), g)


def test_covariance_passed_as_trial_variances_when_b_equals_d_says_so():
    """With B = d a (B, d) array of variances has the shape of a shared (d, d) matrix: its asymmetry
    is reported with the likely cause."""
    model, traj, mean, cov, g = _lg_data(B=4)
    variances = torch.arange(1.0, 5.0, dtype=torch.float64).expand(4, 4)  # each trial's variances, by row
    with pytest.raises(
        ValueError,
        match=r"cov: covariance at batch index 0 \(trial\) is not symmetric \(a \(d, d\) "
        r"matrix shared by every trial was given; if these are per-trial variances",
    ):
        KalmanFilter(model)(traj.observations, mean, variances, g)


def test_too_many_particles_says_bytes_and_knobs():
    model, traj, mean, cov, g = _lg_data()
    with pytest.raises(
        MemoryError,
        match=r"BootstrapParticleFilter: out of memory running 3 trials x 100000000000 "
        r"particles \(one allocation of [\d.e+]+ GiB\); estimated [\d.e+]+ GiB per time "
        r"step\. .*particle_chunk=.*memory_budget_gb",
    ):
        BootstrapParticleFilter(model, n_particles=int(1e11))(traj.observations, mean, cov, g)


class _Raw(SensorNetwork):
    """A user's model with one raw (unconstrained) learnable covariance: ``which`` is "Q" or "R"."""

    def __init__(self, which, C):
        super().__init__(d=4)
        self.which = which
        setattr(self, f"{which}raw", torch.nn.Parameter(C))

    def transition_cov(self, x=None):
        return self.Qraw if self.which == "Q" else super().transition_cov(x)

    def measurement_cov(self, x=None):
        return self.Rraw if self.which == "R" else super().measurement_cov(x)


def test_learned_covariance_that_left_the_cone_names_the_parameter():
    """An optimiser step can make a raw learnable Q or R indefinite: the error names the filter, the
    model, the covariance and the parameter (torchflow's own models keep theirs valid by construction)."""
    model, traj, mean, cov, g = _lg_data()
    eye = torch.eye(4, dtype=torch.float64)
    with pytest.raises(
        ValueError,
        match=r"BootstrapParticleFilter: _Raw's transition covariance \(parameter 'Qraw'\): "
        r"covariance is not positive semi-definite \(smallest eigenvalue -1\)",
    ):
        BootstrapParticleFilter(_Raw("Q", -eye), n_particles=10)(traj.observations, mean, cov, g)
    with pytest.raises(
        ValueError,
        match=r"KalmanFilter: _Raw's measurement covariance \(parameter 'Rraw'\): "
        r"covariance is not positive semi-definite",
    ):
        KalmanFilter(_Raw("R", eye - 2 * torch.ones(4, 4, dtype=torch.float64)))(traj.observations, mean, cov, g)


def test_learned_asymmetric_covariance_is_refused():
    model, traj, mean, cov, g = _lg_data()
    Q = torch.eye(4, dtype=torch.float64) + 0.3 * torch.triu(torch.ones(4, 4, dtype=torch.float64), 1)
    with pytest.raises(
        ValueError,
        match=r"KalmanFilter: _Raw's transition covariance \(parameter 'Qraw'\): "
        r"covariance is not symmetric",
    ):
        KalmanFilter(_Raw("Q", Q))(traj.observations, mean, cov, g)


def test_torchflow_learnable_covariances_stay_valid():
    """SensorNetwork(learnable=True) parametrises Q and R (valid by construction): the check passes."""
    model = SensorNetwork(d=4, learnable=True)
    check_covariances(model, "KalmanFilter")


def test_negative_regularization_names_what_is_expected():
    model = SensorNetwork(d=4)
    with pytest.raises(ValueError, match=r"regularization: expected a non-negative variance or 4 of them, got -1"):
        BootstrapParticleFilter(model, n_particles=10, regularization=-1)


def test_trial_streams_for_other_trial_count():
    from torchflow.core.random import TrialStreams

    model, traj, mean, cov, g = _lg_data(B=2)
    with pytest.raises(
        ValueError,
        match=r"BootstrapParticleFilter: generator: TrialStreams made for 5 trials, but the "
        r"observations have B = 2 trials",
    ):
        BootstrapParticleFilter(model, n_particles=10)(traj.observations, mean, cov, TrialStreams(0, 5, "bpf"))


def test_run_experiment_with_a_list_of_filters():
    from torchflow.app.runner.plan import ConfigError

    model = SensorNetwork(d=4)
    with pytest.raises(
        ConfigError,
        match=r"filters: expected a mapping of names to filters \(torchflow Estimators: the filters and the "
        r"localisers\), e.g. \{'kf': KalmanFilter\(model\)\}, got list",
    ):
        run_experiment(model, [KalmanFilter(model)], trials=2, steps=2, progress=False)
    with pytest.raises(ConfigError, match=r"got a mapping with str"):
        run_experiment(model, {"kf": "kf"}, trials=2, steps=2, progress=False)
    with pytest.raises(ConfigError, match=r"got a mapping with Linear"):  # a module, but not an estimator
        run_experiment(model, {"lin": torch.nn.Linear(2, 2)}, trials=2, steps=2, progress=False)


def test_integrate_flow_with_two_dimensional_particles():
    """Own case: ``(B, d)`` particles gave 'not enough values to unpack'."""
    from torchflow.flows import FlowPrior

    model = SensorNetwork(d=4)
    eye = torch.eye(4, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"particles: expected \(B, N, d\) \(trials, particles, state\), got \(3, 4\)"):
        integrate_flow(
            LEDHFlow(),
            model,
            torch.zeros(3, 4, dtype=torch.float64),
            torch.zeros(3, 4, dtype=torch.float64),
            FlowPrior(torch.zeros(3, 4, dtype=torch.float64), eye.expand(3, 4, 4)),
        )


def test_sigterm_during_a_gpfis_step_stops_at_once(monkeypatch):
    """After SIGTERM, GPFIS at d = 144 used to take 82 s to stop. The runner's handler raises
    inside a chunk at once, so a signal arriving during a GPFIS pseudo-time flow ends the run there,
    not at the end of the chunk (measured through the command line on SkewedTPoisson, d = 144,
    N = 20: SIGTERM 40 s into a 378 s step, stopped 1.5 s later)."""
    import torchflow.proposals.gpfis as gp
    from torchflow.app.runner import STOP
    from torchflow.filters import GPFIS

    calls = []
    real = gp.gpfis_flow

    def flow(*a, **kw):
        calls.append(1)
        if len(calls) == 2:  # the second time step of the first chunk
            STOP.handler(15, None)
        return real(*a, **kw)

    monkeypatch.setattr(gp, "gpfis_flow", flow)
    model = SensorNetwork(d=4)
    try:
        res = run_experiment(model, {"gpfis": GPFIS(model, n_particles=10)}, trials=2, steps=5, progress=False)
        assert res.interrupted and res.summary[0]["error"] == "interrupted after 0 of 2 trials"
        assert len(calls) == 2  # nothing ran after the signal
    finally:
        STOP.reset()


def test_diagonal_covariances_are_checked_on_their_diagonal():
    """The O(d^2) path for diagonal matrices (a declared Q = 0, R = r I, a diagonal prior) gives the
    same verdicts as the factorisation: zero and positive diagonals pass, a negative entry is named
    with its value, a NaN is named as non-finite, and an off-diagonal entry sends the matrix to the
    factorisation (here: not symmetric)."""
    from torchflow.core.checks import _off_diagonal, check_psd

    A = torch.randn(3, 5, 5, dtype=torch.float64)
    off = _off_diagonal(A)
    mask = ~torch.eye(5, dtype=torch.bool)
    assert torch.equal(off.reshape(3, -1).sort(-1).values, A[:, mask].sort(-1).values)
    check_psd("Q", torch.zeros(300, 300, dtype=torch.float64))
    check_psd("R", 2.0 * torch.eye(300, dtype=torch.float64))
    bad = torch.eye(300, dtype=torch.float64)
    bad[7, 7] = -0.5
    with pytest.raises(ValueError, match=r"R: covariance is not positive semi-definite \(smallest eigenvalue -0.5\)"):
        check_psd("R", bad)
    bad = torch.eye(300, dtype=torch.float64)
    bad[7, 9] = float("nan")
    with pytest.raises(ValueError, match="R: 1 non-finite value"):
        check_psd("R", bad)
    bad = torch.eye(300, dtype=torch.float64)
    bad[7, 9] = 0.5
    with pytest.raises(ValueError, match="R: covariance is not symmetric"):
        check_psd("R", bad)
