"""3-D source localisation from time differences of arrival (Zhang, Khojasteh, Atanasov &
Meyer 2024, the TDOA scenario).

Static sources ``x`` in the cube ``[-r, r]^3`` are heard by V receivers; sensor s is a receiver pair
``(a, b)`` and measures

    z = h_ab(x) + v,   h_ab(x) = (||x - p_a|| - ||x - p_b||) / c,   v ~ N(0, sigma_v^2),

at most once per source (detection probability ``p_d``), plus Poisson clutter (mean ``mu_c`` per
sensor) uniform on the feasible interval ``[-||p_a - p_b|| / c, ||p_a - p_b|| / c]``.

As a :class:`~torchflow.models.StateSpaceModel`, the sensors are the time steps (:attr:`TDOA3D.n_steps`),
the state is the static sources ``(3 n,)`` and ``observations (B, S, M)`` are padded with 0 and come
with a ``mask`` (:class:`TDOAData`): only the localisers of :mod:`torchflow.tdoa` run on it.
Defaults: the paper's pair list and source count appear only in a figure; ours are read from it.
"""

from __future__ import annotations

import operator
from dataclasses import dataclass
from typing import Optional, Sequence

import torch

from torchflow.core.checks import as_real_tensor, check_number
from torchflow.core.errors import ArgumentError
from torchflow.models.base import GaussianStateSpaceModel, Trajectory
from torchflow.models.contract import check_simulate_args
from torchflow.models.structure import Structure


def face_receivers(half_width: float = 1000.0) -> torch.Tensor:
    """The six face centres ``(+x, -x, +y, -y, +z, -z) * half_width``, ``(6, 3)``."""
    eye = torch.eye(3, dtype=torch.float64) * half_width
    return torch.stack([eye[0], -eye[0], eye[1], -eye[1], eye[2], -eye[2]])


def plus_minus_pairs() -> list:
    """Each "+" face receiver (0, 2, 4) with each "-" face receiver (1, 3, 5): nine pairs."""
    return [(a, b) for a in (0, 2, 4) for b in (1, 3, 5)]


@dataclass
class TDOAData(Trajectory):
    """Simulated runs with padded measurement sets: ``states (B, S + 1, 3 n)`` (the static sources;
    :attr:`sources` ``(B, n, 3)``), ``observations (B, S, M)`` (padded with 0; also :attr:`z`),
    ``mask (B, S, M)`` (the real measurements), ``origin (B, S, M)`` (each measurement's source;
    -1: clutter or padding)."""

    mask: torch.Tensor
    origin: torch.Tensor

    @property
    def sources(self) -> torch.Tensor:
        return self.states[:, 0].reshape(self.states.shape[0], -1, 3)

    @property
    def z(self) -> torch.Tensor:
        return self.observations

    def __getitem__(self, idx) -> "TDOAData":
        return TDOAData(self.states[idx], self.observations[idx], self.mask[idx], self.origin[idx])


