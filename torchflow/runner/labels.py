"""Row labels: the config key of a filter, plus what an override changed that the key does not say."""
from __future__ import annotations

_FLOW_NAMES = {"EDHFlow": "edh", "LEDHFlow": "ledh", "GeodesicFlow": "geodesic", "GromovFlow": "gromov",
               "OptimalDiffusionFlow": "osd"}


def flow_label(flow) -> str:
    """Config-style name of a flow: ``ledh``, ``gromov``; ``_global`` for a per-trial linearisation
    of a flow that is per particle by default."""
    name = _FLOW_NAMES.get(type(flow).__name__, type(flow).__name__)
    if name not in ("edh", "ledh") and getattr(flow, "points", "particle") != "particle":
        name += "_global"
    return name


def _gaussian_sum_label(key: str, f, flow) -> str:
    tags = [f"{f.particles_per_component}x{f.n_components}"]
    fl = None if flow is None else flow_label(flow)
    if fl != ("ledh" if key.startswith("pf") else None):
        tags.append(f"flow={fl}")
    if getattr(f, "estimate", "mixture_mean") != "mixture_mean":
        tags.append(f"estimate={f.estimate}")
    return f"{key}[{','.join(tags)}]"


def row_label(key: str, f) -> str:
    """A result row's label: the config key, plus the flow and linearisation points it really ran
    when an override made the key's name wrong (``pfpf_ledh`` run with
    ``flow@filter.pfpf_ledh.flow=edh`` -> ``pfpf_ledh[flow=edh]``; with
    ``filter.pfpf_ledh.points=global`` -> ``pfpf_ledh[points=global]``)."""
    flow = getattr(f, "flow", None)
    if hasattr(f, "method"):  # TDOA localisers: the key names the method
        return key
    if hasattr(f, "n_components"):  # Gaussian-sum filters: the seed's N* x G label, and a flow the key does not say
        return _gaussian_sum_label(key, f, flow)
    if flow is None:
        return key
    fl = flow_label(flow)
    named = [n for n in sorted(set(_FLOW_NAMES.values()), key=len, reverse=True) if n in key.split("_")]
    expected = named[0] if named else "ledh"  # a key naming no flow (pfpf_clustered) runs LEDH by default
    tags = [] if fl == expected else [f"flow={fl}"]
    points = getattr(getattr(f, "points", None), "name", None)
    default_points = "clustered" if "clustered" in key.split("_") else flow.points
    if points is not None and points != default_points:
        tags.append(f"points={points}")
    return f"{key}[{','.join(tags)}]" if tags else key
