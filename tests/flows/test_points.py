"""Linearisation points as a choice of the filter: any flow pairs with global, per-particle or
clustered points, and the pairing reproduces the flow classes that fix them."""
import pytest
import torch

from torchflow.filters import ParticleFlowFilter, ParticleFlowParticleFilter
from torchflow.flows import EDHFlow, GeodesicFlow, GromovFlow, LEDHFlow, integrate_flow
from torchflow.models import AcousticTracking
from torchflow.random import TrialStreams


def _data(B=3, T=3):
    model = AcousticTracking(sigma_w=0.1)
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(B, T, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    return model, traj.observations, mean, cov


@pytest.mark.parametrize("flow, points, reference", [
    (LEDHFlow(), "global", EDHFlow()),
    (EDHFlow(), "particle", LEDHFlow()),
    (GeodesicFlow(), "global", GeodesicFlow(local=False)),
    (GeodesicFlow(local=False), "particle", GeodesicFlow()),
    (GromovFlow(), "global", GromovFlow(local=False)),
    (GromovFlow(local=False), "particle", GromovFlow()),
])
def test_points_override_equals_the_flow_that_fixes_them(flow, points, reference):
    model, obs, mean, cov = _data()
    a = ParticleFlowParticleFilter(model, flow=flow, points=points, n_particles=24)(obs, mean, cov,
                                                                                 TrialStreams(0, 3, "pfpf"))
    b = ParticleFlowParticleFilter(model, flow=reference, n_particles=24)(obs, mean, cov, TrialStreams(0, 3, "pfpf"))
    torch.testing.assert_close(a.estimates, b.estimates, rtol=0, atol=1e-10)
    torch.testing.assert_close(a.log_evidence, b.log_evidence, rtol=0, atol=1e-10)


def test_flow_filter_takes_points_too():
    model, obs, mean, cov = _data()
    a = ParticleFlowFilter(model, flow="ledh", points="global", n_particles=24)(obs, mean, cov,
                                                                                TrialStreams(0, 3, "x"))
    b = ParticleFlowFilter(model, flow="edh", n_particles=24)(obs, mean, cov, TrialStreams(0, 3, "x"))
    torch.testing.assert_close(a.estimates, b.estimates, rtol=0, atol=1e-10)
    with pytest.raises(ValueError, match="points: the unweighted flow filter takes 'global' or 'particle'"):
        ParticleFlowFilter(model, points="clustered")


def test_points_errors():
    model, obs, mean, cov = _data()
    with pytest.raises(ValueError, match=r"points: expected one of \('global', 'particle', 'clustered'\) or None"):
        ParticleFlowParticleFilter(model, points="medoids")
    x = torch.zeros(3, 5, 16, dtype=torch.float64)
    with pytest.raises(ValueError, match="index: clustered linearisation points need the"):
        integrate_flow(LEDHFlow(), model, x, obs[:, 0], None, points="clustered")
