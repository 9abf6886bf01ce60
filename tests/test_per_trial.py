"""Per-trial parameters (:func:`torchflow.inference.per_trial_values`): B trials holding B parameter
values give the numbers of B separate calls, each with its trial's value as the model's own, for
every model that declares per-trial parameters and every filter family that runs on it.

Deterministic filters agree to 1e-10, particle filters to 1e-9 with per-trial random streams
(:class:`~torchflow.core.random.TrialStreams`: trial b draws the same numbers alone and in the batch).
Both are round-off bounds: the batched call runs its linear algebra on B matrices at once, and the
separate calls take the shortcuts a shared value allows (identity scales, a scalar R), which the
per-trial call stands aside from.
"""

import math

import pytest
import torch
from conftest import cuda

import torchflow.filters as F
from torchflow.core import constraints, tuning
from torchflow.core.errors import ArgumentError, ArgumentTypeError
from torchflow.core.random import TrialStreams
from torchflow.inference import per_trial_values
from torchflow.models import AcousticTracking, LinearGaussian, Lorenz96, SkewedTPoisson
from torchflow.models.linear_gaussian import sensor_network_covariance
from torchflow.proposals import UnscentedProposal

f64 = dict(dtype=torch.float64)
B, T = 3, 4


def _t(rows):
    return torch.tensor(rows, **f64)


# ---- the models: a factory of the model with one trial's values, and the B values -------------------

LG_VALUES = {
    "F": torch.stack([_t([[0.9, 0.1], [0.0, 0.8]]), _t([[0.5, -0.2], [0.3, 0.6]]), _t([[1.0, 0.0], [0.1, 0.95]])]),
    "Q": torch.stack([_t([[0.5, 0.1], [0.1, 0.4]]), _t([[1.0, -0.3], [-0.3, 0.8]]), _t([[0.2, 0.0], [0.0, 0.3]])]),
    "H": torch.stack(
        [
            _t([[1.0, 0.0], [0.5, 1.0], [0.0, 1.0]]),
            _t([[2.0, 0.1], [0.0, 1.0], [1.0, 1.0]]),
            _t([[0.5, 0.0], [0.0, 0.5], [0.3, -0.3]]),
        ]
    ),
    "R": torch.stack(
        [
            0.3 * torch.eye(3, **f64),
            _t([[1.0, 0.2, 0.0], [0.2, 0.5, 0.1], [0.0, 0.1, 0.7]]),
            torch.diag(_t([0.1, 0.2, 0.4])),
        ]
    ),
    "m0": _t([[0.0, 1.0], [2.0, -1.0], [0.5, 0.5]]),
    "P0": torch.stack([torch.eye(2, **f64), 0.5 * torch.eye(2, **f64), _t([[2.0, 0.3], [0.3, 1.0]])]),
}
EYE4 = torch.eye(4, **f64)
SENSOR_VALUES = {
    "F": torch.stack([a * EYE4 for a in (0.9, 0.5, 0.99)]),
    "R": torch.stack([r * EYE4 for r in (0.25, 1.0, 0.1)]),
}


def _lg(learnable=False, **v):
    return LinearGaussian(
        v.get("F", LG_VALUES["F"][0]),
        v.get("Q", LG_VALUES["Q"][0]),
        v.get("H", LG_VALUES["H"][0]),
        v.get("R", LG_VALUES["R"][0]),
        v.get("m0", LG_VALUES["m0"][0]),
        v.get("P0", LG_VALUES["P0"][0]),
        learnable=learnable,
    )


def _sensor(**v):
    """The sensor network's structure (F = a I, H = I, R = r I: the identity-scale shortcuts)."""
    return LinearGaussian(
        v.get("F", 0.9 * EYE4), sensor_network_covariance(2), EYE4, v.get("R", 0.25 * EYE4), P0=0.5 * EYE4
    )


def _floats(v):
    return {k: float(x) for k, x in v.items()}


