"""Particle flows: modules that state the drift (and, for stochastic flows, the diffusion) of the
log-homotopy; :func:`integrate_flow` steps any of them over a lambda schedule."""
from .base import FlowCoefficients, FlowOutput, FlowPrior, ParticleFlow, integrate_flow
from .daum_huang import EDHFlow, LEDHFlow, daum_huang_coefficients
from .points import cluster_distance, kmedoids
from .measurement import GaussianMeasurement, Linearisation
from .geodesic import (GeodesicFlow, GromovFlow, OptimalDiffusionFlow, diffusion_condition_number,
                       optimal_diffusion_scale, symmetric_sqrt)

__all__ = ["ParticleFlow", "FlowCoefficients", "FlowPrior", "FlowOutput", "integrate_flow", "EDHFlow",
           "LEDHFlow", "daum_huang_coefficients", "GeodesicFlow", "GromovFlow", "OptimalDiffusionFlow",
           "optimal_diffusion_scale", "diffusion_condition_number", "symmetric_sqrt", "cluster_distance", "kmedoids", "GaussianMeasurement", "Linearisation"]
