"""The runner's public names at their old place (the runner is :mod:`torchflow.runner`)."""

from __future__ import annotations

from .runner import (  # noqa: F401 - re-exported at the old place
    STOP,
    SUMMARY_COLUMNS,
    ExperimentResult,
    StopRequest,
    choose_chunk_size,
    format_table,
    resolve_device,
    resolve_dtype,
    run_experiment as _run,
)
from .runner.plan import simulate as _simulate


def run_experiment(model, filters, **kwargs):
    """:func:`torchflow.runner.run_experiment`; simulates with this module's ``_simulate`` (recorded
    ``observations=`` replace the simulation)."""
    if kwargs.get("observations") is None:
        kwargs.setdefault("simulator", _simulate)
    return _run(model, filters, **kwargs)


run_experiment.__doc__ = _run.__doc__
