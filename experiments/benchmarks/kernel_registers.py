"""Registers, spills and warp shuffles of the fused pseudo-step kernel (``torchflow.flows.kernels.gpu``)
compiled for an NVIDIA GPU, without one: Triton compiles for ``GPUTarget("cuda", arch, 32)`` on any
machine and its bundled ``ptxas -v`` reports what the kernel would use.

    python -m experiments.benchmarks.kernel_registers                 # sm_90 (H100/H200), both LIN
    python -m experiments.benchmarks.kernel_registers --arch 80 --warps 2 --dtype float32

One line per measurement kind (``LIN`` 0: W read from memory, 1: the acoustic measurement inside):
registers per thread, spill stores/loads and stack bytes per thread, warp shuffles in the PTX (each
a reduction split across threads: none is intended) and the PTX's length. On 2026-11-26 (sm_90,
float64, 1 warp): 255 registers, ~1.2-1.8 KB of spill stores, 0 shuffles; the first version of the
kernel: 168 registers, 17.7 KB of spill stores, 1,728 shuffles.
"""

from __future__ import annotations

import argparse
import inspect
import os
import re
import subprocess
import tempfile

#: pointer arguments of ``kernel_rows`` that hold the state's dtype (the rest: float64 or int64)
_STATE_PTRS = ("W", "Y", "Lp", "LS", "PC", "MEAN", "ETA", "AUX", "ETA_OUT", "AUX_OUT", "LOGDET", "SENS")
#: pointer arguments of ``kernel_info`` that are float64 whatever the state's dtype (formed once per integration)
_F64_PTRS = ("C", "PI", "LAMS", "EPSS", "CONST")


def measure(
    lin: int = 0,
    warps: int = 1,
    arch: int = 90,
    dtype: str = "float64",
    bk: int = 8,
    bd: int = 16,
    layout: str = "rows",
    compute: str = "float64",
) -> dict:
    """Compile ``kernel_<layout>`` (``rows`` or ``info``) for ``sm_<arch>`` with its state in
    ``dtype`` and its arithmetic in ``compute`` (``tuning.kernel_float32``: ``float32`` for a
    float32 state) and read its resources: ``registers``, ``spill_stores``, ``spill_loads``,
    ``stack`` (bytes per thread), ``shuffles``, ``ptx_lines``."""
    import torch
    import triton
    import triton.language as tl
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    from torchflow.flows.kernels import gpu as _fused_kernel

    kernel_rows = getattr(_fused_kernel, "kernel_" + layout)
    names = list(inspect.signature(kernel_rows.fn).parameters)
    ct = torch.float32 if compute == "float32" else torch.float64
    const = {
        "BK": bk,
        "BD": bd,
        "BP": 32 * warps,
        "LIN": lin,
        "DT": tl.float32 if compute == "float32" else tl.float64,
        "TINY": float(torch.finfo(ct).tiny),
    }
    ptr = "*fp64" if dtype == "float64" else "*fp32"
    sig = {
        n: "constexpr"
        if n in const
        else "*i64"
        if n == "SUP"
        else ptr
        if n in _STATE_PTRS
        else "*fp64"
        if n in _F64_PTRS
        else "i32"
        for n in names
    }
    src = ASTSource(fn=kernel_rows, signature=sig, constexprs={(names.index(k),): v for k, v in const.items()})
    compiled = triton.compile(src, target=GPUTarget("cuda", arch, 32), options={"num_warps": warps})
    ptx = compiled.asm["ptx"]
    ptxas = os.path.join(os.path.dirname(triton.__file__), "backends", "nvidia", "bin", "ptxas")
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "k.ptx")
        with open(path, "w") as fh:
            fh.write(ptx)
        out = subprocess.run(
            [ptxas, f"-arch=sm_{arch}{'a' if arch == 90 else ''}", "-v", path, "-o", os.path.join(tmp, "k.cubin")],
            capture_output=True,
            text=True,
            check=True,
        )
    info = out.stdout + out.stderr
    num = lambda pattern: int(re.search(pattern, info).group(1))
    return dict(
        registers=num(r"Used (\d+) registers"),
        spill_stores=num(r"(\d+) bytes spill stores"),
        spill_loads=num(r"(\d+) bytes spill loads"),
        stack=num(r"(\d+) bytes stack frame"),
        shuffles=ptx.count("shfl.sync"),
        ptx_lines=ptx.count("\n"),
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--arch", type=int, default=90)
    ap.add_argument("--warps", type=int, default=1)
    ap.add_argument("--dtype", default="float64", choices=("float64", "float32"))
    ap.add_argument(
        "--compute",
        default="float64",
        choices=("float64", "float32"),
        help="the kernel's arithmetic (float32: tuning.kernel_float32=1 on a float32 run)",
    )
    ap.add_argument("--layout", default="info,rows", help="the kernels' forms, comma-separated (info, rows)")
    a = ap.parse_args(argv)
    for layout in a.layout.split(","):
        for lin in (0, 1):
            r = measure(lin, a.warps, a.arch, a.dtype, layout=layout, compute=a.compute)
            print(
                f"kernel_{layout}, sm_{a.arch}, {a.dtype} ({a.compute} arithmetic), {a.warps} warp(s), LIN={lin}: "
                + ", ".join(f"{k} {v}" for k, v in r.items())
            )


if __name__ == "__main__":
    main()
