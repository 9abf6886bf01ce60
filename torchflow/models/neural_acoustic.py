"""Acoustic tracking with a learned sensor response: a neural network inside the measurement.

:class:`NeuralAcoustic` is :class:`~torchflow.models.AcousticTracking` (the same targets, dynamics,
sensor grid, noise, prior and simulation) with the per-target sensor response
``Psi / (r + d0)`` replaced by a module ``g``:

    z_s = sum_c g(|p_c - s_s|) + w_s,     w_s ~ N(0, sigma_w^2).

``g`` is any ``nn.Module`` that maps distances ``r (...)`` to positive amplitudes ``(...)``
elementwise. Its parameters are the model's (``model.parameters()``), so a filter's log-evidence
backpropagates into them and :class:`~torchflow.app.lightning.FilterLightningModule` learns them like
any other parameter. The flows and the EKF/UKF need ``dh/dx`` (GPFIS also the second derivatives):
``dz_s / dp_c = g'(r) (p_c - s_s) / r``; a response that gives ``derivatives(r, order)`` (as both
responses here do, in closed form) is differentiated by it, any other by forward-mode autodiff
(:func:`torch.func.jvp`, elementwise).

* :class:`ResponseMLP`: ``g(r) = exp(f(log(r + d0)))`` with ``f`` a small tanh MLP (positive by
  construction; the physical law ``Psi / (r + d0)`` is the line ``log Psi - u`` in these
  coordinates, so the MLP can represent it, and far more).
* :class:`InverseDistance`: ``g(r) = Psi / (r + d0)``, the physical law as a module; with it
  :class:`NeuralAcoustic` gives the numbers of :class:`~torchflow.models.AcousticTracking`.
"""

from __future__ import annotations

import math
from typing import Callable, Optional, Sequence, Tuple

import torch
from torch import nn
from torch.func import jvp

from torchflow.core.checks import check_count, check_learnable, check_positive
from torchflow.core.errors import ArgumentError, ArgumentTypeError
from torchflow.models.acoustic import _X0, AcousticTracking
from torchflow.models.structure import Structure


class InverseDistance(nn.Module):
    """The acoustic model's response ``g(r) = Psi / (r + d0)`` (constants held as buffers).

    Args:
        psi: source amplitude Psi (10).
        d0: distance offset d0 (0.1).
    """

    def __init__(self, psi: float = 10.0, d0: float = 0.1):
        super().__init__()
        for name, value in (("psi", psi), ("d0", d0)):
            self.register_buffer(name, torch.tensor(check_positive(name, value), dtype=torch.float64))

    def forward(self, r: torch.Tensor) -> torch.Tensor:
        """Amplitudes ``(...)`` at distances ``r (...)``."""
        return self.psi / (r + self.d0)

    def derivatives(self, r: torch.Tensor, order: int = 1) -> Tuple[torch.Tensor, ...]:
        """``(g, g', g'')`` up to ``order`` at ``r (...)``, each ``(...)``: ``g' = -Psi / (r + d0)^2``,
        ``g'' = 2 Psi / (r + d0)^3``."""
        inv = 1 / (r + self.d0)
        g = self.psi * inv
        out = (g, -g * inv, 2 * g * inv * inv)
        return out[: order + 1]


