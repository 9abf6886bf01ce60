"""Localisation geometry: where state coordinates and observations are, how far apart, and the
taper that turns a distance into a weight. Read by every localising filter and flow (the LETKF,
the local particle filter, the localised lag-one flow, the kernel flow's tapered prior).

* :func:`gaspari_cohn`: Gaspari & Cohn's compactly supported correlation of a distance;
* :func:`periodic_distances`, :func:`periodic_neighbours`: a ring of ``d`` sites (Lorenz-96);
* :func:`local_observations`: the observations within a radius of each state coordinate, in the
  model's *declared* geometry (``structure.sites = "ring"``, ``site_distances()``, or distances
  given); :func:`declared_distances`, :func:`check_distances`, :func:`check_radius`: the checks.

Models are read through what they declare (``structure``, ``observed``, ``site_distances``), never
imported: this module sits below the models.
"""

from __future__ import annotations

import math
from typing import Optional, Tuple

import torch

from torchflow.core.errors import ArgumentError, ArgumentTypeError

__all__ = [
    "DIAGONAL_NOISE",
    "gaspari_cohn",
    "periodic_distances",
    "periodic_neighbours",
    "local_observations",
    "check_distances",
    "declared_distances",
    "check_radius",
]

#: the declared measurement-noise structures whose R is diagonal: each observation's precision can be
#: tapered on its own (what localisation needs)
DIAGONAL_NOISE = ("scalar", "diagonal", "state_dependent_diagonal")


def gaspari_cohn(dist: torch.Tensor, radius: float) -> torch.Tensor:
    """Gaspari & Cohn's (1999, eq. 4.10) compactly supported correlation function of ``dist``
    (any shape, >= 0), with half-width ``c = radius / 2``: 1 at 0, about 0.21 at ``c`` and 0 from
    ``radius = 2c`` on. ``radius = inf`` gives 1 everywhere."""
    if math.isinf(radius):
        return torch.ones_like(dist)
    r = dist / (0.5 * radius)
    near = ((-0.25 * r + 0.5) * r + 0.625) * r**3 - (5.0 / 3.0) * r**2 + 1.0
    rs = r.clamp_min(1e-300)  # the far branch is used only for 1 < r < 2
    far = ((((r / 12.0 - 0.5) * r + 0.625) * r + 5.0 / 3.0) * r - 5.0) * r + 4.0 - 2.0 / (3.0 * rs)
    return torch.where(r <= 1, near, torch.where(r < 2, far, torch.zeros_like(r))).clamp_min(0.0)


def periodic_distances(d: int, positions: torch.Tensor) -> torch.Tensor:
    """``(d, m)`` distances on a ring of ``d`` sites (site ``i`` at position ``i``) between the state
    coordinates and observations at ``positions (m,)`` (site indices, e.g. Lorenz-96's observed
    coordinates): ``min(|i - p_j|, d - |i - p_j|)``."""
    diff = (torch.arange(d, dtype=torch.float64).unsqueeze(1) - positions.to(torch.float64).unsqueeze(0)).abs()
    return torch.minimum(diff, d - diff)


def periodic_neighbours(d: int, positions: torch.Tensor, radius: float) -> Tuple[torch.Tensor, torch.Tensor]:
    """The observations within ``radius`` of each site of a ring of ``d`` sites, for ``radius <= d / 2``,
    without the ``(d, m)`` distance matrix: ``(taper (d, K), index (d, K))``, the Gaspari-Cohn taper
    and the observation index of each (K: the most observations one site reaches; unused slots have
    taper 0 and index 0). The same neighbours and tapers as :func:`periodic_distances` then
    :func:`gaspari_cohn`, in ``O(d K)`` memory (d = 10^5 and more)."""
    pos = positions.to(torch.float64)
    order = torch.argsort(pos)
    ps, m = pos[order], pos.shape[0]
    ext = torch.cat([ps - d, ps, ps + d])  # the ring unrolled three times: a window never wraps
    ext_index = torch.cat([order, order, order])
    site = torch.arange(d, dtype=torch.float64)
    lo = torch.searchsorted(ext, site - radius, right=True)  # the first at distance < radius
    hi = torch.searchsorted(ext, site + radius, right=False)
    count = hi - lo
    K = max(1, int(count.max()))
    slot = lo.unsqueeze(1) + torch.arange(K)
    valid = torch.arange(K) < count.unsqueeze(1)
    slot = slot.clamp(max=3 * m - 1)
    taper = torch.where(valid, gaspari_cohn((ext[slot] - site.unsqueeze(1)).abs(), radius), torch.zeros(()))
    return taper, torch.where(valid, ext_index[slot], torch.zeros((), dtype=torch.long))


