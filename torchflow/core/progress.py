"""Progress of the long loops outside the filters (a model's simulation over time steps).

A loop calls :func:`report` ``(done, total)`` after each unit of its work; whoever started the loop
may install a watcher with :func:`watching`, which sees every report and may log progress or end
the loop by raising (the runner's watcher raises ``KeyboardInterrupt`` on a stop request, see
:class:`torchflow.app.runner.StopRequest`). Without a watcher a report is one global read. Neutral:
models report here without importing the runner.
"""

from __future__ import annotations

import contextlib
from typing import Callable, Optional

_watcher: Optional[Callable[[int, int], None]] = None


def report(done: int, total: int) -> None:
    """``done`` of ``total`` units of a long loop are finished (a Python call; no device work)."""
    w = _watcher
    if w is not None:
        w(done, total)


@contextlib.contextmanager
def watching(watcher: Callable[[int, int], None]):
    """``watcher(done, total)`` sees every :func:`report` inside the block (the one before is restored)."""
    global _watcher
    before, _watcher = _watcher, watcher
    try:
        yield watcher
    finally:
        _watcher = before
