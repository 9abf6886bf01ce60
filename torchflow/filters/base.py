"""The filter contract shared by every filter: ``init`` / ``step`` / ``forward``."""

from __future__ import annotations

import contextlib
import functools
import itertools
import math
import warnings
from dataclasses import dataclass, field
from typing import Dict, Optional

import torch
import torch.utils.checkpoint
from torch import nn

from torchflow.core import linalg
from torchflow.core import missing as _missing
from torchflow.core import paths as _paths
from torchflow.core import random as _random
from torchflow.core import resampling as _resampling
from torchflow.core.blocks import blockwise
from torchflow.core.checks import (
    allocation_failure,
    check_choice,
    check_count,
    check_finite,
    check_psd,
    check_same,
    check_tensor,
)
from torchflow.core.covariances import Covariance, DiagonalCovariance, sample_prior
from torchflow.core.errors import ArgumentError, ArgumentTypeError
from torchflow.core.random import check_generator
from torchflow.filters import graph_step, guards
from torchflow.filters import marginal as _marginal
from torchflow.flows import select as _select
from torchflow.models.base import StateSpaceModel, partial_observations, require_gaussian
from torchflow.models.contract import (
    COVARIANCE_CHECK_NUMBERS,
    DECLARED_CHECK_NUMBERS,
    check_covariances,
    check_dtype,
    check_parameters,
    check_shapes,
)
from torchflow.models.structure import kernel_structure
from torchflow.models.trials import check_trial_count
from torchflow.proposals import BootstrapProposal, Proposal
from torchflow.proposals.flow import check_informative


@dataclass
class GaussianState:
    """Belief of a Kalman-type filter after a step.

    Attributes:
        mean: ``(B, d)`` posterior mean (the estimate).
        cov: ``(B, d, d)`` posterior covariance.
        log_evidence_increment: ``(B,)`` log p(z_k | z_{1:k-1}) of the step (0 after ``init``).
        step: number of observations processed.
        n_particles: particles drawn per step by sampling-based Gaussian filters (the unweighted
            flow filters), ``None`` for Kalman-type filters.
    """

    mean: torch.Tensor
    cov: torch.Tensor
    log_evidence_increment: torch.Tensor
    step: int = 0
    n_particles: Optional[int] = None

    @property
    def estimate(self) -> torch.Tensor:
        return self.mean

    @property
    def ess(self) -> Optional[torch.Tensor]:
        return None


@dataclass
class ParticleState:
    """Belief of a particle filter after a step.

    Attributes:
        particles: ``(B, N, d)``.
        log_weights: ``(B, N)`` normalised log-weights (after any resampling).
        estimate: ``(B, d)`` weighted mean before resampling.
        ess: ``(B,)`` effective sample size before resampling.
        log_evidence_increment: ``(B,)`` log of the estimate of p(z_k | z_{1:k-1}).
        resampled: ``(B,)`` bool, which trials were resampled this step.
        n_repaired: ``(B,)`` number of steps so far in which non-finite particles or weights were
            repaired (``nonfinite="recover"``).
        cov: optional :class:`~torchflow.core.covariances.Covariance` carried between steps (a PF-PF's
            tracked covariance: per trial or per particle, typed, not guessed from its shape).
        step: number of observations processed.
        extras: filter-specific tensors with a leading ``(B, N)`` that follow resampling.
        invalid: ``(B,)`` bool, trials with NaN/inf particles or weights this step (filters run with
            ``nonfinite="raise"``; ``forward`` raises :class:`NonFiniteError` for them), else ``None``.
    """

    particles: torch.Tensor
    log_weights: torch.Tensor
    estimate: torch.Tensor
    ess: torch.Tensor
    log_evidence_increment: torch.Tensor
    resampled: torch.Tensor
    n_repaired: Optional[torch.Tensor] = None
    cov: Optional[Covariance] = None
    step: int = 0
    extras: Dict[str, torch.Tensor] = field(default_factory=dict)
    invalid: Optional[torch.Tensor] = None


@dataclass
class FilterResult:
    """Output of :meth:`Filter.forward`.

    Attributes:
        estimates: ``(B, T, d)`` state estimates after each observation.
        log_evidence: ``(B,)`` log p(z_{1:T}) (exact for the KF, an unbiased-in-exp estimate for
            particle filters); differentiable where the filter is.
        log_evidence_increments: ``(B, T)``.
        ess: ``(B, T)`` effective sample size before resampling, ``None`` for Kalman-type filters.
        covariances: ``(B, T, d, d)`` posterior covariances if requested and defined.
        particles: ``(B, T, N, d)`` particles if requested (large).
        log_weights: ``(B, T, N)`` log-weights if particles were requested.
        n_repaired: ``(B,)`` steps in which non-finite particles/weights were repaired, for
            particle filters run with ``nonfinite="recover"`` (``None`` otherwise).
        g_eff: ``(B, T)`` effective number of Gaussians ``1 / sum_j alpha_j^2`` of Gaussian-sum
            filters (``None`` for others).
        std: ``(B, T, d)`` the filtering law's standard deviation of each coordinate, if requested
            (``forward(return_std=True)``; :func:`belief_std`).
        paths: ``{path: count}``: the execution paths the call's time steps took
            (:mod:`torchflow.core.paths`): ``"kernel:<name>"`` per flow integration by a
            fused kernel, ``"graph:flow"`` / ``"graph:step"`` per integration / step sent to a CUDA
            graph, ``"torch"`` per integration (or step without any of these) in plain PyTorch.
            Host-side counts; no number depends on them.
    """

    estimates: torch.Tensor
    log_evidence: torch.Tensor
    log_evidence_increments: torch.Tensor
    ess: Optional[torch.Tensor] = None
    covariances: Optional[torch.Tensor] = None
    particles: Optional[torch.Tensor] = None
    log_weights: Optional[torch.Tensor] = None
    n_repaired: Optional[torch.Tensor] = None
    g_eff: Optional[torch.Tensor] = None
    std: Optional[torch.Tensor] = None
    paths: Optional[Dict[str, int]] = None


def belief_std(state) -> torch.Tensor:
    """``(B, d)`` standard deviation of each state coordinate under a filter's belief after a step:
    the covariance's diagonal (Gaussian beliefs), the weighted particles' spread (particle beliefs),
    the mixture's (Gaussian-sum beliefs: within- plus between-component variance)."""
    if isinstance(state, ParticleState):
        w = torch.softmax(state.log_weights, -1).unsqueeze(-1)
        dev = state.particles - (w * state.particles).sum(1, keepdim=True)
        return (w * dev * dev).sum(1).clamp_min(0).sqrt()
    if isinstance(state, GaussianState):
        return state.cov.diagonal(dim1=-2, dim2=-1).clamp_min(0).sqrt()
    alpha = torch.softmax(state.log_alpha, -1).unsqueeze(-1)  # a mixture: (B, G, 1)
    spread = state.covs.diagonal(dim1=-2, dim2=-1) + (state.means - state.estimate.unsqueeze(1)).pow(2)
    return (alpha * spread).sum(1).clamp_min(0).sqrt()


