"""Pseudo-time (lambda) step schedules for particle flows.

A schedule is a sequence of step sizes ``eps_1..eps_n`` summing to one; ``lambda_j`` is the
pseudo-time after step j (``lambda_n = 1``). Flows evaluate their drift at ``lambda_j`` (the
value after the increment), as in Li & Coates' code.
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch

from torchflow.core.checks import check_count
from torchflow.core.errors import ArgumentError, ArgumentTypeError


class LambdaSchedule:
    """Base class: subclasses implement :meth:`step_sizes`."""

    n_steps: int

    def step_sizes(self) -> torch.Tensor:
        """``(n,)`` float64 step sizes summing to 1, on the CPU."""
        raise NotImplementedError

    def steps(self, dtype=torch.float64, device=None) -> Tuple[torch.Tensor, torch.Tensor]:
        """Step sizes ``eps (n,)`` and pseudo-times after each step ``lambda (n,)``, ``lambda[-1] = 1``.

        Built once per dtype and device and then reused (a flow calls this every time step: no
        host-to-device copy each time); the tensors are shared, so treat them as read-only."""
        key = ("steps", dtype, str(torch.device(device) if device is not None else torch.device("cpu")), self._state())
        cache = self.__dict__.setdefault("_cache", {})
        if key not in cache:
            eps = self.check()
            lam = torch.cumsum(eps, 0)
            lam[-1] = 1.0
            cache[key] = (eps.to(dtype=dtype, device=device), lam.to(dtype=dtype, device=device))
        return cache[key]

    def host_steps(self, dtype=torch.float64) -> Tuple[float, ...]:
        """The step sizes as Python floats, rounded to ``dtype`` like :meth:`steps`: the pseudo-steps'
        host-side constants (``alpha`` of fused products), never read back from a device tensor.
        Built once per dtype."""
        key = ("host", dtype, self._state())
        cache = self.__dict__.setdefault("_cache", {})
        if key not in cache:
            cache[key] = tuple(self.check().to(dtype).tolist())  # a CPU float64 tensor: no device read
        return cache[key]

    def check(self) -> torch.Tensor:
        """The step sizes, checked: a 1-D tensor of finite, positive steps summing to 1 (to 1e-9);
        a ValueError naming the schedule otherwise (a custom :meth:`step_sizes` is not trusted).
        Checked once per setting of the schedule's public attributes, then cached (no host reads
        per filter step)."""
        key = ("checked", self._state())
        cache = self.__dict__.setdefault("_cache", {})
        if key in cache:
            return cache[key]
        eps = self.step_sizes()
        name = type(self).__name__
        if not isinstance(eps, torch.Tensor) or eps.dim() != 1 or eps.numel() == 0 or not eps.is_floating_point():
            got = f"shape {tuple(eps.shape)} {eps.dtype}" if isinstance(eps, torch.Tensor) else type(eps).__name__
            raise ArgumentError(f"{name}.step_sizes(): expected a non-empty 1-D float tensor, got {got}")
        eps = eps.detach().to(torch.float64, copy=False).cpu()
        if not bool(torch.isfinite(eps).all()) or bool((eps <= 0).any()):
            raise ArgumentError(f"{name}.step_sizes(): expected finite steps > 0, got smallest {eps.min().item():.4g}")
        if abs(eps.sum().item() - 1.0) > 1e-9:
            raise ArgumentError(
                f"{name}.step_sizes(): expected steps summing to 1 (lambda from 0 to 1), "
                f"got a sum of {eps.sum().item():.6g}"
            )
        cache[key] = eps
        return eps

    def _state(self) -> str:
        """The public settings: a cache key that follows any change to them."""
        return repr(sorted((k, v) for k, v in vars(self).items() if not k.startswith("_")))

    def __len__(self) -> int:
        return self.n_steps

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v}" for k, v in vars(self).items() if not k.startswith("_"))
        return f"{type(self).__name__}({args})"


class ExponentialSchedule(LambdaSchedule):
    """Exponentially spaced steps ``eps_j = eps_1 q^(j-1)``, ``eps_1 = (q - 1)/(q^n - 1)``
    (Li & Coates: n = 29, q = 1.2, so eps_1 = 1.0162e-3 and eps_29 = 0.16751)."""

    def __init__(self, n_steps: int = 29, ratio: float = 1.2):
        if ratio <= 0:
            raise ArgumentError(f"ratio: expected > 0, got {ratio}")
        self.n_steps, self.ratio = check_count("n_steps", n_steps), float(ratio)

    def step_sizes(self):
        q, n = self.ratio, self.n_steps
        j = torch.arange(n, dtype=torch.float64)
        if abs(q - 1.0) < 1e-12:
            return torch.full((n,), 1.0 / n, dtype=torch.float64)
        return (q - 1.0) / (q**n - 1.0) * q**j


class UniformSchedule(LambdaSchedule):
    """``n_steps`` equal steps of ``1 / n_steps``."""

    def __init__(self, n_steps: int = 29):
        self.n_steps = check_count("n_steps", n_steps)

    def step_sizes(self):
        return torch.full((self.n_steps,), 1.0 / self.n_steps, dtype=torch.float64)


class GeometricSchedule(LambdaSchedule):
    """The schedule of Zhang, Khojasteh, Atanasov & Meyer (2024): a first step ``first_step`` (Delta_1), each next
    step ``ratio`` (beta) times the previous, and a last step that closes at lambda = 1:
    ``eps_j = Delta_1 beta^(j-1)`` while ``sum < 1``, then ``eps_n = 1 - lambda_(n-1)``.

    The step count follows from the two knobs: ``Delta_1 = 1e-4, beta = 2`` gives 14 steps,
    ``Delta_1 = 1e-5, beta = 1.5`` gives 27.
    """

    def __init__(self, first_step: float = 1e-4, ratio: float = 2.0):
        if not 0 < first_step <= 1:
            raise ArgumentError(f"first_step: expected in (0, 1], got {first_step}")
        if ratio < 1:
            raise ArgumentError(f"ratio: expected >= 1, got {ratio}")
        self.first_step, self.ratio = float(first_step), float(ratio)
        eps, total = [], 0.0
        while total + self.first_step * self.ratio ** len(eps) < 1.0 - 1e-12:
            eps.append(self.first_step * self.ratio ** len(eps))
            total += eps[-1]
            if len(eps) > 100_000:
                raise ArgumentError(f"first_step={first_step}, ratio={ratio}: more than 1e5 steps")
        eps.append(1.0 - total)
        self._eps = eps
        self.n_steps = len(eps)

    def step_sizes(self):
        return torch.tensor(self._eps, dtype=torch.float64)


#: schedules by name, built with their defaults (``schedule="uniform"``)
SCHEDULES = {"exponential": ExponentialSchedule, "uniform": UniformSchedule, "geometric": GeometricSchedule}


def resolve_schedule(schedule, default: Optional[LambdaSchedule] = None, *, name: str = "schedule") -> LambdaSchedule:
    """``schedule`` as a checked :class:`LambdaSchedule`: ``None`` gives ``default`` (else the
    exponential schedule, 29 steps, ratio 1.2), a name of :data:`SCHEDULES` that schedule with its
    defaults; anything else is an error naming ``name``."""
    if schedule is None:
        return default if default is not None else ExponentialSchedule()
    if isinstance(schedule, str):
        if schedule not in SCHEDULES:
            raise ArgumentError(f"{name}: expected a LambdaSchedule or one of {tuple(SCHEDULES)}, got {schedule!r}")
        return SCHEDULES[schedule]()
    if not isinstance(schedule, LambdaSchedule):
        raise ArgumentTypeError(
            f"{name}: expected a LambdaSchedule (torchflow.flows.schedules) or one of {tuple(SCHEDULES)}, "
            f"got {type(schedule).__name__}"
        )
    schedule.check()
    return schedule
