"""One place mapping names to torchflow's classes and functions (:data:`REGISTRY`: kind -> name ->
``"module.attribute"``, imported on use; :func:`lookup`, :func:`table`), and the config nodes made from
their signatures. :func:`register_configs` stores in Hydra's ConfigStore, as ``signature/<module.Class>``,
each registered class's ``_target_`` and constructor arguments with their defaults; a config extends its
node (``defaults: [/signature/torchflow.filters.BootstrapParticleFilter@_here_]``) and holds only what
differs, and ``filter.bpf.ess_threshold=0.3`` works without a ``+``. Left out of a node: arguments with
no default (``model``), ``*args``/``**kwargs`` (followed into the keyword-only arguments of the base class
receiving them) and defaults YAML cannot hold (tensors, callables, objects). The command line registers
the nodes before Hydra composes; code composing configs/ itself calls :func:`register_configs` first."""

from __future__ import annotations

import importlib
import inspect
from typing import Any, Callable, Dict

from torchflow.core.errors import ArgumentError


def _kind(module: str, **names: str) -> Dict[str, str]:
    return {name: f"{module}.{attr}" for name, attr in names.items()}


#: kind -> name -> "module.attribute"
REGISTRY: Dict[str, Dict[str, str]] = {
    "filter": _kind(
        "torchflow.filters",
        kf="KalmanFilter",
        ekf="ExtendedKalmanFilter",
        ukf="UnscentedKalmanFilter",
        pf="ParticleFilter",
        bpf="BootstrapParticleFilter",
        pfpf="ParticleFlowParticleFilter",
        pfpf_clustered="ClusteredParticleFlowParticleFilter",
        flow_filter="ParticleFlowFilter",
        gpfis="GaussianParticleFlowImportanceSampler",
        gspf="GaussianSumParticleFilter",
        pfgspf="ParticleFlowGaussianSumParticleFilter",
        enkf="EnsembleKalmanFilter",
        etkf="EnsembleTransformKalmanFilter",
        letkf="LocalEnsembleTransformKalmanFilter",
        kpff="KernelParticleFlowFilter",
        lpf="LocalParticleFilter",
        lag1_flow="LagOneFlowFilter",
        lag1_pfpf="LagOneFlowParticleFilter",
        lag1_pfpf_local="LocalLagOneFlowParticleFilter",
    ),
    "localiser": _kind("torchflow.tdoa", bs="BootstrapLocaliser", pfi="FlowMixtureLocaliser"),
    "flow": _kind(
        "torchflow.flows",
        edh="EDHFlow",
        ledh="LEDHFlow",
        geodesic="GeodesicFlow",
        gromov="GromovFlow",
        osd="OptimalDiffusionFlow",
    ),
    "proposal": _kind(
        "torchflow.proposals",
        bootstrap="BootstrapProposal",
        flow="flow_proposal",
        gpfis="GPFISProposal",
        unscented="UnscentedProposal",
    ),
    "model": _kind(
        "torchflow.models",
        acoustic="AcousticTracking",
        linear_gaussian="SensorNetwork",
        skewed_t_poisson="SkewedTPoisson",
        tdoa="TDOA3D",
        lorenz63="Lorenz63",
        lorenz96="Lorenz96",
        stochastic_volatility="StochasticVolatility",
    ),
    "schedule": _kind(
        "torchflow.flows.schedules",
        exponential="ExponentialSchedule",
        uniform="UniformSchedule",
        geometric="GeometricSchedule",
    ),
    "resampling": _kind(
        "torchflow.core.resampling",
        multinomial="multinomial",
        systematic="systematic",
        stratified="stratified",
        residual="residual",
    ),
}
GROUP = "signature"  #: the ConfigStore group of the nodes: ``/signature/<module.Class>`` in a defaults list
_NO_YAML = object()


def resolve(path: str) -> Any:
    """The object named ``"module.attribute"``."""
    module, _, attr = path.rpartition(".")
    return getattr(importlib.import_module(module), attr)


def lookup(kind: str, name: object, arg_name: str = "") -> Any:
    """The object registered as ``name``; a ``ValueError`` naming the choices if there is none."""
    if not isinstance(name, str) or name not in REGISTRY[kind]:
        raise ArgumentError(f"{arg_name or kind}: expected one of {sorted(REGISTRY[kind])}, got {name!r}")
    return resolve(REGISTRY[kind][name])


def table(kind: str) -> Dict[str, Any]:
    """``name -> object`` of one kind (imports them: call it at the end of the module that defines them)."""
    return {name: resolve(path) for name, path in REGISTRY[kind].items()}


def yaml_value(v: Any) -> Any:
    """``v`` as YAML holds it (tuples as lists), or ``_NO_YAML``."""
    if v is None or isinstance(v, (bool, int, float, str)):
        return v
    if isinstance(v, (list, tuple)):
        out = [yaml_value(x) for x in v]
    elif isinstance(v, dict) and all(isinstance(k, str) for k in v):
        out = {k: yaml_value(x) for k, x in v.items()}
    else:
        return _NO_YAML
    return _NO_YAML if any(x is _NO_YAML for x in (out.values() if isinstance(out, dict) else out)) else out


def signature_defaults(target: Callable) -> Dict[str, Any]:
    """``argument -> default`` of ``target`` (a class: its ``__init__``, following ``**kwargs`` into the
    keyword-only arguments of the torchflow base class receiving them; a base's positional ones are the
    subclass's to give)."""
    out: Dict[str, Any] = {}
    chain = (
        [c for c in target.__mro__ if "__init__" in vars(c) and c.__module__.startswith("torchflow")]
        if inspect.isclass(target)
        else [target]
    )
    for depth, fn in enumerate(chain):
        params = inspect.signature(fn).parameters.values()
        out.update(
            {
                p.name: p.default
                for p in params
                if p.default is not p.empty and p.name not in out and (depth == 0 or p.kind is p.KEYWORD_ONLY)
            }
        )
        if not any(p.kind is p.VAR_KEYWORD for p in params):
            break
    return out


def signature_node(target: Callable, path: str = "") -> Dict[str, Any]:
    """``_target_`` (``path``, default the defining module's) and every default YAML can hold."""
    node = {k: yaml_value(v) for k, v in signature_defaults(target).items()}
    return {
        "_target_": path or f"{target.__module__}.{target.__qualname__}",
        **{k: v for k, v in node.items() if v is not _NO_YAML},
    }


def targets() -> Dict[str, type]:
    """``"module.Class" -> class`` of every class in the registry (what configs may extend)."""
    objs = {path: resolve(path) for kind in REGISTRY.values() for path in kind.values()}
    return {path: obj for path, obj in objs.items() if inspect.isclass(obj)}


def register_configs() -> None:
    """Store :func:`signature_node` of every registered class in Hydra's ConfigStore (idempotent)."""
    from hydra.core.config_store import ConfigStore

    for path, cls in targets().items():
        ConfigStore.instance().store(group=GROUP, name=path, node=signature_node(cls, path), provider="torchflow")


__all__ = [
    "REGISTRY",
    "GROUP",
    "resolve",
    "lookup",
    "table",
    "yaml_value",
    "signature_defaults",
    "signature_node",
    "targets",
    "register_configs",
]
