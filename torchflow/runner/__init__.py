"""The Monte Carlo runner: :mod:`.plan` (check, simulate once, chunks) -> :mod:`.execute` (filters x
chunks, :data:`STOP`, shards of :mod:`.distributed`) -> :mod:`.score`; :mod:`.checkpoint` (resume),
:mod:`.writers` and :mod:`.figures` (result files), :mod:`.sweep` (Hydra sweeps), :mod:`.config`
(the command line's checks). ``run_experiment`` is plain Python; :mod:`torchflow.cli` is the command line.
"""
from .checkpoint import ChunkStore, fingerprint
from .distributed import Shard
from .execute import STOP, StopRequest, run_experiment
from .plan import ConfigError, choose_chunk_size, resolve_device, resolve_dtype
from .score import SUMMARY_COLUMNS, ExperimentResult, format_table

__all__ = ["run_experiment", "ExperimentResult", "SUMMARY_COLUMNS", "format_table", "STOP", "StopRequest",
           "ChunkStore", "fingerprint", "Shard", "ConfigError", "choose_chunk_size", "resolve_device",
           "resolve_dtype"]
