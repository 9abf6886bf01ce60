"""A particle filter's whole time step replayed from a CUDA graph (small, launch-bound batches).

A bootstrap PF step of 100 trials x 200 particles is ~130 small kernels whose arithmetic takes a
few microseconds each: launched one by one from Python, the step costs ~1.8 ms of host time on an
H100 while the GPU works ~0.4 ms of it. Replayed from a CUDA graph the step is one launch.

The step draws random numbers, which a graph cannot: a replay would repeat the captured counters.
So the draws are split in two (:class:`~torchflow.random.TrialStreams` with the Philox back end,
the default on CUDA): the Philox words of each draw are made eagerly, outside the graph (one
kernel per draw, advancing the streams' counters on the host as always), and the graph takes them
as inputs and turns them into uniforms and normals with the eager kernels. The draws a step makes
(kind, shape, dtype) are recorded once per state layout by running the step eagerly with a
recording stream; later steps replay. Same kernels on the same numbers: the eager run's numbers,
bit for bit (``tests/test_graph_step.py``, emulated on the CPU; compared on CUDA there too).

Used by :meth:`torchflow.filters.Filter.forward` when the filter declares its step graph-safe
(:attr:`ParticleFilter.graph_step`: the generic step with a proposal that says so, e.g. the
bootstrap PF), on CUDA, without a gradient, with per-trial Philox streams, ``tuning.cuda_graphs``
on and at most ``tuning.graph_step_max_elems`` state elements (larger steps are bound by the GPU's
arithmetic, where a graph saves nothing and would keep a large memory pool). Anything else runs
the step eagerly, as does a step whose recorded draws do not match (a one-time warning).
"""
from __future__ import annotations

import dataclasses
import warnings
import weakref
from typing import Optional
import torch

from .. import cudagraphs, tuning
from ..random import TrialStreams

__all__ = ["run_step", "eligible"]

#: recorded draws per filter and state layout: ``{filter: {layout: specs or None}}`` (None: the
#: step cannot be replayed, e.g. it selected sub-streams or drew off the GPU)
_specs: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
_warned = set()


class _Mismatch(RuntimeError):
    """A step asked for other draws than the ones recorded for its layout."""


class _Recording(TrialStreams):
    """Delegates every draw to ``real`` and records ``(kind, shape, n, dtype, device)``; replayable
    while every draw is a Philox draw on ``device`` (the step's)."""

    def __init__(self, real: TrialStreams, device):  # noqa: D107 - no TrialStreams.__init__: a view of ``real``
        self.__dict__.update(real.__dict__)
        self.real, self.device, self.specs, self.replayable = real, torch.device(device), [], True

    def _draw(self, kind, shape, dtype, device):
        out = self.real._draw(kind, shape, dtype, device)
        dev = torch.device("cpu") if device is None else torch.device(device)
        n = out.numel() // max(len(self.trials), 1)
        self.specs.append((kind, tuple(int(s) for s in shape), n, dtype, dev))
        if self.real.backend != "philox" or dev != self.device:
            self.replayable = False
        return out

    def select(self, index):
        self.replayable = False
        return self.real.select(index)

    def get_state(self):
        self.replayable = False
        return self.real.get_state()


class _Tape(TrialStreams):
    """Hands out the recorded draws, made from given Philox words, in order."""

    def __init__(self, real: TrialStreams, specs, words):  # noqa: D107
        self.__dict__.update(real.__dict__)
        self.specs, self.words, self.i = specs, words, 0

    def _draw(self, kind, shape, dtype, device):
        if self.i >= len(self.specs):
            raise _Mismatch(f"draw {self.i} ({kind}, {tuple(shape)}) beyond the {len(self.specs)} recorded")
        k, sh, n, dt, _ = self.specs[self.i]
        if (k, sh, dt) != (kind, tuple(int(s) for s in shape), dtype):
            raise _Mismatch(f"draw {self.i}: asked ({kind}, {tuple(shape)}, {dtype}), recorded ({k}, {sh}, {dt})")
        out = TrialStreams._philox_numbers(kind, self.words[self.i], n, dtype).reshape(sh)
        self.i += 1
        return out

    def select(self, index):
        raise _Mismatch("select() inside a replayed step")


