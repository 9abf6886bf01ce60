"""Per-trial random streams: numbers independent of chunking, order and config names."""

import math

import pytest
import torch
from conftest import cuda

from torchflow.app.runner import run_experiment
from torchflow.core.random import TrialStreams, check_generator, philox4x32
from torchflow.filters import BootstrapParticleFilter, KalmanFilter, ParticleFlowFilter, ParticleFlowParticleFilter
from torchflow.models import AcousticTracking, SensorNetwork

F64 = torch.float64


@pytest.mark.parametrize(
    "counter, key, expected",
    [
        # known-answer vectors of Random123 (kat_vectors, philox4x32 with 10 rounds)
        ([0, 0, 0, 0], [0, 0], [0x6627E8D5, 0xE169C58D, 0xBC57AC4C, 0x9B00DBD8]),
        ([0xFFFFFFFF] * 4, [0xFFFFFFFF] * 2, [0x408F276D, 0x41C83B0E, 0xA20BC7C6, 0x6D5451FD]),
        (
            [0x243F6A88, 0x85A308D3, 0x13198A2E, 0x03707344],
            [0xA4093822, 0x299F31D0],
            [0xD16CFE09, 0x94FDCCEB, 0x5001E420, 0x24126EA1],
        ),
    ],
)
def test_philox_known_answers(counter, key, expected):
    out = philox4x32([torch.tensor(c) for c in counter], [torch.tensor(k) for k in key])
    assert out.tolist() == expected


