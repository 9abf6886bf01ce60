"""The Monte Carlo runner: plan -> execute -> score -> checkpoint / resume, over processes.

- :mod:`.plan`: check the arguments, simulate once, choose each filter's chunks of trials.
- :mod:`.execute`: filters x chunks, stop requests (:data:`STOP`), checkpoints, shards.
- :mod:`.score`: summary, per-trial and per-step metrics (:class:`ExperimentResult`).
- :mod:`.checkpoint`: :class:`ChunkStore`, per-chunk files for resuming a killed run.
- :mod:`.distributed`: :class:`Shard`, one run over ``torchrun`` processes.
- :mod:`.writers`, :mod:`.figures`: result files (atomic CSV / JSON) and pictures (matplotlib).
- :mod:`.sweep`: what happened to every job of a Hydra sweep.

``run_experiment`` is plain Python (no Hydra); :mod:`torchflow.cli` is the command line.
"""
from .checkpoint import ChunkStore, fingerprint
from .distributed import Shard
from .errors import ConfigError
from .execute import STOP, StopRequest
from .experiment import run_experiment
from .plan import choose_chunk_size, resolve_device, resolve_dtype
from .score import SUMMARY_COLUMNS, ExperimentResult, format_table

__all__ = ["run_experiment", "ExperimentResult", "SUMMARY_COLUMNS", "format_table", "STOP", "StopRequest",
           "ChunkStore", "fingerprint", "Shard", "ConfigError", "choose_chunk_size", "resolve_device",
           "resolve_dtype"]
