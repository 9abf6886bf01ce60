"""The run says once when a flow filter will run on the slower torch path on the CPU (no Numba)."""

import logging

from torchflow.app.runner.execute import say_slow_path
from torchflow.filters import BootstrapParticleFilter, ParticleFlowParticleFilter
from torchflow.flows.kernels import steps
from torchflow.models import AcousticTracking


def test_the_slow_path_is_said_once_with_the_remedy(monkeypatch, caplog):
    model = AcousticTracking()
    filters = {"pfpf_ledh": ParticleFlowParticleFilter(model, n_particles=8), "bpf": BootstrapParticleFilter(model)}
    monkeypatch.setattr(steps, "numba_available", lambda: False)
    with caplog.at_level(logging.WARNING, logger="torchflow.app.runner"):
        text = say_slow_path(filters, "cpu")
    assert "pfpf_ledh" in text and "bpf" not in text and "torchflow[kernels]" in text
    assert [r.getMessage() for r in caplog.records] == [text]
    assert say_slow_path({"bpf": filters["bpf"]}, "cpu") is None  # no flow: nothing to say
    assert say_slow_path(filters, "cuda") is None  # the GPU kernels are Triton's
    monkeypatch.setattr(steps, "numba_available", lambda: True)
    assert say_slow_path(filters, "cpu") is None
