"""CUDA graph capture of pure tensor functions: the deterministic flows' pseudo-time loop on a GPU.

A particle flow's integration is thousands of small kernels per filter step (op counts:
``python -m experiments.benchmarks.bench_ops``). Launched one by one
from Python each costs more host time than its arithmetic takes on the GPU; replayed from a
captured CUDA graph the whole loop is one launch. :func:`graphed` captures a function of tensors
once per *key* (the shapes, dtypes and everything else the function's kernels depend on) and
replays it afterwards:

    out = graphed(key, fn, inputs)    # inputs: a tuple of tensors (or None)

* The first call with a key runs ``fn`` eagerly on a side stream (the warm-up, whose result is
  returned, so nothing is computed twice) and then captures it on static copies of the inputs.
* Later calls copy the inputs into the static buffers, replay the graph and return clones of the
  static outputs. The kernels are the eager ones, so the numbers are the eager numbers.
* Tensors the function reads without taking them as inputs (a model's parameters, a schedule's
  cached steps) are read at their addresses at replay time: an in-place update is seen, a
  reassigned attribute is not. Callers put the identity and the data pointers of such tensors in
  the key (:func:`state_key`).
* A capture that fails (an op that cannot be captured, a host read) is not retried for that key:
  the call returns the eager result and a one-time warning names the error.

Used by :func:`torchflow.flows.integrate_flow` for deterministic flows on CUDA without a gradient,
and by :mod:`torchflow.filters.graph_step` for a graph-safe particle filter's whole time step
(``torchflow.core.tuning`` ``cuda_graphs``; 0 turns both off). Keys also hold the process-wide switches
that choose kernels (TF32, float32 matmul precision, deterministic algorithms, autocast), and a
capture and its replays run on the inputs' GPU. Each cached graph keeps its memory pool:
the cache holds the ``max_graphs`` most recent keys (:func:`clear` frees them all).
"""

from __future__ import annotations

import contextlib
import math
import warnings
from collections import OrderedDict
from typing import Callable, Hashable, Optional, Sequence, Tuple

import torch

__all__ = ["graphed", "clear", "state_key", "stats"]

#: the most recent captured graphs kept (each holds its private memory pool)
max_graphs = 4
_cache: "OrderedDict[Hashable, Optional[_Graph]]" = OrderedDict()
_stats = {"captures": 0, "replays": 0, "failures": 0}
_warned = set()


class _Graph:
    """A captured graph with its static inputs (compact: stride-0 dimensions stored once) and
    outputs."""

    def __init__(self, replay, static_in, static_out, fn):
        self.replay, self.static_in, self.static_out = replay, static_in, static_out
        self.fn = fn  # keeps alive what the graph reads at fixed addresses (the function's closure)

    def __call__(self, inputs):
        for s, x in zip(self.static_in, inputs):
            if s is not None:
                s.copy_(_compact(x))
        self.replay()
        return tuple(None if o is None else o.clone() for o in self.static_out)


class _CudaBackend:
    """Warm-up on a side stream and capture with ``torch.cuda.graph`` (tests substitute an
    emulation that re-runs the function on the static buffers)."""

    @staticmethod
    def warmup(fn, inputs):
        stream = torch.cuda.Stream()
        stream.wait_stream(torch.cuda.current_stream())
        try:
            with torch.cuda.stream(stream):  # capture wants its warm-up off the default stream
                return tuple(fn(*inputs))
        finally:  # also when fn raises: the caller's stream waits for what was launched
            torch.cuda.current_stream().wait_stream(stream)

    @staticmethod
    def capture(fn, views):
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            static_out = tuple(fn(*views))
        return graph.replay, static_out


_backend = _CudaBackend()


def _compact(x: torch.Tensor) -> torch.Tensor:
    """``x`` with its broadcast (stride-0, size > 1) dimensions narrowed to size 1: the memory it
    really has, so a static copy neither materialises an expansion nor changes the kernels."""
    for dim in range(x.dim()):
        if x.stride(dim) == 0 and x.shape[dim] > 1:
            x = x.narrow(dim, 0, 1)
    return x


def _static_copy(x: torch.Tensor) -> torch.Tensor:
    """A static buffer holding ``x`` with ``x``'s strides (after :func:`_compact`), so the captured
    kernels see the layout the eager ones saw (a strided slice stays strided: BLAS kernels may
    choose by layout)."""
    c = _compact(x)
    return torch.empty_strided(c.shape, c.stride(), dtype=c.dtype, device=c.device).copy_(c)


