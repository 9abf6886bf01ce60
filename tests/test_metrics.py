"""Tests for torchflow.core.metrics (hand-computed cases, float64)."""

import math

import pytest
import torch
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist

from torchflow.core import metrics, tuning
from torchflow.core.metrics import ess, log_evidence_relative_error, lost_tracks, mse, omat, ospa

DT = torch.float64


def t(x):
    return torch.tensor(x, dtype=DT)


# --------------------------------------------------------------------- mse


def test_mse_simple():
    est = t([[[1.0, 2.0], [3.0, 4.0]]])  # (1, 2, 2)
    states = torch.zeros(1, 2, 2, dtype=DT)
    out = mse(est, states)
    assert out.shape == (1, 2)
    torch.testing.assert_close(out, t([[2.5, 12.5]]))


def test_mse_float32_dtype_preserved():
    out = mse(torch.ones(2, 3, 4), torch.zeros(2, 3, 4))
    assert out.dtype == torch.float32
    torch.testing.assert_close(out, torch.ones(2, 3))


# -------------------------------------------------------------------- omat


def test_omat_swapped_targets():
    true = t([[[[0.0, 0.0], [10.0, 0.0]]]])  # (1, 1, 2, 2)
    est = t([[[[10.0, 1.0], [0.0, 2.0]]]])
    # identity: (sqrt(101) + sqrt(104)) / 2; swapped: (2 + 1) / 2 = 1.5
    out = omat(est, true)
    assert out.shape == (1, 1)
    torch.testing.assert_close(out, t([[1.5]]))


def test_omat_3d():
    true = t([[[[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0]]]])
    est = t([[[[0.0, 10.0, 2.0], [1.0, 2.0, 2.0], [10.0, 0.0, 3.0]]]])
    # true0<->est1: 3, true1<->est2: 3, true2<->est0: 2  -> 8/3
    torch.testing.assert_close(omat(est, true), t([[8.0 / 3.0]]))


def test_omat_batched_matches_per_case():
    g = torch.Generator().manual_seed(0)
    true = torch.rand(3, 4, 3, 2, generator=g, dtype=DT) * 10
    est = torch.rand(3, 4, 3, 2, generator=g, dtype=DT) * 10
    out = omat(est, true)
    for b in range(3):
        for s in range(4):
            d = cdist(true[b, s].numpy(), est[b, s].numpy())
            r, c = linear_sum_assignment(d)
            assert out[b, s].item() == pytest.approx(d[r, c].sum() / 3)


def test_omat_scipy_fallback_matches_brute_force(monkeypatch):
    g = torch.Generator().manual_seed(1)
    C = 8
    true = torch.rand(2, 2, C, 2, generator=g, dtype=DT) * 10
    est = torch.rand(2, 2, C, 2, generator=g, dtype=DT) * 10
    fallback = omat(est, true)  # C = 8 > 7: scipy path
    # direct scipy computation
    for b in range(2):
        for s in range(2):
            d = cdist(true[b, s].numpy(), est[b, s].numpy())
            r, c = linear_sum_assignment(d)
            assert fallback[b, s].item() == pytest.approx(d[r, c].sum() / C)
    # brute force over all 8! permutations
    monkeypatch.setattr(tuning, "_current", tuning.Tuning(assignment_brute_force_max=8))
    brute = omat(est, true)
    torch.testing.assert_close(fallback, brute)


def test_omat_gradient_flows_through_fallback():
    g = torch.Generator().manual_seed(2)
    true = torch.rand(1, 1, 8, 2, generator=g, dtype=DT)
    est = torch.rand(1, 1, 8, 2, generator=g, dtype=DT).requires_grad_()
    omat(est, true).sum().backward()
    assert est.grad is not None and torch.isfinite(est.grad).all()


# -------------------------------------------------------------------- ospa


def test_ospa_equal_cardinality():
    X = t([[[[0.0, 0.0], [10.0, 0.0]]]])
    Y = t([[[[10.0, 3.0], [0.0, 4.0]]]])
    torch.testing.assert_close(ospa(X, Y, cutoff=40.0, order=1.0), t([[3.5]]))


def test_ospa_cardinality_penalty():
    X = t([[[[0.0, 0.0]]]])
    Y = t([[[[3.0, 4.0], [100.0, 100.0]]]])
    # (5 + 40 * 1) / 2
    torch.testing.assert_close(ospa(X, Y, cutoff=40.0, order=1.0), t([[22.5]]))


def test_ospa_cutoff_active():
    X = t([[[[0.0, 0.0], [50.0, 0.0]]]])
    Y = t([[[[0.0, 3.0], [200.0, 0.0]]]])
    # (3 + min(10, 150)) / 2
    torch.testing.assert_close(ospa(X, Y, cutoff=10.0, order=1.0), t([[6.5]]))


