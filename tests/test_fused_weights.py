"""The CPU weighting kernel (torchflow.flows.kernels.cpu_weights, tuning.fused_weights): a particle
filter's weighting, estimate, ESS and resampling in one Numba call agree with the torch path to
round-off, draw the same uniforms, and hand non-finite steps, gradients and other resamplers to the
torch path."""

import math

import pytest
import torch

from torchflow.core import paths, resampling, tuning
from torchflow.core.random import TrialStreams
from torchflow.filters import BootstrapParticleFilter
from torchflow.flows import select
from torchflow.flows.kernels import steps
from torchflow.models import SensorNetwork, StochasticVolatility

pytestmark = pytest.mark.skipif(not steps.weights_available(), reason="needs Numba (the kernels extra)")


def _inputs(B=5, N=200, d=3, seed=0, spread=1.5):
    """Particles, normalised previous log-weights and increments whose spread grows from trial to
    trial (``0.1 spread`` to ``spread``), so that a threshold splits the batch."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(B, N, d, dtype=torch.float64, generator=g)
    prev = 0.1 * torch.randn(B, N, dtype=torch.float64, generator=g)
    prev = prev - prev.logsumexp(-1, keepdim=True)
    scale = spread * torch.linspace(0.1, 1.0, B, dtype=torch.float64)[:, None]
    inc = scale * torch.randn(B, N, dtype=torch.float64, generator=g)
    return x, prev, inc


def _filter(**kw):
    """A bootstrap PF whose weighting step is called directly (the model only sizes the resampler)."""
    return BootstrapParticleFilter(SensorNetwork(d=1), **kw)


def _both(filt, x, prev, inc, seed=1, make_gen=None, fallback=None):
    """``weight_and_resample`` with the kernel and with the torch path, each from a fresh generator;
    returns the two states and the two generators afterwards (and checks which path each took)."""
    out = []
    for fused in (1, 0):
        g = make_gen() if make_gen else torch.Generator().manual_seed(seed)
        with tuning.tuned(fused_weights=fused), torch.no_grad(), paths.recording() as used:
            st = filt.weight_and_resample(x, prev, inc, g, 1, fallback=x if fallback is None else fallback)
        assert used == ({"kernel:weights": 1} if fused else {}), used
        out.append((st, g))
    return out


def _close(a, b, rtol=1e-12):
    assert torch.allclose(a, b, rtol=rtol, atol=1e-13), (a - b).abs().max()


@pytest.mark.parametrize("scheme", ["systematic", "stratified"])
@pytest.mark.parametrize("threshold", [0.0, 0.3, 0.5, 1.0])
@pytest.mark.parametrize("d", [1, 3])
def test_the_kernel_gives_the_torch_paths_numbers(scheme, threshold, d):
    x, prev, inc = _inputs(d=d)
    f = _filter(resampling=scheme, ess_threshold=threshold)
    (k, gk), (t, gt) = _both(f, x, prev, inc)
    _close(k.log_weights, t.log_weights)
    _close(k.estimate, t.estimate)
    _close(k.ess, t.ess)
    _close(k.log_evidence_increment, t.log_evidence_increment)
    assert torch.equal(k.resampled, t.resampled)
    assert torch.equal(k.particles, t.particles)  # the same ancestors, exactly
    assert torch.equal(gk.get_state(), gt.get_state())  # the same draws
    if threshold in (0.3, 0.5):  # a mixed batch: some trials resampled, some kept
        assert 0 < int(k.resampled.sum()) < x.shape[0]


def test_indices_equal_the_reference_inversion_with_zero_weights_and_ties():
    """The kernel's ancestors against resampling._strata_indices on weights with exact zeros and
    equal values, systematic and stratified uniforms including 0."""
    g = torch.Generator().manual_seed(3)
    B, N = 6, 64
    lw = torch.randn(B, N, dtype=torch.float64, generator=g)
    lw[1] = 0.0  # ties: equal weights
    lw[2, 7:20] = lw[2, 7]
    lw[:, ::5] = float("-inf")  # zero weights (row 1: equal weights between them, not the identity)
    lw = lw - lw.logsumexp(-1, keepdim=True)
    x = torch.arange(B * N, dtype=torch.float64).reshape(B, N, 1)
    for u in (
        torch.rand(B, 1, dtype=torch.float64, generator=g),
        torch.zeros(B, 1, dtype=torch.float64),
        torch.rand(B, N, dtype=torch.float64, generator=g),
    ):
        # log_increment 0: the normalised weights are lw itself; threshold 1: every trial resamples
        out = steps.weigh_resample(x, lw, torch.zeros_like(lw), u, 1.0)
        want = resampling._strata_indices(lw, u)
        assert bool(out[5].all())  # every trial resampled (zero weights: ESS < N)
        assert torch.equal(out[0][..., 0].long() - torch.arange(B)[:, None] * N, want)


def _nonfinite_inputs():
    x, prev, inc = _inputs()
    x[1, 3, 0] = float("nan")  # a particle to repair
    inc[3, 5] = float("inf")  # a NaN/+inf increment to repair
    inc[4] = float("-inf")  # a dead trial: no weight left
    return x, prev, inc


def test_non_finite_trials_take_the_torch_path_with_their_uniforms():
    """The flagged trials (1, 3, 4) get the torch path's repair, bit for bit, with their own rows of
    the uniforms; the clean ones (0, 2) the kernel's numbers; the generator ends in the same state."""
    x, prev, inc = _nonfinite_inputs()
    f = _filter(ess_threshold=0.9)
    (k, gk), (t, gt) = _both(f, x, prev, inc, fallback=torch.zeros_like(x))
    assert bool(torch.isfinite(k.particles).all())
    bad, clean = [1, 3, 4], [0, 2]
    for name in ("particles", "log_weights", "estimate", "ess", "log_evidence_increment", "resampled", "n_repaired"):
        a, b = getattr(k, name), getattr(t, name)
        if name == "estimate":  # torch's bmm rounds a row differently in batches of other sizes (d = 3)
            assert torch.allclose(a[bad], b[bad], rtol=1e-14, atol=1e-15), name
        else:
            assert torch.equal(a[bad], b[bad]), name
        assert (
            torch.equal(a[clean], b[clean])
            if not a.is_floating_point()
            else torch.allclose(a[clean], b[clean], rtol=1e-12)
        ), name
    assert torch.equal(k.particles, t.particles) and bool(k.resampled[clean].any())
    assert k.n_repaired.tolist() == [0, 1, 0, 1, 1]
    assert torch.equal(gk.get_state(), gt.get_state())