def local_observations(
    model, radius: float, distances: Optional[torch.Tensor] = None
) -> Tuple[torch.Tensor, torch.Tensor]:
    """The observations within ``radius`` of each state coordinate, ``(taper (d, K), index (d, K))``:
    the Gaspari-Cohn taper and the observation index of each (K: the most observations one coordinate
    reaches; unused slots have taper 0 and index 0), on the CPU.

    ``distances (d, m)`` between state coordinates and observations; ``None``: the model's declared
    geometry, observation ``j`` at the site ``model.observed[j]`` (the state coordinate it reads),
    or at site ``j`` when ``m = d`` and the model has no ``observed``: a ring of ``d`` sites where
    the model declares ``structure.sites = "ring"`` (Lorenz-96; with ``radius <= d / 2`` no ``(d, m)``
    matrix is formed, :func:`periodic_neighbours`), else its ``site_distances()``; a model that
    declares neither is refused (a 1-D ring is not every model's geometry). ``radius = inf`` needs
    no geometry."""
    d, m = model.state_dim, model.obs_dim
    if distances is not None:
        dist = check_distances("distances", distances, (d, m))
    elif math.isinf(radius):  # no localisation: every observation everywhere, no geometry needed
        return torch.ones(d, m, dtype=torch.float64), torch.arange(m).expand(d, m).clone()
    else:
        observed = getattr(model, "observed", None)
        if isinstance(observed, torch.Tensor) and tuple(observed.shape) == (m,):
            positions = observed.cpu()
        elif m == d:
            positions = torch.arange(d)
        else:
            raise ArgumentError(
                f"distances: the model ({type(model).__name__}, d = {d}, m = {m}) does not say which state "
                "coordinate each observation reads (an `observed` tensor (m,)); pass distances (d, m)"
            )
        if model.structure.sites == "ring":
            if radius <= d / 2:  # the ring's neighbours directly: no (d, m) matrix
                return periodic_neighbours(d, positions, radius)
            dist = periodic_distances(d, positions)
        else:
            dist = declared_distances(model, "distances")[:, positions]
    rho = gaspari_cohn(dist, radius)  # (d, m)
    K = max(1, int((rho > 0).sum(-1).max()))  # observations that reach the best-reached coordinate
    return rho.topk(K, dim=-1)  # (d, K)


def check_distances(name: str, distances, shape: Tuple[int, int]) -> torch.Tensor:
    """``distances`` checked: a tensor of ``shape``, finite and ``>= 0``; float64 on the CPU."""
    if not isinstance(distances, torch.Tensor):
        raise ArgumentTypeError(f"{name}: expected a tensor {shape} or None, got {type(distances).__name__}")
    if tuple(distances.shape) != tuple(shape):
        raise ArgumentError(f"{name}: expected a tensor {tuple(shape)}, got {tuple(distances.shape)}")
    dist = distances.detach().to("cpu", torch.float64)
    bad = ~torch.isfinite(dist) | (dist < 0)
    if bool(bad.any()):
        i, j = torch.nonzero(bad)[0].tolist()
        raise ArgumentError(f"{name}: expected finite distances >= 0, got {float(dist[i, j])} at ({i}, {j})")
    return dist


def declared_distances(model, name: str) -> torch.Tensor:
    """The model's ``(d, d)`` :meth:`site_distances` (checked), or a one-line refusal naming ``name``
    where it declares none."""
    d = model.state_dim
    method = getattr(model, "site_distances", None)  # a model with a geometry of its own (the sensor grid)
    found = method() if callable(method) else None
    if found is None:
        raise ArgumentError(
            f"{name}: {type(model).__name__} declares no distances between its state coordinates (site_distances(); "
            f"Lorenz-96's sites are a ring, the sensor network's a grid), so a finite radius has nothing to measure: "
            f"pass {name} or use radius=inf (no localisation)"
        )
    return check_distances(f"{type(model).__name__}.site_distances()", found, (d, d))


def check_radius(radius) -> float:
    """A localisation radius: a number > 0 (``inf``: no localisation)."""
    ok = isinstance(radius, (int, float)) and not isinstance(radius, bool) and radius > 0 and not math.isnan(radius)
    if not ok:
        raise ArgumentError(
            f"radius: expected a number > 0 (the localisation radius; inf: no localisation), got {radius!r}"
        )
    return float(radius)
