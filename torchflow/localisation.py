"""Multi-source localisation from TDOAs with belief propagation and flow-induced Gaussian-mixture
importance sampling (seed 002: Zhang, Khojasteh, Atanasov & Meyer 2024; MODELS.md §12).

The sensors (receiver pairs) are processed one after another (the posterior after sensor s - 1 is
the prior of sensor s; the sources are static). The belief is a set of potential objects (POs),
each with an existence probability ``r_k`` and a Gaussian mixture of G components. For sensor s:

1. every component of every PO is flowed by every measurement (:func:`~torchflow.flows.flow_gaussian`
   with PFI-D = EDH, PFI-S = Gromov or PFI-OS = optimised diffusion), and N_p samples are drawn from
   each flowed component; the per-component importance ratio
   ``N(x; mu_n, P_n) l_m(x) / N(x; mu'_nm, P'_nm)`` gives ``int f_k l_m`` (unbiased) and each
   candidate component's weighted moments;
2. the same for a birth mixture (a grid of Gaussians covering the region; UNCONF: the seed's birth
   density is uniform, approximated here by that mixture);
3. loopy BP (:func:`~torchflow.association.loopy_association`) gives the association messages;
4. each legacy PO's candidates (its components times "missed", plus one per component and
   measurement) are weighted by the BP messages and reduced back to G components by systematic
   resampling of candidate indices (weights reset to equal; UNCONF §12.3); its existence is
   ``r C / (r C + 1 - r)``; each measurement makes a new PO the same way from the birth mixture;
5. POs with existence below ``prune`` are dropped and at most ``max_objects`` are kept (the most
   likely; a fixed size keeps every tensor shape static, with no host synchronisation).

Declared sources: POs with existence above ``declare`` (0.5), at their mixture mean. Everything is
batched over runs x POs x components x measurements x samples (in memory-bounded chunks of
``sample_chunk`` numbers); the loop over sensors is the sequential processing itself.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Optional

import torch
from torch import nn

from . import linalg
from .association import loopy_association
from .flows import EDHFlow, GromovFlow, OptimalDiffusionFlow
from .proposals import FlowedMixtureProposal
from .models.tdoa import TDOA3D
from .random import check_generator, uniform
from .schedules import GeometricSchedule, LambdaSchedule

METHODS = ("pfi_d", "pfi_s", "pfi_os")


@dataclass
class POState:
    """Potential objects after a sensor.

    Attributes:
        existence: ``(B, K)`` existence probabilities (0 for empty slots).
        mask: ``(B, K)`` bool, the live POs.
        log_weights: ``(B, K, G)`` normalised log weights of the components (or particles).
        means: ``(B, K, G, 3)`` component means (:class:`FlowMixtureLocaliser`) or particles
            (:class:`BootstrapLocaliser`).
        scale_trils: ``(B, K, G, 3, 3)`` component factors, ``None`` for particles.
        underflow: ``(B, M)`` bool after an update: the live measurements of that sensor whose
            BP terms all underflowed to 0, under every PO and the birth density (each such
            measurement acts as clutter; :func:`_underflow`). ``None`` before the first sensor.
    """

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
    """Result of :meth:`FlowMixtureLocaliser.forward`: the declared sources ``positions (B, K, 3)``
    with ``declared (B, K)``, the final :class:`POState`, and ``underflow (B, S, M)``: the
    (run, sensor, measurement) triples at which every component's weight underflowed (the
    measurement was then treated as clutter, not turned into NaN)."""

    positions: torch.Tensor
    declared: torch.Tensor
    state: POState
    underflow: Optional[torch.Tensor] = None

    def underflow_report(self, run_offset: int = 0) -> list:
        """``"run b, sensor s, measurement m"`` strings of every underflow (reads the mask on the
        host: call it after the run, not inside one)."""
        if self.underflow is None:
            return []
        return [f"run {b + run_offset}, sensor {s}, measurement {m}"
                for b, s, m in torch.nonzero(self.underflow).tolist()]


def _check_common(model, **kw):
    if not isinstance(model, TDOA3D):
        raise TypeError(f"model: expected a torchflow TDOA3D, got {type(model).__name__}")
    if model.clutter_rate <= 0:
        raise ValueError(f"model.clutter_rate: BP divides by the clutter intensity; expected > 0, got "
                         f"{model.clutter_rate}")
    for name in ("n_components", "samples_per_component", "n_particles", "birth_per_axis", "max_objects",
                 "bp_iterations", "sample_chunk"):
        v = kw.get(name, 1)
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"{name}: expected a positive integer, got {v!r}")
    for name in ("prune", "declare"):
        v = kw.get(name, 0.0)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= float(v) < 1.0:
            raise ValueError(f"{name}: expected a probability in [0, 1), got {v!r}")
    v = kw.get("birth_rate", 1.0)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not float(v) > 0:
        raise ValueError(f"birth_rate: expected > 0, got {v!r}")


def _forward(self, z: torch.Tensor, mask: torch.Tensor, generator) -> "Localisation":
    """Localise from measurements ``z (B, S, M)`` with ``mask`` (:class:`~torchflow.models.TDOAData`),
    processing the sensors in order; ``generator``: a ``torch.Generator`` or per-run
    :class:`~torchflow.random.TrialStreams`."""
    self.model.check_measurements(z, mask)
    check_generator(generator, "generator")
    state = self.init(z.shape[0], z.dtype, z.device)
    underflow = []
    for s in range(z.shape[1]):  # sequential processing of the sensors
        state = self.update(state, z[:, s], mask[:, s], s, generator)
        underflow.append(state.underflow)
    declared = state.mask & (state.existence > self.declare)
    return Localisation(state.positions, declared, state, torch.stack(underflow, 1) if underflow else None)


def _underflow(log_Ib: torch.Tensor, log_Ik: torch.Tensor, log_cf, po_mask: torch.Tensor, z_mask: torch.Tensor):
    """``(B, M)``: live measurements whose every BP term underflows to 0, i.e. the estimated integral
    of the likelihood over clutter intensity, ``exp(log I - log(mu_c f_c))``, is 0 in floating point
    under the birth density (``log_Ib (B, M)``) and under every live PO (``log_Ik (B, K, M)``); the
    log-space integrals themselves stay finite."""
    dead = (torch.exp(log_Ik - log_cf) == 0) | ~po_mask.unsqueeze(-1)
    return z_mask & (torch.exp(log_Ib - log_cf) == 0) & dead.all(1)


def birth_mixture(region: float, per_axis: int, sd_factor: float = 0.5, dtype=torch.float64, device=None):
    """A grid of ``per_axis^3`` equal-weight Gaussians covering ``[-region, region]^3``: cell centres,
    isotropic standard deviation ``sd_factor`` times the cell width. Returns ``(means (Nb, 3),
    scale_tril (3, 3))``."""
    w = 2 * region / per_axis
    c = -region + w * (torch.arange(per_axis, dtype=dtype, device=device) + 0.5)
    grid = torch.stack(torch.meshgrid(c, c, c, indexing="ij"), -1).reshape(-1, 3)
    return grid, torch.eye(3, dtype=dtype, device=device) * (sd_factor * w)


class FlowMixtureLocaliser(nn.Module):
    """BP localisation with flowed-mixture importance sampling (module docstring).

    Args:
        model: :class:`~torchflow.models.TDOA3D` (``clutter_rate > 0``).
        method: ``"pfi_d"`` (EDH), ``"pfi_s"`` (Gromov) or ``"pfi_os"`` (optimised diffusion).
        n_components: G per PO (seed: 100).
        samples_per_component: N_p per flowed component (seed: 5000).
        schedule: lambda grid (default :class:`~torchflow.schedules.GeometricSchedule` ``(1e-5, 1.5)``).
        alpha, c_rule: PFI-OS: the objective weight and the reading of c*
            (:func:`~torchflow.flows.optimal_diffusion_scale`: ``"printed"`` (default, MODELS.md §12.1),
            ``"literal_shift"`` or ``"printed_shift"``).
        birth_rate: mean number of new sources per measurement, mu_b (UNCONF 0.01).
        birth_per_axis, birth_sd: the birth mixture (:func:`birth_mixture`; 5^3 = 125 components).
        max_objects: POs kept after each sensor.
        prune: existence below which a PO is dropped (1e-3).
        declare: existence above which a PO is a declared source (0.5).
        bp_iterations: message passes (20).
        jitter: relative diagonal jitter of the refitted covariances (of the component's prior scale).
        evaluate_at: ``"end"`` (default, ``lambda_l``) or ``"start"`` (``lambda_{l-1}``): where each
            lambda step takes its flow coefficients (:func:`~torchflow.flows.flow_gaussian`, UNCONF).
        name: label in results (default: the class name).
        sample_chunk: numbers drawn per pass (memory bound). Draws are made per pass, so with the
            numpy back end of per-trial streams (which splits draws above 2^18 numbers) results
            can depend on it; keep it fixed to compare runs.
    """

    def __init__(self, model: TDOA3D, method: str = "pfi_os", *, n_components: int = 100,
                 samples_per_component: int = 5000, schedule: Optional[LambdaSchedule] = None, alpha: float = 0.1,
                 c_rule: str = "printed", birth_rate: float = 0.01, birth_per_axis: int = 5, birth_sd: float = 0.5,
                 max_objects: int = 30, prune: float = 1e-3, declare: float = 0.5, bp_iterations: int = 20,
                 jitter: float = 1e-6, sample_chunk: int = 20_000_000, evaluate_at: str = "end",
                 name: Optional[str] = None):
        super().__init__()
        self.name = name or type(self).__name__
        _check_common(model, n_components=n_components, samples_per_component=samples_per_component,
                      birth_per_axis=birth_per_axis, max_objects=max_objects, bp_iterations=bp_iterations,
                      sample_chunk=sample_chunk, prune=prune, declare=declare, birth_rate=birth_rate)
        if method not in METHODS:
            raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
        self.model, self.method = model, method
        if method == "pfi_d":
            self.flow = EDHFlow()
        elif method == "pfi_s":
            self.flow = GromovFlow(points="global")
        else:
            self.flow = OptimalDiffusionFlow(alpha=alpha, points="global", c_rule=c_rule)
        self.schedule = schedule or GeometricSchedule(1e-5, 1.5)
        if len(self.schedule) < 1:
            raise ValueError("schedule: expected at least one pseudo-time step, got an empty schedule")
        self.proposal = FlowedMixtureProposal(self.flow, self.schedule, ratio="component", evaluate_at=evaluate_at)
        bm, bL = birth_mixture(model.region, birth_per_axis, birth_sd)
        self.register_buffer("birth_means", bm)
        self.register_buffer("birth_scale_tril", bL)
        self.G, self.n_samples = n_components, samples_per_component
        self.birth_rate, self.birth_per_axis, self.birth_sd = float(birth_rate), birth_per_axis, float(birth_sd)
        self.max_objects, self.prune, self.declare = max_objects, float(prune), float(declare)
        self.bp_iterations, self.jitter, self.sample_chunk = bp_iterations, float(jitter), sample_chunk

    # ---- one sensor --------------------------------------------------------------------------
    def _flowed_terms(self, log_w, means, L, z, s, generator):
        """For mixtures ``(B, K, G)`` and measurements ``z (B, M)``: ``log int N_n l_m`` per
        component and measurement ``(B, K, G, M)`` and the candidates' weighted moments
        ``(B, K, G, M, 3)``, ``(B, K, G, M, 3, 3)`` (scale trils)."""
        model = self.model
        B, K, G, d = means.shape
        M = z.shape[1]
        R = K * G * M
        m0 = means.unsqueeze(3).expand(B, K, G, M, d).reshape(B, R, d)
        L0 = L.unsqueeze(3).expand(B, K, G, M, d, d).reshape(B, R, d, d)
        zr = z.reshape(B, 1, 1, M).expand(B, K, G, M).reshape(B, R)
        # every (component, measurement) row is one Gaussian of the flowed-mixture proposal, with the
        # per-component ratio (its own weight 1): omega = N(x; mu_n, P_n) l_m(x) / N(x; mu'_n, P'_n)
        mu1, P1 = self.proposal.flowed(m0, L0, model.gaussian_measurement(zr.reshape(-1), s))
        L1 = linalg.safe_cholesky(P1)
        n = self.n_samples
        per = max(1, self.sample_chunk // max(1, B * n * d))
        log_I, pm, pc = [], [], []
        scale = L0.pow(2).sum((-2, -1)) / d  # tr(P0) / d per row
        eye = torch.eye(d, dtype=means.dtype, device=means.device)
        for a in range(0, R, per):  # memory chunks (see sample_chunk)
            sl = slice(a, min(R, a + per))
            r = sl.stop - a
            x, lo, _ = self.proposal.sample(means.new_zeros(B, r), m0[:, sl], L0[:, sl], mu1[:, sl], L1[:, sl],
                                            lambda x: model.log_likelihood(zr[:, sl].unsqueeze(-1), x, s), n,
                                            generator)
            log_I.append(torch.logsumexp(lo, -1) - math.log(n))
            mean, cov = linalg.weighted_mean_cov(x.reshape(B * r, n, d), lo.reshape(B * r, n))
            pm.append(mean.reshape(B, r, d))
            pc.append(cov.reshape(B, r, d, d) + (self.jitter * scale[:, sl])[..., None, None] * eye)
        shape = (B, K, G, M)
        return (torch.cat(log_I, 1).reshape(shape), torch.cat(pm, 1).reshape(*shape, d),
                linalg.safe_cholesky(torch.cat(pc, 1)).reshape(*shape, d, d))

    def update(self, state: POState, z: torch.Tensor, z_mask: torch.Tensor, sensor: int, generator) -> POState:
        """Process the measurements ``z (B, M)`` (real where ``z_mask``) of sensor ``sensor``."""
        model, G = self.model, self.G
        B, M = z.shape
        dt, dev = z.dtype, z.device
        K = state.existence.shape[1]
        pd = model.p_d
        log_cf = math.log(model.clutter_rate) + model.clutter_log_density(sensor).to(dt)  # log(mu_c f_c)
        neg = torch.tensor(float("-inf"), dtype=dt, device=dev)
        # birth: the new PO of every measurement
        bm, bL = self.birth_means.to(dt), self.birth_scale_tril.to(dt)
        Nb = bm.shape[0]
        b_logw = torch.full((B, 1, Nb), -math.log(Nb), dtype=dt, device=dev)
        bI, b_mean, b_L = self._flowed_terms(b_logw, bm.expand(B, 1, Nb, 3), bL.expand(B, 1, Nb, 3, 3), z, sensor,
                                             generator)
        log_Ib = torch.logsumexp(b_logw.unsqueeze(-1) + bI, 2)[:, 0]  # (B, M)
        if K:
            I, p_mean, p_L = self._flowed_terms(state.log_weights, state.means, state.scale_trils, z, sensor,
                                                generator)
            log_Ik = torch.logsumexp(state.log_weights.unsqueeze(-1) + I, 2)  # (B, K, M)
        else:
            log_Ik = torch.zeros(B, 0, M, dtype=dt, device=dev)
        beta, xi = _bp_terms(model, state.existence, log_Ik, log_Ib, log_cf, self.birth_rate)
        assoc = loopy_association(beta, xi, state.mask, z_mask, self.bp_iterations)
        # legacy POs: "missed" plus one candidate per component and measurement, reduced to G
        if K:
            live = state.mask.unsqueeze(-1) & z_mask.unsqueeze(-2)  # (B, K, M)
            log_nu = torch.where(live, torch.log(assoc.nu.clamp_min(torch.finfo(dt).tiny)), neg)
            missed = state.log_weights + (math.log(1 - pd) if pd < 1 else float("-inf"))
            hit = (state.log_weights.unsqueeze(-1) + math.log(pd) + log_nu.unsqueeze(2) - log_cf + I)  # (B,K,G,M)
            cand_w = torch.cat([missed, hit.reshape(B, K, G * M)], -1)
            cand_m = torch.cat([state.means, p_mean.reshape(B, K, G * M, 3)], 2)
            cand_L = torch.cat([state.scale_trils, p_L.reshape(B, K, G * M, 3, 3)], 2)
            log_C = torch.logsumexp(cand_w, -1)  # log C_k
            r = state.existence
            r_leg = _legacy_existence(r, log_C)
            leg = _reduce(cand_w, cand_m, cand_L, G, generator)
        # new POs: the birth candidates of each measurement, reduced to G
        nb_w = (b_logw[:, 0].unsqueeze(-1) + bI[:, 0]).transpose(1, 2)  # (B, M, Nb)
        new = _reduce(nb_w, b_mean[:, 0].transpose(1, 2), b_L[:, 0].transpose(1, 2), G, generator)
        r_new = assoc.new_existence
        if K:
            r_all = torch.cat([r_leg, r_new], 1)
            mask = torch.cat([state.mask, z_mask], 1)
            parts = [torch.cat([a, b], 1) for a, b in zip(leg, new)]
        else:
            r_all, mask, parts = r_new, z_mask, list(new)
        return POState(*_prune_and_cap(r_all, mask, parts, self.prune, self.max_objects),
                       underflow=_underflow(log_Ib, log_Ik, log_cf, state.mask, z_mask))

    # ---- whole scene -------------------------------------------------------------------------
    def init(self, batch_size: int, dtype=torch.float64, device=None) -> POState:
        """No PO before the first sensor."""
        B, G = batch_size, self.G
        z = torch.zeros(B, 0, dtype=dtype, device=device)
        return POState(z, z.bool(), torch.zeros(B, 0, G, dtype=dtype, device=device),
                       torch.zeros(B, 0, G, 3, dtype=dtype, device=device),
                       torch.zeros(B, 0, G, 3, 3, dtype=dtype, device=device))

    forward = _forward

    def extra_repr(self) -> str:
        return (f"method={self.method!r}, n_components={self.G}, samples_per_component={self.n_samples}, "
                f"schedule={self.schedule!r}")


LOCALISATION_COLUMNS = ["filter", "n_particles", "trials", "ospa", "ospa_se", "declared", "true_sources",
                        "sec_per_run", "underflows", "error"]


def run_localisation(model: TDOA3D, localisers, *, runs: int = 10, seed: int = 0, ospa_cutoff: float = 30.0,
                     ospa_order: float = 1.0, device="cpu", dtype="float64", rng_backend: str = "auto",
                     progress: bool = True, on_filter_done=None):
    """Simulate ``runs`` scenes once and localise them with every localiser (seed 002's tables).

    The scenes are simulated together from ``seed`` (as the state-space runner simulates its
    trajectories), so scene b depends on ``runs``. Each run is then localised alone, trimmed to its
    own largest number of measurements per sensor, with its own random stream
    (:class:`~torchflow.random.TrialStreams` keyed by seed, run and method): given the scenes, a
    run's result does not depend on the other runs.
    A localiser that raises does not stop the others: its row gets the error. Ctrl-C or SIGTERM
    (with :data:`~torchflow.experiment.STOP`'s handler installed, as ``experiments/run.py`` does)
    stops the run at once; the finished runs keep their rows, the interrupted localiser's summary
    row covers them (``trials`` = runs finished) with the error "interrupted after n of N runs",
    and later localisers get "not run: interrupted".

    Returns:
        ``(summary, per_run, data, examples)``: summary rows (:data:`LOCALISATION_COLUMNS`), one row
        per localiser and run (``ospa``, ``declared``, ``sec``), the simulated :class:`TDOAData`
        (CPU) and run 0's declared positions per localiser.
    """
    import time

    from .experiment import STOP, resolve_device, resolve_dtype
    from .metrics import ospa as ospa_metric
    from .random import TrialStreams

    dev, dt = resolve_device(device), resolve_dtype(dtype)
    model.to(device=dev, dtype=dt)
    data = model.simulate(int(runs), torch.Generator(device=dev).manual_seed(int(seed)))
    counts = data.mask.sum(-1).amax(-1).tolist()  # per run: its own padding (one read, before any localiser)
    summary, per_run, examples = [], [], {}
    try:
        from tqdm.auto import tqdm
    except ImportError:  # pragma: no cover
        tqdm = None
    interrupted = False
    for name, loc in localisers.items():
        row = {c: None for c in LOCALISATION_COLUMNS}
        if interrupted:  # an earlier localiser was interrupted: this one does not start
            row.update(filter=name, trials=0, true_sources=model.n_sources, error="not run: interrupted")
            summary.append(row)
            continue
        loc.to(device=dev, dtype=dt)
        row.update(filter=name, trials=runs, true_sources=model.n_sources,
                   n_particles=getattr(loc, "n_particles", None) or loc.G * loc.n_samples)
        bar = tqdm(total=runs, unit="run", leave=False, desc=name) if progress and tqdm is not None else None
        vals, decl, secs, under = [], [], [], []
        try:
            with torch.no_grad():
                for b in range(runs):
                    STOP.check()  # Ctrl-C / SIGTERM between runs (experiments/run.py installs the handler)
                    M = int(counts[b])
                    z, mask = data.z[b:b + 1, :, :M], data.mask[b:b + 1, :, :M]
                    g = TrialStreams(seed, [b], key=f"localise_{loc.method}", backend=rng_backend)
                    if dev.type == "cuda":
                        torch.cuda.synchronize()
                    t0 = time.perf_counter()
                    with STOP.interruptible():
                        res = loc(z, mask, g)
                    if dev.type == "cuda":
                        torch.cuda.synchronize()
                    secs.append(time.perf_counter() - t0)
                    o = ospa_metric(res.positions.unsqueeze(1).double(), data.sources[b:b + 1].unsqueeze(1).double(),
                                    cutoff=ospa_cutoff, order=ospa_order, X_mask=res.declared.unsqueeze(1))
                    vals.append(float(o))
                    decl.append(int(res.declared.sum()))
                    lost = res.underflow_report(run_offset=b)
                    if lost:
                        warnings.warn(f"{name}: every component's weight underflowed (measurement treated as "
                                      f"clutter) at " + "; ".join(lost), RuntimeWarning, stacklevel=2)
                    under.append(len(lost))
                    per_run.append({"filter": name, "trial": b, "ospa": vals[-1], "declared": decl[-1], "sec": secs[-1],
                                    "underflows": len(lost)})
                    if b == 0:
                        examples[name] = res.positions[0][res.declared[0]].cpu()
                    if bar is not None:
                        bar.update(1)
        except KeyboardInterrupt:  # keep the finished runs; the localisers after this one do not start
            interrupted = True
            row["error"] = f"interrupted after {len(vals)} of {runs} runs"
        except Exception as e:  # one failing localiser must not lose the others' results
            row["error"] = f"{type(e).__name__}: {e}"
        if bar is not None:
            bar.close()
        if vals:
            v = torch.tensor(vals, dtype=torch.float64)
            row.update(trials=len(vals), ospa=float(v.mean()),
                       ospa_se=float(v.std() / math.sqrt(len(vals))) if len(vals) > 1 else None, declared=sum(decl) / len(decl), sec_per_run=sum(secs) / len(secs), underflows=sum(under))
        summary.append(row)
        if on_filter_done is not None:
            on_filter_done(summary)
    cpu = type(data)(*(t.cpu() for t in (data.sources, data.z, data.mask, data.origin)))
    return summary, per_run, cpu, examples


def scene_figure(plt, model: TDOA3D, sources: torch.Tensor, examples: dict, title: str):
    """A 3-D picture of one run: receivers, true sources and every localiser's declared sources."""
    fig = plt.figure(figsize=(6.5, 5.5))
    ax = fig.add_subplot(projection="3d")
    rec = model.receivers.cpu()
    ax.scatter(*rec.T, marker="s", s=40, c="k", label="receivers")
    ax.scatter(*sources.T, marker="*", s=160, c="gold", edgecolors="k", label="true sources")
    marks = "o^vDs<>"
    for i, (name, pos) in enumerate(examples.items()):
        if len(pos):
            ax.scatter(*pos.T, marker=marks[i % len(marks)], s=50, facecolors="none", edgecolors=f"C{i}", label=name)
        else:
            ax.scatter([], [], [], marker=marks[i % len(marks)], label=f"{name} (none declared)")
    r = model.region
    ax.set_xlim(-r, r), ax.set_ylim(-r, r), ax.set_zlim(-r, r)
    ax.set_xlabel("x (m)"), ax.set_ylabel("y (m)"), ax.set_zlabel("z (m)")
    ax.legend(fontsize=7, loc="upper left")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return fig


def _prune_and_cap(r, mask, parts, prune: float, max_objects: int):
    """Drop POs with existence below ``prune`` and keep the ``max_objects`` most likely (a fixed
    number of slots: no host synchronisation). Returns ``(r, mask, *parts)`` gathered."""
    B = r.shape[0]
    mask = mask & (r >= prune)  # a nan existence is dropped too
    r = torch.where(mask, r, torch.zeros_like(r))
    keep = min(max_objects, r.shape[1])
    top = torch.where(mask, r, torch.full_like(r, -1.0)).topk(keep, dim=1).indices  # (B, keep)

    def g(t):
        return t.gather(1, top.reshape(B, keep, *([1] * (t.dim() - 2))).expand(B, keep, *t.shape[2:]))

    return (g(r), g(mask), *(g(t) for t in parts))


def _bp_terms(model, r, log_Ik, log_Ib, log_cf, birth_rate):
    """``beta (B, K, M + 1)`` and ``xi (B, M)`` from the integrals ``log int f_k l_m`` and
    ``log int f_b l_m``."""
    pd = model.p_d
    beta = torch.cat([(1 - r * pd).unsqueeze(-1), (r * pd).unsqueeze(-1) * torch.exp(log_Ik - log_cf)], -1)
    return beta, 1 + birth_rate * torch.exp(log_Ib - log_cf)


def _systematic_indices(log_w: torch.Tensor, n: int, generator) -> torch.Tensor:
    """``n`` indices per row of ``log_w (B, K, C)`` by systematic resampling (one uniform per row);
    a row with no positive weight resamples uniformly."""
    B, K, C = log_w.shape
    w = torch.softmax(log_w, -1)
    w = torch.where(torch.isfinite(w).all(-1, keepdim=True), w, torch.full_like(w, 1.0 / C))
    cdf = w.cumsum(-1)
    cdf = cdf / cdf[..., -1:].clamp_min(torch.finfo(w.dtype).tiny)
    u = uniform((B, K, 1), dtype=w.dtype, device=w.device, generator=generator)
    pos = (torch.arange(n, dtype=w.dtype, device=w.device) + u) / n
    return torch.searchsorted(cdf.contiguous(), pos.contiguous()).clamp(max=C - 1)  # (B, K, n)


class BootstrapLocaliser(nn.Module):
    """The bootstrap baseline of seed 002 (``BS``): each PO is a plain set of N_p particles; for
    each sensor the proposal is the previous posterior itself (the sources are static), the
    weights are the BP-weighted likelihood terms, and each PO is resampled (systematic). New POs
    start from N_p particles uniform in the region. The same BP, pruning and declaration as
    :class:`FlowMixtureLocaliser`; likelihoods are evaluated in chunks of ``sample_chunk`` numbers.

    Args:
        model: :class:`~torchflow.models.TDOA3D` (``clutter_rate > 0``).
        n_particles: N_p per PO (seed: 2e6 and 4e7).
        birth_rate, max_objects, prune, declare, bp_iterations, sample_chunk: as
            :class:`FlowMixtureLocaliser`.
    """

    method = "bs"

    def __init__(self, model: TDOA3D, *, n_particles: int = 100_000, birth_rate: float = 0.01, max_objects: int = 30,
                 prune: float = 1e-3, declare: float = 0.5, bp_iterations: int = 20, sample_chunk: int = 20_000_000,
                 name: Optional[str] = None):
        super().__init__()
        self.name = name or type(self).__name__
        _check_common(model, n_particles=n_particles, max_objects=max_objects, bp_iterations=bp_iterations,
                      sample_chunk=sample_chunk, prune=prune, declare=declare, birth_rate=birth_rate)
        self.model, self.n_particles = model, n_particles
        self.birth_rate, self.max_objects, self.prune, self.declare = float(birth_rate), max_objects, float(prune), \
            float(declare)
        self.bp_iterations, self.sample_chunk = bp_iterations, sample_chunk

    def _loglik(self, x, z, s, own: bool = False):
        """``log l_m(x)`` of particles ``x (B, K, N, 3)`` for measurements ``z (B, M)`` ->
        ``(B, K, N, M)``, or with ``own`` (K = M: one set per measurement) ``(B, M, N)``, in
        chunks of particles."""
        B, K, N, _ = x.shape
        M = z.shape[1]
        per = max(1, self.sample_chunk // max(1, B * K * (1 if own else M) * 3))
        zz = z.reshape(B, M, 1) if own else z.reshape(B, 1, 1, M)
        out = [self.model.log_likelihood(zz, x[:, :, a:a + per] if own else x[:, :, a:a + per].unsqueeze(-2), s)
               for a in range(0, N, per)]
        return torch.cat(out, 2)

    def update(self, state: "POState", z, z_mask, sensor, generator) -> "POState":
        model = self.model
        B, M = z.shape
        dt, dev = z.dtype, z.device
        N, K = self.n_particles, state.existence.shape[1]
        pd = model.p_d
        log_cf = math.log(model.clutter_rate) + model.clutter_log_density(sensor).to(dt)
        xb = (uniform((B, M, N, 3), dtype=dt, device=dev, generator=generator) * 2 - 1) * model.region
        llb = self._loglik(xb, z, sensor, own=True)  # (B, M, N): each new PO against its own measurement
        log_Ib = torch.logsumexp(llb, -1) - math.log(N)
        ll = self._loglik(state.means, z, sensor) if K else torch.zeros(B, 0, N, M, dtype=dt, device=dev)
        log_Ik = torch.logsumexp(state.log_weights.unsqueeze(-1) + ll, 2)  # (B, K, M)
        beta, xi = _bp_terms(model, state.existence, log_Ik, log_Ib, log_cf, self.birth_rate)
        assoc = loopy_association(beta, xi, state.mask, z_mask, self.bp_iterations)
        live = state.mask.unsqueeze(-1) & z_mask.unsqueeze(-2)
        tiny = torch.finfo(dt).tiny
        log_nu = torch.where(live, torch.log(assoc.nu.clamp_min(tiny)), torch.tensor(float("-inf"), dtype=dt))
        terms = torch.cat([torch.full((B, K, N, 1), math.log(1 - pd) if pd < 1 else float("-inf"), dtype=dt,
                                      device=dev),
                           math.log(pd) + log_nu.unsqueeze(2) - log_cf + ll], -1)
        lw = state.log_weights + torch.logsumexp(terms, -1)  # (B, K, N)
        log_C = torch.logsumexp(lw, -1)
        r = state.existence
        r_leg = _legacy_existence(r, log_C)
        idx = _systematic_indices(lw, N, generator)
        leg = state.means.gather(2, idx.unsqueeze(-1).expand(B, K, N, 3))
        nidx = _systematic_indices(llb, N, generator)
        new = xb.gather(2, nidx.unsqueeze(-1).expand(B, M, N, 3))
        r_all = torch.cat([r_leg, assoc.new_existence], 1)
        mask = torch.cat([state.mask, z_mask], 1)
        flat = torch.full((B, K + M, N), -math.log(N), dtype=dt, device=dev)
        r2, m2, lw2, x2 = _prune_and_cap(r_all, mask, [flat, torch.cat([leg, new], 1)], self.prune, self.max_objects)
        # particles in ``means``, no factors
        return POState(r2, m2, lw2, x2, underflow=_underflow(log_Ib, log_Ik, log_cf, state.mask, z_mask))

    def init(self, batch_size: int, dtype=torch.float64, device=None) -> "POState":
        z = torch.zeros(batch_size, 0, dtype=dtype, device=device)
        return POState(z, z.bool(), torch.zeros(batch_size, 0, self.n_particles, dtype=dtype, device=device),
                       torch.zeros(batch_size, 0, self.n_particles, 3, dtype=dtype, device=device))

    forward = _forward

    def extra_repr(self) -> str:
        return f"n_particles={self.n_particles}"


def _legacy_existence(r: torch.Tensor, log_C: torch.Tensor) -> torch.Tensor:
    """Updated existence ``r C / (r C + 1 - r)`` of legacy POs (both localisers); 0, not 0/0, when
    ``r = 1`` and ``C = 0``."""
    rc = r * log_C.exp()
    return torch.where(rc > 0, rc / (rc + 1 - r), torch.zeros_like(rc))


def _reduce(log_w: torch.Tensor, means: torch.Tensor, L: torch.Tensor, n: int, generator):
    """Keep ``n`` of the candidate components ``(B, K, C)`` by systematic resampling of their indices
    (one uniform per PO); returns ``(log_weights (B, K, n) equal, means, scale_trils)``."""
    B, K, C = log_w.shape
    idx = _systematic_indices(log_w, n, generator)
    gm = means.gather(2, idx.unsqueeze(-1).expand(B, K, n, means.shape[-1]))
    gL = L.gather(2, idx[..., None, None].expand(B, K, n, *L.shape[-2:]))
    return torch.full((B, K, n), -math.log(n), dtype=means.dtype, device=means.device), gm, gL


__all__ = ["run_localisation", "scene_figure", "LOCALISATION_COLUMNS", "FlowMixtureLocaliser", "BootstrapLocaliser",
           "POState", "Localisation", "birth_mixture", "METHODS"]
