"""Particle flows: modules that state the drift (and, for stochastic flows, the diffusion) of the
log-homotopy at linearisation points (:mod:`.points`); :func:`integrate_flow` steps any of them,
at any points, over a lambda schedule."""

from .base import FlowCoefficients, FlowOutput, FlowPrior, ParticleFlow
from .daum_huang import EDHFlow, LEDHFlow, daum_huang_coefficients
from .points import (
    POINTS,
    ClusteredPoints,
    GlobalPoints,
    LinearisationPoints,
    ParticlePoints,
    cluster_distance,
    kmedoids,
    resolve_points,
)
from .integrate import flow_gaussian, integrate_flow, which_kernel
from .measurement import GaussianMeasurement, Linearisation
from .geodesic import (
    GeodesicFlow,
    GromovFlow,
    OptimalDiffusionFlow,
    diffusion_condition_number,
    optimal_diffusion_scale,
    symmetric_sqrt,
)

__all__ = [
    "ParticleFlow",
    "FlowCoefficients",
    "FlowPrior",
    "FlowOutput",
    "integrate_flow",
    "flow_gaussian",
    "EDHFlow",
    "LEDHFlow",
    "daum_huang_coefficients",
    "which_kernel",
    "GeodesicFlow",
    "GromovFlow",
    "OptimalDiffusionFlow",
    "optimal_diffusion_scale",
    "diffusion_condition_number",
    "symmetric_sqrt",
    "cluster_distance",
    "kmedoids",
    "GaussianMeasurement",
    "Linearisation",
    "LinearisationPoints",
    "GlobalPoints",
    "ParticlePoints",
    "ClusteredPoints",
    "POINTS",
    "resolve_points",
]
