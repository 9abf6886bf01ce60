"""The fused pseudo-step's variants side by side in one process (GPU): PF-PF(LEDH) on
acoustic tracking, seconds per trial-step for ``tuning.fused_flows`` 0 (torch) and 1 (the fused
kernel, a particle per thread, with 1 and 2 warps of 32 particles per program; with the acoustic
measurement linearised by torch, ``fused_measurement=0``, or inside the kernel, 1; in row form,
``fused_info=0``, or information form, 1), each after its
own warm-up (``profile_step`` timing only). On an H100 (2026-11-26; a retired kernel with one program
per particle then took 0.071 s per time step): torch 0.095, fused 0.053, with the measurement inside
0.031, alike for 1, 2 and 4 warps (4 is no longer a variant here). Prints one line per variant and, last,
``BEST <variant>``; a variant that fails prints its error and is skipped. ``--short``: the two
forms with the measurement inside and the torch path only.

    python -m experiments.benchmarks.ab_fused --device cuda --trials 100
"""

from __future__ import annotations

import sys

from . import profile_step


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    quick = "--short" in argv  # the two forms with the measurement inside, and the torch path
    variants = (
        ([] if quick else [("1", "0", "1", "1"), ("1", "0", "1", "0")])
        + [("1", "1", "1", "1"), ("1", "1", "1", "0")]
        + ([] if quick else [("1", "1", "2", "1"), ("1", "1", "2", "0")])
        + [("0", "0", "0", "0")]
    )
    best = None
    for fused, inside, warps, info in variants:
        name = f"fused={fused} measurement={inside} warps={warps} info={info}"
        try:
            r = profile_step.run(
                [x for x in argv if x != "--short"]
                + [
                    "--top",
                    "0",
                    "--fused",
                    fused,
                    "--fused-measurement",
                    inside,
                    "--rows-warps",
                    warps,
                    "--fused-info",
                    info,
                ]
            )
        except Exception as exc:
            print(f"{name}: FAILED {type(exc).__name__}: {str(exc)[:2000]}", flush=True)
            continue
        if fused != "0" and (best is None or r["sec_per_trial_step"] < best[0]):
            best = (r["sec_per_trial_step"], name)
    if best:
        print(f"BEST {best[1]} ({best[0]:.3g} s per trial-step)")


if __name__ == "__main__":
    main()
