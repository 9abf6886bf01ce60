"""The Monte Carlo runner: :mod:`.plan` (check, simulate once, chunks) -> :mod:`.execute` (filters x
chunks, :data:`STOP`, shards of :mod:`.distributed`) -> :mod:`.score`; :mod:`.checkpoint` (resume),
:mod:`.writers` and :mod:`.figures` (result files), :mod:`.sweep` (Hydra sweeps), :mod:`.config`
(the command line's checks), :mod:`.shell` (the command shell of ``torchflow`` and ``torchflow-learn``:
settings, output folder and lock file, signals and exit statuses, job environment). The metrics
scored, the summary columns, the result files' metric columns and the per-step figure's panels
follow :data:`torchflow.core.metrics.REGISTRY`. ``run_experiment``
is plain Python; :mod:`torchflow.app.cli` and :mod:`torchflow.app.learn` are the commands.

May import: every torchflow package but the rest of :mod:`torchflow.app` above it
(:mod:`~torchflow.app.data` excepted, which it reads recorded observations with).
"""

from torchflow.app.runner.checkpoint import ChunkStore, fingerprint
from torchflow.app.runner.distributed import Shard
from torchflow.app.runner.execute import STOP, RunStopped, StopRequest, plan_run, run_experiment
from torchflow.app.runner.plan import ConfigError, choose_chunk_size, resolve_device, resolve_dtype
from torchflow.app.runner.score import SUMMARY_COLUMNS, ExperimentResult, format_table, summary_columns

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
