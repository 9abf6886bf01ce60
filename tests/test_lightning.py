import pytest
import torch

pl = pytest.importorskip("pytorch_lightning")

from torch.utils.data import DataLoader

from torchflow.app.lightning import FilterLightningModule, TrajectoryDataset
from torchflow.filters import KalmanFilter, ParticleFlowParticleFilter
from torchflow.models import LinearGaussian


def _data(d=2, B=64, T=20):
    eye = torch.eye(d, dtype=torch.float64)
    truth = LinearGaussian(0.9 * eye, 0.2 * eye, eye, 0.1 * eye, torch.zeros(d, dtype=torch.float64), eye)
    traj = truth.simulate(B, T, torch.Generator().manual_seed(0))
    mean, cov = truth.initial_belief(traj.states[:, 0])
    return traj, mean, cov


def _fit(f, traj, mean, cov, epochs):
    module = FilterLightningModule(f, lr=0.05)
    trainer = pl.Trainer(
        max_epochs=epochs,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        accelerator="cpu",
    )
    trainer.fit(module, DataLoader(TrajectoryDataset(traj, mean, cov), batch_size=32))


def test_lightning_learns_transition_matrix_through_kf():
    traj, mean, cov = _data()
    eye = torch.eye(2, dtype=torch.float64)
    model = LinearGaussian(
        0.5 * eye, 0.2 * eye, eye, 0.1 * eye, torch.zeros(2, dtype=torch.float64), eye, learnable=True
    )
    _fit(KalmanFilter(model), traj, mean, cov, epochs=15)
    assert abs(float(model.F.diagonal().mean()) - 0.9) < 0.1  # moved from 0.5 to the truth 0.9


def test_lightning_with_pfpf_improves_likelihood():
    traj, mean, cov = _data(B=32, T=10)
    eye = torch.eye(2, dtype=torch.float64)
    model = LinearGaussian(
        0.5 * eye, 0.2 * eye, eye, 0.1 * eye, torch.zeros(2, dtype=torch.float64), eye, learnable=["F"]
    )
    assert not isinstance(model.Q, torch.nn.Parameter)
    _fit(ParticleFlowParticleFilter(model, flow="edh", n_particles=32), traj, mean, cov, epochs=8)
    assert float(model.F.diagonal().mean()) > 0.7


def test_lightning_rejects_filter_without_parameters():
    traj, mean, cov = _data()
    with pytest.raises(ValueError, match="learnable"):
        FilterLightningModule(KalmanFilter(LinearGaussian(torch.eye(2), torch.eye(2), torch.eye(2), torch.eye(2))))


def test_lightning_no_validation_warning_and_validated_variant(tmp_path, recwarn):
    from torchflow.app.lightning import ValidatedFilterLightningModule

    traj, mean, cov = _data(B=16, T=5)
    eye = torch.eye(2, dtype=torch.float64)
    model = LinearGaussian(
        0.5 * eye, 0.2 * eye, eye, 0.1 * eye, torch.zeros(2, dtype=torch.float64), eye, learnable=["F"]
    )
    data = DataLoader(TrajectoryDataset(traj, mean, cov), batch_size=8)
    trainer = pl.Trainer(max_epochs=1, default_root_dir=tmp_path, enable_progress_bar=False, accelerator="cpu")
    trainer.fit(FilterLightningModule(KalmanFilter(model), lr=0.05), data)
    assert not [w for w in recwarn if "validation_step" in str(w.message)]
    module = ValidatedFilterLightningModule(KalmanFilter(model), lr=0.05)
    trainer = pl.Trainer(max_epochs=1, default_root_dir=tmp_path, enable_progress_bar=False, accelerator="cpu")
    trainer.fit(module, data, val_dataloaders=data)
    assert "val_nll_per_step" in trainer.callback_metrics


@pytest.mark.parametrize(
    "bad",
    [
        {"betas": (0.9,)},
        {"betas": (0.9, 1.0)},
        {"betas": "adam"},
        {"lr_decay": 0.0},
        {"lr_decay": True},
        {"checkpoint_steps": "yes"},
        {"memory_budget_gb": -1},
        {"common_random_numbers": 1},
    ],
)
def test_lightning_options_are_checked(bad):
    eye = torch.eye(2, dtype=torch.float64)
    f = KalmanFilter(LinearGaussian(eye, eye, eye, eye, learnable=["F"]))
    with pytest.raises(ValueError, match=next(iter(bad))):
        FilterLightningModule(f, **bad)


def test_lightning_betas_and_decay_reach_the_optimiser():
    eye = torch.eye(2, dtype=torch.float64)
    f = KalmanFilter(LinearGaussian(eye, eye, eye, eye, learnable=["F"]))
    cfg = FilterLightningModule(f, lr=0.1, betas=[0.0, 0.9], lr_decay=0.5).configure_optimizers()
    opt = cfg["optimizer"]
    assert opt.param_groups[0]["betas"] == (0.0, 0.9) and opt.param_groups[0]["lr"] == 0.1
    cfg["lr_scheduler"].step()
    assert opt.param_groups[0]["lr"] == pytest.approx(0.05)
    assert isinstance(FilterLightningModule(f).configure_optimizers(), torch.optim.Adam)  # no decay: no scheduler


