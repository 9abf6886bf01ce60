"""Tests for torchflow.core.resampling."""

import math

import pytest
import torch

from torchflow.core.resampling import (
    RESAMPLERS,
    effective_sample_size,
    gather_particles,
    get_resampler,
    normalize_log_weights,
    resample_if_needed,
    residual,
    systematic,
)

SCHEMES = sorted(RESAMPLERS)

# N = 10 weights chosen so that no N * w_i is close to an integer:
# N w = [0.3, 1.7, 0.55, 2.1, 0.05, 1.2, 0.95, 1.45, 0.8, 0.9].
W = torch.tensor(
    [0.03, 0.17, 0.055, 0.21, 0.005, 0.12, 0.095, 0.145, 0.08, 0.09],
    dtype=torch.float64,
)
N = W.numel()
B = 2000


def _gen(seed=0):
    g = torch.Generator()
    g.manual_seed(seed)
    return g


def _counts(indices, n):
    """Offspring counts (B, n) from indices (B, M)."""
    counts = torch.zeros(indices.shape[0], n, dtype=torch.int64)
    return counts.scatter_add_(1, indices, torch.ones_like(indices))


def _batch_log_w(dtype=torch.float64):
    return W.log().to(dtype).expand(B, N).clone()


# ---------------------------------------------------------------------------
# Weight utilities
# ---------------------------------------------------------------------------
def test_normalize_log_weights():
    lw = torch.tensor([[0.0, 1.0, 2.0], [-1000.0, -1001.0, -float("inf")]])
    out = normalize_log_weights(lw)
    assert out.shape == lw.shape
    torch.testing.assert_close(torch.logsumexp(out, dim=1), torch.zeros(2))
    assert out[1, 2] == -float("inf")


def test_ess_uniform_and_one_hot():
    lw_uniform = torch.full((3, 7), 2.5, dtype=torch.float64)
    torch.testing.assert_close(effective_sample_size(lw_uniform), torch.full((3,), 7.0, dtype=torch.float64))
    lw_hot = torch.full((2, 7), -float("inf"))
    lw_hot[0, 3] = 0.0
    lw_hot[1, 6] = -4.0
    torch.testing.assert_close(effective_sample_size(lw_hot), torch.ones(2))


def test_ess_matches_definition():
    lw = torch.randn(5, 9, generator=_gen(1), dtype=torch.float64)
    w = torch.softmax(lw, dim=1)
    torch.testing.assert_close(effective_sample_size(lw), 1.0 / (w**2).sum(dim=1))


# ---------------------------------------------------------------------------
# Statistical tests
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("scheme", SCHEMES)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_mean_offspring_unbiased(scheme, dtype):
    idx = RESAMPLERS[scheme](_batch_log_w(dtype), _gen(123))
    assert idx.shape == (B, N) and idx.dtype == torch.int64
    assert int(idx.min()) >= 0 and int(idx.max()) < N
    mean = _counts(idx, N).double().mean(dim=0)
    # Tolerance: for multinomial resampling the offspring count of particle i
    # is Binomial(N, w_i) with sd sqrt(N w_i (1 - w_i)), so the mean over B
    # i.i.d. trials has standard error sqrt(N w_i (1 - w_i) / B). Systematic,
    # stratified and residual resampling are unbiased with lower variance, so
    # the multinomial standard error is a valid conservative bound. 5 standard
    # errors => false-failure probability ~6e-7 per particle (seeded anyway).
    se = torch.sqrt(N * W * (1 - W) / B)
    assert torch.all((mean - N * W).abs() < 5 * se), (mean, N * W)


def _random_log_weights(b, n, seed):
    return 2.0 * torch.randn(b, n, generator=_gen(seed), dtype=torch.float64)


