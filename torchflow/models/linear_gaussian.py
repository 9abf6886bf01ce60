"""Linear-Gaussian state-space model and the spatial sensor network of Li & Coates (2017) §V."""

from __future__ import annotations

import math
from typing import Optional, Tuple

import torch
from torch import nn

from torchflow.core import constraints, linalg
from torchflow.core.checks import (
    as_real_tensor,
    check_choice,
    check_learnable,
    check_nonnegative,
    check_number,
    check_positive,
    check_psd,
    check_tensor,
)
from torchflow.core.errors import ArgumentError
from torchflow.core.linalg import _LOG_2PI
from torchflow.models.base import GaussianStateSpaceModel
from torchflow.models.structure import Structure
from torchflow.models.trials import per_trial_structure, trial_factor, trial_names, trial_view


class LinearGaussian(GaussianStateSpaceModel):
    """``x_k = F x_{k-1} + v_k``, ``v ~ N(0, Q)``; ``z_k = H x_k + w_k``, ``w ~ N(0, R)``.

    The true initial state is drawn from ``N(m0, P0)`` and the filters' prior is the same
    ``N(m0, P0)``, so the Kalman filter is the exact posterior and its log-evidence is exact.
    ``P0`` may be singular (e.g. 0: a known initial state).

    Args:
        F: ``(d, d)`` transition matrix.
        Q: ``(d, d)`` process noise covariance (positive definite).
        H: ``(m, d)`` measurement matrix (m may differ from d).
        R: ``(m, m)`` measurement noise covariance (positive definite).
        m0: ``(d,)`` initial mean (default zeros).
        P0: ``(d, d)`` initial covariance (default zeros: x_0 = m0 known).
        learnable: ``True`` makes F, Q, H, R learnable (else buffers); a list such as ``["F", "H"]``
            makes only those learnable. F and H are plain ``nn.Parameter``s; a learnable Q or R
            stays positive definite by construction (:mod:`torchflow.core.constraints`): ``model.Q``
            is ``L L^T`` with ``L`` lower triangular with a positive diagonal (a diagonal R,
            ``measurement_noise="diagonal"``, is ``diag(exp(log-variances))``); the optimiser
            moves ``model.parametrizations.Q.original`` and ``model.Q`` is always the valid value.
        measurement_noise: the declared structure of R (``"scalar"``, ``"diagonal"``, ``"dense"``);
            ``None`` reads it from R once, here (``"dense"`` for a learnable R).

    The structure (R's, and whether F or H is a scaled identity) is fixed at construction: change
    F, H or R in place only through learning (learnable matrices are treated as general).

    Per trial (:func:`torchflow.inference.per_trial_values`): F, Q, H, R, m0 and P0 may each hold one
    value per trial, ``(B, d, d)``, ``(B, m, m)``, ``(B, d)`` and so on (a learnable Q or R through its
    constraint). While F (or H) is per trial the model declares no ``linear_dynamics``
    (``linear_measurement``): filters then read its Jacobian at each state, which is that trial's
    matrix, and the Kalman filter's Riccati recursion, shared by trials with one covariance, runs per
    trial.
    """

    #: one value per trial for any of the matrices and the prior (module :mod:`torchflow.models.trials`)
    per_trial_parameters = ("F", "Q", "H", "R", "m0", "P0")

    def __init__(self, F, Q, H, R, m0=None, P0=None, *, learnable=False, measurement_noise: Optional[str] = None):
        super().__init__()
        F, H, Q, R = (as_real_tensor(k, v) for k, v in (("F", F), ("H", H), ("Q", Q), ("R", R)))
        if F.dim() != 2 or F.shape[0] != F.shape[1] or not F.numel():
            raise ArgumentError(f"F: expected a square matrix (d, d) with d >= 1, got {tuple(F.shape)}")
        d = F.shape[0]
        if H.dim() != 2 or H.shape[1] != d or not H.numel():
            raise ArgumentError(f"H: expected (m, d) = (*, {d}) with m >= 1 and F's d, got {tuple(H.shape)}")
        m = H.shape[0]
        Q = check_tensor("Q", Q, (d, d), "(d, d) with F's d")
        R = check_tensor("R", R, (m, m), "(m, m) with H's m")
        check_psd("Q", Q)
        check_psd("R", R)
        m0 = torch.zeros(d, dtype=torch.float64) if m0 is None else as_real_tensor("m0", m0)
        P0 = torch.zeros(d, d, dtype=torch.float64) if P0 is None else as_real_tensor("P0", P0)
        check_tensor("m0", m0, (d,), "(d,) with F's d")
        check_tensor("P0", P0, (d, d), "(d, d) with F's d")
        check_psd("P0", P0)
        self.state_dim, self.obs_dim = d, m
        names = ("F", "Q", "H", "R")
        learn = check_learnable(learnable, names)
        diagonal = bool((R == torch.diag_embed(R.diagonal())).all())
        if measurement_noise is None:
            measurement_noise = (
                "dense" if "R" in learn or not diagonal else "scalar" if _identity_scale(R) is not None else "diagonal"
            )
        for name, val in zip(names, (F, Q, H, R)):
            if name in ("Q", "R") and name in learn:  # valid by construction (torchflow.core.constraints)
                if bool((torch.linalg.cholesky_ex(val)[1] > 0).any()):
                    raise ArgumentError(
                        f"{name}: a learnable covariance is parametrised by its Cholesky factor, "
                        f"so it must be positive definite; got a singular matrix"
                    )
                self.register_buffer(name, val.clone())
                kind = "diagonal" if name == "R" and measurement_noise == "diagonal" else "cholesky"
                constraints.constrain(self, name, kind)
            elif name in learn:
                setattr(self, name, nn.Parameter(val.clone()))
            else:
                self.register_buffer(name, val.clone())
        self.register_buffer("m0", m0.clone())
        self.register_buffer("P0", P0.clone())
        # a constant Q is factored once (a learnable one is its parametrisation's factor, no Cholesky)
        self.register_buffer("Q_tril", None if "Q" in learn else linalg.safe_cholesky(Q))
        # R's factor once, for the flows' whitening at every pseudo-time step (no per-call check)
        self.register_buffer("R_tril", None if "R" in learn else linalg.safe_cholesky(R))
        # structure declared once, here (filters never test the matrices at run time); a learnable
        # matrix is general, so that every entry receives its gradient. F, H, R are fixed after
        # construction unless learnable.
        check_choice("measurement_noise", measurement_noise, ("scalar", "diagonal", "dense"))
        self.structure = type(self).structure.replace(
            transition_matrix_scale=None if "F" in learn else _identity_scale(F),
            measurement_matrix_scale=None if "H" in learn else _identity_scale(H),
            measurement_noise_scale=None if "R" in learn else _identity_scale(R),
            measurement_noise=measurement_noise,
        )
        if measurement_noise == "scalar" and self.structure.measurement_noise_scale is None:
            raise ArgumentError("measurement_noise: declared 'scalar' but R is not a constant multiple of I")
        if measurement_noise == "diagonal" and not diagonal:
            raise ArgumentError("measurement_noise: declared 'diagonal' but R has off-diagonal entries")

    #: linear dynamics and measurement; R's structure and the identity scales per instance
    structure = Structure(linear_dynamics=True, linear_measurement=True, graph_safe=True)

    def _per_trial_structure(self, names):
        """F, H and R as they enter: a per-trial R is declared ``"diagonal"`` when every trial's is
        (read once, here), else ``"dense"``."""
        s = per_trial_structure(self, names, dynamics="F" in names, measurement="H" in names, noise="R" in names)
        if "R" in names:
            R = self.R.detach()
            diagonal = bool((R == torch.diag_embed(R.diagonal(dim1=-2, dim2=-1))).all())
            s = s.replace(measurement_noise="diagonal" if diagonal else "dense")
        return s

    # analytic, constant matrices (per trial: (B, ., .), viewed against the states where they are given)
    def transition_matrix(self) -> torch.Tensor:
        return self.F

    def measurement_matrix(self) -> torch.Tensor:
        return self.H

    def transition_jacobian(self, x):
        """F at every state ``x (..., d)``: ``(..., d, d)`` (its trial's, per trial)."""
        return trial_view(self.F, 2, x, 2).expand(*x.shape[:-1], *self.F.shape[-2:])

    def measurement_jacobian(self, x):
        """H at every state ``x (..., d)``: ``(..., m, d)`` (its trial's, per trial)."""
        return trial_view(self.H, 2, x, 2).expand(*x.shape[:-1], *self.H.shape[-2:])

    def transition_cov(self, x=None):
        return self.Q if x is None else trial_view(self.Q, 2, x, 2)

    def transition_scale_tril(self, x=None):
        L = self._factor("Q", self.Q_tril)
        return L if x is None else trial_view(L, 2, x, 2)

    def measurement_cov(self, x=None):
        return self.R if x is None else trial_view(self.R, 2, x, 2)

    def measurement_scale_tril(self, x=None):
        L = self._factor("R", self.R_tril)
        return L if x is None else trial_view(L, 2, x, 2)

    def _factor(self, name, kept):
        """The Cholesky factor of Q or R: the one kept from construction, the constraint's (no
        factorisation; per trial too), or, for per-trial values of a buffer, factored once per value."""
        if kept is not None and name not in trial_names(self):
            return kept
        L = constraints.scale_tril(self, name)
        return L if L is not None else trial_factor(self, name, getattr(self, name))

    def sample_transition(self, x, generator=None):
        """``x F^T + xi L_Q^T`` as two fused matrix products over all leading dims (a scaled
        identity F, e.g. the sensor network's ``0.9 I``, is a scaled addition instead). Per-trial F or
        Q: each trial's, ``F_b x + L_b xi`` (the same draws)."""
        d = self.state_dim
        flat = x.reshape(-1, d)
        xi = linalg.standard_normal(flat.shape, dtype=x.dtype, device=x.device, generator=generator)
        if {"F", "Q"} & set(trial_names(self)):
            return self.transition_mean(x) + linalg.matvec(self.transition_scale_tril(x), xi.reshape(x.shape))
        out = xi @ self.transition_scale_tril().T
        alpha = self.structure.transition_matrix_scale
        if alpha is not None:
            out.add_(flat, alpha=alpha)
        else:
            out.addmm_(flat, self.F.T)  # in place: no copy of the (B N, d) result
        return out.reshape(x.shape)

    def measurement_log_prob(self, z, x):
        """Whitened residual ``L_R^{-1} z - (L_R^{-1} H) x``: the triangular solve is applied to
        ``H`` and ``z`` once, not to every particle's residual. ``z (..., m)`` broadcasts with
        ``x (..., d)``. Per-trial H or R: the density with each trial's."""
        if {"H", "R"} & set(trial_names(self)):
            return linalg.mvn_log_prob(z, self.measure(x), self.measurement_scale_tril(x))
        h, r = self.structure.measurement_matrix_scale, self.structure.measurement_noise_scale
        if h is not None and r is not None and r > 0:  # z = h x + w, R = r I: elementwise residuals
            m = self.obs_dim
            quad = torch.linalg.vector_norm(x * h - z if h != 1.0 else x - z, dim=-1).square() / r
            return -0.5 * (quad + m * _LOG_2PI) - 0.5 * m * math.log(r)
        L = self.measurement_scale_tril()
        m, d = self.obs_dim, self.state_dim
        W = torch.linalg.solve_triangular(L, self.H, upper=False)  # (m, d)
        zs = z.reshape(-1, m)
        wz = torch.linalg.solve_triangular(L, zs.T, upper=False).T.reshape(z.shape)
        if x.dim() == 3 and wz.dim() == 3 and wz.shape[1] == 1:
            u = torch.baddbmm(wz, x, W.T.expand(x.shape[0], d, m), alpha=-1.0)  # (B, N, m)
        else:
            u = wz - x @ W.T
        quad = torch.linalg.vector_norm(u, dim=-1).square()
        return -0.5 * (quad + m * _LOG_2PI) - torch.log(L.diagonal()).sum()

    def initial_state(self, batch_size, generator=None):
        xi = torch.randn(batch_size, self.state_dim, dtype=self.dtype, device=self.device, generator=generator)
        if bool((self.P0 == 0).all()):
            return self.m0.expand(batch_size, -1).clone()
        return self.m0 + linalg.matvec(linalg.safe_cholesky(self.P0), xi)

    def initial_belief(self, states0, generator=None) -> Tuple[torch.Tensor, torch.Tensor]:
        return self.declared_prior(states0.shape[0])

    def declared_prior(self, batch_size: int) -> Tuple[torch.Tensor, torch.Tensor]:
        """``N(m0, P0)`` for every trial (per trial: each its own), ``(B, d)`` and ``(B, d, d)`` (no true
        state needed)."""
        return self.m0.expand(batch_size, -1).clone(), self.P0.expand(batch_size, -1, -1).clone()


