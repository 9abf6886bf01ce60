"""Which execution path a computation took: a host-side tally of the kernel selection's decisions.

The selection (:mod:`~torchflow.flows.select`) notes each run-time decision it takes while
someone listens (:func:`recording`); nothing is noted, and nothing costs more than a thread-local
lookup, when no one does. No device is synchronised: a note is a Python counter increment. The
paths, and what one count is:

* ``"kernel:lanes"``, ``"kernel:diagonal"``, ``"kernel:gromov"``: one flow integration
  (:func:`~torchflow.flows.integrate_flow`) by that fused kernel (Numba on the CPU, Triton on a
  GPU); ``"kernel:gpfis"``: one GPFIS transport by the CPU kernel; ``"kernel:weights"``: one
  particle-filter time step weighed and resampled by the CPU kernel;
* ``"graph:flow"``: one flow integration sent to a CUDA graph (:func:`select.flow_graph`); the
  first call of each graph also runs the integration eagerly (its warm-up), counted once more
  under the path that takes; the capture itself is not counted;
* ``"graph:step"``: one filter time step replayed from a CUDA graph
  (:mod:`~torchflow.filters.graph_step`);
* ``"torch"``: one flow integration or GPFIS transport by the reference PyTorch code, and, in a
  filter's :meth:`~torchflow.filters.Filter.forward`, one time step in which nothing was noted (a
  Kalman filter's, a bootstrap PF's, an eagerly run graph-safe step).

:meth:`Filter.forward <torchflow.filters.Filter.forward>` records its time steps and reports the
counts as :attr:`FilterResult.paths <torchflow.filters.FilterResult.paths>`; the runner sums them
over a filter's chunks (``results.json``'s ``paths``, the summary's ``path`` column:
:func:`describe`).
"""

from __future__ import annotations

import contextlib
import threading
from typing import Callable, Dict, Iterator, Mapping, Optional

import torch

__all__ = ["PATHS", "recording", "note", "listening", "per_step", "describe", "merge"]

#: every path a decision may note
PATHS = (
    "kernel:lanes",
    "kernel:diagonal",
    "kernel:gromov",
    "kernel:gpfis",
    "kernel:weights",
    "graph:flow",
    "graph:step",
    "torch",
)

_local = threading.local()  # ``stack``: this thread's listening dicts, innermost last


def listening() -> bool:
    """Whether a :func:`recording` is open on this thread."""
    return bool(getattr(_local, "stack", None))


@contextlib.contextmanager
def recording() -> Iterator[Dict[str, int]]:
    """Count the paths taken on this thread inside the block: yields a dict ``{path: count}``
    filled as decisions are taken (nested recordings each see every note made inside them)."""
    stack = _local.__dict__.setdefault("stack", [])
    counts: Dict[str, int] = {}
    stack.append(counts)
    try:
        yield counts
    finally:
        for i in range(len(stack) - 1, -1, -1):  # by identity: equal dicts may be open at once
            if stack[i] is counts:
                del stack[i]
                break


def note(path: str) -> None:
    """Count one use of ``path`` (one of :data:`PATHS`) in every open :func:`recording` of this
    thread; nothing while none is open or while a CUDA graph is being captured (a capture runs
    nothing: its replays are counted)."""
    stack = getattr(_local, "stack", None)
    if not stack or (torch.cuda.is_initialized() and torch.cuda.is_current_stream_capturing()):
        return
    for counts in stack:
        counts[path] = counts.get(path, 0) + 1


def per_step(step: Callable, counts: Mapping[str, int]) -> Callable:
    """``step`` that notes ``"torch"`` for a call in which no path was noted into ``counts``
    (a time step that ran no kernel, no graph and no flow integration)."""

    def run(*args, **kwargs):
        before = sum(counts.values())
        out = step(*args, **kwargs)
        if sum(counts.values()) == before:
            note("torch")
        return out

    return run


def merge(*tallies: Optional[Mapping[str, int]]) -> Dict[str, int]:
    """The sum of several ``{path: count}`` tallies (``None`` skipped)."""
    out: Dict[str, int] = {}
    for tally in tallies:
        for path, n in (tally or {}).items():
            out[path] = out.get(path, 0) + int(n)
    return out


def describe(tally: Optional[Mapping[str, int]]) -> Optional[str]:
    """A short label of a tally: its paths, most counted first, joined by ``+``
    (``"kernel:diagonal"``, ``"graph:flow+torch"``); ``None`` for an empty or missing tally."""
    if not tally:
        return None
    return "+".join(sorted(tally, key=lambda p: (-tally[p], p)))
