"""GPFIS as a proposal (Bunch & Godsill 2016; the transport is :func:`torchflow.flows.gpfis.gpfis_flow`):
the Gaussian transition moved by progressively linearised Gaussian flows, with the map's exact
autodiff ``log|det|`` in ``log q``, so the particle filter's evidence estimate is unbiased."""

from __future__ import annotations

from typing import Optional

from torchflow.core.blocks import blockwise
from torchflow.core.checks import check_choice
from torchflow.flows import FlowPrior, GaussianMeasurement
from torchflow.flows.gpfis import JACOBIANS, ROOTS, gpfis_flow
from torchflow.flows.schedules import LambdaSchedule, resolve_schedule
from torchflow.models.structure import bytes_per_point
from torchflow.proposals.base import Proposal, Proposed


class GPFISProposal(Proposal):
    """GPFIS as a proposal: the Gaussian transition moved by :func:`gpfis_flow`.

    Args:
        schedule: lambda grid (default: the exponential 29-step grid of the flows; the papers give
            no step-size control for GPFIS, Bunch & Godsill 2016).
        root: ``"cholesky"`` (default) or ``"symmetric"`` (:mod:`torchflow.flows.gpfis`).
        jacobian: each step's Jacobian ``"analytic"`` (default: written out, with the model's
            second derivatives) or ``"autodiff"`` (forward mode through the whole step); see
            :func:`~torchflow.flows.gpfis.gpfis_flow`.
    """

    def __init__(
        self, model, schedule: Optional[LambdaSchedule] = None, root: str = "cholesky", jacobian: str = "analytic"
    ):
        super().__init__(model)
        self.root = check_choice("root", root, ROOTS)
        self.jacobian = check_choice("jacobian", jacobian, JACOBIANS)
        self.schedule = resolve_schedule(schedule)

    def propose(self, particles, log_weights, estimate, z, carry, generator, *, chunk=None) -> Proposed:
        model = self.model
        x_prev = particles
        x0 = model.sample_transition(x_prev, generator)
        meas = GaussianMeasurement.from_model(model, z)

        def block(x0, x_prev):
            log_q0 = model.transition_log_prob(x0, x_prev)
            prior = FlowPrior(model.transition_mean(x_prev), model.transition_scale_tril(x_prev))
            x, log_det = gpfis_flow(meas, x0, prior, self.schedule, self.root, self.jacobian)
            return x, log_q0 - log_det

        x, log_q = blockwise(block, x0, x_prev, chunk=chunk)
        return Proposed(x, log_q, fallback=x0)

    def extra_repr(self) -> str:
        return f"root={self.root!r}, jacobian={self.jacobian!r}"

    def bytes_per_trial(self, n_particles):
        N = int(n_particles)
        d, m = self.model.state_dim, self.model.obs_dim
        k = d if self.model.structure.measurement_support is None else len(self.model.structure.measurement_support)
        # k tangent copies of the step's per-particle tensors (m x k Jacobians, k x k factors)
        per_point = (k + 1) * (3 * m * k + 6 * k * k + 4 * m + 8 * d) + 4 * d * d
        return 8 * N * per_point + N * bytes_per_point(self.model) * (k + 1)
