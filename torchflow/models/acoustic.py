"""Multi-target acoustic tracking (Li & Coates 2017 §V-A).

C = 4 targets move with nearly constant velocity in a 40 m x 40 m field; 25 acoustic sensors on a
5 x 5 grid measure the summed amplitude ``z_s = sum_c Psi / (|p_c - s_s| + d0) + w_s``.
State layout is target-major: ``x = [px1, py1, vx1, vy1, px2, ...]`` (d = 16, m = 25).
"""

from __future__ import annotations

import math
from typing import Optional, Sequence, Tuple

import torch
from torch.distributions import constraints as support

from torchflow.core import constraints, linalg
from torchflow.core.checks import as_real_tensor, check_choice, check_learnable, check_number, check_positive
from torchflow.core.errors import ArgumentError, ArgumentTypeError
from torchflow.core.linalg import block_diagonal
from torchflow.core.progress import report
from torchflow.models.base import GaussianStateSpaceModel, Trajectory
from torchflow.models.contract import check_simulate_args
from torchflow.models.structure import Structure
from torchflow.models.trials import per_trial_structure, trial_view

_X0 = [12, 6, 0.001, 0.001, 32, 32, -0.001, -0.005, 20, 13, -0.1, 0.01, 15, 35, 0.002, 0.002]


def _blockdiag(block: torch.Tensor, n: int) -> torch.Tensor:
    return torch.block_diag(*([block] * n))