def _identity_scale(M: torch.Tensor) -> Optional[float]:
    """``c`` if the square matrix ``M == c I`` exactly, else ``None`` (read once, at construction).
    Lets the samplers, likelihoods and the Kalman filter replace products by scalings for models
    such as the sensor network (F = 0.9 I, H = I, R = 0.25 I)."""
    if M.dim() != 2 or M.shape[0] != M.shape[1]:
        return None
    c = M[0, 0]
    return float(c) if bool((M == c * torch.eye(M.shape[0], dtype=M.dtype, device=M.device)).all()) else None


def sensor_grid(grid_size: int) -> torch.Tensor:
    """``(d, 2)`` positions of the sensors on a ``grid_size x grid_size`` grid with unit spacing,
    x fastest (index ``s = grid_size * iy + ix``)."""
    coords = torch.linspace(1.0, float(grid_size), grid_size, dtype=torch.float64)
    yy, xx = torch.meshgrid(coords, coords, indexing="ij")
    return torch.stack([xx.reshape(-1), yy.reshape(-1)], -1)


def sensor_network_covariance(
    grid_size: int, alpha0: float = 3.0, alpha1: float = 0.01, beta: float = 20.0
) -> torch.Tensor:
    """Process noise of the spatial sensor network: ``Sigma_ij = alpha0 exp(-|R_i - R_j|^2 / beta)
    + alpha1 delta_ij`` over a ``grid_size x grid_size`` grid with unit spacing (``d = grid_size^2``).

    Sensor order: x fastest (index ``s = grid_size * iy + ix``, :func:`sensor_grid`).
    """
    R = sensor_grid(grid_size)  # (d, 2)
    sq = (R[:, None, :] - R[None, :, :]).pow(2).sum(-1)
    d = grid_size * grid_size
    return alpha0 * torch.exp(-sq / beta) + alpha1 * torch.eye(d, dtype=torch.float64)


