"""torchflow's flows inside a Stone Soup tracking loop, beside Stone Soup's own updaters.

    pip install -e ".[stonesoup]"
    python experiments/stonesoup_example.py [--runs 10] [--steps 20] [--particles 500] [--plot tracks.png]

The scenario of Stone Soup's particle filter tutorial: a 2-D nearly-constant-velocity target
(``CombinedLinearGaussianTransitionModel`` of two ``ConstantVelocity(0.05)``, 5 s steps) seen by a
bearing-range sensor at (50, 0) (``CartesianToBearingRange`` with the tutorial's noise covariance
``np.diag([np.radians(0.2), 1])``: bearing variance 0.0035 rad^2, range variance 1 m^2). Each run simulates a truth
with Stone Soup's
``SingleTargetGroundTruthSimulator`` and detections with the measurement model, then runs every
updater from the same prior particles with Stone Soup's ``ParticlePredictor`` and an
``ESSResampler`` (N/2) after each update:

* Stone Soup ``ParticleUpdater`` (bootstrap);
* Stone Soup ``GromovFlowParticleUpdater`` as shipped (weights unchanged by the flow);
* torchflow ``FlowParticleUpdater`` with LEDH and with Gromov (PF-PF weights: the predictions carry
  their parents and the linear-Gaussian transition).

Printed per updater: position RMSE (Stone Soup's ``Euclidean`` measure on (x, y), over runs and
steps; and each run's RMSE averaged over runs with its standard error), the mean ESS of the updated weights before
resampling, and seconds per update (the update
call only, the same for all). ``--plot`` saves Stone Soup's plot of the last run's truth, detections
and tracks.
"""

from __future__ import annotations

import argparse
import datetime
import time
import warnings

import numpy as np


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--particles", type=int, default=500)
    ap.add_argument("--plot", default=None, help="save Stone Soup's plot of the last run here (.png)")
    ap.add_argument("--skip-stonesoup-gromov", action="store_true", help="leave out Stone Soup's Gromov updater (slow)")
    a = ap.parse_args(argv)

    from stonesoup.measures import Euclidean
    from stonesoup.models.measurement.nonlinear import CartesianToBearingRange
    from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel, ConstantVelocity
    from stonesoup.predictor.particle import ParticlePredictor
    from stonesoup.resampler.particle import ESSResampler
    from stonesoup.simulator.simple import SingleTargetGroundTruthSimulator
    from stonesoup.types.array import StateVectors
    from stonesoup.types.detection import Detection
    from stonesoup.types.hypothesis import SingleHypothesis
    from stonesoup.types.state import GaussianState, ParticleState
    from stonesoup.types.track import Track
    from stonesoup.updater.particle import GromovFlowParticleUpdater, ParticleUpdater

    from torchflow.interop.stonesoup import FlowParticleUpdater

    t0 = datetime.datetime(2020, 1, 1)
    tm = CombinedLinearGaussianTransitionModel([ConstantVelocity(0.05), ConstantVelocity(0.05)])
    mm = CartesianToBearingRange(
        ndim_state=4,
        mapping=(0, 2),
        noise_covar=np.diag([np.radians(0.2), 1]),
        translation_offset=np.array([[50], [0]]),
    )
    updaters = {"Stone Soup ParticleUpdater": ParticleUpdater(mm)}
    if not a.skip_stonesoup_gromov:
        updaters["Stone Soup GromovFlowParticleUpdater"] = GromovFlowParticleUpdater(mm)
    updaters["torchflow FlowParticleUpdater (LEDH)"] = FlowParticleUpdater(mm, flow="ledh")
    updaters["torchflow FlowParticleUpdater (Gromov)"] = FlowParticleUpdater(mm, flow="gromov")
    stats = {k: dict(err=[], ess=[], sec=[], failed=0, run_rmse=[]) for k in updaters}
    euclid = Euclidean(mapping=(0, 2))
    tracks = {}
    for run in range(a.runs):
        np.random.seed(run)
        sim = SingleTargetGroundTruthSimulator(
            transition_model=tm,
            initial_state=GaussianState([[0], [1], [0], [1]], np.diag([0.0] * 4), timestamp=t0),
            timestep=datetime.timedelta(seconds=5),
            number_steps=a.steps + 1,
        )
        truth = [next(iter(paths)).states[-1] for _, paths in sim]
        detections = [
            Detection(mm.function(s, noise=True), timestamp=s.timestamp, measurement_model=mm) for s in truth[1:]
        ]
        x0 = np.random.default_rng(run).multivariate_normal([0, 1, 0, 1], np.diag([1.5, 0.5, 1.5, 0.5]), a.particles).T
        for name, updater in updaters.items():
            np.random.seed(1000 + run)  # the predictor's and the resampler's numpy draws
            state = ParticleState(StateVectors(x0), log_weight=np.full(a.particles, -np.log(a.particles)), timestamp=t0)
            predictor, resampler, track = ParticlePredictor(tm), ESSResampler(), Track()
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    for det, gt in zip(detections, truth[1:]):
                        pred = predictor.predict(state, timestamp=det.timestamp)
                        tic = time.perf_counter()
                        post = updater.update(SingleHypothesis(pred, det))
                        stats[name]["sec"].append(time.perf_counter() - tic)
                        w = np.exp(np.asarray(post.log_weight, float))
                        stats[name]["ess"].append(1.0 / (w**2).sum())
                        stats[name]["err"].append(euclid(post, gt) ** 2)
                        track.append(post)
                        state = resampler.resample(post)
            except Exception:
                stats[name]["failed"] += 1
            if len(track):
                stats[name]["run_rmse"].append(np.sqrt(np.mean(stats[name]["err"][-len(track) :])))
            tracks[name] = track
    print(f"{a.runs} runs x {a.steps} steps, N = {a.particles} particles, bearing-range sensor\n")
    print(
        "| updater | position RMSE | RMSE per run: mean (SE) | mean ESS before resampling | s per update | runs "
        "failed |"
    )
    print("|---|---|---|---|---|---|")
    for name, s in stats.items():
        rmse = np.sqrt(np.mean(s["err"])) if s["err"] else float("nan")
        r = np.array(s["run_rmse"])
        per_run = f"{r.mean():.3g} ({r.std(ddof=1) / np.sqrt(len(r)):.2g})" if len(r) > 1 else "-"
        print(
            f"| {name} | {rmse:.4g} | {per_run} | {np.mean(s['ess']) if s['ess'] else float('nan'):.1f} | "
            f"{np.mean(s['sec']) if s['sec'] else float('nan'):.4f} | {s['failed']} |"
        )
    if a.plot:
        import matplotlib

        matplotlib.use("Agg")
        from stonesoup.plotter import Plotter
        from stonesoup.types.groundtruth import GroundTruthPath

        plotter = Plotter()
        plotter.plot_ground_truths({GroundTruthPath(truth)}, [0, 2])
        plotter.plot_measurements(detections, [0, 2])
        for name, track in tracks.items():
            if len(track):
                plotter.plot_tracks({track}, [0, 2], track_label=name)
        plotter.fig.savefig(a.plot, dpi=120, bbox_inches="tight")
        print(f"\nplot: {a.plot}")


if __name__ == "__main__":
    main()