class AcousticTracking(GaussianStateSpaceModel):
    """Multi-target acoustic tracking model.

    Args:
        sigma_w: measurement noise standard deviation (0.1; the paper's stiff variant uses 0.001).
        psi: source amplitude Psi (10).
        d0: distance offset d0 (0.1).
        true_noise_scale: true process noise ``V = blockdiag(scale * G)`` (0.05).
        filter_noise: ``"inflated"`` (Li & Coates' V_f, default) or ``"truth"`` (use the true V
            for the filters too, as Pal & Coates' code does; ``"true"``/``True`` are accepted, since
            YAML reads ``true`` as a boolean).
        area: side of the square field in metres (40).
        sensor_grid: sensors per side (5), placed on ``linspace(0, area, sensor_grid)``.
        prior_std: per-target prior standard deviations of [px, py, vx, vy] ([10, 10, 1, 1]).
        initial_state: true x_0 (16 numbers; default: Li & Coates' four targets).
        margin: trajectories are redrawn until every position stays in
            ``[margin, 1 - margin] * area`` (0.05).
        max_redraws: cap on rejection rounds before an error is raised.
        learnable: parameters to learn, a subset of ``["psi", "sigma_w"]`` (``True``: both). Each
            is positive by construction, stored as its logarithm (:class:`~torchflow.core.constraints.
            Positive`): ``model.psi`` is always the positive value, and the optimiser moves
            ``model.parametrizations.psi.original``.

    Per trial (:func:`torchflow.inference.per_trial_values`): ``psi`` and ``sigma_w`` may each hold one
    value per trial, ``(B,)`` (learnable ones through their constraint). While ``sigma_w`` is per trial
    R is declared ``"diagonal"`` (still ``sigma_w^2 I`` in each trial); while ``psi`` is, the flow
    kernels' named form of h stands aside.
    """

    n_targets = 4
    #: the measurement's amplitude and noise may hold one value per trial, ``(B,)``
    per_trial_parameters = {"psi": support.positive, "sigma_w": support.positive}
    #: linear dynamics, R = sigma_w^2 I, h reads the positions only (``(0, 1, 4, 5, ...)``, k = 2C
    #: of d = 4C), ``z_i = Psi sum_c 1 / (|p_c - s_i| + d0)`` in the flow kernels' named form
    structure = Structure(
        linear_dynamics=True,
        measurement_noise="scalar",
        has_positions=True,
        graph_safe=True,
        measurement_support=tuple(4 * c + i for c in range(4) for i in (0, 1)),
        measurement_form=("inverse_distance_sum", ("sensors", "psi", "d0")),
    )

    def __init__(
        self,
        *,
        sigma_w: float = 0.1,
        psi: float = 10.0,
        d0: float = 0.1,
        true_noise_scale: float = 0.05,
        filter_noise: str = "inflated",
        area: float = 40.0,
        sensor_grid: int = 5,
        prior_std: Sequence[float] = (10.0, 10.0, 1.0, 1.0),
        initial_state: Optional[Sequence[float]] = None,
        margin: float = 0.05,
        max_redraws: int = 10000,
        learnable=False,
    ):
        super().__init__()
        for name, value in (
            ("sigma_w", sigma_w),
            ("psi", psi),
            ("d0", d0),
            ("true_noise_scale", true_noise_scale),
            ("area", area),
        ):
            check_positive(name, value)
        f64_range = torch.finfo(torch.float64)
        if not f64_range.tiny <= float(sigma_w) * float(sigma_w) < math.inf:
            raise ArgumentError(
                f"sigma_w: expected a noise scale whose square is a normal float64 (in "
                f"[{f64_range.tiny**0.5:.3g}, {f64_range.max**0.5:.3g}]), got {sigma_w!r} (the "
                "measurement covariance sigma_w^2 I would underflow to a singular matrix or overflow)"
            )
        sensor_grid = check_number("sensor_grid", sensor_grid, lambda v: v >= 1, "an integer >= 1", integer=True)
        check_number("margin", margin, lambda v: 0 <= v < 0.5, "a fraction of the area in [0, 0.5)")
        check_number("max_redraws", max_redraws, lambda v: v >= 1, "an integer >= 1", integer=True)
        ps = as_real_tensor("prior_std", prior_std, finite=False)
        if ps.shape != (4,):
            raise ArgumentError(f"prior_std: expected 4 numbers [px, py, vx, vy], got {tuple(ps.shape)}")
        for i, s in enumerate(ps.tolist()):
            check_positive(f"prior_std[{i}]", s)
        if filter_noise is True or filter_noise == "true":
            filter_noise = "truth"
        check_choice("filter_noise", filter_noise, ("inflated", "truth"))
        C = self.n_targets
        self.state_dim, self.obs_dim = 4 * C, sensor_grid * sensor_grid
        self.structure = type(self).structure.replace(bytes_per_point=8 * 6 * C * self.obs_dim)
        f64 = dict(dtype=torch.float64)
        F1 = torch.tensor([[1, 0, 1, 0], [0, 1, 0, 1], [0, 0, 1, 0], [0, 0, 0, 1]], **f64)
        G = torch.tensor([[1 / 3, 0, 1 / 2, 0], [0, 1 / 3, 0, 1 / 2], [1 / 2, 0, 1, 0], [0, 1 / 2, 0, 1]], **f64)
        Vf1 = torch.tensor([[3, 0, 0.1, 0], [0, 3, 0, 0.1], [0.1, 0, 0.03, 0], [0, 0.1, 0, 0.03]], **f64)
        V = _blockdiag(true_noise_scale * G, C)
        self.register_buffer("F", _blockdiag(F1, C))
        self.register_buffer("V_true", V)
        self.register_buffer("V_filter", _blockdiag(Vf1, C) if filter_noise == "inflated" else V.clone())
        # the filters' noise is constant: factor it once (no factorisation, and no host
        # synchronisation, per filter step)
        self.register_buffer("V_filter_tril", linalg.safe_cholesky(self.V_filter))
        self.filter_noise = filter_noise
        ticks = torch.linspace(0.0, area, sensor_grid, **f64)
        sy, sx = torch.meshgrid(ticks, ticks, indexing="ij")
        self.register_buffer("sensors", torch.stack([sx.reshape(-1), sy.reshape(-1)], -1))  # (m, 2), x fastest
        for name, value in (("psi", psi), ("d0", d0), ("sigma_w", sigma_w)):
            self.register_buffer(name, torch.tensor(float(value), **f64))
        names = ("psi", "sigma_w")
        learn = check_learnable(learnable, names)
        for name in sorted(learn):
            constraints.constrain(self, name, "positive")
        x0 = torch.tensor(_X0, **f64) if initial_state is None else as_real_tensor("initial_state", initial_state)
        if x0.shape != (self.state_dim,):
            raise ArgumentError(f"initial_state: expected {self.state_dim} numbers, got {tuple(x0.shape)}")
        self.register_buffer("x0", x0)
        lo, hi = margin * area, (1 - margin) * area
        if not self._inside(x0.reshape(1, C, 4)[..., :2], lo, hi):  # simulate keeps every track inside
            raise ArgumentError(
                f"initial_state: expected target positions inside the field [margin, 1 - margin] * "
                f"area = [{lo:g}, {hi:g}]^2, got {x0.reshape(C, 4)[:, :2].tolist()}"
            )
        self.register_buffer("prior_std", ps.repeat(C))
        self.area, self.margin, self.max_redraws = float(area), float(margin), int(max_redraws)

    def _per_trial_structure(self, names):
        return per_trial_structure(self, names, dynamics=False, measurement=False, noise="sigma_w" in names)

    def _psi(self, x, event):
        """Psi (a scalar, or ``(B,)`` per trial) against states ``x (B, ..., d)``, ``event`` trailing dims."""
        return trial_view(self.psi, 0, x, event)

    def _sd(self, x, event):
        """sigma_w against ``x`` (``None``: per trial ``(B, 1.., 1)`` with ``event`` trailing dims)."""
        return trial_view(self.sigma_w, 0, x, event)

    # ---- dynamics --------------------------------------------------------------------------
    def transition_matrix(self):
        return self.F

    def transition_cov(self, x=None):
        return self.V_filter

    def transition_scale_tril(self, x=None):
        return self.V_filter_tril

    def true_transition_scale_tril(self):
        return linalg.safe_cholesky(self.V_true)

    # ---- measurement -----------------------------------------------------------------------
    def positions(self, x):
        """``(..., 16) -> (..., 4, 2)`` target positions."""
        return x.reshape(*x.shape[:-1], self.n_targets, 4)[..., :2]

    def measure(self, x):
        # per-coordinate differences (..., C, m): avoids the (..., C, m, 2) tensor, which for
        # 1e5 particles x 26 trials is 4 GB
        pos = self.positions(x)
        dx = pos[..., 0:1] - self.sensors[:, 0]
        dy = pos[..., 1:2] - self.sensors[:, 1]
        r = torch.sqrt(dx * dx + dy * dy)
        return (self._psi(x, 2) / (r + self.d0)).sum(-2)

    def measurement_cov(self, x=None):
        return self._sd(x, 2) ** 2 * torch.eye(self.obs_dim, dtype=self.sigma_w.dtype, device=self.sigma_w.device)

    def measurement_scale_tril(self, x=None):
        return self._sd(x, 2) * torch.eye(self.obs_dim, dtype=self.sigma_w.dtype, device=self.sigma_w.device)

    def measurement_log_prob(self, z, x):
        # diagonal R: avoid the generic triangular solve
        resid = (z - self.measure(x)) / self._sd(x, 1)
        m = self.obs_dim
        return -0.5 * resid.pow(2).sum(-1) - m * torch.log(self._sd(x, 0)) - 0.5 * m * linalg._LOG_2PI

    def _sensor_offsets(self, x):
        """Per-sensor offsets and ranges ``(..., m, C)`` (sensor-major, so the Jacobian needs no
        transpose)."""
        xv = x.reshape(*x.shape[:-1], 1, self.n_targets, 4)  # (..., 1, C, 4): fewer ops than positions()
        dx = xv[..., 0] - self.sensors[:, 0:1]  # (..., m, C)
        dy = xv[..., 1] - self.sensors[:, 1:2]
        return dx, dy, torch.sqrt(dx * dx + dy * dy)

    def _support_jacobian(self, dx, dy, r, inv, psi):
        # d/dp [Psi / (r + d0)] = -Psi (p - s) / (r (r + d0)^2); inv = 1 / (r + d0)
        coef = (-psi) * inv * inv / r.clamp_min(torch.finfo(r.dtype).tiny)
        return torch.stack([coef * dx, coef * dy], -1).flatten(-2)  # (..., m, 2C)

    def measurement_jacobian_support(self, x):
        """Position columns of the Jacobian, ``(..., 25, 8)`` in the order of
        :attr:`measurement_support`: dz_s/dpx_c = -Psi (px_c - s_x) / (r (r + d0)^2)."""
        dx, dy, r = self._sensor_offsets(x)
        return self._support_jacobian(dx, dy, r, 1 / (r + self.d0), self._psi(x, 2))

    def linearize_measurement(self, x, support=False, scale=None):
        if not support:
            return super().linearize_measurement(x, support, scale)
        dx, dy, r = self._sensor_offsets(x)
        inv = 1 / (r + self.d0)
        psi = self.psi if scale is None else self.psi * scale  # fold the scale into Psi: free
        return trial_view(psi, 0, x, 1) * inv.sum(-1), self._support_jacobian(dx, dy, r, inv, trial_view(psi, 0, x, 2))

    def measurement_hessian_blocks(self, x, support=False, scale=None):
        """Analytic second derivatives as one block per target, ``(..., m, C, b, b)`` (``b = 2``
        positions with ``support``, else ``b = 4`` with zero velocity rows): per sensor and target
        ``Psi [2 u u^T / (r + d0)^3 - (I - u u^T) / (r (r + d0)^2)]`` with ``u = (p - s) / r``; zero
        between targets (each measurement is a sum over targets)."""
        dx, dy, r = self._sensor_offsets(x)  # (..., m, C)
        inv = 1 / (r + self.d0)
        psi = trial_view(self.psi if scale is None else self.psi * scale, 0, x, 2)
        ir = 1 / r.clamp_min(torch.finfo(r.dtype).tiny)
        b = psi * inv * inv * ir  # (I - u u^T) coefficient
        c = (2 * psi * inv * inv * inv + b) * ir * ir  # u u^T = (p - s)(p - s)^T / r^2
        hxy = c * dx * dy
        block = torch.stack([c * dx * dx - b, hxy, hxy, c * dy * dy - b], -1).unflatten(-1, (2, 2))  # (..., m, C, 2, 2)
        if support:
            return block
        return torch.nn.functional.pad(block, (0, 2, 0, 2))  # velocities: zero rows and columns

    def measurement_hessian(self, x, support=False, scale=None):
        """Analytic second derivatives ``(..., m, k, k)`` (k = 8 positions with ``support``, else
        16): :meth:`measurement_hessian_blocks` placed on the diagonal."""
        return block_diagonal(self.measurement_hessian_blocks(x, support, scale))

    def measurement_jacobian(self, x):
        """Analytic Jacobian ``(..., 25, 16)``; zero for velocities."""
        J = torch.zeros(*x.shape[:-1], self.obs_dim, self.n_targets, 4, dtype=x.dtype, device=x.device)
        J[..., :2] = self.measurement_jacobian_support(x).reshape(*x.shape[:-1], self.obs_dim, self.n_targets, 2)
        return J.reshape(*x.shape[:-1], self.obs_dim, self.state_dim)

    # ---- truth and prior -------------------------------------------------------------------
    def _inside(self, pos: torch.Tensor, lo: float, hi: float) -> torch.Tensor:
        """All positions within [lo, hi]^2, reduced over every dim except the first."""
        ok = (pos >= lo) & (pos <= hi)
        return ok.reshape(pos.shape[0], -1).all(-1)

    def initial_state(self, batch_size, generator=None):
        return self.x0.expand(batch_size, -1).clone()

    def simulate(self, batch_size, steps, generator=None):
        """Simulate with the true noise V, conditioned on every target's position staying inside
        ``[margin, 1 - margin] * area`` at every step.

        Li & Coates redraw a whole trajectory until all four targets stay inside. Targets move
        independently and the condition is a product over targets, so redrawing each (trial,
        target) track separately samples exactly the same conditional distribution, far faster
        (a single target stays inside only a few per cent of the time). Rejection is batched over
        the tracks still invalid.
        """
        batch_size, steps = check_simulate_args(self, batch_size, steps, generator)
        C = self.n_targets
        with torch.no_grad():
            x0 = self.initial_state(batch_size).reshape(batch_size * C, 4)
            F1 = self.F[:4, :4]
            L1 = self.true_transition_scale_tril()[:4, :4]
            tracks = torch.empty(batch_size * C, steps + 1, 4, dtype=self.dtype, device=self.device)
            todo = torch.arange(batch_size * C, device=self.device)
            lo, hi = self.margin * self.area, (1 - self.margin) * self.area
            for _ in range(self.max_redraws):
                n = todo.numel()
                x = x0[todo]
                xi = torch.randn(n, steps, 4, dtype=self.dtype, device=self.device, generator=generator)
                traj = x.new_empty(n, steps + 1, 4)
                traj[:, 0] = x
                for k in range(steps):
                    x = x @ F1.transpose(-1, -2) + xi[:, k] @ L1.transpose(-1, -2)
                    traj[:, k + 1] = x
                    report(k + 1, steps)
                ok = self._inside(traj[..., :2], lo, hi)
                tracks[todo[ok]] = traj[ok]
                todo = todo[~ok]
                if todo.numel() == 0:
                    break
            else:
                raise ArgumentError(
                    f"AcousticTracking.simulate: {todo.numel()} target tracks still leave the field "
                    f"[{lo:g}, {hi:g}]^2 after max_redraws={self.max_redraws} redraws (fewer steps, a "
                    "larger area or a smaller margin keep them inside)"
                )
            # (B*C, T+1, 4) -> (B, T+1, C*4), target-major
            states = tracks.reshape(batch_size, C, steps + 1, 4).transpose(1, 2).reshape(batch_size, steps + 1, 4 * C)
            obs = self.sample_measurement(states[:, 1:], generator)
            return Trajectory(states, obs)

    def simulation_bytes(self, batch_size: int, steps: int) -> int:
        """Peak memory of :meth:`simulate`: about 13 times its output (measured), mostly the
        measurement's per-(target, sensor) distances over the whole trajectory, ``(B, T, 4, 25)``
        three times, and the rejection rounds' tracks and noise."""
        size = torch.empty((), dtype=self.dtype).element_size()
        per_step = 5 * self.state_dim + 5 * self.obs_dim + 4 * self.n_targets * self.obs_dim
        return size * batch_size * (steps + 1) * per_step

    def initial_belief(self, states0, generator=None) -> Tuple[torch.Tensor, torch.Tensor]:
        """Prior mean ``m_0 = x_0 + sigma_0 * xi``, redrawn until all four positions lie in the
        field; covariance ``diag(sigma_0^2)``. Returns ``(B, 16)``, ``(B, 16, 16)``."""
        if not isinstance(generator, torch.Generator):
            raise ArgumentTypeError(
                f"AcousticTracking.initial_belief: generator: expected a torch.Generator (the prior "
                f"mean is drawn), got {type(generator).__name__}"
            )
        B = states0.shape[0]
        mean = torch.empty_like(states0)
        todo = torch.arange(B, device=states0.device)
        for _ in range(self.max_redraws):
            xi = torch.randn(
                todo.numel(), self.state_dim, dtype=states0.dtype, device=states0.device, generator=generator
            )
            cand = states0[todo] + self.prior_std * xi
            ok = self._inside(self.positions(cand), 0.0, self.area)
            mean[todo[ok]] = cand[ok]
            todo = todo[~ok]
            if todo.numel() == 0:
                break
        cov = torch.diag_embed(self.prior_std**2).expand(B, -1, -1).clone()
        return mean, cov

    def declared_prior(self, batch_size: int) -> Tuple[torch.Tensor, torch.Tensor]:
        """The prior without true states (recorded data): ``N(x0, diag(prior_std^2))``, the law
        :meth:`initial_belief` draws its means from, centred on the declared initial state;
        ``(B, 16)``, ``(B, 16, 16)``."""
        cov = torch.diag_embed(self.prior_std**2).expand(batch_size, -1, -1).clone()
        return self.x0.expand(batch_size, -1).clone(), cov