MODELS = {
    # name: (factory of the model with one trial's values, the B values, prior from the model's declared prior)
    "lg": (lambda **v: _lg(**v), LG_VALUES, True),
    "lg_learnable": (lambda **v: _lg(learnable=True, **v), {k: LG_VALUES[k] for k in ("F", "Q", "H", "R")}, True),
    "sensor": (_sensor, SENSOR_VALUES, True),
    "acoustic": (
        lambda **v: AcousticTracking(**_floats(v)),
        {"psi": _t([10.0, 8.0, 12.0]), "sigma_w": _t([0.5, 1.0, 0.3])},
        False,
    ),
    "acoustic_learnable": (
        lambda **v: AcousticTracking(learnable=True, **_floats(v)),
        {"psi": _t([10.0, 8.0, 12.0]), "sigma_w": _t([0.5, 1.0, 0.3])},
        False,
    ),
    "lorenz96": (
        lambda **v: Lorenz96(d=8, spin_up=20, **{"model_noise": 0.3, **_floats(v)}),
        {"forcing": _t([8.0, 4.0, 10.0]), "model_noise": _t([0.3, 0.5, 0.2]), "obs_std": _t([1.0, 0.5, 2.0])},
        False,
    ),
    "skewed": (
        lambda **v: SkewedTPoisson(d=9, **_floats(v)),
        {"alpha": _t([0.9, 0.5, 0.7]), "m1": _t([1.0, 2.0, 0.5]), "m2": _t([1 / 3, 0.5, 0.2])},
        False,
    ),
}


# ---- the filters: name -> (factory, the models it runs on) --------------------------------------------


def _gs(m, flow=None, G=2):
    return F.GaussianSumParticleFilter(m, flow=flow, n_components=G, particles_per_component=m.state_dim + 3)


LINEAR = ("lg", "lg_learnable", "sensor")
GAUSSIAN_TRANSITION = ("lg", "lg_learnable", "sensor", "acoustic", "acoustic_learnable", "lorenz96")
ALL = tuple(MODELS)
FILTERS = {
    "kf": (lambda m: F.KalmanFilter(m), LINEAR),
    "ekf": (lambda m: F.ExtendedKalmanFilter(m), ALL),
    "ukf": (lambda m: F.UnscentedKalmanFilter(m), ALL),
    "enkf": (lambda m: F.EnsembleKalmanFilter(m, n_particles=16), ("lg", "sensor", "acoustic", "lorenz96")),
    "etkf": (lambda m: F.EnsembleTransformKalmanFilter(m, n_particles=16), ("lg", "sensor", "lorenz96")),
    "letkf": (lambda m: F.LocalEnsembleTransformKalmanFilter(m, n_particles=16, radius=3.0), ("lorenz96",)),
    "bpf": (lambda m: F.BootstrapParticleFilter(m, n_particles=32), ALL),
    "upf": (lambda m: F.ParticleFilter(m, UnscentedProposal(m), n_particles=16), GAUSSIAN_TRANSITION),
    "pfpf_edh": (lambda m: F.ParticleFlowParticleFilter(m, flow="edh", n_particles=16), ALL),
    "pfpf_ledh": (lambda m: F.ParticleFlowParticleFilter(m, flow="ledh", n_particles=16), ALL),
    "ledh": (lambda m: F.ParticleFlowFilter(m, flow="ledh", n_particles=16), ("lg", "acoustic", "lorenz96")),
    "gpf": (lambda m: _gs(m, G=1), ("lg", "sensor", "acoustic", "lorenz96", "skewed")),
    "gspf": (lambda m: _gs(m), ("lg", "acoustic", "skewed")),
    "pfgpf": (lambda m: _gs(m, "ledh", G=1), ("lg", "acoustic", "lorenz96")),
    "pfgspf": (lambda m: _gs(m, "ledh"), ("lg", "sensor", "acoustic", "skewed")),
    "gpfis": (lambda m: F.GPFIS(m, n_particles=16), ("lg", "acoustic", "lorenz96", "skewed")),
}
CASES = [(f, m) for f, (_, models) in FILTERS.items() for m in models]
DETERMINISTIC = ("kf", "ekf", "ukf")


def _data(model_name, device="cpu"):
    make, values, declared = MODELS[model_name]
    model = make().to(device)
    g = torch.Generator(device=device).manual_seed(0)
    traj = model.simulate(B, T, g)
    values = {k: v.to(device) for k, v in values.items()}
    if declared:
        with per_trial_values(model, values):
            mean, cov = model.declared_prior(B)
    else:
        mean, cov = model.initial_belief(traj.states[:, 0], g)
    return make, model, values, traj.observations, mean, cov


