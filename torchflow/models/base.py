"""The model contract: a core that says what a state-space model is, and an optional Gaussian form.

* :class:`StateSpaceModel` (the core): the initial law, the transition and the measurement, each
  as a sampler and a log-density on ``(..., d)`` tensors. A model that gives only the core runs
  with the bootstrap particle filter (and the runner).
* :class:`GaussianStateSpaceModel` (the Gaussian form): ``x_k = g(x_{k-1}) + v_k``,
  ``v_k ~ N(0, Q(x_{k-1}))`` and ``z_k = h(x_k) + w_k``, ``w_k ~ N(0, R(x_k))``, given by the
  transition mean and covariance, h and R; the core follows from them. The Kalman family, the
  particle flows and the Gaussian proposals need it; Jacobians come from :mod:`torch.func` unless
  the model gives them.

What a model declares about itself (linearity, the structure of R, which coordinates h reads,
what a kernel may exploit) is one record, :class:`~torchflow.models.structure.Structure`. The
outputs of a model's methods are shape-checked once per model, on a filter's first call
(:func:`torchflow.models.contract.check_shapes`), with an error naming the method.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Optional, Tuple

import torch
from torch import nn

from torchflow.core import linalg, missing
from torchflow.core.checks import check_tensor
from torchflow.core.errors import ArgumentError, ArgumentTypeError
from torchflow.core.linearize import jacobian
from torchflow.core.progress import report
from torchflow.models.contract import GAUSSIAN_FORM, check_shapes, check_simulate_args, check_simulated
from torchflow.models.structure import Structure
from torchflow.models.trials import batch_jacobian, per_trial_structure, trial_names, trial_view


@dataclass
class Trajectory:
    """Simulated data.

    Attributes:
        states: ``(B, T+1, d)`` true states, index 0 is the initial state x_0.
        observations: ``(B, T, m)`` measurements z_1..z_T.
    """

    states: torch.Tensor
    observations: torch.Tensor

    def __getitem__(self, idx) -> "Trajectory":
        """Select trials, e.g. ``traj[0:10]``."""
        return Trajectory(self.states[idx], self.observations[idx])


def _missing(model, method: str, what: str):
    return NotImplementedError(
        f"{type(model).__name__}.{method}: not given; a model gives {what} (torchflow.models.StateSpaceModel's core)"
    )


class StateSpaceModel(nn.Module):
    r"""A state-space model: the core every filter reads.

    A model gives six methods, all on any leading batch shape:

    * the initial law: :meth:`initial_state` (true states ``x_0``) and :meth:`initial_belief` (the
      Gaussian prior ``(mean, cov)`` a filter starts from);
    * the transition: :meth:`sample_transition` and :meth:`transition_log_prob`;
    * the measurement: :meth:`sample_measurement` and :meth:`measurement_log_prob`;

    and states ``state_dim`` (d), ``obs_dim`` (m) and its :attr:`structure`. :meth:`simulate`
    follows from the core. Parameters are buffers or ``nn.Parameter``\ s (learnable).
    Randomness comes only through the ``generator`` passed in: draw with
    :func:`torchflow.core.linalg.standard_normal` (it also serves the runner's per-trial streams).

    Example (stochastic volatility, ``x_k = phi x_{k-1} + sigma v_k``, ``z_k | x_k ~ N(0, exp(x_k))``)::

        class StochasticVolatility(StateSpaceModel):
            state_dim = obs_dim = 1
            def __init__(self, phi=0.9, sigma=0.5):
                super().__init__()
                self.register_buffer("phi", torch.tensor(phi, dtype=torch.float64))
                self.register_buffer("sigma", torch.tensor(sigma, dtype=torch.float64))
            def stationary_var(self):
                return self.sigma ** 2 / (1 - self.phi ** 2)
            def initial_state(self, batch_size, generator=None):
                xi = standard_normal((batch_size, 1), dtype=self.dtype, device=self.device, generator=generator)
                return self.stationary_var().sqrt() * xi
            def initial_belief(self, states0, generator=None):
                B = states0.shape[0]
                return states0.new_zeros(B, 1), self.stationary_var().expand(B, 1, 1).clone()
            def sample_transition(self, x, generator=None):
                return self.phi * x + self.sigma * standard_normal(x.shape, dtype=x.dtype, device=x.device,
                                                                   generator=generator)
            def transition_log_prob(self, x_next, x):
                r, var = (x_next - self.phi * x).squeeze(-1), self.sigma ** 2
                return -0.5 * (torch.log(2 * torch.pi * var) + r * r / var)
            def sample_measurement(self, x, generator=None):
                return (x / 2).exp() * standard_normal(x.shape, dtype=x.dtype, device=x.device, generator=generator)
            def measurement_log_prob(self, z, x):
                z, x = z.squeeze(-1), x.squeeze(-1)  # variance exp(x)
                return -0.5 * (torch.log(torch.tensor(2 * torch.pi, dtype=x.dtype)) + x + z * z * (-x).exp())
    """

    #: the Gaussian form is given (:class:`GaussianStateSpaceModel` declares it): the shape checks of
    #: :mod:`torchflow.models.contract` read this declaration
    _gaussian: bool = False

    state_dim: int
    obs_dim: int
    #: the model's declared structure (:class:`~torchflow.models.structure.Structure`)
    structure: Structure = Structure()
    #: names of the parameters that may carry a leading trial dimension ``(B, ...)``: one value per
    #: trial (or MCMC chain, :func:`torchflow.inference.pmmh`), broadcast by the model's methods over
    #: any leading shape ``(B, ...)`` of their inputs. A dict also declares each one's domain, name ->
    #: a ``torch.distributions.constraints`` object (``positive``, ``interval(-1, 1)``, ...): a
    #: particle-MCMC prior must put no mass outside it (:func:`torchflow.models.trials.parameter_domain`)
    per_trial_parameters: tuple = ()

    # ---- dtype / device --------------------------------------------------------------------
    @property
    def dtype(self) -> torch.dtype:
        """The dtype of the model's first parameter or buffer."""
        return self._reference_tensor().dtype

    @property
    def device(self) -> torch.device:
        """The device of the model's first parameter or buffer."""
        return self._reference_tensor().device

    def _reference_tensor(self) -> torch.Tensor:
        for t in itertools.chain(self.parameters(), self.buffers()):
            return t
        raise RuntimeError(
            f"{type(self).__name__} has no parameters or buffers (register the model's numbers "
            "as buffers or nn.Parameters: they give its dtype and device)"
        )

    def _per_trial_structure(self, names) -> Structure:
        """The structure while the parameters ``names`` hold one value per trial
        (:func:`torchflow.inference.per_trial_values` declares it for the block): by default every
        shortcut that assumes one value for all trials stands aside
        (:func:`~torchflow.models.trials.per_trial_structure`); a model that knows which of its
        matrices a parameter enters says so."""
        return per_trial_structure(self, names)

    # ---- the core ----------------------------------------------------------------------------
    def initial_state(self, batch_size: int, generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """True initial states ``x_0 (B, d)``."""
        raise _missing(self, "initial_state", "initial_state(batch_size, generator) -> (B, d)")

    def initial_belief(
        self, states0: torch.Tensor, generator: Optional[torch.Generator] = None
    ) -> Tuple[torch.Tensor, torch.Tensor]:
        """The filters' prior for each trial given the true ``states0 (B, d)``: mean ``(B, d)`` and
        covariance ``(B, d, d)``."""
        raise _missing(self, "initial_belief", "initial_belief(states0, generator) -> ((B, d), (B, d, d))")

    def declared_prior(self, batch_size: int) -> Tuple[torch.Tensor, torch.Tensor]:
        """Optional: the filters' prior without true states (recorded data, learning on data): mean
        ``(B, d)`` and covariance ``(B, d, d)``, computed from the current parameters (differentiably,
        where they are learnable). The default raises: a model whose prior needs the truth (its
        :meth:`initial_belief` draws around it) runs recorded data only with a prior given
        explicitly (:func:`torchflow.app.data.declared_prior`)."""
        raise _missing(self, "declared_prior", "declared_prior(batch_size) -> ((B, d), (B, d, d))")

    def sample_transition(self, x: torch.Tensor, generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """Draw ``x_k ~ p(x_k | x_{k-1} = x)`` for ``x (..., d)`` -> ``(..., d)``."""
        raise _missing(self, "sample_transition", "sample_transition(x (..., d), generator) -> (..., d)")

    def transition_log_prob(self, x_next: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``log p(x_next | x)`` for ``x_next``, ``x`` broadcastable ``(..., d)`` -> ``(...)``."""
        raise _missing(self, "transition_log_prob", "transition_log_prob(x_next, x) -> (...)")

    def sample_measurement(self, x: torch.Tensor, generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """Draw ``z ~ p(z | x)`` for ``x (..., d)`` -> ``(..., m)``."""
        raise _missing(self, "sample_measurement", "sample_measurement(x (..., d), generator) -> (..., m)")

    def measurement_log_prob(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``log p(z | x)`` for ``z`` broadcastable to ``(..., m)`` and ``x (..., d)`` -> ``(...)``."""
        raise _missing(self, "measurement_log_prob", "measurement_log_prob(z, x) -> (...)")

    def measurement_log_prob_observed(self, z: torch.Tensor, x: torch.Tensor, observed: torch.Tensor) -> torch.Tensor:
        """``log p(z_o | x)``, the density of the observed coordinates of ``z`` alone (missing
        observations, :mod:`torchflow.core.missing`).

        Args:
            z: broadcastable to ``(..., m)``, finite (its unobserved coordinates hold a filler).
            x: ``(..., d)``.
            observed: ``(..., m)`` bool, broadcastable like ``z``: True where observed.

        Returns:
            ``(...)``. The default takes whole-step gaps only: :meth:`measurement_log_prob` where any
            coordinate is observed, 0 where none is. A model whose measurement coordinates can be
            missing one at a time overrides it (the Gaussian form does, exactly; a model with
            conditionally independent coordinates sums their densities over the observed ones);
            filters refuse a partly observed step for a model that does not
            (:func:`torchflow.models.base.partial_observations`).
        """
        ll = self.measurement_log_prob(z, x)
        return torch.where(observed.any(-1), ll, torch.zeros_like(ll))

    # ---- what follows from the core ---------------------------------------------------------
    def simulate(self, batch_size: int, steps: int, generator: Optional[torch.Generator] = None) -> Trajectory:
        """Simulate ``batch_size`` independent trajectories of ``steps`` steps.

        Returns:
            :class:`Trajectory` with states ``(B, T+1, d)`` and observations ``(B, T, m)``.
        """
        batch_size, steps = check_simulate_args(self, batch_size, steps, generator)
        with torch.no_grad():
            x = self.initial_state(batch_size, generator)
            who = f"{type(self).__name__}.simulate"
            if not isinstance(x, torch.Tensor) or tuple(x.shape) != (batch_size, self.state_dim):
                got = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
                raise ArgumentError(
                    f"{who}: initial_state returned {got}; expected (B, d) = ({batch_size}, {self.state_dim})"
                )
            check_shapes(self, x, who)  # every method's output shape, once per model and layout
            # written into the outputs step by step (a list of 2 T small tensors would cost more than the data)
            states, obs = x.new_empty((x.shape[0], steps + 1, *x.shape[1:])), None
            states[:, 0] = x
            for k in range(steps):
                x = self._simulation_transition(x, generator)
                z = self.sample_measurement(x, generator)
                if obs is None:
                    obs = z.new_empty((z.shape[0], steps, *z.shape[1:]))
                states[:, k + 1], obs[:, k] = x, z
                report(k + 1, steps)  # the runner's watcher: progress, stop requests
            traj = Trajectory(states, obs)
        check_simulated(who, traj, getattr(self, "simulation_hint", None))
        return traj

    def simulation_bytes(self, batch_size: int, steps: int) -> int:
        """Estimated peak memory of :meth:`simulate` (bytes on the model's device): by default its
        output, states ``(B, T+1, d)`` and observations ``(B, T, m)`` in the model's dtype. The
        runner refuses a run whose data cannot fit before simulating it; a model whose
        :meth:`simulate` needs more at its peak (temporaries of a whole trajectory) says so here."""
        size = torch.empty((), dtype=self.dtype).element_size()
        return size * batch_size * ((steps + 1) * self.state_dim + steps * (self.obs_dim or 0))

    def _simulation_transition(self, x: torch.Tensor, generator) -> torch.Tensor:
        """One step of :meth:`simulate`'s process (the filters' transition, unless a model's
        simulated truth differs from what its filters assume)."""
        return self.sample_transition(x, generator)

    def check_observations(self, observations: torch.Tensor) -> torch.Tensor:
        """Raise a clear error unless ``observations`` is a ``(B, T, m)`` tensor on the model's
        dtype and device whose values are finite or NaN (NaN: not observed, :mod:`torchflow.core.missing`;
        ``inf`` is an error)."""
        check_tensor(
            "observations", observations, (None, None, self.obs_dim), "(B, T, m)", dtype=self.dtype, device=self.device
        )
        if observations.shape[0] == 0 or observations.shape[1] == 0:
            raise ArgumentError(
                f"observations: expected (B, T, m) with at least one trial and one time step, "
                f"got {tuple(observations.shape)}"
            )
        inf = torch.isinf(observations)
        if bool(inf.any()):  # NaN marks a missing value; an infinity is an error
            trials = torch.nonzero(inf.flatten(1).any(-1)).flatten().tolist()
            raise ArgumentError(
                f"observations: {int(inf.sum())} infinite value(s), in trial(s) {trials[:10]} "
                "(NaN marks a value not observed; inf is not a measurement)"
            )
        return observations


def require_gaussian(model, who: str) -> None:
    """Raise unless ``model`` has the Gaussian form (a
    :class:`~torchflow.models.GaussianStateSpaceModel`), naming the filter ``who``."""
    if not isinstance(model, StateSpaceModel):
        raise ArgumentTypeError(
            f"{who}: model: expected a torchflow.models.StateSpaceModel, got {type(model).__name__}"
        )
    if not isinstance(model, GaussianStateSpaceModel):
        raise ArgumentTypeError(
            f"{who}: model: {type(model).__name__} gives only the core (samplers and densities); "
            f"{who} needs the Gaussian form ({', '.join(GAUSSIAN_FORM)}): subclass "
            "torchflow.models.GaussianStateSpaceModel, or use BootstrapParticleFilter"
        )


class GaussianStateSpaceModel(StateSpaceModel):
    """The Gaussian form of a state-space model: ``x_k = g(x_{k-1}) + v_k``, ``v_k ~ N(0, Q)`` and
    ``z_k = h(x_k) + w_k``, ``w_k ~ N(0, R)`` (Q and R may depend on the state).

    A model gives :meth:`transition_mean` (g), :meth:`transition_cov` (Q), :meth:`measure` (h),
    :meth:`measurement_cov` (R) and the initial law; a linear model may give
    :meth:`transition_matrix` / :meth:`measurement_matrix` (declaring ``structure.linear_dynamics``
    / ``linear_measurement``) instead of g and h. Jacobians come from :mod:`torch.func` unless the
    model overrides :meth:`measurement_jacobian` (or :meth:`linearize_measurement`) with analytic
    ones. The core's samplers and densities follow from the Gaussian form; a model with another
    law (skewed-t dynamics, Poisson counts) overrides them and declares
    ``structure.gaussian_transition = False``: its Gaussian form is then the approximation that
    moves particles (flows, trackers), while the core weighs them exactly.

    :meth:`simulate` draws the truth with :meth:`sample_true_transition`, whose noise factor
    :meth:`true_transition_scale_tril` may differ from the filters' (acoustic tracking).
    """

    _gaussian = True

    # ---- dynamics ----------------------------------------------------------------------------
    def transition_mean(self, x: torch.Tensor) -> torch.Tensor:
        """Noise-free dynamics g(x, E[v]): ``(..., d) -> (..., d)`` (default: ``x F^T``, linear models;
        a per-trial F ``(B, d, d)`` applies to its trial's states ``(B, ..., d)``)."""
        F = self.transition_matrix()
        return linalg.matvec(trial_view(F, 2, x, 2), x) if F.dim() > 2 else x @ F.transpose(-1, -2)

    def transition_cov(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        """Cov[x_k | x_{k-1}] used by filters: broadcastable ``(d, d)`` or ``(..., d, d)``."""
        raise NotImplementedError(f"{type(self).__name__}.transition_cov: not given (the Gaussian form needs Q)")

    def transition_scale_tril(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        """Lower Cholesky factor of :meth:`transition_cov`."""
        return linalg.safe_cholesky(self.transition_cov(x))

    def transition_jacobian(self, x: torch.Tensor) -> torch.Tensor:
        """d g / d x at ``x (..., d)`` -> ``(..., d, d)`` (the matrix of linear dynamics, else torch.func:
        on single points, or on the whole batch while parameters hold per-trial values)."""
        if self.structure.linear_dynamics:
            F = self.transition_matrix()
            return trial_view(F, 2, x, 2).expand(*x.shape[:-1], *F.shape[-2:])
        return batch_jacobian(self.transition_mean, x) if trial_names(self) else jacobian(self.transition_mean, x)

    def transition_mean_and_jacobian(self, x: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """``(g(x) (..., d), dg/dx (..., d, d))`` at ``x (..., d)``: what a linearisation of the
        measurement of the forecast, ``h(g(x))``, reads (the lag-one flows). Default:
        :meth:`transition_mean` and :meth:`transition_jacobian`; a model that computes both in one
        pass overrides it (Lorenz-63's compiled Runge-Kutta tangents)."""
        return self.transition_mean(x), self.transition_jacobian(x)

    def transition_matrix(self) -> torch.Tensor:
        """``(d, d)`` matrix of a linear transition (only when ``structure.linear_dynamics``)."""
        raise NotImplementedError(f"{type(self).__name__} has no constant transition matrix")

    def sample_transition(self, x: torch.Tensor, generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """Draw x_k ~ p(x_k | x_{k-1} = x) for ``x (..., d)`` (a Gaussian transition by default; a
        model with another noise law overrides this and keeps :meth:`sample_transition_gaussian`)."""
        return self.sample_transition_gaussian(x, generator)

    def sample_transition_gaussian(self, x: torch.Tensor, generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """Draw from the Gaussian fit ``N(transition_mean(x), transition_cov(x))`` (the transition
        itself when ``structure.gaussian_transition``)."""
        L = self.transition_scale_tril(x)
        xi = linalg.standard_normal(x.shape, dtype=x.dtype, device=x.device, generator=generator)
        return self.transition_mean(x) + linalg.matvec(L, xi)

    def transition_log_prob(self, x_next: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """log p(x_next | x) -> ``(...)``."""
        return linalg.mvn_log_prob(x_next, self.transition_mean(x), self.transition_scale_tril(x))

    # ---- measurement -------------------------------------------------------------------------
    def measure(self, x: torch.Tensor) -> torch.Tensor:
        """Noise-free measurement h(x, 0): ``(..., d) -> (..., m)`` (default: ``x H^T``, linear models;
        a per-trial H ``(B, m, d)`` applies to its trial's states ``(B, ..., d)``)."""
        H = self.measurement_matrix()
        return linalg.matvec(trial_view(H, 2, x, 2), x) if H.dim() > 2 else x @ H.transpose(-1, -2)

    def measurement_cov(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        """R: broadcastable ``(m, m)`` or ``(..., m, m)``."""
        raise NotImplementedError(f"{type(self).__name__}.measurement_cov: not given (the Gaussian form needs R)")

    def measurement_scale_tril(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        return linalg.safe_cholesky(self.measurement_cov(x))

    def measurement_variance(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        """R's diagonal, broadcastable to ``(..., m)``, for a model that declares a diagonal R
        (``structure.measurement_noise`` ``"scalar"``, ``"diagonal"`` or
        ``"state_dependent_diagonal"``): what the elementwise densities of partly observed steps and
        the ensemble filters' whitening read. Default: :meth:`measurement_cov`'s diagonal; a model
        with many observations overrides it so that no ``(m, m)`` matrix is formed (Lorenz-96)."""
        return self.measurement_cov(x).diagonal(dim1=-2, dim2=-1)

    def measurement_jacobian(self, x: torch.Tensor) -> torch.Tensor:
        """dh/dx at ``x (..., d)`` -> ``(..., m, d)``; the matrix of a linear measurement, else torch.func
        (vmapped jacrev)."""
        if self.structure.linear_measurement:
            H = self.measurement_matrix()
            return trial_view(H, 2, x, 2).expand(*x.shape[:-1], *H.shape[-2:])
        return batch_jacobian(self.measure, x) if trial_names(self) else jacobian(self.measure, x)

    def measurement_jacobian_support(self, x: torch.Tensor) -> torch.Tensor:
        """dh/dx restricted to :attr:`Structure.measurement_support`: ``(..., m, k)`` (the other columns of
        the Jacobian are zero). Default: columns of :meth:`measurement_jacobian`."""
        J = self.measurement_jacobian(x)
        return J if self.structure.measurement_support is None else J[..., list(self.structure.measurement_support)]

    def linearize_measurement(self, x: torch.Tensor, support: bool = False, scale=None):
        """``(h(x) (..., m), dh/dx (..., m, d))`` at ``x (..., d)``; with ``support`` the Jacobian
        is :meth:`measurement_jacobian_support`'s ``(..., m, k)``; with a scalar ``scale`` both are
        multiplied by it (the flows whiten by ``1 / sigma`` when ``R = sigma^2 I``). Models with an
        analytic Jacobian override this to share work between the two (the flows call it every
        pseudo-time step)."""
        H = self.measurement_jacobian_support(x) if support else self.measurement_jacobian(x)
        h = self.measure(x)
        return (h, H) if scale is None else (h * scale, H * scale)

    def linearize_measurement_diagonal(self, x: torch.Tensor):
        """``(h(x) (..., m), the Jacobian's diagonal (..., m), R's factor's diagonal (..., m))`` at
        ``x (..., d)`` for a model whose Jacobian and R are diagonal by declaration
        (``structure.measurement_jacobian_diagonal``, a diagonal R): what the flows' diagonal paths read,
        without ``d x d`` matrices per point. Default: the diagonals of :meth:`linearize_measurement`
        and :meth:`measurement_scale_tril`; a model overrides it with the elementwise forms (the same
        numbers)."""
        h, H = self.linearize_measurement(x)
        return h, H.diagonal(dim1=-2, dim2=-1), self.measurement_scale_tril(x).diagonal(dim1=-2, dim2=-1)

    def measurement_hessian(self, x: torch.Tensor, support: bool = False, scale=None) -> torch.Tensor:
        """Second derivatives of h at ``x (..., d)``: ``(..., m, k, k)`` with entry ``[..., a, t, j]``
        ``= d^2 h_a / dx_t dx_j`` over the :attr:`Structure.measurement_support` coordinates (``support``; all
        d coordinates otherwise, k = d), multiplied by the scalar ``scale`` when given: the
        derivative of :meth:`linearize_measurement`'s Jacobian along each coordinate, which GPFIS's
        step Jacobian needs (:mod:`torchflow.flows.gpfis`). Default: forward-mode autodiff of that
        Jacobian (``torch.func.jvp``, the k directions batched with ``vmap``); a model with analytic
        second derivatives overrides it."""
        from torch.func import jvp, vmap

        idx = (
            list(self.structure.measurement_support)
            if support and self.structure.measurement_support is not None
            else None
        )
        index = None if idx is None else torch.tensor(idx, device=x.device)
        xs = x if index is None else x[..., index]
        k = xs.shape[-1]

        def jacobian(v):
            return self.linearize_measurement(v if index is None else x.index_copy(-1, index, v), support=support)[1]

        eye = torch.eye(k, dtype=x.dtype, device=x.device)
        tangents = eye.reshape(k, *([1] * (x.dim() - 1)), k).expand(k, *x.shape[:-1], k)
        # out_dims=0 and a move, not out_dims=-2: torch 2.13 crashes (segmentation fault) on a negative
        # out_dims over jvp of the default Jacobian's vmap(jacrev)
        dH = vmap(lambda t: jvp(jacobian, (xs,), (t,))[1])(tangents).movedim(0, -2)
        return dH if scale is None else dH * scale

    def measurement_hessian_blocks(self, x: torch.Tensor, support: bool = False, scale=None) -> torch.Tensor:
        """:meth:`measurement_hessian` as its diagonal blocks, ``(..., m, n_b, b, b)``: the k coordinates
        fall in ``n_b`` consecutive groups of ``b`` (``k = n_b b``) and second derivatives across
        groups are zero (e.g. one group per target when each measurement is a sum over targets).
        Default: the dense Hessian as one block (``n_b = 1``); a model with that structure
        overrides it (GPFIS's step Jacobian then reads ``n_b`` times fewer numbers)."""
        return self.measurement_hessian(x, support, scale).unsqueeze(-3)

    def measurement_matrix(self) -> torch.Tensor:
        """``(m, d)`` matrix of a linear measurement (only when ``structure.linear_measurement``)."""
        raise NotImplementedError(f"{type(self).__name__} has no constant measurement matrix")

    def measurement_log_prob(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """log p(z | x) for ``z`` broadcastable to ``(..., m)`` -> ``(...)``."""
        return linalg.mvn_log_prob(z, self.measure(x), self.measurement_scale_tril(x))

    def measurement_log_prob_terms(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``log p(z_j | x)`` per observation ``(..., m)``, for a measurement whose coordinates are
        independent given the state (what local particle filters weigh with): here the Gaussian form
        with a diagonal R (declared ``scalar``, ``diagonal`` or ``state_dependent_diagonal``). A NaN
        in ``z`` (not observed) gives the term 0. ``z`` broadcastable to ``(..., m)``, ``x (..., d)``."""
        noise = self.structure.measurement_noise
        if noise not in ("scalar", "diagonal", "state_dependent_diagonal"):
            raise ArgumentTypeError(
                f"{type(self).__name__}.measurement_log_prob_terms: the observations' densities one by one need a "
                f"diagonal measurement noise (declared scalar, diagonal or state_dependent_diagonal); this model "
                f"declares {noise!r}. Override measurement_log_prob_terms for another independent measurement law"
            )
        h = self.measure(x)
        r = self.measurement_variance(x if noise.startswith("state_dependent") else None)
        if r.dim() > 1 and not noise.startswith("state_dependent"):  # per-trial (B, m): one row per trial
            r = trial_view(r, 1, h)
        resid = z - h
        terms = -0.5 * (resid * resid / r + torch.log(r * (2.0 * math.pi)))
        return torch.where(torch.isnan(z), torch.zeros_like(terms), terms)

    def measurement_log_prob_observed(self, z: torch.Tensor, x: torch.Tensor, observed: torch.Tensor) -> torch.Tensor:
        """The density of the observed coordinates (:meth:`StateSpaceModel.measurement_log_prob_observed`):
        for a Gaussian measurement (``structure.gaussian_measurement``), exactly
        ``log N(z_o; h_o(x), R_oo)``: elementwise for a declared diagonal R, else through R with its
        unobserved rows and columns replaced by the identity's (:func:`torchflow.core.missing.masked_noise`).
        Other measurement laws take whole-step gaps only, unless the model overrides this."""
        if not self.structure.gaussian_measurement:
            return super().measurement_log_prob_observed(z, x, observed)
        h = self.measure(x)
        shape = torch.broadcast_shapes(h.shape, z.shape, observed.shape)
        full = observed.expand(shape)
        resid = torch.where(full, z - h, torch.zeros_like(h))
        if self.structure.measurement_noise in ("scalar", "diagonal", "state_dependent_diagonal"):
            var = self.measurement_variance(x).expand(shape)
            terms = resid * resid / var + torch.log(var) + linalg._LOG_2PI
            return -0.5 * torch.where(full, terms, torch.zeros_like(terms)).sum(-1)
        # per trial (the mask's own batch shape), not per particle, where R is constant
        R = missing.masked_noise(self.measurement_cov(x), observed)
        return linalg.mvn_log_prob(
            resid, torch.zeros_like(resid), linalg.safe_cholesky(R)
        ) + missing.unobserved_correction(full, dtype=h.dtype)

    def sample_measurement(self, x: torch.Tensor, generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """Draw z ~ p(z | x) for ``x (..., d)`` -> ``(..., m)``."""
        mean = self.measure(x)
        L = self.measurement_scale_tril(x)
        xi = torch.randn(mean.shape, dtype=x.dtype, device=x.device, generator=generator)
        return mean + linalg.matvec(L, xi)

    # ---- the simulated truth -------------------------------------------------------------------
    def true_transition_scale_tril(self) -> torch.Tensor:
        """Cholesky factor of the noise used by :meth:`simulate` (defaults to the filter's)."""
        return self.transition_scale_tril()

    def sample_true_transition(self, x: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """One step of :meth:`simulate`'s process: Gaussian with :meth:`true_transition_scale_tril` by default."""
        xi = torch.randn(x.shape, dtype=x.dtype, device=x.device, generator=generator)
        return self.transition_mean(x) + linalg.matvec(self.true_transition_scale_tril(), xi)

    def _simulation_transition(self, x: torch.Tensor, generator) -> torch.Tensor:
        return self.sample_true_transition(x, generator)


def partial_observations(model) -> bool:
    """Whether ``model`` weighs a measurement with some of its coordinates missing, as its class
    declares by what it gives: a ``measurement_log_prob_observed`` of its own, or the Gaussian
    form's with ``structure.gaussian_measurement`` (a one-coordinate measurement: always, a gap is
    then a whole step). Particle filters refuse a partly observed step otherwise."""
    own = type(model).measurement_log_prob_observed
    if own is StateSpaceModel.measurement_log_prob_observed:
        return model.obs_dim == 1
    if own is GaussianStateSpaceModel.measurement_log_prob_observed:
        return model.obs_dim == 1 or model.structure.gaussian_measurement
    return True