def test_ospa_order_two():
    X = t([[[[0.0, 0.0], [10.0, 0.0]]]])
    Y = t([[[[10.0, 3.0], [0.0, 4.0], [50.0, 50.0]]]])
    # ((16 + 9 + 5**2 * 1) / 3) ** 0.5
    expected = math.sqrt(50.0 / 3.0)
    torch.testing.assert_close(ospa(X, Y, cutoff=5.0, order=2.0), t([[expected]]))


def test_ospa_empty_sets():
    Y = t([[[[1.0, 2.0], [3.0, 4.0]]]])
    X = torch.zeros(1, 1, 0, 2, dtype=DT)
    torch.testing.assert_close(ospa(X, Y, cutoff=7.0), t([[7.0]]))
    torch.testing.assert_close(ospa(Y, X, cutoff=7.0), t([[7.0]]))
    torch.testing.assert_close(ospa(X, X.clone(), cutoff=7.0), t([[0.0]]))


def test_ospa_swap_symmetry():
    g = torch.Generator().manual_seed(3)
    X = torch.rand(2, 3, 2, 2, generator=g, dtype=DT) * 20
    Y = torch.rand(2, 3, 4, 2, generator=g, dtype=DT) * 20
    for p in (1.0, 2.0):
        a = ospa(X, Y, cutoff=8.0, order=p)
        b = ospa(Y, X, cutoff=8.0, order=p)
        assert a.shape == (2, 3)
        torch.testing.assert_close(a, b)


def test_ospa_equals_omat_when_below_cutoff():
    g = torch.Generator().manual_seed(4)
    true = torch.rand(3, 5, 4, 2, generator=g, dtype=DT) * 100
    perm = torch.tensor([2, 0, 3, 1])
    est = true[:, :, perm] + torch.randn(3, 5, 4, 2, generator=g, dtype=DT) * 3
    o = omat(est, true)
    assert (o > 0).all()
    torch.testing.assert_close(ospa(est, true, cutoff=40.0, order=1.0), o)


def test_ospa_scipy_fallback_matches_brute_force(monkeypatch):
    g = torch.Generator().manual_seed(5)
    X = torch.rand(2, 2, 3, 2, generator=g, dtype=DT) * 10
    Y = torch.rand(2, 2, 8, 2, generator=g, dtype=DT) * 10
    fallback = ospa(X, Y, cutoff=6.0, order=2.0)
    monkeypatch.setattr(tuning, "_current", tuning.Tuning(assignment_brute_force_max=8))
    torch.testing.assert_close(fallback, ospa(X, Y, cutoff=6.0, order=2.0))


# --------------------------------------------------------------------- ess


def test_ess_uniform_and_one_hot():
    torch.testing.assert_close(ess(torch.zeros(2, 3, 10, dtype=DT)), torch.full((2, 3), 10.0, dtype=DT))
    lw = torch.full((2, 5), -math.inf, dtype=DT)
    lw[0, 1] = 0.0
    lw[1, 4] = 123.0
    torch.testing.assert_close(ess(lw), t([1.0, 1.0]))


def test_ess_hand_value_and_shift_invariance():
    lw = torch.log(t([1.0, 1.0, 2.0]))  # normalised [.25, .25, .5] -> 1 / 0.375
    torch.testing.assert_close(ess(lw), t(8.0 / 3.0))
    g = torch.Generator().manual_seed(6)
    lw = torch.randn(4, 50, generator=g, dtype=DT)
    ref = ess(lw)
    torch.testing.assert_close(ess(lw + 1000.0), ref)
    torch.testing.assert_close(ess(lw - 1000.0), ref)


# ------------------------------------------------- log evidence, lost tracks


def test_log_evidence_relative_error():
    out = log_evidence_relative_error(t([-90.0, -100.0, -120.0]), t([-100.0, -100.0, -100.0]))
    torch.testing.assert_close(out, t([0.01, 0.0, 0.04]))


def test_lost_tracks():
    o = t([[1.0, 2.0, 4.0], [2.0, 2.0, 2.0], [0.5, 0.5, 0.5]])  # means 7/3, 2, 0.5
    out = lost_tracks(o, threshold=2.0)
    assert out.dtype == torch.bool
    assert out.tolist() == [True, False, False]
    assert lost_tracks(o, threshold=0.1).tolist() == [True, True, True]


# ------------------------------------------------------------ input errors