class Estimator(nn.Module):
    """What the Monte Carlo runner (:func:`torchflow.app.runner.run_experiment`) reads of everything
    it runs: the filters (:class:`Filter`) and the TDOA localisers
    (:mod:`torchflow.tdoa`). Both derive from this class and declare these members; the
    runner reads nothing else of them.

    Declarations (class attributes; a subclass overrides them):

    * :attr:`output`: ``"states"`` (``forward`` returns a :class:`FilterResult` of point estimates
      ``(B, T, d)``) or ``"sets"`` (declared sources with a mask, scored as sets);
    * :attr:`padded_measurements`: ``forward`` takes measurement sets padded with a ``mask``;
    * :attr:`trials_per_call`: the most trials one call takes (``None``: any number);
    * :attr:`n_particles`, :attr:`particle_chunk`: particles per trial and the block of particles
      per-particle work runs in (``None`` where it has none);
    * :attr:`uses_randomness`, :attr:`random_stream` (:attr:`stream_name`): whether it draws, and
      the stable key of its per-trial random streams;
    * :attr:`estimates_evidence`: its ``log_evidence`` is worth scoring.

    Sizes (methods): :meth:`bytes_per_trial`, :meth:`preferred_chunk_trials`, :meth:`plan_memory`
    and :meth:`describe_blocks`, all taking ``n_particles=None`` (the estimator's own count).
    Set in ``__init__``: :attr:`name` (the label in results) and :attr:`model`.
    """

    output = "states"
    padded_measurements = False
    trials_per_call: Optional[int] = None
    n_particles: Optional[int] = None
    particle_chunk: Optional[int] = None
    uses_randomness = False
    random_stream: Optional[str] = None
    estimates_evidence = True
    name: str

    @property
    def stream_name(self) -> str:
        """The key of this estimator's random streams (:attr:`random_stream` or the class name)."""
        return self.random_stream or type(self).__name__

    def bytes_per_trial(self, n_particles: Optional[int] = None) -> int:
        """Rough peak memory of one trial in one step, used to size chunks of trials."""
        raise NotImplementedError(f"{type(self).__name__}.bytes_per_trial")

    def preferred_chunk_trials(self, n_particles: Optional[int] = None) -> Optional[int]:
        """Largest number of trials per call that runs at full speed (``None``: no limit beyond
        memory). Used by the experiment runner when no ``chunk_size`` is given."""
        return self.trials_per_call

    def plan_memory(self, budget_bytes: float, n_particles: Optional[int] = None) -> Optional[int]:
        """Blocks that keep one trial within ``budget_bytes`` (particle filters set
        :attr:`particle_chunk`, the LETKF its coordinates' ``local_chunk``); ``None``: no blocks."""
        return None

    def describe_blocks(self, chunk: int) -> str:
        """Words for the blocks :meth:`plan_memory` chose (the runner's warning)."""
        return f"{chunk} of its {self.n_particles} particles"


