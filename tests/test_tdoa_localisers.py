"""BP localisation with flow-induced mixture importance sampling on 3-D TDOA (Zhang et al. (2024))."""

import pytest
import torch

from torchflow.core import metrics
from torchflow.core.random import TrialStreams
from torchflow.flows.schedules import GeometricSchedule
from torchflow.models import TDOA3D
from torchflow.tdoa import FlowMixtureLocaliser, birth_mixture


def _scene(n_sources=1, runs=2, clutter=0.05, seed=0):
    model = TDOA3D(n_sources=n_sources, clutter_rate=clutter, p_d=1.0)
    return model, model.simulate(runs, generator=torch.Generator().manual_seed(seed))


@pytest.mark.parametrize("method", ["pfi_d", "pfi_s", "pfi_os"])
def test_one_source_is_found(method):
    """One source, every sensor detects it, almost no clutter: exactly one declared source per run,
    within 20 m of the truth (the region is 2 km wide; the OSPA cut-off is 30 m; measured 0.5-17 m
    at these small sizes, G = 10, N_p = 100)."""
    model, data = _scene()
    loc = FlowMixtureLocaliser(
        model, method, n_components=10, samples_per_component=100, schedule=GeometricSchedule(1e-4, 2.0)
    )
    res = loc(data.z, generator=TrialStreams(0, range(2), "loc"), mask=data.mask)
    assert res.declared.sum(1).tolist() == [1, 1]
    est = res.positions[res.declared].reshape(2, 3)
    err = (est - data.sources[:, 0]).norm(dim=-1)
    assert (err < 20).all(), err
    ospa = metrics.ospa(
        res.positions.unsqueeze(1), data.sources.unsqueeze(1), cutoff=30.0, X_mask=res.declared.unsqueeze(1)
    )
    torch.testing.assert_close(ospa.flatten(), err)


def test_memory_chunks_do_not_change_the_numbers():
    model, data = _scene(n_sources=2, clutter=1.0)
    out = []
    for chunk in (10**8, 5000):
        loc = FlowMixtureLocaliser(
            model,
            "pfi_d",
            n_components=6,
            samples_per_component=50,
            schedule=GeometricSchedule(1e-3, 2.0),
            sample_chunk=chunk,
        )
        out.append(loc(data.z, generator=TrialStreams(0, range(2), "loc"), mask=data.mask))
    torch.testing.assert_close(out[0].state.existence, out[1].state.existence, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out[0].positions, out[1].positions, rtol=1e-12, atol=1e-9)


def test_birth_mixture_covers_the_region():
    means, L = birth_mixture(1000.0, 5)
    assert means.shape == (125, 3) and means.abs().max() == 800.0
    torch.testing.assert_close(L, torch.eye(3, dtype=torch.float64) * 200.0)


def test_bad_input():
    model = TDOA3D()
    with pytest.raises(ValueError, match="method"):
        FlowMixtureLocaliser(model, "bs")
    with pytest.raises(ValueError, match="model.clutter_rate"):
        FlowMixtureLocaliser(TDOA3D(clutter_rate=0.0))
    with pytest.raises(ValueError, match="n_components"):
        FlowMixtureLocaliser(model, n_components=0)
    with pytest.raises(ValueError, match="declare"):
        FlowMixtureLocaliser(model, declare=1.5)
    with pytest.raises(TypeError, match="model"):
        FlowMixtureLocaliser("tdoa")
    loc = FlowMixtureLocaliser(model, n_components=2, samples_per_component=2)
    z = torch.zeros(1, 9, 2, dtype=torch.float64)
    with pytest.raises(ValueError, match="mask"):
        loc(z, generator=torch.Generator(), mask=torch.ones(1, 9, 3, dtype=torch.bool))


