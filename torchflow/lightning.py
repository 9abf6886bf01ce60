"""PyTorch Lightning wrapper: learn a model's parameters by maximising a filter's log-evidence.

The core library never imports Lightning; import this module explicitly::

    from torchflow.lightning import FilterLightningModule, TrajectoryDataset

Lightning's ``Trainer`` writes logs and checkpoints under its ``default_root_dir`` (the working
folder unless given): pass ``default_root_dir=...`` or ``logger=False, enable_checkpointing=False``.
"""
from __future__ import annotations

from typing import Optional

import pytorch_lightning as pl
import torch
from torch.utils.data import Dataset

from .filters.base import Filter
from .models.base import Trajectory
from .random import TrialStreams


class TrajectoryDataset(Dataset):
    """Trials of observations with their filter priors, as ``(observations (T, m), mean (d,),
    cov (d, d), trial index ())``. The index keys the trial's random stream, so a trial draws the
    same numbers whichever batch or process (DDP rank) it lands in.

    Args:
        trajectory: simulated or recorded data, observations ``(B, T, m)``.
        mean, cov: per-trial priors ``(B, d)``, ``(B, d, d)``.
    """

    def __init__(self, trajectory: Trajectory, mean: torch.Tensor, cov: torch.Tensor):
        B = trajectory.observations.shape[0]
        if mean.shape[0] != B or cov.shape[0] != B:
            raise ValueError(f"mean, cov: expected {B} trials like the observations, got {mean.shape[0]}, {cov.shape[0]}")
        self.obs, self.mean, self.cov = trajectory.observations, mean, cov

    def __len__(self) -> int:
        return self.obs.shape[0]

    def __getitem__(self, i):
        return self.obs[i], self.mean[i], self.cov[i], torch.tensor(i)


class FilterLightningModule(pl.LightningModule):
    """Maximum-likelihood learning through a filter: the loss is the negative log-evidence per
    time step, averaged over the trials of a batch (exact for the Kalman filter; for particle
    filters the gradient of the particle log-evidence estimate, with resampling treated as fixed).

    Args:
        filter: any torchflow filter whose model has ``nn.Parameter``s (e.g. ``learnable=True``).
        lr: Adam learning rate.
        seed: seeds the filter's randomness. With batches from :class:`TrajectoryDataset`
            (which carry trial indices) each trial draws from its own stream
            (:class:`~torchflow.random.TrialStreams`, keyed by the epoch), so the loss and its
            gradient do not depend on the batch split: ``Trainer(strategy="ddp")`` on P processes,
            each with B / P trials, gives the gradient of one process with all B (DDP averages the
            ranks' means; when P does not divide B, Lightning's distributed sampler pads with
            repeated trials and the two differ). Training and validation use separate streams.
            Batches of three tensors (no index) get a ``torch.Generator`` seeded with
            ``seed + batch_idx``.
    """

    def __init__(self, filter: Filter, *, lr: float = 1e-2, seed: int = 0):
        super().__init__()
        if not any(p.requires_grad for p in filter.parameters()):
            raise ValueError("filter: its model has no learnable parameters (construct it with learnable=True)")
        self.filter = filter
        self.lr = float(lr)
        self.seed = int(seed)

    def forward(self, observations, mean, cov, generator: Optional[torch.Generator] = None):
        return self.filter(observations, mean, cov, generator)

    def _loss(self, batch, batch_idx, stage: str = "train"):
        obs, mean, cov = batch[:3]
        if len(batch) > 3:  # trial indices: per-trial streams, independent of how trials are batched
            g = TrialStreams(self.seed, batch[3].reshape(-1).tolist(),
                             key=f"{self.filter.stream_name}/{stage}/epoch{self.current_epoch}")
        else:
            g = torch.Generator(device=obs.device).manual_seed(self.seed + batch_idx)
        loss = -self.filter(obs, mean, cov, g).log_evidence.mean() / obs.shape[1]
        self.log(f"{stage}_nll_per_step", loss, prog_bar=True, batch_size=obs.shape[0])
        return loss

    def training_step(self, batch, batch_idx):
        return self._loss(batch, batch_idx)

    def configure_optimizers(self):
        return torch.optim.Adam([p for p in self.filter.parameters() if p.requires_grad], lr=self.lr)


class ValidatedFilterLightningModule(FilterLightningModule):
    """:class:`FilterLightningModule` with a validation loop (logs ``val_nll_per_step``): pass
    ``val_dataloaders`` to ``Trainer.fit``. A separate class because Lightning warns on every run
    when a module defines ``validation_step`` and no validation data is given."""

    def validation_step(self, batch, batch_idx):
        return self._loss(batch, batch_idx, "val")
