"""CUDA graph capture of the deterministic flows' loop (torchflow.core.cudagraphs, tuning.cuda_graphs).

On the CPU the capture is emulated (the "graph" re-runs the function on the static buffers), which
checks the plumbing: the function reads only its static inputs, outputs are cloned, keys capture
what they must, a failed capture falls back to eager once, and that the captured function makes no
tensor from host data and reads nothing back (what a real capture refuses). On CUDA the real
capture is compared with the eager run."""

import traceback
import warnings

import pytest
import torch
from conftest import cuda
from torch.utils._python_dispatch import TorchDispatchMode

from torchflow.core import cudagraphs, tuning
from torchflow.filters import ClusteredParticleFlowParticleFilter, ParticleFlowParticleFilter
from torchflow.flows import select
from torchflow.flows.schedules import ExponentialSchedule
from torchflow.models import AcousticTracking


class _CaptureRules(TorchDispatchMode):
    """What a real CUDA capture refuses, on the CPU: a tensor made from host data inside the captured
    function (``torch.tensor``, ``new_tensor``, a list index: on a GPU a copy from the host) and a
    read back to the host (``.item()``, ``bool(t)``, ``nonzero``)."""

    REFUSED = {
        "aten.lift_fresh.default": "Cannot copy between CPU and CUDA tensors during CUDA graph capture",
        "aten._local_scalar_dense.default": "operation not permitted when stream is capturing",
        "aten.nonzero.default": "operation not permitted when stream is capturing",
    }

    #: the CPU kernels' results come back through ``torch.from_numpy`` (a CPU-only path: on a GPU
    #: the Triton kernels run instead)
    CPU_ONLY = ("_cpu_back",)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if str(func) in self.REFUSED and not any(f.name in self.CPU_ONLY for f in traceback.extract_stack()):
            raise RuntimeError(f"{self.REFUSED[str(func)]} ({func}, emulated)")
        return func(*args, **(kwargs or {}))


class _Emulated:
    """A stand-in for CUDA capture: replay re-runs the function on the captured static buffers, as a
    GPU runs it (``tuning``: no host reads, the batched jitter ladder) and under the capture's rules
    (:class:`_CaptureRules`)."""

    def __init__(self, fail=False):
        self.fail, self.calls = fail, 0

    def warmup(self, fn, inputs):  # eager, as on a GPU (its caches, e.g. the jitter ladder, are made here)
        with tuning.tuned(host_reads_cpu=0, batched_jitter_cpu=1):
            return tuple(fn(*inputs))

    @staticmethod
    def _as_captured(fn, views):
        with tuning.tuned(host_reads_cpu=0, batched_jitter_cpu=1), _CaptureRules():
            return tuple(fn(*views))

    def capture(self, fn, views):
        if self.fail:
            raise RuntimeError("operation not permitted when stream is capturing")
        static_out = self._as_captured(fn, views)

        def replay():
            self.calls += 1
            for o, n in zip(static_out, self._as_captured(fn, views)):
                if o is not None:
                    cudagraphs._compact(o).copy_(cudagraphs._compact(n))

        return replay, static_out


@pytest.fixture
def emulated(monkeypatch):
    backend = _Emulated()
    monkeypatch.setattr(cudagraphs, "_backend", backend)
    monkeypatch.setattr(
        select,
        "flow_graph",
        lambda flow, particles: not flow.stochastic and not torch.is_grad_enabled() and bool(tuning.get().cuda_graphs),
    )
    cudagraphs.clear()
    yield backend
    cudagraphs.clear()