def _check_equal_to_separate_calls(filter_name, model_name, device="cpu"):
    make_filter = FILTERS[filter_name][0]
    make, model, values, obs, mean, cov = _data(model_name, device)
    tol = 1e-10 if filter_name in DETERMINISTIC else 1e-9
    key = f"{filter_name}-{model_name}"
    # the reference loop: the fused flow kernel takes a per-trial parameter and a scalar through different
    # arithmetic (LEDH on the acoustic model: 1.3e-9 relative in one of 64 numbers, measured), so it is
    # held to round-off, not to this bound
    with per_trial_values(model, values), tuning.tuned(fused_flows=0):
        together = make_filter(model)(obs, mean, cov, TrialStreams(7, B, key), return_covariances=True)
    for k, v in values.items():  # the model's own values are back
        assert getattr(model, k).shape == v.shape[1:]
    for b in range(B):
        alone_model = make(**{k: v[b].cpu() for k, v in values.items()}).to(device)
        with tuning.tuned(fused_flows=0):
            alone = make_filter(alone_model)(
                obs[b : b + 1],
                mean[b : b + 1],
                cov[b : b + 1],
                TrialStreams(7, B, key).select([b]),
                return_covariances=True,
            )
        close = dict(rtol=tol, atol=tol)
        torch.testing.assert_close(
            together.estimates[b], alone.estimates[0], **close, msg=lambda m: f"{key} trial {b}: {m}"
        )
        torch.testing.assert_close(
            together.log_evidence[b], alone.log_evidence[0], **close, msg=lambda m: f"{key} trial {b}: {m}"
        )
        if alone.covariances is not None:
            torch.testing.assert_close(
                together.covariances[b], alone.covariances[0], **close, msg=lambda m: f"{key} trial {b}: {m}"
            )
    assert len(set(together.log_evidence.tolist())) == B  # the trials' values did differ


@pytest.mark.parametrize("filter_name,model_name", CASES, ids=[f"{f}-{m}" for f, m in CASES])
def test_per_trial_values_give_the_numbers_of_separate_calls(filter_name, model_name):
    _check_equal_to_separate_calls(filter_name, model_name)


CUDA_CASES = [
    ("kf", "lg"),
    ("ekf", "acoustic"),
    ("ukf", "lorenz96"),
    ("enkf", "lorenz96"),
    ("bpf", "skewed"),
    ("pfpf_edh", "acoustic"),
    ("pfpf_ledh", "acoustic_learnable"),
    ("pfpf_ledh", "sensor"),
    ("pfgspf", "skewed"),
    ("gpfis", "acoustic"),
]


@cuda
@pytest.mark.parametrize("filter_name,model_name", CUDA_CASES, ids=[f"{f}-{m}" for f, m in CUDA_CASES])
def test_per_trial_values_give_the_numbers_of_separate_calls_cuda(filter_name, model_name):
    """The same on the GPU (per-trial Philox streams there), for a filter of each family."""
    _check_equal_to_separate_calls(filter_name, model_name, device="cuda")


# ---- gradients: trial b's log-evidence depends on value b alone ------------------------------------------


def _gradient_rows(le, value):
    """``d le[b] / d value`` for every b: ``(B, *value.shape)``."""
    return torch.stack([torch.autograd.grad(le[b], value, retain_graph=True)[0] for b in range(le.shape[0])])


