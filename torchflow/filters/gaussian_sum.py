"""Gaussian and Gaussian-sum particle filters, with and without a particle flow (Comandur,
Li & Nannuru 2022, eqs 4-16; Kotecha & Djuric 2003).

The belief is a mixture ``sum_j alpha^j N(mu^j, Sigma^j)`` of G components; no resampling anywhere.
One step, for all trials and all G components in one batched call (components are rows of a
``(B*G, N*, d)`` batch, never a Python loop):

1. **Predict** (eqs 4, 5, 8): ``x_{t-1}^{ij} ~ N(mu^j, Sigma^j)`` (fresh draws), ``eta_0^{ij} =
   g(x_{t-1}^{ij}, v^{ij})`` (the model's stochastic transition), and the component's Gaussian fit
   ``mu_bar^j``, ``Sigma_bar^j`` (sample moments, divisor N* as printed, plus a jitter
   ``jitter * tr(Sigma_bar^j) / d`` on the diagonal; the posterior covariances get the same
   jitter, relative to their component's predictive, since weights on a few particles leave them
   of low rank or zero).
2. **Update** without flow (GPF/GSPF): ``x^{ij} = eta_0^{ij}``, ``w^{ij} = p(z | x^{ij})``. With a
   flow (PFGPF/PFGSPF, eqs 9-14): the LEDH flow moves ``eta_0^{ij}`` with the *component's* prior
   (``P = Sigma_bar^j``, ``eta_bar_0 = mu_bar^j``), each particle linearised at its own auxiliary
   point, and ``log w = log N(eta_1; mu_bar, Sigma_bar) + log p(z | eta_1) + log|det| -
   log N(eta_0; mu_bar, Sigma_bar)``.
3. **Moments and mixture weights** (eqs 7, 15): within-component normalised weights give
   ``mu^j``, ``Sigma^j``; ``alpha^j <- alpha^j sum_i w^{ij}`` normalised, all in log space with every
   normalising constant kept, so components whose weights differ by 1e300 stay finite. The estimate
   is ``sum_j alpha^j mu^j``; the effective number of Gaussians ``G_eff = 1 / sum_j (alpha^j)^2``
   (eq 16) is reported per step.

Choices the paper leaves open are knobs (defaults first):

* ``linearize_at``: ``"auxiliary"``: each particle's point starts at its noise-free prediction
  ``g(x_{t-1}^{ij}, 0)`` (the model's ``transition_mean``) and migrates with its own drift, so each
  particle's map is affine in ``eta_0`` and ``log|det|`` is exact (as in PF-PF(LEDH));
  ``"particle"``: the literal reading, linearised at the particle itself (the weight's
  ``log|det|`` is then approximate).
* ``redraw_eta0``: ``False`` (the seed's literal algorithm: ``eta_0`` comes from propagation but is
  scored under the Gaussian fit); ``True`` draws ``eta_0 ~ N(mu_bar, Sigma_bar)`` afresh after the
  fit, which makes the weight an exact importance weight for the fitted predictive.
* ``init``: ``"prior"`` (every component is the filter prior, ``alpha_0 = 1/G``) or ``"spread"``
  (``mu_0^j ~ N(m_0, P_0)``, ``Sigma_0^j = P_0``).
* ``estimate``: ``"mixture_mean"`` (the seed's ``sum_j alpha^j mu^j``, CONF) or ``"top_component"``
  (the mean of the component with the largest weight). On multi-target tracking the components
  may hold the targets in different orders (labels are exchangeable); the mixture mean then
  averages different targets' positions, while each component tracks well (seen on acoustic
  tracking: components at 0.2-1 m OMAT, their mixture mean at 3-6 m).

``log_evidence`` is the importance-sampling estimate of ``p(z_t | z_{1:t-1})`` under the fitted
Gaussian-sum predictive, ``log sum_j alpha^j (1/N*) sum_i w^{ij}``: an approximation (the fit is not
the model's predictive), so it is not scored against a reference (``estimates_evidence = False``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch

from torchflow.core import linalg, missing
from torchflow.core.checks import check_choice, check_count
from torchflow.core.errors import ArgumentError
from torchflow.filters.base import ParticleFilter
from torchflow.flows import FlowPrior, integrate_flow, which_kernel
from torchflow.flows.points import ParticlePoints, flow_points_per_call
from torchflow.flows.schedules import LambdaSchedule, resolve_schedule
from torchflow.models.base import require_gaussian
from torchflow.models.structure import bytes_per_point
from torchflow.proposals import resolve_flow

LINEARIZE_AT = ("auxiliary", "particle")
ESTIMATES = ("mixture_mean", "top_component")
INITS = ("prior", "spread")


@dataclass
class MixtureState:
    """Belief of a Gaussian-sum filter after a step.

    Attributes:
        log_alpha: ``(B, G)`` normalised log mixture weights.
        means: ``(B, G, d)`` component means.
        covs: ``(B, G, d, d)`` component covariances.
        estimate: ``(B, d)`` mixture mean ``sum_j alpha^j mu^j``.
        ess: ``(B,)`` effective sample size of the step's ``G N*`` particles under their combined
            weights ``alpha_{t-1}^j w^{ij}`` (``G N*`` at step 0).
        g_eff: ``(B,)`` effective number of Gaussians ``1 / sum_j (alpha^j)^2``.
        log_evidence_increment: ``(B,)``.
        n_repaired: ``(B,)`` steps in which non-finite particles or weights were repaired.
        step: observations processed.
        invalid: ``(B,)`` trials with non-finite particles or weights (``nonfinite="raise"``).
    """

    log_alpha: torch.Tensor
    means: torch.Tensor
    covs: torch.Tensor
    estimate: torch.Tensor
    ess: torch.Tensor
    g_eff: torch.Tensor
    log_evidence_increment: torch.Tensor
    n_repaired: torch.Tensor
    step: int = 0
    invalid: Optional[torch.Tensor] = None


def mixture_update(log_alpha: torch.Tensor, log_w: torch.Tensor):
    """Mixture weights after a step, in log space.

    Args:
        log_alpha: ``(B, G)`` normalised log weights before the step.
        log_w: ``(B, G, N*)`` unnormalised log importance weights on one scale across components.

    Returns:
        ``(log_alpha_new (B, G), log_evidence_increment (B,), g_eff (B,))`` with
        ``alpha_new^j ∝ alpha^j (1/N*) sum_i w^{ij}`` and the increment ``log sum_j`` of it. A
        component with no positive weight gets ``log_alpha = -inf``; a trial with none keeps
        ``log_alpha`` (and its increment is ``-inf``).
    """
    n = log_w.shape[-1]
    log_comp = log_alpha + torch.logsumexp(log_w, -1) - math.log(n)  # (B, G)
    inc = torch.logsumexp(log_comp, -1)
    dead = ~torch.isfinite(inc)
    new = torch.where(dead.unsqueeze(-1), log_alpha, log_comp - inc.unsqueeze(-1))
    g_eff = 1.0 / torch.exp(2 * new).sum(-1)
    return new, inc.masked_fill(dead, float("-inf")), g_eff


def _factor(S: torch.Tensor, jitter: float) -> torch.Tensor:
    """Cholesky factor of ``S + jitter tr(S)/d I`` (``S (..., d, d)``)."""
    d = S.shape[-1]
    scale = S.diagonal(dim1=-2, dim2=-1).mean(-1)
    eye = torch.eye(d, dtype=S.dtype, device=S.device)
    return linalg.safe_cholesky(S + (jitter * scale)[..., None, None] * eye)


class GaussianSumParticleFilter(ParticleFilter):
    """Gaussian-sum particle filter, optionally with the LEDH flow as each component's proposal
    (GSPF, and PFGSPF with ``flow``; G = 1 gives GPF and PFGPF). See the module docstring.

    Args:
        model: state-space model (its stochastic transition ``sample_transition`` and measurement
            log-likelihood; with a flow, its Gaussian measurement term).
        n_components: G >= 1.
        particles_per_component: N* per component, at least ``d + 1`` (each component fits a
            ``d x d`` covariance from them; fewer would leave it singular, which the jitter would
            only mask). The total is ``n_particles = G N*``.
        flow: ``None`` (no flow: GPF/GSPF), ``"ledh"`` or a deterministic
            :class:`~torchflow.flows.ParticleFlow` with per-particle points (PFGPF/PFGSPF).
        schedule: lambda schedule of the flow (default exponential, 29 steps, ratio 1.2, as Li & Coates 2017).
        linearize_at: ``"auxiliary"`` (default) or ``"particle"``; see the module docstring.
        redraw_eta0: redraw ``eta_0`` from the fitted predictive (default False, the seed's).
        init: ``"prior"`` (default) or ``"spread"``.
        estimate: ``"mixture_mean"`` (default, the seed's) or ``"top_component"``.
        jitter: relative diagonal jitter of every fitted covariance (default 1e-6; not in the
            paper: with N* = 200 particles in d = 144 the sample covariance is near-singular).
        nonfinite: ``"recover"`` (default): particles with a non-finite position or weight get
            weight zero; a component left with none keeps its predicted moments and gets
            ``alpha = 0``; a trial left with none keeps its mixture weights. ``"raise"``: the
            trial is reported by :class:`~torchflow.core.checks.NonFiniteError`.
        particle_chunk: flow at most this many of a trial's particles per pass (memory).
        resampling_gradient: accepted for every particle filter's sake (validated like theirs);
            these filters never resample: each step draws afresh from the fitted Gaussians by
            reparameterisation (``mu + L xi``), so the gradient of the log-evidence is pathwise
            whatever this says, and no estimator changes it.
    """

    random_stream = "gaussian_sum"
    estimates_evidence = False

    def __init__(
        self,
        model,
        *,
        n_components: int = 1,
        particles_per_component: int = 500,
        flow=None,
        schedule: Optional[LambdaSchedule] = None,
        linearize_at: str = "auxiliary",
        redraw_eta0: bool = False,
        init: str = "prior",
        jitter: float = 1e-6,
        estimate: str = "mixture_mean",
        nonfinite: str = "recover",
        particle_chunk: Optional[int] = None,
        resampling_gradient: str = "stop_gradient",
        validate: bool = True,
        name: Optional[str] = None,
    ):
        G = check_count("n_components", n_components)
        n = check_count("particles_per_component", particles_per_component)
        d = model.state_dim
        if n < d + 1:
            raise ArgumentError(
                f"particles_per_component: expected at least d + 1 = {d + 1} to fit a {d} x {d} "
                f"covariance per component, got {n}"
            )
        super().__init__(
            model,
            n_particles=G * n,
            nonfinite=nonfinite,
            particle_chunk=particle_chunk,
            resampling_gradient=resampling_gradient,
            validate=validate,
            name=name,
        )
        self.linearize_at = check_choice("linearize_at", linearize_at, LINEARIZE_AT)
        self.estimate = check_choice("estimate", estimate, ESTIMATES)
        self.init_mode = check_choice("init", init, INITS)
        if not isinstance(redraw_eta0, bool):
            raise ArgumentError(f"redraw_eta0: expected True or False, got {redraw_eta0!r}")
        if isinstance(jitter, bool) or not isinstance(jitter, (int, float)) or not 0 <= jitter < 1:
            raise ArgumentError(f"jitter: expected a relative jitter in [0, 1), got {jitter!r}")
        self.flow = None if flow is None else resolve_flow(flow)
        if self.flow is not None:  # the flows linearise h and start from the transition mean
            require_gaussian(model, self.name)
        if self.flow is not None and self.flow.stochastic:
            raise ArgumentError(
                f"flow: the Gaussian-sum filters weigh with the flow's log|det|, so the flow must be "
                f"deterministic (EDH/LEDH family), got {type(self.flow).__name__}"
            )
        self.n_components, self.particles_per_component = G, n
        self.schedule = resolve_schedule(schedule)
        self.redraw_eta0, self.jitter = redraw_eta0, float(jitter)

    def extra_repr(self) -> str:
        return (
            f"n_components={self.n_components}, particles_per_component={self.particles_per_component}, "
            f"linearize_at={self.linearize_at!r}, redraw_eta0={self.redraw_eta0}, init={self.init_mode!r}, "
            f"estimate={self.estimate!r}"
        )

    def bytes_per_trial(self, n_particles=None):
        G, n = self.n_components, self.particles_per_component
        d, m = self.model.state_dim, self.model.obs_dim
        per_particle = 8 * d + 3 * m + 8
        if self.flow is not None:  # per-particle LEDH algebra: ~12 d x d and a few m x d matrices
            per_particle += 12 * d * d + 4 * m * d
        return 8 * G * (n * per_particle + 4 * d * d) + G * n * bytes_per_point(self.model)

    def preferred_chunk_trials(self, n_particles=None):
        if self.flow is None:
            return super().preferred_chunk_trials(n_particles)
        return max(
            1,
            min(
                ParticlePoints().preferred_chunk_trials(self.n_particles),
                flow_points_per_call(self.model) // self.n_particles,
            ),
        )

    # ---- contract ------------------------------------------------------------------------------
    def init(self, mean, cov, n_particles=None, generator=None) -> MixtureState:
        if n_particles is not None and self._resolve_n(n_particles) != self.n_particles:
            raise ArgumentError(
                f"n_particles: a Gaussian-sum filter's total is n_components x particles_per_component "
                f"= {self.n_particles}; set those instead (got n_particles={n_particles})"
            )
        B, d = mean.shape
        G = self.n_components
        if self.init_mode == "spread":
            means = linalg.sample_mvn(mean, linalg.safe_cholesky(cov), (G,), generator)  # (B, G, d)
        else:
            means = mean.unsqueeze(1).expand(B, G, d)
        covs = cov.unsqueeze(1).expand(B, G, d, d)
        log_alpha = torch.full((B, G), -math.log(G), dtype=mean.dtype, device=mean.device)
        zero = torch.zeros(B, dtype=mean.dtype, device=mean.device)
        return MixtureState(
            log_alpha,
            means,
            covs,
            (log_alpha.exp().unsqueeze(-1) * means).sum(1),
            torch.full_like(zero, float(self.n_particles)),
            torch.full_like(zero, float(G)),
            zero,
            torch.zeros(B, dtype=torch.long, device=mean.device),
        )

    def step(self, state: MixtureState, z: torch.Tensor, generator=None) -> MixtureState:
        draws = self.draw(state, generator)
        return self.update(state, z, *draws)

    def draw(self, state: MixtureState, generator):
        """The step's random numbers turned into particles: ``x_prev (B, G, N*, d)`` drawn from the
        components, ``eta0 (B, G, N*, d)`` propagated (or redrawn from the fit, ``redraw_eta0``),
        and the fitted predictive ``mu_bar (B, G, d)``, ``L_bar (B, G, d, d)``."""
        B, G, d = state.means.shape
        n = self.particles_per_component
        L_post = linalg.safe_cholesky(state.covs)
        xi = linalg.standard_normal(
            (B, G, n, d), dtype=state.means.dtype, device=state.means.device, generator=generator
        )
        x_prev = state.means.unsqueeze(2) + xi @ L_post.transpose(-1, -2)
        eta0 = self.model.sample_transition(x_prev.reshape(B, G * n, d), generator).reshape(B, G, n, d)
        mu_bar = eta0.mean(2)
        dev = eta0 - mu_bar.unsqueeze(2)
        L_bar = _factor(linalg.symmetrize(dev.transpose(-1, -2) @ dev / n), self.jitter)
        if self.redraw_eta0:
            xi = linalg.standard_normal((B, G, n, d), dtype=eta0.dtype, device=eta0.device, generator=generator)
            eta0 = mu_bar.unsqueeze(2) + xi @ L_bar.transpose(-1, -2)
        return x_prev, eta0, mu_bar, L_bar

    def update(self, state: MixtureState, z: torch.Tensor, x_prev, eta0, mu_bar, L_bar) -> MixtureState:
        """Weights, component moments and mixture weights from the drawn particles (:meth:`draw`);
        separated from the draws so that tests can feed the bank and single components the same
        particles."""
        model = self.model
        B, G, n, d = eta0.shape
        flat = (B * G, n, d)
        z1 = z.unsqueeze(1)
        rows = self._row_chunk(z.device)

        def loglik(xs):  # on the trial's G N* particles (the model's batch is the trials)
            return missing.measurement_log_prob(model, z1, xs)  # observed coordinates only (torchflow.core.missing)

        if self.flow is None:
            x = eta0
            log_w = self.per_particle(loglik, eta0.reshape(B, G * n, d)).reshape(B, G, n)
        else:
            zz = z.repeat_interleave(G, 0)  # (B*G, m): each component row flows with its trial's observation
            mb = mu_bar.reshape(B * G, 1, d)
            Lb = L_bar.reshape(B * G, 1, d, d)
            start = eta0 if self.linearize_at == "particle" else model.transition_mean(x_prev)

            def block(e0, s0):
                prior = FlowPrior(mb.expand(-1, e0.shape[1], -1), Lb)
                out = integrate_flow(self.flow, model, e0, zz, prior, self.schedule, points="particle", start=s0)
                x1 = out.particles
                return x1, linalg.mvn_log_prob(x1, mb, Lb) + out.log_det - linalg.mvn_log_prob(e0, mb, Lb)

            x, log_w = self.per_particle(block, eta0.reshape(flat), start.reshape(flat), chunk=rows)
            x = x.reshape(B, G, n, d)
            log_w = log_w.reshape(B, G, n) + self.per_particle(loglik, x.reshape(B, G * n, d)).reshape(B, G, n)
        # non-finite particles or weights: weight zero, counted (recover) or flagged (raise): the
        # particle filters' one path
        x, log_w, bad_trial = self.repair(x, log_w, None)
        log_alpha, inc, g_eff = mixture_update(state.log_alpha, log_w)
        dead_comp = ~torch.isfinite(torch.logsumexp(log_w, -1))  # (B, G)
        lw = log_w.masked_fill(dead_comp.unsqueeze(-1), 0.0)  # dead: any finite weights (replaced below)
        means, covs = linalg.weighted_mean_cov(x.reshape(B * G, n, d), lw.reshape(B * G, n))
        means, covs = means.reshape(B, G, d), covs.reshape(B, G, d, d)
        # the weights may sit on a few particles (covs of low rank, or zero): jitter relative to the
        # component's predictive scale keeps every stored covariance positive definite
        S_bar = L_bar @ L_bar.transpose(-1, -2)
        eye = torch.eye(d, dtype=covs.dtype, device=covs.device)
        covs = covs + (self.jitter * S_bar.diagonal(dim1=-2, dim2=-1).mean(-1))[..., None, None] * eye
        # a component with no positive weight keeps its fitted predictive (its alpha is zero)
        means = torch.where(dead_comp.unsqueeze(-1), mu_bar, means)
        covs = torch.where(dead_comp[..., None, None], S_bar, covs)
        alpha = log_alpha.exp()
        if self.estimate == "top_component":
            top = log_alpha.argmax(-1)
            estimate = means.gather(1, top[:, None, None].expand(B, 1, d)).squeeze(1)
        else:
            estimate = torch.einsum("bg,bgd->bd", alpha, means)
        lv = (state.log_alpha.unsqueeze(-1) + log_w).reshape(B, G * n)
        ess = 1.0 / torch.softmax(lv, -1).pow(2).sum(-1)
        ess = torch.where(torch.isfinite(ess), ess, torch.zeros_like(ess))  # no positive weight: 0
        repaired, invalid = self.account(bad_trial, ~torch.isfinite(inc), state.n_repaired)
        return MixtureState(log_alpha, means, covs, estimate, ess, g_eff, inc, repaired, state.step + 1, invalid)

    def _row_chunk(self, device=None) -> Optional[int]:
        """Particles per component row per pass (the filter's ``particle_chunk``, or with a flow the
        cache-sized block of :func:`~torchflow.flows.points.flow_points_per_call`, is per trial)."""
        c = self.particle_chunk if self.flow is None else self.flow_chunk(device)
        return None if not c else max(1, c // self.n_components)

    def flow_chunk(self, device=None) -> Optional[int]:
        """A trial's particles per flow pass: ``particle_chunk`` when set, else the cache-sized
        :func:`~torchflow.flows.points.flow_points_per_call` when the trial's particles exceed it;
        no blocks when the flow runs as the diagonal CPU kernel on ``device``
        (:func:`~torchflow.flows.which_kernel` is ``"diagonal"``: no ``d x d`` matrix per particle
        is built, and blocks only add calls; the numbers are the same either way)."""
        if self.particle_chunk:
            return self.particle_chunk
        if device is not None and which_kernel(self.flow, self.model, device) == "diagonal":
            return None
        cap = flow_points_per_call(self.model)
        return cap if self.n_particles > cap else None


class GaussianParticleFilter(GaussianSumParticleFilter):
    """Gaussian particle filter (Kotecha & Djuric 2003): one Gaussian component, proposal = the
    fitted predictive. A :class:`GaussianSumParticleFilter` with ``n_components = 1``."""

    def __init__(self, model, *, n_particles: int = 500, **kwargs):
        kwargs.setdefault("particles_per_component", n_particles)
        super().__init__(model, n_components=1, **kwargs)


class ParticleFlowGaussianParticleFilter(GaussianParticleFilter):
    """PFGPF (Comandur, Li & Nannuru): the Gaussian particle filter with the LEDH flow as its
    proposal (``flow="ledh"`` by default)."""

    def __init__(self, model, *, flow="ledh", **kwargs):
        super().__init__(model, flow=flow, **kwargs)


class ParticleFlowGaussianSumParticleFilter(GaussianSumParticleFilter):
    """PFGSPF (Comandur, Li & Nannuru): a bank of G PFGPFs with mixture weights
    (``flow="ledh"`` by default)."""

    def __init__(self, model, *, flow="ledh", **kwargs):
        super().__init__(model, flow=flow, **kwargs)


GPF = GaussianParticleFilter
GSPF = GaussianSumParticleFilter
PFGPF = ParticleFlowGaussianParticleFilter
PFGSPF = ParticleFlowGaussianSumParticleFilter

__all__ = [
    "MixtureState",
    "mixture_update",
    "GaussianSumParticleFilter",
    "GaussianParticleFilter",
    "ParticleFlowGaussianParticleFilter",
    "ParticleFlowGaussianSumParticleFilter",
    "GPF",
    "GSPF",
    "PFGPF",
    "PFGSPF",
]
