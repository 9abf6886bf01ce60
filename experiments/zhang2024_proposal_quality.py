"""How good is each flowed Gaussian as an importance-sampling proposal? Zhang et al.'s (2024) Table II
variants, one TDOA measurement at a time, without belief propagation.

    python -m experiments.zhang2024_proposal_quality --scenes 32 --n-samples 500

Table II's cells differ only in how each prior component is flowed (method, alpha, the (beta,
Delta_1) grid) and, on our side, in two UNCONF readings: where a lambda step takes its coefficients
(``evaluate_at``: ``end`` = lambda_l, ``start`` = lambda_{l-1}) and which c* the optimised diffusion
uses (``c_rule``: ``printed``, ``literal_shift`` or ``printed_shift``,
:func:`~torchflow.flows.optimal_diffusion_scale`).
A localiser fails when the flowed components are poor proposals: then each candidate's moments come
from a handful of effective samples. This script measures that directly, per variant, on two
kinds of prior component:

- ``birth``: the 5^3 birth mixture (sd 200 m) and a TDOA of sensor 0 from a source uniform in the
  region (the first sensor of a run);
- ``legacy``: one Gaussian per scene that is already thin (sd 1 m) along sensor 0's gradient at the
  source and 200 m wide across it, centred one draw away from the source, and a TDOA of sensor 1
  (every later sensor of a run).

Printed per variant, over scenes (and components, weighted by each component's share of the
evidence, taken from a bootstrap reference with ``--reference`` prior draws per component):

- ``ess``: the mean fraction ESS_n / N_p of a component's own per-component-ratio weights;
- ``deg``: the share of the evidence carried by components with ESS_n < 10 (degenerate fits);
- ``max|x|``: the largest per-step amplification ``|1 - eps_l k|`` of the Euler step over the
  components and the flow's directions (``> 1``: the step overshoots and grows the error).

No claim is made that these numbers give the OSPA of Table II; they show which variants make
unusable proposals, and where in the grid.
"""

from __future__ import annotations

import argparse
import math

import torch

from torchflow.core import linalg
from torchflow.flows import EDHFlow, GromovFlow, OptimalDiffusionFlow, flow_gaussian
from torchflow.flows.base import FlowPrior
from torchflow.flows.geodesic import C_RULES
from torchflow.flows.schedules import GeometricSchedule
from torchflow.models import TDOA3D
from torchflow.tdoa import birth_mixture, sensor_measurement

GRIDS = ((1e-13, 1.3), (1e-5, 1.5), (1e-4, 2.0))  # (Delta_1, beta): Table II's columns
METHODS = (("pfi_d", None), ("pfi_s", None), ("pfi_os", 0.01), ("pfi_os", 0.1), ("pfi_os", 0.5))


def make_flow(method: str, alpha, c_rule: str):
    if method == "pfi_d":
        return EDHFlow()
    if method == "pfi_s":
        return GromovFlow(points="global")
    return OptimalDiffusionFlow(alpha=alpha, points="global", c_rule=c_rule)


def scenes(model: TDOA3D, n: int, generator: torch.Generator) -> dict:
    """Priors ``(R, 3)``, ``(R, 3, 3)``, measurements ``(R,)``, sensor and the row's scene index for
    both stages."""
    src = (torch.rand(n, 3, generator=generator, dtype=torch.float64) * 2 - 1) * model.region
    bm, bL = birth_mixture(model.region, 5, 0.5)
    Nb = bm.shape[0]
    z0 = model.measure(src, 0) + model.sigma_v * torch.randn(n, generator=generator, dtype=torch.float64)
    birth = dict(
        mean=bm.repeat(n, 1),
        L=bL.expand(n * Nb, 3, 3).clone(),
        z=z0.repeat_interleave(Nb),
        sensor=0,
        scene=torch.arange(n).repeat_interleave(Nb),
    )
    # legacy: thin (1 m) along sensor 0's gradient at the source, 200 m across it
    g = model.jacobian(src, 0)
    u = g / torch.linalg.vector_norm(g, dim=-1, keepdim=True)
    P = 200.0**2 * (torch.eye(3, dtype=torch.float64) - u.unsqueeze(-1) * u.unsqueeze(-2)) + 1.0**2 * u.unsqueeze(
        -1
    ) * u.unsqueeze(-2)
    L = torch.linalg.cholesky(P)
    mean = src + (L @ torch.randn(n, 3, 1, generator=generator, dtype=torch.float64)).squeeze(-1)
    z1 = model.measure(src, 1) + model.sigma_v * torch.randn(n, generator=generator, dtype=torch.float64)
    legacy = dict(mean=mean, L=L, z=z1, sensor=1, scene=torch.arange(n))
    return {"birth": birth, "legacy": legacy}


def reference_log_evidence(model, st: dict, n_ref: int, generator) -> torch.Tensor:
    """Bootstrap estimate of ``log int N(x; mu_n, P_n) l(x) dx`` per row ``(R,)``."""
    out = []
    for a in range(0, st["mean"].shape[0], 64):
        sl = slice(a, a + 64)
        xi = torch.randn(st["mean"][sl].shape[0], n_ref, 3, generator=generator, dtype=torch.float64)
        x = st["mean"][sl].unsqueeze(1) + xi @ st["L"][sl].transpose(-1, -2)
        ll = model.log_likelihood(st["z"][sl].unsqueeze(-1), x, st["sensor"])
        out.append(torch.logsumexp(ll, -1) - math.log(n_ref))
    return torch.cat(out)


