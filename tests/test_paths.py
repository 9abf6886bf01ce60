"""Which execution path a filter ran (torchflow.core.paths): FilterResult.paths, the
runner's results.json ``paths`` and the summary's ``path`` column; recording moves no number."""

import json

import pytest
import torch
from conftest import cuda
from test_cudagraphs import _Emulated

from torchflow.app.runner import ChunkStore, format_table, run_experiment, writers
from torchflow.core import cudagraphs, paths, tuning
from torchflow.core.random import TrialStreams
from torchflow.filters import BootstrapParticleFilter, ParticleFlowParticleFilter, graph_step
from torchflow.flows import select
from torchflow.flows.kernels import steps
from torchflow.models import AcousticTracking, SensorNetwork, SkewedTPoisson

T = 3
#: a diagonal measurement too large for the lane tiles: LEDH takes the "diagonal" CPU kernel
KERNEL = "kernel:diagonal" if select.cpu_kernels_on("cpu") else "torch"
#: the bootstrap PF's steps on the CPU: weighed and resampled by the CPU kernel (tuning.fused_weights)
BPF_PATH = "kernel:weights" if steps.weights_available() else "torch"


def _data(model, B=2, steps=T, seed=0):
    g = torch.Generator().manual_seed(seed)
    traj = model.simulate(B, steps, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    return traj.observations, mean, cov


def _ledh(model):
    return ParticleFlowParticleFilter(model, flow="ledh", n_particles=8)


def test_pfpf_ledh_reports_its_kernel_and_the_torch_path_where_it_takes_it():
    model = SkewedTPoisson(d=25)
    obs, mean, cov = _data(model)
    f = _ledh(model)
    with torch.no_grad():
        fused = f(obs, mean, cov, torch.Generator().manual_seed(1))
        with tuning.tuned(fused_flows=0):
            plain = f(obs, mean, cov, torch.Generator().manual_seed(1))
    with pytest.warns(UserWarning, match="mean requires grad"):  # a gradient is recorded: no kernel, said once
        graded = f(obs, mean.clone().requires_grad_(True), cov, torch.Generator().manual_seed(1))
    assert f(obs, mean, cov, torch.Generator().manual_seed(1)).paths == {KERNEL: T}  # grad mode, nothing to record
    assert fused.paths == {KERNEL: T}
    assert plain.paths == {"torch": T} and graded.paths == {"torch": T}


def test_the_kernel_path_is_reported_when_numba_is_installed():
    pytest.importorskip("numba")
    assert KERNEL == "kernel:diagonal"  # the CPU kernels are on wherever Numba imports (fused_flows=1)


def test_bootstrap_pf_on_the_cpu_reports_its_weighting_kernel_or_torch():
    model = SkewedTPoisson(d=25)
    obs, mean, cov = _data(model)
    f = BootstrapParticleFilter(model, n_particles=8)
    with torch.no_grad():
        res = f(obs, mean, cov, torch.Generator().manual_seed(1))
        with tuning.tuned(fused_weights=0):
            plain = f(obs, mean, cov, torch.Generator().manual_seed(1))
    graded = f(obs, mean, cov, torch.Generator().manual_seed(1))  # no gradient is recorded: the kernel
    assert res.paths == {BPF_PATH: T} and graded.paths == {BPF_PATH: T}
    assert plain.paths == {"torch": T}


def test_recording_moves_no_number(monkeypatch):
    """The same call with every note and the per-step wrapper switched off gives the same bits."""
    model = SkewedTPoisson(d=25)
    obs, mean, cov = _data(model)
    f = _ledh(model)
    with torch.no_grad():
        recorded = f(obs, mean, cov, torch.Generator().manual_seed(1))
        monkeypatch.setattr(paths, "note", lambda path: None)
        monkeypatch.setattr(paths, "per_step", lambda step, counts: step)
        silent = f(obs, mean, cov, torch.Generator().manual_seed(1))
    assert recorded.paths == {KERNEL: T} and silent.paths == {}
    for name in ("estimates", "log_evidence", "log_evidence_increments", "ess"):
        assert torch.equal(getattr(recorded, name), getattr(silent, name)), name


def test_recording_counts_around_any_code_and_nests():
    model = SkewedTPoisson(d=25)
    obs, mean, cov = _data(model)
    assert not paths.listening()
    with paths.recording() as outer, torch.no_grad():
        with paths.recording() as inner:
            res = _ledh(model)(obs, mean, cov, torch.Generator().manual_seed(1))
        BootstrapParticleFilter(model, n_particles=8)(obs, mean, cov, torch.Generator().manual_seed(1))
    assert inner == res.paths == {KERNEL: T}
    assert outer == paths.merge(res.paths, {BPF_PATH: T})
    assert not paths.listening()
    assert paths.describe({"torch": 1, "graph:step": 5}) == "graph:step+torch" and paths.describe({}) is None


def test_a_replayed_graph_step_is_reported(monkeypatch):
    """With the capture emulated on the CPU (as in test_graph_step): the first steps run eagerly
    (recording the draws, the capture's warm-up), the others are replays."""
    monkeypatch.setattr(cudagraphs, "_backend", _Emulated())
    monkeypatch.setattr(
        graph_step, "eligible", lambda filt, state, gen: select.graph_step(filt, state.particles, gen, emulated=True)
    )
    cudagraphs.clear()
    model = SensorNetwork(d=4)
    obs, mean, cov = _data(model, steps=6)
    f = BootstrapParticleFilter(model, n_particles=16)
    try:
        with torch.no_grad(), tuning.tuned(fused_weights=0):  # a GPU's step (no CPU weighting kernel)
            res = f(obs, mean, cov, TrialStreams(1, 2, f.stream_name, backend="philox"))
            with tuning.tuned(cuda_graphs=0):
                eager = f(obs, mean, cov, TrialStreams(1, 2, f.stream_name, backend="philox"))
    finally:
        cudagraphs.clear()
    assert res.paths == {"graph:step": 4, "torch": 2} and eager.paths == {"torch": 6}
    assert torch.equal(res.estimates, eager.estimates)


def test_the_runner_records_each_filters_path(tmp_path):
    model = SkewedTPoisson(d=25)
    filters = {"bpf": BootstrapParticleFilter(model, n_particles=8), "ledh": _ledh(model)}
    store = ChunkStore(tmp_path / "chunks")
    res = run_experiment(model, filters, trials=2, steps=T, seed=3, chunk_size=1, progress=False, store=store)
    # two chunks of one trial: each filter's counts are summed over its calls
    assert res.paths == {"bpf": {BPF_PATH: 2 * T}, "ledh": {KERNEL: 2 * T}}
    assert {r["filter"]: r["path"] for r in res.summary} == {"bpf": BPF_PATH, "ledh": KERNEL}
    assert "path" in format_table(res.summary).splitlines()[0]
    writers.write_run(tmp_path, res, {})
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["paths"] == res.paths and [r["path"] for r in data["summary"]] == [BPF_PATH, KERNEL]
    # a resumed run reads the paths saved with its chunks
    again = run_experiment(
        model,
        filters,
        trials=2,
        steps=T,
        seed=3,
        chunk_size=1,
        progress=False,
        store=ChunkStore(tmp_path / "chunks", resume=True),
    )
    assert again.paths == res.paths and again.per_trial == res.per_trial


@cuda
def test_the_gpu_paths_are_reported():
    """On CUDA: the bootstrap PF's steps replayed from a graph, PF-PF(LEDH)'s flow loop sent to a
    graph (its warm-up counted under the Triton kernel), the kernel alone with cuda_graphs=0."""
    cudagraphs.clear()
    model = AcousticTracking().to("cuda")
    g = torch.Generator(device="cuda").manual_seed(0)
    traj = model.simulate(2, 6, g)
    obs, (mean, cov) = traj.observations, model.initial_belief(traj.states[:, 0], g)
    boot = BootstrapParticleFilter(model, n_particles=64)
    ledh = ParticleFlowParticleFilter(model, flow="ledh", n_particles=64)
    lanes = "kernel:lanes" if steps.runs_on(torch.device("cuda")) else "torch"
    try:
        with torch.no_grad():
            stepped = boot(obs, mean, cov, TrialStreams(1, 2, boot.stream_name, backend="philox"))
            graphed = ledh(obs, mean, cov, TrialStreams(1, 2, ledh.stream_name, backend="philox"))
            with tuning.tuned(cuda_graphs=0):
                fused = ledh(obs, mean, cov, TrialStreams(1, 2, ledh.stream_name, backend="philox"))
    finally:
        cudagraphs.clear()
    assert stepped.paths.get("graph:step", 0) >= 4 and sum(stepped.paths.values()) == 6
    assert graphed.paths["graph:flow"] == 6 and set(graphed.paths) <= {"graph:flow", lanes}
    assert fused.paths == {lanes: 6}
