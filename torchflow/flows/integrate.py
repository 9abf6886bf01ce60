"""The one integrator of every flow and every kind of linearisation points.

:func:`integrate_flow` steps ``d eta = (A eta + b) d lambda [+ Q^{1/2} dW]`` over a lambda schedule.
At every pseudo-time step the flow's coefficients are computed at the L linearisation points
``(B, L, d)`` of the strategy (:mod:`~torchflow.flows.points`: L = 1 global, L = N per particle,
L = K clustered), the points move with their own drift, and each particle moves with its point's
coefficients (gathered by the ``(B, N) -> L`` index, or broadcast). There is one loop for all of
them; two choices in it are costs, not meanings:

* a deterministic flow with few points (``L d^2 <= N k``, k measured coordinates) composes each
  point's affine map on ``d x d`` matrices, ``M <- (I + eps A) M``, and applies it to the particles
  once at the end, instead of moving the particles at every step;
* per-particle points (L = N) move the particles, the points and the tracked means with one
  stacked product.

Outputs: migrated particles; ``log|det|`` of each particle's map (deterministic flows); each
particle's Gaussian law ``N(mu_1, S_1)`` and density (stochastic flows given ``proposal``: the
coefficients depend only on the deterministic points, so
``mu_j = (I + eps_j A_j) mu_{j-1} + eps_j b_j``, ``S_j = (I + eps_j A_j) S_{j-1} (I + eps_j A_j)^T + eps_j Q_j``);
and, on request, the Gaussian image ``(mu_1, Sigma_1)`` of each point's prior.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Optional, Union

import torch

from torchflow.core import cudagraphs, linalg, tuning
from torchflow.core.checks import check_choice
from torchflow.core.errors import ArgumentError, ArgumentTypeError
from torchflow.flows import loops, select
from torchflow.flows.base import FlowCoefficients, FlowOutput, FlowPrior, ParticleFlow, _gather_points
from torchflow.flows.ensemble import EnsembleFlow, EnsembleMeasurement
from torchflow.flows.measurement import GaussianMeasurement
from torchflow.flows.points import LinearisationPoints, resolve_points
from torchflow.flows.schedules import LambdaSchedule, resolve_schedule


def integrate_flow(
    flow: ParticleFlow,
    model,
    particles: torch.Tensor,
    z: torch.Tensor,
    prior: FlowPrior,
    schedule: Optional[LambdaSchedule] = None,
    *,
    generator: Optional[torch.Generator] = None,
    proposal: Optional[FlowPrior] = None,
    noise=None,
    index: Optional[torch.Tensor] = None,
    points: Union[None, str, LinearisationPoints] = None,
    gaussian_image: bool = False,
    measurement=None,
    start: Optional[torch.Tensor] = None,
    map_jacobian: bool = False,
) -> FlowOutput:
    """Integrate a flow from lambda = 0 to 1 (see the module docstring).

    Deterministic flows take Euler steps and accumulate ``log|det(I + eps_j A_j)|``, the
    log-Jacobian of the particle map, which the PF-PF weight needs. Stochastic flows take
    Euler-Maruyama steps (noise from ``generator``) and, given ``proposal``, return each
    particle's log-density under its exact Gaussian law.

    Args:
        flow: the flow (states A, b and, if stochastic, the diffusion).
        model: state-space model (its measurement term, unless ``measurement`` is given).
        particles: ``(B, N, d)`` samples eta_0.
        z: ``(B, m)``.
        prior: :class:`FlowPrior` at the points: ``(B, d)`` or ``(B, 1, d)`` (global),
            ``(B, N, d)`` (per particle), ``(B, K, d)`` (clustered); factors broadcastable to
            ``(B, L, d, d)``. The homotopy of each point starts from it.
        schedule: lambda schedule (default: exponential, 29 steps, ratio 1.2).
        generator: random generator for the diffusion noise (stochastic flows).
        proposal: stochastic flows: the law ``eta_0 ~ N(mean, scale_tril scale_tril^T)`` the
            particles were drawn from, mean ``(B, N, d)``, factor broadcastable to
            ``(B, N, d, d)``. When given, the output carries ``log_proposal``.
        points: where the flow is linearised: a :class:`~torchflow.flows.points.LinearisationPoints`
            or its name (``"global"``, ``"particle"``, ``"clustered"``), or ``"ensemble"``: an
            ensemble flow (:mod:`~torchflow.flows.ensemble`) states its drift at the members
            themselves, reading ``measurement`` (an
            :class:`~torchflow.flows.ensemble.EnsembleMeasurement`) and ``prior``
            (:func:`~torchflow.flows.ensemble.ensemble_prior`); default: the flow's own
            (:attr:`ParticleFlow.points`), or ``"clustered"`` when ``index`` is given.
        index: ``(B, N)`` the point of each particle (clustered points).
        measurement: the :class:`~torchflow.flows.measurement.GaussianMeasurement` to linearise
            at the points (default: the model's own, ``GaussianMeasurement.from_model(model, z)``);
            a filter passes its own for state-dependent noise, mixture components or data
            association. The flow itself only sees the whitened tensors at the points.
        gaussian_image: also return the image ``(image_mean, image_cov)`` of each point's prior
            Gaussian (costs a ``d x d`` covariance recursion per point).
        noise: stochastic flows: optional ``noise(j, shape) -> (B, N, r)`` standard normals of
            pseudo-time step ``j`` (instead of drawing them from ``generator``); a filter that
            flows particles in blocks uses it to keep the draws those of the whole cloud.
        map_jacobian: deterministic flows: also return each particle's map matrix ``M``
            (``eta_1 = M eta_0 + c``; the coefficients depend on the points, not on the particle),
            ``(B, 1, d, d)`` for one point per trial, else ``(B, N, d, d)``: the marginal particle
            weights push each parent's transition through it (costs a ``d x d`` product per point
            and pseudo-time step; the reference loop).
        start: where the points start, batched like ``prior.mean`` (default: ``prior.mean``
            itself, as in EDH/LEDH, whose first linearisation point is the prior mean). The prior
            mean ``eta_bar_0`` of the homotopy stays ``prior.mean``; a filter whose prior is
            shared by a group of particles but whose points are per particle (PFGPF: the
            component's moments, each particle linearised from its noise-free prediction) gives both.

    Returns:
        :class:`FlowOutput`; ``aux``, ``image_mean`` and ``image_cov`` are per point, without the
        point dimension when ``prior`` was given per trial ``(B, d)``.
    """
    if not isinstance(particles, torch.Tensor) or particles.dim() != 3:
        got = tuple(particles.shape) if isinstance(particles, torch.Tensor) else type(particles).__name__
        raise ArgumentError(f"particles: expected (B, N, d) (trials, particles, state), got {got}")
    schedule = resolve_schedule(schedule)
    eps_all, lam_all = schedule.steps(dtype=particles.dtype, device=particles.device)
    eps_host = schedule.host_steps(particles.dtype)
    if isinstance(flow, EnsembleFlow) or points == "ensemble":
        return _integrate_ensemble(flow, measurement, particles, prior, eps_all, lam_all)
    strategy = resolve_points(flow, "clustered" if points is None and index is not None else points)
    if map_jacobian and flow.stochastic:
        raise ArgumentError(
            "map_jacobian: a stochastic flow's map is not deterministic; its law is the output's "
            "proposal_mean and proposal_cov (give proposal=)"
        )
    graphable = (
        measurement is None
        and proposal is None
        and noise is None
        and start is None
        and not gaussian_image
        and not map_jacobian
        and select.flow_graph(flow, particles)
    )
    if measurement is None:
        measurement = GaussianMeasurement.from_model(model, z)
    if start is not None:
        if start.shape != prior.mean.shape:
            raise ArgumentError(
                f"start: expected the points' starting positions shaped like prior.mean "
                f"{tuple(prior.mean.shape)}, got {tuple(start.shape)}"
            )
        if gaussian_image:
            raise ArgumentError(
                "start: the Gaussian image follows the prior mean (the points' own start); "
                "give either start or gaussian_image=True"
            )
    prior, index, squeeze = strategy.arrange(prior, particles, index)
    start = None if start is None else start.reshape(prior.mean.shape)
    if graphable:
        out = _integrate_graphed(
            flow, model, schedule, strategy, particles, z, prior, index, (eps_all, eps_host), lam_all
        )
    else:
        out = _integrate(
            flow,
            measurement,
            particles,
            prior,
            index,
            strategy.per_particle,
            (eps_all, eps_host),
            lam_all,
            generator,
            proposal,
            noise,
            gaussian_image,
            start,
            map_jacobian,
        )
    if squeeze:
        out.aux = out.aux.squeeze(-2)
        if gaussian_image:
            out.image_mean, out.image_cov = out.image_mean.squeeze(-2), out.image_cov.squeeze(-3)
    return out


def _integrate_ensemble(flow, measurement, particles, prior, eps_all, lam_all) -> FlowOutput:
    """The loop of an ensemble flow (:mod:`~torchflow.flows.ensemble`, ``points="ensemble"``): at
    each pseudo-time step the flow states its coefficients at the members themselves, and every
    member moves by ``eps (A x + b)``; ``log_det`` sums the flow's ``log|det(I + eps A)|`` (the same
    for every member; ``None`` where the flow states none). ``aux`` is the prior mean."""
    if not isinstance(flow, EnsembleFlow):
        raise ArgumentTypeError(
            f"points: 'ensemble' steps an ensemble flow (torchflow.flows.ensemble), got {type(flow).__name__}"
        )
    if not isinstance(measurement, EnsembleMeasurement):
        raise ArgumentTypeError(
            f"measurement: an ensemble flow reads an EnsembleMeasurement (the members' whitened measurements), "
            f"got {type(measurement).__name__}"
        )
    B, N, _ = particles.shape
    X, log_det = particles, None
    eps_steps, lam_steps = eps_all.unbind(0), lam_all.unbind(0)
    for j in range(len(eps_steps)):  # pseudo-time steps, not a loop over trials or members
        eps = eps_steps[j]
        co = flow.ensemble_coefficients(X, measurement, prior, lam_steps[j], eps, j)
        if co.b.dim() == 2:  # A x + b shared by the members: A applied to all of them at once
            AX = co.apply_A(X.transpose(1, 2)).transpose(1, 2) if co.A is None else X @ co.A.transpose(-1, -2)
            X = X + eps * (AX + co.b.unsqueeze(1))
        else:  # a drift per member
            X = X + eps * co.b
        if co.log_det is not None:
            log_det = co.log_det if log_det is None else log_det + co.log_det
    return FlowOutput(X, None if log_det is None else log_det.unsqueeze(1).expand(B, N), prior.mean)


def _integrate(
    flow,
    measurement,
    particles,
    prior,
    index,
    per_particle,
    eps_all,
    lam_all,
    generator,
    proposal,
    noise,
    gaussian_image,
    start=None,
    map_jacobian=False,
) -> FlowOutput:
    """The loop of :func:`integrate_flow`: ``prior`` at ``(B, L, d)`` points, ``index (B, N)`` or
    ``None`` (points broadcast against the particles, or are the particles). A fused kernel takes
    the integration where :func:`torchflow.flows.select.flow_kernel` chooses one; the loop
    below is the reference."""
    d = particles.shape[-1]
    k = d if measurement.support is None else len(measurement.support)
    track = flow.stochastic and proposal is not None
    kernel = select.flow_kernel(
        flow,
        measurement,
        particles,
        k,
        per_particle=per_particle,
        track=track,
        gaussian_image=gaussian_image or map_jacobian,
    )
    if kernel is not None:
        return loops.run_flow(
            kernel, flow, measurement, particles, prior, index, eps_all, lam_all, generator, proposal, noise, start
        )
    return _reference(
        flow,
        measurement,
        particles,
        prior,
        index,
        per_particle,
        eps_all,
        lam_all,
        generator,
        proposal,
        noise,
        gaussian_image,
        start,
        map_jacobian,
    )


def _reference(
    flow,
    measurement,
    particles,
    prior,
    index,
    per_particle,
    eps_all,
    lam_all,
    generator,
    proposal,
    noise,
    gaussian_image,
    start=None,
    map_jacobian=False,
) -> FlowOutput:
    """The reference pseudo-time loop (module docstring), for every flow and kind of points."""
    B, N, d = particles.shape
    eps_all, eps_host = eps_all  # the step sizes on the device, and as Python floats
    prior = prior.reduced(measurement.support)
    if getattr(measurement, "fixed", False):  # W fixed over pseudo-time: a flow keeps what it derives from it
        prior = replace(prior, fixed={})
    measurement.prepare(particles)
    image = _Image(prior, gaussian_image)
    aux, eta = (prior.mean if start is None else start), particles  # (B, L, d), (B, N, d)
    L = aux.shape[-2]
    k = d if measurement.support is None else len(measurement.support)
    stochastic = flow.stochastic
    track = stochastic and proposal is not None
    compose = not stochastic and not per_particle and L * d * d <= N * k
    eye = torch.eye(d, dtype=particles.dtype, device=particles.device)
    if compose or map_jacobian:  # each point's map eta -> M eta + c, composed on (d, d) matrices
        M = eye.expand(B, L, d, d)
    if compose:
        c = torch.zeros(B, L, d, dtype=particles.dtype, device=particles.device)
    if track:  # the law N(mu (B, N, d), Sig (B, N|1, d, d)) the particles were drawn from
        mu, Sig = proposal.mean.expand(B, N, d), proposal.scale_tril @ proposal.scale_tril.transpose(-1, -2)
        Sig = Sig.expand(B, 1, d, d) if Sig.dim() == 2 else Sig
    tracked = [mu] if track else []
    log_det = torch.zeros(B, L, dtype=particles.dtype, device=particles.device)
    eps_steps, lam_steps = eps_all.unbind(0), lam_all.unbind(0)  # one op for all the steps' 0-d views
    for j in range(len(eps_all)):
        eps, lam = eps_steps[j], lam_steps[j]
        co = flow.coefficients_at(measurement.at(aux, prior.support), prior, lam, eps)
        if stochastic and (co.A is None or not co.has_noise):
            raise ArgumentTypeError(
                f"{type(flow).__name__}: a stochastic flow must give an explicit A and a diffusion "
                "(noise_factor or noise_product)"
            )
        image.step(co, eps_host[j])  # at the points
        if not stochastic:
            log_det = log_det + co.log_det
        if map_jacobian and not compose:
            M = (eye + eps * co.dense_A()) @ M
        if compose:
            step = eye + eps * co.dense_A()  # (B, L, d, d)
            M = step @ M
            c = linalg.matvec(step, c) + eps * co.b
            aux = linalg.matvec(step, aux) + eps * co.b
            continue
        if per_particle:  # the points are the particles': one stacked product for every vector
            drifts = co.drift(eta, aux, *tracked)
            aux = aux + eps * drifts[1]
            at = co
        else:  # move the points, then view their coefficients per particle
            aux = aux + eps * co.drift(aux)[0]
            at = co if index is None else co.gather(index)
            drifts = at.drift(eta, *tracked)
        eta = eta + eps * drifts[0]
        if stochastic:
            shape = (B, N, at.noise_rank)
            xi = (
                noise(j, shape)
                if noise is not None
                else linalg.standard_normal(shape, dtype=eta.dtype, device=eta.device, generator=generator)
            )
            eta = eta + eps.sqrt() * at.diffuse(xi)
            if track:
                mu = mu + eps * drifts[-1]
                Sig = _propagate_cov(Sig, at, eps_host[j], eye)
                tracked = [mu]
    if compose:
        if L == 1:
            eta = torch.baddbmm(c, particles, M[:, 0].transpose(-1, -2))
        else:
            eta = linalg.matvec(_gather_points(M, index), particles) + _gather_points(c, index)
    if track:  # each particle's log-density under its law (the proposal density of Pal & Coates' Algorithm 1)
        Sig = linalg.symmetrize(Sig)
        log_q = linalg.mvn_log_prob(eta, mu, linalg.safe_cholesky(Sig))
        return image.output(FlowOutput(eta, None, aux, log_proposal=log_q, proposal_mean=mu, proposal_cov=Sig))
    if stochastic:
        return image.output(FlowOutput(eta, None, aux))
    log_det = log_det.expand(B, N) if index is None else _gather_points(log_det.unsqueeze(-1), index).squeeze(-1)
    out = FlowOutput(eta, log_det, aux)
    if map_jacobian:
        out.map_jacobian = M if index is None else _gather_points(M, index)
    return image.output(out)


def which_kernel(flow: ParticleFlow, model, device) -> Optional[str]:
    """The fused kernel a no-gradient :func:`integrate_flow` of ``flow`` at per-particle points on
    ``model`` takes on ``device``, as far as it is known before the measurement is built
    (:func:`torchflow.flows.select.per_particle_kernel`): ``"diagonal"`` or ``None``."""
    return select.per_particle_kernel(flow, model, device)


def _integrate_graphed(flow, model, schedule, strategy, particles, z, prior, index, eps_all, lam_all) -> FlowOutput:
    """:func:`_integrate` for the model's own measurement, replayed from a CUDA graph captured once
    per flow, model state, schedule, points, shapes and tuning. The prior's factors are reduced to
    the measured coordinates here, outside the graph (they are built from host values)."""
    prior = prior.reduced(model.structure.measurement_support)
    fields = (prior.mean, prior.scale_tril, prior.support, prior.root, prior.cols, prior.cols_support, prior.cov_cols)
    per_particle = strategy.per_particle

    def fn(particles, z, index, *prior_fields):
        measurement = GaussianMeasurement.from_model(model, z)
        out = _integrate(
            flow,
            measurement,
            particles,
            FlowPrior(*prior_fields),
            index,
            per_particle,
            eps_all,
            lam_all,
            None,
            None,
            None,
            False,
        )
        return out.particles, out.log_det, out.aux

    key = ("integrate_flow", cudagraphs.state_key(flow, model, schedule, strategy), tuning.get())
    eta, log_det, aux = cudagraphs.graphed(
        key, fn, (particles, z, index) + fields, name=f"integrate_flow({type(flow).__name__})"
    )
    return FlowOutput(eta, log_det, aux)


EVALUATE_AT = ("end", "start")


def flow_gaussian(
    flow: ParticleFlow,
    measurement,
    prior: FlowPrior,
    schedule: Optional[LambdaSchedule] = None,
    evaluate_at: str = "end",
    on_step=None,
):
    """Flow the *parameters* of Gaussians instead of particles (the flow-induced proposal of
    Zhang, Khojasteh, Atanasov & Meyer 2024, eqs 6-7): for each prior ``N(mu_0, P_0)``, linearise the measurement at
    the migrating
    mean and step

        mu_l = mu_{l-1} + eps_l (A_l mu_{l-1} + b_l),
        P_l = (I + eps_l A_l) P_{l-1} (I + eps_l A_l)^T + eps_l Q_l,

    with ``A``, ``b`` (and the diffusion ``Q`` of a stochastic flow) from the prior ``N(mu_0, P_0)``
    and ``lambda_l``; no particles, no Jacobians. With a linear measurement the Gromov flow
    (``Q = M^{-1} J M^{-1}``) gives the exact Kalman posterior on any grid (``P_l = M(lambda_l)^{-1}``
    step by step), EDH (``Q = 0``) as the grid is refined.

    Args:
        flow: any flow (EDH, Gromov, optimised diffusion, ...); its coefficients are evaluated at the
            migrating means, one point per Gaussian.
        measurement: a :class:`~torchflow.flows.measurement.GaussianMeasurement` whose ``z`` has the
            Gaussians' leading batch dimension.
        prior: :class:`FlowPrior` with ``mean (..., d)`` and factor ``(..., d, d)``.
        schedule: lambda schedule (default exponential, 29 steps, ratio 1.2).
        evaluate_at: pseudo-time at which step l's ``A``, ``b``, ``Q`` are taken: ``"end"``
            (default, ``lambda_l``, as the Euler-Maruyama step of Zhang et al. 2024, eqs 1-11, and
            Li & Coates' flows) or ``"start"`` (``lambda_{l-1}``, ``lambda_0 = 0``: the plain
            explicit Euler step, which is unstable when ``eps_1`` times the measurement's precision
            in prior units is large).
        on_step: optional observer ``on_step(coefficients, eps)`` called with each step's
            :class:`FlowCoefficients` before the step is taken (diagnostics; the result is unchanged).

    Returns:
        ``(mean (..., d), cov (..., d, d))`` of the flowed Gaussians.
    """
    check_choice("evaluate_at", evaluate_at, EVALUATE_AT)
    schedule = resolve_schedule(schedule)
    eps_all, lam_all = schedule.steps(dtype=prior.mean.dtype, device=prior.mean.device)
    eps_host = schedule.host_steps(prior.mean.dtype)
    if evaluate_at == "start":
        lam_all = lam_all - eps_all  # lambda_{l-1}; exactly 0 for the first step
        lam_all[0] = 0.0
    prior = prior.reduced(measurement.support)
    image = _Image(prior, True)
    mu = prior.mean
    for j in range(len(eps_all)):
        eps, lam = eps_all[j], lam_all[j]
        co = flow.coefficients_at(measurement.at(mu, prior.support), prior, lam, eps)
        if on_step is not None:
            on_step(co, eps)
        image.step(co, eps_host[j])
        mu = mu + eps * co.drift(mu)[0]
    return mu, linalg.symmetrize(image.cov)


class _Image:
    """The Gaussian image of the points' prior ``N(mean, P)``: the mean is the auxiliary point
    itself; the covariance follows ``S <- (I + eps A) S (I + eps A)^T (+ eps Q)``."""

    def __init__(self, prior: "FlowPrior", on: bool):
        self.on = on
        if on:
            L = prior.scale_tril
            self.cov = L @ L.transpose(-1, -2)
            self.eye = torch.eye(L.shape[-1], dtype=L.dtype, device=L.device)

    def step(self, co: "FlowCoefficients", eps: float) -> None:
        if not self.on:
            return
        if co.A is None and co.form_A is not None:
            co.matrix()  # formed once on the caller's coefficients, so the particles' drift reuses it
        self.cov = _propagate_cov(self.cov, co, eps, self.eye)

    def output(self, out: "FlowOutput") -> "FlowOutput":
        if self.on:
            out.image_mean, out.image_cov = out.aux, linalg.symmetrize(self.cov)
        return out


def _propagate_cov(Sig, co: "FlowCoefficients", eps: float, eye):
    """``(I + eps A) Sig (I + eps A)^T + eps Q``, ``Sig (..., d, d)``; ``eps`` a Python float.

    With a measurement support A has only k nonzero columns ``A_s (..., d, k)``:
    ``V = (I + eps A) Sig = Sig + eps A_s Sig[s, :]`` and ``V (I + eps A)^T = V + eps V[:, s] A_s^T``,
    two ``d x k x d`` products fused with their additions (``baddbmm``), and ``Q`` given as a pair
    ``Q = Q1 Q2^T`` is added by a third; no separate passes over the ``d x d`` matrices."""
    if co.support is None:
        T = eye + eps * co.dense_A()
        return T @ Sig @ T.transpose(-1, -2) + eps * co.diffusion_cov()
    A, sup, e = co.matrix(), co.support, eps
    pair = co.noise_cov_pair
    shapes = [Sig.shape[:-2], A.shape[:-2]] + ([p.shape[:-2] for p in pair] if pair is not None else [])
    batch = torch.broadcast_shapes(*shapes)
    _flat3 = lambda x: (x if x.shape[:-2] == batch else x.expand(*batch, *x.shape[-2:])).reshape(-1, *x.shape[-2:])
    S3, A3 = _flat3(Sig), _flat3(A)
    V = torch.baddbmm(
        S3, A3, S3[:, sup], alpha=e
    )  # rows by basic indexing: a contiguous copy, cheaper than index_select on the CPU
    out = torch.baddbmm(V, V.index_select(-1, sup), A3.transpose(-1, -2), alpha=e)
    if pair is not None:
        out = torch.baddbmm(out, _flat3(pair[0]), _flat3(pair[1]).transpose(-1, -2), alpha=e)
        return out.reshape(*batch, *Sig.shape[-2:])
    return out.reshape(*batch, *Sig.shape[-2:]) + eps * co.diffusion_cov()