@pytest.mark.parametrize("nonfinite", ["recover", "raise"])
def test_a_trials_numbers_do_not_depend_on_its_neighbours(nonfinite):
    """The kernel's batch, and each trial alone, give every trial the same bits: clean trials next to
    trials to repair included (the chunk a trial runs in changes none of its numbers)."""
    x, prev, inc = _nonfinite_inputs()
    f = _filter(ess_threshold=0.9, nonfinite=nonfinite)
    B = x.shape[0]
    u = TrialStreams(3, B, "bpf")
    with torch.no_grad():
        whole = f.weight_and_resample(x, prev, inc, u, 1, fallback=torch.zeros_like(x))
        for b in range(B):
            one = f.weight_and_resample(
                x[b : b + 1],
                prev[b : b + 1],
                inc[b : b + 1],
                TrialStreams(3, [b], "bpf"),
                1,
                fallback=torch.zeros_like(x[b : b + 1]),
            )
            for name in (
                "particles",
                "log_weights",
                "estimate",
                "ess",
                "log_evidence_increment",
                "resampled",
                "n_repaired",
            ):
                a, w = getattr(one, name)[0], getattr(whole, name)[b]
                if name == "estimate" and b in (1, 3, 4):  # a repaired trial's: torch's bmm, batch-size round-off
                    assert torch.allclose(a, w, rtol=1e-14, atol=1e-15), (b, name)
                else:
                    assert torch.equal(a, w), (b, name)
            if nonfinite == "raise":
                assert bool(one.invalid[0]) == bool(whole.invalid[b]) == (b in (1, 3, 4))


def test_per_trial_streams_draw_the_same_uniforms():
    x, prev, inc = _inputs(B=4)
    f = _filter(resampling="stratified", ess_threshold=1.0)
    (k, gk), (t, gt) = _both(f, x, prev, inc, make_gen=lambda: TrialStreams(7, 4, "bpf"))
    assert torch.equal(k.particles, t.particles)
    _close(k.log_weights, t.log_weights)


