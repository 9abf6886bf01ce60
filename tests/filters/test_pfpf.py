"""PF-PF and unweighted flow filters."""

import math

import pytest
import torch
from conftest import mild_lg, random_lg, replicated, simulate_with_belief
from torch.func import functional_call

from torchflow.app.runner import run_experiment
from torchflow.filters import BootstrapParticleFilter, KalmanFilter, ParticleFlowFilter, ParticleFlowParticleFilter
from torchflow.flows import EDHFlow, LEDHFlow
from torchflow.flows.schedules import ExponentialSchedule, UniformSchedule
from torchflow.models import AcousticTracking

_replicated = replicated


@pytest.mark.parametrize("flow", ["ledh", "edh"])
@pytest.mark.parametrize("covariance", ["ekf", "ukf"])
def test_pfpf_log_evidence_unbiased_on_lg(flow, covariance):
    """E[Z_hat / Z] = 1 for the PF-PF: the mean of exp(log Z_hat - log Z) over 400 independent runs
    on the same data lies within 4 standard errors of 1 (SE from the sample sd of the ratios)."""
    model = mild_lg()
    obs, mean, cov = _replicated(model, 400, 6)
    logz = KalmanFilter(model)(obs[:1], mean[:1], cov[:1]).log_evidence
    f = ParticleFlowParticleFilter(model, flow=flow, n_particles=64, covariance=covariance)
    res = f(obs, mean, cov, torch.Generator().manual_seed(1))
    r = torch.exp(res.log_evidence - logz)
    se = r.std() / math.sqrt(r.numel())
    assert abs(float(r.mean()) - 1) < 4 * float(se), (float(r.mean()), float(se))
    assert float(se) < 0.05  # the test has power: a 20% bias would be caught


def test_pfpf_without_jacobian_term_would_be_biased(monkeypatch):
    """Sanity check of the test above: dropping log|det| from the weights biases Z_hat far
    beyond the tolerance, so the unbiasedness test can fail."""
    import torchflow.proposals.flow as proposals_mod
    from torchflow.flows import integrate as flow_base

    real = flow_base.integrate_flow

    def no_det(*a, **k):
        out = real(*a, **k)
        return flow_base.FlowOutput(out.particles, torch.zeros_like(out.log_det), out.aux)

    monkeypatch.setattr(proposals_mod, "integrate_flow", no_det)
    model = mild_lg()
    obs, mean, cov = _replicated(model, 400, 6)
    logz = KalmanFilter(model)(obs[:1], mean[:1], cov[:1]).log_evidence
    res = ParticleFlowParticleFilter(model, flow="ledh", n_particles=16)(
        obs, mean, cov, torch.Generator().manual_seed(1)
    )
    r = torch.exp(res.log_evidence - logz)
    assert abs(float(r.mean()) - 1) > 10 * float(r.std() / 20), float(r.mean())


@pytest.mark.parametrize("flow", ["ledh", "edh"])
def test_pfpf_lg_consistent_with_kf(flow):
    """4 trajectories x 25 independent replicates: the replicate-mean error of the PF-PF estimate
    against the KF mean lies within 4.5 of its own standard error (sample sd / sqrt(25)) for every
    trial, step and coordinate (72 comparisons, t with 24 df: ~1% family-wise false alarm)."""
    model = mild_lg()
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(4, 6, g)
    R = 25
    obs = traj.observations.repeat(R, 1, 1)
    mean, cov = model.initial_belief(traj.states[:, 0].repeat(R, 1))
    kf = KalmanFilter(model)(traj.observations, mean[:4], cov[:4])
    res = ParticleFlowParticleFilter(model, flow=flow, n_particles=500)(obs, mean, cov, g)
    err = (res.estimates - kf.estimates.repeat(R, 1, 1)).reshape(R, 4, 6, 3)
    t = err.mean(0) / (err.std(0) / math.sqrt(R))
    assert t.abs().max() < 4.5, float(t.abs().max())
    assert res.ess.mean() > 0.3 * 500


@pytest.mark.parametrize("flow", [EDHFlow(), LEDHFlow()], ids=["edh", "ledh"])
def test_unweighted_flow_filter_tracks_kf_on_lg(flow):
    model = random_lg(3, 4, seed=8)
    traj, mean, cov, g = simulate_with_belief(model, 4, 5)
    kf = KalmanFilter(model)(traj.observations, mean, cov, return_covariances=True)
    N = 4000
    f = ParticleFlowFilter(model, flow=flow, n_particles=N, schedule=UniformSchedule(200))
    res = f(traj.observations, mean, cov, g, return_covariances=True)
    torch.testing.assert_close(res.covariances, kf.covariances)  # EKF covariance = KF on LG
    sd = (kf.covariances.diagonal(dim1=-2, dim2=-1) / N).sqrt()
    # sample-mean sd of the posterior draws, plus the Euler bias at 200 steps (see test_flows)
    assert ((res.estimates - kf.estimates).abs() <= 5 * sd + 0.01).all()
    assert res.ess is None and not f.estimates_evidence


