"""The weighted particle flow on deterministic dynamics: a PF-PF over the lag-one target.

With dynamics ``x_k = M(x_{k-1})`` and no transition density, the filter weighs particles of the
previous state against the lag-one target

    p(x_{k-1} | z_{1:k})  ∝  p̂(x_{k-1}) p(z_k | M(x_{k-1})),

where ``p̂`` is the *regularised prior*: the previous weighted particles ``(x_j, W_j)`` smoothed by
a Gaussian kernel whose covariance is ``h^2`` times their weighted covariance ``Sigma`` (``h``:
:attr:`bandwidth`, relative to the weighted spread, as DAPPER's ``PartFilt`` scales its
regularisation), with Liu & West's shrinkage of the centres towards the weighted mean ``mu``
(``c_j = mu + sqrt(1 - h^2) (x_j - mu)``: the mixture keeps the particles' mean and covariance),
and a defensive component ``N(mu, kappa^2 U)`` of weight ``epsilon`` (:attr:`defensive`,
:attr:`defensive_scale`; ``U`` the particles' unweighted covariance, the cloud's extent whatever the
weights) that keeps the target's tails where the weights have collapsed::

    p̂(x) = (1 - epsilon) sum_j W_j N(x; c_j, h^2 Sigma) + epsilon N(x; mu, kappa^2 U).

No model noise is invented: the target is a density because of the kernel, and the kernel is
relative to the particles' own spread, so it shrinks as they concentrate. (``Sigma`` holds
:data:`FLOOR` times the unweighted covariance too: weights that collapse onto one particle leave the
kernels a width.)

**The kernels' shape** (:attr:`kernel`). ``"spread"``: every kernel has the covariance
``h^2 Sigma``. ``"propagated"`` (default): kernel ``j`` has particle ``j``'s own covariance, the
posterior covariance of the component it was drawn from (the flow's Gaussian image) carried to
time k by the model's Jacobian, ``J(x) C J(x)^T``, rescaled to the trace of ``h^2 Sigma`` and mixed
with it (``kernel_mix``, the share of ``h^2 Sigma``): the kernels then lie along the directions the
dynamics stretch and not across the ones they contract (on Lorenz-63 the attractor is thin: a
kernel across it puts prior mass where the dynamics leave none). The mixture then keeps the
particles' mean, and their covariance's trace.

**Proposal: each kernel component's lag-one flow.** Particle ``i`` is drawn from one component
``a_i`` of ``p̂`` and moved by the exact Daum-Huang flow (LEDH: its point starts at the component's
centre and is linearised there at every pseudo-time step) from that component's Gaussian
``N(c_{a_i}, S_{a_i})`` to its posterior under the measurement of the forecast ``h(M(x))``
(:meth:`~torchflow.flows.GaussianMeasurement.lag_one`: the chain rule through the model's
Jacobian). A component's flow is affine in the particle, so its image is the Gaussian
``N(T_a(c_a), M_a S_a M_a^T)`` (``M_a`` the map's Jacobian: its determinant is in that covariance).
Components are chosen by an auxiliary first stage (Pitt & Shephard 1999): with probabilities
``lambda_a ∝ w_a N(z; h(M(c_a)), H_a S_a H_a^T + R)`` (the linearised evidence of each component)
when their effective sample size falls below ``ess_threshold`` times N (systematic resampling),
else each particle keeps its own component.

**Weights** (the deterministic-mixture estimator of Owen & Zhou 2000, as the marginal particle
filter of Klaas, de Freitas & Doucet 2005)::

    w_i ∝ p̂(x_i) p(z_k | x_k,i) / [(1/N) sum_n N(x_i; T_{a_n}(c_{a_n}), M_{a_n} S_{a_n} M_{a_n}^T)],

with ``x_k,i`` the particle carried to time k by the model's transition (``M(x_i)`` for
deterministic dynamics; a model with noise draws it, and the weight stays exact: the target is then
``p̂(x_{k-1}) p(x_k | x_{k-1}) p(z_k | x_k)``). ``(1/N) sum_i w_i`` is an unbiased estimate of the
regularised target's evidence ``∫ p̂(x) p(z_k | M(x)) dx``, whatever the flow does (it only has to
be a Gaussian of known law per component); in a linear-Gaussian model with deterministic dynamics
the regularised prior has the filter's moments and the flow is exact, so the weighted particles
reproduce the Kalman filter (tested). The evidence is the regularised model's (the kernel is part
of it): particle MCMC (:func:`~torchflow.inference.pmmh`) and learning through this filter target
that model's posterior, which approaches the deterministic model's as the bandwidth falls. Cost per
step: ``flow_steps + 2`` linearisations of ``h(M(.))``
at N points (N model runs and Jacobians each) and ``O(N^2 d^2)`` for the mixtures (in blocks).

**Missing observations.** A NaN in ``z (B, m)`` is not observed: its rows drop out of the flow and
the weights; a trial with nothing observed at a step is a prediction: its particles go through the
model's transition with their weights, and the step adds nothing to the evidence.
"""