class TDOA3D(GaussianStateSpaceModel):
    """The TDOA scenario of Zhang et al. 2024 (see the module docstring).

    Args:
        receivers: ``(V, 3)`` receiver positions (default :func:`face_receivers`).
        pairs: S pairs ``(a, b)`` of receiver indices (default :func:`plus_minus_pairs`).
        speed: propagation speed c (m/s).
        sigma_v: measurement noise standard deviation (s).
        p_d: detection probability in (0, 1].
        clutter_rate: mean number of clutter measurements per sensor, >= 0.
        n_sources: sources per run.
        region: half width r of the region ``[-r, r]^3`` (m).
    """

    obs_dim = None  # masked measurement sets of varying size (structure.padded_measurements)
    structure = Structure(has_positions=True, padded_measurements=True)

    def __init__(
        self,
        receivers: Optional[torch.Tensor] = None,
        pairs: Optional[Sequence[Sequence[int]]] = None,
        *,
        speed: float = 1500.0,
        sigma_v: float = 5e-4,
        p_d: float = 0.95,
        clutter_rate: float = 1.0,
        n_sources: int = 3,
        region: float = 1000.0,
    ):
        super().__init__()
        self.speed, self.sigma_v, self.region = (
            check_number(k, v, lambda v: v > 0, "a positive number")
            for k, v in (("speed", speed), ("sigma_v", sigma_v), ("region", region))
        )
        rec = face_receivers(self.region) if receivers is None else as_real_tensor("receivers", receivers)
        if rec.dim() != 2 or rec.shape[-1] != 3 or rec.shape[0] < 2:
            raise ArgumentError(f"receivers: expected (V, 3) positions with V >= 2, got {tuple(rec.shape)}")
        gap = torch.cdist(rec, rec) + torch.eye(len(rec), dtype=rec.dtype) * 1e300
        if bool((gap <= 0).any()):
            i, j = [int(v) for v in torch.nonzero(gap <= 0)[0]]
            raise ArgumentError(
                f"receivers: receivers {i} and {j} coincide at {rec[i].tolist()}; a pair needs two distinct positions"
            )
        try:  # integer indices: operator.index refuses 0.5 and "a" (int() would truncate or parse them)
            pairs = plus_minus_pairs() if pairs is None else [tuple(operator.index(v) for v in p) for p in pairs]
        except TypeError:
            raise ArgumentError(f"pairs: expected pairs (a, b) of receiver indices, got {pairs!r}") from None
        if not pairs:
            raise ArgumentError("pairs: expected at least one receiver pair (a, b), got none")
        for p in pairs:
            if len(p) != 2 or p[0] == p[1] or not all(0 <= v < len(rec) for v in p):
                raise ArgumentError(
                    f"pairs: expected pairs (a, b) of distinct receiver indices in [0, {len(rec)}), got {p}"
                )
        self.p_d = check_number("p_d", p_d, lambda v: 0 < v <= 1, "a detection probability in (0, 1]")
        self.clutter_rate = check_number("clutter_rate", clutter_rate, lambda v: v >= 0, "a mean clutter count >= 0")
        check_number("n_sources", n_sources, lambda v: isinstance(v, int) and v >= 0, "an integer >= 0")
        self.n_sources = n_sources
        self.register_buffer("receivers", rec)
        self.register_buffer("pairs", torch.tensor(pairs, dtype=torch.long))
        self.state_dim = 3 * n_sources

    @property
    def n_sensors(self) -> int:
        return self.pairs.shape[0]

    @property
    def n_steps(self) -> int:  # one step per sensor (the runner takes the step count from here)
        return self.n_sensors

    # ---- the static sources as a state-space model -------------------------------------------
    def transition_mean(self, x: torch.Tensor) -> torch.Tensor:
        return x

    def transition_cov(self, x: Optional[torch.Tensor] = None) -> torch.Tensor:
        return self.receivers.new_zeros(self.state_dim, self.state_dim)

    def positions(self, x: torch.Tensor) -> torch.Tensor:
        """Source positions ``(..., n, 3)`` of states ``(..., 3 n)``."""
        return x.reshape(*x.shape[:-1], -1, 3)

    def initial_belief(self, states0: torch.Tensor, generator=None):
        """Moments of the uniform prior on the region, ``(B, 3 n)`` and ``(B, 3 n, 3 n)`` (no draw)."""
        B, d = states0.shape
        cov = torch.eye(d, dtype=states0.dtype, device=states0.device) * (self.region**2 / 3)
        return states0.new_zeros(B, d), cov.expand(B, d, d)

    def _ends(self, sensor):
        s = torch.as_tensor(sensor, dtype=torch.long, device=self.pairs.device)
        return self.receivers[self.pairs[s, 0]], self.receivers[self.pairs[s, 1]]

    def measure(self, x: torch.Tensor, sensor) -> torch.Tensor:
        """``h_s(x)`` of positions ``x (..., 3)`` for sensor index ``sensor`` (an int or a long tensor
        broadcastable to ``x[..., 0]``) -> ``(...)``."""
        pa, pb = (p.to(x.dtype) for p in self._ends(sensor))
        return (torch.linalg.vector_norm(x - pa, dim=-1) - torch.linalg.vector_norm(x - pb, dim=-1)) / self.speed

    def jacobian(self, x: torch.Tensor, sensor) -> torch.Tensor:
        """``dh_s/dx = ((x - p_a)/||x - p_a|| - (x - p_b)/||x - p_b||) / c``, ``(..., 3)``."""
        da, db = (x - p.to(x.dtype) for p in self._ends(sensor))
        return (
            da / torch.linalg.vector_norm(da, dim=-1, keepdim=True)
            - db / torch.linalg.vector_norm(db, dim=-1, keepdim=True)
        ) / self.speed

    def feasible_half_width(self, sensor) -> torch.Tensor:
        """``||p_a - p_b|| / c``: TDOAs of sensor s lie in ``[-w, w]``."""
        pa, pb = self._ends(sensor)
        return torch.linalg.vector_norm(pa - pb, dim=-1) / self.speed

    def clutter_log_density(self, sensor) -> torch.Tensor:
        """``log f_c = -log(2 w)`` of the uniform clutter density of sensor s."""
        return -torch.log(2 * self.feasible_half_width(sensor))

    def log_likelihood(self, z: torch.Tensor, x: torch.Tensor, sensor) -> torch.Tensor:
        """``log N(z; h_s(x), sigma_v^2)`` for ``z`` broadcastable against ``x[..., 0]``."""
        r = (z - self.measure(x, sensor)) / self.sigma_v
        return -0.5 * r * r - torch.log(torch.as_tensor(self.sigma_v * (2 * torch.pi) ** 0.5, dtype=x.dtype))

    def check_measurements(self, z: torch.Tensor, mask: torch.Tensor) -> None:
        """Raise a clear error unless ``z (B, S, M)`` and ``mask`` (bool, same shape) fit this model."""
        if not isinstance(z, torch.Tensor) or z.dim() != 3 or z.shape[1] != self.n_sensors:
            got = tuple(z.shape) if isinstance(z, torch.Tensor) else type(z).__name__
            raise ArgumentError(f"z: expected (B, S, M) measurements with S = {self.n_sensors} sensors, got {got}")
        if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool or mask.shape != z.shape:
            got = f"{tuple(mask.shape)} of {mask.dtype}" if isinstance(mask, torch.Tensor) else type(mask).__name__
            raise ArgumentError(f"mask: expected a bool tensor shaped like z {tuple(z.shape)}, got {got}")

    def simulate(
        self, batch_size: int, steps: Optional[int] = None, generator: Optional[torch.Generator] = None
    ) -> TDOAData:
        """``batch_size`` scenes drawn together (a scene depends on ``batch_size``), each sensor's
        measurements in random order, padded to the largest count. ``steps``: ``None`` or :attr:`n_steps`."""
        if steps is not None and steps != self.n_steps:
            raise ArgumentError(
                f"steps: TDOA3D has one step per sensor; expected None or {self.n_steps}, got {steps!r}"
            )
        B, _ = check_simulate_args(self, batch_size, self.n_steps, generator)
        n, S = self.n_sources, self.n_sensors
        dt, dev = self.receivers.dtype, self.receivers.device
        src = (torch.rand(B, n, 3, generator=generator, dtype=dt, device=dev) * 2 - 1) * self.region
        sens = torch.arange(S, device=dev)
        h = self.measure(src.unsqueeze(1), sens.view(1, S, 1))  # (B, S, n)
        z_src = h + self.sigma_v * torch.randn(B, S, n, generator=generator, dtype=dt, device=dev)
        det = torch.rand(B, S, n, generator=generator, dtype=dt, device=dev) < self.p_d
        n_c = torch.poisson(torch.full((B, S), self.clutter_rate, dtype=dt, device=dev), generator=generator).long()
        C = int(n_c.max()) if n_c.numel() else 0
        w = self.feasible_half_width(sens).to(dt)  # (S,)
        z_cl = (torch.rand(B, S, C, generator=generator, dtype=dt, device=dev) * 2 - 1) * w.view(1, S, 1)
        cl_mask = torch.arange(C, device=dev).view(1, 1, C) < n_c.unsqueeze(-1)
        z = torch.cat([z_src, z_cl], -1)
        mask = torch.cat([det, cl_mask], -1)
        origin = torch.cat([torch.arange(n, device=dev).expand(B, S, n), torch.full((B, S, C), -1, device=dev)], -1)
        # random order within each sensor, real measurements first (padding last)
        key = torch.rand(z.shape, generator=generator, dtype=dt, device=dev) + (~mask).to(dt) * 2
        order = key.argsort(-1)
        z, mask, origin = (t.gather(-1, order) for t in (z, mask, origin))
        M = int(mask.sum(-1).max()) if mask.numel() else 0
        z, mask, origin = z[..., :M], mask[..., :M], origin[..., :M]
        states = src.reshape(B, 1, 3 * n).expand(B, S + 1, 3 * n)
        return TDOAData(states, z.masked_fill(~mask, 0.0), mask, origin.masked_fill(~mask, -1))

    def extra_repr(self) -> str:
        return (
            f"receivers={len(self.receivers)}, sensors={self.n_sensors}, speed={self.speed}, "
            f"sigma_v={self.sigma_v}, p_d={self.p_d}, clutter_rate={self.clutter_rate}, "
            f"n_sources={self.n_sources}, region={self.region}"
        )


__all__ = ["TDOA3D", "TDOAData", "face_receivers", "plus_minus_pairs"]