class ResponseMLP(nn.Module):
    """A positive response ``g(r) = exp(f(u))``, ``u = log(r + d0)``, where ``f: R -> R`` is an MLP
    with ``tanh`` hidden layers of the widths ``hidden`` and a linear output.

    Args:
        hidden: widths of the hidden layers ((16,): one layer of 16 units, 49 parameters).
        d0: offset of the log-distance input (0.1).
        seed: seeds the initial weights (PyTorch's default ``nn.Linear`` law, ``U(-1/sqrt(fan_in),
            1/sqrt(fan_in))``, drawn from a generator of its own).
    """

    def __init__(self, hidden: Sequence[int] = (16,), d0: float = 0.1, seed: int = 0):
        super().__init__()
        try:
            widths = [check_count(f"hidden[{i}]", h) for i, h in enumerate(hidden)]
        except TypeError as e:
            raise ArgumentTypeError(f"hidden: expected a sequence of layer widths, got {hidden!r}") from e
        if not widths:
            raise ArgumentError(f"hidden: expected at least one hidden layer width, got {hidden!r}")
        self.register_buffer("d0", torch.tensor(check_positive("d0", d0), dtype=torch.float64))
        g = torch.Generator().manual_seed(check_count("seed", seed, minimum=0))
        sizes = [1, *widths, 1]
        self.layers = nn.ModuleList()
        for fan_in, fan_out in zip(sizes[:-1], sizes[1:]):
            layer = nn.Linear(fan_in, fan_out, dtype=torch.float64)
            bound = 1 / math.sqrt(fan_in)
            with torch.no_grad():
                layer.weight.copy_((2 * torch.rand(fan_out, fan_in, generator=g, dtype=torch.float64) - 1) * bound)
                layer.bias.copy_((2 * torch.rand(fan_out, generator=g, dtype=torch.float64) - 1) * bound)
            self.layers.append(layer)

    def forward(self, r: torch.Tensor) -> torch.Tensor:
        """Amplitudes ``(...)`` at distances ``r (...)``."""
        return self.derivatives(r, 0)[0]

    def log_response(self, u: torch.Tensor, order: int = 0) -> Tuple[torch.Tensor, ...]:
        """``(f(u), f'(u), f''(u))`` up to ``order`` at log-distances ``u (...)``, by forward-mode
        differentiation through the layers in closed form (``tanh' = 1 - tanh^2``)."""
        x = u.unsqueeze(-1)  # (..., 1)
        dx = torch.ones_like(x) if order >= 1 else None
        ddx = torch.zeros_like(x) if order >= 2 else None
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            W = layer.weight.transpose(-1, -2)  # (in, out)
            a = x @ W + layer.bias
            da = dx @ W if order >= 1 else None
            dda = ddx @ W if order >= 2 else None
            if i == last:
                x, dx, ddx = a, da, dda
                break
            x = torch.tanh(a)
            t = 1 - x * x
            if order >= 2:
                ddx = t * dda - 2 * x * t * da * da
            if order >= 1:
                dx = t * da
        return tuple(v.squeeze(-1) for v in (x, dx, ddx)[: order + 1])

    def derivatives(self, r: torch.Tensor, order: int = 1) -> Tuple[torch.Tensor, ...]:
        """``(g, g', g'')`` up to ``order`` at ``r (...)``, each ``(...)``: with ``q = 1 / (r + d0)``,
        ``g' = g f' q`` and ``g'' = g q^2 (f'^2 + f'' - f')``."""
        q = 1 / (r + self.d0)
        f = self.log_response(torch.log(r + self.d0), order)
        g = torch.exp(f[0])
        out = [g]
        if order >= 1:
            out.append(g * f[1] * q)
        if order >= 2:
            out.append(g * q * q * (f[1] * f[1] + f[2] - f[1]))
        return tuple(out)

    def fit(
        self,
        target: Callable[[torch.Tensor], torch.Tensor],
        r_max: float,
        *,
        points: int = 200,
        steps: int = 1500,
        lr: float = 0.01,
    ) -> float:
        """Fit the response to ``target`` (a positive function of distance) by least squares on the
        log scale over ``points`` distances spaced evenly in ``log(r + d0)`` on ``[0, r_max]``
        (full-batch Adam, ``steps`` steps): to start a model from a chosen wrong law. Returns the
        final root-mean-square error of ``log g``."""
        check_positive("r_max", r_max)
        d0 = float(self.d0)
        u = torch.linspace(math.log(d0), math.log(r_max + d0), check_count("points", points), dtype=torch.float64)
        r = u.exp() - d0
        with torch.no_grad():
            goal = torch.log(target(r))
        if not bool(torch.isfinite(goal).all()):
            raise ArgumentError(
                "target: expected positive finite amplitudes on [0, r_max], got a non-positive or non-finite value"
            )
        opt = torch.optim.Adam(self.parameters(), lr=lr)
        for _ in range(check_count("steps", steps)):
            opt.zero_grad()
            loss = (self.log_response(u)[0] - goal).pow(2).mean()
            loss.backward()
            opt.step()
        with torch.no_grad():
            return float((self.log_response(u)[0] - goal).pow(2).mean().sqrt())


def response_derivatives(response: nn.Module, r: torch.Tensor, order: int) -> Tuple[torch.Tensor, ...]:
    """``(g, g', g'')`` up to ``order`` of an elementwise ``response`` at ``r (...)``: its own
    ``derivatives`` if it has one, else forward-mode autodiff (:func:`torch.func.jvp` along a tangent
    of ones, exact for an elementwise map)."""
    own = getattr(response, "derivatives", None)
    if callable(own):
        return tuple(own(r, order))
    if order == 0:
        return (response(r),)
    ones = torch.ones_like(r)
    if order == 1:
        return tuple(jvp(response, (r,), (ones,)))

    def first(s):
        return jvp(response, (s,), (torch.ones_like(s),))[1]

    g = response(r)
    g1, g2 = jvp(first, (r,), (ones,))
    return g, g1, g2


