"""Speed knobs (torchflow.core.tuning): one documented place, settable from Python and the runner, and
they never change a number."""

import pytest
import torch

from torchflow.core import tuning
from torchflow.core.random import TrialStreams
from torchflow.filters import (
    BootstrapParticleFilter,
    GaussianSumParticleFilter,
    ParticleFlowGaussianSumParticleFilter,
    ParticleFlowParticleFilter,
)
from torchflow.flows.points import flow_points_per_call
from torchflow.models import AcousticTracking, SkewedTPoisson


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
    with tuning.tuned(points_per_call=40_000, cache_bytes_per_call=2**20, flow_bytes_per_call=0):
        assert pf.preferred_chunk_trials() == 80
        assert bpf.preferred_chunk_trials() == 2**20 // (1000 * 16 * 8)
    assert pf.preferred_chunk_trials() == 20  # restored
    with tuning.tuned(points_per_call=40_000):  # 8 MiB of 8 x 8 matrices (acoustic support): 16384 points
        assert pf.preferred_chunk_trials() == 16384 // 500
    assert pf.flow_chunk() is None  # 500 particles: one pass


def test_high_dimensional_flows_run_in_cache_sized_blocks():
    """d = 144: 8 MiB of 144 x 144 matrices is 50 points, so one trial per call and blocks of 50 particles
    (PFGSPF: 10 per component row at G = 5); a particle_chunk given by the user wins."""
    model = SkewedTPoisson(d=144)
    pf = ParticleFlowParticleFilter(model, flow="ledh", n_particles=200)
    assert flow_points_per_call(model) == (8 << 20) // (8 * 144 * 144) == 50
    assert pf.preferred_chunk_trials() == 1 and pf.flow_chunk() == 50
    gs = ParticleFlowGaussianSumParticleFilter(model, n_components=5, particles_per_component=200)
    assert gs.preferred_chunk_trials() == 1 and gs._row_chunk() == 10
    assert (
        ParticleFlowGaussianSumParticleFilter(
            model, n_components=5, particles_per_component=200, particle_chunk=100
        )._row_chunk()
        == 20
    )
    assert GaussianSumParticleFilter(model, n_components=5, particles_per_component=200)._row_chunk() is None
    with tuning.tuned(flow_bytes_per_call=0):
        assert flow_points_per_call(model) == 10_000 and pf.flow_chunk() is None and gs._row_chunk() is None


def test_flow_blocks_and_operator_form_change_speed_not_numbers():
    """PF-PF(LEDH) and PFGSPF on the skewed-t model (d = 16): cache-sized particle blocks and the
    operator form of A against one pass with A formed; the same estimates and evidence up to
    round-off."""
    model = SkewedTPoisson(d=16)
    for make in (
        lambda: ParticleFlowParticleFilter(model, flow="ledh", n_particles=60),
        lambda: ParticleFlowGaussianSumParticleFilter(model, n_components=3, particles_per_component=20),
    ):
        # blocks of 16 particles, A as an operator
        with tuning.tuned(flow_bytes_per_call=8 * 16 * 16 * 16, flow_operator_min_dim=0):
            f = make()
            assert f.flow_chunk() == 16
            ref = _run(f, model)
        with tuning.tuned(flow_bytes_per_call=0, flow_operator_min_dim=10**6):  # one pass, A formed
            other = _run(make(), model)
        torch.testing.assert_close(other.estimates, ref.estimates, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(other.log_evidence, ref.log_evidence, rtol=1e-9, atol=1e-9)


def test_bad_knobs_are_named():
    with pytest.raises(ValueError, match=r"tuning: unknown knob\(s\) \['points_per_cal'\]"):
        tuning.set(points_per_cal=1)
    with pytest.raises(ValueError, match="tuning.points_per_call: expected an integer >= 0, got -1"):
        tuning.set(points_per_call=-1)
    assert tuning.get() == tuning.Tuning()


def test_the_runner_config_names_every_knob():
    """configs/config.yaml's ``tuning`` block lists exactly torchflow.core.tuning's knobs, so each can be
    set from the command line without ``+`` (a knob missing there made ``tuning.<knob>=0`` an error)."""
    from dataclasses import fields
    from pathlib import Path

    from omegaconf import OmegaConf

    cfg = OmegaConf.load(Path(__file__).resolve().parents[1] / "configs" / "config.yaml")
    assert set(cfg.tuning) == {f.name for f in fields(tuning.Tuning)}
