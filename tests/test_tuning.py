"""Speed knobs (torchflow.tuning): one documented place, settable from Python and the runner, and
they never change a number."""
import pytest
import torch

from torchflow import tuning
from torchflow.filters import BootstrapParticleFilter, ParticleFlowParticleFilter
from torchflow.models import AcousticTracking
from torchflow.random import TrialStreams


def _run(filt, model, B=3, T=3):
    g = torch.Generator().manual_seed(1)
    traj = model.simulate(B, T, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    return filt(traj.observations, mean, cov, TrialStreams(0, B, "t"))


def test_knobs_change_speed_paths_not_numbers():
    model = AcousticTracking(sigma_w=0.1)
    f = ParticleFlowParticleFilter(model, flow="ledh", n_particles=40)
    ref = _run(f, model)
    # single-threaded small solves off; brute-force assignments never; trials filled on threads always
    with tuning.tuned(serial_solve_max_dim=0, assignment_brute_force_max=0, parallel_draw_min=0):
        other = _run(f, model)
    torch.testing.assert_close(other.estimates, ref.estimates, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(other.log_evidence, ref.log_evidence, rtol=1e-12, atol=1e-12)


def test_chunk_preferences_follow_the_knobs():
    model = AcousticTracking()
    pf = ParticleFlowParticleFilter(model, flow="ledh", n_particles=500)
    bpf = BootstrapParticleFilter(model, n_particles=1000)
    assert pf.preferred_chunk_trials() == 20
    with tuning.tuned(points_per_call=40_000, cache_bytes_per_call=2**20):
        assert pf.preferred_chunk_trials() == 80
        assert bpf.preferred_chunk_trials() == 2**20 // (1000 * 16 * 8)
    assert pf.preferred_chunk_trials() == 20  # restored


def test_bad_knobs_are_named():
    with pytest.raises(ValueError, match=r"tuning: unknown knob\(s\) \['points_per_cal'\]"):
        tuning.set(points_per_cal=1)
    with pytest.raises(ValueError, match="tuning.points_per_call: expected an integer >= 0, got -1"):
        tuning.set(points_per_call=-1)
    assert tuning.get() == tuning.Tuning()
