"""Logging of the command line: messages below WARNING to stdout, the rest to stderr, everything
(with tracebacks) to the run's ``run.log`` (see ``configs/hydra/job_logging/torchflow.yaml``)."""

from __future__ import annotations

import logging


class BelowWarning(logging.Filter):
    """Passes records below WARNING (the stdout handler's filter)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno < logging.WARNING
