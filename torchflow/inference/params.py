"""What the particle MCMC samplers share: the parameters' unconstrained space and priors, per-trial
parameter values, and the adaptive random walk."""

from __future__ import annotations

import contextlib
import math
from typing import Dict, Optional

import torch
from torch.distributions import Distribution, transform_to

from torchflow.core.checks import check_count
from torchflow.core.errors import ArgumentError, ArgumentTypeError
from torchflow.core.random import check_generator
from torchflow.models.trials import parameter_domain, support_within


@contextlib.contextmanager
def per_trial_values(model, values: Dict[str, torch.Tensor]):
    """Within the block, ``model``'s parameters or buffers named in ``values`` hold one value per
    trial, ``(B, *shape)`` for a parameter of shape ``shape`` (the same B for every name); the model's
    own are put back afterwards, also on error.

    Every name must be one the model declares in ``per_trial_parameters`` (its methods broadcast
    those over the trials' states). A constrained learnable parameter (:mod:`torchflow.core.constraints`)
    keeps its constraint: its values, given as the constrained values, are mapped to the
    unconstrained space by the constraint's inverse and the model reads them back through the
    constraint (valid by construction; a value outside it is refused, naming the parameter), so a
    gradient reaches the values either way. For the block the model also declares a structure
    without the shortcuts that assume one value for every trial (its ``_per_trial_structure``:
    identity scales, a scalar R read as one number, matrices read once for all trials, captured
    graphs), and filters see which names hold per-trial values
    (:func:`torchflow.models.trials.trial_names`; the Kalman filter's Riccati recursion shared by
    the trials stands aside).

    Raises:
        ArgumentError: a name the model does not declare, a value that is not ``(B, *shape)`` on the
            model's dtype and device, a non-finite value, a value outside the domain the model
            declares for the name (:func:`torchflow.models.trials.parameter_domain`: a negative
            ``sigma``), or trial counts that differ between names.
    """
    from torch.nn.utils import parametrize

    declared = tuple(getattr(model, "per_trial_parameters", ()) or ())
    who = type(model).__name__
    saved, B = [], None
    try:
        for name, value in values.items():
            if name not in declared:
                raise ArgumentError(
                    f"values: {who} does not declare {name!r} as a per-trial parameter (it declares "
                    f"{list(declared)}): its methods would not give each trial its own value"
                )
            shared = getattr(model, name)
            if not isinstance(value, torch.Tensor):
                raise ArgumentTypeError(
                    f"values[{name!r}]: expected a tensor (B, *{tuple(shared.shape)}), got {type(value).__name__}"
                )
            if value.dim() != shared.dim() + 1 or tuple(value.shape[1:]) != tuple(shared.shape) or not value.shape[0]:
                raise ArgumentError(
                    f"values[{name!r}]: expected one value per trial, (B, *{tuple(shared.shape)}) with "
                    f"B >= 1, got {tuple(value.shape)}"
                )
            if value.dtype != shared.dtype or value.device != shared.device:
                raise ArgumentError(
                    f"values[{name!r}]: expected {shared.dtype} on {shared.device} (the model's), got "
                    f"{value.dtype} on {value.device}"
                )
            if B is not None and value.shape[0] != B:
                raise ArgumentError(f"values[{name!r}]: {value.shape[0]} trials, where another value has {B}")
            finite = torch.isfinite(value.detach()).reshape(value.shape[0], -1).all(1)
            if not bool(finite.all()):  # once, on entering the block (not in a filter step)
                bad = torch.nonzero(~finite).squeeze(1).tolist()
                raise ArgumentError(
                    f"values[{name!r}]: expected finite values, got NaN or infinity in trial(s) {bad[:10]}"
                )
            domain = parameter_domain(model, name)
            if domain is not None:  # the model's declared domain (also once, on entering the block)
                inside = domain.check(value.detach()).reshape(value.shape[0], -1).all(1)
                if not bool(inside.all()):
                    bad = torch.nonzero(~inside).squeeze(1).tolist()
                    first = value.detach()[bad[0]]
                    shown = f"{float(first):.6g}" if first.numel() == 1 else "a value outside it"
                    raise ArgumentError(
                        f"values[{name!r}]: expected values in {who}'s domain of {name} ({domain}), got "
                        f"{shown} in trial(s) {bad[:10]}"
                    )
            B = value.shape[0]
            if parametrize.is_parametrized(model, name):  # through the same constraint
                plist = model.parametrizations[name]
                table, key = plist._parameters, "original"
                try:
                    value = plist[0].right_inverse(value)
                except (ArgumentError, RuntimeError) as exc:  # a covariance's Cholesky fails: torch's LinAlgError
                    raise ArgumentError(
                        f"values[{name!r}]: outside {type(plist[0]).__name__}'s constraint: {exc}"
                    ) from None
            else:
                table, key = (model._parameters if name in model._parameters else model._buffers), name
            saved.append((table, key, table[key]))
            table[key] = value
        saved.append((model.__dict__, "_trial_names", model.__dict__.get("_trial_names", _ABSENT)))
        model.__dict__["_trial_names"] = tuple(values)
        hook = getattr(model, "_per_trial_structure", None)
        structure = hook(tuple(values)) if values and hook is not None else getattr(model, "structure", None)
        saved.append((model.__dict__, "_shared_structure", model.__dict__.get("_shared_structure", _ABSENT)))
        model.__dict__["_shared_structure"] = model.structure
        saved.append((model.__dict__, "structure", model.__dict__.get("structure", _ABSENT)))
        model.__dict__["structure"] = structure
        yield model
    finally:
        for table, key, value in reversed(saved):
            if value is _ABSENT:
                del table[key]
            else:
                table[key] = value
        model.__dict__.pop("_trial_factors", None)


