"""Proposals of the particle filters, one file each; a proposal is fed tensors, never the filter.

* :class:`BootstrapProposal` (``bootstrap.py``): the transition.
* :class:`InvertibleFlowProposal`, :class:`StochasticFlowProposal` (``flow.py``): particle flows.
* :class:`GPFISProposal` (``gpfis.py``): Gaussian particle flow importance sampling.
* :class:`UnscentedProposal` (``unscented.py``): a per-particle UKF (the unscented PF) or EKF.
* :class:`FlowedMixtureProposal` (``mixture.py``): flow-induced Gaussian-mixture importance sampling.

The contract is in ``base.py`` (:class:`Proposal`, :class:`Proposed`).

May import: :mod:`torchflow.core`, :mod:`torchflow.models`, :mod:`torchflow.flows` (not its kernels).
"""

from torchflow.proposals.base import Proposal, Proposed
from torchflow.proposals.bootstrap import BootstrapProposal
from torchflow.proposals.flow import (
    FLOWS,
    FlowProposal,
    InvertibleFlowProposal,
    StochasticFlowProposal,
    flow_proposal,
    resolve_flow,
)
from torchflow.proposals.gpfis import GPFISProposal
from torchflow.proposals.mixture import FlowedMixtureProposal
from torchflow.proposals.unscented import UnscentedProposal

__all__ = [
    "Proposal",
    "Proposed",
    "BootstrapProposal",
    "FlowProposal",
    "InvertibleFlowProposal",
    "StochasticFlowProposal",
    "flow_proposal",
    "resolve_flow",
    "FLOWS",
    "GPFISProposal",
    "UnscentedProposal",
    "FlowedMixtureProposal",
]
