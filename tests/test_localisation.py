"""BP localisation with flow-induced mixture importance sampling on 3-D TDOA (seed 002)."""
import pytest
import torch

from torchflow import metrics
from torchflow.localisation import FlowMixtureLocaliser, birth_mixture
from torchflow.models import TDOA3D
from torchflow.random import TrialStreams
from torchflow.schedules import GeometricSchedule


def _scene(n_sources=1, runs=2, clutter=0.05, seed=0):
    model = TDOA3D(n_sources=n_sources, clutter_rate=clutter, p_d=1.0)
    return model, model.simulate(runs, torch.Generator().manual_seed(seed))


@pytest.mark.parametrize("method", ["pfi_d", "pfi_s", "pfi_os"])
def test_one_source_is_found(method):
    """One source, every sensor detects it, almost no clutter: exactly one declared source per run,
    within 20 m of the truth (the region is 2 km wide; the OSPA cut-off is 30 m; measured 0.5-17 m
    at these small sizes, G = 10, N_p = 100)."""
    model, data = _scene()
    loc = FlowMixtureLocaliser(model, method, n_components=10, samples_per_component=100,
                               schedule=GeometricSchedule(1e-4, 2.0))
    res = loc(data.z, data.mask, TrialStreams(0, range(2), "loc"))
    assert res.declared.sum(1).tolist() == [1, 1]
    est = res.positions[res.declared].reshape(2, 3)
    err = (est - data.sources[:, 0]).norm(dim=-1)
    assert (err < 20).all(), err
    ospa = metrics.ospa(res.positions.unsqueeze(1), data.sources.unsqueeze(1), cutoff=30.0,
                        X_mask=res.declared.unsqueeze(1))
    torch.testing.assert_close(ospa.flatten(), err)


def test_memory_chunks_do_not_change_the_numbers():
    model, data = _scene(n_sources=2, clutter=1.0)
    out = []
    for chunk in (10**8, 5000):
        loc = FlowMixtureLocaliser(model, "pfi_d", n_components=6, samples_per_component=50,
                                   schedule=GeometricSchedule(1e-3, 2.0), sample_chunk=chunk)
        out.append(loc(data.z, data.mask, TrialStreams(0, range(2), "loc")))
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
        loc(z, torch.ones(1, 9, 3, dtype=torch.bool), torch.Generator())


