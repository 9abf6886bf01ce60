"""Counting what a filter step asks of the device: aten operations (on a GPU, each a kernel launch)
and host synchronisations (reads of a tensor's value back to the host, which stall a GPU's queue).

    from torchflow.core.profiling import OpCounter

    with OpCounter() as c:
        filt.step(state, z, generator)
    c.ops, c.syncs          # 5096, []

Counted with a ``TorchDispatchMode``, so it works on the CPU and counts what would run on a GPU.
"""

from __future__ import annotations

from collections import Counter

from torch.utils._python_dispatch import TorchDispatchMode

#: aten ops that read a value back to the host: ``bool(t)``, ``.item()``, ``float(t)``
#: (``_local_scalar_dense``), ``is_nonzero``, ``item``, and ``nonzero`` (a data-dependent shape)
SYNC_OPS = frozenset(
    {"aten._local_scalar_dense.default", "aten.is_nonzero.default", "aten.item.default", "aten.nonzero.default"}
)

__all__ = ["OpCounter", "SYNC_OPS"]


class OpCounter(TorchDispatchMode):
    """Counts the aten ops dispatched inside its ``with`` block: ``ops`` (all), ``syncs`` (the names
    of those in :data:`SYNC_OPS`, in order) and ``by_op`` (a ``Counter`` per op name)."""

    def __init__(self):
        super().__init__()
        self.ops, self.syncs, self.by_op = 0, [], Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = str(func)
        self.ops += 1
        self.by_op[name] += 1
        if name in SYNC_OPS:
            self.syncs.append(name)
        return func(*args, **(kwargs or {}))
