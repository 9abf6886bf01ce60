"""One place that maps names to torchflow's classes and functions, and the Hydra config nodes made
from their signatures.

:data:`REGISTRY` holds, per kind, ``name -> "module.attribute"`` (imported on first use, so any
module may import this one). Library code looks names up with :func:`lookup`; :func:`table` is a
read-only view of one kind (``torchflow.resampling.RESAMPLERS``, ``torchflow.proposals.FLOWS``).

Configs hold only what differs from the Python defaults. :func:`register_configs` stores, in
Hydra's ConfigStore, one node per class of the registry as ``signature/<module.Class>``: its
``_target_`` and every constructor argument with its default (:func:`signature_node`). A component
config extends it through its defaults list, so ``filter.bpf.ess_threshold=0.3`` works without a
``+`` although configs/filter/bpf.yaml does not name the key::

    # @package filter.bpf
    defaults: [/signature/torchflow.filters.BootstrapParticleFilter@_here_]
    n_particles: ${n_particles}

Arguments left out of a node: those without a default (``model``, given when the filter is built),
``*args`` / ``**kwargs`` themselves, and defaults YAML cannot hold (tensors, callables, objects);
a ``**kwargs`` is followed into the keyword-only arguments of the base class that receives it.
The command line registers the nodes before Hydra composes; code that composes the configs itself
calls :func:`register_configs` first.
"""
from __future__ import annotations

import importlib
import inspect
from typing import Any, Callable, Dict, Iterator, List, Mapping

#: kind -> name -> "module.attribute"
REGISTRY: Dict[str, Dict[str, str]] = {
    "filter": {
        "kf": "torchflow.filters.KalmanFilter",
        "ekf": "torchflow.filters.ExtendedKalmanFilter",
        "ukf": "torchflow.filters.UnscentedKalmanFilter",
        "pf": "torchflow.filters.ParticleFilter",
        "bpf": "torchflow.filters.BootstrapParticleFilter",
        "pfpf": "torchflow.filters.ParticleFlowParticleFilter",
        "pfpf_clustered": "torchflow.filters.ClusteredParticleFlowParticleFilter",
        "flow_filter": "torchflow.filters.ParticleFlowFilter",
        "gpfis": "torchflow.filters.GaussianParticleFlowImportanceSampler",
        "gspf": "torchflow.filters.GaussianSumParticleFilter",
        "pfgspf": "torchflow.filters.ParticleFlowGaussianSumParticleFilter",
    },
    "flow": {
        "edh": "torchflow.flows.EDHFlow",
        "ledh": "torchflow.flows.LEDHFlow",
        "geodesic": "torchflow.flows.GeodesicFlow",
        "gromov": "torchflow.flows.GromovFlow",
        "osd": "torchflow.flows.OptimalDiffusionFlow",
    },
    "proposal": {
        "bootstrap": "torchflow.proposals.BootstrapProposal",
        "flow": "torchflow.proposals.flow_proposal",
        "gpfis": "torchflow.proposals.GPFISProposal",
        "unscented": "torchflow.proposals.UnscentedProposal",
    },
    "model": {
        "acoustic": "torchflow.models.AcousticTracking",
        "linear_gaussian": "torchflow.models.SensorNetwork",
        "skewed_t_poisson": "torchflow.models.SkewedTPoisson",
        "tdoa": "torchflow.models.TDOA3D",
    },
    "schedule": {
        "exponential": "torchflow.schedules.ExponentialSchedule",
        "uniform": "torchflow.schedules.UniformSchedule",
        "geometric": "torchflow.schedules.GeometricSchedule",
    },
    "resampling": {
        "multinomial": "torchflow.resampling.multinomial",
        "systematic": "torchflow.resampling.systematic",
        "stratified": "torchflow.resampling.stratified",
        "residual": "torchflow.resampling.residual",
    },
}

#: the ConfigStore group of the signature nodes (``/signature/<module.Class>`` in a defaults list)
GROUP = "signature"


def resolve(path: str) -> Any:
    """The object named by ``"module.attribute"``."""
    module, _, attr = path.rpartition(".")
    return getattr(importlib.import_module(module), attr)


