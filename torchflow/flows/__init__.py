"""Particle flows: modules that state the drift (and, for stochastic flows, the diffusion) of the
log-homotopy at linearisation points (:mod:`.points`); :func:`integrate_flow` steps any of them,
at any points, over a lambda schedule.

May import: :mod:`torchflow.core`, :mod:`torchflow.models`, :mod:`torchflow.flows.kernels`.

* :mod:`.base`, :mod:`.daum_huang`, :mod:`.geodesic`, :mod:`.gpfis`: the flows; :mod:`.ensemble`:
  the ensemble flows of data assimilation (lag-one, localised Kalman-Bucy, kernel), whose drift is
  stated at the members (``points="ensemble"``); :mod:`.points`:
  where they are linearised; :mod:`.measurement`: the Gaussian measurement they read;
  :mod:`.schedules`: pseudo-time schedules; :mod:`.integrate`: the reference integrator;
* :mod:`.select`: which fused kernel runs (the one place that decides); :mod:`.loops`: the
  pseudo-time loops that drive a chosen kernel.
"""

from torchflow.flows.base import FlowCoefficients, FlowOutput, FlowPrior, ParticleFlow
from torchflow.flows.daum_huang import EDHFlow, LEDHFlow, daum_huang_coefficients
from torchflow.flows.ensemble import (
    EnsembleFlow,
    EnsembleMeasurement,
    KernelFlow,
    LagOneFlow,
    LocalisedKalmanBucyFlow,
    WhitenedMembers,
    ensemble_prior,
    regression_jacobian,
)
from torchflow.flows.geodesic import (
    GeodesicFlow,
    GromovFlow,
    OptimalDiffusionFlow,
    diffusion_condition_number,
    optimal_diffusion_scale,
    symmetric_sqrt,
)
from torchflow.flows.integrate import flow_gaussian, integrate_flow, which_kernel
from torchflow.flows.measurement import GaussianMeasurement, Linearisation
from torchflow.flows.points import (
    POINTS,
    ClusteredPoints,
    GlobalPoints,
    LinearisationPoints,
    ParticlePoints,
    cluster_distance,
    kmedoids,
    resolve_points,
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
    "EnsembleFlow",
    "EnsembleMeasurement",
    "WhitenedMembers",
    "LagOneFlow",
    "LocalisedKalmanBucyFlow",
    "KernelFlow",
    "ensemble_prior",
    "regression_jacobian",
]
