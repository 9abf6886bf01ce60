"""The GPU goals in one table (``run_all --device cuda`` runs it; any device works, the goals
are stated for an H100/H200):

* PF-PF(LEDH) on Pal & Coates (2019) Table II's setting (acoustic, sigma_w = 0.1, N = 500, 40 steps, float64)
  for each ``--trials`` count in one call (``chunk = trials``, per-trial streams as the runner):
  wall seconds of the call, after an untimed warm-up of the same shape; goals: 100 trials under
  0.5 s, 500 trials under 2 s, and the cost per trial-step flat or falling as trials grow (met when
  the largest count's cost is at most 1.05x the smallest's: 5 % for timing noise);
* the bootstrap PF against PyDPF (``peer_pydpf_bpf.compare``: SensorNetwork d = 64, float32, 100
  trials x 10 steps) at every ``--bpf-ns``; goal: PyDPF's time / ours >= 1 at each N. PyDPF needs
  Python >= 3.12: without it the rows say ``skipped``;
* GPFIS against PF-PF(LEDH) at ``--gpfis-trials`` trials (the same setting, ``--gpfis-steps``
  steps): time per trial-step of each in one process; goal: GPFIS <= 5x PF-PF(LEDH) (the CPU
  goal, recorded here for the GPU; ``--gpfis-trials 0``: none);
* the CUDA contract tests (``pytest -k cuda`` over the contract, graph and fused-kernel
  tests, in a subprocess): goal: all pass (on a machine without CUDA they skip: no verdict).

    python -m experiments.benchmarks.bench_gpu --device cuda
    python -m experiments.benchmarks.bench_gpu --quick --device cpu      # the plumbing, on a CPU

``--fused`` sets ``tuning.fused_flows`` for the run (default: as it is). Each PF-PF(LEDH) row also
gives the first call's wall time (``first``: the warm-up, with the CUDA graph capture and, in a fresh
process, the kernels' compilation or loading), as a runner's single chunk pays it.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time

import torch

from torchflow.core import tuning
from torchflow.models import AcousticTracking

from . import harness as h
from . import peer_pydpf_bpf as peer

LEDH_GOALS = {100: 0.5, 500: 2.0}
GPFIS_GOAL = 5.0
FLAT = 1.05
CUDA_TESTS = [
    "tests/flows/test_fused.py",
    "tests/test_cudagraphs.py",
    "tests/filters/test_contract.py",
    "tests/test_random.py",
    "tests/test_bad_inputs.py",
    "tests/test_philox_fused.py",
]


def _sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def ledh_rows(device, trials_list, particles, steps, dtype, reps, seed=0, key="ledh", label="PF-PF(LEDH)") -> list:
    """PF-PF(LEDH)'s (or ``key``'s) wall time per call of ``B`` trials (one chunk), each ``B`` of ``trials_list``."""
    model = AcousticTracking(sigma_w=0.1).to(dtype=dtype)
    traj, mean, cov = h.simulate(model, max(trials_list), steps, seed)  # on the CPU (its generator), then moved
    model = model.to(device=device)
    traj_obs, mean, cov = traj.observations.to(device), mean.to(device), cov.to(device)
    f = h.make_filter(key, model, particles)
    rows = []
    for B in trials_list:
        obs, m, c = traj_obs[:B], mean[:B], cov[:B]

        def call():
            with torch.no_grad():
                f(obs, m, c, h.streams(seed + 1, f.stream_name)(0, B))
            _sync(device)

        t0 = time.perf_counter()
        call()  # warm-up: the same shapes (CUDA graphs are captured here)
        first = time.perf_counter() - t0
        best = float("inf")
        for _ in range(reps):
            t0 = time.perf_counter()
            call()
            best = min(best, time.perf_counter() - t0)
        goal = LEDH_GOALS.get(B) if key == "ledh" else None
        rows.append(
            dict(
                name=f"{label} {B} x {particles} x {steps}",
                trials=B,
                wall=best,
                first=first,
                per_ts=best / (B * steps),
                goal=goal,
                met=None if goal is None else best < goal,
            )
        )
        print(rows[-1], flush=True)
    return rows


def contract_tests(extra=()) -> dict:
    """Run the CUDA contract tests in a subprocess; their pass/skip/fail counts."""
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *CUDA_TESTS, "-k", "cuda", *extra]
    out = subprocess.run(cmd, capture_output=True, text=True).stdout
    counts = {
        k: int(n) for n, k in re.findall(r"(\d+) (passed|failed|skipped|error)", out.splitlines()[-1] if out else "")
    }
    return dict(
        passed=counts.get("passed", 0),
        failed=counts.get("failed", 0) + counts.get("error", 0),
        skipped=counts.get("skipped", 0),
        tail=out.splitlines()[-1] if out else "",
    )


def run(argv=None) -> dict:
    a = h.options(
        __doc__,
        argv,
        dict(
            trials="2,4",
            particles=30,
            steps=3,
            bpf_ns="50,200",
            bpf_trials=4,
            bpf_steps=3,
            reps=1,
            tests=False,
            gpfis_trials=2,
            gpfis_steps=2,
        ),
        device="cuda" if torch.cuda.is_available() else "cpu",
        trials="100,500",
        particles=500,
        steps=40,
        dtype="float64",
        reps=2,
        bpf_ns="200,1000,10000,100000",
        bpf_trials=100,
        bpf_steps=10,
        bpf_d=64,
        tests=True,
        gpfis_trials=100,
        gpfis_steps=5,
        fused=-1,
    )
    device = torch.device(a.device)
    knobs = {} if a.fused < 0 else dict(fused_flows=int(a.fused))
    with h.session("bench_gpu", argv, device=device) as info, tuning.tuned(**knobs):
        rows = ledh_rows(device, h.ints(a.trials, "--trials"), a.particles, a.steps, getattr(torch, a.dtype), a.reps)
        flat = rows[-1]["per_ts"] / rows[0]["per_ts"]
        rows.append(
            dict(
                name=f"PF-PF(LEDH) cost per trial-step, {rows[-1]['trials']} / {rows[0]['trials']} trials",
                ratio=flat,
                goal=f"<= {FLAT}",
                met=flat <= FLAT if len(rows) > 1 else None,
            )
        )
        if a.gpfis_trials > 0:  # 0: no GPFIS rows
            pair = [
                ledh_rows(
                    device,
                    [a.gpfis_trials],
                    a.particles,
                    a.gpfis_steps,
                    getattr(torch, a.dtype),
                    a.reps,
                    key=key,
                    label=label,
                )[0]
                for key, label in (("ledh", "PF-PF(LEDH)"), ("gpfis", "GPFIS"))
            ]
            vs = pair[1]["per_ts"] / pair[0]["per_ts"]
            rows += [
                pair[1],
                dict(
                    name=f"GPFIS / PF-PF(LEDH) per trial-step, {a.gpfis_trials} trials x {a.gpfis_steps} steps",
                    ratio=vs,
                    goal=f"<= {GPFIS_GOAL}x",
                    met=vs <= GPFIS_GOAL,
                ),
            ]
        bpf = []
        if peer.pydpf_available():
            try:  # a failing comparison must not lose the rows above
                for r in peer.compare(
                    device, h.ints(a.bpf_ns, "--bpf-ns"), a.bpf_trials, a.bpf_steps, a.bpf_d, torch.float32, a.reps
                ):
                    ratio = None if r["PyDPF"] is None else r["PyDPF"] / r["torchflow"]
                    bpf.append(
                        dict(
                            name=f"BPF vs PyDPF, N = {r['N']}",
                            per_ts=r["torchflow"],
                            peer=r["PyDPF"],
                            ratio=ratio,
                            goal=">= 1x",
                            met=None if ratio is None else ratio >= 1,
                            error=r.get("PyDPF error"),
                        )
                    )
            except Exception as exc:
                bpf.append(
                    dict(
                        name="BPF vs PyDPF",
                        status=f"FAILED: {type(exc).__name__}: {str(exc)[:300]}",
                        goal=">= 1x",
                        met=False,
                    )
                )
        else:
            bpf.append(
                dict(
                    name="BPF vs PyDPF",
                    status="skipped: PyDPF not importable (needs Python >= 3.12 and pydpf)",
                    goal=">= 1x",
                    met=None,
                )
            )
        rows += bpf
        if a.tests:
            t = contract_tests()
            ran = t["passed"] + t["failed"]
            rows.append(
                dict(
                    name="CUDA contract tests",
                    status=t["tail"],
                    goal="all pass",
                    met=(t["failed"] == 0) if ran else None,
                )
            )
    cells = []
    for r in rows:
        ours = r.get("wall") if "wall" in r else r.get("per_ts")
        cells.append(
            [
                r["name"],
                h.fmt(ours, "{:.4g}"),
                h.fmt(r.get("first"), "{:.3g}"),
                h.fmt(r.get("peer"), "{:.4g}"),
                h.fmt(r.get("ratio"), "{:.2f}"),
                h.fmt(r.get("goal"), "< {} s" if isinstance(r.get("goal"), float) else "{}"),
                h.met_cell(r.get("met")),
                r.get("status") or r.get("error") or "",
            ]
        )
    md = h.report(
        "## GPU goals",
        a,
        info,
        [
            f"Device {device}; PF-PF(LEDH): acoustic sigma_w = 0.1, N = {a.particles}, {a.steps} steps, {a.dtype}, "
            f"one call per trial count (best of {a.reps} after a warm-up); BPF: SensorNetwork d = {a.bpf_d}, "
            f"float32, {a.bpf_trials} trials x {a.bpf_steps} steps. tuning.fused_flows = "
            f"{knobs.get('fused_flows', tuning.get().fused_flows)}; `first`: the first call's wall time "
            f"(warm-up: graph capture, kernel loading), seconds."
        ],
        [
            "benchmark",
            "ours (s; PF-PF(LEDH): per call, BPF: per trial-step)",
            "first",
            "PyDPF s/trial-step",
            "ratio",
            "goal",
            "met",
            "note",
        ],
        cells,
    )
    return dict(rows=rows, markdown=md, machine=info, args=vars(a))


if __name__ == "__main__":
    h.main(run, "gpu")
