"""PyTorch Lightning wrapper: learn a model's parameters by maximising a filter's log-evidence.

The core library never imports Lightning; import this module explicitly::

    from torchflow.app.lightning import FilterLightningModule, TrajectoryDataset

Lightning's ``Trainer`` writes logs and checkpoints under its ``default_root_dir`` (the working
folder unless given): pass ``default_root_dir=...`` or ``logger=False, enable_checkpointing=False``.
"""

from __future__ import annotations

import math
import numbers
import re
from functools import reduce
from typing import Dict, List, Optional

import pytorch_lightning as pl
import torch
from torch import nn
from torch.utils.data import Dataset

from torchflow.app.data import check_observations, declared_prior
from torchflow.core import random as _random
from torchflow.core.checks import check_count
from torchflow.core.covariances import DiagonalCovariance
from torchflow.core.errors import ArgumentError, ArgumentTypeError, NonFiniteError
from torchflow.core.random import TrialStreams
from torchflow.filters.base import Filter
from torchflow.models.base import StateSpaceModel, Trajectory


def _learnable(module: nn.Module) -> Dict[str, List[nn.Parameter]]:
    """``name -> its nn.Parameters`` of the learnable (``requires_grad``) parameters of ``module``,
    a parametrised one (``parametrizations.psi.original``) under its own name (``psi``); sorted."""
    out: Dict[str, List[nn.Parameter]] = {}
    for name, p in module.named_parameters():
        if p.requires_grad:
            out.setdefault(re.sub(r"\.original\d*$", "", name.replace("parametrizations.", "")), []).append(p)
    return dict(sorted(out.items()))


def _describe(v: torch.Tensor) -> str:
    v = v.detach()
    return f"{float(v):.4g}" if v.numel() == 1 else f"{tuple(v.shape)}, largest |entry| {float(v.abs().max()):.4g}"


def learned_parameters(module: nn.Module) -> Dict[str, torch.Tensor]:
    """The learnable parameters of ``module`` (a model, or a filter: ``model.psi``) by name, each
    as the module uses it: a parametrised one (stored as ``parametrizations.psi.original``, e.g.
    a logarithm) as ``psi`` with its constrained value. Sorted by name."""
    return {n: reduce(getattr, n.split("."), module) for n in _learnable(module)}


def backward_bytes_per_step(
    filter: Filter, observations: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor, generator=None
) -> int:
    """Bytes of the tensors autograd keeps for the backward pass of one time step of ``filter``
    (the prior draw and the first step on ``observations (B, T, m)``, counted by a
    ``saved_tensors_hooks``; views of one tensor are counted each time, so an upper estimate). The
    generator is left as it was."""
    snap = _random.get_state(generator)
    total = [0]

    def pack(t):
        total[0] += t.numel() * t.element_size()
        return t

    mean, cov = filter.check_prior(mean, cov, observations.shape[0])  # as forward gives them to init
    try:
        with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
            state = filter.init(mean, cov, None, generator)
            filter.step(state, observations[:, 0], generator)
    finally:
        _random.set_state(generator, snap)
    return total[0]


class TrajectoryDataset(Dataset):
    """Trials of observations, as ``(observations (T, m), mean (d,), cov (d, d), trial index ())``
    with their filter priors, or ``(observations (T, m), trial index ())`` without: then
    :class:`FilterLightningModule` starts the filter from the model's declared prior
    (:func:`torchflow.app.data.declared_prior`), recomputed from the parameters at every optimiser
    step. The index keys the trial's random stream, so a trial draws the same numbers whichever
    batch or process (DDP rank) it lands in.

    Args:
        trajectory: a :class:`~torchflow.models.Trajectory` (its observations; the states are not
            read), or recorded observations ``(B, T, m)`` (``(T, m)``: one trial), NaN where not
            observed.
        mean, cov: per-trial priors ``(B, d)``, ``(B, d, d)`` (or a
            :class:`~torchflow.core.covariances.DiagonalCovariance`: its variances are batched, ``(B, d)``,
            and the module rebuilds it); both ``None`` (default): the model's declared prior.
    """

    def __init__(self, trajectory, mean: Optional[torch.Tensor] = None, cov: Optional[torch.Tensor] = None):
        obs = (
            trajectory.observations
            if isinstance(trajectory, Trajectory)
            else check_observations(trajectory, name="trajectory")
        )
        obs = obs.unsqueeze(0) if obs.dim() == 2 else obs
        B = obs.shape[0]
        if (mean is None) != (cov is None):
            raise ArgumentError(
                "mean, cov: expected both (the trials' priors) or neither (the model's declared prior), "
                f"got {'mean' if cov is None else 'cov'} alone"
            )
        if mean is not None and (mean.shape[0] != B or cov.shape[0] != B):
            raise ArgumentError(
                f"mean, cov: expected {B} trials like the observations, got {mean.shape[0]}, {cov.shape[0]}"
            )
        # a DiagonalCovariance as its variances: batches are collated from tensors ((B, d), rebuilt in _loss)
        self.obs, self.mean = obs, mean
        self.cov = cov.variance if isinstance(cov, DiagonalCovariance) else cov

    def __len__(self) -> int:
        return self.obs.shape[0]

    def __getitem__(self, i):
        if self.mean is None:
            return self.obs[i], torch.tensor(i)
        return self.obs[i], self.mean[i], self.cov[i], torch.tensor(i)


