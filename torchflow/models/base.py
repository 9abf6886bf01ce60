"""The single model interface every filter consumes."""
from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Optional, Tuple

import torch
from torch import nn

from .. import linalg
from .._checks import check_count, check_finite, check_psd, check_tensor
from ..linearize import jacobian
from ..random import generator_hint


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


class StateSpaceModel(nn.Module):
    """Base class of state-space models ``x_k = g(x_{k-1}) + v_k``, ``z_k = h(x_k) + w_k``.

    The filter-side distributions (``transition_*``, ``measurement_*``) are what the filters use;
    :meth:`simulate` may use a different, "true" process (e.g. the acoustic model's filter noise
    is inflated relative to its true noise). Model functions take any leading batch shape
    ``(..., d)`` and broadcast. Parameters are buffers or ``nn.Parameter``s so they can be learned.

    Subclasses implement :meth:`transition_mean`, :meth:`transition_cov`, :meth:`measure`,
    :meth:`measurement_cov`, :meth:`initial_state` and :meth:`initial_belief` (a linear model may
    give :meth:`transition_matrix` / :meth:`measurement_matrix` instead of the mean and Jacobian);
    they may override :meth:`measurement_jacobian` with an analytic Jacobian.
    """

    state_dim: int
    obs_dim: int
    #: ``True`` when g is linear, ``g(x) = transition_matrix() @ x``: filters then skip Jacobians and
    #: share covariance recursions that cannot differ between particles.
    linear_dynamics: bool = False
    #: ``True`` when p(x_k | x_{k-1}) is the Gaussian ``N(transition_mean, transition_cov)``; a model
    #: with another transition (skewed-t) declares False, and its transition_mean/cov are the
    #: Gaussian fit that flows, trackers and stochastic-flow proposals use (MODELS.md §14e).
    gaussian_transition: bool = True
    #: ``True`` when h is linear, ``h(x) = measurement_matrix() @ x``.
    linear_measurement: bool = False
    #: structure of the measurement noise R, declared by the model and never detected at run time:
    #: ``"scalar"`` (``R = sigma^2 I``, constant), ``"diagonal"`` (constant), ``"dense"`` (constant)
    #: ``"state_dependent"`` (``measurement_cov(x)`` varies with x) or ``"state_dependent_diagonal"``
    #: (varies with x and is diagonal: flows whiten by a division instead of a triangular solve
    #: per point). Flows whiten with it.
    measurement_noise: str = "dense"
    #: ``True`` when the model's sampling and densities (:meth:`sample_transition`,
    #: :meth:`transition_log_prob`, :meth:`measurement_log_prob`) are pure functions of their
    #: tensors that draw only through the passed generator's ``normal``/``uniform``, with no host
    #: read and no Python-side state: a particle filter's whole step may then be replayed from a
    #: CUDA graph (:mod:`torchflow.flows.kernels.graph_step`). Declared by each class itself, not
    #: inherited (a subclass may change those methods); checked on a GPU for the linear-Gaussian
    #: models and acoustic tracking (``tests/test_graph_step.py``).
    graph_safe: bool = False
    #: ``True`` when each measurement reads only its own state coordinate (``m == d`` and
    #: ``dh_i/dx_j = 0`` for ``i != j``; declared, never detected): the flows then scale by the
    #: Jacobian's diagonal instead of multiplying by the ``d x d`` matrix (the same numbers).
    measurement_jacobian_diagonal: bool = False
    #: ``c`` when the (constant) transition matrix is exactly ``c I`` (declared; ``None`` otherwise)
    transition_matrix_scale: Optional[float] = None
    #: ``c`` when the (constant) measurement matrix is exactly ``c I`` (declared; ``None`` otherwise)
    measurement_matrix_scale: Optional[float] = None
    #: ``r`` when the (constant) measurement noise is exactly ``r I`` (declared; ``None`` otherwise)
    measurement_noise_scale: Optional[float] = None
    #: a named form of h that a flow kernel may linearise itself, ``(name, names of the model's
    #: tensors it reads)``: ``("inverse_distance_sum", ("sensors", "psi", "d0"))`` declares
    #: ``h_i(x) = psi sum_c 1 / (|p_c - s_i| + d0)`` over 2-D positions ``p_c`` (the support's
    #: coordinate pairs) and sensors ``s_i`` ``(m, 2)``, with a scalar R. Declared by each class
    #: itself, not inherited (a subclass may change the measurement); ``None``: no such form.
    measurement_form: Optional[tuple] = None

    # ---- dtype / device --------------------------------------------------------------------
    @property
    def dtype(self) -> torch.dtype:
        return self._reference_tensor().dtype

    @property
    def device(self) -> torch.device:
        return self._reference_tensor().device

    def _reference_tensor(self) -> torch.Tensor:
        for t in itertools.chain(self.parameters(), self.buffers()):
            return t
        raise RuntimeError(f"{type(self).__name__} has no parameters or buffers")

    # ---- dynamics ----------------------------------------------------------------------------
    def transition_mean(self, x: torch.Tensor) -> torch.Tensor:
        """Noise-free dynamics g(x, E[v]): ``(..., d) -> (..., d)`` (default: ``x F^T``, linear models)."""
        return x @ self.transition_matrix().transpose(-1, -2)

    def transition_cov(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        """Cov[x_k | x_{k-1}] used by filters: broadcastable ``(d, d)`` or ``(..., d, d)``."""
        raise NotImplementedError

    def check_covariances(self, who: str = "") -> None:
        """Raise unless the constant transition and measurement covariances (``transition_cov()``,
        ``measurement_cov()``; state-dependent ones are skipped) are symmetric positive
        semi-definite, naming the model, the covariance and, for a parameter of the model, its name.
        Filters call it once per call (a learnable covariance may leave the cone after an optimiser
        step; :mod:`torchflow.constraints` keeps one valid by construction)."""
        params = {id(p): n for n, p in self.named_parameters()}
        for what, fn in (("transition covariance", self.transition_cov), ("measurement covariance", self.measurement_cov)):
            try:
                C = fn()
            except (NotImplementedError, TypeError, RuntimeError, ValueError):
                continue  # state-dependent: no constant matrix to check
            if not isinstance(C, torch.Tensor) or C.dim() != 2:
                continue
            name = params.get(id(C))
            label = f"{type(self).__name__}'s {what}" + (f" (parameter {name!r})" if name else "")
            if C.requires_grad and not name:
                label += " (built from learnable parameters)"
            check_psd(f"{who + ': ' if who else ''}{label}", C.detach())

    def transition_scale_tril(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        """Lower Cholesky factor of :meth:`transition_cov`."""
        return linalg.safe_cholesky(self.transition_cov(x))

    def transition_jacobian(self, x: torch.Tensor) -> torch.Tensor:
        """d g / d x at ``x (..., d)`` -> ``(..., d, d)`` (the matrix of linear dynamics, else torch.func)."""
        if self.linear_dynamics:
            F = self.transition_matrix()
            return F.expand(*x.shape[:-1], *F.shape)
        return jacobian(self.transition_mean, x)

    def transition_matrix(self) -> torch.Tensor:
        """``(d, d)`` matrix of a linear transition (only when :attr:`linear_dynamics`)."""
        raise NotImplementedError(f"{type(self).__name__} has no constant transition matrix")

    def sample_transition(self, x: torch.Tensor, generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """Draw x_k ~ p(x_k | x_{k-1} = x) for ``x (..., d)`` (a Gaussian transition by default; a
        model with another noise law overrides this and keeps :meth:`sample_transition_gaussian`)."""
        return self.sample_transition_gaussian(x, generator)

    def sample_transition_gaussian(self, x: torch.Tensor, generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """Draw from the Gaussian fit ``N(transition_mean(x), transition_cov(x))`` (the transition
        itself when :attr:`gaussian_transition`)."""
        L = self.transition_scale_tril(x)
        xi = linalg.standard_normal(x.shape, dtype=x.dtype, device=x.device, generator=generator)
        return self.transition_mean(x) + linalg.matvec(L, xi)

    def transition_log_prob(self, x_next: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """log p(x_next | x) -> ``(...)``."""
        return linalg.mvn_log_prob(x_next, self.transition_mean(x), self.transition_scale_tril(x))

    # ---- measurement -------------------------------------------------------------------------
    def measure(self, x: torch.Tensor) -> torch.Tensor:
        """Noise-free measurement h(x, 0): ``(..., d) -> (..., m)`` (default: ``x H^T``, linear models)."""
        return x @ self.measurement_matrix().transpose(-1, -2)

    def measurement_cov(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        """R: broadcastable ``(m, m)`` or ``(..., m, m)``."""
        raise NotImplementedError

    def measurement_scale_tril(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        return linalg.safe_cholesky(self.measurement_cov(x))

    def measurement_jacobian(self, x: torch.Tensor) -> torch.Tensor:
        """dh/dx at ``x (..., d)`` -> ``(..., m, d)``; the matrix of a linear measurement, else torch.func
        (vmapped jacrev)."""
        if self.linear_measurement:
            H = self.measurement_matrix()
            return H.expand(*x.shape[:-1], *H.shape)
        return jacobian(self.measure, x)

    #: state coordinates the measurement depends on (``None``: all). A model whose h reads only
    #: some coordinates (positions, not velocities) declares them here; the flows then linearise
    #: in that k-dimensional subspace (``k x k`` systems instead of ``d x d``), exactly.
    measurement_support: Optional[Tuple[int, ...]] = None

    def measurement_jacobian_support(self, x: torch.Tensor) -> torch.Tensor:
        """dh/dx restricted to :attr:`measurement_support`: ``(..., m, k)`` (the other columns of
        the Jacobian are zero). Default: columns of :meth:`measurement_jacobian`."""
        J = self.measurement_jacobian(x)
        return J if self.measurement_support is None else J[..., list(self.measurement_support)]

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
        (:attr:`measurement_jacobian_diagonal`, a diagonal R): what the flows' diagonal paths read,
        without ``d x d`` matrices per point. Default: the diagonals of :meth:`linearize_measurement`
        and :meth:`measurement_scale_tril`; a model overrides it with the elementwise forms (the same
        numbers)."""
        h, H = self.linearize_measurement(x)
        return h, H.diagonal(dim1=-2, dim2=-1), self.measurement_scale_tril(x).diagonal(dim1=-2, dim2=-1)

    def measurement_hessian(self, x: torch.Tensor, support: bool = False, scale=None) -> torch.Tensor:
        """Second derivatives of h at ``x (..., d)``: ``(..., m, k, k)`` with entry ``[..., a, t, j]``
        ``= d^2 h_a / dx_t dx_j`` over the :attr:`measurement_support` coordinates (``support``; all
        d coordinates otherwise, k = d), multiplied by the scalar ``scale`` when given: the
        derivative of :meth:`linearize_measurement`'s Jacobian along each coordinate, which GPFIS's
        step Jacobian needs (:mod:`torchflow.flows.gpfis`). Default: forward-mode autodiff of that
        Jacobian (``torch.func.jvp``, the k directions batched with ``vmap``); a model with analytic
        second derivatives overrides it."""
        from torch.func import jvp, vmap

        idx = list(self.measurement_support) if support and self.measurement_support is not None else None
        index = None if idx is None else torch.tensor(idx, device=x.device)
        xs = x if index is None else x[..., index]
        k = xs.shape[-1]

        def jacobian(v):
            return self.linearize_measurement(v if index is None else x.index_copy(-1, index, v), support=support)[1]

        eye = torch.eye(k, dtype=x.dtype, device=x.device)
        tangents = eye.reshape(k, *([1] * (x.dim() - 1)), k).expand(k, *x.shape[:-1], k)
        dH = vmap(lambda t: jvp(jacobian, (xs,), (t,))[1], out_dims=-2)(tangents)
        return dH if scale is None else dH * scale

    def measurement_hessian_blocks(self, x: torch.Tensor, support: bool = False, scale=None) -> torch.Tensor:
        """:meth:`measurement_hessian` as its diagonal blocks, ``(..., m, n_b, b, b)``: the k coordinates
        fall in ``n_b`` consecutive groups of ``b`` (``k = n_b b``) and second derivatives across
        groups are zero (e.g. one group per target when each measurement is a sum over targets).
        Default: the dense Hessian as one block (``n_b = 1``); a model with that structure
        overrides it (GPFIS's step Jacobian then reads ``n_b`` times fewer numbers)."""
        return self.measurement_hessian(x, support, scale).unsqueeze(-3)

    def measurement_matrix(self) -> torch.Tensor:
        """``(m, d)`` matrix of a linear measurement (only when :attr:`linear_measurement`)."""
        raise NotImplementedError(f"{type(self).__name__} has no constant measurement matrix")

    def measurement_log_prob(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """log p(z | x) for ``z`` broadcastable to ``(..., m)`` -> ``(...)``."""
        return linalg.mvn_log_prob(z, self.measure(x), self.measurement_scale_tril(x))

    def sample_measurement(self, x: torch.Tensor, generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """Draw z ~ p(z | x) for ``x (..., d)`` -> ``(..., m)``."""
        mean = self.measure(x)
        L = self.measurement_scale_tril(x)
        xi = torch.randn(mean.shape, dtype=x.dtype, device=x.device, generator=generator)
        return mean + linalg.matvec(L, xi)

    # ---- truth and priors --------------------------------------------------------------------
    def true_transition_scale_tril(self) -> torch.Tensor:
        """Cholesky factor of the noise used by :meth:`simulate` (defaults to the filter's)."""
        return self.transition_scale_tril()

    def initial_state(self, batch_size: int, generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """True initial states x_0 -> ``(B, d)``."""
        raise NotImplementedError

    def initial_belief(self, states0: torch.Tensor, generator: Optional[torch.Generator] = None
                       ) -> Tuple[torch.Tensor, torch.Tensor]:
        """The filters' prior for each trial given the true ``states0 (B, d)``.

        Returns:
            mean ``(B, d)`` and covariance ``(B, d, d)``.
        """
        raise NotImplementedError

    def simulate(self, batch_size: int, steps: int, generator: Optional[torch.Generator] = None) -> Trajectory:
        """Simulate ``batch_size`` independent trajectories of ``steps`` steps.

        Returns:
            :class:`Trajectory` with states ``(B, T+1, d)`` and observations ``(B, T, m)``.
        """
        batch_size, steps = self.check_simulate_args(batch_size, steps, generator)
        with torch.no_grad():
            x = self.initial_state(batch_size, generator)
            states, obs = [x], []
            for _ in range(steps):
                x = self.sample_true_transition(x, generator)
                states.append(x)
                obs.append(self.sample_measurement(x, generator))
            return Trajectory(torch.stack(states, 1), torch.stack(obs, 1))

    def sample_true_transition(self, x: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """One step of :meth:`simulate`'s process: Gaussian with :meth:`true_transition_scale_tril` by default."""
        xi = torch.randn(x.shape, dtype=x.dtype, device=x.device, generator=generator)
        return self.transition_mean(x) + linalg.matvec(self.true_transition_scale_tril(), xi)

    def bytes_per_point(self) -> int:
        """Rough memory of evaluating the model at one point (intermediates of ``measure``,
        log-densities); filters multiply it by their particle count to size chunks of trials."""
        return 8 * 4 * (self.state_dim + self.obs_dim)

    # ---- tracking ------------------------------------------------------------------------------
    #: the state holds target positions (:meth:`positions`)
    has_positions: bool = False

    def positions(self, x: torch.Tensor) -> torch.Tensor:
        """Target positions ``(..., C, 2 or 3)`` of states ``(..., d)`` (tracking models only)."""
        raise NotImplementedError(f"{type(self).__name__} has no target positions")

    # ---- validation ----------------------------------------------------------------------------
    def check_dtype(self, who: str) -> None:
        """Raise unless the model is in float32 or float64 (the precisions filters support)."""
        if self.dtype not in (torch.float32, torch.float64):
            raise TypeError(f"{who}: the model is in {self.dtype}; filters and simulation run in float32 or "
                            "float64 (convert with model.double() or model.float())")

    def check_simulate_args(self, batch_size, steps, generator) -> Tuple[int, int]:
        """Validate :meth:`simulate`'s arguments; returns ``(batch_size, steps)`` as ints."""
        who = f"{type(self).__name__}.simulate"
        batch_size = check_count(f"{who}: batch_size", batch_size)
        steps = check_count(f"{who}: steps", steps)
        if not isinstance(generator, torch.Generator):
            raise TypeError(f"{who}: generator: expected a torch.Generator, got {type(generator).__name__}"
                            f"{generator_hint(generator)}")
        self.check_dtype(who)
        return batch_size, steps

    def check_observations(self, observations: torch.Tensor) -> torch.Tensor:
        """Raise a clear error unless ``observations`` is a finite ``(B, T, m)`` tensor on the
        model's dtype and device."""
        check_tensor("observations", observations, (None, None, self.obs_dim), "(B, T, m)",
                     dtype=self.dtype, device=self.device)
        if observations.shape[0] == 0 or observations.shape[1] == 0:
            raise ValueError(f"observations: expected (B, T, m) with at least one trial and one time step, "
                             f"got {tuple(observations.shape)}")
        check_finite("observations", observations)
        return observations
