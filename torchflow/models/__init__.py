"""State-space models: the core contract every filter consumes (:class:`StateSpaceModel`), the
Gaussian form (:class:`GaussianStateSpaceModel`), the declared :class:`Structure`, and the models
of the seed papers.

May import: :mod:`torchflow.core`.
"""

from torchflow.models.acoustic import AcousticTracking
from torchflow.models.base import GaussianStateSpaceModel, StateSpaceModel, Trajectory
from torchflow.models.linear_gaussian import LinearGaussian, SensorNetwork, sensor_network_covariance
from torchflow.models.lorenz63 import Lorenz63
from torchflow.models.lorenz96 import Lorenz96
from torchflow.models.neural_acoustic import InverseDistance, NeuralAcoustic, ResponseMLP
from torchflow.models.skewed_t import SkewedTPoisson
from torchflow.models.stochastic_volatility import StochasticVolatility
from torchflow.models.structure import Structure
from torchflow.models.tdoa import TDOA3D, TDOAData

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
