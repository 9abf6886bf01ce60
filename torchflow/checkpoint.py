"""Moved to :mod:`torchflow.runner.checkpoint`."""

from .runner.checkpoint import CHUNK_FIELDS, ChunkStore, checksum, fingerprint  # noqa: F401 - re-exported
