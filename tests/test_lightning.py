import pytest
import torch

pl = pytest.importorskip("pytorch_lightning")

from torch.utils.data import DataLoader  # noqa: E402

from torchflow.filters import KalmanFilter, ParticleFlowParticleFilter  # noqa: E402
from torchflow.lightning import FilterLightningModule, TrajectoryDataset  # noqa: E402
from torchflow.models import LinearGaussian  # noqa: E402


def _data(d=2, B=64, T=20):
    eye = torch.eye(d, dtype=torch.float64)
    truth = LinearGaussian(0.9 * eye, 0.2 * eye, eye, 0.1 * eye, torch.zeros(d, dtype=torch.float64), eye)
    traj = truth.simulate(B, T, torch.Generator().manual_seed(0))
    mean, cov = truth.initial_belief(traj.states[:, 0])
    return traj, mean, cov


def _fit(f, traj, mean, cov, epochs):
    module = FilterLightningModule(f, lr=0.05)
    trainer = pl.Trainer(max_epochs=epochs, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, accelerator="cpu")
    trainer.fit(module, DataLoader(TrajectoryDataset(traj, mean, cov), batch_size=32))


def test_lightning_learns_transition_matrix_through_kf():
    traj, mean, cov = _data()
    eye = torch.eye(2, dtype=torch.float64)
    model = LinearGaussian(0.5 * eye, 0.2 * eye, eye, 0.1 * eye, torch.zeros(2, dtype=torch.float64), eye,
                           learnable=True)
    _fit(KalmanFilter(model), traj, mean, cov, epochs=15)
    assert abs(float(model.F.diagonal().mean()) - 0.9) < 0.1  # moved from 0.5 to the truth 0.9


def test_lightning_with_pfpf_improves_likelihood():
    traj, mean, cov = _data(B=32, T=10)
    eye = torch.eye(2, dtype=torch.float64)
    model = LinearGaussian(0.5 * eye, 0.2 * eye, eye, 0.1 * eye, torch.zeros(2, dtype=torch.float64), eye,
                           learnable=["F"])
    assert not isinstance(model.Q, torch.nn.Parameter)
    _fit(ParticleFlowParticleFilter(model, flow="edh", n_particles=32), traj, mean, cov, epochs=8)
    assert float(model.F.diagonal().mean()) > 0.7


def test_lightning_rejects_filter_without_parameters():
    traj, mean, cov = _data()
    with pytest.raises(ValueError, match="learnable"):
        FilterLightningModule(KalmanFilter(LinearGaussian(torch.eye(2), torch.eye(2), torch.eye(2), torch.eye(2))))


def test_lightning_no_validation_warning_and_validated_variant(tmp_path, recwarn):
    from torchflow.lightning import ValidatedFilterLightningModule

    traj, mean, cov = _data(B=16, T=5)
    eye = torch.eye(2, dtype=torch.float64)
    model = LinearGaussian(0.5 * eye, 0.2 * eye, eye, 0.1 * eye, torch.zeros(2, dtype=torch.float64), eye,
                           learnable=["F"])
    data = DataLoader(TrajectoryDataset(traj, mean, cov), batch_size=8)
    trainer = pl.Trainer(max_epochs=1, default_root_dir=tmp_path, enable_progress_bar=False, accelerator="cpu")
    trainer.fit(FilterLightningModule(KalmanFilter(model), lr=0.05), data)
    assert not [w for w in recwarn if "validation_step" in str(w.message)]
    module = ValidatedFilterLightningModule(KalmanFilter(model), lr=0.05)
    trainer = pl.Trainer(max_epochs=1, default_root_dir=tmp_path, enable_progress_bar=False, accelerator="cpu")
    trainer.fit(module, data, val_dataloaders=data)
    assert "val_nll_per_step" in trainer.callback_metrics


@pytest.mark.parametrize("bad", [{"betas": (0.9,)}, {"betas": (0.9, 1.0)}, {"betas": "adam"}, {"lr_decay": 0.0},
                                 {"lr_decay": True}, {"checkpoint_steps": "yes"}, {"memory_budget_gb": -1},
                                 {"common_random_numbers": 1}])
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