class SensorNetwork(LinearGaussian):
    """Linear-Gaussian spatial sensor network (Li & Coates 2017 §V).

    ``x_k = alpha x_{k-1} + v_k`` with ``v ~ N(0, Sigma)`` (:func:`sensor_network_covariance`),
    ``z_k = x_k + w_k`` with ``w ~ N(0, sigma_z^2 I)``, one sensor per grid cell, ``x_0 = 0`` known
    (``prior_var = 0``) unless ``prior_var > 0`` gives ``x_0 ~ N(0, prior_var I)``.

    Args:
        d: state dimension, a perfect square (default 64).
        alpha, alpha0, alpha1, beta: dynamics constants (0.9, 3, 0.01, 20).
        sigma_z: measurement noise standard deviation (0.5).
        prior_var: variance of the (true and assumed) initial state (0: known x_0 = 0).
        learnable: make F, Q, H, R ``nn.Parameter``s.
    """

    structure = LinearGaussian.structure  # declared again: graph-safe and kernel-ready as its parent

    def __init__(
        self,
        *,
        d: int = 64,
        alpha: float = 0.9,
        alpha0: float = 3.0,
        alpha1: float = 0.01,
        beta: float = 20.0,
        sigma_z: float = 0.5,
        prior_var: float = 0.0,
        learnable: bool = False,
    ):
        d = check_number(
            "d",
            d,
            lambda v: v >= 1 and round(math.sqrt(v)) ** 2 == v,
            "a perfect square >= 1 (grid side^2: 1, 4, 9, ..., 64)",
            integer=True,
        )
        g = int(round(math.sqrt(d)))
        check_number("alpha", alpha)
        check_nonnegative("alpha0", alpha0)
        check_nonnegative("alpha1", alpha1)  # alpha0 = alpha1 = 0: Q = 0 (singular, for filters that allow it)
        for name, value in (("beta", beta), ("sigma_z", sigma_z)):
            check_positive(name, value)
        check_number(
            "sigma_z",
            sigma_z,
            lambda v: float(v) * float(v) < math.inf,
            "a noise scale whose square is a finite float64 (the measurement covariance sigma_z^2 I)",
        )
        check_nonnegative("prior_var", prior_var)
        eye = torch.eye(d, dtype=torch.float64)
        super().__init__(
            F=alpha * eye,
            Q=sensor_network_covariance(g, alpha0, alpha1, beta),
            H=eye,
            R=sigma_z**2 * eye,
            m0=torch.zeros(d, dtype=torch.float64),
            P0=prior_var * eye,
            learnable=learnable,
        )

    def site_distances(self) -> torch.Tensor:
        """``(d, d)`` Euclidean distances between the sensors on their grid (unit spacing,
        :func:`sensor_grid`): the localising filters' geometry; sensor j observes coordinate j."""
        R = sensor_grid(int(round(math.sqrt(self.state_dim))))
        return (R[:, None, :] - R[None, :, :]).pow(2).sum(-1).sqrt()
