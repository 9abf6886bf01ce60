"""Filters: every filter is an ``nn.Module`` with the ``init`` / ``step`` / ``forward`` contract.

May import: :mod:`torchflow.core`, :mod:`torchflow.models`, :mod:`torchflow.flows` (its kernels
only through :mod:`torchflow.flows.select`), :mod:`torchflow.proposals`.

* :mod:`.base`: the contract (:class:`Filter`) and the particle filter of every proposal
  (:class:`ParticleFilter`); :mod:`.guards`: non-finite values; :mod:`.marginal`: the marginal
  weights; :mod:`.graph_step`: a particle filter's whole step replayed from a CUDA graph;
* :mod:`.kalman` (KF, EKF, UKF), :mod:`.bootstrap`, :mod:`.pfpf` (PF-PF, clustered PF-PF),
  :mod:`.gpfis`, :mod:`.gaussian_sum` (Gaussian and Gaussian-sum PFs), :mod:`.ensemble`
  (ensemble Kalman filters), :mod:`.assimilation` (localised and lag-one flow filters for data
  assimilation), :mod:`.weighted_flow` (the weighted lag-one flow: a PF-PF on deterministic dynamics).
"""

from torchflow.filters.assimilation import KernelParticleFlowFilter, LagOneFlowFilter, LocalParticleFilter
from torchflow.filters.base import (
    Estimator,
    Filter,
    FilterResult,
    GaussianState,
    ParticleFilter,
    ParticleFilterBase,
    ParticleState,
)
from torchflow.filters.bootstrap import BootstrapParticleFilter
from torchflow.filters.ensemble import (
    EnsembleKalmanFilter,
    EnsembleTransformKalmanFilter,
    LocalEnsembleTransformKalmanFilter,
)
from torchflow.filters.gaussian_sum import (
    GaussianParticleFilter,
    GaussianSumParticleFilter,
    MixtureState,
    ParticleFlowGaussianParticleFilter,
    ParticleFlowGaussianSumParticleFilter,
)
from torchflow.filters.gpfis import GPFIS, GaussianParticleFlowImportanceSampler
from torchflow.filters.kalman import (
    ExtendedKalmanFilter,
    KalmanFilter,
    UnscentedKalmanFilter,
    ekf_predict,
    kalman_update,
)
from torchflow.filters.local_weighted_flow import LocalLagOneFlowParticleFilter
from torchflow.filters.pfpf import ClusteredParticleFlowParticleFilter, ParticleFlowFilter, ParticleFlowParticleFilter
from torchflow.filters.weighted_flow import LagOneFlowParticleFilter

__all__ = [
    "Estimator",
    "Filter",
    "FilterResult",
    "GaussianState",
    "ParticleState",
    "ParticleFilter",
    "ParticleFilterBase",
    "KalmanFilter",
    "ExtendedKalmanFilter",
    "UnscentedKalmanFilter",
    "EnsembleKalmanFilter",
    "EnsembleTransformKalmanFilter",
    "LocalEnsembleTransformKalmanFilter",
    "KernelParticleFlowFilter",
    "LagOneFlowFilter",
    "LagOneFlowParticleFilter",
    "LocalLagOneFlowParticleFilter",
    "LocalParticleFilter",
    "BootstrapParticleFilter",
    "ParticleFlowParticleFilter",
    "ClusteredParticleFlowParticleFilter",
    "ParticleFlowFilter",
    "GaussianParticleFlowImportanceSampler",
    "GPFIS",
    "GaussianParticleFilter",
    "GaussianSumParticleFilter",
    "ParticleFlowGaussianParticleFilter",
    "ParticleFlowGaussianSumParticleFilter",
    "MixtureState",
    "kalman_update",
    "ekf_predict",
]