from __future__ import annotations

import math
from typing import Optional

import torch

from torchflow.core import linalg
from torchflow.core import missing as _missing
from torchflow.core.checks import check_count, check_number
from torchflow.core.covariances import sample_prior
from torchflow.core.errors import ArgumentError, ArgumentTypeError
from torchflow.core.random import uniform
from torchflow.filters.base import Filter, ParticleState
from torchflow.filters.marginal import gaussian_pairs, mixture_logsumexp, pair_rows
from torchflow.flows import FlowPrior, GaussianMeasurement, LEDHFlow, integrate_flow
from torchflow.flows.schedules import ExponentialSchedule

__all__ = ["LagOneFlowParticleFilter", "kernel_prior", "propagated_kernels"]

#: ``kernel=`` choices: one covariance for every kernel, or each particle's own propagated one
KERNELS = ("spread", "propagated")
#: the unweighted covariance's share in the kernels' ``Sigma``: a floor for weights that collapse onto one particle
FLOOR = 0.05


def kernel_prior(particles: torch.Tensor, log_weights: torch.Tensor, bandwidth: float, *, shrink: bool = True):
    """The previous weighted particles smoothed by a Gaussian kernel (module docstring).

    Args:
        particles: ``(B, N, d)``; log_weights: ``(B, N)`` normalised.
        bandwidth: ``h`` in (0, 1], the kernel's scale relative to the weighted spread.
        shrink: Liu & West's shrinkage of the centres (the mixture keeps the weighted mean and
            covariance); ``False``: centres at the particles (the mixture's covariance is
            ``(1 + h^2) Sigma``).

    Returns:
        ``(centres (B, N, d), kernel factor (B, d, d), mean mu (B, 1, d), spread factor (B, d, d))``:
        the kernel's covariance is ``factor factor^T = h^2 Sigma``, ``Sigma`` the weighted
        covariance plus :data:`FLOOR` times the unweighted one (weights collapsed onto one particle
        leave the kernel a width); the spread factor is that of the particles' unweighted covariance, the cloud's
        extent whatever the weights (the defensive component's scale: it stays wide when the
        weights have collapsed onto one particle, where ``Sigma`` vanishes).
    """
    N = particles.shape[1]
    w = log_weights.exp().unsqueeze(-1)  # (B, N, 1)
    mu = (w * particles).sum(1, keepdim=True)
    D = particles - mu
    E = particles - particles.mean(1, keepdim=True)
    unweighted = linalg.symmetrize(E.transpose(1, 2) @ E / N)
    sigma = linalg.symmetrize((w * D).transpose(1, 2) @ D) + FLOOR * unweighted  # (B, d, d)
    L = linalg.safe_cholesky(sigma)
    spread = linalg.safe_cholesky(unweighted)
    a = math.sqrt(max(0.0, 1.0 - bandwidth * bandwidth)) if shrink else 1.0
    return mu + a * D, bandwidth * L, mu, spread


