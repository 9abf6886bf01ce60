"""Batched small-matrix linear algebra, one op at a time: what a per-particle flow's pseudo-step costs
on this device (a PF-PF(LEDH) step on acoustic tracking factors B x N matrices of k = 8, and
16 x 16 predictive covariances, at every pseudo-step).

    python -m experiments.benchmarks.micro_small_linalg --device cuda [--batch 50000] [--ks 8,16]

Per op: microseconds per call (median of ``--reps`` after a warm-up), for the library call
(``torch.linalg``) and for the column-by-column formulas in plain tensor ops
(:func:`torchflow.core.linalg.small_cholesky`, :func:`torchflow.core.linalg.small_solve_lower`), which on a GPU
may beat the batched LAPACK-style kernels for tiny matrices.
"""

from __future__ import annotations

import statistics
import time

import torch

from torchflow.core import linalg

from . import harness as h


def _time(fn, reps, sync):
    fn()
    sync()
    out = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        sync()
        out.append(time.perf_counter() - t0)
    return statistics.median(out) * 1e6


def run(argv=None) -> dict:
    a = h.options(
        __doc__,
        argv,
        dict(batch=2000, reps=3),
        device="cpu",
        batch=50_000,
        ks="8,16",
        reps=20,
        dtype="float64",
        threads=2,
    )
    torch.set_num_threads(a.threads)
    device, dtype = torch.device(a.device), getattr(torch, a.dtype)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    g = torch.Generator(device=device).manual_seed(0)
    rows = []
    for k in h.ints(a.ks, "--ks"):
        X = torch.randn(a.batch, k, k, generator=g, device=device, dtype=dtype)
        A = X @ X.transpose(-1, -2) / k + torch.eye(k, device=device, dtype=dtype)
        L = torch.linalg.cholesky(A)
        V, v = (
            torch.randn(a.batch, k, k, generator=g, device=device, dtype=dtype),
            torch.randn(a.batch, k, 1, generator=g, device=device, dtype=dtype),
        )
        ops = {
            "cholesky_ex": lambda: torch.linalg.cholesky_ex(A),
            "small_cholesky": lambda: linalg.small_cholesky(A),
            "solve_triangular k cols": lambda: torch.linalg.solve_triangular(L, V, upper=False),
            "small_solve_lower k cols": lambda: linalg.small_solve_lower(L, V),
            "solve_triangular 1 col": lambda: torch.linalg.solve_triangular(L, v, upper=False),
            "small_solve_lower 1 col": lambda: linalg.small_solve_lower(L, v),
            "cholesky_solve k cols": lambda: torch.cholesky_solve(V, L),
            "bmm k x k": lambda: A @ V,
            "mul+add (elementwise)": lambda: A * 2.0 + V,
        }
        err_c = (linalg.small_cholesky(A) - L).abs().max().item()
        err_s = (linalg.small_solve_lower(L, V) - torch.linalg.solve_triangular(L, V, upper=False)).abs().max().item()
        for name, fn in ops.items():
            rows.append(dict(k=k, op=name, us=_time(fn, a.reps, sync)))
        print(f"k = {k}: small_cholesky max |diff| {err_c:.2e}, small_solve_lower {err_s:.2e}")
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    print(f"{name}, {a.dtype}, batch {a.batch}: microseconds per call")
    for r in rows:
        print(f"  k={r['k']:3d}  {r['op']:28s} {r['us']:10.1f}")
    return dict(rows=rows)


if __name__ == "__main__":
    run()