def test_pfpf_ledh_beats_bpf_on_acoustic():
    model = AcousticTracking()
    filters = {
        "pfpf_ledh": ParticleFlowParticleFilter(
            model, flow="ledh", n_particles=100, schedule=ExponentialSchedule(15, 1.3)
        ),
        "bpf": BootstrapParticleFilter(model, n_particles=100),
    }
    res = run_experiment(model, filters, trials=4, steps=12, seed=1, progress=False)
    rows = {r["filter"]: r for r in res.summary}
    assert rows["pfpf_ledh"]["omat"] < 0.5 * rows["bpf"]["omat"], (rows["pfpf_ledh"]["omat"], rows["bpf"]["omat"])
    assert rows["pfpf_ledh"]["ess"] > rows["bpf"]["ess"]


@pytest.mark.parametrize("flow", ["ledh", "edh"])
def test_stiff_acoustic_runs_finite(flow):
    model = AcousticTracking(sigma_w=0.001)
    g = torch.Generator().manual_seed(3)
    traj = model.simulate(3, 8, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    f = ParticleFlowParticleFilter(model, flow=flow, n_particles=50)
    res = f(traj.observations, mean, cov, g)
    assert torch.isfinite(res.estimates).all() and torch.isfinite(res.ess).all()
    assert res.n_repaired is not None and (res.n_repaired >= 0).all()
    assert not torch.isnan(res.log_evidence).any()


def test_pfpf_log_evidence_backpropagates_to_parameters():
    model = random_lg(3, 2, seed=5, learnable=True)
    g = torch.Generator().manual_seed(0)
    traj = model.simulate(2, 4, g)
    mean, cov = model.initial_belief(traj.states[:, 0])
    f = ParticleFlowParticleFilter(model, flow="ledh", n_particles=20)
    f(traj.observations, mean, cov, g).log_evidence.sum().backward()
    for p in model.parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0


@pytest.mark.parametrize("flow", ["ledh", "edh"])
def test_pfpf_log_evidence_gradcheck(flow):
    """gradcheck in float64 with the random draws held fixed (generator re-seeded per call) and
    resampling off (its indices are piecewise constant)."""
    model = random_lg(2, 2, seed=6, learnable=True)
    traj = model.simulate(1, 2, torch.Generator().manual_seed(0))
    mean, cov = model.initial_belief(traj.states[:, 0])
    f = ParticleFlowParticleFilter(
        model, flow=flow, n_particles=3, ess_threshold=0.0, schedule=ExponentialSchedule(5, 1.2)
    )

    def fn(Fm, Hm):
        out = functional_call(
            f, {"model.F": Fm, "model.H": Hm}, (traj.observations, mean, cov, torch.Generator().manual_seed(1))
        )
        return out.log_evidence

    inputs = (model.F.detach().clone().requires_grad_(True), model.H.detach().clone().requires_grad_(True))
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5)


def test_nonfinite_recover_counts_repairs():
    from test_contract import nan_likelihood_run

    model, traj, mean, cov = nan_likelihood_run()
    f = BootstrapParticleFilter(model, n_particles=16, nonfinite="recover")
    res = f(traj.observations, mean, cov, torch.Generator().manual_seed(0))
    assert torch.isfinite(res.estimates).all()
    assert res.n_repaired.tolist() == [0, 1, 0]
    with pytest.raises(ValueError, match="nonfinite"):
        BootstrapParticleFilter(model, nonfinite="ignore")


def test_pfpf_bad_arguments():
    model = random_lg(3, 2)
    with pytest.raises(ValueError, match="flow"):
        ParticleFlowParticleFilter(model, flow="bogus")
    with pytest.raises(TypeError, match="flow"):
        ParticleFlowParticleFilter(model, flow=3)
    with pytest.raises(ValueError, match="covariance"):
        ParticleFlowParticleFilter(model, covariance="pf")


def test_hydra_pairs_any_pfpf_with_any_flow_and_schedule():
    from pathlib import Path

    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    cfg_dir = str(Path(__file__).resolve().parents[2] / "configs")
    with initialize_config_dir(config_dir=cfg_dir, version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                "model=linear_gaussian",
                "model.d=4",
                "filter=[pfpf_ledh,pfpf_edh,edh]",
                "flow@filter.pfpf_ledh.flow=edh",
                "schedule@filter.pfpf_edh.schedule=uniform",
                "filter.pfpf_edh.schedule.n_steps=7",
            ],
        )
    model = instantiate(cfg.model)
    fs = {k: instantiate(v, model=model) for k, v in cfg.filter.items()}
    assert type(fs["pfpf_ledh"].flow) is EDHFlow
    assert isinstance(fs["pfpf_edh"].schedule, UniformSchedule) and len(fs["pfpf_edh"].schedule) == 7
    assert isinstance(fs["edh"], ParticleFlowFilter) and type(fs["edh"].flow) is EDHFlow
