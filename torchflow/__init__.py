"""torchflow: batched Bayesian filters and particle-flow particle filters in PyTorch."""

from . import errors, filters, linalg, linearize, metrics, models, registry, resampling
from .errors import ArgumentError, ArgumentTypeError, NonFiniteError, TorchflowError

__version__ = "0.1.0"
__all__ = [
    "errors",
    "ArgumentError",
    "ArgumentTypeError",
    "NonFiniteError",
    "TorchflowError",
    "filters",
    "linalg",
    "linearize",
    "metrics",
    "models",
    "registry",
    "resampling",
]
