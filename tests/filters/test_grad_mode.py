"""Grad mode does not turn the kernels off, a gradient does: a call with nothing that requires grad runs
as under ``torch.no_grad()`` (the same numbers, the kernel's path); one with a tensor that requires
grad records the gradient on the reference path and says so once, naming the tensor."""

import warnings

import pytest
import torch

from torchflow.filters import BootstrapParticleFilter, ParticleFlowParticleFilter
from torchflow.flows import select
from torchflow.models import AcousticTracking


def _data():
    model = AcousticTracking()
    g = torch.Generator().manual_seed(0)
    data = model.simulate(2, 3, g)
    mean, cov = model.initial_belief(data.states[:, 0], g)
    return model, data.observations, mean, cov


def test_grad_mode_with_nothing_to_differentiate_takes_the_kernel_path_with_the_same_numbers():
    model, obs, mean, cov = _data()
    filt = ParticleFlowParticleFilter(model, flow="ledh", n_particles=16)
    assert torch.is_grad_enabled() and filt.gradient_source(obs, mean, cov) is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing to say: no gradient is recorded
        on = filt(obs, mean, cov, torch.Generator().manual_seed(1))
    with torch.no_grad():
        off = filt(obs, mean, cov, torch.Generator().manual_seed(1))
    assert torch.equal(on.estimates, off.estimates) and torch.equal(on.log_evidence, off.log_evidence)
    assert on.paths == off.paths
    if select.cpu_kernels_on("cpu"):
        assert "torch" not in on.paths, on.paths
    assert not on.log_evidence.requires_grad


def test_a_prior_mean_that_requires_grad_records_the_gradient_and_is_named_once():
    model, obs, mean, cov = _data()
    filt = ParticleFlowParticleFilter(model, flow="ledh", n_particles=16)
    mean = mean.clone().requires_grad_(True)
    with pytest.warns(UserWarning, match="mean requires grad") as record:
        res = filt(obs, mean, cov, torch.Generator().manual_seed(1))
    assert len([w for w in record if "a gradient is recorded" in str(w.message)]) == 1
    assert res.paths == {"torch": 3}
    (g,) = torch.autograd.grad(res.log_evidence.sum(), mean)
    assert bool(torch.isfinite(g).all()) and float(g.abs().sum()) > 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # said once per filter
        filt(obs, mean, cov, torch.Generator().manual_seed(1))


def test_a_model_parameter_that_requires_grad_is_named_by_its_dotted_name():
    model, obs, mean, cov = _data()
    model.extra_scale = torch.nn.Parameter(torch.tensor(1.0, dtype=torch.float64))
    filt = ParticleFlowParticleFilter(model, flow="ledh", n_particles=16)
    assert filt.gradient_source(obs, mean, cov) == "model.extra_scale"
    with pytest.warns(UserWarning, match="model.extra_scale requires grad"):
        res = filt(obs, mean, cov, torch.Generator().manual_seed(1))
    assert res.paths == {"torch": 3}
    with torch.no_grad():  # grad mode off: nothing is recorded, whatever requires grad
        assert filt(obs, mean, cov, torch.Generator().manual_seed(1)).paths != {"torch": 3} or not (
            select.cpu_kernels_on("cpu")
        )


def test_a_filter_without_a_kernel_records_the_gradient_silently():
    model, obs, mean, cov = _data()
    mean = mean.clone().requires_grad_(True)
    filt = BootstrapParticleFilter(model, n_particles=5000)  # over the weighting kernel's 4096
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = filt(obs, mean, cov, torch.Generator().manual_seed(1))
    assert res.log_evidence.requires_grad