@pytest.mark.parametrize("backend", ["numpy", "philox"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_trial_draws_do_not_depend_on_the_batch(backend, dtype):
    full = TrialStreams(5, 6, "k", backend=backend)
    draws = [
        full.normal((6, 7, 3), dtype=dtype),
        full.uniform((6, 4), dtype=dtype),
        full.normal((6 * 5, 2), dtype=dtype),
    ]  # a trial-major multiple of B
    for chunk in ([0, 1, 2], [3], [4, 5]):
        part = TrialStreams(5, chunk, "k", backend=backend)
        got = [
            part.normal((len(chunk), 7, 3), dtype=dtype),
            part.uniform((len(chunk), 4), dtype=dtype),
            part.normal((len(chunk) * 5, 2), dtype=dtype),
        ]
        rows = torch.tensor(chunk)
        assert torch.equal(got[0], draws[0][rows])
        assert torch.equal(got[1], draws[1][rows])
        assert torch.equal(got[2].reshape(len(chunk), 5, 2), draws[2].reshape(6, 5, 2)[rows])
    # different seeds / keys give different numbers
    assert not torch.equal(
        TrialStreams(6, 6, "k", backend=backend).normal((6, 3)), TrialStreams(5, 6, "k", backend=backend).normal((6, 3))
    )
    assert not torch.equal(
        TrialStreams(5, 6, "j", backend=backend).normal((6, 3)), TrialStreams(5, 6, "k", backend=backend).normal((6, 3))
    )


def test_large_draws_in_blocks_do_not_depend_on_batch_or_threads():
    from torchflow.core.random import BLOCK

    n = 2 * BLOCK + 5  # three blocks per trial, filled on parallel threads
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(3)  # parallel whatever this process's count (one thread per xdist worker)
        full = TrialStreams(9, 3, "big").normal((3, n))
        alone = TrialStreams(9, [2], "big").normal((1, n))
        torch.set_num_threads(1)
        serial = TrialStreams(9, 3, "big").normal((3, n))
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(full[2], alone[0])
    assert torch.equal(serial, full)
    assert abs(float(full.mean())) < 5 / math.sqrt(full.numel())


def test_select_continues_the_streams():
    a = TrialStreams(1, 4, "k")
    b = TrialStreams(1, 4, "k")
    a.normal((4, 10))
    first = a.normal((4, 10))
    b.normal((4, 10))
    sub = b.select([1, 3])
    assert sub.trials == [1, 3]
    assert torch.equal(sub.normal((2, 10)), first[[1, 3]])
    p = TrialStreams(1, 4, "k", backend="philox")
    q = TrialStreams(1, 4, "k", backend="philox")
    p.uniform((4, 9))
    nxt = p.uniform((4, 9))
    q.uniform((4, 9))
    assert torch.equal(q.select(slice(2, 4)).uniform((2, 9)), nxt[2:])


@pytest.mark.parametrize("backend", ["numpy", "philox"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_stream_moments(backend, dtype):
    """Mean, variance, 4th moment, uniform mean and the cross-trial correlation each within 5
    standard errors of the exact value; the SEs are the exact ones of the sample moments of k
    independent draws: sqrt(1/k), sqrt(2/k) (Var z^2 = 2), sqrt(96/k) (Var z^4 = 105 - 9),
    sqrt(1/(12 k)). With fixed seeds the test is deterministic; 5 SE leaves room for the 6 checks."""
    n = 200_000
    s = TrialStreams(0, 2, "m", backend=backend)
    z = s.normal((2, n), dtype=dtype).double()
    u = s.uniform((2, n), dtype=dtype).double()
    assert z.dtype == torch.float64 and u.min() >= 0 and u.max() < 1
    k = 2 * n
    assert abs(float(z.mean())) < 5 / math.sqrt(k)
    assert abs(float(z.var()) - 1) < 5 * math.sqrt(2 / k)
    assert abs(float((z**4).mean()) - 3) < 5 * math.sqrt(96 / k)
    assert abs(float(u.mean()) - 0.5) < 5 * math.sqrt(1 / 12 / k)
    # the two trials are uncorrelated
    assert abs(float((z[0] * z[1]).mean())) < 5 / math.sqrt(n)


def test_stream_errors():
    s = TrialStreams(0, 4)
    with pytest.raises(ValueError, match=r"multiple of B = 4.*\(6, 2\)"):
        s.normal((6, 2))
    with pytest.raises(TypeError, match="float64 or float32"):
        s.normal((4, 2), dtype=torch.float16)
    with pytest.raises(ValueError, match="seed: expected a non-negative int, got -1"):
        TrialStreams(-1, 4)
    with pytest.raises(ValueError, match="backend"):
        TrialStreams(0, 4, backend="mt")
    with pytest.raises(ValueError, match="trials: expected a positive number of trials, got 0"):
        TrialStreams(0, 0)
    with pytest.raises(TypeError, match=r"generator: expected a torch.Generator .* got NoneType"):
        check_generator(None)
    with pytest.raises(TypeError, match=r"got int \(for a seed, pass torch.Generator\(\).manual_seed\(3\)\)"):
        check_generator(3)


def test_filters_refuse_a_missing_or_int_generator():
    model = SensorNetwork(d=4)
    traj = model.simulate(2, 2, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0])
    bpf = BootstrapParticleFilter(model, n_particles=10)
    with pytest.raises(TypeError, match="BootstrapParticleFilter: generator: expected a torch.Generator"):
        bpf(traj.observations, mean, cov)
    with pytest.raises(TypeError, match="got int"):
        bpf(traj.observations, mean, cov, 0)
    KalmanFilter(model)(traj.observations, mean, cov)  # deterministic filters need none


def _per_trial(res, name):
    return [r for r in res.per_trial if r["filter"] == name]


@pytest.mark.filterwarnings("ignore:memory_budget_gb")
def test_runner_numbers_do_not_depend_on_chunks_budget_or_names():
    """The runner's reproducibility check, scaled down: BPF per-trial numbers are identical (==) for
    every chunk size and memory budget; renaming the filter or adding others changes nothing."""
    model = SensorNetwork(d=16)
    runs = []
    for kw in (
        dict(chunk_size=1),
        dict(chunk_size=3),
        dict(chunk_size=8),
        dict(memory_budget_gb=1e-4),
        dict(memory_budget_gb=4.0),
    ):
        res = run_experiment(
            model,
            {"bpf": BootstrapParticleFilter(model, n_particles=64)},
            trials=8,
            steps=4,
            seed=11,
            progress=False,
            **kw,
        )
        runs.append(_per_trial(res, "bpf"))
    assert all(r == runs[0] for r in runs[1:])
    renamed = run_experiment(
        model,
        {"kf": KalmanFilter(model), "my_bpf": BootstrapParticleFilter(model, n_particles=64)},
        trials=8,
        steps=4,
        seed=11,
        progress=False,
    )
    assert [dict(r, filter="bpf") for r in _per_trial(renamed, "my_bpf")] == runs[0]
    other_seed = run_experiment(
        model, {"bpf": BootstrapParticleFilter(model, n_particles=64)}, trials=8, steps=4, seed=12, progress=False
    )
    assert _per_trial(other_seed, "bpf") != runs[0]


@pytest.mark.parametrize(
    "make",
    [
        lambda m: ParticleFlowParticleFilter(m, flow="ledh", n_particles=40),
        lambda m: ParticleFlowParticleFilter(m, flow="gromov", n_particles=40),
        lambda m: ParticleFlowFilter(m, flow="edh", n_particles=40),
    ],
)
def test_runner_flow_filters_chunk_independent_to_round_off(make):
    """Random draws are identical; batched linear algebra (BLAS blocking depends on the batch
    size) may differ in the last bits, so flow filters agree to round-off."""
    model = AcousticTracking(sigma_w=0.1)
    a = run_experiment(model, {"f": make(model)}, trials=4, steps=3, seed=2, chunk_size=1, progress=False)
    b = run_experiment(model, {"f": make(model)}, trials=4, steps=3, seed=2, chunk_size=4, progress=False)
    for ra, rb in zip(a.per_trial, b.per_trial):
        for k in ("mse", "omat", "log_evidence"):
            assert ra[k] == pytest.approx(rb[k], rel=1e-10, abs=1e-10)


def test_particle_chunks_keep_stochastic_flow_noise():
    """A local stochastic flow run in blocks of particles uses the whole cloud's noise draws."""
    model = AcousticTracking(sigma_w=0.1)
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(3, 3, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    out = []
    for chunk in (None, 7):
        f = ParticleFlowParticleFilter(model, flow="gromov", n_particles=30, particle_chunk=chunk)
        out.append(f(traj.observations, mean, cov, TrialStreams(0, 3, "pfpf")))
    torch.testing.assert_close(out[1].estimates, out[0].estimates, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(out[1].log_evidence, out[0].log_evidence, rtol=1e-10, atol=1e-10)


@cuda
def test_philox_same_bits_on_cuda_and_cpu():
    a = TrialStreams(3, 5, "k", backend="philox").uniform((5, 1000), dtype=F64)
    b = TrialStreams(3, 5, "k", backend="philox").uniform((5, 1000), dtype=F64, device="cuda")
    assert torch.equal(a, b.cpu())
    z = TrialStreams(3, 5, "k").normal((5, 1000), dtype=F64, device="cuda")  # auto -> philox on CUDA
    assert z.device.type == "cuda" and torch.isfinite(z).all()


def test_correlated_streams_record_then_replay():
    """A CorrelatedStreams records its normals on first use and replays them after rewind():
    normals are the tape, uniforms Phi(tape) in [0, 1); a filter run replays bit for bit."""
    from torchflow.core.random import CorrelatedStreams

    s = CorrelatedStreams(3, 4, "k")
    z = s.normal((4, 5), dtype=torch.float64)
    u = s.uniform((8, 3), dtype=torch.float32)  # two draws per trial (trial-major), as one entry
    assert [t.shape for t in s.tape] == [(4, 5), (4, 6)] and s.position == 2
    assert torch.equal(z, s.tape[0])
    phi = torch.special.ndtr(s.tape[1]).reshape(8, 3)
    assert u.dtype == torch.float32 and torch.allclose(u.double(), phi, atol=1e-7)
    s.rewind()
    assert torch.equal(s.normal((4, 5), dtype=torch.float64), z)
    assert torch.equal(s.uniform((8, 3), dtype=torch.float32), u)
    # Phi of a large normal rounds to 1: kept below it
    big = CorrelatedStreams(0, 1, tape=[torch.full((1, 2), 40.0, dtype=torch.float64)])
    for dt in (torch.float64, torch.float32):
        assert float(big.rewind().uniform((1, 2), dtype=dt).max()) < 1.0
    # a filter's run replays exactly, and its first run equals the recorded numbers' run
    from conftest import random_lg

    lg = random_lg(2, 2, seed=1)
    traj = lg.simulate(3, 6, torch.Generator().manual_seed(0))
    mean, cov = lg.initial_belief(traj.states[:, 0])
    f = BootstrapParticleFilter(lg, n_particles=16, ess_threshold=1.0)
    g = CorrelatedStreams(5, 3, f.stream_name)
    first = f(traj.observations, mean, cov, g).log_evidence
    n_draws = len(g.tape)
    again = f(traj.observations, mean, cov, g.rewind()).log_evidence
    assert torch.equal(first, again) and len(g.tape) == n_draws
    # trial b's numbers are its own: a selected trial replays its rows
    one = f(traj.observations[1:2], mean[1:2], cov[1:2], g.select([1]).rewind()).log_evidence
    assert torch.equal(one, first[1:2])


def test_crank_nicolson_moves_keep_the_normal_law():
    """u' = rho u + sqrt(1 - rho^2) eps: mean 0, variance 1 and correlation rho with u (each within
    4 standard errors over 40 000 numbers); where() takes rows per trial."""
    from torchflow.core.random import CorrelatedStreams

    s = CorrelatedStreams(1, 4, "k")
    s.normal((4, 10000), dtype=torch.float64)
    moved = s.crank_nicolson(0.9, seed=2)
    u, v = s.tape[0].reshape(-1), moved.tape[0].reshape(-1)
    n = u.numel()
    assert abs(float(v.mean())) < 4 / math.sqrt(n)
    assert abs(float(v.var()) - 1) < 4 * math.sqrt(2 / n)
    corr = float(torch.corrcoef(torch.stack([u, v]))[0, 1])
    assert abs(corr - 0.9) < 4 * (1 - 0.81) / math.sqrt(n)
    assert torch.equal(s.crank_nicolson(0.9, seed=2).tape[0], moved.tape[0])  # reproducible
    keep = torch.tensor([True, False, True, False])
    merged = moved.where(keep, s)
    assert torch.equal(merged.tape[0][keep], moved.tape[0][keep])
    assert torch.equal(merged.tape[0][~keep], s.tape[0][~keep])
    # a run that asks for other sizes than the tape holds is refused
    with pytest.raises(ValueError, match="draw 0 asks for 3 numbers per trial, but the tape holds 10000"):
        moved.normal((4, 3), dtype=torch.float64)
    with pytest.raises(ValueError, match=r"tape\[0\]: expected a \(B, n\) tensor with B = 4"):
        CorrelatedStreams(0, 4, tape=[torch.zeros(3, 2)])


def test_index_tensor_is_made_once_per_values_and_device():
    """``linalg.index_tensor``: the int64 tensor of the values, the same object on every call with
    equal values and device (no copy from the host per filter step), another for other values."""
    from torchflow.core import linalg

    a = linalg.index_tensor((3, 1, 2), "cpu")
    assert a.dtype == torch.int64 and a.tolist() == [3, 1, 2]
    assert linalg.index_tensor([3, 1, 2], torch.device("cpu")) is a
    assert linalg.index_tensor((1, 2), "cpu") is not a