class Filter(Estimator):
    """Base class: a filter holds its model (a submodule) and its settings, never the belief.

    Subclasses implement :meth:`init` and :meth:`step`; :meth:`forward` runs them over time,
    validates inputs and raises :class:`~torchflow.core.checks.NonFiniteError` naming the filter,
    step and trials where an estimate stops being finite.

    Args:
        model: the :class:`~torchflow.models.StateSpaceModel` to filter.
        validate: check input shapes, dtypes, devices and covariances (cheap; turn off in
            tight loops).
        name: label used in error messages and result tables (defaults to the class's).
    """

    uses_particles = False
    #: whether ``log_evidence`` is an estimate of p(z_{1:T}) worth scoring (False for filters that
    #: only carry a Gaussian approximation of it, such as the unweighted flow filters)
    estimates_evidence = True
    #: advice added to a :class:`NonFiniteError` for a non-finite estimate (the filter's own knobs)
    nonfinite_hint: Optional[str] = None
    #: default of ``forward(checkpoint_steps=...)``: recompute each time step in the backward pass
    checkpoint_steps = False
    #: under autograd, check the gradient flowing back into every step and the model parameters'
    #: gradients, raising :class:`~torchflow.core.errors.NonFiniteError` naming the step, trials or
    #: parameter (:mod:`torchflow.filters.guards`; one host read per step of the backward pass)
    check_gradients = True
    #: the filter reads the model's Gaussian form (:class:`~torchflow.models.GaussianStateSpaceModel`);
    #: a particle filter leaves this to its proposal
    gaussian_form = True
    #: :meth:`init` takes a :class:`~torchflow.core.covariances.DiagonalCovariance` prior as it is (its
    #: variances, no ``d x d`` matrix: the ensemble Kalman filters, the bootstrap PF); other filters
    #: are given its dense matrix by :meth:`check_prior`
    diagonal_prior = False
    # what the runner reads (output, n_particles, particle_chunk, trials_per_call, random_stream,
    # uses_randomness, ...) is declared by :class:`Estimator`

    def __init__(self, model: StateSpaceModel, *, validate: bool = True, name: Optional[str] = None):
        super().__init__()
        self.name = name or type(self).__name__
        if not isinstance(model, StateSpaceModel):
            raise ArgumentTypeError(
                f"{self.name}: model: expected a torchflow StateSpaceModel, got {type(model).__name__}"
            )
        if self.gaussian_form:
            require_gaussian(model, self.name)
        self.model = model
        self.validate = validate

    # ---- contract ------------------------------------------------------------------------------
    def init(
        self,
        mean: torch.Tensor,
        cov: torch.Tensor,
        n_particles: Optional[int] = None,
        generator: Optional[torch.Generator] = None,
    ):
        """Initial state from the prior ``N(mean (B, d), cov (B, d, d))``."""
        raise NotImplementedError

    def step(self, state, z: torch.Tensor, generator: Optional[torch.Generator] = None):
        """Process one observation ``z (B, m)``; returns the new state."""
        raise NotImplementedError

    def bytes_per_trial(self, n_particles: Optional[int] = None) -> int:
        """Rough peak memory of one trial in one step, used to size chunks of trials."""
        d, m = self.model.state_dim, self.model.obs_dim
        return 8 * 8 * (d * d + m * d + m * m)

    # ---- helpers -------------------------------------------------------------------------------
    def check_model(self) -> None:
        """What this filter needs of its model's current parameters, checked once per call before
        the first step (with ``validate``; host reads are fine here, not in a step): the model's
        constant transition and measurement covariances are symmetric positive semi-definite
        (:func:`~torchflow.models.contract.check_covariances`; a learnable one may have left
        the cone after an optimiser step)."""
        check_parameters(self.model, self.name)
        check_covariances(self.model, self.name)

    def require_definite(self, which: str, why: str) -> None:
        """Raise unless the model's constant ``which`` covariance (``"transition"``: Q,
        ``"measurement"``: R of a Gaussian-form model declaring it constant) is positive definite;
        ``why``: what this filter needs it for, and what to do. One factorisation and host read per
        call (before the first step); a state-dependent covariance is left to the steps' non-finite
        handling."""
        from torchflow.models.base import GaussianStateSpaceModel

        model = self.model
        if not isinstance(model, GaussianStateSpaceModel) or (
            which == "measurement" and model.structure.measurement_noise not in ("scalar", "diagonal", "dense")
        ):
            return
        k = model.state_dim if which == "transition" else (model.obs_dim or 0)
        scale = model.structure.measurement_noise_scale
        declared_scalar = which == "measurement" and model.structure.measurement_noise == "scalar" and scale is not None
        if (
            declared_scalar and k * k > DECLARED_CHECK_NUMBERS or k * k > COVARIANCE_CHECK_NUMBERS
        ):  # not formed for a check: a declared R = r I by its scale
            if declared_scalar and not scale > 0:
                raise ArgumentError(
                    f"{self.name}: the model's measurement covariance is not positive definite "
                    f"(declared {scale:g} I); {why}"
                )
            return
        try:
            C = model.transition_cov() if which == "transition" else model.measurement_cov()
        except (NotImplementedError, TypeError, RuntimeError, ValueError):
            return  # no constant covariance to check
        if not isinstance(C, torch.Tensor) or C.dim() != 2:
            return
        if bool((torch.linalg.cholesky_ex(C.detach())[1] > 0).any()):  # the error path reads the eigenvalue
            ev = torch.linalg.eigvalsh(linalg.symmetrize(C.detach())).min().item()
            learnable = " (built from learnable parameters)" if C.requires_grad else ""
            raise ArgumentError(
                f"{self.name}: the model's {which} covariance{learnable} is not positive definite "
                f"(smallest eigenvalue {ev:.3g}); {why}"
            )

    def check_prior(self, mean: torch.Tensor, cov, batch_size: Optional[int] = None):
        """Validate (and broadcast ``(d,)``/``(d, d)`` to) ``mean (B, d)``, ``cov (B, d, d)``. A
        :class:`~torchflow.core.covariances.DiagonalCovariance` (variances ``(B, d)`` or ``(d,)``) is
        checked on its variances and kept where the filter declares :attr:`diagonal_prior`, else
        given as its dense matrix."""
        d = self.model.state_dim
        ref = self.model._reference_tensor()
        if isinstance(mean, torch.Tensor) and mean.dim() == 1 and batch_size is not None:
            mean = mean.expand(batch_size, -1)
        if isinstance(cov, DiagonalCovariance):
            return mean, self._check_diagonal_prior(mean, cov, batch_size, d, ref)
        shared = isinstance(cov, torch.Tensor) and cov.dim() == 2
        if shared and tuple(cov.shape) != (d, d):
            raise ArgumentError(
                f"cov: expected (d, d) = ({d}, {d}) shared by every trial or (B, d, d), got "
                f"{tuple(cov.shape)} (per-trial variances (B, d) are torch.diag_embed(variances), or "
                "torchflow.core.covariances.DiagonalCovariance(variances) without the matrix)"
            )
        if shared and batch_size is not None:
            cov = cov.expand(batch_size, -1, -1)
        check_tensor("mean", mean, (batch_size, d), "(B, d)")
        check_tensor("cov", cov, (mean.shape[0], d, d), "(B, d, d)")
        check_same("mean", mean, ref)
        check_same("cov", cov, ref)
        if self.validate:
            check_finite("mean", mean)
            try:
                check_psd("cov", cov)
            except ValueError as err:
                if shared and d == mean.shape[0]:  # a (B, d) array of variances looks like (d, d) when B = d
                    raise ArgumentError(
                        f"{err} (a (d, d) matrix shared by every trial was given; if these are "
                        "per-trial variances (B, d), pass torch.diag_embed(variances) or "
                        "torchflow.core.covariances.DiagonalCovariance(variances))"
                    ) from None
                raise
        return mean, cov

    def _check_diagonal_prior(self, mean, cov: DiagonalCovariance, batch_size, d: int, ref):
        """:meth:`check_prior` of a diagonal prior: ``(B, d)`` variances, finite and >= 0."""
        var = cov.variance
        shared = var.dim() == 1 and tuple(var.shape) == (d,) and batch_size is not None
        if shared:
            var = var.expand(batch_size, -1)
        check_tensor("mean", mean, (batch_size, d), "(B, d)")
        check_tensor("cov.variance", var, (mean.shape[0], d), "(B, d) (a DiagonalCovariance's variances)")
        check_same("mean", mean, ref)
        check_same("cov.variance", var, ref)
        if self.validate:
            check_finite("mean", mean)
            check_finite("cov.variance", var)
            if bool((var < 0).any()):
                b = int(torch.nonzero((var < 0).any(-1))[0])
                raise ArgumentError(
                    f"cov.variance: expected variances >= 0 (a diagonal covariance), got "
                    f"{float(var[b].min()):.3g} in trial {b}"
                )
        if self.diagonal_prior:
            return DiagonalCovariance(var)
        # the matrix: one shared by every trial stays one (a view), as a shared (d, d) prior does
        return cov.dense().expand(batch_size, d, d) if shared else DiagonalCovariance(var).dense()

    def _checkpointed_step(self, state, z, generator):
        """:meth:`step` under ``torch.utils.checkpoint``: the recomputation in the backward pass
        starts from the generator's state before the step and leaves the generator as it was."""
        snap = _random.get_state(generator)
        calls = []

        def run(state, z):
            after = _random.get_state(generator) if calls else None  # a recomputation
            _random.set_state(generator, snap)
            try:  # a recomputation may stop early (by an exception) once it has what backward needs
                return self.step(state, z, generator)
            finally:
                if calls:
                    _random.set_state(generator, after)
                calls.append(1)

        return torch.utils.checkpoint.checkpoint(run, state, z, use_reentrant=False)

    def _raise_out_of_memory(self, err: BaseException, trials: int, n_particles: Optional[int]) -> None:
        """Re-raise an allocator's out-of-memory error as a :class:`MemoryError` that says what was
        asked for and which knobs bound it; return for any other error."""
        size = allocation_failure(err)
        if size is None:
            return
        n = getattr(self, "n_particles", None) if n_particles is None else n_particles
        try:
            est = f"; estimated {self.bytes_per_trial(n) * trials / 2**30:.3g} GiB per time step"
        except Exception:
            est = ""
        what = f"{trials} trials" + (f" x {int(n)} particles" if n is not None else "")
        raise MemoryError(
            f"{self.name}: out of memory running {what}{size}{est}. Use fewer particles, or fewer "
            "trials per call; particle filters can also work on blocks of particles "
            "(particle_chunk=...); the runner sizes its calls from memory_budget_gb (and chunk_size)"
        ) from err

    def _check_trace(self, trace: "_Trace", *, warn: bool) -> None:
        """The non-finite contract after the steps so far (:mod:`.guards`): raise
        :class:`NonFiniteError` for the earliest non-finite estimate, flagged particles/weights or
        log-evidence increment; with ``warn``, warn of steps that carried no measurement. One host
        read."""
        if not trace.n:
            return
        table = guards.table_to_host(
            guards.first_steps(
                trace.estimates(),
                trace.invalid_steps(),
                trace.increments(),
                getattr(self, "nonfinite", None) == "recover",
            )
        )
        guards.raise_first(self.name, table, getattr(self, "nonfinite_hint", None))
        if warn:
            guards.raise_never_measured(self.name, table, trace.n)
            guards.warn_dead_steps(self.name, table)
            if trace.first_collapse is not None:  # a second small read, once per call
                both = torch.stack((trace.first_collapse, trace.collapse_count)).tolist()
                text = guards.collapse_warning(
                    self.name, both[0], both[1], trace.n, getattr(self, "collapse_remedy", None)
                )
                if text is not None:
                    warnings.warn(text, RuntimeWarning, stacklevel=3)

    def forward(
        self,
        observations: torch.Tensor,
        mean: torch.Tensor,
        cov: torch.Tensor,
        generator: Optional[torch.Generator] = None,
        *,
        n_particles: Optional[int] = None,
        return_covariances: bool = False,
        return_particles: bool = False,
        progress=None,
        checkpoint_steps: Optional[bool] = None,
        return_std: bool = False,
    ) -> FilterResult:
        """Filter ``observations (B, T, m)`` from the prior ``N(mean (B, d), cov (B, d, d))``.

        Args:
            observations: ``(B, T, m)``.
            mean, cov: prior per trial (``(d,)`` / ``(d, d)`` are broadcast over trials).
            generator: source of all randomness: a ``torch.Generator`` (one stream for the
                batch) or :class:`~torchflow.core.random.TrialStreams` (one stream per trial, so a
                trial's numbers do not depend on the batch it runs in). Required by filters that
                draw random numbers (particle filters, flow filters).
            n_particles: override the filter's particle count (particle filters).
            return_covariances: also return per-step covariances (Gaussian filters).
            return_particles: also return per-step particles and log-weights (large).
            return_std: also return each step's standard deviation per coordinate ``(B, T, d)``
                (:func:`belief_std`).
            progress: optional callable invoked after each step (e.g. a progress bar update).
            checkpoint_steps: when gradients are recorded, keep only each time step's inputs and
                recompute the step in the backward pass (``torch.utils.checkpoint``, with the
                generator's state restored so that the step redraws the same numbers): the
                backward pass then holds one step's intermediates (a per-particle flow's
                pseudo-time matrices) instead of all T steps', for about one extra forward pass.
                Values and gradients are unchanged. ``None``: :attr:`checkpoint_steps` (False).

        A gradient is recorded only where one can flow: with grad mode on but no parameter, buffer
        or tensor attribute of the filter or its model (:meth:`gradient_source`), and none of
        ``observations``, ``mean`` and ``cov``, requiring grad, the call runs as under
        :func:`torch.no_grad` and the fused kernels serve it. Where one does and the filter has a
        kernel, the first such call warns that the reference PyTorch path runs, naming the tensor.
        (A tensor that requires grad hidden in a closure is not seen: register it as a parameter or
        buffer.)
        """
        source = self.gradient_source(observations, mean, cov) if torch.is_grad_enabled() else None
        if source is None and torch.is_grad_enabled():  # nothing to differentiate: the kernels' path
            with torch.no_grad():
                return self._forward(
                    observations, mean, cov, generator, n_particles, return_covariances, return_particles,
                    progress, checkpoint_steps, return_std,
                )  # fmt: skip
        if source is not None and not self._said_gradient_path and _select.has_kernel(self):
            self._said_gradient_path = True
            warnings.warn(
                f"{self.name}: a gradient is recorded ({source} requires grad), so the reference PyTorch path runs "
                "instead of the fused kernels, which record none; under torch.no_grad(), or with nothing requiring "
                "grad, the kernels run (said once per filter)",
                UserWarning,
                stacklevel=2,
            )
        return self._forward(
            observations, mean, cov, generator, n_particles, return_covariances, return_particles, progress,
            checkpoint_steps, return_std,
        )  # fmt: skip

    #: the first gradient-recording call's warning has been given (:meth:`forward`)
    _said_gradient_path = False

    def gradient_source(self, *inputs) -> Optional[str]:
        """The name of the first tensor a call would differentiate (``"observations"``, ``"mean"``,
        ``"cov"`` for ``inputs`` in that order, or a parameter, buffer or tensor attribute of this
        filter and its submodules, its model among them, by its dotted name), or ``None``: nothing
        requires grad. No device is read."""
        for name, value in zip(("observations", "mean", "cov"), inputs):
            if _requires_grad(value):
                return name
        for prefix, module in self.named_modules():
            for name, value in itertools.chain(
                module.named_parameters(recurse=False), module.named_buffers(recurse=False), vars(module).items()
            ):
                if _requires_grad(value):
                    return f"{prefix}.{name}" if prefix else name
        return None

    def _forward(
        self, observations, mean, cov, generator, n_particles, return_covariances, return_particles, progress,
        checkpoint_steps, return_std,
    ) -> FilterResult:  # fmt: skip
        """:meth:`forward`'s work, in the grad mode it chose."""
        check_dtype(self.model, self.name)
        if progress is not None and not callable(progress):
            raise ArgumentTypeError(
                f"progress: expected a callable invoked after each step (or None), got {type(progress).__name__}"
            )
        if n_particles is not None:  # a count even where the filter has no particles (it is then unused)
            check_count("n_particles", n_particles)
        if self.validate:
            self.model.check_observations(observations)
            self.check_model()
        gaps = self.check_missing(observations)
        mean, cov = self.check_prior(mean, cov, observations.shape[0])
        check_trial_count(self.model, observations.shape[0], self.name)  # per-trial values: one per trial
        if self.validate:  # once per model and batch layout: each method's output shape, naming the method
            check_shapes(self.model, mean.detach(), self.name, gaussian=self.gaussian_form or None)
            # a flow whose model's measurement Jacobian is zero cannot move the particles: said once
            check_informative(getattr(self, "proposal", None), mean, self.name, cov)
        if self.uses_randomness:
            check_generator(generator, f"{self.name}: generator", observations.shape[0])
        try:
            state = self.init(mean, cov, n_particles, generator)
        except Exception as err:
            self._raise_out_of_memory(_uncountable(err), observations.shape[0], n_particles)
            raise
        trace = _Trace(
            observations.shape[0],
            observations.device,
            return_covariances,
            return_particles,
            return_std,
            steps=observations.shape[1],
        )
        if checkpoint_steps is None:
            checkpoint_steps = self.checkpoint_steps
        step = self._checkpointed_step if checkpoint_steps and torch.is_grad_enabled() else self.step
        if step == self.step and not gaps and graph_step.eligible(self, state, generator):  # one launch per step (CUDA)
            step = functools.partial(graph_step.run_step, self, memo={})
        with (
            _missing.observations_missing(gaps),
            _paths.recording() as used,
        ):  # NaN: not observed (torchflow.core.missing)
            step = _paths.per_step(step, used)  # each step's kernel / graph / torch path, counted on the host
            state = self._run_steps(state, step, observations, generator, trace, n_particles, progress)
        self._check_trace(trace, warn=True)  # the one host read of the check
        try:  # the per-step outputs stacked: with return_particles, (B, T, N, d) more
            result = trace.result(state)
            result.paths = used
            return result
        except Exception as err:
            self._raise_out_of_memory(_uncountable(err), observations.shape[0], n_particles)
            raise

    def check_missing(self, observations: torch.Tensor) -> bool:
        """Whether ``observations (B, T, m)`` hold NaN (values not observed, :mod:`torchflow.core.missing`):
        one host read per call, before the first step. Raises when a step is partly observed and
        this filter weighs particles with a model whose measurement density cannot leave out single
        coordinates (:func:`torchflow.models.base.partial_observations`)."""
        nan = torch.isnan(observations) if observations.is_floating_point() else None
        if nan is None or not bool(nan.any()):
            return False
        if self.uses_particles and not partial_observations(self.model):
            partial = nan.any(-1) & ~nan.all(-1)  # (B, T)
            if bool(partial.any()):
                b, t = (int(i) for i in torch.nonzero(partial)[0])
                raise ArgumentError(
                    f"{self.name}: observations: step {t + 1} of trial {b} is partly observed (NaN in some of its "
                    f"{observations.shape[-1]} coordinates), but {type(self.model).__name__} gives no density of "
                    "the observed coordinates alone: a whole step may be missing (all NaN), or the model overrides "
                    "measurement_log_prob_observed(z, x, observed) (or declares a Gaussian measurement)"
                )
        return True

    def _run_steps(self, state, step, observations, generator, trace, n_particles, progress):
        """The loop of :meth:`forward` over the time steps."""
        grad_check = self.check_gradients and torch.is_grad_enabled()
        if grad_check:  # a parameter's non-finite gradient is named (hooks of the last call removed)
            guards.replace_parameter_hooks(self, self.model)
        for t in range(observations.shape[1]):
            if grad_check:  # the gradient reaching step t + 1 is checked in the backward pass
                state = guards.guard_state(state, self.name, t + 1)
            try:
                state = step(state, observations[:, t], generator)
            except Exception as err:
                self._check_trace(trace, warn=False)  # an earlier non-finite value is the cause
                self._raise_out_of_memory(_uncountable(err), observations.shape[0], n_particles)
                raise
            trace.add(state, t)
            if progress is not None:
                progress()
        return state


