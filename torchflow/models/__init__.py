"""State-space models: the core contract every filter consumes (:class:`StateSpaceModel`), the
Gaussian form (:class:`GaussianStateSpaceModel`), the declared :class:`Structure`, and the models
of the seed papers."""

from .acoustic import AcousticTracking
from .base import GaussianStateSpaceModel, StateSpaceModel, Trajectory
from .structure import Structure
from .linear_gaussian import LinearGaussian, SensorNetwork, sensor_network_covariance
from .lorenz63 import Lorenz63
from .lorenz96 import Lorenz96
from .neural_acoustic import InverseDistance, NeuralAcoustic, ResponseMLP
from .skewed_t import SkewedTPoisson
from .stochastic_volatility import StochasticVolatility
from .tdoa import TDOA3D, TDOAData

__all__ = [
    "StateSpaceModel",
    "GaussianStateSpaceModel",
    "Structure",
    "Trajectory",
    "LinearGaussian",
    "SensorNetwork",
    "sensor_network_covariance",
    "AcousticTracking",
    "NeuralAcoustic",
    "ResponseMLP",
    "InverseDistance",
    "SkewedTPoisson",
    "TDOA3D",
    "TDOAData",
    "Lorenz63",
    "Lorenz96",
    "StochasticVolatility",
]
