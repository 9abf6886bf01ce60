"""Multi-source localisation from TDOAs with belief propagation and flow-induced Gaussian-mixture
importance sampling (Zhang, Khojasteh, Atanasov & Meyer 2024).

The sensors (receiver pairs) are processed in turn: the posterior after sensor s - 1 is the prior
of sensor s. The belief is a set of potential objects (POs), each with an existence probability
``r_k`` and a Gaussian mixture of G components. For sensor s:

1. every component of every PO (and of the birth mixture, a grid covering the region, where the
   paper's birth density is uniform) is flowed by every measurement (:func:`~torchflow.flows.flow_gaussian`:
   PFI-D = EDH, PFI-S = Gromov, PFI-OS = optimised diffusion) and N_p samples are drawn from it; the
   ratio ``N(x; mu_n, P_n) l_m(x) / N(x; mu'_nm, P'_nm)`` gives ``int f_k l_m`` and the moments;
2. loopy BP (:func:`~torchflow.tdoa.association.loopy_association`) gives the association messages;
3. each legacy PO's candidates ("missed" plus one per component and measurement) are weighted by
   the messages and reduced back to G components by systematic resampling (the paper does not say how), with
   existence ``r C / (r C + 1 - r)``; each measurement makes a new PO from the birth mixture;
4. POs with existence below ``prune`` are dropped and at most ``max_objects`` kept (fixed shapes).

Declared sources: POs with existence above ``declare``, at their mixture mean. Everything is
batched over runs x POs x components x measurements x samples (in chunks of ``sample_chunk``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F

from torchflow.core import linalg
from torchflow.core.checks import check_count as _count
from torchflow.core.errors import ArgumentError, ArgumentTypeError
from torchflow.core.random import check_generator, uniform
from torchflow.core.resampling import systematic
from torchflow.filters.base import Estimator
from torchflow.flows import EDHFlow, GaussianMeasurement, GromovFlow, OptimalDiffusionFlow
from torchflow.flows.schedules import GeometricSchedule, LambdaSchedule, resolve_schedule
from torchflow.models.tdoa import TDOA3D, check_number
from torchflow.proposals import FlowedMixtureProposal
from torchflow.tdoa.association import loopy_association

METHODS = ("pfi_d", "pfi_s", "pfi_os")


@dataclass
class POState:
    """Potential objects after a sensor: ``existence (B, K)`` (0 for empty slots), ``mask (B, K)``
    (the live POs), ``log_weights (B, K, G)`` (normalised), ``means (B, K, G, 3)`` (component means,
    or particles of :class:`BootstrapLocaliser`), ``scale_trils (B, K, G, 3, 3)`` (``None`` for
    particles), ``underflow (B, M)``: the sensor's measurements treated as clutter (:meth:`_Localiser._bp`;
    ``None`` before the first sensor)."""

    existence: torch.Tensor
    mask: torch.Tensor
    log_weights: torch.Tensor
    means: torch.Tensor
    scale_trils: Optional[torch.Tensor] = None
    underflow: Optional[torch.Tensor] = None

    @property
    def positions(self) -> torch.Tensor:
        """``(B, K, 3)`` mixture means."""
        return (self.log_weights.exp().unsqueeze(-1) * self.means).sum(-2)


@dataclass
class Localisation:
    """A localiser's result after each sensor: positions ``estimates (B, S, K, 3)`` (K = ``max_objects``
    slots, empty ones 0), declared sources ``estimate_mask (B, S, K)``, ``underflow (B, S, M)`` (the
    measurements treated as clutter: see :meth:`_Localiser._bp`), the final :class:`POState`;
    :attr:`positions` and :attr:`declared` are the final ``(B, K, 3)`` and ``(B, K)``."""

    estimates: torch.Tensor
    estimate_mask: torch.Tensor
    underflow: torch.Tensor
    state: POState

    @property
    def positions(self) -> torch.Tensor:
        return self.estimates[:, -1]

    @property
    def declared(self) -> torch.Tensor:
        return self.estimate_mask[:, -1]


class _Localiser(Estimator):
    """What both localisers share: BP, pruning, declaration, the run over the sensors (:meth:`forward`)
    and what the runner reads. A localiser's draws depend on the padded number of measurements of
    its batch, so it declares ``trials_per_call = 1`` (the runner gives it one run per chunk) and
    :meth:`forward` trims the batch to its last real measurement column: a run's numbers depend
    only on the scene, the seed and its index.

    Args (both localisers):
        model: :class:`~torchflow.models.TDOA3D` (``clutter_rate > 0``).
        birth_rate: mean number of new sources per measurement, mu_b (0.01: the paper gives no value).
        max_objects: POs kept after each sensor (30); prune: existence below which a PO is dropped
            (1e-3); declare: existence above which a PO is a declared source (0.5).
        bp_iterations: message passes (20).
        sample_chunk: numbers drawn per pass (memory bound). Draws are made per pass, so with the
            numpy back end of per-trial streams (which splits draws above 2^18 numbers) results
            can depend on it; keep it fixed to compare runs.
        name: label in results (default: the class name).
    """

    # the runner's declarations (:class:`~torchflow.filters.base.Estimator`): sets of declared
    # sources, masked measurement sets, one run per call, per-run random streams
    output, padded_measurements, trials_per_call, uses_randomness = "sets", True, 1, True
    estimates_evidence = False
    method: str

    def __init__(self, model: TDOA3D, *, birth_rate, max_objects, prune, declare, bp_iterations, sample_chunk, name):
        super().__init__()
        if not isinstance(model, TDOA3D):
            raise ArgumentTypeError(f"model: expected a torchflow TDOA3D, got {type(model).__name__}")
        if model.clutter_rate <= 0:
            raise ArgumentError(
                f"model.clutter_rate: BP divides by the clutter intensity; expected > 0, got {model.clutter_rate}"
            )
        self.model, self.name = model, name or type(self).__name__
        self.birth_rate = check_number("birth_rate", birth_rate, lambda v: v > 0, "> 0")
        self.prune, self.declare = (
            check_number(k, v, lambda v: 0 <= v < 1, "a probability in [0, 1)")
            for k, v in (("prune", prune), ("declare", declare))
        )
        self.max_objects, self.bp_iterations, self.sample_chunk = (
            _count(k, v)
            for k, v in (("max_objects", max_objects), ("bp_iterations", bp_iterations), ("sample_chunk", sample_chunk))
        )

    @property
    def stream_name(self) -> str:  # key of the per-run random streams
        return f"localise_{self.method}"

    def bytes_per_trial(self, n_particles=None) -> int:  # rough peak memory of one run: a pass of sample_chunk numbers
        return 8 * 8 * self.sample_chunk

    def forward(
        self, observations: torch.Tensor, mean=None, cov=None, generator=None, *, mask: torch.Tensor, progress=None
    ) -> Localisation:
        """Localise from measurements ``observations (B, S, M)`` with ``mask`` (bool, same shape;
        :class:`~torchflow.models.TDOAData`), sensor after sensor. ``generator``: a ``torch.Generator``
        or per-run :class:`~torchflow.core.random.TrialStreams`. ``mean``, ``cov`` (the runner's prior) are
        not used (new sources come from the birth density). ``progress``: called after each sensor."""
        self.model.check_measurements(observations, mask)
        check_generator(generator, "generator")
        W = mask.shape[-1]  # trimmed to the batch's last real column: one read, before the sensors
        M = int((mask.flatten(0, 1).any(0) * torch.arange(1, W + 1, device=mask.device)).max()) if mask.numel() else 0
        z, zm = observations[..., :M], mask[..., :M]
        state = self.init(z.shape[0], z.dtype, z.device)
        est, declared, underflow = [], [], []
        for s in range(z.shape[1]):  # sequential processing of the sensors
            state = self.update(state, z[:, s], zm[:, s], s, generator)
            pad = (0, self.max_objects - state.mask.shape[1])  # a fixed number of slots in the results
            est.append(F.pad(state.positions, (0, 0, *pad)))
            declared.append(F.pad(state.mask & (state.existence > self.declare), pad))
            underflow.append(F.pad(state.underflow, (0, observations.shape[-1] - M)))
            if progress is not None:
                progress()
        return Localisation(torch.stack(est, 1), torch.stack(declared, 1), torch.stack(underflow, 1), state)

    def init(self, batch_size: int, dtype=torch.float64, device=None) -> POState:  # no PO before the first sensor
        e = torch.zeros(batch_size, 0, dtype=dtype, device=device)
        n = self.G if self.mixture else self.n_particles
        return POState(
            e,
            e.bool(),
            e.new_zeros(batch_size, 0, n),
            e.new_zeros(batch_size, 0, n, 3),
            e.new_zeros(batch_size, 0, n, 3, 3) if self.mixture else None,
        )

    def _bp(self, state: POState, log_Ik, log_Ib, z_mask, sensor):
        """Loopy BP from the integrals ``log int f_k l_m (B, K, M)`` of the legacy POs and ``log int
        f_b l_m (B, M)`` of the birth density; returns the association, ``log nu (B, K, M)`` (-inf
        off the live pairs), ``log(mu_c f_c)`` and the underflow ``(B, M)``: the live measurements
        whose every BP term ``exp(log I - log(mu_c f_c))`` is 0 in floating point, under the birth
        density and every live PO (the log-space integrals themselves stay finite)."""
        model, r, pd, dt = self.model, state.existence, self.model.p_d, log_Ib.dtype
        log_cf = math.log(model.clutter_rate) + model.clutter_log_density(sensor).to(dt)  # log(mu_c f_c)
        ratio_k, ratio_b = torch.exp(log_Ik - log_cf), torch.exp(log_Ib - log_cf)
        beta = torch.cat([(1 - r * pd).unsqueeze(-1), (r * pd).unsqueeze(-1) * ratio_k], -1)
        assoc = loopy_association(beta, 1 + self.birth_rate * ratio_b, state.mask, z_mask, self.bp_iterations)
        live = state.mask.unsqueeze(-1) & z_mask.unsqueeze(-2)  # (B, K, M)
        log_nu = torch.where(live, torch.log(assoc.nu.clamp_min(torch.finfo(dt).tiny)), log_Ib.new_tensor(-math.inf))
        underflow = z_mask & (ratio_b == 0) & ((ratio_k == 0) | ~state.mask.unsqueeze(-1)).all(1)
        return assoc, log_nu, log_cf, underflow


def sensor_measurement(model: TDOA3D, z: torch.Tensor, sensor) -> GaussianMeasurement:
    """The flows' measurement term of sensor ``sensor``'s scalar TDOAs ``z (R,)``, one per batch
    row: ``h`` the model's TDOA of that sensor pair, its gradient, and ``R = sigma_v^2``."""

    def linearise(points, support=False, scale=None):
        h, H = model.measure(points, sensor).unsqueeze(-1), model.jacobian(points, sensor).unsqueeze(-2)
        return (h, H) if scale is None else (h * scale, H * scale)

    return GaussianMeasurement(
        z.reshape(-1, 1),
        linearise,
        lambda points: torch.full((1, 1), model.sigma_v, dtype=points.dtype, device=points.device),
        "scalar",
    )


def birth_mixture(region: float, per_axis: int, sd_factor: float = 0.5, dtype=torch.float64, device=None):
    """A grid of ``per_axis^3`` equal-weight Gaussians covering ``[-region, region]^3``: cell centres,
    isotropic standard deviation ``sd_factor`` times the cell width. Returns ``(means (Nb, 3),
    scale_tril (3, 3))``."""
    w = 2 * region / per_axis
    c = -region + w * (torch.arange(per_axis, dtype=dtype, device=device) + 0.5)
    grid = torch.stack(torch.meshgrid(c, c, c, indexing="ij"), -1).reshape(-1, 3)
    return grid, torch.eye(3, dtype=dtype, device=device) * (sd_factor * w)


class FlowMixtureLocaliser(_Localiser):
    """BP localisation with flowed-mixture importance sampling (module docstring).

    Args:
        method: ``"pfi_d"`` (EDH), ``"pfi_s"`` (Gromov) or ``"pfi_os"`` (optimised diffusion).
        n_components: G per PO (seed: 100).
        samples_per_component: N_p per flowed component (seed: 5000).
        schedule: lambda grid (default :class:`~torchflow.flows.schedules.GeometricSchedule` ``(1e-5, 1.5)``).
        alpha, c_rule: PFI-OS: the objective weight and the reading of c*
            (:func:`~torchflow.flows.optimal_diffusion_scale`: ``"printed"`` (default, the paper's typeset formula),
            ``"literal_shift"`` or ``"printed_shift"``).
        birth_per_axis, birth_sd: the birth mixture (:func:`birth_mixture`; 5^3 = 125 components).
        jitter: relative diagonal jitter of the refitted covariances (of the component's prior scale).
        evaluate_at: ``"end"`` (default, ``lambda_l``) or ``"start"`` (``lambda_{l-1}``): where each
            lambda step takes its flow coefficients (:func:`~torchflow.flows.flow_gaussian`; the paper does not say).
        birth_rate, max_objects, prune, declare, bp_iterations, sample_chunk, name: :class:`_Localiser`.
    """

    mixture = True  # POs are Gaussian mixtures (with factors)

    def __init__(
        self,
        model: TDOA3D,
        method: str = "pfi_os",
        *,
        n_components: int = 100,
        samples_per_component: int = 5000,
        schedule: Optional[LambdaSchedule] = None,
        alpha: float = 0.1,
        c_rule: str = "printed",
        birth_rate: float = 0.01,
        birth_per_axis: int = 5,
        birth_sd: float = 0.5,
        max_objects: int = 30,
        prune: float = 1e-3,
        declare: float = 0.5,
        bp_iterations: int = 20,
        jitter: float = 1e-6,
        sample_chunk: int = 20_000_000,
        evaluate_at: str = "end",
        name: Optional[str] = None,
    ):
        super().__init__(
            model,
            birth_rate=birth_rate,
            max_objects=max_objects,
            prune=prune,
            declare=declare,
            bp_iterations=bp_iterations,
            sample_chunk=sample_chunk,
            name=name,
        )
        if method not in METHODS:
            raise ArgumentError(f"method: expected one of {METHODS}, got {method!r}")
        self.method = method
        self.flow = (
            EDHFlow()
            if method == "pfi_d"
            else GromovFlow(points="global")
            if method == "pfi_s"
            else OptimalDiffusionFlow(alpha=alpha, points="global", c_rule=c_rule)
        )
        self.schedule = resolve_schedule(schedule, GeometricSchedule(1e-5, 1.5))
        if len(self.schedule) < 1:
            raise ArgumentError("schedule: expected at least one pseudo-time step, got an empty schedule")
        self.proposal = FlowedMixtureProposal(self.flow, self.schedule, ratio="component", evaluate_at=evaluate_at)
        self.G = _count("n_components", n_components)
        self.n_samples = _count("samples_per_component", samples_per_component)
        bm, bL = birth_mixture(model.region, _count("birth_per_axis", birth_per_axis), birth_sd)
        self.register_buffer("birth_means", bm)
        self.register_buffer("birth_scale_tril", bL)
        self.jitter = float(jitter)

    @property
    def n_particles(self) -> int:  # samples per PO
        return self.G * self.n_samples

    # ---- one sensor --------------------------------------------------------------------------
    def _flowed_terms(self, means, L, z, s, generator):
        """For components ``means (B, K, G, 3)``, ``L (B, K, G, 3, 3)`` and measurements ``z (B, M)``:
        ``log int N_n l_m (B, K, G, M)`` and the candidates' moments (means and scale trils)."""
        model = self.model
        B, K, G, d = means.shape
        M = z.shape[1]
        R = K * G * M
        m0 = means.unsqueeze(3).expand(B, K, G, M, d).reshape(B, R, d)
        L0 = L.unsqueeze(3).expand(B, K, G, M, d, d).reshape(B, R, d, d)
        zr = z.reshape(B, 1, 1, M).expand(B, K, G, M).reshape(B, R)
        # every (component, measurement) row is one Gaussian of the flowed-mixture proposal, with the
        # per-component ratio (its own weight 1): omega = N(x; mu_n, P_n) l_m(x) / N(x; mu'_n, P'_n)
        mu1, P1 = self.proposal.flowed(m0, L0, sensor_measurement(model, zr.reshape(-1), s))
        L1 = linalg.safe_cholesky(P1)
        n = self.n_samples
        per = max(1, self.sample_chunk // max(1, B * n * d))
        log_I, pm, pc = [], [], []
        scale = L0.pow(2).sum((-2, -1)) / d  # tr(P0) / d per row
        eye = torch.eye(d, dtype=means.dtype, device=means.device)
        for a in range(0, R, per):  # memory chunks (see sample_chunk)
            sl = slice(a, min(R, a + per))
            r = sl.stop - a
            x, lo, _ = self.proposal.sample(
                means.new_zeros(B, r),
                m0[:, sl],
                L0[:, sl],
                mu1[:, sl],
                L1[:, sl],
                lambda x: model.log_likelihood(zr[:, sl].unsqueeze(-1), x, s),
                n,
                generator,
            )
            log_I.append(torch.logsumexp(lo, -1) - math.log(n))
            mean, cov = linalg.weighted_mean_cov(x.reshape(B * r, n, d), lo.reshape(B * r, n))
            pm.append(mean.reshape(B, r, d))
            pc.append(cov.reshape(B, r, d, d) + (self.jitter * scale[:, sl])[..., None, None] * eye)
        shape = (B, K, G, M)
        return (
            torch.cat(log_I, 1).reshape(shape),
            torch.cat(pm, 1).reshape(*shape, d),
            linalg.safe_cholesky(torch.cat(pc, 1)).reshape(*shape, d, d),
        )

    def update(self, state: POState, z: torch.Tensor, z_mask: torch.Tensor, sensor: int, generator) -> POState:
        """Process the measurements ``z (B, M)`` (real where ``z_mask``) of sensor ``sensor``."""
        G, pd = self.G, self.model.p_d
        B, M = z.shape
        dt, dev = z.dtype, z.device
        K = state.existence.shape[1]
        # birth: the new PO of every measurement
        bm, bL = self.birth_means.to(dt), self.birth_scale_tril.to(dt)
        Nb = bm.shape[0]
        b_logw = torch.full((B, 1, Nb), -math.log(Nb), dtype=dt, device=dev)
        bI, b_mean, b_L = self._flowed_terms(bm.expand(B, 1, Nb, 3), bL.expand(B, 1, Nb, 3, 3), z, sensor, generator)
        log_Ib = torch.logsumexp(b_logw.unsqueeze(-1) + bI, 2)[:, 0]  # (B, M)
        log_Ik = torch.zeros(B, 0, M, dtype=dt, device=dev)
        if K:
            I, p_mean, p_L = self._flowed_terms(state.means, state.scale_trils, z, sensor, generator)
            log_Ik = torch.logsumexp(state.log_weights.unsqueeze(-1) + I, 2)  # (B, K, M)
        assoc, log_nu, log_cf, underflow = self._bp(state, log_Ik, log_Ib, z_mask, sensor)
        r_all, mask, parts = assoc.new_existence, z_mask, []
        if K:  # legacy POs: "missed" plus one candidate per component and measurement, reduced to G
            missed = state.log_weights + (math.log(1 - pd) if pd < 1 else float("-inf"))
            hit = state.log_weights.unsqueeze(-1) + math.log(pd) + log_nu.unsqueeze(2) - log_cf + I  # (B,K,G,M)
            cand_w = torch.cat([missed, hit.reshape(B, K, G * M)], -1)
            cand_m = torch.cat([state.means, p_mean.reshape(B, K, G * M, 3)], 2)
            cand_L = torch.cat([state.scale_trils, p_L.reshape(B, K, G * M, 3, 3)], 2)
            r_all = torch.cat([_legacy_existence(state.existence, torch.logsumexp(cand_w, -1)), r_all], 1)
            mask = torch.cat([state.mask, z_mask], 1)
            parts = _reduce(cand_w, cand_m, cand_L, G, generator)
        # new POs: the birth candidates of each measurement, reduced to G
        nb_w = (b_logw[:, 0].unsqueeze(-1) + bI[:, 0]).transpose(1, 2)  # (B, M, Nb)
        new = _reduce(nb_w, b_mean[:, 0].transpose(1, 2), b_L[:, 0].transpose(1, 2), G, generator)
        parts = [torch.cat([a, b], 1) for a, b in zip(parts, new)] if K else list(new)
        return POState(*_prune_and_cap(r_all, mask, parts, self.prune, self.max_objects), underflow=underflow)

    def extra_repr(self) -> str:
        return (
            f"method={self.method!r}, n_components={self.G}, samples_per_component={self.n_samples}, "
            f"schedule={self.schedule!r}"
        )


def _prune_and_cap(r, mask, parts, prune: float, max_objects: int):
    """``(r, mask, *parts)`` of the ``max_objects`` most likely POs with existence >= ``prune``."""
    B = r.shape[0]
    mask = mask & (r >= prune)  # a nan existence is dropped too
    r = torch.where(mask, r, torch.zeros_like(r))
    keep = min(max_objects, r.shape[1])
    top = torch.where(mask, r, torch.full_like(r, -1.0)).topk(keep, dim=1).indices  # (B, keep)

    def g(t):
        return t.gather(1, top.reshape(B, keep, *([1] * (t.dim() - 2))).expand(B, keep, *t.shape[2:]))

    return (g(r), g(mask), *(g(t) for t in parts))


class BootstrapLocaliser(_Localiser):
    """The bootstrap baseline of Zhang et al. 2024 (``BS``): each PO is a set of ``n_particles`` N_p
    (the paper: 2e6 and 4e7); the proposal is the previous posterior (static sources), the weights the BP-weighted
    likelihood terms, and each PO is resampled (systematic). New POs start uniform in the region.
    The other arguments: :class:`_Localiser`."""

    method, mixture = "bs", False  # POs are particle sets

    def __init__(
        self,
        model: TDOA3D,
        *,
        n_particles: int = 100_000,
        birth_rate: float = 0.01,
        max_objects: int = 30,
        prune: float = 1e-3,
        declare: float = 0.5,
        bp_iterations: int = 20,
        sample_chunk: int = 20_000_000,
        name: Optional[str] = None,
    ):
        super().__init__(
            model,
            birth_rate=birth_rate,
            max_objects=max_objects,
            prune=prune,
            declare=declare,
            bp_iterations=bp_iterations,
            sample_chunk=sample_chunk,
            name=name,
        )
        self.n_particles = _count("n_particles", n_particles)

    def _loglik(self, x, z, s, own: bool = False):
        """``log l_m(x) (B, K, N, M)`` of particles ``x (B, K, N, 3)``, measurements ``z (B, M)``, in chunks;
        with ``own`` (K = M: one set per measurement) ``(B, M, N)``."""
        B, K, N, _ = x.shape
        M = z.shape[1]
        per = max(1, self.sample_chunk // max(1, B * K * (1 if own else M) * 3))
        zz = z.reshape(B, M, 1) if own else z.reshape(B, 1, 1, M)
        out = [
            self.model.log_likelihood(zz, x[:, :, a : a + per] if own else x[:, :, a : a + per].unsqueeze(-2), s)
            for a in range(0, N, per)
        ]
        return torch.cat(out, 2)

    def update(self, state: POState, z, z_mask, sensor, generator) -> POState:
        """Process the measurements ``z (B, M)`` (real where ``z_mask``) of sensor ``sensor``."""
        B, M = z.shape
        dt, dev = z.dtype, z.device
        N, K, pd = self.n_particles, state.existence.shape[1], self.model.p_d
        xb = (uniform((B, M, N, 3), dtype=dt, device=dev, generator=generator) * 2 - 1) * self.model.region
        llb = self._loglik(xb, z, sensor, own=True)  # (B, M, N): each new PO against its own measurement
        log_Ib = torch.logsumexp(llb, -1) - math.log(N)
        ll = self._loglik(state.means, z, sensor) if K else torch.zeros(B, 0, N, M, dtype=dt, device=dev)
        log_Ik = torch.logsumexp(state.log_weights.unsqueeze(-1) + ll, 2)  # (B, K, M)
        assoc, log_nu, log_cf, underflow = self._bp(state, log_Ik, log_Ib, z_mask, sensor)
        terms = torch.cat(
            [
                torch.full((B, K, N, 1), math.log(1 - pd) if pd < 1 else float("-inf"), dtype=dt, device=dev),
                math.log(pd) + log_nu.unsqueeze(2) - log_cf + ll,
            ],
            -1,
        )
        lw = state.log_weights + torch.logsumexp(terms, -1)  # (B, K, N)
        r_all = torch.cat([_legacy_existence(state.existence, torch.logsumexp(lw, -1)), assoc.new_existence], 1)
        leg = state.means.gather(2, _resample(lw, generator).unsqueeze(-1).expand(B, K, N, 3))
        new = xb.gather(2, _resample(llb, generator).unsqueeze(-1).expand(B, M, N, 3))
        flat = torch.full((B, K + M, N), -math.log(N), dtype=dt, device=dev)
        r2, m2, lw2, x2 = _prune_and_cap(
            r_all, torch.cat([state.mask, z_mask], 1), [flat, torch.cat([leg, new], 1)], self.prune, self.max_objects
        )
        return POState(r2, m2, lw2, x2, underflow=underflow)  # particles in ``means``, no factors

    def extra_repr(self) -> str:
        return f"n_particles={self.n_particles}"


def _resample(log_w: torch.Tensor, generator) -> torch.Tensor:
    """Systematic resampling indices ``(B, K, N)`` of every PO's particles, ``log_w (B, K, N)``; a PO
    with no positive (or a NaN) weight resamples uniformly."""
    B, K, N = log_w.shape
    lw = log_w.reshape(B * K, N)
    ok = torch.isfinite(lw).any(-1, keepdim=True) & ~(torch.isnan(lw) | torch.isposinf(lw)).any(-1, keepdim=True)
    return systematic(torch.where(ok, lw, torch.zeros_like(lw)), generator, validate=False).reshape(B, K, N)


def _legacy_existence(r: torch.Tensor, log_C: torch.Tensor) -> torch.Tensor:
    """Updated existence ``r C / (r C + 1 - r)`` of legacy POs; 0, not 0/0, when ``r = 1`` and ``C = 0``."""
    rc = r * log_C.exp()
    return torch.where(rc > 0, rc / (rc + 1 - r), torch.zeros_like(rc))


def _reduce(log_w: torch.Tensor, means: torch.Tensor, L: torch.Tensor, n: int, generator):
    """Keep ``n`` of the candidate components ``(B, K, C)`` by systematic resampling of their indices
    (one uniform per PO; no positive weight: uniform; C = G (1 + M) or 125 candidates, so not
    :func:`torchflow.core.resampling.systematic`); returns ``(log_weights (B, K, n) equal, means, scale_trils)``."""
    B, K, C = log_w.shape
    w = torch.softmax(log_w, -1)
    cdf = torch.where(torch.isfinite(w).all(-1, keepdim=True), w, torch.full_like(w, 1.0 / C)).cumsum(-1)
    cdf = cdf / cdf[..., -1:].clamp_min(torch.finfo(w.dtype).tiny)
    u = uniform((B, K, 1), dtype=w.dtype, device=w.device, generator=generator)
    pos = (torch.arange(n, dtype=w.dtype, device=w.device) + u) / n
    idx = torch.searchsorted(cdf.contiguous(), pos.contiguous()).clamp(max=C - 1)  # (B, K, n)
    gm = means.gather(2, idx.unsqueeze(-1).expand(B, K, n, means.shape[-1]))
    gL = L.gather(2, idx[..., None, None].expand(B, K, n, *L.shape[-2:]))
    return torch.full((B, K, n), -math.log(n), dtype=means.dtype, device=means.device), gm, gL


__all__ = ["FlowMixtureLocaliser", "BootstrapLocaliser", "POState", "Localisation", "birth_mixture", "METHODS"]
