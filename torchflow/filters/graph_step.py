"""A particle filter's whole time step replayed from a CUDA graph (small, launch-bound batches).

A bootstrap PF step of 100 trials x 200 particles is ~130 small kernels, each with little
arithmetic: launched one by one from Python, the step's host time (launch overhead) exceeds the
GPU's work several times over. Replayed from a CUDA graph the step is one launch (timings:
``experiments/benchmarks/bench_gpu.py``).

The step draws random numbers, which a graph cannot: a replay would repeat the captured counters.
So the draws are split in two (:class:`~torchflow.core.random.TrialStreams` with the Philox back end,
the default on CUDA): the Philox words of each draw are made eagerly, outside the graph (one
kernel per draw, advancing the streams' counters on the host as always), and the graph takes them
as inputs and turns them into uniforms and normals with the eager kernels. The draws a step makes
(kind, shape, dtype, device) are recorded by running the step eagerly once with a recording
stream, per state layout, input shapes and settings (the filter's, model's, proposal's and
resampler's attributes and tensors, and ``torchflow.core.tuning``); later steps replay. Same kernels on
the same numbers: the eager run's numbers, bit for bit (``tests/test_graph_step.py``, emulated on
the CPU; compared on CUDA there too). A step that asks for other draws than recorded, or fewer,
runs eagerly from the stream positions the graph's words took (one warning per filter).

Used by :meth:`torchflow.filters.Filter.forward` when the filter's step is graph-safe by
declaration (:attr:`ParticleFilter.graph_step`: the generic step, with a proposal class and a model
class that each declare ``graph_safe``: the bootstrap proposal and the deterministic flows'
proposal with global or per-particle points (PF-PF(EDH), PF-PF(LEDH), geodesic: the flow loop is
then captured inside the step's graph); the linear-Gaussian models and acoustic tracking), on CUDA, without a
gradient, with per-trial Philox streams (a plain
:class:`~torchflow.core.random.TrialStreams`), ``tuning.cuda_graphs`` on and at most
``tuning.graph_step_max_elems`` state elements (larger steps are bound by the GPU's arithmetic,
where a graph saves nothing and would keep a large memory pool). Anything else runs eagerly. A
replayed step is noted (:mod:`~torchflow.core.paths`: ``"graph:step"``); an eager one is
counted by the filter's ``forward`` as ``"torch"``.
Known limits: process-wide switches outside :func:`torchflow.core.cudagraphs._settings` (which holds
the TF32, precision, determinism and autocast flags) are not seen by a cached graph.
"""

from __future__ import annotations

import dataclasses
import warnings
import weakref
from typing import Optional

import torch

from torchflow.core import cudagraphs, paths, tuning
from torchflow.core.covariances import Covariance
from torchflow.core.random import TrialStreams
from torchflow.flows import select

__all__ = ["run_step", "eligible"]

#: recorded draws per filter: ``{filter: {(state layout, input signature, settings key, tuning):
#: {"specs": draws, "out": output layout} or None}}`` (None: the step cannot be replayed, e.g. it
#: selected sub-streams, drew off the GPU or drew otherwise than recorded)
_specs: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
_warned: "weakref.WeakSet" = weakref.WeakSet()  # filters warned about a fallback
#: recorded layouts kept per filter (the oldest is forgotten first)
MAX_RECORDED = 16


class _Mismatch(RuntimeError):
    """A step asked for other draws than the ones recorded for its layout."""


class _Recording(TrialStreams):
    """Delegates every draw to ``real`` and records ``(kind, shape, n, dtype, device)``; replayable
    while every draw is a Philox draw on ``device`` (the step's)."""

    def __init__(self, real: TrialStreams, device):
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

    def set_state(self, state):
        self.replayable = False
        self.real.set_state(state)


class _Tape(TrialStreams):
    """Hands out the recorded draws, made from given Philox words, in order."""

    def __init__(self, template: dict, specs, words):
        self.__dict__.update(template)
        self.specs, self.words, self.i = specs, words, 0

    @staticmethod
    def template(real: TrialStreams) -> dict:
        """What a tape keeps of the real streams: their identity (seed, key, trials, back end)."""
        return dict(
            seed=real.seed, key=real.key, trials=real.trials, backend="philox", _np=None, _counter=0, _keys=None
        )

    def _draw(self, kind, shape, dtype, device):
        if self.i >= len(self.specs):
            raise _Mismatch(f"draw {self.i} ({kind}, {tuple(shape)}) beyond the {len(self.specs)} recorded")
        k, sh, n, dt, dv = self.specs[self.i]
        dev = torch.device("cpu") if device is None else torch.device(device)
        if (k, sh, dt, dv) != (kind, tuple(int(s) for s in shape), dtype, dev):
            raise _Mismatch(f"draw {self.i}: asked ({kind}, {tuple(shape)}, {dtype}), recorded ({k}, {sh}, {dt})")
        out = TrialStreams._philox_numbers(kind, self.words[self.i], n, dtype).reshape(sh)
        self.i += 1
        return out

    def select(self, index):
        raise _Mismatch("select() inside a replayed step")

    def get_state(self):
        raise _Mismatch("get_state() inside a replayed step")

    def set_state(self, state):
        raise _Mismatch("set_state() inside a replayed step")


