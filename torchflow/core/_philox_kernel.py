"""The Triton kernel of :func:`torchflow.core.random.philox4x32_fused` (imported only when it is used:
Triton is an optional dependency). One program handles ``BLOCK`` (trial, counter) pairs; each runs
the 10 Philox4x32 rounds in 32-bit integer registers."""

import triton
import triton.language as tl


@triton.jit
def philox_kernel(key_ptr, out_ptr, ctr0, blocks, total, ROUNDS: tl.constexpr, BLOCK: tl.constexpr):
    """``out[b, j, :] = philox4x32((ctr0 + j) as (lo, hi, 0, 0), keys[b])``; ``key_ptr`` (B, 2) and
    ``out_ptr`` (B, blocks, 4) int64 holding 32-bit words."""
    idx = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK).to(tl.int64)
    mask = idx < total
    b = idx // blocks
    ctr = ctr0 + idx % blocks
    c0 = (ctr & 0xFFFFFFFF).to(tl.uint32)
    c1 = ((ctr >> 32) & 0xFFFFFFFF).to(tl.uint32)
    c2 = tl.zeros_like(c0)
    c3 = tl.zeros_like(c0)
    k0 = tl.load(key_ptr + 2 * b, mask=mask, other=0).to(tl.uint32)
    k1 = tl.load(key_ptr + 2 * b + 1, mask=mask, other=0).to(tl.uint32)
    m0 = tl.full(c0.shape, 0xD2511F53, tl.uint32)
    m1 = tl.full(c0.shape, 0xCD9E8D57, tl.uint32)
    w0 = tl.full(c0.shape, 0x9E3779B9, tl.uint32)
    w1 = tl.full(c0.shape, 0xBB67AE85, tl.uint32)
    for r in tl.static_range(ROUNDS):
        hi0, lo0 = tl.umulhi(c0, m0), c0 * m0
        hi1, lo1 = tl.umulhi(c2, m1), c2 * m1
        c0, c1, c2, c3 = hi1 ^ c1 ^ k0, lo1, hi0 ^ c3 ^ k1, lo0
        k0 = k0 + w0
        k1 = k1 + w1
    base = out_ptr + 4 * idx
    tl.store(base, c0.to(tl.int64), mask=mask)
    tl.store(base + 1, c1.to(tl.int64), mask=mask)
    tl.store(base + 2, c2.to(tl.int64), mask=mask)
    tl.store(base + 3, c3.to(tl.int64), mask=mask)
