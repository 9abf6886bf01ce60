"""A particle filter's whole step replayed from a CUDA graph (torchflow.filters.graph_step).

On the CPU the capture is emulated as in test_cudagraphs (the "graph" re-runs the function on its
static buffers), with the Philox back end the GPU uses: that checks the plumbing (the draws split
into words made outside and numbers made inside, the state flattened and rebuilt, the recorded
draws checked). On CUDA the real capture is compared with the eager run, bit for bit."""

import warnings

import pytest
import torch
from conftest import cuda, random_lg
from test_cudagraphs import _Emulated

from torchflow.core import cudagraphs, tuning
from torchflow.core.random import TrialStreams
from torchflow.filters import BootstrapParticleFilter, ParticleFilter, graph_step
from torchflow.flows import select
from torchflow.models import AcousticTracking, SensorNetwork
from torchflow.proposals import BootstrapProposal


@pytest.fixture
def emulated(monkeypatch):
    backend = _Emulated()
    monkeypatch.setattr(cudagraphs, "_backend", backend)
    monkeypatch.setattr(
        graph_step, "eligible", lambda filt, state, gen: select.graph_step(filt, state.particles, gen, emulated=True)
    )
    cudagraphs.clear()
    # a GPU's step: the CPU's weighting kernel (tuning.fused_weights) never runs in a graph step
    with tuning.tuned(fused_weights=0):
        yield backend
    cudagraphs.clear()