@pytest.mark.parametrize(
    "call, name",
    [
        (lambda: mse(torch.zeros(4, 10, 2), torch.zeros(4, 10, 3)), "estimates"),
        (lambda: mse(torch.zeros(4, 10, 3), torch.zeros(4, 10)), "states"),
        (lambda: omat(torch.zeros(2, 3, 4, 2), torch.zeros(2, 3, 5, 2)), "est_positions"),
        (lambda: omat(torch.zeros(2, 3, 4, 4), torch.zeros(2, 3, 4, 4)), "true_positions"),
        (lambda: omat(torch.zeros(2, 3, 4), torch.zeros(2, 3, 4)), "true_positions"),
        (lambda: ospa(torch.zeros(2, 3, 4, 2), torch.zeros(2, 4, 4, 2)), "Y"),
        (lambda: ospa(torch.zeros(2, 3, 4), torch.zeros(2, 3, 4, 2)), "X"),
        (lambda: ospa(torch.zeros(2, 3, 4, 2), torch.zeros(2, 3, 4, 2), cutoff=0.0), "cutoff"),
        (lambda: ospa(torch.zeros(2, 3, 4, 2), torch.zeros(2, 3, 4, 2), order=0.5), "order"),
        (lambda: ess(torch.zeros(3, 0)), "log_weights"),
        (lambda: ess(torch.zeros(3, dtype=torch.long)), "log_weights"),
        (lambda: log_evidence_relative_error(torch.zeros(3), torch.zeros(4)), "log_evidence"),
        (lambda: log_evidence_relative_error(torch.zeros(3), torch.zeros(3, 1)), "reference"),
        (lambda: lost_tracks(torch.zeros(3)), "omat_per_step"),
    ],
)
def test_bad_input_raises_value_error(call, name):
    with pytest.raises(ValueError, match=rf"^{name}: expected"):
        call()


def test_error_message_contains_shapes():
    with pytest.raises(ValueError) as exc:
        mse(torch.zeros(4, 10, 2), torch.zeros(4, 10, 3))
    assert str(exc.value) == "estimates: expected (B, T, d) matching states (4, 10, 3), got (4, 10, 2)"


# ---- OSPA over sets of varying cardinality (masks) --------------------------------------------
def _ospa_reference(x, y, c, p):
    """Schuhmacher et al.'s OSPA of two lists of points by scipy's assignment (Stone Soup's
    definition: the cut-off distance to the power p, mean over max(|x|, |y|), then the p-th root)."""
    import numpy
    from scipy.optimize import linear_sum_assignment

    m, n = len(x), len(y)
    if m == 0 and n == 0:
        return 0.0
    if m == 0 or n == 0:
        return c
    d = numpy.minimum(numpy.linalg.norm(numpy.asarray(x)[:, None] - numpy.asarray(y)[None], axis=-1), c) ** p
    r, col = linear_sum_assignment(d)
    return ((d[r, col].sum() + c**p * abs(m - n)) / max(m, n)) ** (1 / p)


def test_ospa_masks_hand_computed():
    # X = {(0,0)}, Y = {(3,4), (100,0)}: match (0,0)-(3,4) (5), the other Y is missed: (5 + 10) / 2 = 7.5
    X = torch.tensor([[[[0.0, 0.0], [9.0, 9.0]]]], dtype=torch.float64)
    Y = torch.tensor([[[[3.0, 4.0], [100.0, 0.0], [7.0, 7.0]]]], dtype=torch.float64)
    xm = torch.tensor([[[True, False]]])
    ym = torch.tensor([[[True, True, False]]])
    assert abs(float(metrics.ospa(X, Y, cutoff=10.0, order=1.0, X_mask=xm, Y_mask=ym)) - 7.5) < 1e-12
    # order 2: sqrt((25 + 100) / 2)
    assert abs(float(metrics.ospa(X, Y, 10.0, 2.0, xm, ym)) - math.sqrt(62.5)) < 1e-12
    # both empty: 0; one empty: the cut-off
    none = torch.zeros(1, 1, 2, dtype=torch.bool)
    assert float(metrics.ospa(X, Y, 10.0, 1.0, none, torch.zeros(1, 1, 3, dtype=torch.bool))) == 0.0
    assert float(metrics.ospa(X, Y, 10.0, 1.0, none, ym)) == 10.0


def test_ospa_masks_match_the_reference_and_the_unmasked_metric():
    g = torch.Generator().manual_seed(0)
    B, T, m, n = 6, 5, 4, 5
    X = torch.rand(B, T, m, 3, generator=g, dtype=torch.float64) * 40
    Y = torch.rand(B, T, n, 3, generator=g, dtype=torch.float64) * 40
    xm = torch.rand(B, T, m, generator=g) < 0.7
    ym = torch.rand(B, T, n, generator=g) < 0.7
    got = metrics.ospa(X, Y, cutoff=30.0, order=1.0, X_mask=xm, Y_mask=ym)
    for b in range(B):
        for t in range(T):
            ref = _ospa_reference(X[b, t][xm[b, t]].numpy(), Y[b, t][ym[b, t]].numpy(), 30.0, 1.0)
            assert abs(float(got[b, t]) - ref) < 1e-10
    full = metrics.ospa(X, Y, 30.0, 2.0)
    torch.testing.assert_close(metrics.ospa(X, Y, 30.0, 2.0, torch.ones(B, T, m, dtype=torch.bool)), full)


def test_ospa_masks_bad_input():
    X = torch.zeros(1, 1, 2, 2, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"X_mask: expected a bool tensor \(B, T, m\) = \(1, 1, 2\), got \(1, 1, 3\)"):
        metrics.ospa(X, X, X_mask=torch.ones(1, 1, 3, dtype=torch.bool))
    with pytest.raises(ValueError, match="Y_mask: expected a bool tensor"):
        metrics.ospa(X, X, Y_mask=torch.ones(1, 1, 2))