#: the key of :attr:`ParticleState.extras` under which a particle filter keeps each step's ancestor
#: indices (:func:`ancestor_extras`; the particle smoothers, :mod:`torchflow.smoothing`)
ANCESTOR = "ancestor"


def ancestor_extras(state, particles: torch.Tensor) -> Optional[Dict[str, torch.Tensor]]:
    """``{ANCESTOR: arange(N)}`` per trial when ``state`` asks for ancestors (its ``extras`` hold
    the key), else ``None``: gathered by the resampler, it becomes the ancestor index ``(B, N)`` of
    each particle after resampling (the step's weighted particles ``particles (B, N, d)``)."""
    if ANCESTOR not in state.extras:
        return None
    B, N = particles.shape[:2]
    return {ANCESTOR: torch.arange(N, device=particles.device).expand(B, N)}


def _uncountable(err: BaseException) -> BaseException:
    """A size past what torch can count (``n_particles=2**62``) as the ``MemoryError`` it is on any
    machine (caused by ``err``); any other error unchanged."""
    text = str(err)
    if "Storage size calculation overflowed" not in text and "Overflow when unpacking long" not in text:
        return err
    out = MemoryError(text.splitlines()[0])
    out.__cause__ = err
    return out


#: from this many particle numbers per step (B x N x d) on, :class:`_Trace` copies a CPU particle
#: filter's per-step estimate, ESS and evidence increment into buffers made once for all T steps
#: instead of keeping each step's small tensors. Kept, those small blocks are carved by the C
#: allocator out of the large blocks the step freed, which then no longer fit the next step's large
#: tensors: the heap grew by ~10 MB a step at B = 100, N = 10^4 (6.5 GB resident after 750 steps,
#: the step twice as slow from page faults; ``python -m experiments.benchmarks.bench_sv``).
TRACE_BUFFER_MIN = 1 << 15