def propagated_kernels(factor: torch.Tensor, shape: torch.Tensor, mix: float) -> torch.Tensor:
    """Each particle's kernel factor ``(B, N, d, d)`` from the spread kernel's ``factor (B, d, d)``
    (``G = factor factor^T = h^2 Sigma``) and the particles' carried covariances ``shape (B, N, d, d)``:
    the factor of ``(1 - mix) S_j tr(G) / tr(S_j) + mix G``."""
    G = factor @ factor.transpose(-1, -2)
    trace = G.diagonal(dim1=-2, dim2=-1).sum(-1).unsqueeze(1)  # (B, 1)
    scale = trace / shape.diagonal(dim1=-2, dim2=-1).sum(-1).clamp_min(torch.finfo(shape.dtype).tiny)
    S = (1 - mix) * shape * scale[..., None, None] + mix * G.unsqueeze(1)
    return linalg.safe_cholesky(linalg.symmetrize(S))


class LagOneFlowParticleFilter(Filter):
    """PF-PF over the lag-one target with a kernel-regularised prior, for deterministic dynamics
    (module docstring).

    Args:
        model: a Gaussian-form model (``transition_mean`` and its Jacobian, ``measure`` and its
            Jacobian, R; ``sample_transition``). Dynamics without noise need nothing more.
        n_particles: N (>= 2).
        bandwidth: ``h`` in (0, 1]: the kernel's scale relative to the weighted spread (0.2: the
            best of a grid on Lorenz-63, ``experiments/RESULTS.md``). Smaller keeps more of the
            particles' shape but lets them collapse; 1 with shrinkage is the Gaussian of their
            moments (the unweighted lag-one flow's prior).
        shrink: Liu & West's shrinkage of the kernel centres towards the weighted mean (default
            True: the regularised prior keeps the particles' mean and covariance).
        inflation: multiplicative inflation (>= 1) of the previous particles' anomalies before the
            kernel (1: none).
        defensive: the weight ``epsilon`` in [0, 1) of the defensive component ``N(mu, kappa^2 U)``
            (``U`` the particles' unweighted covariance; 0: none).
        defensive_scale: ``kappa`` (>= 1).
        ess_threshold: choose components by the auxiliary first stage (systematic resampling) when
            its effective sample size is below this fraction of N (in [0, 1]; 1: every step; 0:
            never, each particle keeps its own component).
        kernel: ``"propagated"`` (default: each particle's own covariance carried through its flow
            and the model's Jacobian, with the trace of ``h^2 Sigma``) or ``"spread"`` (``h^2 Sigma``
            for every kernel); module docstring.
        kernel_mix: with ``"propagated"``, the share in (0, 1] of ``h^2 Sigma`` in each kernel (0.05;
            with none, the carried covariances grow ill-conditioned along the contracting
            directions and every trial of Lorenz-63 diverged).
        flow_steps, step_ratio: the flow's exponential pseudo-time schedule.
        validate, name: as :class:`~torchflow.filters.Filter`.

    The state's ``particles`` are the weighted particles at time k (``log_weights`` normalised,
    ``ess`` their effective sample size, ``resampled`` whether the components were chosen by the
    first stage, ``extras["shape"]`` each particle's carried covariance ``(B, N, d, d)`` with
    ``kernel="propagated"``); the estimate is their weighted mean. The log-evidence increment estimates the
    regularised model's ``log p(z_k | z_{1:k-1})``.

    Shapes: particles ``(B, N, d)``, observations ``z (B, m)`` (NaN: not observed).
    """

    uses_particles = True
    uses_randomness = True
    diagonal_prior = True  # the initial particles are drawn with the variances alone
    random_stream = "lag_one_pfpf"
    nonfinite_hint = (
        "the weights or the flow diverged: a larger bandwidth, a defensive component (defensive=0.01), more "
        "flow_steps, or dynamics that blow up at the model's time step (a smaller dt or more substeps)"
    )

    def __init__(
        self,
        model,
        *,
        n_particles: int = 100,
        bandwidth: float = 0.2,
        shrink: bool = True,
        inflation: float = 1.0,
        defensive: float = 0.01,
        defensive_scale: float = 3.0,
        ess_threshold: float = 0.5,
        kernel: str = "propagated",
        kernel_mix: float = 0.05,
        flow_steps: int = 20,
        step_ratio: float = 1.2,
        validate: bool = True,
        name: Optional[str] = None,
    ):
        super().__init__(model, validate=validate, name=name)
        #: particles per trial N (>= 2: a weighted covariance needs two)
        self.n_particles = check_count("n_particles", n_particles, minimum=2, hint=" (particles per trial)")
        self.bandwidth = check_number(
            "bandwidth", bandwidth, lambda v: 0 < v <= 1, "a number in (0, 1] (the kernel's scale over the spread)"
        )
        if not isinstance(shrink, bool):
            raise ArgumentTypeError(f"shrink: expected True or False, got {shrink!r}")
        self.shrink = shrink
        self.inflation = check_number(
            "inflation", inflation, lambda v: v >= 1, "a finite number >= 1 (inflation of the previous anomalies)"
        )
        self.defensive = check_number(
            "defensive", defensive, lambda v: 0 <= v < 1, "a number in [0, 1) (the defensive component's weight)"
        )
        self.defensive_scale = check_number(
            "defensive_scale", defensive_scale, lambda v: v >= 1, "a number >= 1 (the defensive component's scale)"
        )
        self.ess_threshold = check_number(
            "ess_threshold", ess_threshold, lambda v: 0 <= v <= 1, "a number in [0, 1] (a fraction of n_particles)"
        )
        if kernel not in KERNELS:
            raise ArgumentError(f"kernel: expected one of {KERNELS}, got {kernel!r}")
        #: the kernels' covariance: ``"spread"``, ``h^2 Sigma`` for every particle; ``"propagated"``, each
        #: particle's own covariance carried through its flow and the model's Jacobian, scaled to the same trace
        self.kernel = kernel
        self.kernel_mix = check_number(
            "kernel_mix", kernel_mix, lambda v: 0 < v <= 1, "a number in (0, 1] (the share of h^2 Sigma in a kernel)"
        )
        self.flow_steps = check_count("flow_steps", flow_steps, minimum=1, hint=" (steps in pseudo-time)")
        self.step_ratio = check_number(
            "step_ratio", step_ratio, lambda v: v > 0, "a number > 0 (each pseudo-time step over the previous one)"
        )
        self.schedule = ExponentialSchedule(self.flow_steps, self.step_ratio)
        self.flow = LEDHFlow()

    def _resolve_n(self, n_particles):
        return (
            self.n_particles
            if n_particles is None
            else check_count("n_particles", n_particles, minimum=2, hint=" (particles per trial)")
        )

    def bytes_per_trial(self, n_particles=None):
        N, d, m = self._resolve_n(n_particles), self.model.state_dim, self.model.obs_dim
        # per particle: its point, map and image (d x d each), the linearisation (m x d); the mixtures in blocks
        return 8 * (N * (6 * d * d + 4 * m * d + 12 * d + 4 * m) + 4 * N * N)

    def check_model(self) -> None:
        """R must be positive definite: the flow and the first stage whiten by it."""
        super().check_model()
        self.require_definite("measurement", "the lag-one flow whitens the measurements by R")

    # ---- contract ------------------------------------------------------------------------------
    def init(self, mean, cov, n_particles=None, generator=None) -> ParticleState:
        """N equally weighted particles per trial drawn from the prior ``N(mean (B, d), cov)``."""
        N = self._resolve_n(n_particles)
        X = sample_prior(mean, cov, N, generator)  # (B, N, d)
        B, d = X.shape[0], X.shape[-1]
        extras = {}
        if self.kernel == "propagated":
            P = cov.dense() if hasattr(cov, "dense") else cov
            extras["shape"] = P.expand(B, d, d).unsqueeze(1).expand(B, N, d, d).contiguous()
        return ParticleState(
            extras=extras,
            particles=X,
            log_weights=torch.full((B, N), -math.log(N), dtype=X.dtype, device=X.device),
            estimate=X.mean(1),
            ess=torch.full((B,), float(N), dtype=X.dtype, device=X.device),
            log_evidence_increment=torch.zeros(B, dtype=X.dtype, device=X.device),
            resampled=torch.zeros(B, dtype=torch.bool, device=X.device),
            step=0,
        )

    def step(self, state: ParticleState, z: torch.Tensor, generator: Optional[torch.Generator] = None):
        """Regularise the previous particles, draw from their kernels (by the first stage where
        needed), flow each to its lag-one posterior, carry them to time k and weigh them."""
        model = self.model
        X, lw = state.particles, state.log_weights
        B, N, d = X.shape
        dt, dev = X.dtype, X.device
        if self.inflation != 1.0:
            wbar = (lw.exp().unsqueeze(-1) * X).sum(1, keepdim=True)
            X = wbar + self.inflation * (X - wbar)
        centres, K, mu, U = kernel_prior(X, lw, self.bandwidth, shrink=self.shrink)
        shape = state.extras.get("shape") if self.kernel == "propagated" else None
        if shape is not None:  # each particle's own shape, with the trace of h^2 Sigma
            K = propagated_kernels(K, shape, self.kernel_mix)  # (B, N, d, d)
        Kc = K if K.dim() == 4 else K.unsqueeze(1)  # (B, N|1, d, d)
        meas = GaussianMeasurement.lag_one(model, z)
        # the target's components: N kernels (shared factor K) and the defensive Gaussian
        eps = self.defensive
        lw_kernel = lw + math.log1p(-eps) if eps > 0 else lw
        # first stage: each component's linearised evidence of z, lambda ~ w N(z; h(M(c)), H S H^T + R)
        lam = lw_kernel + self._component_evidence(meas, centres, Kc)
        if eps > 0:
            wide = self.defensive_scale * U
            lam = torch.cat([lam, math.log(eps) + self._component_evidence(meas, mu, wide.unsqueeze(1))], 1)
        lam = lam - torch.logsumexp(lam, -1, keepdim=True)
        ess_lam = 1.0 / lam.exp().square().sum(-1)
        resample = ess_lam < self.ess_threshold * N  # (B,)
        drawn = _systematic_draws(lam, N, generator)  # (B, N) in [0, N] (N: the defensive component)
        own = torch.arange(N, device=dev).expand(B, N)
        idx = torch.where(resample.unsqueeze(-1), drawn, own)
        c0 = torch.cat([centres, mu], 1) if eps > 0 else centres
        c0 = c0.gather(1, idx.unsqueeze(-1).expand(B, N, d))  # (B, N, d): each particle's component centre
        Kd = Kc.expand(B, N, d, d)
        if Kc.shape[1] > 1:  # each particle's component's own kernel
            Kd = Kd.gather(1, idx.clamp_max(N - 1).view(B, N, 1, 1).expand(B, N, d, d))
        if eps > 0:
            is_wide = (idx == N).view(B, N, 1, 1)
            F0 = torch.where(is_wide, wide.unsqueeze(1), Kd)  # (B, N, d, d)
        else:
            F0 = Kd
        xi = linalg.standard_normal((B, N, d), dtype=dt, device=dev, generator=generator)
        eta = c0 + linalg.matvec(F0, xi)
        out = integrate_flow(
            self.flow,
            model,
            eta,
            z,
            FlowPrior(c0, F0),
            self.schedule,
            points="particle",
            measurement=meas,
            gaussian_image=True,
        )
        x = out.particles
        # the target's density at the flowed particles, and the proposal's (the components' images)
        rows = pair_rows(B, N, N, d * (d + 1), x.element_size())
        (lp,) = mixture_logsumexp(gaussian_pairs(x, centres, K), [lw_kernel], N, rows)
        if eps > 0:
            lp = torch.logaddexp(lp, math.log(eps) + linalg.mvn_log_prob(x, mu, wide.unsqueeze(1)))
        img = linalg.safe_cholesky(out.image_cov)  # (B, N, d, d)
        uniform_w = torch.full((B, N), -math.log(N), dtype=dt, device=dev)
        (lq,) = mixture_logsumexp(gaussian_pairs(x, out.image_mean, img), [uniform_w], N, rows)
        Xk = model.sample_transition(x, generator)  # M(x) for deterministic dynamics
        extras = {}
        if self.kernel == "propagated":  # the component's posterior covariance carried to time k (tangent map)
            J = model.transition_mean_and_jacobian(x)[1]
            extras["shape"] = linalg.symmetrize(J @ out.image_cov @ J.transpose(-1, -2))
        ll = _missing.measurement_log_prob(model, z.unsqueeze(1), Xk)  # (B, N)
        v = lp + ll - lq
        total = torch.logsumexp(v, -1)
        lw_new = v - total.unsqueeze(-1)
        inc = total - math.log(N)
        if _missing.active():  # a trial with nothing observed: a prediction, its weights kept (no kernel)
            empty = torch.isnan(z).all(-1)  # (B,)
            Xp = model.sample_transition(state.particles, generator)
            Xk = torch.where(empty.view(B, 1, 1), Xp, Xk)
            lw_new = torch.where(empty.unsqueeze(-1), lw, lw_new)
            inc = torch.where(empty, torch.zeros_like(inc), inc)
            resample = resample & ~empty
            if "shape" in extras:
                J = model.transition_mean_and_jacobian(state.particles)[1]
                carried = state.extras.get("shape", extras["shape"])
                kept = linalg.symmetrize(J @ carried @ J.transpose(-1, -2))
                extras["shape"] = torch.where(empty.view(B, 1, 1, 1), kept, extras["shape"])
        W = lw_new.exp()
        return ParticleState(
            particles=Xk,
            log_weights=lw_new,
            estimate=(W.unsqueeze(-1) * Xk).sum(1),
            ess=1.0 / W.square().sum(-1),
            log_evidence_increment=inc,
            resampled=resample,
            step=state.step + 1,
            extras=extras,
        )

    @staticmethod
    def _component_evidence(meas: GaussianMeasurement, centres: torch.Tensor, factor: torch.Tensor) -> torch.Tensor:
        """``(B, K)``: ``log N(z; h(M(c)), H S H^T + R)`` up to a constant of the trial, for components
        ``N(c (B, K, d), S = F F^T)`` (``factor (B, K|1, d, d)``), linearised at their centres;
        unobserved rows carry nothing."""
        lin = meas.at(centres)
        W = lin.W if lin.W.dim() == 4 else lin.W.expand(*centres.shape[:2], *lin.W.shape[-2:])
        r = lin.y - linalg.matvec(W, centres)  # L_R^{-1} (z - h(M(c)))
        WF = W @ factor  # (B, K, m, d)
        S = WF @ WF.transpose(-1, -2)
        S.diagonal(dim1=-2, dim2=-1).add_(1.0)
        C = linalg.safe_cholesky(S)
        u = linalg.solve_triangular(C, r.unsqueeze(-1), upper=False).squeeze(-1)
        return -0.5 * u.square().sum(-1) - linalg.chol_logdet(C)

    def extra_repr(self) -> str:
        return (
            f"n_particles={self.n_particles}, bandwidth={self.bandwidth:g}, shrink={self.shrink}, "
            f"inflation={self.inflation:g}, defensive={self.defensive:g}, defensive_scale={self.defensive_scale:g}, "
            f"ess_threshold={self.ess_threshold:g}, kernel={self.kernel!r}"
            + (f", kernel_mix={self.kernel_mix:g}" if self.kernel == "propagated" else "")
            + f", flow_steps={self.flow_steps}, step_ratio={self.step_ratio:g}"
        )


def _systematic_draws(log_weights: torch.Tensor, n: int, generator) -> torch.Tensor:
    """``(B, n)`` indices into ``log_weights (B, K)`` (normalised) by systematic resampling: one
    uniform per trial, ``n`` evenly spaced positions on the weights' cumulative sum."""
    B, K = log_weights.shape
    u = uniform((B, 1), dtype=log_weights.dtype, device=log_weights.device, generator=generator)
    positions = (torch.arange(n, dtype=log_weights.dtype, device=log_weights.device) + u) / n  # (B, n)
    cdf = log_weights.exp().cumsum(-1)
    cdf = cdf / cdf[:, -1:]
    return torch.searchsorted(cdf.contiguous(), positions.contiguous()).clamp_max(K - 1)