def test_parallel_trials_give_the_serial_bits():
    x, prev, inc = _inputs(B=40, N=2000, d=2)
    assert x.shape[0] * x.shape[1] >= steps.PARALLEL_WEIGHTS_MIN
    u = torch.rand(40, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        serial = steps.weigh_resample(x, prev, inc, u, 0.5)
        torch.set_num_threads(2)
        parallel = steps.weigh_resample(x, prev, inc, u, 0.5)
    finally:
        torch.set_num_threads(threads)
    assert serial[-1] is None and parallel[-1] is None  # no trial to repair
    for a, b in zip(serial[:-1], parallel[:-1]):
        assert torch.equal(a, b)


def test_what_the_kernel_does_not_cover_takes_the_torch_path():
    x, prev, inc = _inputs()
    kw = dict(resampler=None, cov=None, extras=None)
    for f in (
        _filter(resampling="multinomial"),
        _filter(resampling="residual"),
        _filter(resampling_gradient="soft"),
        _filter(resampling_gradient="ot"),
    ):
        kw["resampler"] = f.resampler
        assert select.weights_kernel(x, prev, inc, **kw) is None, f.resampler
    f = _filter()
    kw["resampler"] = f.resampler
    assert select.weights_kernel(x, prev, inc, **kw) == "systematic"
    f.resampler.sort = "first"
    assert select.weights_kernel(x, prev, inc, **kw) is None
    f.resampler.sort = None
    assert select.weights_kernel(x.float(), prev.float(), inc.float(), **kw) is None  # float32: the torch path
    assert select.weights_kernel(x, prev, inc, **dict(kw, extras={"ancestor": prev.long()})) is None
    with tuning.tuned(fused_weights=0):
        assert select.weights_kernel(x, prev, inc, **kw) is None
    many = select.WEIGHTS_KERNEL_MAX_PARTICLES + 1  # more particles per trial: torch's vectorised passes
    assert select.weights_kernel(torch.zeros(1, many, 1, dtype=torch.float64), **kw) is None
    assert select.weights_kernel(x, prev, inc.requires_grad_(), **kw) is None  # a gradient is recorded
    with torch.no_grad():
        assert select.weights_kernel(x, prev, inc, **kw) == "systematic"
    regular = _filter(regularization=0.1)  # jitter after resampling: the torch path
    assert select.weights_kernel(x, prev, inc.detach(), **dict(kw, resampler=regular.resampler)) is None


def test_a_learnable_model_records_gradients_through_the_torch_path():
    model = StochasticVolatility(learnable=True)
    y = 0.5 * torch.randn(1, 20, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    mean, cov = model.declared_prior(1)
    res = BootstrapParticleFilter(model, n_particles=64)(y, mean, cov, torch.Generator().manual_seed(1))
    assert res.paths == {"torch": 20}
    res.log_evidence.sum().backward()
    assert model.mu.grad is not None and math.isfinite(float(model.mu.grad))


def test_a_whole_run_agrees_with_the_torch_path():
    """Stochastic volatility, 200 steps, 4 trials x 500 particles: round-off, not another run."""
    model = StochasticVolatility()
    g = torch.Generator().manual_seed(5)
    traj = model.simulate(4, 200, g)
    mean, cov = model.declared_prior(4)
    f = BootstrapParticleFilter(model, n_particles=500)
    runs = []
    for fused in (1, 0):
        with tuning.tuned(fused_weights=fused), torch.no_grad():
            runs.append(f(traj.observations, mean, cov, torch.Generator().manual_seed(9)))
    k, t = runs
    assert k.paths == {"kernel:weights": 200} and t.paths == {"torch": 200}
    _close(k.log_evidence, t.log_evidence, rtol=1e-11)
    _close(k.estimates, t.estimates, rtol=1e-10)


def test_a_resampler_without_the_declaration_takes_the_torch_path():
    x, prev, inc = _inputs()
    assert select.weights_kernel(x, prev, inc, resampler=torch.nn.Identity(), cov=None, extras=None) is None


@pytest.mark.parametrize("nonfinite", ["recover", "raise"])
def test_the_trace_buffers_give_the_kept_steps_numbers(monkeypatch, nonfinite):
    """A large particle filter's per-step outputs copied into buffers made once (filters.base.
    TRACE_BUFFER_MIN) are those kept step by step: every output, both non-finite policies."""
    from torchflow.filters import base

    model = StochasticVolatility()
    traj = model.simulate(3, 30, torch.Generator().manual_seed(2))
    mean, cov = model.declared_prior(3)
    f = BootstrapParticleFilter(model, n_particles=50, nonfinite=nonfinite)
    runs, puts = [], []
    put = base._Trace._put
    monkeypatch.setattr(base._Trace, "_put", lambda self, *a, **k: puts.append(1) or put(self, *a, **k))
    for limit in (0, 2**62):  # buffered, kept
        monkeypatch.setattr(base, "TRACE_BUFFER_MIN", limit)
        with torch.no_grad():
            runs.append(f(traj.observations, mean, cov, torch.Generator().manual_seed(4)))
        if limit == 0:
            assert len(puts) >= 3 * 30  # the buffers were used: estimate, increment, ESS per step
    for name in ("estimates", "log_evidence", "log_evidence_increments", "ess", "n_repaired"):
        assert torch.equal(getattr(runs[0], name), getattr(runs[1], name)), name
    assert runs[0].estimates.shape == (3, 30, 1)


def test_buffered_traces_name_and_warn_the_same_steps(monkeypatch):
    """The non-finite contract with the trace buffered: a step without the measurement is warned
    (recover) or raised (raise) naming the same step and trial as the kept steps do."""
    from test_nonfinite_contract import lg, observations, run

    from torchflow.core.errors import NonFiniteError
    from torchflow.filters import base

    monkeypatch.setattr(base, "TRACE_BUFFER_MIN", 0)
    z = observations()
    z[1, 2] = 1e200  # (z - x)^2 / R overflows: every log-weight -inf
    with pytest.warns(RuntimeWarning, match=r"at 1 step\(s\) \(first at time step 3\) in trial\(s\) \[1\]"):
        out = run(BootstrapParticleFilter(lg(R=1e-4), n_particles=20), z)
    assert out.log_evidence[1] == float("-inf") and torch.isfinite(out.log_evidence[[0, 2]]).all()
    with pytest.raises(NonFiniteError, match=r"at time step 3 in trial\(s\) \[1\]"):
        run(BootstrapParticleFilter(lg(R=1e-4), n_particles=20, nonfinite="raise"), z)