class NeuralAcoustic(AcousticTracking):
    """Multi-target acoustic tracking whose per-target sensor response is a module (a neural
    network): ``z_s = sum_c g(|p_c - s_s|) + w_s`` (module docstring).

    Everything but the response is :class:`~torchflow.models.AcousticTracking`'s, with the number
    of targets free: ``d = 4 C``, ``m = sensor_grid^2``.

    Args:
        response: the response module ``g`` (distances ``(...)`` -> positive amplitudes ``(...)``,
            elementwise), converted to float64 in place; default a fresh :class:`ResponseMLP`. Its
            parameters are learned unless their ``requires_grad`` is off.
        n_targets: C (1 to 4 with the default initial state, Li & Coates' first C targets; any C
            with ``initial_state``).
        learnable: ``"sigma_w"`` (or ``True``) to learn the noise scale too (stored as its
            logarithm); default ``False``.
        other arguments: as :class:`~torchflow.models.AcousticTracking` (``sigma_w``,
            ``true_noise_scale``, ``filter_noise``, ``area``, ``sensor_grid``, ``prior_std``,
            ``initial_state`` with 4C numbers, ``margin``, ``max_redraws``).
    """

    #: the noise scale may hold one value per trial; the response's amplitude is the module's own
    per_trial_parameters = ("sigma_w",)

    #: linear dynamics, R = sigma_w^2 I, h reads positions only (the support is set per instance);
    #: no kernel form (the response is the user's module) and no graph-safety promise
    structure = Structure(linear_dynamics=True, measurement_noise="scalar", has_positions=True)

    def __init__(
        self,
        response: Optional[nn.Module] = None,
        *,
        n_targets: int = 4,
        sigma_w: float = 0.1,
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
        C = check_count("n_targets", n_targets)
        if initial_state is None and C > len(_X0) // 4:
            raise ArgumentError(
                f"n_targets: expected at most {len(_X0) // 4} without an initial_state (the default "
                f"has {len(_X0) // 4} targets), got {C}"
            )
        if response is None:
            response = ResponseMLP()
        if not isinstance(response, nn.Module):
            raise ArgumentTypeError(
                f"response: expected an nn.Module mapping distances to amplitudes, got {type(response).__name__}"
            )
        learn = check_learnable(learnable, ("sigma_w",))
        object.__setattr__(self, "n_targets", C)  # read by AcousticTracking.__init__ (a class attribute there)
        super().__init__(
            sigma_w=sigma_w,
            true_noise_scale=true_noise_scale,
            filter_noise=filter_noise,
            area=area,
            sensor_grid=sensor_grid,
            prior_std=prior_std,
            initial_state=_X0[: 4 * C] if initial_state is None else initial_state,
            margin=margin,
            max_redraws=max_redraws,
            learnable=sorted(learn),
        )
        del self.psi, self.d0  # the physical law's constants: the response holds its own
        self.response = response.to(dtype=torch.float64)
        width = sum(p.numel() for p in response.parameters()) + 8
        self.structure = type(self).structure.replace(
            measurement_support=tuple(4 * c + i for c in range(C) for i in (0, 1)),
            bytes_per_point=8 * 6 * C * self.obs_dim * width,
        )

    # ---- measurement -----------------------------------------------------------------------
    def _response(self, r: torch.Tensor, order: int) -> Tuple[torch.Tensor, ...]:
        return response_derivatives(self.response, r, order)

    def measure(self, x: torch.Tensor) -> torch.Tensor:
        """``h(x) = sum_c g(|p_c - s|)``: ``(..., d) -> (..., m)``."""
        _, _, r = self._sensor_offsets(x)  # (..., m, C)
        return self._response(r, 0)[0].sum(-1)

    def measurement_jacobian_support(self, x: torch.Tensor) -> torch.Tensor:
        """Position columns of the Jacobian ``(..., m, 2C)`` in :attr:`measurement_support`'s order:
        ``dz_s / dp_c = g'(r) (p_c - s) / r``."""
        return self.linearize_measurement(x, support=True)[1]

    def linearize_measurement(self, x, support=False, scale=None):
        if not support:
            return super().linearize_measurement(x, support, scale)
        dx, dy, r = self._sensor_offsets(x)
        g, g1 = self._response(r, 1)
        coef = g1 / r.clamp_min(torch.finfo(r.dtype).tiny)
        h = g.sum(-1)
        if scale is not None:
            h, coef = h * scale, coef * scale
        return h, torch.stack([coef * dx, coef * dy], -1).flatten(-2)  # (..., m), (..., m, 2C)

    def measurement_hessian_blocks(self, x, support=False, scale=None):
        """Second derivatives, one block per target ``(..., m, C, b, b)`` (``b = 2`` with ``support``,
        else 4 with zero velocity rows): ``g'' u u^T + (g' / r) (I - u u^T)``, ``u = (p - s) / r``."""
        dx, dy, r = self._sensor_offsets(x)  # (..., m, C)
        _, g1, g2 = self._response(r, 2)
        ir = 1 / r.clamp_min(torch.finfo(r.dtype).tiny)
        a = g1 * ir  # identity coefficient
        c = (g2 - a) * ir * ir  # (p - s)(p - s)^T coefficient
        if scale is not None:
            a, c = a * scale, c * scale
        hxy = c * dx * dy
        block = torch.stack([c * dx * dx + a, hxy, hxy, c * dy * dy + a], -1).unflatten(-1, (2, 2))
        return block if support else nn.functional.pad(block, (0, 2, 0, 2))
