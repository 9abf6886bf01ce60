"""torchflow: batched Bayesian filters and particle-flow particle filters in PyTorch."""
from . import filters, linalg, linearize, metrics, models, registry, resampling

__version__ = "0.1.0"
__all__ = ["filters", "linalg", "linearize", "metrics", "models", "registry", "resampling"]
