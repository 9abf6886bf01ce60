"""Filters: every filter is an ``nn.Module`` with the ``init`` / ``step`` / ``forward`` contract."""

from .base import Filter, FilterResult, GaussianState, ParticleFilter, ParticleFilterBase, ParticleState
from .bootstrap import BootstrapParticleFilter
from .pfpf import ClusteredParticleFlowParticleFilter, ParticleFlowFilter, ParticleFlowParticleFilter
from .gpfis import GPFIS, GaussianParticleFlowImportanceSampler
from .gaussian_sum import (
    GaussianParticleFilter,
    GaussianSumParticleFilter,
    MixtureState,
    ParticleFlowGaussianParticleFilter,
    ParticleFlowGaussianSumParticleFilter,
)
from .ensemble import EnsembleKalmanFilter, EnsembleTransformKalmanFilter, LocalEnsembleTransformKalmanFilter
from .assimilation import KernelParticleFlowFilter, LagOneFlowFilter, LocalParticleFilter
from .kalman import ExtendedKalmanFilter, KalmanFilter, UnscentedKalmanFilter, ekf_predict, kalman_update

__all__ = [
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