def _run(f, model, seed=0, B=3, T=5):
    g = torch.Generator().manual_seed(seed)
    traj = model.simulate(B, T, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    with torch.no_grad():
        return f(traj.observations, mean, cov, torch.Generator().manual_seed(seed + 1))


FILTERS = {
    "ledh": lambda m: ParticleFlowParticleFilter(m, flow="ledh", n_particles=40, schedule=ExponentialSchedule(8, 1.3)),
    "edh": lambda m: ParticleFlowParticleFilter(m, flow="edh", n_particles=40, schedule=ExponentialSchedule(8, 1.3)),
    "geodesic": lambda m: ParticleFlowParticleFilter(
        m, flow="geodesic", n_particles=40, schedule=ExponentialSchedule(8, 1.3)
    ),
    "clustered": lambda m: ClusteredParticleFlowParticleFilter(
        m, n_particles=40, n_clusters=5, schedule=ExponentialSchedule(8, 1.3)
    ),
}


@pytest.mark.parametrize("name", list(FILTERS))
def test_replayed_flow_gives_the_eager_numbers(emulated, name):
    """Captured once, replayed at every later step: bit for bit the eager filter's numbers."""
    model = AcousticTracking()
    with tuning.tuned(cuda_graphs=0):
        eager = _run(FILTERS[name](model), model)
    before = cudagraphs.stats()
    graphed = _run(FILTERS[name](model), model)
    after = cudagraphs.stats()
    assert after["captures"] - before["captures"] == 1  # one shape: captured once
    assert after["replays"] - before["replays"] == 4 and emulated.calls == 4  # the other 4 steps replay
    assert torch.equal(graphed.estimates, eager.estimates)
    assert torch.equal(graphed.log_evidence, eager.log_evidence)


def test_gradient_or_stochastic_flows_run_eagerly(emulated):
    model = AcousticTracking()
    f = ParticleFlowParticleFilter(model, flow="gromov", n_particles=20, schedule=ExponentialSchedule(5, 1.3))
    _run(f, model, T=3)
    assert cudagraphs.stats()["cached"] == 0  # stochastic: never captured
    f = FILTERS["ledh"](model)
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(2, 3, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    with warnings.catch_warnings():  # the filter says once that the reference path runs
        warnings.simplefilter("ignore")
        f(traj.observations, mean.clone().requires_grad_(True), cov, g)  # a gradient: eager, autograd sees the loop
    assert cudagraphs.stats()["cached"] == 0


def test_model_state_is_part_of_the_key(emulated):
    """A reassigned tensor attribute (a new address the graph would not read) or a changed scalar
    attribute gives a new capture; the replayed numbers follow the new model."""
    model = AcousticTracking()
    f = FILTERS["ledh"](model)
    _run(f, model, T=3)
    n0 = cudagraphs.stats()["captures"]
    model.sensors = model.sensors.clone() + 1.0
    res = _run(f, model, T=3)
    assert cudagraphs.stats()["captures"] == n0 + 1
    with tuning.tuned(cuda_graphs=0):
        eager = _run(FILTERS["ledh"](model), model, T=3)
    assert torch.equal(res.estimates, eager.estimates)


def test_state_key_sees_tensors_and_scalars():
    model = AcousticTracking()
    k0 = cudagraphs.state_key(model)
    assert cudagraphs.state_key(model) == k0
    model.sensors = model.sensors.clone()
    k1 = cudagraphs.state_key(model)
    assert k1 != k0
    model.d0 = model.d0 * 2
    assert cudagraphs.state_key(model) != k1


def test_failed_capture_falls_back_once_with_a_warning(monkeypatch):
    monkeypatch.setattr(cudagraphs, "_backend", _Emulated(fail=True))
    monkeypatch.setattr(cudagraphs, "_warned", set())
    cudagraphs.clear()
    x = torch.arange(6.0).reshape(2, 3)
    with pytest.warns(RuntimeWarning, match=r"f: CUDA graph capture failed \(RuntimeError: operation not permitted"):
        out = cudagraphs.graphed("k", lambda a: (a * 2,), (x,), name="f")
    assert torch.equal(out[0], x * 2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no second warning, no second attempt
        out = cudagraphs.graphed("k", lambda a: (a * 3,), (x,), name="f")
    assert torch.equal(out[0], x * 3) and cudagraphs.stats()["cached"] == 0
    cudagraphs.clear()


def test_broadcast_inputs_stay_compact(emulated):
    """A stride-0 (expanded) input is stored once, expanded in the graph the same way."""
    base = torch.randn(1, 3, 2)
    seen = []

    def fn(a):
        seen.append(a.stride())
        return (a.sum(-1),)

    cudagraphs.graphed("b", fn, (base.expand(5, 3, 2),))
    static = cudagraphs._cache[next(reversed(cudagraphs._cache))].static_in[0]
    assert static.shape == (1, 3, 2) and seen[-1][0] == 0
    new = torch.randn(1, 3, 2)
    out = cudagraphs.graphed("b", fn, (new.expand(5, 3, 2),))
    assert torch.equal(out[0], new.expand(5, 3, 2).sum(-1))


def test_cache_is_bounded(emulated, monkeypatch):
    monkeypatch.setattr(cudagraphs, "max_graphs", 2)
    for n in range(1, 5):
        cudagraphs.graphed("c", lambda a: (a + 1,), (torch.zeros(n),))
    assert cudagraphs.stats()["cached"] == 2


def test_knob_is_validated():
    with pytest.raises(ValueError, match="tuning.cuda_graphs: expected an integer >= 0"):
        tuning.set(cuda_graphs=-1)


@cuda
@pytest.mark.parametrize("name", list(FILTERS))
def test_cuda_graph_matches_eager(name):
    """The real capture on a GPU: the replayed steps give the eager numbers (same kernels)."""
    cudagraphs.clear()
    model = AcousticTracking().to(device="cuda")

    def run():
        g = torch.Generator(device="cuda").manual_seed(0)
        traj = model.simulate(4, 6, g)
        mean, cov = model.initial_belief(traj.states[:, 0], g)
        with torch.no_grad():
            return FILTERS[name](model)(traj.observations, mean, cov, torch.Generator(device="cuda").manual_seed(1))

    with tuning.tuned(cuda_graphs=0):
        eager = run()
    before = cudagraphs.stats()
    graphed = run()
    after = cudagraphs.stats()
    assert after["failures"] == before["failures"], "capture failed"
    assert after["replays"] - before["replays"] >= 5
    torch.testing.assert_close(graphed.estimates, eager.estimates, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(graphed.log_evidence, eager.log_evidence, rtol=1e-9, atol=1e-9)
    cudagraphs.clear()
