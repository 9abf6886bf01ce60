"""Reference cases: per-trial numbers of every filter, recorded so that a refactoring (the flow-layer
redesign) can be checked trial by trial against the numbers of the code before it.

    python -m tests.reference.cases          # rewrite per_trial.json (only when a change is meant
                                             # to change the numbers; say so in the commit)

The cases run through :func:`torchflow.app.runner.run_experiment`, so each trial draws from its own
random stream and the numbers do not depend on chunking.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from torchflow.app.runner import run_experiment
from torchflow.core import tuning
from torchflow.filters import (
    BootstrapParticleFilter,
    ExtendedKalmanFilter,
    KalmanFilter,
    ParticleFlowFilter,
    ParticleFlowParticleFilter,
    UnscentedKalmanFilter,
)
from torchflow.flows.schedules import ExponentialSchedule
from torchflow.models import AcousticTracking, SensorNetwork

HERE = Path(__file__).resolve().parent

FLOWS = ("edh", "ledh", "geodesic", "gromov", "osd")


def _filters(model, N, linear):
    sched = ExponentialSchedule(12, 1.2)
    out = {
        "ekf": ExtendedKalmanFilter(model),
        "ukf": UnscentedKalmanFilter(model),
        "bpf": BootstrapParticleFilter(model, n_particles=N),
    }
    if linear:
        out["kf"] = KalmanFilter(model)
    for fl in FLOWS:
        out[f"pfpf_{fl}"] = ParticleFlowParticleFilter(model, flow=fl, n_particles=N, schedule=sched)
        out[fl] = ParticleFlowFilter(model, flow=fl, n_particles=N, schedule=sched)
    return out


def cases():
    """``{case: (model, filters, run_experiment kwargs)}``."""
    lg = SensorNetwork(d=16)
    ac = AcousticTracking(sigma_w=0.1)
    return {
        "sensor_network_d16": (lg, _filters(lg, 40, True), dict(trials=5, steps=4, seed=1)),
        "acoustic_sigma0.1": (ac, _filters(ac, 40, False), dict(trials=3, steps=4, seed=2)),
    }


#: the flows' torch path (the same everywhere): the fused CPU kernel, taken by default where Numba is
#: installed, agrees with it to round-off per flow (tests/flows/test_fused.py), which a chaotic
#: trial amplifies past this test's tolerance
ARITHMETIC = dict(fused_flows=0)


def run_case(model, filters, kw):
    with tuning.tuned(**ARITHMETIC):
        res = run_experiment(model, filters, progress=False, **kw)
    errors = {r["filter"]: r["error"] for r in res.summary if r.get("error")}
    if errors:
        raise RuntimeError(f"reference filters failed: {errors}")
    return res.per_trial


def main():
    out = {name: run_case(*case) for name, case in cases().items()}
    meta = {"torch": torch.__version__, "note": "per-trial numbers, see tests/reference/cases.py"}
    (HERE / "per_trial.json").write_text(json.dumps({"meta": meta, "cases": out}, indent=0))
    print(f"wrote {HERE / 'per_trial.json'}: {sum(len(v) for v in out.values())} rows")


if __name__ == "__main__":
    main()