def test_bootstrap_baseline_finds_a_source_in_a_small_region():
    """The bootstrap sampler works where its particles are dense enough: a 100 m cube, 2e4
    particles per PO (in the seed's 2 km cube it needs millions: BS 2e6 there has OSPA 25.9)."""
    from torchflow.localisation import BootstrapLocaliser

    model = TDOA3D(n_sources=1, clutter_rate=0.05, p_d=1.0, region=50.0, sigma_v=1e-3)
    data = model.simulate(2, torch.Generator().manual_seed(0))
    loc = BootstrapLocaliser(model, n_particles=20000)
    res = loc(data.z, data.mask, TrialStreams(0, range(2), "bs"))
    assert res.declared.sum(1).tolist() == [1, 1]
    err = (res.positions[res.declared].reshape(2, 3) - data.sources[:, 0]).norm(dim=-1)
    assert (err < 5).all(), err  # measured 0.9 and 2.8 m
    # memory chunks do not change the numbers
    small = BootstrapLocaliser(model, n_particles=20000, sample_chunk=7000)
    res2 = small(data.z, data.mask, TrialStreams(0, range(2), "bs"))
    torch.testing.assert_close(res2.positions, res.positions, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("kind", ["pfi_os", "bs"])
def test_an_underflowing_measurement_is_reported_not_nan(kind, recwarn):
    """A TDOA far outside every sensor's feasible interval has likelihood exp(-1e10) under every
    sample: both localisers flag that (run, sensor, measurement), treat it as clutter (the source
    is still found, nothing is NaN), and the runner's warning and per-run row name it."""
    from torchflow.localisation import BootstrapLocaliser, run_localisation

    model, data = _scene(runs=2)
    pad = torch.zeros(2, 9, 1, dtype=data.z.dtype)
    z = torch.cat([data.z, pad], -1)
    mask = torch.cat([data.mask, pad.bool()], -1)
    z[1, 4, -1], mask[1, 4, -1] = 50.0, True
    if kind == "bs":
        model = TDOA3D(n_sources=1, clutter_rate=0.05, p_d=1.0, region=50.0, sigma_v=1e-3)
        data = model.simulate(2, torch.Generator().manual_seed(0))
        z = torch.cat([data.z, pad], -1)
        mask = torch.cat([data.mask, pad.bool()], -1)
        z[1, 4, -1], mask[1, 4, -1] = 50.0, True
        loc = BootstrapLocaliser(model, n_particles=20000)
    else:
        loc = FlowMixtureLocaliser(model, kind, n_components=10, samples_per_component=100,
                                   schedule=GeometricSchedule(1e-4, 2.0))
    res = loc(z, mask, TrialStreams(0, range(2), "loc"))
    assert res.underflow.shape == z.shape
    assert torch.nonzero(res.underflow).tolist() == [[1, 4, z.shape[-1] - 1]]
    assert res.underflow_report() == [f"run 1, sensor 4, measurement {z.shape[-1] - 1}"]
    assert res.declared.sum(1).tolist() == [1, 1]
    assert torch.isfinite(res.positions[res.declared]).all() and torch.isfinite(res.state.existence).all()
    clean = loc(data.z, data.mask, TrialStreams(0, range(2), "loc"))
    assert not clean.underflow.any()


def test_runner_reports_underflows(monkeypatch):
    """run_localisation warns with the localiser, run, sensor and measurement, and counts them."""
    from torchflow.localisation import run_localisation
    from torchflow.models.tdoa import TDOAData

    model = TDOA3D(n_sources=1, clutter_rate=0.05, p_d=1.0)
    real = model.simulate

    def simulate(runs, generator):
        d = real(runs, generator)
        pad = torch.zeros(runs, 9, 1, dtype=d.z.dtype)
        z, mask = torch.cat([d.z, pad], -1), torch.cat([d.mask, pad.bool()], -1)
        j = int(d.mask[0, 2].sum())  # right after sensor 2's real measurements (padding comes last)
        z[0, 2, j], mask[0, 2, j] = -40.0, True
        origin = torch.cat([d.origin, pad.long() - 1], -1)
        return TDOAData(d.sources, z, mask, origin)

    monkeypatch.setattr(model, "simulate", simulate)
    loc = FlowMixtureLocaliser(model, "pfi_d", n_components=5, samples_per_component=50,
                               schedule=GeometricSchedule(1e-3, 2.0))
    with pytest.warns(RuntimeWarning, match=r"pfi: every component's weight underflowed .* run 0, sensor 2, "
                                            r"measurement"):
        summary, per_run, _, _ = run_localisation(model, {"pfi": loc}, runs=2, progress=False)
    assert [r["underflows"] for r in per_run] == [1, 0] and summary[0]["underflows"] == 1


def test_an_interrupted_run_keeps_the_finished_runs():
    """A stop request (Ctrl-C / SIGTERM through experiment.STOP) during run 1 of the first localiser
    ends the job at once: run 0's row is kept, the summary row covers it and says so, and the
    second localiser does not start."""
    from torchflow.experiment import STOP
    from torchflow.localisation import run_localisation

    model = TDOA3D(n_sources=1, clutter_rate=0.05, p_d=1.0)
    loc = FlowMixtureLocaliser(model, "pfi_d", n_components=4, samples_per_component=20,
                               schedule=GeometricSchedule(1e-3, 2.0))
    other = FlowMixtureLocaliser(model, "pfi_s", n_components=4, samples_per_component=20,
                                 schedule=GeometricSchedule(1e-3, 2.0))
    calls = []
    real = loc.update

    def update(*a, **k):
        calls.append(1)
        if len(calls) == 9 + 3:  # sensor 3 of run 1 (9 sensors per run): as if SIGTERM arrived there
            STOP.handler(15, None)
        return real(*a, **k)

    loc.update = update
    try:
        summary, per_run, _, _ = run_localisation(model, {"a": loc, "b": other}, runs=3, progress=False)
    finally:
        STOP.reset()
    assert [r["trial"] for r in per_run] == [0]
    assert summary[0]["error"] == "interrupted after 1 of 3 runs" and summary[0]["trials"] == 1
    assert summary[0]["ospa"] == per_run[0]["ospa"]
    assert summary[1]["error"] == "not run: interrupted" and summary[1]["ospa"] is None