def names(kind: str) -> List[str]:
    """The names of one kind, sorted."""
    return sorted(REGISTRY[kind])


def lookup(kind: str, name: object, arg_name: str = "") -> Any:
    """The class or function registered as ``name``; a ``ValueError`` naming the choices if none."""
    if not isinstance(name, str) or name not in REGISTRY[kind]:
        raise ValueError(f"{arg_name or kind}: expected one of {names(kind)}, got {name!r}")
    return resolve(REGISTRY[kind][name])


class _Table(Mapping):
    """Read-only ``name -> object`` view of one kind (objects imported on first access)."""

    def __init__(self, kind: str):
        self.kind = kind

    def __getitem__(self, name: str) -> Any:
        if name not in REGISTRY[self.kind]:
            raise KeyError(name)
        return resolve(REGISTRY[self.kind][name])

    def __iter__(self) -> Iterator[str]:
        return iter(REGISTRY[self.kind])

    def __len__(self) -> int:
        return len(REGISTRY[self.kind])

    def __repr__(self) -> str:
        return f"registry.table({self.kind!r})"


def table(kind: str) -> Mapping[str, Any]:
    """``name -> object`` for one kind, e.g. ``table("resampling")["systematic"]``."""
    return _Table(kind)


# ---------------------------------------------------------------------------------------------
# config nodes from signatures

_MISSING = object()


def _yaml_value(v: Any) -> Any:
    """``v`` as YAML can hold it (tuples as lists), or ``_MISSING``."""
    if v is None or isinstance(v, (bool, int, float, str)):
        return v
    if isinstance(v, (list, tuple)):
        out = [_yaml_value(x) for x in v]
        return _MISSING if any(x is _MISSING for x in out) else out
    if isinstance(v, dict) and all(isinstance(k, str) for k in v):
        out = {k: _yaml_value(x) for k, x in v.items()}
        return _MISSING if any(x is _MISSING for x in out.values()) else out
    return _MISSING


def signature_defaults(target: Callable) -> Dict[str, Any]:
    """``argument -> default`` of ``target`` (a class: its ``__init__``, following ``**kwargs`` into
    the keyword-only arguments of the torchflow base class that receives them), raw Python values."""
    out: Dict[str, Any] = {}
    chain = [c for c in target.__mro__ if "__init__" in vars(c) and c.__module__.startswith("torchflow")] \
        if inspect.isclass(target) else [target]
    for depth, fn in enumerate(chain):
        params = inspect.signature(fn).parameters.values()
        forwards = False
        for p in params:
            if p.kind is p.VAR_KEYWORD:
                forwards = True
            elif p.kind is not p.VAR_POSITIONAL and p.default is not p.empty and p.name not in out \
                    and (depth == 0 or p.kind is p.KEYWORD_ONLY):  # a base's positional ones are the subclass's to give
                out[p.name] = p.default
        if not forwards:
            break
    return out


def signature_node(target: Callable, path: str = "") -> Dict[str, Any]:
    """The config node of ``target`` (named ``path``, default its module and name): ``_target_`` and
    every default YAML can hold."""
    node: Dict[str, Any] = {"_target_": path or f"{target.__module__}.{target.__qualname__}"}
    for k, v in signature_defaults(target).items():
        v = _yaml_value(v)
        if v is not _MISSING:
            node[k] = v
    return node


def targets() -> Dict[str, Callable]:
    """``"module.Class" -> class`` of every class in the registry (the targets configs may extend)."""
    out = {}
    for kind in REGISTRY.values():
        for path in kind.values():
            obj = resolve(path)
            if inspect.isclass(obj):
                out[path] = obj
    return out


def register_configs() -> None:
    """Store :func:`signature_node` of every registered class in Hydra's ConfigStore as
    ``signature/<module.Class>`` (idempotent; call before Hydra composes the configs)."""
    from hydra.core.config_store import ConfigStore

    cs = ConfigStore.instance()
    for path, cls in targets().items():
        cs.store(group=GROUP, name=path, node=signature_node(cls, path), provider="torchflow")


__all__ = ["REGISTRY", "GROUP", "resolve", "names", "lookup", "table", "signature_defaults", "signature_node",
           "targets", "register_configs"]