_ABSENT = object()


class ParameterSpace:
    """The parameters named in ``priors`` (name -> ``torch.distributions.Distribution`` of the
    constrained value) as one unconstrained vector per chain, ``u (C, p)``: each block maps to its
    parameter by ``transform_to(prior.support)``, and the prior density in ``u`` carries the
    transform's log-Jacobian."""

    def __init__(self, model, priors: Dict[str, Distribution], n_chains: int):
        if not isinstance(priors, dict) or not priors:
            raise ArgumentError("priors: expected a dict name -> torch.distributions.Distribution (at least one)")
        declared = tuple(getattr(model, "per_trial_parameters", ()) or ())
        for name, dist in priors.items():
            if not isinstance(dist, Distribution):
                raise ArgumentTypeError(
                    f"priors[{name!r}]: expected a torch.distributions.Distribution, got {type(dist).__name__}"
                )
            if name not in declared:
                raise ArgumentError(
                    f"priors: {type(model).__name__} does not declare {name!r} as a per-trial "
                    f"parameter (it declares {list(declared)}): a chain's value must reach its own trial"
                )
            domain = parameter_domain(model, name)
            if not support_within(dist.support, domain):
                raise ArgumentError(
                    f"priors[{name!r}]: {type(dist).__name__}'s support ({dist.support}) reaches outside "
                    f"{type(model).__name__}.{name}'s domain ({domain}): draws there are not valid values; "
                    "choose a prior on that domain (for a positive parameter: Gamma, LogNormal, HalfNormal)"
                )
        self.model, self.priors, self.C = model, priors, check_count("n_chains", n_chains)
        self.names = list(priors)
        self.transforms = {n: transform_to(priors[n].support) for n in self.names}
        self.shapes = {n: tuple(priors[n].batch_shape + priors[n].event_shape) for n in self.names}
        self.sizes = {n: int(math.prod(self.shapes[n])) for n in self.names}

    @property
    def dim(self) -> int:
        return sum(self.sizes.values())

    def _blocks(self, u: torch.Tensor):
        i = 0
        for n in self.names:
            uu = u[..., i : i + self.sizes[n]].reshape(*u.shape[:-1], *self.shapes[n])
            yield n, uu
            i += self.sizes[n]

    def constrained(self, u: torch.Tensor) -> Dict[str, torch.Tensor]:
        """name -> constrained values ``(..., *shape)`` of ``u (..., p)``."""
        return {n: self.transforms[n](uu) for n, uu in self._blocks(u)}

    def on_model(self, u: torch.Tensor) -> Dict[str, torch.Tensor]:
        """:meth:`constrained` on the model's dtype and device (what :func:`per_trial_values` takes)."""
        return {n: v.to(dtype=self.model.dtype, device=self.model.device) for n, v in self.constrained(u).items()}

    def log_prior(self, u: torch.Tensor) -> torch.Tensor:
        """``(C,)`` log prior density of ``u (C, p)`` (in u: with the transforms' log-Jacobians)."""
        total = torch.zeros(u.shape[0], dtype=torch.float64)
        for n, uu in self._blocks(u):
            theta = self.transforms[n](uu)
            lp = self.priors[n].log_prob(theta) + self.transforms[n].log_abs_det_jacobian(uu, theta)
            total = total + lp.reshape(u.shape[0], -1).sum(-1)
        return total

    def initial(self, init: Optional[Dict[str, torch.Tensor]], generator: torch.Generator) -> torch.Tensor:
        """``u (C, p)`` from ``init`` (name -> constrained value, shared or per chain) or, without
        it, a draw from each prior per chain (torch.distributions draw from torch's global
        generator: here seeded from ``generator``, and restored afterwards)."""
        C = self.C
        if init is None:
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(int(torch.randint(0, 2**40, (1,), generator=generator)))
                start = {n: self.priors[n].sample((C,)) for n in self.names}
        else:
            absent = [n for n in self.names if n not in init]
            if absent:
                raise ArgumentError(f"init: expected a starting value for every parameter in priors, missing {absent}")
            start = {n: torch.as_tensor(init[n], dtype=torch.float64).expand(C, *self.shapes[n]) for n in self.names}
        return torch.cat([self.transforms[n].inv(start[n].double()).reshape(C, -1) for n in self.names], 1)