def _settings() -> tuple:
    """Process-wide settings that change which kernels run (part of every key)."""
    return (
        torch.get_float32_matmul_precision(),
        torch.backends.cuda.matmul.allow_tf32,
        torch.backends.cudnn.allow_tf32,
        torch.are_deterministic_algorithms_enabled(),
        torch.is_autocast_enabled("cuda"),
    )


def _signature(inputs) -> tuple:
    """Shapes, dtypes, devices and broadcast pattern of the inputs (part of every key)."""
    return tuple(
        None if x is None else (tuple(x.shape), tuple(s == 0 for s in x.stride()), x.dtype, str(x.device))
        for x in inputs
    )


def state_key(*objects) -> tuple:
    """A key part for objects whose state a captured function reads: for each object, its ``id``,
    the data pointers and shapes of its tensors (parameters, buffers and tensor attributes) and
    its plain scalar attributes (numbers, strings, booleans, tuples of them)."""
    out = []
    for obj in objects:
        items = []
        attrs = dict(vars(obj)) if hasattr(obj, "__dict__") else {}
        if isinstance(obj, torch.nn.Module):
            attrs.update(dict(obj.named_parameters()))
            attrs.update(dict(obj.named_buffers()))
            attrs.pop("_parameters", None), attrs.pop("_buffers", None), attrs.pop("_modules", None)
        for name in sorted(attrs):
            v = attrs[name]
            if isinstance(v, torch.Tensor):
                items.append((name, v.data_ptr(), tuple(v.shape), v.dtype))
            elif isinstance(v, (bool, int, float, str, type(None))) or (
                isinstance(v, tuple) and all(isinstance(e, (bool, int, float, str)) for e in v)
            ):
                items.append((name, "nan" if isinstance(v, float) and math.isnan(v) else v))
        out.append((id(obj), tuple(items)))
    return tuple(out)


def graphed(
    key: Hashable,
    fn: Callable[..., Sequence[Optional[torch.Tensor]]],
    inputs: Tuple[Optional[torch.Tensor], ...],
    *,
    name: str = "function",
) -> Tuple[Optional[torch.Tensor], ...]:
    """``fn(*inputs)`` through a CUDA graph captured once per ``key`` (see the module docstring).

    Args:
        key: hashable; must change whenever ``fn``'s kernels or the tensors it reads at fixed
            addresses would (the inputs' shapes are added here).
        fn: a pure function of the inputs returning a tuple of tensors (or ``None``); no host
            reads, no data-dependent shapes, no randomness.
        inputs: CUDA tensors (or ``None``).
        name: what the function is, for the one-time warning when its capture fails.

    Returns:
        ``fn``'s outputs (fresh tensors the caller owns).
    """
    key = (key, _signature(inputs), torch.is_inference_mode_enabled(), _settings())
    device = next((x.device for x in inputs if x is not None and x.is_cuda), None)
    with torch.cuda.device(device) if device is not None else contextlib.nullcontext():  # the inputs' GPU
        return _graphed(key, fn, inputs, name)


def _graphed(key, fn, inputs, name):
    if key in _cache:
        _cache.move_to_end(key)
        g = _cache[key]
        if g is None:  # capture failed before: eager
            return tuple(fn(*inputs))
        _stats["replays"] += 1
        return g(inputs)
    out = _backend.warmup(fn, inputs)  # eager; its result is this call's answer
    static_in = [None if x is None else _static_copy(x) for x in inputs]
    views = [None if s is None else s.expand(x.shape) for s, x in zip(static_in, inputs)]
    try:
        replay, static_out = _backend.capture(fn, views)
    except Exception as err:
        _stats["failures"] += 1
        _cache[key] = None
        _trim()
        if name not in _warned:
            _warned.add(name)
            warnings.warn(
                f"{name}: CUDA graph capture failed ({type(err).__name__}: {err}); running it eagerly "
                "(set tuning.cuda_graphs=0 to skip the attempt)",
                RuntimeWarning,
                stacklevel=3,
            )
        return out
    _stats["captures"] += 1
    _cache[key] = _Graph(replay, static_in, static_out, fn)
    _trim()
    return out


def _trim() -> None:
    """Keep the ``max_graphs`` most recent keys (failed captures count too)."""
    while len(_cache) > max_graphs:
        _cache.popitem(last=False)


def clear() -> None:
    """Forget every captured graph (frees their memory pools once nothing else holds them)."""
    _cache.clear()


def stats() -> dict:
    """Counts since import: ``captures``, ``replays``, ``failures``, and ``cached`` graphs."""
    return dict(_stats, cached=sum(g is not None for g in _cache.values()))
