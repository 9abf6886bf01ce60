"""NeuralAcoustic: acoustic tracking whose sensor response is a module (a small MLP), learned
through the filters' log-evidence."""

import math

import pytest
import torch
from torch import nn

from torchflow.core.linearize import jacobian
from torchflow.filters import BootstrapParticleFilter, ExtendedKalmanFilter, ParticleFlowParticleFilter
from torchflow.flows.schedules import ExponentialSchedule
from torchflow.models import AcousticTracking, GaussianStateSpaceModel, InverseDistance, NeuralAcoustic, ResponseMLP
from torchflow.models.contract import check_shapes

SCHED = ExponentialSchedule(8, 1.3)


def _small(response=None, **kw):
    return NeuralAcoustic(response, n_targets=2, sensor_grid=3, **kw)


def _points(model, shape, seed=0):
    g = torch.Generator().manual_seed(seed)
    return model.x0 + 4 * torch.randn(*shape, model.state_dim, generator=g, dtype=torch.float64)


def test_with_the_inverse_distance_response_it_is_the_acoustic_model():
    """InverseDistance(10, 0.1) inside NeuralAcoustic gives AcousticTracking's simulated data,
    measurements, Jacobians, Hessians and densities (4 targets, 25 sensors)."""
    ref, ours = AcousticTracking(), NeuralAcoustic(InverseDistance(10.0, 0.1))
    a, b = ref.simulate(3, 6, torch.Generator().manual_seed(1)), ours.simulate(3, 6, torch.Generator().manual_seed(1))
    assert torch.equal(a.states, b.states)
    torch.testing.assert_close(a.observations, b.observations, atol=1e-12, rtol=0)
    x = a.states[:, 1:]
    for name in ("measure", "measurement_jacobian", "measurement_jacobian_support"):
        torch.testing.assert_close(getattr(ours, name)(x), getattr(ref, name)(x), atol=1e-12, rtol=1e-12)
    for support in (False, True):
        torch.testing.assert_close(
            ours.measurement_hessian_blocks(x, support, 2.0),
            ref.measurement_hessian_blocks(x, support, 2.0),
            atol=1e-10,
            rtol=1e-12,
        )
        for u, v in zip(ours.linearize_measurement(x, support, 0.5), ref.linearize_measurement(x, support, 0.5)):
            torch.testing.assert_close(u, v, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(
        ours.measurement_log_prob(a.observations, x), ref.measurement_log_prob(a.observations, x)
    )
    assert ours.structure.measurement_support == ref.structure.measurement_support
    assert ours.structure.measurement_form is None  # no kernel's own arithmetic for a user's response


@pytest.mark.parametrize("hidden", [(16,), (8, 8)])
def test_closed_form_derivatives_equal_autodiff(hidden):
    """The MLP's Jacobian and Hessian blocks (closed-form forward mode) equal torch.func's
    Jacobian of ``measure`` and the default Hessian (forward mode over that Jacobian)."""
    model = _small(ResponseMLP(hidden, seed=3))
    x = _points(model, (5, 3))
    J = model.measurement_jacobian(x)
    assert J.shape == (5, 3, 9, 8)
    torch.testing.assert_close(J, jacobian(model.measure, x), atol=1e-12, rtol=1e-10)
    assert (J[..., 2::4] == 0).all() and (J[..., 3::4] == 0).all()  # velocities unobserved
    H = model.measurement_hessian(x, support=True)
    H_ad = GaussianStateSpaceModel.measurement_hessian(model, x, support=True)
    torch.testing.assert_close(H, H_ad, atol=1e-13, rtol=1e-8)
    assert float(H.detach().abs().max()) > 1e-5  # not vacuous (a random MLP's response is flat-ish)


class _Plain(nn.Module):
    """An elementwise response without a ``derivatives`` method: differentiated by torch.func."""

    def __init__(self, mlp):
        super().__init__()
        self.mlp = mlp

    def forward(self, r):
        return self.mlp(r)


def test_a_response_without_derivatives_is_differentiated_by_forward_mode():
    mlp = ResponseMLP(seed=2)
    closed, plain = _small(mlp), _small(_Plain(mlp))
    x = _points(closed, (4,))
    torch.testing.assert_close(plain.measure(x), closed.measure(x))
    torch.testing.assert_close(plain.measurement_jacobian(x), closed.measurement_jacobian(x), atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(
        plain.measurement_hessian_blocks(x, True), closed.measurement_hessian_blocks(x, True), atol=1e-10, rtol=1e-8
    )


def test_it_passes_the_model_contract_checks_in_both_precisions():
    for dtype in (torch.float64, torch.float32):
        model = _small().to(dtype)
        assert model.dtype == dtype and all(p.dtype == dtype for p in model.parameters())
        traj = model.simulate(3, 4, torch.Generator().manual_seed(0))
        check_shapes(model, traj.states[:, 1], "test")  # raises on a wrong shape
        assert traj.states.shape == (3, 5, 8) and traj.observations.shape == (3, 4, 9)
        assert torch.isfinite(traj.observations).all()


@pytest.mark.parametrize(
    "make",
    [
        lambda m: BootstrapParticleFilter(m, n_particles=64),
        lambda m: ParticleFlowParticleFilter(m, n_particles=16, schedule=SCHED),
        lambda m: ExtendedKalmanFilter(m),
    ],
    ids=["bpf", "pfpf_ledh", "ekf"],
)
def test_filters_run_on_it(make):
    model = _small()
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(2, 5, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    out = make(model)(traj.observations, mean, cov, g)
    assert out.estimates.shape == (2, 5, 8) and torch.isfinite(out.estimates).all()
    assert torch.isfinite(out.log_evidence).all()


@pytest.mark.parametrize(
    "make",
    [
        lambda m: BootstrapParticleFilter(m, n_particles=64),
        lambda m: ParticleFlowParticleFilter(m, n_particles=16, schedule=SCHED),
        lambda m: ParticleFlowParticleFilter(m, n_particles=16, schedule=SCHED, proposal_gradient="score"),
    ],
    ids=["bpf", "pfpf_ledh_pathwise", "pfpf_ledh_score"],
)
def test_the_log_evidence_gradient_reaches_every_mlp_parameter(make):
    model = _small()
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(2, 5, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    make(model)(traj.observations, mean, cov, g).log_evidence.sum().backward()
    names = [n for n, _ in model.named_parameters()]
    assert names == [
        "response.layers.0.weight",
        "response.layers.0.bias",
        "response.layers.1.weight",
        "response.layers.1.bias",
    ]
    for n, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), n
        assert float(p.grad.abs().max()) > 0, n


def test_a_short_fit_through_the_lightning_module_raises_the_log_likelihood():
    """From a response fitted to a wrong law (5 / (r + 0.1)^0.75), 12 Adam steps through the
    bootstrap PF (one target, 9 sensors, 4 tracks x 10 steps) raise the log-likelihood of the
    training data, estimated with 4 filter runs before and after (the same seeds): the mean rise
    must exceed 4 standard errors of the paired difference (measured: +4.3 nats per track, from
    59.2; the true response's is 62.0)."""
    pl = pytest.importorskip("pytorch_lightning")
    from torch.utils.data import DataLoader

    from torchflow.app.lightning import FilterLightningModule, TrajectoryDataset

    truth = NeuralAcoustic(InverseDistance(), n_targets=1, sensor_grid=3)
    g = torch.Generator().manual_seed(0)
    traj = truth.simulate(4, 10, g)
    mean, cov = truth.initial_belief(traj.states[:, 0], g)
    model = NeuralAcoustic(ResponseMLP(), n_targets=1, sensor_grid=3)
    assert model.response.fit(lambda r: 5.0 / (r + 0.1) ** 0.75, 60.0, steps=300, lr=0.05) < 0.05

    def loglik():
        pf = BootstrapParticleFilter(model, n_particles=2000)
        with torch.no_grad():
            return torch.stack(
                [
                    pf(traj.observations, mean, cov, torch.Generator().manual_seed(s)).log_evidence.mean()
                    for s in range(4)
                ]
            )

    before = loglik()
    module = FilterLightningModule(BootstrapParticleFilter(model, n_particles=300), lr=0.01, betas=(0.5, 0.9))
    trainer = pl.Trainer(
        max_epochs=12,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        accelerator="cpu",
        devices=1,
    )
    trainer.fit(module, DataLoader(TrajectoryDataset(traj, mean, cov), batch_size=4))
    rise = loglik() - before
    assert float(rise.mean()) > 4 * float(rise.std()) / 2 and float(rise.mean()) > 1.0, rise


def test_response_mlp_fits_a_law_and_stays_positive():
    mlp = ResponseMLP(seed=1)
    rms = mlp.fit(lambda r: 10 / (r + 0.1), 60.0, steps=400, lr=0.05)
    assert rms < 0.05
    r = torch.tensor([0.0, 1.0, 10.0, 50.0], dtype=torch.float64)
    with torch.no_grad():
        torch.testing.assert_close(mlp(r), 10 / (r + 0.1), rtol=0.1, atol=0)
        assert (mlp(torch.tensor([1e3, 1e6], dtype=torch.float64)) > 0).all()


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="n_targets: expected at most 4"):
        NeuralAcoustic(n_targets=5)
    with pytest.raises(ValueError, match="n_targets"):
        NeuralAcoustic(n_targets=0)
    with pytest.raises(TypeError, match="response: expected an nn.Module"):
        NeuralAcoustic(lambda r: 1 / r)
    with pytest.raises(ValueError, match="learnable"):
        NeuralAcoustic(learnable=["psi"])
    with pytest.raises(ValueError, match="initial_state: expected 8 numbers"):
        NeuralAcoustic(n_targets=2, initial_state=[10.0] * 12)
    with pytest.raises(ValueError, match=r"hidden\[1\]"):
        ResponseMLP((16, 0))
    with pytest.raises(ValueError, match="hidden: expected at least one"):
        ResponseMLP(())
    with pytest.raises(ValueError, match="psi"):
        InverseDistance(psi=-1.0)
    model = NeuralAcoustic(n_targets=2, initial_state=[10.0, 10, 0, 0, 30, 30, 0, 0], learnable=True)
    assert model.state_dim == 8 and "parametrizations.sigma_w.original" in dict(model.named_parameters())
    assert not hasattr(model, "psi") and math.isclose(float(model.sigma_w), 0.1)


def test_the_noise_scale_alone_may_hold_per_trial_values():
    """The neural model has no physical amplitude psi (its response holds its own): only sigma_w
    may hold one value per trial, and a per-trial psi is refused by name, not by an AttributeError."""
    from torchflow.core.errors import ArgumentError
    from torchflow.inference import per_trial_values

    model = _small()
    assert model.per_trial_parameters == ("sigma_w",)
    with per_trial_values(model, {"sigma_w": torch.tensor([0.1, 0.2], dtype=torch.float64)}):
        assert model.measurement_cov(torch.zeros(2, 3, model.state_dim, dtype=torch.float64)).shape[0] == 2
    with pytest.raises(ArgumentError, match="psi"):
        with per_trial_values(model, {"psi": torch.tensor([1.0, 2.0], dtype=torch.float64)}):
            pass
