"""Covariances carried by a particle filter's state, typed by what they belong to.

A PF-PF tracks the flow's prior covariance with an EKF/UKF, either once per trial (global and
clustered linearisation points) or once per particle (per-particle points, LEDH); the type says
which, and so how resampling treats it:

* :class:`TrialCovariance` ``(B, d, d)``: one per trial; resampling leaves it alone.
* :class:`ParticleCovariance` ``(B, N, d, d)``: one per particle; resampled with the particles.
  ``identical=True`` (declared by the filter: an EKF on a linear model gives every particle the
  same covariance) stores one ``(B, 1, d, d)`` that broadcasts, and resampling leaves it alone.

Clusters are rebuilt every step (:class:`~torchflow.flows.points.ClusteredPoints`), so a
per-cluster covariance never outlives a step: a clustered flow is given the trial's covariance at
its K points, ``(B, 1, d, d)`` broadcast over clusters.

A *prior* covariance is a dense tensor ``(B, d, d)`` or, for a model that declares a diagonal
prior (:attr:`~torchflow.models.Structure.prior_covariance`), a :class:`DiagonalCovariance`: its
variances ``(B, d)`` alone, so that a state of ``d = 10^5`` coordinates or more needs no ``d x d``
matrix before the first step. The filters that start from the prior by sampling it (ensemble
Kalman filters, the bootstrap PF: :attr:`~torchflow.filters.Filter.diagonal_prior`) use the
variances directly; the others are given the dense matrix.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from torchflow.core.errors import ArgumentError


@dataclass
class Covariance:
    """Base: ``matrix`` and how it follows resampling (:meth:`resampled`)."""

    matrix: torch.Tensor

    #: the tracker predicts at each particle (True) or at the trial's estimate (False)
    per_particle = False

    def resampled(self, index: torch.Tensor) -> "Covariance":
        """This covariance after the particles were resampled with ``index (B, N)``."""
        return self

    def transported(self, plan: torch.Tensor) -> "Covariance":
        """This covariance after transport resampling: new particle ``j`` is ``sum_i plan[b, i, j]
        x_i`` (``plan (B, N, N)``, columns summing to one)."""
        return self

    def like(self, matrix: torch.Tensor) -> "Covariance":
        """The same type with a new ``matrix`` (the step's updated covariance)."""
        return replace(self, matrix=matrix)


@dataclass
class TrialCovariance(Covariance):
    """One covariance per trial, ``(B, d, d)``."""


@dataclass
class ParticleCovariance(Covariance):
    """One covariance per particle, ``(B, N, d, d)``; with ``identical=True`` a single ``(B, 1, d, d)``
    that every particle shares (declared, e.g. an EKF on a linear model)."""

    identical: bool = False
    per_particle = True

    def resampled(self, index: torch.Tensor) -> "Covariance":
        if self.identical:
            return self
        from torchflow.core.resampling import gather_particles

        return self.like(gather_particles(self.matrix, index))

    def transported(self, plan: torch.Tensor) -> "Covariance":
        """Each new particle carries the same convex combination of the covariances (still
        positive definite)."""
        if self.identical:
            return self
        return self.like(torch.einsum("bij,bi...->bj...", plan.to(self.matrix.dtype), self.matrix))


class DiagonalCovariance:
    """A diagonal prior covariance held as its variances: ``variance (B, d)`` (one per trial) or
    ``(d,)`` (shared), standing for the matrix ``diag(variance)`` of shape ``(B, d, d)`` /
    ``(d, d)`` (:attr:`shape`) without forming it.

    It behaves as that matrix where the runner and the filters pass a prior on: trials are selected
    with ``cov[s:e]`` (or an index tensor), ``.to(...)``, ``.detach()``, ``.expand(B, d, d)`` and
    ``.diagonal()`` work on the variances, and :meth:`dense` forms the matrix where a filter needs
    it (Kalman filters, flows). A filter declaring :attr:`~torchflow.filters.Filter.diagonal_prior`
    draws its initial particles as ``mean + sqrt(variance) xi``.

    Example::

        cov = DiagonalCovariance(torch.full((4, 100_000), 0.25))   # 4 trials, d = 10^5
        cov.shape          # torch.Size([4, 100000, 100000]): the matrix it stands for
        cov[1:3].variance  # (2, 100000)
    """

    __slots__ = ("variance",)

    def __init__(self, variance: torch.Tensor):
        if not isinstance(variance, torch.Tensor) or variance.dim() not in (1, 2) or not variance.is_floating_point():
            got = tuple(variance.shape) if isinstance(variance, torch.Tensor) else type(variance).__name__
            raise ArgumentError(
                f"DiagonalCovariance: variance: expected a floating-point tensor (B, d) or (d,) "
                f"(the prior's variances), got {got}"
            )
        self.variance = variance

    # ---- what a (B, d, d) tensor offers the code that passes a prior on ----------------------------
    @property
    def shape(self) -> torch.Size:
        """The shape of the matrix it stands for: ``(B, d, d)`` or ``(d, d)``."""
        return torch.Size((*self.variance.shape, self.variance.shape[-1]))

    @property
    def dtype(self) -> torch.dtype:
        return self.variance.dtype

    @property
    def device(self) -> torch.device:
        return self.variance.device

    @property
    def requires_grad(self) -> bool:
        return self.variance.requires_grad

    def dim(self) -> int:
        return self.variance.dim() + 1

    @property
    def ndim(self) -> int:
        return self.dim()

    def __len__(self) -> int:
        return self.variance.shape[0]

    def __getitem__(self, index) -> "DiagonalCovariance":
        """Trials selected along the first dimension (``cov[s:e]``, ``cov[i]``, ``cov[index]``)."""
        if self.variance.dim() != 2 or isinstance(index, tuple):
            raise ArgumentError(
                f"DiagonalCovariance: only trials are selected (cov[s:e], cov[i], cov[index]) "
                f"from variances (B, d); got index {index!r} on {tuple(self.variance.shape)}"
            )
        return DiagonalCovariance(self.variance[index])

    def to(self, *args, **kwargs) -> "DiagonalCovariance":
        return DiagonalCovariance(self.variance.to(*args, **kwargs))

    def detach(self) -> "DiagonalCovariance":
        return DiagonalCovariance(self.variance.detach())

    def cpu(self) -> "DiagonalCovariance":
        return DiagonalCovariance(self.variance.cpu())

    def double(self) -> "DiagonalCovariance":
        return DiagonalCovariance(self.variance.double())

    def float(self) -> "DiagonalCovariance":
        return DiagonalCovariance(self.variance.float())

    def expand(self, *sizes) -> "DiagonalCovariance":
        """``expand(B, d, d)`` (or ``-1`` entries) of a shared ``(d,)`` prior: the variances ``(B, d)``
        (a view)."""
        sizes = tuple(sizes[0]) if len(sizes) == 1 and isinstance(sizes[0], (tuple, list, torch.Size)) else sizes
        d = self.variance.shape[-1]
        if len(sizes) != 3 or any(s not in (-1, d) for s in sizes[-2:]):
            raise ArgumentError(f"DiagonalCovariance.expand: expected (B, d, d) with d = {d} (or -1), got {sizes}")
        return DiagonalCovariance(self.variance.expand(sizes[0], -1))

    def clone(self) -> "DiagonalCovariance":
        return DiagonalCovariance(self.variance.clone())

    def diagonal(self, offset: int = 0, dim1: int = -2, dim2: int = -1) -> torch.Tensor:
        """The variances (the matrix's diagonal)."""
        if offset != 0 or {dim1 % self.dim(), dim2 % self.dim()} != {self.dim() - 2, self.dim() - 1}:
            raise ArgumentError("DiagonalCovariance.diagonal: only the main diagonal of the last two dims")
        return self.variance

    # ---- its own ---------------------------------------------------------------------------------
    def dense(self) -> torch.Tensor:
        """The matrix ``(B, d, d)`` / ``(d, d)`` (``d^2`` numbers per trial)."""
        return torch.diag_embed(self.variance)

    def scale(self) -> torch.Tensor:
        """The standard deviations ``(B, d)`` / ``(d,)``: the diagonal Cholesky factor."""
        return self.variance.sqrt()

    def __repr__(self) -> str:
        return f"DiagonalCovariance(variance of shape {tuple(self.variance.shape)}, {self.variance.dtype})"


def dense_prior(cov) -> torch.Tensor:
    """``cov`` as a dense tensor: a :class:`DiagonalCovariance`'s matrix, any other value as it is."""
    return cov.dense() if isinstance(cov, DiagonalCovariance) else cov


def sample_prior(mean: torch.Tensor, cov, n: int, generator=None) -> torch.Tensor:
    """``n`` draws per trial from the prior ``N(mean (B, d), cov)``: ``(B, n, d)``. A dense ``cov
    (B, d, d)`` through its Cholesky factor (:func:`~torchflow.core.linalg.sample_mvn`), a
    :class:`DiagonalCovariance` as ``mean + sqrt(variance) xi``; the same standard normals ``xi``
    either way."""
    from torchflow.core import linalg

    if isinstance(cov, DiagonalCovariance):
        xi = linalg.standard_normal(
            (mean.shape[0], n, mean.shape[-1]), dtype=mean.dtype, device=mean.device, generator=generator
        )
        return torch.addcmul(mean.unsqueeze(1), cov.scale().unsqueeze(1), xi)
    return linalg.sample_mvn(mean, linalg.safe_cholesky(cov), (n,), generator)


def prior_bytes(model, element_bytes: int) -> int:
    """Bytes of one trial's prior covariance: ``b d`` where the model declares a diagonal prior
    (:attr:`~torchflow.models.Structure.prior_covariance`), else ``b d^2``."""
    d = model.state_dim
    return element_bytes * (d if model.structure.prior_covariance == "diagonal" else d * d)


__all__ = [
    "Covariance",
    "TrialCovariance",
    "ParticleCovariance",
    "DiagonalCovariance",
    "dense_prior",
    "prior_bytes",
    "sample_prior",
]