class FilterLightningModule(pl.LightningModule):
    """Maximum-likelihood learning through a filter: the loss is the negative log-evidence per
    time step, averaged over the trials of a batch (exact for the Kalman filter; for particle
    filters the gradient of the particle log-evidence estimate, with resampling treated as fixed).

    Batches: ``(observations (B, T, m), mean (B, d), cov (B, d, d)[, trial indices (B,)])``, or
    without a prior ``(observations[, trial indices])`` (recorded data: a :class:`TrajectoryDataset`
    without ``mean``/``cov``, a ``TensorDataset`` of observations): the filter then starts from the
    model's declared prior (:func:`torchflow.app.data.declared_prior`), recomputed at every step from
    the current parameters, so a prior that depends on them (a stationary law) is learned through.

    Args:
        filter: any torchflow filter whose model has ``nn.Parameter``s (e.g. ``learnable=True``).
        lr: Adam learning rate.
        seed: seeds the filter's randomness. With batches from :class:`TrajectoryDataset`
            (which carry trial indices) each trial draws from its own stream
            (:class:`~torchflow.core.random.TrialStreams`, keyed by the epoch), so the loss and its
            gradient do not depend on the batch split: ``Trainer(strategy="ddp")`` on P processes,
            each with B / P trials, gives the gradient of one process with all B (DDP averages the
            ranks' means; when P does not divide B, Lightning's distributed sampler pads with
            repeated trials and the two differ). Training and validation use separate streams.
            Batches of three tensors (no index) get a ``torch.Generator`` seeded with
            ``seed + batch_idx``.
        checkpoint_steps: recompute each time step in the backward pass (``Filter.forward``'s
            ``checkpoint_steps``; same values and gradients, one step's intermediates in memory):
            ``True``, ``False`` or ``"auto"`` (default): on when the tensors the backward pass
            would keep, measured on the first batch's first step (:func:`backward_bytes_per_step`)
            times T, exceed ``memory_budget_gb``.
        memory_budget_gb: the budget of ``"auto"``.
        lr_decay: the learning rate is multiplied by this after every epoch (1: constant).
        common_random_numbers: draw the same random numbers in every epoch (each trial's stream
            keyed without the epoch), so the loss is one fixed Monte Carlo approximation of the
            likelihood that the optimiser minimises (sample-average approximation: less noisy
            steps, at the price of that one approximation's error); default False: fresh draws.
        allow_approximate_evidence: learn through a filter whose ``log_evidence`` is only a
            Gaussian approximation, not an estimate of the evidence (``Filter.estimates_evidence``
            is False: the unweighted particle flow filter, the Gaussian-sum particle filters); by
            default such a filter is refused, since the gradient it gives is not the likelihood's.
        betas: Adam's decay rates of the gradient's first and second moments (torch's default
            ``(0.9, 0.999)``). From a start far from the optimum a particle filter's early
            gradients are orders of magnitude larger than those near it: the momentum, filled with
            them, carries the parameter well past the optimum, and a second moment that remembers
            ~1000 steps keeps the way back slow. ``(0.5, 0.9)`` (memories of ~2 and ~10 steps;
            what ``torchflow-learn`` uses) turns at the optimum (``python -m experiments.learn``).

    Non-finite values stop the fit with :class:`~torchflow.core.errors.NonFiniteError` naming the
    filter, the quantity and the epoch: a non-finite log-evidence (or one the filter raises), a
    non-finite gradient of a learned parameter, a learned parameter (its constrained value, e.g.
    ``psi``) non-finite after an optimiser step (a learning rate too large).
    """

    def __init__(
        self,
        filter: Filter,
        *,
        lr: float = 1e-2,
        seed: int = 0,
        checkpoint_steps="auto",
        memory_budget_gb: float = 4.0,
        lr_decay: float = 1.0,
        common_random_numbers: bool = False,
        betas=(0.9, 0.999),
        allow_approximate_evidence: bool = False,
    ):
        super().__init__()
        if not isinstance(filter, Filter):
            hint = (
                (
                    " (wrap the model in a filter, e.g. BootstrapParticleFilter(model, n_particles=500) or "
                    "KalmanFilter(model))"
                )
                if isinstance(filter, StateSpaceModel)
                else ""
            )
            raise ArgumentTypeError(f"filter: expected a torchflow Filter, got {type(filter).__name__}{hint}")
        if isinstance(lr, bool) or not isinstance(lr, numbers.Real) or not (math.isfinite(lr) and lr > 0):
            raise ArgumentError(f"lr: expected a positive finite learning rate, got {lr!r}")
        check_count("seed", seed, minimum=0)
        if not isinstance(allow_approximate_evidence, bool):
            raise ArgumentError(
                f"allow_approximate_evidence: expected True or False, got {allow_approximate_evidence!r}"
            )
        if not filter.estimates_evidence and not allow_approximate_evidence:
            raise ArgumentError(
                f"filter: expected a filter that estimates the log-evidence, got {type(filter).__name__}, whose "
                "log_evidence is a Gaussian approximation (estimates_evidence = False), so its gradient is not the "
                "likelihood's; learn through a Kalman filter, a bootstrap PF, a PF-PF, a GPFIS or another particle "
                "filter, or pass allow_approximate_evidence=True"
            )
        if not any(p.requires_grad for p in filter.parameters()):
            raise ArgumentError("filter: its model has no learnable parameters (construct it with learnable=True)")
        if checkpoint_steps not in (True, False, "auto"):
            raise ArgumentError(f"checkpoint_steps: expected True, False or 'auto', got {checkpoint_steps!r}")
        if (
            isinstance(memory_budget_gb, bool)
            or not isinstance(memory_budget_gb, (int, float))
            or memory_budget_gb <= 0
        ):
            raise ArgumentError(f"memory_budget_gb: expected a positive number of GB, got {memory_budget_gb!r}")
        self.filter = filter
        self.lr = float(lr)
        self.seed = int(seed)
        self.checkpoint_steps, self.memory_budget_gb = checkpoint_steps, float(memory_budget_gb)
        if isinstance(lr_decay, bool) or not isinstance(lr_decay, (int, float)) or not 0 < lr_decay <= 1:
            raise ArgumentError(f"lr_decay: expected a factor in (0, 1], got {lr_decay!r}")
        if not isinstance(common_random_numbers, bool):
            raise ArgumentError(f"common_random_numbers: expected True or False, got {common_random_numbers!r}")
        self.lr_decay, self.common_random_numbers = float(lr_decay), common_random_numbers
        betas = tuple(betas) if isinstance(betas, (list, tuple)) else betas
        if not (
            isinstance(betas, tuple)
            and len(betas) == 2
            and all(isinstance(b, (int, float)) and not isinstance(b, bool) and 0 <= b < 1 for b in betas)
        ):
            raise ArgumentError(f"betas: expected two Adam decay rates in [0, 1), got {betas!r}")
        self.betas = (float(betas[0]), float(betas[1]))
        self.allow_approximate_evidence = allow_approximate_evidence

    def _in_epoch(self, what: str) -> str:
        return f"{what} in epoch {self.current_epoch + 1}"

    def _with_epoch(self, err: NonFiniteError) -> NonFiniteError:
        """``err`` (raised by the filter) with the epoch in its quantity."""
        return NonFiniteError(err.filter_name, err.step, err.trials, self._in_epoch(err.what), hint=err.hint)

    def forward(self, observations, mean, cov, generator: Optional[torch.Generator] = None):
        return self.filter(observations, mean, cov, generator)

    def _loss(self, batch, batch_idx, stage: str = "train"):
        batch = [batch] if isinstance(batch, torch.Tensor) else list(batch)
        obs = batch[0]
        if len(batch) >= 3:
            mean, cov, index = batch[1], batch[2], batch[3] if len(batch) > 3 else None
            if cov.dim() == 2:  # a batch of variances (B, d) (TrajectoryDataset of a diagonal prior)
                cov = DiagonalCovariance(cov)
        else:  # no prior given: the model's declared prior at the current parameters (differentiable)
            mean, cov = declared_prior(self.filter.model, obs.shape[0])
            index = batch[1] if len(batch) > 1 else None
        if index is not None:  # trial indices: per-trial streams, independent of how trials are batched
            g = TrialStreams(
                self.seed,
                index.reshape(-1).tolist(),
                key=f"{self.filter.stream_name}/{stage}"
                + ("" if self.common_random_numbers else f"/epoch{self.current_epoch}"),
            )
        else:
            g = torch.Generator(device=obs.device).manual_seed(self.seed + batch_idx)
        if self.checkpoint_steps == "auto" and torch.is_grad_enabled():
            need = backward_bytes_per_step(self.filter, obs, mean, cov, g) * obs.shape[1]
            self.checkpoint_steps = need > self.memory_budget_gb * 1e9
        ckpt = self.checkpoint_steps is True
        try:
            log_evidence = self.filter(obs, mean, cov, g, checkpoint_steps=ckpt).log_evidence
        except NonFiniteError as err:
            raise self._with_epoch(err) from err
        except ArgumentError as err:  # the filter refuses the model the optimiser's steps have made
            if self.global_step == 0:
                raise
            values = ", ".join(
                f"{n.removeprefix('model.')} {_describe(v)}" for n, v in learned_parameters(self.filter).items()
            )
            raise ArgumentError(
                f"{self.filter.name}: in epoch {self.current_epoch + 1} the learned parameters ({values}) "
                f"give a model the filter refuses ({err})"
            ) from err
        bad = ~torch.isfinite(log_evidence.detach())
        if bool(bad.any()):
            raise NonFiniteError(
                self.filter.name, 0, torch.nonzero(bad).flatten().tolist(), self._in_epoch("log-evidence")
            )
        loss = -log_evidence.mean() / obs.shape[1]
        self.log(f"{stage}_nll_per_step", loss, prog_bar=True, batch_size=obs.shape[0])
        return loss

    def training_step(self, batch, batch_idx):
        return self._loss(batch, batch_idx)

    def backward(self, loss, *args, **kwargs):
        try:
            super().backward(loss, *args, **kwargs)
        except NonFiniteError as err:  # the filter's own gradient checks
            raise self._with_epoch(err) from err

    def on_after_backward(self):
        bad = [
            n.removeprefix("model.")
            for n, ps in _learnable(self.filter).items()
            if any(p.grad is not None and not bool(torch.isfinite(p.grad).all()) for p in ps)
        ]
        if bad:
            raise NonFiniteError(self.filter.name, 0, [], self._in_epoch(f"gradient of {', '.join(bad)}"))

    def on_train_batch_end(self, outputs, batch, batch_idx):
        bad = [
            n.removeprefix("model.")
            for n, v in learned_parameters(self.filter).items()
            if not bool(torch.isfinite(v).all())
        ]
        if bad:
            raise NonFiniteError(
                self.filter.name, 0, [], f"{', '.join(bad)} after the optimiser step of epoch {self.current_epoch + 1}"
            )

    def configure_optimizers(self):
        opt = torch.optim.Adam([p for p in self.filter.parameters() if p.requires_grad], lr=self.lr, betas=self.betas)
        if self.lr_decay == 1.0:
            return opt
        return {"optimizer": opt, "lr_scheduler": torch.optim.lr_scheduler.ExponentialLR(opt, self.lr_decay)}


class ValidatedFilterLightningModule(FilterLightningModule):
    """:class:`FilterLightningModule` with a validation loop (logs ``val_nll_per_step``): pass
    ``val_dataloaders`` to ``Trainer.fit``. A separate class because Lightning warns on every run
    when a module defines ``validation_step`` and no validation data is given."""

    def validation_step(self, batch, batch_idx):
        return self._loss(batch, batch_idx, "val")