def amplification_observer():
    """An ``on_step`` observer for :func:`~torchflow.flows.flow_gaussian` and a getter of
    ``max_l |1 - eps_l k_l|`` per row over the eigenvalues k of ``-A_l`` (at the migrating mean)."""
    worst = []

    def on_step(co, eps):
        A = co.dense_A()
        eye = torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)
        amp = torch.linalg.eigvals(eye + eps * A).abs().amax(-1)
        worst.append(amp if not worst else torch.maximum(worst.pop(), amp))

    return on_step, lambda: worst[0]


def amplification(flow, model, st, schedule, evaluate_at: str) -> torch.Tensor:
    """``max_l |1 - eps_l k_l|`` per row (the flow run alone, for tests; :func:`evaluate` observes
    the same flow it samples from)."""
    on_step, get = amplification_observer()
    flow_gaussian(
        flow,
        sensor_measurement(model, st["z"], st["sensor"]),
        FlowPrior(st["mean"], st["L"]),
        schedule,
        evaluate_at,
        on_step=on_step,
    )
    return get()


def evaluate(model, st, flow, schedule, evaluate_at, n, log_ref, generator) -> dict:
    meas = sensor_measurement(model, st["z"], st["sensor"])
    on_step, get_amp = amplification_observer()
    mu1, P1 = flow_gaussian(flow, meas, FlowPrior(st["mean"], st["L"]), schedule, evaluate_at, on_step=on_step)
    L1 = linalg.safe_cholesky(P1)
    xi = torch.randn(mu1.shape[0], n, 3, generator=generator, dtype=torch.float64)
    x = mu1.unsqueeze(1) + xi @ L1.transpose(-1, -2)
    lo = (
        linalg.mvn_log_prob(x, st["mean"].unsqueeze(1), st["L"].unsqueeze(1))
        + model.log_likelihood(st["z"].unsqueeze(-1), x, st["sensor"])
        - linalg.mvn_log_prob(x, mu1.unsqueeze(1), L1.unsqueeze(1))
    )
    ess = torch.exp(2 * torch.logsumexp(lo, -1) - torch.logsumexp(2 * lo, -1))
    # evidence share of each row within its scene (reference)
    scene = st["scene"]
    ns = int(scene.max()) + 1
    zmax = torch.full((ns,), -math.inf, dtype=torch.float64).scatter_reduce(0, scene, log_ref, "amax")
    w = torch.exp(log_ref - zmax[scene])
    w = w / torch.zeros(ns, dtype=torch.float64).index_add(0, scene, w)[scene] / ns
    amp = get_amp()
    return {"ess": float((w * ess / n).sum()), "deg": float((w * (ess < 10).double()).sum()), "amp": float(amp.max())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=int, default=32)
    ap.add_argument("--n-samples", type=int, default=500, help="N_p per flowed component")
    ap.add_argument("--reference", type=int, default=20000, help="prior draws per component for the shares")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--stages", nargs="+", default=["birth", "legacy"], choices=["birth", "legacy"])
    ap.add_argument(
        "--rules",
        nargs="+",
        default=list(C_RULES),
        choices=list(C_RULES),
        help="PFI-OS readings of c* (optimal_diffusion_scale)",
    )
    ap.add_argument("--os-only", action="store_true", help="only the PFI-OS rows")
    args = ap.parse_args(argv)
    model = TDOA3D()
    gen = torch.Generator().manual_seed(args.seed)
    data = scenes(model, args.scenes, gen)
    print(f"# Zhang et al. (2024) proposal quality: {args.scenes} scenes, N_p = {args.n_samples}, seed {args.seed}")
    print("# cells: ess (mean ESS_n / N_p, evidence-weighted) / deg (evidence share with ESS_n < 10) / max|1 - eps k|")
    for stage in args.stages:
        st = data[stage]
        log_ref = reference_log_evidence(model, st, args.reference, gen)
        print(f"\n## {stage} components ({st['mean'].shape[0]} rows)")
        head = " | ".join(f"({b}, {d:g}) {e}" for d, b in GRIDS for e in ("end", "start"))
        print(f"| method | c_rule | {head} |")
        print("|---|---|" + "---|" * (2 * len(GRIDS)))
        for method, alpha in METHODS:
            if args.os_only and method != "pfi_os":
                continue
            for c_rule in args.rules if method == "pfi_os" else ("-",):
                flow = make_flow(method, alpha, c_rule)
                cells = []
                for d1, beta in GRIDS:
                    sched = GeometricSchedule(d1, beta)
                    for ev in ("end", "start"):
                        # the same draws for every cell (common random numbers): a cell's numbers do not
                        # depend on which other rows ran, and cells differ only by their proposals
                        cell = torch.Generator().manual_seed(args.seed + 1)
                        r = evaluate(model, st, flow, sched, ev, args.n_samples, log_ref, cell)
                        cells.append(f"{r['ess']:.3f} / {r['deg']:.2f} / {r['amp']:.3g}")
                name = method if alpha is None else f"{method} a={alpha}"
                print(f"| {name} | {c_rule} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
