"""Linearisation points as a choice of the filter: any flow pairs with global, per-particle or
clustered points, and the pairing reproduces the flow classes that fix them."""

import pytest
import torch

from torchflow.core import tuning
from torchflow.core.random import TrialStreams
from torchflow.filters import ParticleFlowFilter, ParticleFlowParticleFilter
from torchflow.flows import (
    ClusteredPoints,
    EDHFlow,
    FlowPrior,
    GeodesicFlow,
    GromovFlow,
    LEDHFlow,
    LinearisationPoints,
    integrate_flow,
)
from torchflow.models import AcousticTracking


def _data(B=3, T=3):
    model = AcousticTracking(sigma_w=0.1)
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(B, T, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    return model, traj.observations, mean, cov


@pytest.mark.parametrize(
    "flow, points, reference",
    [
        (LEDHFlow(), "global", EDHFlow()),
        (EDHFlow(), "particle", LEDHFlow()),
        (GeodesicFlow(), "global", GeodesicFlow(points="global")),
        (GeodesicFlow(points="global"), "particle", GeodesicFlow()),
        (GromovFlow(), "global", GromovFlow(points="global")),
        (GromovFlow(points="global"), "particle", GromovFlow()),
    ],
)
def test_points_override_equals_the_flow_that_fixes_them(flow, points, reference):
    model, obs, mean, cov = _data()
    a = ParticleFlowParticleFilter(model, flow=flow, points=points, n_particles=24)(
        obs, mean, cov, TrialStreams(0, 3, "pfpf")
    )
    b = ParticleFlowParticleFilter(model, flow=reference, n_particles=24)(obs, mean, cov, TrialStreams(0, 3, "pfpf"))
    torch.testing.assert_close(a.estimates, b.estimates, rtol=0, atol=1e-10)
    torch.testing.assert_close(a.log_evidence, b.log_evidence, rtol=0, atol=1e-10)


def test_flow_filter_takes_points_too():
    model, obs, mean, cov = _data()
    a = ParticleFlowFilter(model, flow="ledh", points="global", n_particles=24)(obs, mean, cov, TrialStreams(0, 3, "x"))
    b = ParticleFlowFilter(model, flow="edh", n_particles=24)(obs, mean, cov, TrialStreams(0, 3, "x"))
    torch.testing.assert_close(a.estimates, b.estimates, rtol=0, atol=1e-10)
    # the flow filter takes any strategy: clustered points with K = N are its per-particle points
    # (each particle's prior at its noise-free prediction, the trial's P)
    c = ParticleFlowFilter(model, flow="ledh", points=ClusteredPoints(n_clusters=24), n_particles=24)(
        obs, mean, cov, TrialStreams(0, 3, "x")
    )
    with tuning.tuned(fused_flows=0):  # one arithmetic: per-particle points would take the fused kernel
        d = ParticleFlowFilter(model, flow="ledh", n_particles=24)(obs, mean, cov, TrialStreams(0, 3, "x"))
    torch.testing.assert_close(c.estimates, d.estimates, rtol=0, atol=1e-10)
    e = ParticleFlowFilter(model, flow="ledh", points=ClusteredPoints(n_clusters=4), n_particles=24)(
        obs, mean, cov, TrialStreams(0, 3, "x")
    )
    assert torch.isfinite(e.estimates).all() and not torch.allclose(e.estimates, d.estimates)


def test_points_errors():
    model, obs, mean, cov = _data()
    with pytest.raises(
        ValueError,
        match=r"points: expected one of \('global', 'particle', 'clustered'\), a LinearisationPoints or None",
    ):
        ParticleFlowParticleFilter(model, points="medoids")
    x = torch.zeros(3, 5, 16, dtype=torch.float64)
    with pytest.raises(ValueError, match="index: clustered linearisation points need the"):
        integrate_flow(LEDHFlow(), model, x, obs[:, 0], None, points="clustered")


class _HalvesPoints(LinearisationPoints):
    """A user-defined strategy, written here without touching the library: two points per trial,
    the particles split by index parity, each point at the mean of its half's predictions."""

    name = "halves"

    def place(self, model, x_prev, mean, scale_tril, z):
        eta_bar = model.transition_mean(x_prev)  # (B, N, d)
        B, N, d = eta_bar.shape
        index = (torch.arange(N, device=eta_bar.device) % 2).expand(B, N)
        means = torch.stack([eta_bar[:, 0::2].mean(1), eta_bar[:, 1::2].mean(1)], 1)  # (B, 2, d)
        return FlowPrior(means, scale_tril.unsqueeze(-3)), index

    def arrange(self, prior, particles, index):
        return prior, index, False


def test_a_new_points_strategy_plugs_in_without_library_edits():
    """A strategy defined in a test file runs in the PF-PF and the flow filter, and the PF-PF's
    log-evidence with it is unbiased on the LG test model (the test of the other PF-PFs)."""
    import math

    from conftest import mild_lg, replicated

    from torchflow.filters import KalmanFilter

    model = mild_lg()
    obs, mean, cov = replicated(model, 400, 6)
    logz = KalmanFilter(model)(obs[:1], mean[:1], cov[:1]).log_evidence
    res = ParticleFlowParticleFilter(model, flow="ledh", points=_HalvesPoints(), n_particles=64)(
        obs, mean, cov, TrialStreams(1, 400, "pfpf")
    )
    r = torch.exp(res.log_evidence - logz)
    se = r.std() / math.sqrt(r.numel())
    assert abs(float(r.mean()) - 1) < 4 * float(se), (float(r.mean()), float(se))
    m2, o2, mu2, c2 = _data()
    out = ParticleFlowFilter(m2, flow="gromov", points=_HalvesPoints(), n_particles=16)(
        o2, mu2, c2, TrialStreams(0, 3, "x")
    )
    assert torch.isfinite(out.estimates).all()