def test_bootstrap_baseline_finds_a_source_in_a_small_region():
    """The bootstrap sampler works where its particles are dense enough: a 100 m cube, 2e4
    particles per PO (in the seed's 2 km cube it needs millions: BS 2e6 there has OSPA 25.9)."""
    from torchflow.tdoa import BootstrapLocaliser

    model = TDOA3D(n_sources=1, clutter_rate=0.05, p_d=1.0, region=50.0, sigma_v=1e-3)
    data = model.simulate(2, generator=torch.Generator().manual_seed(0))
    loc = BootstrapLocaliser(model, n_particles=20000)
    res = loc(data.z, generator=TrialStreams(0, range(2), "bs"), mask=data.mask)
    assert res.declared.sum(1).tolist() == [1, 1]
    err = (res.positions[res.declared].reshape(2, 3) - data.sources[:, 0]).norm(dim=-1)
    assert (err < 5).all(), err  # measured 0.9 and 2.8 m
    # memory chunks do not change the numbers
    small = BootstrapLocaliser(model, n_particles=20000, sample_chunk=7000)
    res2 = small(data.z, generator=TrialStreams(0, range(2), "bs"), mask=data.mask)
    torch.testing.assert_close(res2.positions, res.positions, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("kind", ["pfi_os", "bs"])
def test_an_underflowing_measurement_is_reported_not_nan(kind, recwarn):
    """A TDOA far outside every sensor's feasible interval has likelihood exp(-1e10) under every
    sample: both localisers flag that (run, sensor, measurement), treat it as clutter (the source
    is still found, nothing is NaN)."""
    from torchflow.tdoa import BootstrapLocaliser

    model, data = _scene(runs=2)
    pad = torch.zeros(2, 9, 1, dtype=data.z.dtype)
    z = torch.cat([data.z, pad], -1)
    mask = torch.cat([data.mask, pad.bool()], -1)
    z[1, 4, -1], mask[1, 4, -1] = 50.0, True
    if kind == "bs":
        model = TDOA3D(n_sources=1, clutter_rate=0.05, p_d=1.0, region=50.0, sigma_v=1e-3)
        data = model.simulate(2, generator=torch.Generator().manual_seed(0))
        z = torch.cat([data.z, pad], -1)
        mask = torch.cat([data.mask, pad.bool()], -1)
        z[1, 4, -1], mask[1, 4, -1] = 50.0, True
        loc = BootstrapLocaliser(model, n_particles=20000)
    else:
        loc = FlowMixtureLocaliser(
            model, kind, n_components=10, samples_per_component=100, schedule=GeometricSchedule(1e-4, 2.0)
        )
    res = loc(z, generator=TrialStreams(0, range(2), "loc"), mask=mask)
    assert res.underflow.shape == z.shape
    assert torch.nonzero(res.underflow).tolist() == [[1, 4, z.shape[-1] - 1]]
    assert res.declared.sum(1).tolist() == [1, 1]
    assert torch.isfinite(res.positions[res.declared]).all() and torch.isfinite(res.state.existence).all()
    clean = loc(data.z, generator=TrialStreams(0, range(2), "loc"), mask=data.mask)
    assert not clean.underflow.any()


def test_runner_reports_underflows(monkeypatch):
    """The runner warns with the localiser, run, sensor and measurement, and counts them."""
    from torchflow.app.runner import run_experiment
    from torchflow.models.tdoa import TDOAData

    model = TDOA3D(n_sources=1, clutter_rate=0.05, p_d=1.0)
    real = model.simulate

    def simulate(runs, steps, generator):
        d = real(runs, steps, generator)
        pad = torch.zeros(runs, 9, 1, dtype=d.z.dtype)
        z, mask = torch.cat([d.z, pad], -1), torch.cat([d.mask, pad.bool()], -1)
        j = int(d.mask[0, 2].sum())  # right after sensor 2's real measurements (padding comes last)
        z[0, 2, j], mask[0, 2, j] = -40.0, True
        origin = torch.cat([d.origin, pad.long() - 1], -1)
        return TDOAData(d.states, z, mask, origin)

    monkeypatch.setattr(model, "simulate", simulate)
    loc = FlowMixtureLocaliser(
        model, "pfi_d", n_components=5, samples_per_component=50, schedule=GeometricSchedule(1e-3, 2.0)
    )
    with pytest.warns(
        RuntimeWarning,
        match=r"pfi: every component's weight underflowed .* run 0, sensor 2, "
        r"measurement",
    ):
        res = run_experiment(model, {"pfi": loc}, trials=2, progress=False)
    assert [r["underflows"] for r in res.per_trial] == [1, 0] and res.summary[0]["underflows"] == 1


def _small(model, method="pfi_d"):
    return FlowMixtureLocaliser(
        model, method, n_components=4, samples_per_component=20, schedule=GeometricSchedule(1e-3, 2.0)
    )


def test_runner_localises_each_run_alone_with_its_own_stream():
    """Through the runner, run b's result is the localiser's on that run alone, trimmed to its own
    largest number of measurements per sensor, with the stream (seed, b, "localise_<method>"):
    the numbers of the former per-run loop. A chunk_size does not batch runs (trials_per_call = 1),
    and a resumed run loads the saved runs."""
    from torchflow.app.runner import run_experiment

    model = TDOA3D(n_sources=2, clutter_rate=1.0)
    res = run_experiment(model, {"a": _small(model)}, trials=3, seed=4, progress=False)
    data = model.simulate(3, generator=torch.Generator().manual_seed(4))
    for b in range(3):
        M = int(data.mask[b].sum(-1).max())
        alone = _small(model)(
            data.z[b : b + 1, :, :M], generator=TrialStreams(4, [b], "localise_pfi_d"), mask=data.mask[b : b + 1, :, :M]
        )
        truth = data.sources[b : b + 1].unsqueeze(1)
        ospa = metrics.ospa(alone.positions.unsqueeze(1), truth, cutoff=40.0, X_mask=alone.declared.unsqueeze(1))
        assert res.per_trial[b]["ospa"] == float(ospa) and res.per_trial[b]["declared"] == int(alone.declared.sum())
    assert res.config["chunk_size"] == {"a": 1} and res.config["steps"] == 9 and len(res.per_step) == 9
    chunked = run_experiment(model, {"a": _small(model)}, trials=3, seed=4, progress=False, chunk_size=3)
    assert chunked.per_trial == res.per_trial and chunked.config["chunk_size"] == {"a": 1}


def test_resume_loads_the_saved_runs(tmp_path):
    from torchflow.app.runner import ChunkStore, run_experiment

    model = TDOA3D(n_sources=1, clutter_rate=0.5)
    first = run_experiment(model, {"a": _small(model)}, trials=2, progress=False, store=ChunkStore(tmp_path))
    store = ChunkStore(tmp_path, resume=True)
    again = run_experiment(model, {"a": _small(model)}, trials=2, progress=False, store=store)
    assert store.loaded == {"a": 2} and again.per_trial == first.per_trial and again.per_step == first.per_step


def test_a_state_space_filter_is_refused_on_the_tdoa_model():
    from torchflow.app.runner import ConfigError, run_experiment
    from torchflow.filters import BootstrapParticleFilter

    model = TDOA3D()
    with pytest.raises(
        ConfigError,
        match=r"filter.bpf: BootstrapParticleFilter cannot run on TDOA3D, whose "
        r"measurements are padded sets",
    ):
        run_experiment(model, {"bpf": BootstrapParticleFilter(model, n_particles=10)}, trials=1, progress=False)


def test_an_interrupted_run_keeps_the_finished_runs(tmp_path):
    """A stop request (Ctrl-C / SIGTERM through STOP) during run 1 of the first localiser ends the
    job at once: run 0 is saved in the checkpoint store, the row says so, and the second
    localiser does not start."""
    from torchflow.app.runner import STOP, ChunkStore, run_experiment

    model = TDOA3D(n_sources=1, clutter_rate=0.05, p_d=1.0)
    loc, other = _small(model), _small(model, "pfi_s")
    calls = []
    real = loc.update

    def update(*a, **k):
        calls.append(1)
        if len(calls) == 9 + 3:  # sensor 3 of run 1 (9 sensors per run): as if SIGTERM arrived there
            STOP.handler(15, None)
        return real(*a, **k)

    loc.update = update
    store = ChunkStore(tmp_path)
    try:
        res = run_experiment(model, {"a": loc, "b": other}, trials=3, progress=False, store=store)
    finally:
        STOP.reset()
    assert res.interrupted and res.not_run == ["b"] and store.computed == {"a": 1}
    assert res.summary[0]["error"] == "interrupted after 1 of 3 trials"


def test_scene_figure_draws_receivers_sources_and_each_localisers_declared_sources():
    plt = pytest.importorskip("matplotlib.pyplot")
    from torchflow.app.runner import figures

    model, data = _scene(n_sources=2)
    examples = {"a": data.sources[0, :1], "b": torch.zeros(0, 3, dtype=torch.float64)}
    fig = figures.scene_figure(plt, model, data, examples, [{"filter": "a"}, {"filter": "b"}], "t")
    ax = fig.axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["receivers", "true sources", "a", "b (none declared)"]
    assert [len(c.get_offsets()) for c in ax.collections] == [6, 2, 1, 0]
    plt.close(fig)


def test_the_localisers_and_the_filters_declare_one_runner_protocol():
    """What the runner reads is one declared base (torchflow.filters.Estimator): the localisers
    declare sets, masked measurements, one run per call and per-run streams; the filters states."""
    from torchflow.filters import BootstrapParticleFilter, Estimator, KalmanFilter
    from torchflow.models import SensorNetwork
    from torchflow.tdoa import BootstrapLocaliser, FlowMixtureLocaliser

    model = TDOA3D(n_sources=1, clutter_rate=0.05, p_d=1.0, region=50.0, sigma_v=1e-3)
    for loc in (BootstrapLocaliser(model, n_particles=100), FlowMixtureLocaliser(model)):
        assert isinstance(loc, Estimator)
        assert (loc.output, loc.padded_measurements, loc.trials_per_call, loc.preferred_chunk_trials()) == (
            "sets",
            True,
            1,
            1,
        )
        assert loc.stream_name == f"localise_{loc.method}" and loc.plan_memory(1e9) is None
        assert loc.bytes_per_trial() == loc.bytes_per_trial(n_particles=7) == 64 * loc.sample_chunk
    lg = SensorNetwork(d=4)
    for f in (KalmanFilter(lg), BootstrapParticleFilter(lg, n_particles=10)):
        assert isinstance(f, Estimator) and f.output == "states" and not f.padded_measurements
        assert f.preferred_chunk_trials() is None or f.preferred_chunk_trials() > 1
