"""Numba kernel for Lorenz-63's RK4 map and its exact Jacobian (forward tangents), on the CPU in
float64: at d = 3 the torch path's cost is per-operation overhead (25 substeps x 4 stages of small
products), which a compiled loop removes. Imported only where Numba is installed
(:func:`torchflow.flows.kernels.steps._importable`); the torch path gives the same numbers to round-off."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, inline="always")
def _tendency(x, y, z, sigma, rho, beta):
    return sigma * (y - x), x * (rho - z) - y, x * y - beta * z


@numba.njit(cache=True, inline="always")
def _tangent(x, y, z, v0, v1, v2, sigma, rho, beta):
    # J(x) v with J the tendency's Jacobian
    return sigma * (v1 - v0), (rho - z) * v0 - v1 - x * v2, y * v0 + x * v1 - beta * v2


@numba.njit(cache=True)
def rk4_tangent(states, h, substeps, sigma, rho, beta):
    """``states (n, 3)`` moved by ``substeps`` RK4 steps of ``h``: ``(next (n, 3), jacobian (n, 3, 3))``."""
    n = states.shape[0]
    out = np.empty((n, 3))
    jac = np.empty((n, 3, 3))
    for i in range(n):
        x, y, z = states[i, 0], states[i, 1], states[i, 2]
        J = np.eye(3)
        for _ in range(substeps):
            k1 = _tendency(x, y, z, sigma, rho, beta)
            a = (x + 0.5 * h * k1[0], y + 0.5 * h * k1[1], z + 0.5 * h * k1[2])
            k2 = _tendency(a[0], a[1], a[2], sigma, rho, beta)
            b = (x + 0.5 * h * k2[0], y + 0.5 * h * k2[1], z + 0.5 * h * k2[2])
            k3 = _tendency(b[0], b[1], b[2], sigma, rho, beta)
            c = (x + h * k3[0], y + h * k3[1], z + h * k3[2])
            k4 = _tendency(c[0], c[1], c[2], sigma, rho, beta)
            Jn = np.empty((3, 3))
            for col in range(3):  # the tangent of each column of J through the four stages
                v0, v1, v2 = J[0, col], J[1, col], J[2, col]
                t1 = _tangent(x, y, z, v0, v1, v2, sigma, rho, beta)
                t2 = _tangent(
                    a[0], a[1], a[2], v0 + 0.5 * h * t1[0], v1 + 0.5 * h * t1[1], v2 + 0.5 * h * t1[2], sigma, rho, beta
                )
                t3 = _tangent(
                    b[0], b[1], b[2], v0 + 0.5 * h * t2[0], v1 + 0.5 * h * t2[1], v2 + 0.5 * h * t2[2], sigma, rho, beta
                )
                t4 = _tangent(c[0], c[1], c[2], v0 + h * t3[0], v1 + h * t3[1], v2 + h * t3[2], sigma, rho, beta)
                Jn[0, col] = v0 + h / 6.0 * (t1[0] + 2.0 * t2[0] + 2.0 * t3[0] + t4[0])
                Jn[1, col] = v1 + h / 6.0 * (t1[1] + 2.0 * t2[1] + 2.0 * t3[1] + t4[1])
                Jn[2, col] = v2 + h / 6.0 * (t1[2] + 2.0 * t2[2] + 2.0 * t3[2] + t4[2])
            J = Jn
            x = x + h / 6.0 * (k1[0] + 2.0 * k2[0] + 2.0 * k3[0] + k4[0])
            y = y + h / 6.0 * (k1[1] + 2.0 * k2[1] + 2.0 * k3[1] + k4[1])
            z = z + h / 6.0 * (k1[2] + 2.0 * k2[2] + 2.0 * k3[2] + k4[2])
        out[i, 0], out[i, 1], out[i, 2] = x, y, z
        jac[i] = J
    return out, jac
