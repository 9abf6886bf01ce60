"""The fused pseudo-step's variants side by side in one process (issue 30, GPU): PF-PF(LEDH) on
acoustic tracking, seconds per trial-step for ``tuning.fused_flows`` 0 (torch) and 1 (the fused
kernel, a particle per thread, with 1, 2 and 4 warps of 32 particles per program; with the acoustic
measurement linearised by torch, ``fused_measurement=0``, or inside the kernel, 1), each after its
own warm-up (``profile_step`` timing only). On an H100 (2026-11-26; a retired kernel with one program
per particle then took 0.071 s per time step): torch 0.095, fused 0.053, with the measurement inside
0.031, alike for 1, 2 and 4 warps. Prints one line per variant and, last,
``BEST fused=<f> measurement=<0|1> warps=<w>``; a variant that fails prints its error and is skipped.

    python -m experiments.benchmarks.ab_fused --device cuda --trials 100
"""
from __future__ import annotations

import sys

from . import profile_step


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    variants = [("1", "0", "1"), ("1", "0", "2"), ("1", "1", "1"), ("1", "1", "2"), ("1", "1", "4"), ("0", "0", "0")]
    best = None
    for fused, inside, warps in variants:
        try:
            r = profile_step.run(argv + ["--top", "0", "--fused", fused, "--fused-measurement", inside,
                                         "--rows-warps", warps])
        except Exception as exc:  # noqa: BLE001 - one failing variant must not hide the others
            print(f"fused={fused} measurement={inside} warps={warps}: FAILED {type(exc).__name__}: {str(exc)[:2000]}",
                  flush=True)
            continue
        if fused != "0" and (best is None or r["sec_per_trial_step"] < best[0]):
            best = (r["sec_per_trial_step"], fused, inside, warps)
    if best:
        print(f"BEST fused={best[1]} measurement={best[2]} warps={best[3]} ({best[0]:.3g} s per trial-step)")


if __name__ == "__main__":
    main()
