"""Particle flows: modules that state the drift (and, for stochastic flows, the diffusion) of the
log-homotopy; :func:`integrate_flow` steps any of them over a lambda schedule."""
from .base import FlowCoefficients, FlowOutput, FlowPrior, ParticleFlow, integrate_flow
from .daum_huang import EDHFlow, LEDHFlow, daum_huang_coefficients

__all__ = ["ParticleFlow", "FlowCoefficients", "FlowPrior", "FlowOutput", "integrate_flow", "EDHFlow",
           "LEDHFlow", "daum_huang_coefficients"]
