"""Why PFGSPF's components stay alike (low G_eff) on the skewed-t / Poisson model: a step-by-step
look at the mixture weights.

    python -m experiments.comandur2022_geff_diagnostic --d 36 --G 5 --n-star 50 200 --trials 2 --steps 15 --fit both

Every component starts from the same prior (``init=prior``), so the components differ only by
Monte Carlo noise, and ``log alpha_j`` moves each step by the component's log mean weight
``c_j = log (1/N*) sum_i w_ij`` (MODELS.md section 9, eq 7). If the ``c_j`` of alike components
differ by noise alone, ``log alpha`` performs a random walk and G_eff falls as its spread grows;
the noise of a log mean weight is about ``sqrt(1/ESS_j - 1/N*)`` (delta method) with ``ESS_j`` the
component's own effective sample size. The script prints, per N*, averaged over trials and steps:

- ``sd_c``: the spread over components of ``c_j`` at one step (sample sd over j);
- ``sd_pred``: the delta-method prediction ``sqrt(mean_j (1/ESS_j - 1/N*))``;
- ``ess_j``: the components' mean ESS;
- ``g_eff``: the mean G_eff over the steps (the runner's number), and its value at the last step.

``--fit pooled`` is a control (:class:`PooledFit`): every component's predictive fit is the one
fitted to all G N* particles of the trial. Then ``sd_c`` can only come from each component's
importance-sampling noise, which ``sd_pred`` predicts. If the filter's own-fit ``sd_c`` is far above
``sd_pred`` and the pooled control's is near it, the mixture weights are driven by the sampling
error of each component's fitted predictive (N* draws fitting a d-dimensional Gaussian), not by
the importance sampling within components.
"""

from __future__ import annotations

import argparse
import math
import sys
from unittest import mock

import torch

from torchflow.core import linalg
from torchflow.filters import ParticleFlowGaussianSumParticleFilter, gaussian_sum
from torchflow.filters.gaussian_sum import mixture_update
from torchflow.models import SkewedTPoisson


class PooledFit(ParticleFlowGaussianSumParticleFilter):
    """Control: every component gets the same predictive fit, taken from all G N* propagated
    particles of the trial, so the components' weights differ only by their own sampling noise."""

    def draw(self, state, generator):
        x_prev, eta0, _, _ = super().draw(state, generator)
        B, G, n, d = eta0.shape
        flat = eta0.reshape(B, G * n, d)
        mu = flat.mean(1)
        dev = flat - mu.unsqueeze(1)
        L = gaussian_sum._factor(linalg.symmetrize(dev.transpose(-1, -2) @ dev / (G * n)), self.jitter)
        return x_prev, eta0, mu.unsqueeze(1).expand(B, G, d), L.unsqueeze(1).expand(B, G, d, d)


def run(d: int, G: int, n_star: int, trials: int, steps: int, seed: int, pooled: bool = False) -> dict:
    """One PFGSPF run of ``trials`` x ``steps`` on the same simulated data for every ``n_star``;
    returns the step-averaged statistics described in the module docstring."""
    model = SkewedTPoisson(d=d).double()
    gen = torch.Generator().manual_seed(seed)
    traj = model.simulate(trials, steps, gen)
    mean, cov = model.initial_belief(traj.states[:, 0])
    f = (PooledFit if pooled else ParticleFlowGaussianSumParticleFilter)(
        model, n_components=G, particles_per_component=n_star
    )
    fgen = torch.Generator().manual_seed(seed + 1)
    state = f.init(mean, cov, generator=fgen)
    sd_c, sd_pred, ess_j, g_eff = [], [], [], []
    captured = {}

    def spy(log_alpha, log_w):  # the filter's own mixture update, recording the step's log-weights
        captured["log_w"] = log_w
        return mixture_update(log_alpha, log_w)

    with torch.no_grad(), mock.patch.object(gaussian_sum, "mixture_update", spy):
        for t in range(steps):
            state = f.step(state, traj.observations[:, t], fgen)
            lw = captured["log_w"]  # (B, G, N*)
            c = torch.logsumexp(lw, -1) - math.log(n_star)  # (B, G)
            w = torch.softmax(lw, -1)
            e = 1.0 / w.pow(2).sum(-1)  # (B, G)
            sd_c.append(c.std(-1))
            sd_pred.append((1.0 / e - 1.0 / n_star).clamp_min(0).mean(-1).sqrt())
            ess_j.append(e.mean(-1))
            g_eff.append(state.g_eff)
    st = lambda v: torch.stack(v).mean().item()
    return dict(
        n_star=n_star,
        sd_c=st(sd_c),
        sd_pred=st(sd_pred),
        ess_j=st(ess_j),
        g_eff=st(g_eff),
        g_eff_last=g_eff[-1].mean().item(),
    )


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--d", type=int, default=36)
    p.add_argument("--G", type=int, default=5)
    p.add_argument("--n-star", type=int, nargs="+", default=[50, 200, 800])
    p.add_argument("--trials", type=int, default=4)
    p.add_argument("--steps", type=int, default=30)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--fit",
        choices=("own", "pooled", "both"),
        default="own",
        help="each component's own predictive fit (the filter), the pooled control, or both",
    )
    a = p.parse_args(argv)
    print(f"SkewedTPoisson d = {a.d}, PFGSPF G = {a.G}, {a.trials} trials x {a.steps} steps, seed {a.seed}")
    print(
        "| N* | fit | sd over components of log mean weight, per step | delta-method prediction | "
        "ESS per component | G_eff (mean over steps) | G_eff at the last step |"
    )
    print("|---|---|---|---|---|---|---|")
    for n in a.n_star:
        for pooled in {"own": (False,), "pooled": (True,), "both": (False, True)}[a.fit]:
            r = run(a.d, a.G, n, a.trials, a.steps, a.seed, pooled)
            print(
                f"| {n} | {'pooled' if pooled else 'own'} | {r['sd_c']:.3f} | {r['sd_pred']:.3f} | {r['ess_j']:.1f} | "
                f"{r['g_eff']:.2f} | {r['g_eff_last']:.2f} |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