class _Trace:
    """What :meth:`Filter.forward` keeps of each step: the per-step outputs, and the first
    non-finite step per trial, recorded on the device (reported once, after the last step: no host
    synchronisation per time step). ``steps``: the number of time steps, when known: a large
    particle filter's small per-step outputs then go into buffers (:data:`TRACE_BUFFER_MIN`)."""

    def __init__(
        self, B: int, device, covariances: bool, particles: bool, std: bool = False, steps: Optional[int] = None
    ):
        self.B, self.device, self.steps = B, device, steps
        self.covariances, self.particles, self.std = covariances, particles, std
        self.est, self.inc, self.ess, self.covs, self.parts, self.lws, self.geff = [], [], [], [], [], [], []
        self.stds = []
        self.invalid = []  # per step: (B,) bool or None
        self.n = 0  # steps added
        self.first_collapse = None  # (B,) long: the first step whose cloud had collapsed (0: none), on the device
        self.collapse_count = None  # (B,) long: how many steps
        self._buf: Optional[Dict[str, torch.Tensor]] = None  # (B, T, ...) buffers, when buffering
        self._invalid_seen = False
        self._stacked = None  # (number of steps, stacked estimates (B, T, d))

    def _buffering(self, state) -> bool:
        """Buffers for a particle filter's CPU state of at least :data:`TRACE_BUFFER_MIN` numbers
        whose outputs record no gradient (a graph keeps its own references: nothing to gain). Not on
        a GPU: its caching allocator does not fragment so, and each copy would be a launch."""
        x = getattr(state, "particles", None)
        return (
            self.steps is not None
            and isinstance(state, ParticleState)
            and x is not None
            and x.is_cpu
            and x.numel() >= TRACE_BUFFER_MIN
            and getattr(state, "g_eff", None) is None
            and not any(
                t is not None and t.requires_grad for t in (state.estimate, state.log_evidence_increment, state.ess)
            )
        )

    def _put(self, name: str, value: torch.Tensor, zeros: bool = False) -> None:
        buf = self._buf.get(name)
        if buf is None:
            shape = (value.shape[0], self.steps) + tuple(value.shape[1:])
            make = torch.zeros if zeros else torch.empty
            buf = self._buf[name] = make(shape, dtype=value.dtype, device=value.device)
        buf.select(1, self.n).copy_(value)

    def add(self, state, t: int) -> None:
        if self.n == 0 and self._buffering(state):
            self._buf = {}
        if self._buf is not None:
            self._put("est", state.estimate)
            self._put("inc", state.log_evidence_increment)
            self._put("ess", state.ess)
            invalid = getattr(state, "invalid", None)
            if invalid is not None:
                self._put("invalid", invalid, zeros=True)
                self._invalid_seen = True
        else:
            self.est.append(state.estimate)
            self.invalid.append(getattr(state, "invalid", None))
            self.inc.append(state.log_evidence_increment)
            if state.ess is not None:
                self.ess.append(state.ess)
            if getattr(state, "g_eff", None) is not None:
                self.geff.append(state.g_eff)
        if self.covariances and isinstance(state, GaussianState):
            self.covs.append(state.cov)
        if self.particles and isinstance(state, ParticleState):
            self.parts.append(state.particles)
            self.lws.append(state.log_weights)
        if self.std:
            self.stds.append(belief_std(state))
        x = getattr(state, "particles", None) if isinstance(state, ParticleState) else None
        if x is not None and x.dim() == 3 and x.shape[1] >= 2:  # collapse: flagged on the device, read once
            now = guards.collapsed(x)
            if self.first_collapse is None:
                self.first_collapse = torch.zeros(now.shape, dtype=torch.long, device=now.device)
                self.collapse_count = torch.zeros_like(self.first_collapse)
                self._collapsed_before = torch.zeros_like(now)
            # collapsed two steps running (the forecast did not spread the copies again: no model
            # noise) while the ESS says 2 or more: a degenerate weight (ESS near 1) shows itself
            ess = getattr(state, "ess", None)
            bad = now & self._collapsed_before
            if ess is not None:
                bad = bad & (ess.detach() >= 2.0)
            self._collapsed_before = now
            self.first_collapse = torch.where((self.first_collapse == 0) & bad, self.n, self.first_collapse)
            self.collapse_count = self.collapse_count + bad.long()
        self.n += 1

    def _view(self, name: str) -> Optional[torch.Tensor]:
        buf = self._buf.get(name)
        return None if buf is None else buf[:, : self.n]

    def estimates(self) -> Optional[torch.Tensor]:
        """The estimates so far, ``(B, T, d)`` (stacked once per length)."""
        if not self.n:
            return None
        if self._buf is not None:
            return self._view("est")
        if self._stacked is None or self._stacked[0] != len(self.est):
            self._stacked = (len(self.est), torch.stack(self.est, 1))
        return self._stacked[1]

    def invalid_steps(self) -> Optional[torch.Tensor]:
        """``(B, T)`` steps flagged invalid (``nonfinite="raise"``), ``None`` if no step flags."""
        if self._buf is not None:
            return self._view("invalid") if self._invalid_seen else None
        flagged = [i for i in self.invalid if i is not None]
        if not flagged:
            return None
        return torch.stack([torch.zeros_like(flagged[0]) if i is None else i for i in self.invalid], 1)

    def increments(self) -> torch.Tensor:
        """``(B, T)`` log-evidence increments so far."""
        return self._view("inc") if self._buf is not None else torch.stack(self.inc, 1)

    def result(self, state) -> FilterResult:
        def stack(xs):
            return torch.stack(xs, 1) if xs else None

        inc_t = self.increments()
        ess = self._view("ess") if self._buf is not None else stack(self.ess)
        return FilterResult(
            estimates=self.estimates(),
            log_evidence=inc_t.sum(1),
            log_evidence_increments=inc_t,
            ess=ess,
            covariances=stack(self.covs),
            particles=stack(self.parts),
            log_weights=stack(self.lws),
            n_repaired=getattr(state, "n_repaired", None),
            g_eff=stack(self.geff),
            std=stack(self.stds),
        )


NONFINITE = ("recover", "raise")
PROPOSAL_GRADIENTS = ("pathwise", "score")


#: the methods of :class:`ParticleFilter` that a fast path stands in for (:attr:`ParticleFilter.kept`)
_KEPT = ("init", "step", "_estimate_and_resample", "account_clean", "account")
_KEPT_FOR_WEIGHTS = frozenset(("_estimate_and_resample", "account_clean", "account"))


