"""Logging of the command line: messages below WARNING to stdout, the rest to stderr, everything
(with tracebacks) to the run's ``run.log`` (see ``configs/hydra/job_logging/torchflow.yaml``)."""

from __future__ import annotations

import logging
import os


class BelowWarning(logging.Filter):
    """Passes records below WARNING (the stdout handler's filter)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno < logging.WARNING


class NoFollowFileHandler(logging.FileHandler):
    """The run's log file (``run.log``), appended to as :class:`logging.FileHandler` does, but opened
    with ``O_NOFOLLOW``: a link planted at the log's name in a shared output folder makes the open
    fail instead of appending the run's log to the link's target (the output guard refuses such a
    folder before this, in one line; this closes the gap between its check and the open)."""

    def _open(self):
        flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND | getattr(os, "O_NOFOLLOW", 0)
        fd = os.open(self.baseFilename, flags, 0o666)  # the umask applies, as open() would
        return os.fdopen(fd, "a", encoding=self.encoding, errors=self.errors)