def _run(f, model, device="cpu", B=3, T=6, seed=0, nonfinite=None):
    model = model.to(device=device)
    g = torch.Generator(device=device).manual_seed(seed)
    traj = model.simulate(B, T, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    with torch.no_grad():
        return f(
            traj.observations,
            mean,
            cov,
            TrialStreams(seed + 1, B, f.stream_name, backend="philox"),
            return_particles=True,
        )


def _same(a, b):
    for name in ("estimates", "log_evidence", "ess", "particles", "log_weights"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


MODELS = {"lg": lambda: random_lg(3, 2), "acoustic": AcousticTracking, "sensors": lambda: SensorNetwork(d=16)}


@pytest.mark.parametrize("model_name", list(MODELS))
@pytest.mark.parametrize("nonfinite", ["recover", "raise"])
def test_replayed_step_gives_the_eager_numbers(emulated, model_name, nonfinite):
    model = MODELS[model_name]()
    f = BootstrapParticleFilter(model, n_particles=32, nonfinite=nonfinite)
    with tuning.tuned(cuda_graphs=0):
        eager = _run(f, model)
    before = cudagraphs.stats()
    graphed = _run(f, model)
    again = _run(f, model)  # a second call: every step replayed (the draws were recorded once)
    after = cudagraphs.stats()
    _same(eager, graphed)
    _same(eager, again)
    # one eager step records the draws; the first state's layout (and, with nonfinite="raise", the
    # later one's: invalid is None at first) is captured once and replayed after
    assert after["captures"] - before["captures"] in (1, 2)
    assert after["replays"] - before["replays"] >= 2 * 6 - 4
    assert emulated.calls >= 2 * 6 - 4


@pytest.mark.parametrize("scheme", ["multinomial", "systematic", "stratified", "residual"])
def test_every_resampling_scheme_is_replayed(emulated, scheme):
    """Each resampling scheme's step is captured (no tensor made from host data inside it: the
    multinomial and residual schemes once made their upper bound with ``new_tensor``, a copy from
    the host that a real capture refuses) and replayed with the eager step's numbers (eager on the
    CPU reads back which trials resample; the captured step, as on a GPU, does not)."""
    model = AcousticTracking()
    f = BootstrapParticleFilter(model, n_particles=32, resampling=scheme)
    with tuning.tuned(cuda_graphs=0):
        eager = _run(f, model)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a failed capture warns and runs eagerly
        before = cudagraphs.stats()
        graphed = _run(f, model)
    _same(eager, graphed)
    assert cudagraphs.stats()["replays"] > before["replays"]


@pytest.mark.parametrize("flow", ["edh", "ledh"])
@pytest.mark.parametrize("model_name", ["lg", "acoustic"])
def test_a_pfpf_step_is_replayed_whole(emulated, flow, model_name):
    """PF-PF with a deterministic flow is captured and replayed whole (its flow loop inside the
    step's graph: not a graph of its own), with the eager step's numbers; the clustered points are
    not declared graph-safe and step eagerly."""
    from torchflow.core import paths
    from torchflow.filters import ClusteredParticleFlowParticleFilter, ParticleFlowParticleFilter

    model = MODELS[model_name]()
    f = ParticleFlowParticleFilter(model, flow=flow, n_particles=24)
    assert f.graph_step
    # the eager step as on a GPU: safe_cholesky's batched jitter ladder (the CPU's default, which
    # reads the failure flags, gives the same factors only up to round-off); the flows' torch path
    # (a GPU runs the Triton kernel inside the graph, not the CPU's Numba one)
    with tuning.tuned(cuda_graphs=0, batched_jitter_cpu=1, fused_flows=0):
        eager = _run(f, model, T=5)
    with warnings.catch_warnings(), tuning.tuned(fused_flows=0):
        warnings.simplefilter("error")  # a capture that fails warns and runs eagerly
        with paths.recording() as counts:
            graphed = _run(f, model, T=5)
    # the same numbers to round-off (LEDH's per-particle products on the graph's static buffers
    # may take other BLAS paths: 4e-11 measured on acoustic tracking)
    for name in ("estimates", "log_evidence", "ess", "particles", "log_weights"):
        torch.testing.assert_close(getattr(graphed, name), getattr(eager, name), rtol=1e-8, atol=1e-8, msg=name)
    assert counts.get("graph:step", 0) >= 2 and "graph:flow" not in counts, counts
    assert not ClusteredParticleFlowParticleFilter(model, n_particles=24).graph_step

    from torchflow.flows.points import ParticlePoints

    class MyPoints(ParticlePoints):  # a subclass may place points otherwise: it declares itself
        pass

    assert not ParticleFlowParticleFilter(model, flow=flow, points=MyPoints(), n_particles=24).graph_step


def test_only_declared_steps_go_through_a_graph(emulated):
    model = random_lg(3, 2)
    f = BootstrapParticleFilter(model, n_particles=16)
    assert f.graph_step
    before = cudagraphs.stats()["captures"]
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(2, 4, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    with torch.no_grad():
        f(traj.observations, mean, cov, torch.Generator().manual_seed(1))  # a torch.Generator: eager
        f(traj.observations, mean, cov, TrialStreams(0, 2, backend="numpy"))  # numpy streams: eager
        with tuning.tuned(graph_step_max_elems=0):
            f(traj.observations, mean, cov, TrialStreams(0, 2, backend="philox"))
    with warnings.catch_warnings():  # the filter says once that the reference path runs
        warnings.simplefilter("ignore")
        f(traj.observations, mean.clone().requires_grad_(True), cov, TrialStreams(0, 2, backend="philox"))  # eager
    assert cudagraphs.stats()["captures"] == before

    class Undeclared(BootstrapProposal):
        graph_safe = False

    assert not ParticleFilter(model, Undeclared(model), n_particles=16).graph_step

    class MyModel(type(model)):
        pass

    assert not BootstrapParticleFilter(
        MyModel(model.F, model.Q, model.H, model.R, model.m0, model.P0), n_particles=16
    ).graph_step

    class OwnStep(BootstrapParticleFilter):
        def step(self, state, z, generator=None):
            return super().step(state, z, generator)

    assert not OwnStep(model, n_particles=16).graph_step


def test_draws_that_change_fall_back_to_eager_with_the_same_numbers(emulated):
    """A proposal that declares itself graph-safe but draws otherwise inside the graph than when it
    was recorded: the step runs eagerly, from the stream positions the graph's words took (given
    back), with a warning; the numbers are the eager run's."""
    model = random_lg(3, 2)

    class Varying(BootstrapProposal):
        graph_safe = True

        def propose(self, particles, log_weights, estimate, z, carry, generator, *, chunk=None):
            if isinstance(generator, graph_step._Tape):  # an extra draw where the graph would replay
                generator.uniform((particles.shape[0], 1), dtype=particles.dtype, device=particles.device)
            return super().propose(particles, log_weights, estimate, z, carry, generator, chunk=chunk)

    f = ParticleFilter(model, Varying(model), n_particles=16)
    with tuning.tuned(cuda_graphs=0):
        eager = _run(f, model)
    graph_step._warned.clear()
    before = cudagraphs.stats()["captures"]
    with pytest.warns(RuntimeWarning, match="not replayed from a CUDA graph"):
        graphed = _run(f, model)
    _same(eager, graphed)
    assert cudagraphs.stats()["captures"] == before


def test_settings_changed_between_calls_give_the_eager_numbers(emulated):
    """The draws are recorded per settings: a resampler that stops drawing (ESS threshold 0) or a
    filter switched between nonfinite modes (another output layout) replays its own graph."""
    model = random_lg(3, 2)
    f = BootstrapParticleFilter(model, n_particles=16)

    def both():
        with tuning.tuned(cuda_graphs=0):
            eager = _run(f, model)
        _same(eager, _run(f, model))
        _same(eager, _run(f, model))

    both()
    f.resampler.ess_threshold = 0.0  # no resampling draw any more
    both()
    f.resampler.ess_threshold = 0.5
    f.nonfinite = "raise"  # the state carries an `invalid` tensor from now on
    both()
    f.nonfinite = "recover"
    both()
    entries = [e for e in graph_step._specs[f].values() if e is not None]
    assert len({len(e["specs"]) for e in entries}) == 2  # with and without the resampling draw
    assert len({e["out"] for e in entries}) == 2  # invalid: None or a tensor


def test_a_step_making_fewer_draws_than_recorded_runs_eagerly(emulated):
    """A step that skips a recorded draw inside the graph would leave the streams' counters ahead of
    the eager run's: it is caught and the step runs eagerly from the words' positions."""
    model = random_lg(3, 2)

    class Skipping(BootstrapProposal):
        graph_safe = True

        def propose(self, particles, log_weights, estimate, z, carry, generator, *, chunk=None):
            out = super().propose(particles, log_weights, estimate, z, carry, generator, chunk=chunk)
            if not isinstance(generator, graph_step._Tape):  # a last draw, except inside the graph
                generator.uniform((particles.shape[0], 1), dtype=particles.dtype, device=particles.device)
            return out

    f = ParticleFilter(model, Skipping(model), n_particles=16, ess_threshold=0.0)  # no resampling draw
    with tuning.tuned(cuda_graphs=0):
        eager = _run(f, model)
    with pytest.warns(RuntimeWarning, match="made 1 of the 2 recorded draws"):
        graphed = _run(f, model)
    _same(eager, graphed)


def test_subclasses_must_declare_themselves(emulated):
    """A proposal subclass inherits no graph-safety (it may draw otherwise), nor does a model
    subclass; a TrialStreams subclass is not replayed (its draws may be its own)."""
    model = random_lg(3, 2)

    class Sub(BootstrapProposal):
        pass

    assert not ParticleFilter(model, Sub(model), n_particles=8).graph_step

    class SubSafe(BootstrapProposal):
        graph_safe = True

    assert ParticleFilter(model, SubSafe(model), n_particles=8).graph_step

    class MyStreams(TrialStreams):
        pass

    f = BootstrapParticleFilter(model, n_particles=8)
    x = torch.zeros(2, 8, 3, dtype=torch.float64)
    with torch.no_grad():
        assert select.graph_step(f, x, TrialStreams(0, 2, backend="philox"), emulated=True)
        assert not select.graph_step(f, x, MyStreams(0, 2, backend="philox"), emulated=True)


def test_philox_split_gives_the_same_draws():
    """Words outside, numbers inside: the draw of TrialStreams bit for bit."""
    for dtype in (torch.float64, torch.float32):
        for kind, n in (("normal", 7), ("uniform", 5), ("normal", 8)):
            a, b = TrialStreams(3, 4, "x", backend="philox"), TrialStreams(3, 4, "x", backend="philox")
            whole = a._draw(kind, (4, n), dtype, "cpu")
            split = TrialStreams._philox_numbers(kind, b._philox_bits(kind, n, dtype, "cpu"), n, dtype)
            assert torch.equal(whole, split) and a._counter == b._counter


@cuda
@pytest.mark.parametrize("model_name", list(MODELS))
def test_graphed_step_matches_eager_on_cuda(model_name):
    model = MODELS[model_name]()
    f = BootstrapParticleFilter(model, n_particles=64)
    with tuning.tuned(cuda_graphs=0):
        eager = _run(f, model, "cuda", B=4, T=8)
    before = cudagraphs.stats()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a failed capture warns: fail the test instead
        graphed = _run(f, model, "cuda", B=4, T=8)
        again = _run(f, model, "cuda", B=4, T=8)
    after = cudagraphs.stats()
    assert after["captures"] > before["captures"] and after["replays"] - before["replays"] >= 8
    _same(eager, graphed)
    _same(eager, again)