def eligible(filt, state, generator) -> bool:
    """Whether ``filt``'s step on ``state`` goes through a CUDA graph (module docstring)."""
    x = getattr(state, "particles", None)
    return (x is not None and x.is_cuda and not torch.cuda.is_current_stream_capturing()
            and _conditions(filt, x, generator))


def _conditions(filt, x, generator) -> bool:
    t = tuning.get()
    return (bool(getattr(filt, "graph_step", False)) and bool(t.cuda_graphs) and not torch.is_grad_enabled()
            and isinstance(generator, TrialStreams) and generator.backend in ("auto", "philox")
            and x.numel() <= t.graph_step_max_elems)


def _flatten(state):
    """``(tensors, layout)`` of a dataclass state: its tensor fields (and a tensor dict's items) in
    order, and what rebuilds it; ``layout`` is None when a field is neither a tensor, None, an int
    (the step count, not part of the layout) nor a dict of tensors."""
    tensors, layout = [], []
    for f in dataclasses.fields(state):
        v = getattr(state, f.name)
        if f.name == "step":
            continue
        if v is None:
            layout.append((f.name, None))
        elif isinstance(v, torch.Tensor):
            layout.append((f.name, "t"))
            tensors.append(v)
        elif isinstance(v, dict) and all(isinstance(e, torch.Tensor) for e in v.values()):
            keys = tuple(sorted(v))
            layout.append((f.name, ("d", keys)))
            tensors += [v[k] for k in keys]
        else:
            return None, None
    return tensors, (type(state), tuple(layout))


def _unflatten(layout, tensors, step: int):
    cls, items = layout
    it, kw = iter(tensors), {"step": step}
    for name, kind in items:
        if kind is None:
            kw[name] = None
        elif kind == "t":
            kw[name] = next(it)
        else:
            kw[name] = {k: next(it) for k in kind[1]}
    return cls(**kw)


def run_step(filt, state, z: torch.Tensor, generator: TrialStreams, *, memo: Optional[dict] = None):
    """``filt.step(state, z, generator)``, replayed from a CUDA graph where it can be (module
    docstring); the same numbers as the eager step. ``memo``: a dict kept for one ``forward`` call
    (the filter's state key is computed once per call: parameters do not change within one)."""
    tensors, layout = _flatten(state)
    if layout is None:
        return filt.step(state, z, generator)
    sig = (layout, cudagraphs._signature(tuple(tensors) + (z,)))
    per_filter = _specs.setdefault(filt, {})
    if sig not in per_filter:  # record this layout's draws with one eager step
        rec = _Recording(generator, state.particles.device)
        new = filt.step(state, z, rec)
        per_filter[sig] = [tuple(rec.specs), None] if rec.replayable else None
        return new
    entry = per_filter[sig]
    if entry is None:
        return filt.step(state, z, generator)
    specs = entry[0]
    counter = generator._counter
    words = tuple(generator._philox_bits(k, n, dt, dev) for k, _, n, dt, dev in specs)

    def fn(*args):
        st = _unflatten(layout, args[:len(tensors)], state.step)
        new = filt.step(st, args[len(tensors)], _Tape(generator, specs, args[len(tensors) + 1:]))
        flat, out_layout = _flatten(new)
        if out_layout is None:
            raise _Mismatch(f"{type(new).__name__} has fields a graph cannot return")
        entry[1] = out_layout
        return tuple(flat)

    memo = {} if memo is None else memo
    if "state" not in memo:
        memo["state"] = cudagraphs.state_key(filt, *filt.modules())
    key = ("filter_step", memo["state"], tuning.get(), layout, specs)
    try:
        out = cudagraphs.graphed(key, fn, tuple(tensors) + (z,) + words, name=f"{filt.name}.step")
    except _Mismatch as err:  # the step's draws differ from the recorded ones: this layout runs eagerly
        per_filter[sig] = None
        if filt.name not in _warned:
            _warned.add(filt.name)
            warnings.warn(f"{filt.name}: its step is not replayed from a CUDA graph ({err}); running it eagerly",
                          RuntimeWarning, stacklevel=3)
        generator._counter = counter  # the words drawn for the graph are given back: the eager step draws them
        return filt.step(state, z, generator)
    return _unflatten(entry[1], out, state.step + 1)
