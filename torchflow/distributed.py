"""Moved to :mod:`torchflow.runner.distributed`."""

from .runner.distributed import Shard  # noqa: F401 - re-exported