def test_systematic_counts_floor_ceil():
    lw = _random_log_weights(500, 17, seed=7)
    nw = 17 * torch.softmax(lw, dim=1)
    counts = _counts(systematic(lw, _gen(3)), 17)
    assert torch.all(counts >= torch.floor(nw))
    assert torch.all(counts <= torch.ceil(nw))
    # also on the fixed weight vector
    counts = _counts(systematic(_batch_log_w(), _gen(4)), N)
    assert torch.all(counts >= torch.floor(N * W)) and torch.all(counts <= torch.ceil(N * W))


@pytest.mark.parametrize("scheme", ["systematic", "stratified"])
def test_inverse_cdf_schemes_sorted(scheme):
    idx = RESAMPLERS[scheme](_random_log_weights(200, 13, seed=8), _gen(5))
    assert torch.all(idx[:, 1:] >= idx[:, :-1])


def test_residual_deterministic_part():
    lw = _random_log_weights(500, 17, seed=9)
    nw = 17 * torch.softmax(lw, dim=1)
    counts = _counts(residual(lw, _gen(6)), 17)
    assert torch.all(counts >= torch.floor(nw))
    assert torch.all(counts.sum(dim=1) == 17)
    counts = _counts(residual(_batch_log_w(), _gen(7)), N)
    assert torch.all(counts >= torch.floor(N * W))