class ParticleFilter(Filter):
    """The particle filter: one step for every proposal.

    ``propose`` (the :class:`~torchflow.proposals.Proposal`, fed tensors) -> weigh
    ``log w_k = log w_{k-1} + log p(x_k | x_{k-1}) + log p(z_k | x_k) - log q(x_k | x_{k-1}, z_k)``
    (a proposal that draws from the transition, ``log_q = None``, leaves the likelihood alone) ->
    estimate (weighted mean) -> resample (:class:`~torchflow.core.resampling.Resampler`). The named
    filters (:class:`~torchflow.filters.BootstrapParticleFilter`, PF-PF, GPFIS, ...) are this class
    with their proposal.

    Args:
        model: the state-space model.
        proposal: a :class:`~torchflow.proposals.Proposal` of ``model``, or a callable
            ``model -> Proposal`` (a Hydra ``_partial_`` config); ``None``: the bootstrap proposal.
        n_particles: particles per trial N (the filter owns the count; ``forward(n_particles=...)``
            overrides it for one call).
        resampling: ``multinomial``, ``systematic``, ``stratified`` or ``residual``.
        ess_threshold: resample a trial when ESS < ess_threshold * N (0 never, 1 nearly always).
        regularization: ``None`` (off), a float variance, or a list of d per-coordinate variances
            of Gaussian jitter added to the particles of resampled trials (absolute).
        regularization_relative: ``None`` (off) or ``h >= 0``: jitter of ``h`` times each
            coordinate's weighted spread before resampling (relative to the cloud, as DAPPER's
            ``reg``); see :class:`~torchflow.core.resampling.Resampler`.
        resampling_gradient: how gradients pass through resampling (``"none"``, ``"stop_gradient"``,
            ``"soft"`` or ``"ot"``; see :class:`~torchflow.core.resampling.Resampler`).
        soft_alpha: the mixture weight of ``resampling_gradient="soft"``, in (0, 1].
        ot_epsilon, ot_iterations: regularisation (relative to the cloud's spread) and Sinkhorn
            iterations of ``resampling_gradient="ot"``.
        proposal_gradient: how the gradient treats the proposal. ``"pathwise"`` (default):
            through the particles' positions, the proposal density and the carried covariance
            (reparameterised draws, flows' maps and ``log|det|``). ``"score"``: the proposal is
            held constant (its particles, density and carry detached) and the gradient comes from
            the weight's model densities alone: by the Fisher identity, ``E_q[grad(p_theta / q)]
            = grad Z`` for any proposal that does not move with theta, so with
            ``resampling_gradient="stop_gradient"`` the estimate of ``grad Z`` stays unbiased
            while avoiding derivatives of particle paths, which are heavy-tailed where the
            measurement is steep (the acoustic model near a sensor). The forward pass is the same
            bit for bit.
        nonfinite: ``"recover"`` (default, every particle filter): a particle with a NaN/inf
            position or log-weight gets weight zero (and a finite fallback position: its pre-flow
            draw); a trial left with no valid particle keeps its previous weights and the fallback
            particles; each step with a repair is counted per trial in ``n_repaired`` (the runner's
            ``repaired`` column). ``"raise"``: :class:`~torchflow.core.checks.NonFiniteError` names the
            filter, step and trials. Recover is the default because a flow's far-tail particle can
            overflow its ``log|det|`` in an otherwise healthy trial, and weight zero is the limit of
            its weight; the count keeps every repair visible.
        weights: ``"standard"`` (default): each particle weighed against its own parent,
            ``p(x | x_prev) / q(x | x_prev)``. ``"marginal"``: against the predictive mixture over the
            previous cloud, ``sum_j W_j p(x | x_j) / ((1/N) sum_j q(x | x_j))`` (the marginal particle
            filter; :mod:`torchflow.filters.marginal`): O(N^2) per step in memory-bounded blocks; a
            flow's moves are no longer charged against its own parent's transition density, and with
            ``proposal_gradient="score"`` the gradient is the O(N^2) score estimator that does not
            degenerate along the genealogy. The evidence stays unbiased. For the bootstrap proposal
            and the weighted flow proposals (on a Gaussian transition).
        particle_chunk: evaluate per-particle work (likelihoods; local flows) in blocks of at most
            this many particles to bound memory (``None``: all at once, or the proposal's own
            blocks). The runner sets it from ``memory_budget_gb`` (:meth:`plan_memory`).
    """

    uses_particles = True
    uses_randomness = True

    gaussian_form = False  # the proposal states what it needs of the model

    #: which of this class's methods the class keeps as they are (:data:`_KEPT`): a subclass's set is
    #: declared once, when the subclass is made (:meth:`__init_subclass__`). The fast paths that stand
    #: in for these methods (the CUDA-graph step, the diagonal prior, the weighting kernel) run only
    #: where the code they replace is the code the filter has.
    kept: frozenset = frozenset()

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        cls.kept = frozenset(name for name in _KEPT if getattr(cls, name) is getattr(ParticleFilter, name))

    def __init__(
        self,
        model,
        proposal=None,
        *,
        n_particles: int = 500,
        resampling: str = "systematic",
        ess_threshold: float = 0.5,
        regularization=None,
        resampling_gradient: str = "stop_gradient",
        soft_alpha: float = 0.5,
        ot_epsilon: float = 0.1,
        ot_iterations: int = 100,
        nonfinite: str = "recover",
        particle_chunk: Optional[int] = None,
        proposal_gradient: str = "pathwise",
        weights: str = "standard",
        regularization_relative: Optional[float] = None,
        validate: bool = True,
        name: Optional[str] = None,
    ):
        super().__init__(model, validate=validate, name=name)
        if proposal is None:
            proposal = BootstrapProposal(model)
        elif not isinstance(proposal, nn.Module) and callable(proposal):
            proposal = proposal(model)
        if not isinstance(proposal, Proposal):
            raise ArgumentTypeError(
                f"proposal: expected a torchflow Proposal (or a callable model -> Proposal), "
                f"got {type(proposal).__name__}"
            )
        if proposal.model is not model:
            raise ArgumentError("proposal: built for another model than the filter's (pass the same model to both)")
        #: how particles are drawn and with what density (:mod:`torchflow.proposals`)
        self.proposal = proposal
        self.particle_chunk = (
            None if particle_chunk is None else check_count("particle_chunk", particle_chunk, hint=" or None")
        )
        if nonfinite not in NONFINITE:
            raise ArgumentError(f"nonfinite: expected one of {NONFINITE}, got {nonfinite!r}")
        self.nonfinite = nonfinite
        if proposal_gradient not in PROPOSAL_GRADIENTS:
            raise ArgumentError(f"proposal_gradient: expected one of {PROPOSAL_GRADIENTS}, got {proposal_gradient!r}")
        self.proposal_gradient = proposal_gradient
        check_choice("weights", weights, _marginal.WEIGHTS)
        if weights == "marginal" and not proposal.has_ancestor_law:
            raise ArgumentError(
                f"weights: 'marginal' needs the proposal's density given every parent, which "
                f"{type(proposal).__name__} does not give (on this model); it is available for the "
                "bootstrap proposal and the weighted flow proposals on models with a Gaussian "
                "transition. Use weights='standard'"
            )
        #: ``"standard"`` or ``"marginal"`` weights (:mod:`torchflow.filters.marginal`)
        self.weights = weights
        proposal.report_ancestor_law = weights == "marginal"
        self.n_particles = int(check_count("n_particles", n_particles))
        #: the resampling part: scheme, ESS trigger, regularisation, gradient estimator
        self.resampler = _resampling.Resampler(
            model.state_dim,
            scheme=resampling,
            ess_threshold=ess_threshold,
            regularization=regularization,
            gradient=resampling_gradient,
            soft_alpha=soft_alpha,
            ot_epsilon=ot_epsilon,
            ot_iterations=ot_iterations,
            dtype=model.dtype,
            regularization_relative=regularization_relative,
        )

    @property
    def graph_step(self) -> bool:
        """Whether the whole step may be replayed from a CUDA graph (:mod:`torchflow.filters.graph_step`):
        the generic step (not overridden), a proposal class and a model class that each declare
        themselves ``graph_safe`` (on the class itself: a subclass may draw otherwise), and the
        proposal's linearisation points, where it has them."""
        return (
            "step" in self.kept
            and self.weights == "standard"
            and bool(vars(type(self.proposal)).get("graph_safe"))
            and (
                getattr(self.proposal, "points", None) is None
                or bool(vars(type(self.proposal.points)).get("graph_safe"))
            )
            and kernel_structure(self.model).graph_safe
        )

    @property
    def diagonal_prior(self) -> bool:
        """Whether :meth:`init` takes a :class:`~torchflow.core.covariances.DiagonalCovariance` as it is:
        when the proposal's class declares it (its :meth:`~torchflow.proposals.Proposal.init_carry`
        does not read the prior covariance: the bootstrap proposal), and the filter's :meth:`init`
        is this class's (a subclass with its own, the Gaussian-sum filters, is given the matrix)."""
        return "init" in self.kept and bool(vars(type(self.proposal)).get("diagonal_prior"))

    resampling_scheme = property(lambda self: self.resampler.scheme)
    ess_threshold = property(lambda self: self.resampler.ess_threshold)
    regularization_std = property(lambda self: self.resampler.regularization_std)

    @property
    def stream_name(self) -> str:
        """The filter family's declared stream name, else the proposal's, else the class name."""
        return self.random_stream or getattr(self.proposal, "random_stream", None) or type(self).__name__

    def bytes_per_trial(self, n_particles=None):
        N = self._resolve_n(n_particles)
        ot = 4 * 8 * N * N if self.resampler.gradient == "ot" else 0  # the Sinkhorn cost and plan
        return self.proposal.bytes_per_trial(N) + ot

    def preferred_chunk_trials(self, n_particles=None):
        return self.proposal.preferred_chunk_trials(self._resolve_n(n_particles))

    def plan_memory(self, budget_bytes: float, n_particles: Optional[int] = None) -> Optional[int]:
        """Set :attr:`particle_chunk` so that one trial's per-particle work fits ``budget_bytes``
        (``None`` when a whole trial fits); returns it. Used by the experiment runner."""
        N = self._resolve_n(n_particles)
        per_trial = self.bytes_per_trial(N)
        self.particle_chunk = None if per_trial <= budget_bytes else max(1, int(N * budget_bytes // per_trial))
        return self.particle_chunk

    def _resolve_n(self, n_particles):
        return self.n_particles if n_particles is None else check_count("n_particles", n_particles)

    def check_model(self) -> None:
        """A proposal weighed by the transition density ``p(x_k | x_{k-1})`` (every proposal but
        the bootstrap's and the unweighted flows') needs a positive definite transition covariance:
        with a singular one that density does not exist and every weight would be invalid. Checked
        on the model's constant covariance (``transition_cov()``); a state-dependent one is left to
        the steps' non-finite handling."""
        super().check_model()
        self.require_definite(
            "measurement",
            "particle filters weigh particles by the measurement density p(z | x), which a singular covariance "
            "does not have, so no weight would carry the measurement. Give the model a positive definite "
            "measurement noise, or use a Kalman filter (which handles a singular R when H P H^T is positive definite)",
        )
        marginal = self.weights == "marginal"
        if (
            getattr(self.proposal, "uses_transition_density", True) or marginal
        ) and self.model.structure.gaussian_transition:
            self.require_definite(
                "transition",
                (
                    "weights='marginal' weighs every particle by the transition density from every parent"
                    if marginal
                    else "this filter weighs particles by the transition density p(x_k | x_(k-1))"
                )
                + ", which a singular covariance does not have. Give the model a positive definite transition "
                "noise, or use a filter that does not need the density: the bootstrap PF (standard weights), the "
                "unweighted flow filter or a Kalman filter",
            )

    def init(self, mean, cov, n_particles=None, generator=None) -> "ParticleState":
        """N particles per trial from the prior ``N(mean (B, d), cov (B, d, d))``, uniform weights and
        what the proposal carries (:meth:`~torchflow.proposals.Proposal.init_carry`)."""
        N = self._resolve_n(n_particles)
        B = mean.shape[0]
        particles = sample_prior(mean, cov, N, generator)  # (B, N, d)
        lw = torch.full((B, N), -math.log(N), dtype=mean.dtype, device=mean.device)
        zero = torch.zeros(B, dtype=mean.dtype, device=mean.device)
        return ParticleState(
            particles,
            lw,
            mean,
            torch.full_like(zero, float(N)),
            zero,
            torch.zeros(B, dtype=torch.bool, device=mean.device),
            n_repaired=torch.zeros(B, dtype=torch.long, device=mean.device),
            cov=self.proposal.init_carry(cov, N),
        )

    def step(self, state: "ParticleState", z: torch.Tensor, generator: Optional[torch.Generator] = None):
        """One step: propose, weigh, estimate, resample (class docstring). Per-particle evaluations
        run in blocks of :attr:`particle_chunk`."""
        score = self.proposal_gradient == "score"
        # the proposal held constant: built without a graph (no tensors kept for a backward pass that
        # would not use them), its outputs detached; only the weight's model densities carry gradients
        with torch.no_grad() if score else contextlib.nullcontext():
            prop = self.proposal.propose(
                state.particles, state.log_weights, state.estimate, z, state.cov, generator, chunk=self.particle_chunk
            )
        model = self.model
        z1 = z.unsqueeze(1)
        if self.weights == "marginal":
            log_lik = self.per_particle(lambda x: _missing.measurement_log_prob(model, z1, x), prop.particles)
            log_inc = _marginal.marginal_log_increment(
                model, prop, state.particles, state.log_weights, log_lik, hold_proposal=score, chunk=self.particle_chunk
            )
            uniform = torch.full_like(state.log_weights, -math.log(state.log_weights.shape[-1]))
            return self.weight_and_resample(
                prop.particles,
                uniform,
                log_inc,
                generator,
                state.step + 1,
                cov=prop.cov,
                fallback=prop.fallback,
                n_repaired=state.n_repaired,
                extras=ancestor_extras(state, prop.particles),
            )

        def measurement_log_prob(z, x):  # of the observed coordinates where z has NaN (torchflow.core.missing)
            return _missing.measurement_log_prob(model, z, x)

        if prop.log_q is None:

            def weigh(x, x_prev):
                ll = measurement_log_prob(z1, x)
                if not score:
                    return ll
                # a transition proposal's score: log p(x | x') - stop_gradient(same), exactly 0 in value
                lt = model.transition_log_prob(x, x_prev)
                return ll + torch.where(torch.isfinite(lt), lt - lt.detach(), torch.zeros_like(lt))

            log_inc = self.per_particle(weigh, prop.particles, state.particles)
        else:

            def weigh(x, x_prev, log_q):
                return model.transition_log_prob(x, x_prev) + measurement_log_prob(z1, x) - log_q

            log_inc = self.per_particle(weigh, prop.particles, state.particles, prop.log_q)
        return self.weight_and_resample(
            prop.particles,
            state.log_weights,
            log_inc,
            generator,
            state.step + 1,
            cov=prop.cov,
            fallback=prop.fallback,
            n_repaired=state.n_repaired,
            extras=ancestor_extras(state, prop.particles),
        )

    def per_particle(self, fn, *tensors, pass_slice: bool = False, chunk: Optional[int] = None):
        """``fn(*tensors)`` in blocks of :attr:`particle_chunk` particles (or ``chunk``, when given;
        :func:`torchflow.core.blocks.blockwise`)."""
        return blockwise(fn, *tensors, chunk=self.particle_chunk if chunk is None else chunk, pass_slice=pass_slice)

    def repair(self, particles: torch.Tensor, log_increment: torch.Tensor, fallback: Optional[torch.Tensor]):
        """The non-finite path of every particle filter: particles ``(B, ..., d)`` with a non-finite
        coordinate or a NaN/+inf ``log_increment (B, ...)`` get log-weight ``-inf`` and the
        ``fallback`` position (zeros when ``None``). Returns ``(particles, log_increment,
        bad_trial (B,))``. No host synchronisation."""
        bad = self._nonfinite(particles, log_increment)
        fb = torch.zeros_like(particles) if fallback is None else fallback
        return (
            torch.where(bad.unsqueeze(-1), fb, particles),
            log_increment.masked_fill(bad, float("-inf")),
            bad.flatten(1).any(-1),
        )

    @staticmethod
    def _nonfinite(particles: torch.Tensor, log_increment: torch.Tensor) -> torch.Tensor:
        """``(B, ...)`` bool: particles with a non-finite coordinate or a NaN/+inf log-increment."""
        # a particle with a non-finite coordinate has a non-finite coordinate sum s (inf - inf = nan):
        # one reduction instead of an elementwise isfinite over (B, N, d). s - s is 0 where s is
        # finite and NaN elsewhere, so the sum below is < inf exactly where the log-increment is
        # neither NaN nor +inf and the particle is finite (five ops)
        s = particles.sum(-1)
        return ~((log_increment + (s - s)) < float("inf"))

    def account(self, bad_trial: torch.Tensor, dead: torch.Tensor, n_repaired: torch.Tensor):
        """``(n_repaired, invalid)`` after a step whose trials had repaired particles (``bad_trial``)
        or no particle of positive weight (``dead``): counted (recover), or flagged for
        :meth:`Filter.forward` to raise (raise)."""
        if self.nonfinite == "recover":
            return n_repaired + (bad_trial | dead).long(), None
        return n_repaired, bad_trial | dead

    def weight_and_resample(
        self,
        particles: torch.Tensor,
        prev_log_weights: torch.Tensor,
        log_increment: torch.Tensor,
        generator: Optional[torch.Generator],
        step: int,
        *,
        cov: Optional[Covariance] = None,
        extras: Optional[Dict[str, torch.Tensor]] = None,
        fallback: Optional[torch.Tensor] = None,
        n_repaired: Optional[torch.Tensor] = None,
    ) -> ParticleState:
        """Update normalised ``prev_log_weights (B, N)`` by ``log_increment (B, N)``, estimate,
        then resample the low-ESS trials (particles, per-particle ``cov`` and ``extras`` follow).

        The step's evidence increment is ``logsumexp(prev_log_weights + log_increment)`` — the
        standard unbiased estimator of p(z_k | z_{1:k-1}) when the previous weights are normalised.

        Args:
            fallback: ``(B, N, d)`` finite positions used for repaired particles (e.g. the
                pre-flow prior samples); defaults to zeros.
            n_repaired: ``(B,)`` running repair count to extend.
        """
        if n_repaired is None:
            n_repaired = torch.zeros(particles.shape[0], dtype=torch.long, device=particles.device)
        if _resampling.reads_host(log_increment):  # the CPU: one read says whether anything needs repair
            if self._weights_kernel(particles, prev_log_weights, log_increment, cov, extras):
                return self._weigh_in_kernel(
                    particles, prev_log_weights, log_increment, generator, step, fallback, n_repaired
                )
            # s - s is 0 where a particle's coordinate sum s is finite, NaN elsewhere: lw is the sum of
            # the weights where every particle is finite, and a trial's logsumexp is finite exactly
            # where no particle needs repair (a non-finite coordinate, a NaN or +inf increment) and
            # some weight is positive
            s = particles[..., 0] if particles.shape[-1] == 1 else particles.sum(-1)
            lw = prev_log_weights + log_increment + (s - s)
            inc = torch.logsumexp(lw, dim=-1)
            # finite sum <=> every term finite (a NaN or an infinity makes it NaN or infinite)
            if math.isfinite(float(inc.detach().sum())):  # nothing to repair, no dead trial
                return self._estimate_and_resample(
                    particles,
                    lw - inc.unsqueeze(-1),
                    inc,
                    generator,
                    step,
                    cov,
                    extras,
                    n_repaired,
                    self.account_clean(n_repaired),
                    None,
                )
        return self._weigh_masked(
            particles, prev_log_weights, log_increment, generator, step, cov, extras, fallback, n_repaired
        )

    def _weights_kernel(self, particles, prev_log_weights, log_increment, cov, extras) -> bool:
        """The CPU weighting kernel takes this step (:func:`torchflow.flows.select.weights_kernel`),
        where this class weighs, estimates and resamples as :class:`ParticleFilter` does."""
        return (
            _KEPT_FOR_WEIGHTS <= self.kept
            and _select.weights_kernel(
                particles, prev_log_weights, log_increment, resampler=self.resampler, cov=cov, extras=extras
            )
            is not None
        )

    def _weigh_in_kernel(self, particles, prev_log_weights, log_increment, generator, step, fallback, n_repaired):
        """:meth:`weight_and_resample` by the CPU weighting kernel (``tuning.fused_weights``). The
        resampler's uniforms are drawn first, where the reference draws them; the trials the kernel
        flags (a particle to repair, no weight left) take :meth:`_weigh_masked` on their own rows with
        their rows of those uniforms, so every trial's numbers are those it gets in any batch."""
        uniforms = self.resampler.draw_uniforms(prev_log_weights, generator)
        x, lw, estimate, ess, inc, resampled, bad = _select.weigh_resample(
            particles, prev_log_weights, log_increment, uniforms, self.resampler.ess_threshold
        )
        _paths.note("kernel:weights")
        invalid = self.account_clean(n_repaired)
        if bad is not None:  # (the kernel's count, read on the host already)
            rows = bad.nonzero().squeeze(1)
            sub = self._weigh_masked(
                particles[rows],
                prev_log_weights[rows],
                log_increment[rows],
                generator,
                step,
                None,
                None,
                None if fallback is None else fallback[rows],
                n_repaired[rows],
                None if uniforms is None else uniforms[rows],
            )
            for out, part in (
                (x, sub.particles),
                (lw, sub.log_weights),
                (estimate, sub.estimate),
                (ess, sub.ess),
                (inc, sub.log_evidence_increment),
                (resampled, sub.resampled),
            ):
                out[rows] = part
            n_repaired = n_repaired.index_copy(0, rows, sub.n_repaired)
            if invalid is not None:
                invalid = invalid.index_copy(0, rows, sub.invalid)
        return ParticleState(
            particles=x,
            log_weights=lw,
            estimate=estimate,
            ess=ess,
            log_evidence_increment=inc,
            resampled=resampled,
            n_repaired=n_repaired,
            cov=None,
            step=step,
            extras={},
            invalid=invalid,
        )

    def _weigh_masked(
        self,
        particles,
        prev_log_weights,
        log_increment,
        generator,
        step,
        cov,
        extras,
        fallback,
        n_repaired,
        uniforms=None,
    ) -> "ParticleState":
        """:meth:`weight_and_resample` with the repair of non-finite particles and dead trials, as
        masked updates over every trial (``uniforms``: the resampler's draws when made already)."""
        bad = self._nonfinite(particles, log_increment)
        # No host synchronisation from here: every branch below is a masked update over all trials;
        # with nonfinite="raise" the offending trials are flagged in ``state.invalid`` and
        # :meth:`Filter.forward` raises after the last step
        log_increment = log_increment.masked_fill(bad, float("-inf"))
        lw = prev_log_weights + log_increment
        inc = torch.logsumexp(lw, dim=-1)
        dead = ~torch.isfinite(inc)  # no particle with positive weight (all -inf)
        n_repaired, invalid = self.account(bad.flatten(1).any(-1), dead, n_repaired)
        lw = torch.where(dead.unsqueeze(-1), prev_log_weights, lw)
        # repaired particles, and every particle of a dead trial, take the fallback position: one
        # pass over (B, N, d) (:meth:`repair`'s values)
        particles = (
            particles.masked_fill(bad.unsqueeze(-1), 0.0)
            if fallback is None
            else torch.where((bad | dead.unsqueeze(-1)).unsqueeze(-1), fallback, particles)
        )
        # rows that were not dead see the same lw, hence the same logsumexp as ``inc``; a dead row
        # keeps the previous weights, which are normalised
        lw = lw - torch.where(dead, 0.0, inc).unsqueeze(-1)
        inc = inc.masked_fill(dead, float("-inf"))  # the evidence estimate of a dead step is zero
        return self._estimate_and_resample(
            particles, lw, inc, generator, step, cov, extras, n_repaired, invalid, dead, uniforms
        )

    def account_clean(self, n_repaired: torch.Tensor):
        """:meth:`account` of a step with nothing repaired and no dead trial."""
        return None if self.nonfinite == "recover" else torch.zeros_like(n_repaired, dtype=torch.bool)

    def _estimate_and_resample(
        self, particles, lw, inc, generator, step, cov, extras, n_repaired, invalid, dead, uniforms=None
    ) -> "ParticleState":
        """The weighted mean of normalised ``lw``, the ESS and the resampling (``dead (B,)``: the
        trials whose step had no particle of positive weight, ``None`` when none had; ``uniforms``:
        the resampler's draws when made already)."""
        w = lw.exp()
        estimate = (
            torch.bmm(w.unsqueeze(1), particles).squeeze(1)
            if particles.dim() == 3  # (B, d)
            else torch.matmul(w.unsqueeze(-2), particles).squeeze(-2)
        )
        ess = (w * w).sum(-1).reciprocal()  # the resampler's trigger (of the weights it goes on with)
        particles, lw_new, cov, extras, resampled = self.resampler(
            particles, lw, generator, cov=cov, extras=extras, ess=ess, uniforms=uniforms
        )
        if dead is not None:  # a dead step keeps the previous weights to go on, but no particle had positive weight
            ess = ess.masked_fill(dead, 0.0)
        return ParticleState(
            particles=particles,
            log_weights=lw_new,
            estimate=estimate,
            ess=ess,
            log_evidence_increment=inc,
            resampled=resampled,
            n_repaired=n_repaired,
            cov=cov,
            step=step,
            extras=extras,
            invalid=invalid,
        )

    def extra_repr(self) -> str:
        return f"n_particles={self.n_particles}, nonfinite={self.nonfinite!r}"


ParticleFilter.kept = frozenset(_KEPT)

#: the former name of :class:`ParticleFilter` (kept for users' code)
ParticleFilterBase = ParticleFilter


def _requires_grad(value) -> bool:
    """``value`` is a tensor that requires grad, or an object (a structured covariance), list, tuple or
    dict holding one at its first level."""
    if isinstance(value, torch.Tensor):
        return value.requires_grad
    if isinstance(value, (list, tuple)):
        return any(isinstance(v, torch.Tensor) and v.requires_grad for v in value)
    if isinstance(value, dict):
        return any(isinstance(v, torch.Tensor) and v.requires_grad for v in value.values())
    if isinstance(value, Covariance):  # its tensors, in __slots__ or __dict__
        names = set(getattr(value, "__dict__", {})) | {
            n for c in type(value).__mro__ for n in getattr(c, "__slots__", ())
        }
        return any(
            _requires_grad(getattr(value, n, None))
            for n in names
            if not isinstance(getattr(value, n, None), Covariance)
        )
    return False
