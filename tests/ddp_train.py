"""Helper of tests/test_scale.py (not a test): one training step of a FilterLightningModule on 8
trials, with ``Trainer(strategy="ddp")`` on N CPU processes (gloo) or on one process, saving the
gradients of the model's parameters after the (all-reduced) backward pass.

    python tests/ddp_train.py <devices> <out.pt>
"""

import sys

import pytorch_lightning as pl
import torch
from torch.utils.data import DataLoader

from torchflow.app.lightning import FilterLightningModule, TrajectoryDataset
from torchflow.filters import BootstrapParticleFilter
from torchflow.models import LinearGaussian


class Probe(FilterLightningModule):
    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.grads, self.seen = None, []

    def training_step(self, batch, batch_idx):
        self.seen += batch[3].tolist()
        return super().training_step(batch, batch_idx)

    def on_after_backward(self):  # DDP has averaged the gradients over ranks by now
        self.grads = {n: p.grad.detach().clone() for n, p in self.filter.named_parameters() if p.grad is not None}


def main(devices: int, out: str):
    torch.manual_seed(0)
    eye = torch.eye(3, dtype=torch.float64)
    H = torch.tensor([[1.0, 0.0, 0.5], [0.0, 1.0, -0.5]], dtype=torch.float64)
    make = lambda a, **kw: LinearGaussian(
        a * eye,
        0.2 * eye,
        H,
        0.1 * torch.eye(2, dtype=torch.float64),
        torch.zeros(3, dtype=torch.float64),
        eye,
        **kw,
    )
    truth = make(0.9)
    traj = truth.simulate(8, 6, torch.Generator().manual_seed(2))
    mean = torch.zeros(8, 3, dtype=torch.float64)
    cov = torch.eye(3, dtype=torch.float64).expand(8, 3, 3).clone()
    model = make(0.5, learnable=True)
    module = Probe(BootstrapParticleFilter(model, n_particles=300), lr=1e-3, seed=5)
    data = TrajectoryDataset(traj, mean, cov)
    trainer = pl.Trainer(
        max_steps=1,
        accelerator="cpu",
        devices=devices,
        strategy="ddp" if devices > 1 else "auto",
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        use_distributed_sampler=True,
    )
    # 8 trials in one batch on one process, 4 per rank on two (the distributed sampler deals them)
    trainer.fit(module, DataLoader(data, batch_size=8 // devices, shuffle=False))
    seen = trainer.strategy.all_gather(torch.tensor(module.seen)) if devices > 1 else torch.tensor([module.seen])
    if trainer.global_rank == 0:
        torch.save(
            {"grads": module.grads, "world": trainer.world_size, "trials_seen": seen.reshape(devices, -1).tolist()}, out
        )
    if torch.distributed.is_initialized():
        torch.distributed.destroy_process_group()


if __name__ == "__main__":
    main(int(sys.argv[1]), sys.argv[2])