# ---------------------------------------------------------------------------
# Deterministic edge cases
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("scheme", ["systematic", "residual"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("n", [1, 7, 10, 100])
def test_uniform_weights_each_particle_once(scheme, dtype, n):
    lw = torch.full((300, n), -3.7, dtype=dtype)
    idx = RESAMPLERS[scheme](lw, _gen(11))
    expected = torch.arange(n).expand(300, n)
    if scheme == "systematic":
        assert torch.equal(idx, expected)
    else:
        assert torch.equal(idx.sort(dim=1).values, expected)


@pytest.mark.parametrize("scheme", SCHEMES)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_one_hot_weights(scheme, dtype):
    n = 8
    hot = torch.tensor([0, 3, 7, 5])
    lw = torch.full((4, n), -float("inf"), dtype=dtype)
    lw[torch.arange(4), hot] = 1.3
    idx = RESAMPLERS[scheme](lw, _gen(12))
    assert torch.equal(idx, hot[:, None].expand(4, n))


@pytest.mark.parametrize("scheme", SCHEMES)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_zero_weights_never_selected(scheme, dtype):
    n = 10
    lw = torch.randn(500, n, generator=_gen(13)).to(dtype)
    zero = torch.zeros(500, n, dtype=torch.bool)
    zero[:, ::2] = True  # leading and interior zeros
    zero[250:] = torch.zeros(n, dtype=torch.bool)
    zero[250:, n // 2 :] = True  # trailing zeros
    lw = lw.masked_fill(zero, -float("inf"))
    idx = RESAMPLERS[scheme](lw, _gen(14))
    assert not torch.any(zero.gather(1, idx))


@pytest.mark.parametrize("scheme", SCHEMES)
def test_same_seed_same_indices(scheme):
    lw = _random_log_weights(50, 12, seed=15)
    a = RESAMPLERS[scheme](lw, _gen(42))
    b = RESAMPLERS[scheme](lw, _gen(42))
    c = RESAMPLERS[scheme](lw, _gen(43))
    assert torch.equal(a, b)
    assert not torch.equal(a, c)


@pytest.mark.parametrize("scheme", SCHEMES)
def test_default_generator(scheme):
    idx = RESAMPLERS[scheme](_random_log_weights(4, 6, seed=16))
    assert idx.shape == (4, 6) and idx.dtype == torch.int64


def test_get_resampler():
    for name in SCHEMES:
        assert get_resampler(name) is RESAMPLERS[name]
    assert set(RESAMPLERS) == {"multinomial", "systematic", "stratified", "residual"}
    with pytest.raises(ValueError, match="name") as info:
        get_resampler("bogus")
    for name in SCHEMES:
        assert name in str(info.value)


# ---------------------------------------------------------------------------
# resample_if_needed
# ---------------------------------------------------------------------------
def _mixed_batch():
    n = 6
    lw = torch.zeros(4, n, dtype=torch.float64)  # rows 0, 2: uniform (ESS = N)
    lw[1] = torch.tensor([10.0, 0, 0, 0, 0, 0])  # ESS ~ 1
    lw[3] = torch.tensor([0.0, -50, -50, 5, -50, -50])  # ESS ~ 1
    return lw


@pytest.mark.parametrize("scheme", SCHEMES)
def test_resample_if_needed_only_low_ess(scheme):
    lw = _mixed_batch() + 3.0  # unnormalised
    n = lw.shape[1]
    idx, resampled, new_lw = resample_if_needed(lw, _gen(17), scheme=scheme, ess_threshold=0.5)
    assert torch.equal(resampled, torch.tensor([False, True, False, True]))
    keep = ~resampled
    assert torch.equal(idx[keep], torch.arange(n).expand(int(keep.sum()), n))
    torch.testing.assert_close(new_lw[keep], normalize_log_weights(lw)[keep])
    torch.testing.assert_close(new_lw[resampled], torch.full((2, n), -math.log(n), dtype=torch.float64))
    assert idx.dtype == torch.int64 and new_lw.dtype == lw.dtype
    # heavy particles dominate the resampled rows
    assert torch.all(idx[1] == 0) and torch.all(idx[3] == 3)


def test_resample_if_needed_thresholds():
    lw = _mixed_batch()
    n = lw.shape[1]
    idx, resampled, new_lw = resample_if_needed(lw, _gen(18), ess_threshold=0.0)
    assert not resampled.any()
    assert torch.equal(idx, torch.arange(n).expand(4, n))
    torch.testing.assert_close(new_lw, normalize_log_weights(lw))
    _, resampled, _ = resample_if_needed(lw, _gen(18), ess_threshold=1.0)
    assert resampled[1] and resampled[3]


def test_resample_if_needed_float32():
    lw = _mixed_batch().float()
    idx, resampled, new_lw = resample_if_needed(lw, _gen(19), scheme="residual")
    assert new_lw.dtype == torch.float32 and idx.dtype == torch.int64
    assert torch.equal(resampled, torch.tensor([False, True, False, True]))


# ---------------------------------------------------------------------------
# gather_particles
# ---------------------------------------------------------------------------
def test_gather_particles_shapes_and_values():
    b, n, d = 3, 5, 2
    x = torch.randn(b, n, d, generator=_gen(20))
    cov = torch.randn(b, n, d, d, generator=_gen(21))
    idx = systematic(torch.randn(b, n, generator=_gen(22)), _gen(23))
    gx = gather_particles(x, idx)
    gc = gather_particles(cov, idx)
    assert gx.shape == (b, n, d) and gc.shape == (b, n, d, d)
    for i in range(b):
        for j in range(n):
            assert torch.equal(gx[i, j], x[i, idx[i, j]])
            assert torch.equal(gc[i, j], cov[i, idx[i, j]])
    assert gather_particles(torch.randn(b, n), idx).shape == (b, n)


def test_gather_particles_bad_input():
    x = torch.randn(3, 5, 2)
    with pytest.raises(ValueError, match="indices"):
        gather_particles(x, torch.zeros(3, dtype=torch.int64))
    with pytest.raises(ValueError, match="indices"):
        gather_particles(x, torch.zeros(3, 5))
    with pytest.raises(ValueError, match="indices"):
        gather_particles(x, torch.zeros(2, 5, dtype=torch.int64))
    with pytest.raises(ValueError, match="x"):
        gather_particles(torch.randn(3), torch.zeros(3, 5, dtype=torch.int64))


# ---------------------------------------------------------------------------
# Bad input
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("scheme", SCHEMES)
def test_bad_log_weights(scheme):
    fn = RESAMPLERS[scheme]
    with pytest.raises(ValueError, match=r"log_weights.*\(B, N\)"):
        fn(torch.zeros(5))
    with pytest.raises(ValueError, match="log_weights.*floating"):
        fn(torch.zeros(2, 5, dtype=torch.int64))
    with pytest.raises(ValueError, match="log_weights"):
        fn(torch.full((2, 5), -float("inf")))
    with pytest.raises(ValueError, match="log_weights"):
        fn(torch.tensor([[0.0, float("nan")]]))


def test_bad_inputs_utilities():
    with pytest.raises(ValueError, match="log_weights"):
        normalize_log_weights(torch.zeros(5))
    with pytest.raises(ValueError, match="log_weights"):
        effective_sample_size(torch.zeros(1, 2, 3))
    lw = torch.zeros(2, 5)
    with pytest.raises(ValueError, match="log_weights"):
        resample_if_needed(torch.zeros(5), None)
    with pytest.raises(ValueError, match="scheme") as info:
        resample_if_needed(lw, None, scheme="bogus")
    assert "systematic" in str(info.value)
    for bad in (1.5, -0.1, float("nan"), "0.5"):
        with pytest.raises(ValueError, match="ess_threshold"):
            resample_if_needed(lw, None, ess_threshold=bad)


# ---------------------------------------------------------------------------
# Sorted resampling (correlated pseudo-marginal MCMC)
# ---------------------------------------------------------------------------
def test_hilbert_index_is_a_curve_through_every_cell():
    """Every cell of the grid gets its own position, and consecutive positions are adjacent cells."""
    import itertools

    from torchflow.core.resampling import hilbert_index

    for d, bits in [(2, 1), (2, 4), (3, 3), (4, 2)]:
        cells = torch.tensor(list(itertools.product(range(2**bits), repeat=d)))
        h = hilbert_index(cells, bits)
        assert sorted(h.tolist()) == list(range(2 ** (bits * d)))
        walk = cells[torch.argsort(h)]
        assert int((walk[1:] - walk[:-1]).abs().sum(-1).max()) == 1


@pytest.mark.parametrize("d", [1, 3])
@pytest.mark.parametrize("sort", ["first", "principal", "hilbert"])
def test_sorted_resampling_keeps_the_weighted_cloud(sort, d):
    """With particles sorted first, systematic resampling still gives particle i floor(N w_i) or
    ceil(N w_i) copies, the resampled particles leave in sorted order (d = 1), and a trial that is
    not resampled keeps its weighted cloud (reordered)."""
    from torchflow.core.resampling import Resampler, sort_order

    g = torch.Generator().manual_seed(0)
    B, N = 6, 50
    x = torch.randn(B, N, d, generator=g, dtype=torch.float64)
    lw = normalize_log_weights(
        torch.randn(B, N, generator=g, dtype=torch.float64)
        * torch.tensor([3.0, 3.0, 3.0, 0.01, 0.01, 0.01], dtype=torch.float64)[:, None]
    )  # the last three: ESS high
    r = Resampler(d, ess_threshold=0.9, sort=sort)
    tag = torch.arange(N, dtype=torch.float64).expand(B, N)
    out, lw_new, _, extras, resampled = r(x, lw, torch.Generator().manual_seed(1), extras={"tag": tag})
    assert resampled.tolist() == [True] * 3 + [False] * 3
    src = extras["tag"].long()  # each new particle's source
    assert torch.equal(out, gather_particles(x, src))
    counts = torch.zeros(B, N, dtype=torch.int64).scatter_add_(1, src, torch.ones_like(src))
    nw = lw.exp() * N
    ok = (counts >= nw.floor() - 1e-9) & (counts <= nw.ceil() + 1e-9)
    assert bool(ok[:3].all())
    for b in range(3, 6):  # a permutation, with the weights following their particles
        assert sorted(src[b].tolist()) == list(range(N))
        assert torch.allclose(lw_new[b], lw[b, src[b]])
    order = sort_order(x, lw, sort)
    assert torch.equal(src[3:], order[3:])
    if d == 1:
        assert bool((out[:3, 1:, 0] >= out[:3, :-1, 0]).all())


def test_sorted_resampling_moves_continuously_with_the_uniform():
    """d = 1: nudging the systematic uniform (through a CorrelatedStreams tape) moves the sorted
    resampled cloud by far less than the unsorted one (an index that shifts picks a neighbour)."""
    from torchflow.core.random import CorrelatedStreams
    from torchflow.core.resampling import Resampler

    g = torch.Generator().manual_seed(2)
    B, N = 200, 100
    x = torch.randn(B, N, 1, generator=g, dtype=torch.float64)
    lw = normalize_log_weights(torch.randn(B, N, generator=g, dtype=torch.float64))
    z = torch.randn(B, 1, generator=g, dtype=torch.float64)
    moved = {}
    for sort in (None, "first"):
        r = Resampler(1, ess_threshold=1.0, sort=sort)
        a = r(x, lw, CorrelatedStreams(0, B, tape=[z]))[0]
        b = r(x, lw, CorrelatedStreams(0, B, tape=[z + 0.02]))[0]
        moved[sort] = float((a - b).abs().mean())
    assert moved["first"] < 0.1 * moved[None], moved
    # already sorted particles: the same numbers as no sort
    xs = x.sort(1)[0]
    same = [
        Resampler(1, ess_threshold=1.0, sort=s)(xs, lw, torch.Generator().manual_seed(3))[0] for s in (None, "first")
    ]
    assert torch.equal(same[0], same[1])


def test_sort_errors():
    from torchflow.core.resampling import Resampler, sort_order

    with pytest.raises(ValueError, match=r"sort: expected None or one of \('first', 'principal', 'hilbert'\)"):
        Resampler(2, sort="value")
    with pytest.raises(ValueError, match="at most 62 dimensions"):
        sort_order(torch.zeros(1, 3, 63, dtype=torch.float64), torch.zeros(1, 3, dtype=torch.float64), "hilbert")


# ---------------------------------------------------------------------------
# The one-pass inversion and the CPU's resampling of only the trials that need it
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("per_trial", [1, None])
@pytest.mark.parametrize("shape", [(1, 4096), (3, 1000), (40, 77)])
def test_one_pass_inversion_equals_the_binary_search(per_trial, shape):
    """The stratified/systematic positions inverted in one pass give exactly the binary search's
    indices: random weights with zero-weight particles, uniform weights (integer CDF steps) and
    uniforms at 0 and just below 1 (where ``i + u`` rounds up to the next integer)."""
    from torchflow.core import resampling as R

    b, n = shape
    g = torch.Generator().manual_seed(3)
    i = torch.arange(n, dtype=torch.float64)
    for weights in ("random", "uniform", "spiky"):
        lw = (
            torch.randn(b, n, dtype=torch.float64, generator=g) * (2 if weights == "random" else 25)
            if weights != "uniform"
            else torch.zeros(b, n, dtype=torch.float64)
        )
        if weights == "random":
            lw[:, ::5] = float("-inf")
        S = R._scaled_cdf(R._unnormalized_weights(lw))
        draws = [
            torch.rand(b, n if per_trial is None else 1, dtype=torch.float64, generator=g),
            torch.zeros(b, 1, dtype=torch.float64),
            torch.full((b, 1), 1 - 2.0**-53, dtype=torch.float64),
        ]
        for u in draws:
            p = R._below(i + u, i + 1.0).expand(b, n)
            with monkeypatch_threshold(R, 0):
                fast = R._invert_strata(S, p)
            assert torch.equal(fast, R._invert_cdf(S, p)), (weights, u.flatten()[:2])


class monkeypatch_threshold:
    """Set ``_LINEAR_INVERSION_MIN`` within a block (0: always the one-pass inversion)."""

    def __init__(self, module, value):
        self.module, self.value = module, value

    def __enter__(self):
        self.old, self.module._LINEAR_INVERSION_MIN = self.module._LINEAR_INVERSION_MIN, self.value

    def __exit__(self, *exc):
        self.module._LINEAR_INVERSION_MIN = self.old


@pytest.mark.parametrize("scheme", ["systematic", "stratified", "multinomial", "residual"])
@pytest.mark.parametrize("sort", [None, "first"])
def test_cpu_resamples_only_the_trials_that_need_it(scheme, sort):
    """``host_reads_cpu=1`` (compute only the trials whose ESS triggers; nothing when none does)
    and ``0`` (every trial, as on a GPU) give the same particles, weights, per-particle extras and
    flags, and leave the generator in the same state: for batches where no trial, some trials and
    every trial resample."""
    from torchflow.core import tuning
    from torchflow.core.resampling import Resampler

    g = torch.Generator().manual_seed(11)
    B, N, d = 6, 50, 2
    x = torch.randn(B, N, d, dtype=torch.float64, generator=g)
    extra = torch.randn(B, N, 3, dtype=torch.float64, generator=g)
    flat = torch.zeros(B, N, dtype=torch.float64)
    peaked = torch.randn(B, N, dtype=torch.float64, generator=g) * 4
    cases = {"none": flat, "all": peaked, "some": torch.where(torch.arange(B)[:, None] % 2 == 0, peaked, flat)}
    rs = Resampler(d, scheme=scheme, ess_threshold=0.5, sort=sort)
    for name, lw in cases.items():
        lw = lw - torch.logsumexp(lw, 1, keepdim=True)
        out = {}
        for rows in (1, 0):
            gen = torch.Generator().manual_seed(5)
            with tuning.tuned(host_reads_cpu=rows):
                p, w, _, ex, r = rs(x, lw, gen, extras={"e": extra})
            out[rows] = (p, w, ex["e"], r, torch.rand(4, generator=gen, dtype=torch.float64))
        expected = {"none": 0, "all": B, "some": B // 2}[name]
        assert int(out[1][3].sum()) == expected, name
        for a, b in zip(out[1], out[0]):
            assert torch.equal(a, b), (scheme, sort, name)


def test_a_users_scheme_is_computed_for_every_trial():
    """A scheme a user registers has no split into draws and inversion: it is called for every
    trial on the CPU too, and the identity kept where the ESS did not trigger."""
    from torchflow.core import resampling as R

    calls = []

    def reverse(log_weights, generator=None, *, validate=True):
        calls.append(tuple(log_weights.shape))
        return torch.arange(log_weights.shape[1]).flip(0).expand(log_weights.shape).clone()

    lw = torch.stack([torch.zeros(5), torch.tensor([9.0, 0, 0, 0, 0])]).double()
    idx, resampled, _ = R._resample_rows(lw, normalize_log_weights(lw), None, reverse, 0.5)
    assert calls == [(2, 5)] and resampled.tolist() == [False, True]
    assert idx.tolist() == [[0, 1, 2, 3, 4], [4, 3, 2, 1, 0]]


def test_host_reads_only_on_plain_cpu_tensors():
    """``reads_host``: a plain CPU tensor with ``host_reads_cpu`` on; not under ``tuning``
    ``host_reads_cpu=0``, nor inside a ``torch.func`` transform (where ``bool(t)`` of a wrapped
    tensor fails or traces)."""
    from torchflow.core import tuning
    from torchflow.core.resampling import reads_host

    x = torch.ones(3, dtype=torch.float64)
    assert reads_host(x)
    with tuning.tuned(host_reads_cpu=0):
        assert not reads_host(x)
    seen = []

    def f(t):
        seen.append(reads_host(t))
        return t.sum()

    torch.func.grad(f)(x)
    torch.func.vmap(f)(x.reshape(3, 1))
    assert seen == [False, False]