class RandomWalk:
    """Gaussian random-walk proposals on ``u (C, p)``: ``u + s_c L xi``, adapted during the first
    ``n_adapt`` iterations and fixed afterwards (so the kept chain is a plain Metropolis chain).

    * the shape ``L``: the identity at first, then, from ``2 p + 2`` adaptation iterations on, the
      Cholesky factor of ``2.38^2 / p`` times the covariance of the states visited so far, pooled
      over the chains (Haario, Saksman & Tamminen 2001; Roberts & Rosenthal's scaling), which
      follows correlated parameters (stochastic volatility's rho and sigma);
    * the scale ``s_c`` of each chain: Robbins-Monro on its logarithm towards ``target`` acceptance.
    """

    def __init__(self, C: int, dim: int, scale: float, n_adapt: int, target: Optional[float], generator):
        if not (isinstance(scale, (int, float)) and not isinstance(scale, bool) and scale > 0):
            raise ArgumentError(f"scale: expected a number > 0, got {scale!r}")
        if int(n_adapt) != n_adapt or n_adapt < 0:
            raise ArgumentError(f"n_adapt: expected an integer >= 0, got {n_adapt!r}")
        self.log_scale = torch.full((C,), math.log(scale), dtype=torch.float64)
        self.n_adapt, self.generator, self.dim = int(n_adapt), generator, int(dim)
        self.target = target if target is not None else (0.44 if dim == 1 else 0.234)
        self.shape = torch.eye(self.dim, dtype=torch.float64)  # L
        self._n, self._sum = 0, torch.zeros(self.dim, dtype=torch.float64)
        self._outer = torch.zeros(self.dim, self.dim, dtype=torch.float64)
        self._relative = False  # the scale is relative to the visited covariance once it is used

    def propose(self, u: torch.Tensor) -> torch.Tensor:
        step = torch.randn(u.shape, generator=self.generator, dtype=torch.float64) @ self.shape.T
        return u + step * self.log_scale.exp().unsqueeze(-1)

    def accept(self, log_alpha: torch.Tensor, it: int) -> torch.Tensor:
        """``(C,)`` bool accept draws for ``log_alpha (C,)`` (NaN: reject); adapts the scale at
        iteration ``it`` (1-based) while ``it <= n_adapt``."""
        log_alpha = torch.nan_to_num(log_alpha, nan=-math.inf)
        ok = torch.log(torch.rand(log_alpha.shape, generator=self.generator, dtype=torch.float64)) < log_alpha
        if it <= self.n_adapt:
            self.log_scale = self.log_scale + (ok.double() - self.target) / it**0.6
        return ok

    def visit(self, u: torch.Tensor, it: int) -> None:
        """Record the chains' states ``u (C, p)`` after iteration ``it``; during adaptation, refresh
        the proposal's shape from the covariance of the states visited so far."""
        if it > self.n_adapt:
            return
        self._n += u.shape[0]
        self._sum += u.sum(0)
        self._outer += u.T @ u
        if it < 2 * self.dim + 2:
            return
        mean = self._sum / self._n
        cov = self._outer / self._n - torch.outer(mean, mean)
        cov = 0.5 * (cov + cov.T) + 1e-10 * torch.eye(self.dim, dtype=torch.float64)
        L, info = torch.linalg.cholesky_ex(cov * (2.38**2 / self.dim))
        if int(info) == 0:
            if not self._relative:  # from here on the scale multiplies the visited covariance's shape
                self.log_scale = torch.zeros_like(self.log_scale)
                self._relative = True
            self.shape = L


def cpu_generator(generator) -> torch.Generator:
    """The samplers' own generator (a seed, or a CPU ``torch.Generator``)."""
    if isinstance(generator, int) and not isinstance(generator, bool):
        return torch.Generator().manual_seed(generator)
    check_generator(generator, "generator")
    if not isinstance(generator, torch.Generator) or generator.device.type != "cpu":
        raise ArgumentError(
            "generator: expected a seed or a CPU torch.Generator (the chains' own draws; the "
            "filters' streams are made on the model's device)"
        )
    return generator


def one_series(observations: torch.Tensor, C: int) -> torch.Tensor:
    """``(T, m)`` or ``(1, T, m)`` expanded to ``(C, T, m)``."""
    if not isinstance(observations, torch.Tensor):
        raise ArgumentTypeError(f"observations: expected a tensor (T, m), got {type(observations).__name__}")
    obs = observations if observations.dim() == 3 else observations.unsqueeze(0)
    if obs.dim() != 3 or obs.shape[0] != 1:
        raise ArgumentError(f"observations: expected one series (T, m) or (1, T, m), got {tuple(observations.shape)}")
    return obs.expand(C, -1, -1)


def prior_of(prior, params: Dict[str, torch.Tensor], C: Optional[int] = None):
    """The filters' prior of the initial state: ``prior`` as ``(mean, cov)``, or ``prior(params)``;
    with ``C``, a shared ``(d,)``, ``(d, d)`` expanded to ``(C, d)``, ``(C, d, d)``."""
    mean, cov = prior(params) if callable(prior) else prior
    if C is not None and mean.dim() == 1:
        mean = mean.expand(C, -1)
    if C is not None and cov.dim() == 2:
        cov = cov.expand(C, -1, -1)
    return mean, cov


__all__ = ["per_trial_values", "ParameterSpace", "RandomWalk"]
