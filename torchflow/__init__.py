"""torchflow: batched Bayesian filters and particle-flow particle filters in PyTorch.

The package is built in floors; a module imports only from its own floor and the floors below
(``python -m torchflow.core.layers`` checks it, and CI runs that check):

1. :mod:`torchflow.core`: foundations (errors and argument checks, linear algebra, random numbers,
   weights and resampling, covariances, constraints, Gaussian trackers, metrics, tuning, registry);
2. :mod:`torchflow.models`: state-space models and their contract;
3. :mod:`torchflow.flows`: particle flows (their fused kernels in :mod:`torchflow.flows.kernels`);
4. :mod:`torchflow.proposals`: the particle filters' proposals;
5. :mod:`torchflow.filters`: the filters;
6. :mod:`torchflow.smoothing`, :mod:`torchflow.inference`, :mod:`torchflow.tdoa`,
   :mod:`torchflow.interop`: what is built on filters (smoothers, particle MCMC, multi-object
   localisers, adapters);
7. :mod:`torchflow.app`: the application (the commands, the Monte Carlo runner, recorded data,
   the learning command and its Lightning module).
"""

from torchflow import core, filters, models
from torchflow.core.errors import ArgumentError, ArgumentTypeError, NonFiniteError, TorchflowError

__version__ = "0.1.0"
__all__ = [
    "ArgumentError",
    "ArgumentTypeError",
    "NonFiniteError",
    "TorchflowError",
    "core",
    "filters",
    "models",
]
