"""Parameter posteriors by particle MCMC, with chains batched in the trial dimension.

* :func:`pmmh`: particle marginal Metropolis-Hastings (Andrieu, Doucet & Holenstein 2010): C chains
  run as the C trials of one filter call per iteration, each trial with its own parameter values
  (the model declares which parameters may carry a leading trial dimension,
  :attr:`~torchflow.models.StateSpaceModel.per_trial_parameters`); any particle filter is the
  likelihood estimator; priors are ``torch.distributions`` over the constrained values; random-walk
  proposals in the unconstrained space, with a per-chain scale adapted towards a target acceptance
  rate during the first iterations and fixed afterwards.
* :func:`particle_gibbs`: conditional SMC with ancestor sampling (:func:`conditional_smc`) for the
  states and a Metropolis-within-Gibbs step for the parameters (the bootstrap proposal; the same
  per-trial parameters).
* :func:`rhat` and :func:`effective_sample_size`: convergence diagnostics of the chains.
* :func:`to_arviz`: the draws as an ArviZ ``InferenceData`` (the optional ``arviz`` extra).

May import: :mod:`torchflow.core`, :mod:`torchflow.models`, :mod:`torchflow.proposals`, :mod:`torchflow.smoothing`,
:mod:`torchflow.filters`.
"""

from torchflow.inference.convert import to_arviz
from torchflow.inference.diagnostics import effective_sample_size, rhat
from torchflow.inference.gibbs import conditional_smc, joint_log_density, particle_gibbs
from torchflow.inference.params import per_trial_values
from torchflow.inference.pmmh import PMMHResult, pmmh

__all__ = [
    "pmmh",
    "particle_gibbs",
    "conditional_smc",
    "joint_log_density",
    "PMMHResult",
    "per_trial_values",
    "rhat",
    "effective_sample_size",
    "to_arviz",
]
