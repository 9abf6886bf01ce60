"""Marginal against standard PF-PF weights in torchflow's Stone Soup updater, where the prior cloud is
wider than the transition noise.

    pip install -e ".[stonesoup]"
    python experiments/stonesoup_marginal.py [--clouds 8] [--particles 2000]

One linear-Gaussian update in Stone Soup: a 2-D nearly-constant-velocity state
(``ConstantVelocity(0.05)`` per axis, 1 s step), prior particles from ``N([0, 1, 0, 1],
diag(1.5, .5, 1.5, .5))`` predicted by Stone Soup's ``ParticlePredictor``, a ``LinearGaussian``
position measurement with noise ``diag(.5, .5)`` and the detection (1.5, -0.8). Per updater, over
``--clouds`` independent prior clouds (the same clouds for every updater): the mean ESS of the
updated weights with its standard error, the ESS difference to the bootstrap ``ParticleUpdater`` on
the same clouds (paired, with its standard error), and the largest |t| of the weighted posterior
mean against Stone Soup's ``KalmanUpdater`` (standard error from the clouds).
"""

from __future__ import annotations

import argparse
import datetime
import time

import numpy as np


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clouds", type=int, default=8)
    ap.add_argument("--particles", type=int, default=2000)
    a = ap.parse_args(argv)

    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel, ConstantVelocity
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.predictor.particle import ParticlePredictor
    from stonesoup.types.array import StateVectors
    from stonesoup.types.detection import Detection
    from stonesoup.types.hypothesis import SingleHypothesis
    from stonesoup.types.state import GaussianState, ParticleState
    from stonesoup.updater.kalman import KalmanUpdater
    from stonesoup.updater.particle import ParticleUpdater

    from torchflow.interop.stonesoup import FlowParticleUpdater

    t0, dt = datetime.datetime(2020, 1, 1), datetime.timedelta(seconds=1)
    tm = CombinedLinearGaussianTransitionModel([ConstantVelocity(0.05), ConstantVelocity(0.05)])
    mean0, cov0 = np.array([0.0, 1.0, 0.0, 1.0]), np.diag([1.5, 0.5, 1.5, 0.5])
    mm = LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=np.diag([0.5, 0.5]))
    z = np.array([[1.5], [-0.8]])
    det = Detection(z, timestamp=t0 + dt, measurement_model=mm)
    kpred = KalmanPredictor(tm).predict(GaussianState(mean0.reshape(-1, 1), cov0, timestamp=t0), timestamp=t0 + dt)
    kf = np.asarray(KalmanUpdater(mm).update(SingleHypothesis(kpred, det)).state_vector, float).ravel()
    updaters = {"Stone Soup ParticleUpdater (bootstrap)": lambda s: ParticleUpdater(mm)}
    for flow in ("ledh", "edh", "gromov"):
        for prior in ("transition", "predicted"):
            for w in ("standard", "marginal"):
                updaters[f"{flow}, flow_prior={prior}, weights={w}"] = lambda s, flow=flow, prior=prior, w=w: (
                    FlowParticleUpdater(mm, flow=flow, seed=s, flow_prior=prior, weights=w)
                )
    N, C = a.particles, a.clouds
    rows = {}
    for name, make in updaters.items():
        ess, means, sec = [], [], 0.0
        for seed in range(C):
            np.random.seed(seed)  # Stone Soup's predictor draws from numpy's global state
            x = np.random.default_rng(seed).multivariate_normal(mean0, cov0, N).T
            pred = ParticlePredictor(tm).predict(
                ParticleState(StateVectors(x), log_weight=np.full(N, -np.log(N)), timestamp=t0), timestamp=t0 + dt
            )
            tic = time.perf_counter()
            post = make(seed).update(SingleHypothesis(pred, det))
            sec += time.perf_counter() - tic
            w = np.exp(np.asarray(post.log_weight, float))
            w /= w.sum()
            ess.append(1.0 / (w**2).sum())
            means.append(np.asarray(post.state_vector, float) @ w)
        means = np.array(means)
        t = np.abs(means.mean(0) - kf) / (means.std(0, ddof=1) / np.sqrt(C))
        rows[name] = (np.array(ess), float(t.max()), sec / C)
    boot = rows["Stone Soup ParticleUpdater (bootstrap)"][0]
    print(f"N = {N} particles, {C} prior clouds; ESS of the updated weights (mean over clouds, SE)\n")
    print("| updater | ESS (SE) | ESS - bootstrap's, paired (SE) | max abs t of the mean vs Kalman | s per update |")
    print("|---|---|---|---|---|")
    for name, (ess, tmax, s) in rows.items():
        diff = ess - boot
        print(
            f"| {name} | {ess.mean():.1f} ({ess.std(ddof=1) / np.sqrt(C):.1f}) | "
            f"{diff.mean():+.1f} ({diff.std(ddof=1) / np.sqrt(C):.1f}) | {tmax:.2f} | {s:.3f} |"
        )


if __name__ == "__main__":
    main()