def eligible(filt, state, generator) -> bool:
    """Whether ``filt``'s step on ``state`` goes through a CUDA graph
    (:func:`torchflow.flows.select.graph_step` decides)."""
    x = getattr(state, "particles", None)
    return x is not None and select.graph_step(filt, x, generator)


def _flatten(state):
    """``(tensors, layout)`` of a dataclass state: its tensor fields (and a tensor dict's items, and
    a :class:`~torchflow.core.covariances.Covariance`'s matrix) in order, and what rebuilds it; ``layout``
    is None when a field is neither a tensor, None, an int (the step count, not part of the layout),
    a dict of tensors nor a covariance."""
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
        elif isinstance(v, Covariance):  # its type and settings are the layout, its matrix a tensor
            rest = tuple((g.name, getattr(v, g.name)) for g in dataclasses.fields(v) if g.name != "matrix")
            layout.append((f.name, ("c", type(v), rest)))
            tensors.append(v.matrix)
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
        elif kind[0] == "c":
            kw[name] = kind[1](matrix=next(it), **dict(kind[2]))
        else:
            kw[name] = {k: next(it) for k in kind[1]}
    return cls(**kw)


def run_step(filt, state, z: torch.Tensor, generator: TrialStreams, *, memo: Optional[dict] = None):
    """``filt.step(state, z, generator)``, replayed from a CUDA graph where it can be (module
    docstring); the same numbers as the eager step. ``memo``: a dict kept for one ``forward`` call
    (the filter's state key is computed once per call: its settings and parameters do not change
    within one)."""
    tensors, layout = _flatten(state)
    if layout is None:
        return filt.step(state, z, generator)
    memo = {} if memo is None else memo
    if "state" not in memo:  # the filter's, model's, proposal's and resampler's settings and tensors
        memo["state"] = cudagraphs.state_key(filt, *filt.modules())
    # the draws are recorded per input layout *and* settings (a changed resampler draws otherwise)
    sig = (layout, cudagraphs._signature(tuple(tensors) + (z,)), memo["state"], tuning.get())
    per_filter = _specs.setdefault(filt, {})
    if sig not in per_filter:  # record this layout's draws with one eager step
        rec = _Recording(generator, state.particles.device)
        new = filt.step(state, z, rec)
        per_filter[sig] = {"specs": tuple(rec.specs), "out": None} if rec.replayable else None
        while len(per_filter) > MAX_RECORDED:
            per_filter.pop(next(iter(per_filter)))
        return new
    entry = per_filter[sig]
    if entry is None:
        return filt.step(state, z, generator)
    specs = entry["specs"]
    counter = generator._counter
    words = tuple(generator._philox_bits(k, n, dt, dev) for k, _, n, dt, dev in specs)
    fn = _step_function(filt, generator, layout, len(tensors), state.step, specs, entry)
    key = ("filter_step", sig)
    replays = cudagraphs.stats()["replays"] if paths.listening() else None
    try:
        out = cudagraphs.graphed(key, fn, tuple(tensors) + (z,) + words, name=f"{filt.name}.step")
    except _Mismatch as err:  # the step's draws differ from the recorded ones: it runs eagerly
        per_filter[sig] = None
        if filt not in _warned:
            _warned.add(filt)
            warnings.warn(
                f"{filt.name}: its step is not replayed from a CUDA graph ({err}); running it eagerly",
                RuntimeWarning,
                stacklevel=3,
            )
        generator._counter = counter  # the words drawn for the graph are given back: the eager step draws them
        return filt.step(state, z, generator)
    if replays is not None and cudagraphs.stats()["replays"] > replays:  # not the capture's eager warm-up
        paths.note("graph:step")
    return _unflatten(entry["out"], out, state.step + 1)


def _step_function(filt, generator, layout, n_in: int, step: int, specs, entry):
    """The pure function of tensors that is captured: ``(state tensors, z, words) -> new state
    tensors``. It keeps no input tensor alive (the graph's closure holds it as long as the graph),
    checks that the step used exactly the recorded draws, and stores the output layout in ``entry``
    (one per recorded layout and settings, so one per graph: a replay runs no Python)."""
    streams = _Tape.template(generator)

    def fn(*args):
        tape = _Tape(streams, specs, args[n_in + 1 :])
        new = filt.step(_unflatten(layout, args[:n_in], step), args[n_in], tape)
        if tape.i != len(specs):
            raise _Mismatch(f"the step made {tape.i} of the {len(specs)} recorded draws")
        flat, out_layout = _flatten(new)
        if out_layout is None:
            raise _Mismatch(f"{type(new).__name__} has fields a graph cannot return")
        entry["out"] = out_layout
        return tuple(flat)

    return fn