def _eye_lg(**kw):
    eye = torch.eye(2, dtype=torch.float64)
    return LinearGaussian(0.9 * eye, 0.2 * eye, eye, 0.1 * eye, torch.zeros(2, dtype=torch.float64), eye, **kw)


def test_a_model_given_instead_of_a_filter_is_refused_naming_the_argument_with_a_hint():
    from torchflow.core.errors import ArgumentTypeError

    with pytest.raises(
        ArgumentTypeError,
        match=r"^filter: expected a torchflow Filter, got LinearGaussian \(wrap the "
        r"model in a filter, e\.g\. BootstrapParticleFilter\(model",
    ):
        FilterLightningModule(_eye_lg(learnable=["F"]))
    with pytest.raises(ArgumentTypeError, match=r"^filter: expected a torchflow Filter, got str$"):
        FilterLightningModule("kf")


@pytest.mark.parametrize(
    "bad",
    [
        {"lr": 0},
        {"lr": -0.1},
        {"lr": float("inf")},
        {"lr": "0.1"},
        {"lr": True},
        {"seed": -1},
        {"seed": 1.5},
        {"seed": "0"},
        {"allow_approximate_evidence": 1},
    ],
)
def test_learning_rate_seed_and_the_evidence_opt_in_are_checked_at_construction(bad):
    from torchflow.core.errors import ArgumentError

    with pytest.raises(ArgumentError, match=f"^{next(iter(bad))}: expected"):
        FilterLightningModule(KalmanFilter(_eye_lg(learnable=["F"])), **bad)


def test_learning_through_a_filter_without_a_consistent_evidence_is_refused_unless_allowed():
    from torchflow.core.errors import ArgumentError
    from torchflow.filters import GaussianSumParticleFilter, ParticleFlowFilter

    for f in (
        ParticleFlowFilter(_eye_lg(learnable=["F"]), n_particles=8),
        GaussianSumParticleFilter(_eye_lg(learnable=["F"]), particles_per_component=8),
    ):
        with pytest.raises(
            ArgumentError,
            match=f"^filter: expected a filter that estimates the log-evidence, got "
            f"{type(f).__name__}, .*allow_approximate_evidence=True$",
        ):
            FilterLightningModule(f)
        assert FilterLightningModule(f, allow_approximate_evidence=True).allow_approximate_evidence is True


def _fit_until_it_fails(module, traj, mean, cov, epochs=3):
    trainer = pl.Trainer(
        max_epochs=epochs,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        accelerator="cpu",
    )
    trainer.fit(module, DataLoader(TrajectoryDataset(traj, mean, cov), batch_size=len(traj.observations)))


def test_a_non_finite_log_evidence_stops_learning_naming_the_filter_trials_and_epoch():
    from torchflow.core.errors import NonFiniteError

    class Faulty(KalmanFilter):  # from its second call (epoch 2 with one batch per epoch), trial 1's is NaN
        calls = 0

        def forward(self, *args, **kwargs):
            res, Faulty.calls = super().forward(*args, **kwargs), Faulty.calls + 1
            if Faulty.calls >= 2:
                res.log_evidence = res.log_evidence * torch.tensor([1.0, float("nan"), 1.0, 1.0], dtype=torch.float64)
            return res

    traj, mean, cov = _data(B=4, T=5)
    with pytest.raises(NonFiniteError, match=r"^Faulty: non-finite log-evidence in epoch 2 in trial\(s\) \[1\]$"):
        _fit_until_it_fails(FilterLightningModule(Faulty(_eye_lg(learnable=["F"])), lr=0.05), traj, mean, cov)


def test_a_non_finite_gradient_stops_learning_naming_the_parameter_and_epoch():
    from torchflow.core.errors import NonFiniteError

    traj, mean, cov = _data(B=4, T=5)
    model, calls = _eye_lg(learnable=["F"]), [0]

    def poison(grad):  # the second backward pass (epoch 2) gives a NaN gradient of F
        calls[0] += 1
        return grad * float("nan") if calls[0] == 2 else grad

    model.F.register_hook(poison)
    with pytest.raises(NonFiniteError, match=r"^KalmanFilter: non-finite gradient of .*F.* in epoch 2"):
        _fit_until_it_fails(FilterLightningModule(KalmanFilter(model), lr=0.05), traj, mean, cov)
    assert torch.isfinite(model.F).all()  # stopped before the optimiser's step


def test_a_parameter_made_non_finite_by_an_optimiser_step_stops_learning_naming_it_and_the_epoch():
    from torchflow.core.errors import NonFiniteError
    from torchflow.filters import BootstrapParticleFilter
    from torchflow.models import AcousticTracking

    truth = AcousticTracking()
    g = torch.Generator().manual_seed(0)
    traj = truth.simulate(2, 3, g)
    mean, cov = truth.initial_belief(traj.states[:, 0], g)
    f = BootstrapParticleFilter(AcousticTracking(learnable=["psi"], psi=5.0), n_particles=20)
    with pytest.raises(
        NonFiniteError,
        match=r"^BootstrapParticleFilter: non-finite psi after the optimiser step of "
        r"epoch 1$",
    ):  # log psi moves by ~lr = 1000: psi = exp(1001) = inf
        _fit_until_it_fails(FilterLightningModule(f, lr=1000.0), traj, mean, cov)