def test_kalman_gradient_is_per_trial_and_that_of_separate_calls():
    """KF on a linear-Gaussian model with per-trial F (a buffer) and Q (learnable, through its
    Cholesky constraint): d log p_b / d F_c and d log p_b / d Q_c vanish for c != b, and the diagonal
    blocks are the gradients of separate calls (to 1e-10)."""
    model = _lg(learnable=["Q"])
    obs = model.simulate(B, 6, torch.Generator().manual_seed(1)).observations
    Fv = LG_VALUES["F"].clone().requires_grad_(True)
    Qv = LG_VALUES["Q"].clone().requires_grad_(True)
    with per_trial_values(model, {"F": Fv, "Q": Qv}):
        mean, cov = model.declared_prior(B)
        le = F.KalmanFilter(model)(obs, mean, cov).log_evidence
    gF, gQ = _gradient_rows(le, Fv), _gradient_rows(le, Qv)
    for b in range(B):
        for c in range(B):
            if c != b:
                assert float(gF[b, c].abs().max()) == 0 and float(gQ[b, c].abs().max()) == 0
        alone = _lg(F=LG_VALUES["F"][b].clone().requires_grad_(True), Q=LG_VALUES["Q"][b].clone().requires_grad_(True))
        m_b, P_b = alone.declared_prior(1)
        le_b = F.KalmanFilter(alone)(obs[b : b + 1], m_b, P_b).log_evidence[0]
        dF, dQ = torch.autograd.grad(le_b, [alone.F, alone.Q])
        assert float(gF[b, b].abs().max()) > 0
        torch.testing.assert_close(gF[b, b], dF, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(gQ[b, b], dQ, rtol=1e-10, atol=1e-10)


def test_particle_filter_gradient_is_per_trial():
    """PF-PF (LEDH) on acoustic tracking with a per-trial learnable Psi (through its positivity
    constraint) and per-trial streams: trial b's log-evidence estimate has a gradient in Psi_b only."""
    model = AcousticTracking(learnable=["psi"])
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(B, 3, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    psi = _t([10.0, 8.0, 12.0]).requires_grad_(True)
    with per_trial_values(model, {"psi": psi}):
        le = F.ParticleFlowParticleFilter(model, flow="ledh", n_particles=16)(
            traj.observations, mean, cov, TrialStreams(3, B, "grad")
        ).log_evidence
    rows = _gradient_rows(le, psi)
    off = rows[~torch.eye(B, dtype=torch.bool)]
    assert float(off.abs().max()) == 0 and bool((rows.diagonal() != 0).all())


# ---- what the block does to the model -----------------------------------------------------------------


def test_the_block_declares_a_structure_without_shared_shortcuts_and_restores_the_model():
    model = _sensor()
    own = model.structure
    assert own.transition_matrix_scale == 0.9 and own.measurement_noise == "scalar" and own.linear_dynamics
    with per_trial_values(model, {"F": SENSOR_VALUES["F"]}):
        s = model.structure
        assert not s.linear_dynamics and s.transition_matrix_scale is None and s.linear_measurement
        assert model.F.shape == (B, 4, 4)
        F.KalmanFilter(model)  # linear for each trial: the Kalman filter takes it
    with per_trial_values(model, {"R": SENSOR_VALUES["R"]}):  # a per-trial R, diagonal in every trial
        assert model.structure.measurement_noise == "diagonal" and model.structure.measurement_noise_scale is None
        assert model.structure.linear_dynamics and model.structure.transition_matrix_scale == 0.9
    with per_trial_values(model, {"R": LG_VALUES["P0"].new_zeros(B, 4, 4) + sensor_network_covariance(2)}):
        assert model.structure.measurement_noise == "dense"
    assert model.structure is own and model.F.shape == (4, 4) and "_trial_names" not in vars(model)
    acoustic = AcousticTracking()
    with per_trial_values(acoustic, {"psi": _t([1.0, 2.0, 3.0])}):  # the kernels' named form reads psi
        assert acoustic.structure.measurement_form is None and not acoustic.structure.graph_safe
    assert acoustic.structure.measurement_form is not None


def test_constrained_values_go_through_the_constraint():
    """A learnable Q (Cholesky) and psi (positive): the model reads the given values back through
    the constraint (per-trial factor without a factorisation), a value outside it is refused by
    name, and the parametrisation's own tensor is back afterwards."""
    model = _lg(learnable=True)
    raw = constraints.unconstrained(model, "Q")
    with per_trial_values(model, {"Q": LG_VALUES["Q"]}):
        torch.testing.assert_close(model.Q, LG_VALUES["Q"], rtol=1e-12, atol=1e-12)
        L = model.transition_scale_tril()
        assert L.shape == (B, 2, 2)
        torch.testing.assert_close(L @ L.transpose(-1, -2), LG_VALUES["Q"], rtol=1e-12, atol=1e-12)
    assert constraints.unconstrained(model, "Q") is raw
    acoustic = AcousticTracking(learnable=True)
    with pytest.raises(ArgumentError, match=r"values\['psi'\]: expected values in .*domain of psi"):
        with per_trial_values(acoustic, {"psi": _t([1.0, -2.0, 3.0])}):
            pass
    assert float(acoustic.psi.detach()) == pytest.approx(10.0)


def test_bad_values_are_named():
    model = _lg()
    with pytest.raises(ArgumentError, match="does not declare 'Z' as a per-trial parameter"):
        with per_trial_values(model, {"Z": _t([1.0])}):
            pass
    with pytest.raises(ArgumentError, match=r"values\['F'\]: expected one value per trial, \(B, \*\(2, 2\)\)"):
        with per_trial_values(model, {"F": LG_VALUES["F"][0]}):
            pass
    with pytest.raises(ArgumentError, match=r"values\['Q'\]: 2 trials, where another value has 3"):
        with per_trial_values(model, {"F": LG_VALUES["F"], "Q": LG_VALUES["Q"][:2]}):
            pass
    with pytest.raises(ArgumentError, match=r"values\['F'\]: expected torch.float64"):
        with per_trial_values(model, {"F": LG_VALUES["F"].float()}):
            pass
    with pytest.raises(ArgumentTypeError, match=r"values\['F'\]: expected a tensor"):
        with per_trial_values(model, {"F": 0.5}):
            pass
    assert model.F.shape == (2, 2) and not model.__dict__.get("_trial_names")


def test_a_sweep_over_a_grid_in_one_call_finds_the_maximum_likelihood():
    """The Lorenz-96 forcing on a grid of 21 values, all in one EKF call: the log-likelihood of data
    simulated with F = 8 peaks within one grid step of 8."""
    truth = Lorenz96(d=8, forcing=8.0, model_noise=0.1, obs_std=0.5, spin_up=50)
    g = torch.Generator().manual_seed(2)
    traj = truth.simulate(1, 40, g)
    grid = torch.linspace(6.0, 10.0, 21, **f64)
    n = grid.shape[0]
    mean, cov = (v.expand(n, *v.shape[1:]) for v in truth.initial_belief(traj.states[:, 0], g))  # one prior
    with per_trial_values(truth, {"forcing": grid}):
        le = F.ExtendedKalmanFilter(truth)(traj.observations.expand(n, -1, -1), mean, cov).log_evidence
    assert abs(float(grid[le.argmax()]) - 8.0) <= 0.2 + 1e-12, le
    assert math.isfinite(float(le.max()))


def test_one_stream_for_every_trial_gives_common_random_numbers():
    """``TrialStreams(seed, [0] * B)``: trials with the same value give the same estimate, bit for bit,
    and a trial with another value another one."""
    model = _lg()
    obs = model.simulate(1, 8, torch.Generator().manual_seed(3)).observations.expand(B, -1, -1)
    with per_trial_values(model, {"F": LG_VALUES["F"][[0, 1, 0]]}):
        mean, cov = model.declared_prior(B)
        out = F.BootstrapParticleFilter(model, n_particles=32)(obs, mean, cov, TrialStreams(1, [0] * B))
    assert torch.equal(out.estimates[0], out.estimates[2]) and torch.equal(out.log_evidence[0], out.log_evidence[2])
    assert not torch.equal(out.log_evidence[0], out.log_evidence[1])


def test_a_per_trial_covariance_that_is_not_positive_semidefinite_is_named_with_its_trial():
    model = _lg()
    bad = LG_VALUES["Q"].clone()
    bad[2] = _t([[1.0, 2.0], [2.0, 1.0]])  # eigenvalues 3 and -1
    obs = model.simulate(B, 3, torch.Generator().manual_seed(0)).observations
    with per_trial_values(model, {"Q": bad}):
        mean, cov = model.declared_prior(B)
        with pytest.raises(ArgumentError, match=r"transition covariance.*batch index 2"):
            F.ExtendedKalmanFilter(model)(obs, mean, cov)


def test_a_covariance_value_outside_its_cholesky_constraint_is_named():
    model = _lg(learnable=["Q"])
    bad = LG_VALUES["Q"].clone()
    bad[1] = _t([[1.0, 2.0], [2.0, 1.0]])
    with pytest.raises(ArgumentError, match=r"values\['Q'\]: outside CholeskyCovariance's constraint"):
        with per_trial_values(model, {"Q": bad}):
            pass
    assert model.Q.shape == (2, 2)


def test_per_trial_measurement_noise_reaches_the_local_filters_terms_trial_by_trial():
    """Q38, Q40: a per-trial ``obs_std`` (B,) with particles (B, N, d) gave a raw broadcast error in
    the per-observation densities the LPF and the localised lag-one flow weigh with; each trial's
    terms are now those of the model with that trial's own value, and both filters run."""
    from torchflow.filters import LagOneFlowFilter, LocalParticleFilter
    from torchflow.inference import per_trial_values
    from torchflow.models import Lorenz96

    g = torch.Generator().manual_seed(0)
    model = Lorenz96(d=8)
    x = torch.randn(2, 5, 8, generator=g, dtype=torch.float64)
    z = torch.randn(2, 1, 8, generator=g, dtype=torch.float64)
    stds = torch.tensor([0.5, 1.0], dtype=torch.float64)
    with per_trial_values(model, {"obs_std": stds}):
        terms = model.measurement_log_prob_terms(z, x)
    for b, s in enumerate(stds.tolist()):
        alone = Lorenz96(d=8, obs_std=s).measurement_log_prob_terms(z[b], x[b])
        assert torch.allclose(terms[b], alone, rtol=1e-12, atol=0), b
    traj = model.simulate(2, 4, torch.Generator().manual_seed(1))
    mean, cov = traj.states[:, 0], 0.1 * torch.eye(8, dtype=torch.float64).expand(2, 8, 8)
    for filt in (
        LocalParticleFilter(model, n_particles=10, radius=3.0),
        LagOneFlowFilter(model, n_particles=10, radius=3.0, likelihood="model"),
    ):
        with per_trial_values(model, {"obs_std": stds}):
            res = filt(traj.observations, mean, cov, torch.Generator().manual_seed(2))
        assert torch.isfinite(res.estimates).all(), type(filt).__name__
