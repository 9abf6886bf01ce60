"""Loopy belief propagation for data association against brute-force enumeration."""

import itertools

import pytest
import torch

from torchflow.tdoa.association import loopy_association


def brute_force(beta, xi):
    """Exact marginals p(a_k = m): every valid joint association (each measurement used by at most
    one PO) weighted by prod_k beta_k(a_k) prod_{m unused} xi(m)."""
    K, M1 = beta.shape
    P = torch.zeros(K, M1, dtype=torch.float64)
    Z = 0.0
    for a in itertools.product(range(M1), repeat=K):
        used = [m for m in a if m > 0]
        if len(used) != len(set(used)):
            continue
        w = 1.0
        for k, m in enumerate(a):
            w *= float(beta[k, m])
        for m in range(1, M1):
            if m not in used:
                w *= float(xi[m - 1])
        Z += w
        for k, m in enumerate(a):
            P[k, m] += w
    return P / Z


def test_two_sources_one_clutter_point_no_missed_detection():
    """p_d = 1 and r = 1 (beta_k(0) = 0), measurements 1, 2 from the sources, 3 clutter. Loopy BP
    is approximate on this loopy graph: its marginals are within 5e-3 of the enumeration (measured
    2.7e-3), and it puts each source on its own measurement."""
    beta = torch.tensor([[[0.0, 5.0, 0.2, 0.1], [0.0, 0.3, 4.0, 0.2]]], dtype=torch.float64)
    xi = torch.tensor([[1.01, 1.01, 1.01]], dtype=torch.float64)
    got = loopy_association(beta, xi, iterations=100).probabilities[0]
    exact = brute_force(beta[0], xi[0])
    assert (got - exact).abs().max() < 5e-3, (got, exact)
    assert got[0].argmax() == 1 and got[1].argmax() == 2
    torch.testing.assert_close(got.sum(-1), torch.ones(2, dtype=torch.float64))


def test_one_object_is_exact_and_padding_is_ignored():
    """With one PO the graph is a tree: BP is exact. Padded POs and measurements change nothing."""
    g = torch.Generator().manual_seed(0)
    beta = torch.rand(1, 1, 4, generator=g, dtype=torch.float64) + 0.1
    xi = 1 + torch.rand(1, 3, generator=g, dtype=torch.float64)
    got = loopy_association(beta, xi).probabilities[0]
    torch.testing.assert_close(got, brute_force(beta[0], xi[0]), rtol=1e-12, atol=1e-12)
    pb = torch.cat(
        [
            torch.cat([beta, torch.rand(1, 1, 4, generator=g, dtype=torch.float64)], 1),
            torch.rand(1, 2, 1, generator=g, dtype=torch.float64),
        ],
        -1,
    )  # a padded PO and measurement
    px = torch.cat([xi, torch.tensor([[3.0]], dtype=torch.float64)], -1)
    om = torch.tensor([[True, False]])
    mm = torch.tensor([[True, True, True, False]])
    res = loopy_association(pb, px, om, mm)
    torch.testing.assert_close(res.probabilities[0, 0, :4], got[0], rtol=1e-12, atol=1e-12)
    assert (res.probabilities[0, 1] == 0).all() and res.new_existence[0, 3] == 0


def test_random_cases_against_enumeration_and_batched():
    """Three POs with missed detections, four measurements, 50 random (often very ambiguous) cases
    in one batched call. Loopy BP's marginals are approximate: measured largest error 0.10 and mean
    of the per-case largest errors 0.016 against the enumeration; allowed 0.15 and 0.03. The
    messages have converged: they are a fixed point of one more pass to 1e-10."""
    g = torch.Generator().manual_seed(1)
    B, K, M = 50, 3, 4
    beta = torch.rand(B, K, M + 1, generator=g, dtype=torch.float64) ** 3 * 5
    xi = 1 + torch.rand(B, M, generator=g, dtype=torch.float64)
    got = loopy_association(beta, xi, iterations=100).probabilities
    err = torch.stack([(got[b] - brute_force(beta[b], xi[b])).abs().max() for b in range(B)])
    assert err.max() < 0.15 and err.mean() < 0.03, (err.max(), err.mean())
    a, b = loopy_association(beta, xi, iterations=100), loopy_association(beta, xi, iterations=101)
    torch.testing.assert_close(a.nu, b.nu, rtol=1e-10, atol=1e-10)


def test_bad_input():
    beta = torch.ones(1, 2, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"xi: expected \(B, M\) = \(1, 2\)"):
        loopy_association(beta, torch.ones(1, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="iterations"):
        loopy_association(beta, torch.ones(1, 2, dtype=torch.float64), iterations=0)
    with pytest.raises(ValueError, match="object_mask"):
        loopy_association(beta, torch.ones(1, 2, dtype=torch.float64), object_mask=torch.ones(1, 3, dtype=torch.bool))


def test_a_certain_object_with_one_measurement_stays_finite():
    """r = 1 and p_d = 1 give beta_k(0) = 0: the leave-one-out sums are formed by exclusion, so there
    is no total-minus-own cancellation (which gave nan) and the PO takes its measurement."""
    beta = torch.tensor([[[0.0, 1.0679e4, 0.0], [1.0, 0.0, 0.0]]], dtype=torch.float64)
    xi = torch.tensor([[1.08, 1.34]], dtype=torch.float64)
    res = loopy_association(beta, xi, torch.tensor([[True, False]]), torch.tensor([[True, False]]))
    assert torch.isfinite(res.probabilities).all() and torch.isfinite(res.nu).all()
    torch.testing.assert_close(res.probabilities[0, 0], torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    assert float(res.new_existence[0, 0]) == 0.0


def test_zero_terms_and_non_finite_padding_give_no_nan():
    """beta_k(0) = 0 with every other term 0 (a certain PO whose measurement likelihood underflowed)
    gives 0, not 0/0; a padded PO with nan terms changes nothing."""
    beta = torch.tensor([[[0.0, 0.0, 0.0], [0.5, 2.0, 1.0]]], dtype=torch.float64)
    res = loopy_association(beta, torch.ones(1, 2, dtype=torch.float64) * 1.5)
    assert torch.isfinite(res.nu).all() and torch.isfinite(res.probabilities[0, 1]).all()
    pad = torch.tensor([[[0.5, 2.0, 1.0], [1.0, float("nan"), float("nan")]]], dtype=torch.float64)
    a = loopy_association(pad, torch.ones(1, 2, dtype=torch.float64) * 1.5, torch.tensor([[True, False]]))
    b = loopy_association(pad[:, :1], torch.ones(1, 2, dtype=torch.float64) * 1.5)
    torch.testing.assert_close(a.probabilities[:, 0], b.probabilities[:, 0])
    assert torch.isfinite(a.new_existence).all()
