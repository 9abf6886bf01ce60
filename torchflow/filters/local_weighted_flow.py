"""The localised weighted lag-one flow: the localised lag-one flow as the proposal, local weights for
what its Gaussian linearisation leaves out, and a local transport of the weighted members.

The localised lag-one flow (:class:`~torchflow.filters.LagOneFlowFilter` with a finite ``radius``)
moves the previous analysis members towards ``p(x_{k-1} | z_{1:k})`` as if every observation were
Gaussian and linear in the state: its drift reads the members' cross-covariance of state and
measurement, the ensemble's statistical linearisation. Where the measurement is not linear (``|x|``,
whose sign is lost) or its errors not Gaussian (Student-t), the flowed members are not distributed as
the target. This filter weighs them for that, locally:

1. **Flow** the members (the localised flow of :class:`~torchflow.filters.LagOneFlowFilter`) and
   carry them to time k by the model, ``x_i = M(x_{k-1,i})`` (with its noise, if it has any).
2. **Linearise each observation locally**: the least-squares regression of the members' whitened
   measurements ``y_ij`` on their state coordinates within :attr:`linear_radius` of observation ``j``
   (the regression is exact for a measurement linear in those coordinates), giving ``ytilde_ij``.
3. **Weigh**: observation ``j``'s log-ratio of the model's own density to the Gaussian of that
   linearisation, ``r_ij = log p(z_j | x_i) - log N(z_j; ytilde_ij, R_jj)``; coordinate ``a``'s
   log-weight of member ``i`` is ``sum_j rho(a, j) r_ij`` (``rho``: the Gaspari-Cohn taper of radius
   :attr:`weight_radius`, as the local particle filter of Penny & Miyoshi 2016 weighs). If the flow
   carried a Gaussian prior exactly to the linearised target, these are the importance weights of the
   true target against it (a likelihood ratio: the prior and the flow's Jacobian cancel); for a
   measurement linear within ``linear_radius`` with Gaussian errors every ratio is equal and the
   filter is the localised flow, to round-off (tested).
4. **Transport** each coordinate's weighted members to equally weighted ones:
   ``"quantile"`` (default): the monotone (one-dimensional optimal transport) map, member ``i``'s
   value moved to the weighted members' quantile at its own rank ``(rank_i + 1/2) / N`` (linear
   between the weighted members' mid-point cumulative weights): equal weights leave every member
   where it is (to round-off), and neighbouring coordinates move smoothly (the kernel density distribution mapping
   idea of Poterjoy's local particle filter); ``"systematic"``: each coordinate's members resampled
   with one uniform per trial (Penny & Miyoshi), which breaks members apart where neighbouring
   coordinates pick different ancestors.

The estimate is the weighted mean of each coordinate (before the transport); the state's ``ess`` is
the local effective sample size averaged over the coordinates. The evidence is the forecast
ensemble's Gaussian approximation, as for the lag-one flow (:attr:`estimates_evidence` is ``False``):
local weights do not multiply into one likelihood.

Cost per step over :class:`~torchflow.filters.LagOneFlowFilter`: one more measurement of the
members, ``m`` regressions on ``K_lin`` coordinates (``O(N K_lin^2)`` each) and a sort of ``N`` values
per coordinate.

Shapes: ensemble ``(B, N, d)``, observations ``z (B, m)`` (NaN: not observed).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional, Tuple

import torch

from torchflow.core.checks import check_number
from torchflow.core.errors import ArgumentError, ArgumentTypeError
from torchflow.core.geometry import DIAGONAL_NOISE, check_radius, local_observations
from torchflow.filters.assimilation import LagOneFlowFilter
from torchflow.filters.ensemble import local_transport, rotate_anomalies
from torchflow.flows.ensemble import ridge_solve

__all__ = ["LocalLagOneFlowParticleFilter", "observation_neighbourhoods"]

#: ``transport=`` choices: the monotone map per coordinate, or systematic resampling per coordinate
TRANSPORTS = ("quantile", "systematic")


def observation_neighbourhoods(model, radius: float, distances=None) -> Tuple[torch.Tensor, torch.Tensor]:
    """The state coordinates within ``radius`` (inclusive) of each observation: ``(index (m, K),
    used (m, K) bool)`` on the CPU (``K``: the most coordinates one observation has; unused slots
    ``False``), from the model's declared geometry or ``distances (d, m)``, as
    :func:`~torchflow.core.geometry.local_observations` reads it (no ``(d, m)`` matrix on a ring)."""
    d, m = model.state_dim, model.obs_dim
    # Gaspari-Cohn is > 0 strictly inside its radius: a margin makes the radius inclusive
    taper, index = local_observations(model, radius + 1e-6 * (1.0 + radius), distances)
    near = taper > 0  # (d, K): coordinate a reaches observation index[a, k]
    coord = torch.arange(d).unsqueeze(1).expand_as(index)[near]
    obs = index[near]
    order = torch.argsort(obs * d + coord)
    coord, obs = coord[order], obs[order]
    counts = torch.bincount(obs, minlength=m)
    K = max(1, int(counts.max()))
    slot = torch.arange(obs.numel()) - (torch.cumsum(counts, 0) - counts)[obs]
    out = torch.zeros(m, K, dtype=torch.long)
    used = torch.zeros(m, K, dtype=torch.bool)
    out[obs, slot] = coord
    used[obs, slot] = True
    return out, used


class LocalLagOneFlowParticleFilter(LagOneFlowFilter):
    """The localised lag-one flow with local importance weights and a local transport (module docstring).

    Args:
        model: as :class:`~torchflow.filters.LagOneFlowFilter`, with a diagonal measurement noise
            (the weights read each observation on its own) and a geometry (a ring, or ``distances``).
        n_particles, inflation, flow_steps, step_ratio, radius, distances, likelihood, rotate: the
            flow's, as :class:`~torchflow.filters.LagOneFlowFilter` (``radius`` finite: the localised flow;
            ``inf``: the global one).
        weight_radius: the Gaspari-Cohn radius of an observation's weight on a coordinate (finite, > 0).
        linear_radius: the state coordinates within this distance of an observation (inclusive; >= 0)
            carry its local linearisation (0: the coordinate it reads).
        transport: ``"quantile"`` (default) or ``"systematic"`` (module docstring).
        validate, name: as :class:`~torchflow.filters.Filter`.

    Shapes: ensemble ``(B, N, d)``, observations ``z (B, m)`` (NaN: not observed).
    """

    nonfinite_hint = (
        "the members or the weights diverged: a smaller weight_radius, transport='quantile', a smaller "
        "inflation, more flow_steps, or dynamics that blow up at the model's time step (a smaller dt)"
    )

    def __init__(
        self,
        model,
        *,
        n_particles: int = 40,
        inflation: float = 1.02,
        flow_steps: int = 20,
        step_ratio: float = 1.2,
        radius: float = 30.0,
        distances: Optional[torch.Tensor] = None,
        likelihood: str = "gaussian",
        rotate: bool = True,
        weight_radius: float = 8.0,
        linear_radius: float = 0.0,
        transport: str = "quantile",
        validate: bool = True,
        name: Optional[str] = None,
    ):
        super().__init__(
            model,
            n_particles=n_particles,
            inflation=inflation,
            flow_steps=flow_steps,
            step_ratio=step_ratio,
            radius=radius,
            distances=distances,
            likelihood=likelihood,
            rotate=rotate,
            validate=validate,
            name=name,
        )
        if model.structure.measurement_noise not in DIAGONAL_NOISE:
            raise ArgumentTypeError(
                f"{self.name}: model: the local weights read each observation on its own, which needs a diagonal "
                f"measurement noise (declared scalar, diagonal or state_dependent_diagonal); {type(model).__name__} "
                f"declares {model.structure.measurement_noise!r}"
            )
        self.weight_radius = check_radius(weight_radius)
        if math.isinf(self.weight_radius):
            raise ArgumentError(
                "weight_radius: expected a finite number > 0 (the weights' localisation radius), got inf; for weights "
                "that every observation gives every coordinate use filter=lag1_pfpf"
            )
        self.linear_radius = check_number(
            "linear_radius", linear_radius, lambda v: 0 <= v < math.inf, "a finite number >= 0 (a distance)"
        )
        if transport not in TRANSPORTS:
            raise ArgumentError(f"transport: expected one of {TRANSPORTS}, got {transport!r}")
        #: ``"quantile"``: the monotone map per coordinate; ``"systematic"``: resampling per coordinate
        self.transport = transport
        taper, index = local_observations(model, self.weight_radius, distances)
        self.register_buffer("weight_index", index.to(model.device), persistent=False)
        self.register_buffer("weight_taper", taper.to(model.dtype).to(model.device), persistent=False)
        lin_index, lin_used = observation_neighbourhoods(model, self.linear_radius, distances)
        self.register_buffer("linear_index", lin_index.to(model.device), persistent=False)
        self.register_buffer("linear_used", lin_used.to(model.device), persistent=False)

    def bytes_per_trial(self, n_particles=None):
        N, d, m = self._resolve_n(n_particles), self.model.state_dim, self.model.obs_dim
        K, Kl = self.weight_index.shape[1], self.linear_index.shape[1]
        return super().bytes_per_trial(n_particles) + 8 * (4 * N * d + N * d * K + 3 * N * m * Kl + m * Kl * Kl)

    def step(self, state, z: torch.Tensor, generator: Optional[torch.Generator] = None):
        """Flow the previous members to the lag-one target, forecast them, weigh every coordinate
        locally and transport its members to equal weights."""
        Xf, ll = self.migrate(state.particles, z)
        Xk = self.model.sample_transition(Xf, generator)
        log_w = self.local_log_weights(Xk, z)  # (B, N, d)
        W = torch.softmax(log_w, 1)
        estimate = (W * Xk).sum(1)
        Xa = local_transport(Xk, W, self.transport, generator)  # the weights computed once, above
        if self.rotate:
            Xa = rotate_anomalies(Xa, generator)
        ess = (1.0 / W.square().sum(1)).mean(-1)  # (B,): the local ESS averaged over coordinates
        return dataclasses.replace(self._state(Xa, ll, state.step + 1), estimate=estimate, ess=ess)

    def local_log_weights(self, X: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """``(B, N, d)``: coordinate ``a``'s log-weight of member ``X[:, i] (B, N, d)`` (states at time k),
        ``sum_j rho(a, j) r_ij`` (module docstring, steps 2-3; unobserved: ``r = 0``)."""
        B, N, d = X.shape
        w = self.whiten(X, X.mean(1), z)  # Y (B, N, m) whitened anomalies, delta (B, m), scale s (B, m)
        m = w.Y.shape[-1]
        idx, used = self.linear_index, self.linear_used.to(X.dtype)  # (m, K)
        K = idx.shape[1]
        D = X - X.mean(1, keepdim=True)
        Dl = D.index_select(2, idx.reshape(-1)).view(B, N, m, K) * used  # (B, N, m, K)
        Dl = Dl.permute(0, 2, 1, 3)  # (B, m, N, K)
        G = Dl.transpose(-1, -2) @ Dl  # (B, m, K, K)
        beta = ridge_solve(G, Dl.transpose(-1, -2) @ w.Y.transpose(1, 2).unsqueeze(-1), N)  # (B, m, K, 1)
        Ylin = (Dl @ beta).squeeze(-1).transpose(1, 2)  # (B, N, m): the linearisation's whitened anomalies
        e_lin = w.delta.unsqueeze(1) - Ylin
        observed = w.observed.unsqueeze(1)
        z0 = torch.where(w.observed, z, torch.zeros_like(z)).unsqueeze(1)  # no NaN into the model's terms
        true = self.model.measurement_log_prob_terms(z0, X)  # (B, N, m)
        gauss = -0.5 * e_lin.square() - w.scale.log().unsqueeze(1) - 0.5 * math.log(2 * math.pi)
        r = torch.where(observed, true - gauss, torch.zeros_like(true))
        return (r[:, :, self.weight_index] * self.weight_taper.to(X.dtype)).sum(-1)

    def extra_repr(self) -> str:
        return (
            super().extra_repr()
            + f", weight_radius={self.weight_radius:g}, linear_radius={self.linear_radius:g}"
            + f", transport={self.transport!r}"
        )
