"""The Monte Carlo runner: :mod:`.plan` (check, simulate once, chunks) -> :mod:`.execute` (filters x
chunks, :data:`STOP`, shards of :mod:`.distributed`) -> :mod:`.score`; :mod:`.checkpoint` (resume),
:mod:`.writers` and :mod:`.figures` (result files), :mod:`.sweep` (Hydra sweeps), :mod:`.config`
(the command line's checks), :mod:`.shell` (the command shell of ``torchflow`` and ``torchflow-learn``:
settings, output folder and lock file, signals and exit statuses, job environment). The metrics
scored, the summary columns, the result files' metric columns and the per-step figure's panels
follow :data:`torchflow.metrics.REGISTRY`. ``run_experiment``
is plain Python; :mod:`torchflow.cli` and :mod:`torchflow.learn` are the commands.
"""

from .checkpoint import ChunkStore, fingerprint
from .distributed import Shard
from .execute import STOP, RunStopped, StopRequest, plan_run, run_experiment
from .plan import ConfigError, choose_chunk_size, resolve_device, resolve_dtype
from .score import SUMMARY_COLUMNS, ExperimentResult, format_table, summary_columns

__all__ = [
    "run_experiment",
    "plan_run",
    "ExperimentResult",
    "SUMMARY_COLUMNS",
    "summary_columns",
    "format_table",
    "STOP",
    "StopRequest",
    "RunStopped",
    "ChunkStore",
    "fingerprint",
    "Shard",
    "ConfigError",
    "choose_chunk_size",
    "resolve_device",
    "resolve_dtype",
]
