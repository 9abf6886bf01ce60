"""Aten ops per time step of the flow filters, counted on the CPU with a
``TorchDispatchMode`` (:class:`torchflow.core.profiling.OpCounter`) over one time step (the second) on
acoustic tracking: on a GPU each op is a dispatch and most are a kernel launch. At per-particle
points the counts do not depend on the trials or particles (PF-PF(LEDH): the same at 2 x 20 as at
4 x 100), only on the code and the 29 pseudo-steps of the default schedule; a global flow (EDH)
composes its maps on d x d matrices when that is cheaper, so its count depends on N (3,933 here,
3,996 at 4 x 100).

Two kinds of test:

* budgets: the counts may not grow past what they are now (2 % slack for small, deliberate
  changes). Before the pseudo-steps were cut down (same set-up): PF-PF(LEDH) 5,103, PF-PF(EDH) 5,279,
  PF-PF(Gromov) 5,576, GPFIS 17,901 (17,054 before its step Jacobian was written out). A change that adds ops to the
  pseudo-step fails here and must
  either remove them or raise the budget with a reason.
* the op targets (PF-PF(LEDH) <= 1,000, PF-PF(Gromov) <= 1,500, GPFIS <= 3,000): all three
  meet theirs on the CPU's default path where Numba is installed (the fused pseudo-steps,
  :mod:`torchflow.flows.kernels.steps`: 506, 717 and 229 ops; GPFIS's whole flow is one kernel call); the
  eager path's do not: strict ``xfail``, so meeting one fails the test until it is made a plain
  assertion.

The budgets are counted on the eager (torch) path (``tuning.fused_flows=0``), the same on every
machine; the fused path's have their own budgets (skipped without Numba).
"""

import pytest
import torch

from experiments.benchmarks.bench_ops import count, filters
from torchflow.core import tuning
from torchflow.models import AcousticTracking

#: ops per time step on the CPU's default path, measured when the budgets were set
BUDGET = {
    "PF-PF(LEDH)": 3820,
    "PF-PF(EDH)": 3933,
    "PF-PF(Gromov)": 4178,
    "PF-PF(geodesic)": 3559,
    "PF-PF(OSD)": 5830,
    "GPFIS": 7696,
    "clustered PF-PF": 4379,
    "flow filter (LEDH)": 4051,
    "PFGSPF (2 components)": 4136,
}
#: ops per time step on the CPU's default path with Numba (the fused EDH/LEDH pseudo-step)
FUSED_BUDGET = {
    "PF-PF(LEDH)": 506,
    "flow filter (LEDH)": 368,
    "PFGSPF (2 components)": 467,
    "PF-PF(Gromov)": 717,
    "GPFIS": 229,
}
TARGET = {"PF-PF(LEDH)": 1000, "PF-PF(Gromov)": 1500, "GPFIS": 3000}
SLACK = 1.02
EAGER = dict(fused_flows=0)


@pytest.fixture(scope="module")
def setting():
    model = AcousticTracking()
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(2, 2, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    return model, traj.observations, mean, cov, filters(model, 20)


@pytest.mark.parametrize("name", sorted(BUDGET))
def test_ops_per_step_within_budget(setting, name):
    model, obs, mean, cov, fs = setting
    with tuning.tuned(**EAGER):
        ops = count(fs[name], obs, mean, cov, False).ops
    assert ops <= BUDGET[name] * SLACK, f"{name}: {ops} aten ops per time step, budget {BUDGET[name]}"
    assert ops > 0.5 * BUDGET[name], f"{name}: {ops} ops, far below the budget {BUDGET[name]}: lower the budget"


@pytest.mark.parametrize("name", sorted(FUSED_BUDGET))
def test_fused_cpu_path_ops_within_budget(setting, name):
    pytest.importorskip("numba")
    model, obs, mean, cov, fs = setting
    with tuning.tuned(fused_flows=1):
        ops = count(fs[name], obs, mean, cov, False).ops
    assert ops <= FUSED_BUDGET[name] * SLACK, f"{name}: {ops} aten ops per time step, budget {FUSED_BUDGET[name]}"
    assert ops > 0.5 * FUSED_BUDGET[name], f"{name}: {ops} ops, far below the budget: lower it"


def test_counts_do_not_depend_on_trials_or_particles(setting):
    model, obs, mean, cov, _ = setting
    g = torch.Generator().manual_seed(1)
    traj = model.simulate(3, 2, g)
    m3, c3 = model.initial_belief(traj.states[:, 0], g)
    small = count(filters(model, 20)["PF-PF(LEDH)"], obs, mean, cov, False).ops
    other = count(filters(model, 35)["PF-PF(LEDH)"], traj.observations, m3, c3, False).ops
    assert small == other


@pytest.mark.parametrize("name", sorted(TARGET))
@pytest.mark.xfail(strict=True, reason="the op targets are not met on the eager path")
def test_op_targets_eager(setting, name):
    model, obs, mean, cov, fs = setting
    with tuning.tuned(**EAGER):
        assert count(fs[name], obs, mean, cov, False).ops <= TARGET[name]


@pytest.mark.parametrize("name", ["PF-PF(LEDH)", "PF-PF(Gromov)", "GPFIS"])
def test_op_targets_on_the_fused_cpu_path(setting, name):
    """PF-PF(LEDH) <= 1,000, PF-PF(Gromov) <= 1,500 and GPFIS <= 3,000 aten ops per time step on the
    CPU with Numba (the default there: their pseudo-steps are one kernel each; GPFIS's whole flow
    one call)."""
    pytest.importorskip("numba")
    model, obs, mean, cov, fs = setting
    with tuning.tuned(fused_flows=1):
        assert count(fs[name], obs, mean, cov, False).ops <= TARGET[name]
