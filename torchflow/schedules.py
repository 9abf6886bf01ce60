"""Pseudo-time (lambda) step schedules for particle flows.

A schedule is a sequence of step sizes ``eps_1..eps_n`` summing to one; ``lambda_j`` is the
pseudo-time after step j (``lambda_n = 1``). Flows evaluate their drift at ``lambda_j`` (the
value after the increment), as in Li & Coates' code.
"""
from __future__ import annotations

from typing import Tuple

import torch


class LambdaSchedule:
    """Base class: subclasses implement :meth:`step_sizes`."""

    n_steps: int

    def step_sizes(self) -> torch.Tensor:
        """``(n,)`` float64 step sizes summing to 1."""
        raise NotImplementedError

    def steps(self, dtype=torch.float64, device=None) -> Tuple[torch.Tensor, torch.Tensor]:
        """Step sizes ``eps (n,)`` and pseudo-times after each step ``lambda (n,)``, ``lambda[-1] = 1``."""
        eps = self.step_sizes()
        lam = torch.cumsum(eps, 0)
        lam[-1] = 1.0
        return eps.to(dtype=dtype, device=device), lam.to(dtype=dtype, device=device)

    def __len__(self) -> int:
        return self.n_steps

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v}" for k, v in vars(self).items())
        return f"{type(self).__name__}({args})"


class ExponentialSchedule(LambdaSchedule):
    """Exponentially spaced steps ``eps_j = eps_1 q^(j-1)``, ``eps_1 = (q - 1)/(q^n - 1)``
    (Li & Coates: n = 29, q = 1.2, so eps_1 = 1.0162e-3 and eps_29 = 0.16751)."""

    def __init__(self, n_steps: int = 29, ratio: float = 1.2):
        if int(n_steps) < 1:
            raise ValueError(f"n_steps: expected >= 1, got {n_steps}")
        if ratio <= 0:
            raise ValueError(f"ratio: expected > 0, got {ratio}")
        self.n_steps, self.ratio = int(n_steps), float(ratio)

    def step_sizes(self):
        q, n = self.ratio, self.n_steps
        j = torch.arange(n, dtype=torch.float64)
        if abs(q - 1.0) < 1e-12:
            return torch.full((n,), 1.0 / n, dtype=torch.float64)
        return (q - 1.0) / (q**n - 1.0) * q**j


class UniformSchedule(LambdaSchedule):
    """``n_steps`` equal steps of ``1 / n_steps``."""

    def __init__(self, n_steps: int = 29):
        if int(n_steps) < 1:
            raise ValueError(f"n_steps: expected >= 1, got {n_steps}")
        self.n_steps = int(n_steps)

    def step_sizes(self):
        return torch.full((self.n_steps,), 1.0 / self.n_steps, dtype=torch.float64)
