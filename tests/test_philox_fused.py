"""The Triton Philox4x32 kernel of per-trial random streams (torchflow.core.random.philox4x32_fused)
gives the bits of the torch-op Philox, and TrialStreams draw the same numbers with and without it:
on the CPU through Triton's interpreter (a subprocess with TRITON_INTERPRET=1; skipped where Triton
is not installed, as in CI), on CUDA with the compiled kernel."""

import json
import os
import subprocess
import sys
import textwrap

import pytest
import torch
from conftest import ROOT, cuda

from torchflow.core import random as R

CHECK = textwrap.dedent("""
    import json, sys
    import numpy as np
    import torch
    from torchflow.core import linalg, tuning
    from torchflow.core import random as R

    device = sys.argv[1]
    keys = torch.tensor(np.random.default_rng(0).integers(0, 2**32, size=(5, 2)), dtype=torch.int64, device=device)
    bits = {}
    for counter, blocks in ((0, 7), (2**32 - 3, 9), (123456789012, 300), (5, 0)):
        got = R.philox4x32_fused(keys, counter, blocks)
        ctr = counter + torch.arange(blocks, dtype=torch.int64, device=device)
        zero = torch.zeros(5, blocks, dtype=torch.int64, device=device)
        want = R.philox4x32([(ctr & 0xFFFFFFFF).expand(5, blocks), (ctr >> 32).expand(5, blocks), zero, zero],
                            (keys[:, :1].expand(5, blocks), keys[:, 1:].expand(5, blocks)))
        bits[f"{counter}+{blocks}"] = bool(torch.equal(got, want.reshape(5, blocks, 4)))
    draws = {}
    for dtype in (torch.float64, torch.float32):
        s1 = R.TrialStreams(3, 4, key="bpf", backend="philox")
        s2 = R.TrialStreams(3, 4, key="bpf", backend="philox")
        fused = [R._philox_fusable(device)]
        a = [linalg.standard_normal((4, 51, 3), dtype=dtype, device=device, generator=s1),
             R.uniform((4, 33), dtype=dtype, device=device, generator=s1)]
        with tuning.tuned(fused_philox=0):
            fused.append(R._philox_fusable(device))
            b = [linalg.standard_normal((4, 51, 3), dtype=dtype, device=device, generator=s2),
                 R.uniform((4, 33), dtype=dtype, device=device, generator=s2)]
        draws[str(dtype)] = dict(fused=fused, equal=[bool(torch.equal(x, y)) for x, y in zip(a, b)],
                                 counters=[s1._counter, s2._counter])
    print("RESULT" + json.dumps(dict(bits=bits, draws=draws)))
""")


def _check(device, env=None):
    out = subprocess.run(
        [sys.executable, "-c", CHECK, device],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, **(env or {})},
        timeout=600,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.split("RESULT")[-1])


def _assert_same(res):
    assert all(res["bits"].values()), res["bits"]
    for dtype, r in res["draws"].items():
        assert r["fused"] == [True, False], f"{dtype}: the fused kernel was not taken (or not left): {r['fused']}"
        assert all(r["equal"]), f"{dtype}: draws differ with the fused Philox: {r}"
        assert r["counters"][0] == r["counters"][1] > 0


def test_fused_philox_gives_the_same_bits_in_triton_interpreter():
    pytest.importorskip("triton")
    _assert_same(_check("cpu", {"TRITON_INTERPRET": "1"}))


def test_not_fused_on_the_cpu_without_the_interpreter():
    """On the CPU TrialStreams draw with numpy by default; a philox stream there uses the torch ops."""
    if os.environ.get("TRITON_INTERPRET", "0") not in ("", "0"):
        pytest.skip("this process runs Triton's interpreter")
    assert not R._philox_fusable("cpu")
    s = R.TrialStreams(0, 2, backend="philox")
    assert R.uniform((2, 5), dtype=torch.float64, device="cpu", generator=s).shape == (2, 5)


def test_a_failing_kernel_falls_back_to_the_torch_ops_once(monkeypatch):
    """Where Triton cannot build the kernel, the draw warns once and uses the torch ops: the same
    numbers as without the kernel."""
    calls = []

    def broken(*a, **k):
        calls.append(1)
        raise RuntimeError("no compiler")

    monkeypatch.setattr(R, "_philox_broken", [])
    monkeypatch.setattr(R, "philox4x32_fused", broken)
    monkeypatch.setattr(R, "_philox_kernel", None)
    real = R._philox_fusable
    monkeypatch.setattr(R, "_philox_fusable", lambda device: not R._philox_broken)
    s1, s2 = R.TrialStreams(1, 3, backend="philox"), R.TrialStreams(1, 3, backend="philox")
    with pytest.warns(RuntimeWarning, match="fused Philox kernel failed"):
        a = R.uniform((3, 7), dtype=torch.float64, device="cpu", generator=s1)
    b = R.uniform((3, 7), dtype=torch.float64, device="cpu", generator=s1)  # no second warning, no second try
    monkeypatch.setattr(R, "_philox_fusable", real)
    from torchflow.core import tuning

    with tuning.tuned(fused_philox=0):
        want = [R.uniform((3, 7), dtype=torch.float64, device="cpu", generator=s2) for _ in range(2)]
    assert len(calls) == 1 and torch.equal(a, want[0]) and torch.equal(b, want[1])


@cuda
def test_fused_philox_gives_the_same_bits_on_cuda():
    pytest.importorskip("triton")
    _assert_same(_check("cuda"))
