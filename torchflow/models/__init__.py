"""State-space models: the interface every filter consumes, and the models of the seed papers."""
from .acoustic import AcousticTracking
from .base import StateSpaceModel, Trajectory
from .linear_gaussian import LinearGaussian, SensorNetwork, sensor_network_covariance
from .skewed_t import SkewedTPoisson
from .tdoa import TDOA3D, TDOAData

__all__ = ["StateSpaceModel", "Trajectory", "LinearGaussian", "SensorNetwork", "sensor_network_covariance",
           "AcousticTracking", "SkewedTPoisson", "TDOA3D", "TDOAData"]
