"""FlowParticleUpdater on bad input and numerical faults: each is refused with an error that names
it, or gets a documented treatment; whatever the updater returns is finite (skipped without Stone Soup)."""

import datetime
import warnings

import numpy as np
import pytest

stonesoup = pytest.importorskip("stonesoup")

from stonesoup.models.measurement.linear import LinearGaussian
from stonesoup.models.measurement.nonlinear import CartesianToBearingRange, CartesianToElevationBearingRange
from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel, ConstantVelocity
from stonesoup.predictor.particle import ParticlePredictor
from stonesoup.resampler.particle import SystematicResampler
from stonesoup.types.array import StateVectors
from stonesoup.types.detection import Detection, MissedDetection
from stonesoup.types.hypothesis import SingleHypothesis
from stonesoup.types.prediction import Prediction
from stonesoup.types.state import ParticleState
from stonesoup.types.update import ParticleStateUpdate

import torchflow.interop.stonesoup as tss
from torchflow.core.errors import ArgumentError, ArgumentTypeError, NonFiniteError
from torchflow.interop.stonesoup import FlowParticleUpdater, StoneSoupMeasurement

# the guide's scenario: a CV target, a bearing-range sensor at (50, 0); few particles (speed)
T0, DT, N = datetime.datetime(2020, 1, 1), datetime.timedelta(seconds=5), 40
TM = CombinedLinearGaussianTransitionModel([ConstantVelocity(0.05), ConstantVelocity(0.05)])
RADAR = CartesianToBearingRange(
    ndim_state=4, mapping=(0, 2), noise_covar=np.diag([np.radians(0.2), 1.0]), translation_offset=np.array([[50], [0]])
)
Z = np.array([[2.44], [46.0]])


def _prior(mean=(0, 1, 0, 1), n=N, t=T0):
    x = np.random.default_rng(0).multivariate_normal(mean, np.diag([1.5, 0.5, 1.5, 0.5]), n).T
    return ParticleState(StateVectors(x), log_weight=np.full(n, -np.log(n)), timestamp=t)


def _prediction(prior=None, t=T0 + DT):
    np.random.seed(0)  # Stone Soup's predictor draws from numpy's global state
    return ParticlePredictor(TM).predict(_prior() if prior is None else prior, timestamp=t)


def _det(z=Z, t=T0 + DT, model=RADAR):
    return Detection(np.asarray(z, float), timestamp=t, measurement_model=model)


def _with(pred, **changes):
    return Prediction.from_state(pred, **changes)


def _update(pred, det=None, **kw):
    return FlowParticleUpdater(RADAR, **kw).update(SingleHypothesis(pred, _det() if det is None else det))


def _no_flow(monkeypatch):
    """Fail the test if the flow runs: the refusal must come before any work."""

    def fail(*a, **k):
        raise AssertionError("the flow ran")

    monkeypatch.setattr(tss, "integrate_flow", fail)


def _finite(post):
    assert np.isfinite(np.asarray(post.state_vector, float)).all()
    lw = np.asarray(post.log_weight, float)
    assert not np.isnan(lw).any() and not np.isposinf(lw).any() and np.exp(lw).sum() == pytest.approx(1.0)


# ---- the updater's own arguments ----------------------------------------------------------------


def test_a_measurement_model_that_is_not_a_stone_soup_model_is_refused_at_construction():
    with pytest.raises(ArgumentTypeError, match="measurement_model: expected a Stone Soup MeasurementModel, got str"):
        FlowParticleUpdater("radar")
    # None is Stone Soup's "every detection carries its own model"
    post = FlowParticleUpdater(None).update(SingleHypothesis(_prediction(), _det()))
    _finite(post)


@pytest.mark.parametrize(
    "covar, got",
    [
        (np.zeros((2, 2)), "smallest eigenvalue 0"),
        (-np.eye(2), "smallest eigenvalue -1"),
        (np.array([[1.0, 0.5], [0.0, 1.0]]), "an asymmetric one"),
        (np.diag([np.nan, 1.0]), "1 NaN or infinite entries"),
    ],
)
def test_a_noise_covariance_that_is_not_symmetric_positive_definite_is_refused(covar, got):
    lg = LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=covar)
    with pytest.raises(
        ArgumentError,
        match=rf"measurement_model.noise_covar: expected a (finite )?symmetric positive "
        rf"definite matrix, got {got}",
    ):
        FlowParticleUpdater(lg)
    # carried by the detection: named as the detection's, refused before the flow runs
    with pytest.raises(ArgumentError, match=rf"detection.measurement_model.noise_covar: .* got {got}"):
        _update(_prediction(), _det([[1.0], [1.0]], model=lg))


def test_update_refuses_what_is_not_a_hypothesis():
    with pytest.raises(
        ArgumentTypeError,
        match=r"hypothesis: expected a Stone Soup SingleHypothesis \(a prediction and "
        r"a detection\), got NoneType",
    ):
        FlowParticleUpdater(RADAR).update(None)


# ---- missed detections and timestamps -----------------------------------------------------------


def test_a_missed_detection_carries_the_prediction_forward(monkeypatch):
    pred = _prediction()
    hyp = SingleHypothesis(pred, MissedDetection(timestamp=pred.timestamp))
    _no_flow(monkeypatch)
    # as Stone Soup's trackers treat a missed hypothesis: the prediction's particles and weights,
    # here as an Update that carries the hypothesis; not resampled even with a resampler set
    post = FlowParticleUpdater(RADAR, resampler=SystematicResampler()).update(hyp)
    assert isinstance(post, ParticleStateUpdate) and post.hypothesis is hyp and post.timestamp == pred.timestamp
    np.testing.assert_array_equal(np.asarray(post.state_vector), np.asarray(pred.state_vector))
    np.testing.assert_array_equal(post.log_weight, pred.log_weight)
    # Stone Soup's other form of the null hypothesis: no detection at all
    post = FlowParticleUpdater(RADAR).update(SingleHypothesis(pred, None))
    assert post.timestamp == pred.timestamp
    np.testing.assert_array_equal(np.asarray(post.state_vector), np.asarray(pred.state_vector))


def test_a_detection_later_than_the_prediction_is_refused():
    with pytest.raises(
        ArgumentError,
        match=r"detection.timestamp: expected the prediction's timestamp 2020-01-01 "
        r"00:00:05, got 2020-01-01 00:00:20 \(after it by 0:00:15\); predict to the "
        r"detection's time first",
    ):
        _update(_prediction(), _det(t=T0 + 4 * DT))


def test_a_detection_before_the_parent_is_refused():
    with pytest.raises(
        ArgumentError,
        match=r"detection.timestamp: expected the prediction's timestamp 2020-01-01 "
        r"00:00:05, got 2019-12-31 23:59:55 \(before it by 0:00:10, before the "
        r"prediction's parent at 2020-01-01 00:00:00\); predict to the detection's",
    ):
        _update(_prediction(), _det(t=T0 - DT))


def test_a_detection_without_timestamp_is_taken_at_the_prediction_time():
    pred = _prediction()
    post = _update(pred, _det(t=None))
    ref = _update(pred, _det())
    assert post.timestamp == pred.timestamp
    np.testing.assert_array_equal(np.asarray(post.state_vector), np.asarray(ref.state_vector))


def test_a_prediction_before_its_parent_is_refused_as_out_of_order():
    pred = _prediction(_prior(t=T0 + 2 * DT), t=T0 + DT)  # the track's last state is later than the detection
    with pytest.raises(
        ArgumentError,
        match=r"prediction.timestamp: expected a time at or after its parent's 2020-01-01 "
        r"00:00:10, got 2020-01-01 00:00:05 \(a negative interval",
    ):
        _update(pred)


def test_a_prediction_without_timestamp_is_refused_where_the_transition_needs_the_interval():
    with pytest.raises(
        ArgumentError,
        match=r"prediction.timestamp: CombinedLinearGaussianTransitionModel needs the "
        r"interval between the prediction and its parent, got timestamps None",
    ):
        _update(_with(_prediction(), timestamp=None))


# ---- the detection ------------------------------------------------------------------------------


def test_a_non_finite_detection_is_refused_before_the_flow(monkeypatch):
    _no_flow(monkeypatch)
    with pytest.raises(
        ArgumentError,
        match=r"detection.state_vector: expected finite values, got \[nan, 46.0\] \(NaN "
        r"or infinite at entries \[0\]\)",
    ):
        _update(_prediction(), _det([[np.nan], [46.0]]))
    with pytest.raises(ArgumentError, match=r"detection.state_vector: expected 2 values, got None"):
        _update(_prediction(), Detection(None, timestamp=T0 + DT, measurement_model=RADAR))


def test_a_detection_model_other_than_the_updaters_is_the_one_used():
    """Stone Soup's rule: the detection's own model wins over the updater's."""
    lg = LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=np.eye(2))
    pred, det = _prediction(), _det([[7.0], [19.0]], model=lg)
    post = FlowParticleUpdater(RADAR).update(SingleHypothesis(pred, det))
    ref = FlowParticleUpdater(lg).update(SingleHypothesis(pred, det))
    np.testing.assert_allclose(np.asarray(post.state_vector, float), np.asarray(ref.state_vector, float))
    six = CartesianToBearingRange(ndim_state=6, mapping=(0, 2), noise_covar=np.diag([0.01, 1.0]))
    with pytest.raises(ArgumentError, match="the measurement model has ndim_state 6, the particles 4 dimensions"):
        _update(pred, _det(model=six))


# ---- the prediction -----------------------------------------------------------------------------


def test_a_prediction_without_particles_is_refused():
    empty = ParticleState(StateVectors(np.zeros((4, 0))), log_weight=np.zeros(0), timestamp=T0 + DT)
    with pytest.raises(ArgumentError, match=r"prediction.state_vector: expected at least one particle, got none"):
        _update(empty)


def test_a_prediction_with_every_weight_zero_is_refused_without_numpy_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(
            ArgumentError,
            match=r"prediction.log_weight: expected at least one positive weight, got all "
            rf"{N} weights zero \(every log-weight -inf\)",
        ):
            _update(_with(_prediction(), log_weight=np.full(N, -np.inf)))


@pytest.mark.parametrize("value, kind", [(np.nan, "NaN"), (np.inf, r"\+inf")])
def test_a_nan_or_infinite_prediction_weight_is_refused_with_its_count(value, kind):
    lw = np.full(N, -np.log(N))
    lw[[3, 7]] = value
    with pytest.raises(
        ArgumentError,
        match=rf"prediction.log_weight: expected real log-weights \(-inf for a zero "
        rf"weight\), got 2 {kind} of {N}",
    ):
        _update(_with(_prediction(), log_weight=lw))


def test_missing_or_misshapen_prediction_weights_are_refused():
    with pytest.raises(ArgumentError, match=rf"prediction.log_weight: expected {N} log-weights, got None"):
        _update(_with(_prediction(), log_weight=None))
    with pytest.raises(
        ArgumentError,
        match=rf"prediction.log_weight: expected {N} log-weights \(one per particle\), "
        r"got shape \(5,\)",
    ):
        _update(_with(_prediction(), log_weight=np.zeros(5)))


def test_a_non_finite_particle_is_refused_with_its_count():
    pred = _prediction()
    x = np.asarray(pred.state_vector, float).copy()
    x[0, 5], x[3, 9] = np.nan, np.inf
    with pytest.raises(
        ArgumentError,
        match=rf"prediction.state_vector: expected finite particles, got 2 of {N} with NaN "
        r"or infinite entries \(particles \[5, 9\]\)",
    ):
        _update(_with(pred, state_vector=StateVectors(x)))


def test_a_parent_that_does_not_fit_the_prediction_is_refused():
    pred = _prediction()
    with pytest.raises(
        ArgumentError,
        match=rf"prediction.parent.state_vector: expected {N} particles \(one per "
        r"particle of the prediction\), got 10",
    ):
        _update(_with(pred, parent=pred.parent[:10]))


def test_unnormalised_prediction_weights_give_the_normalised_posterior():
    pred = _prediction()
    post = _update(_with(pred, log_weight=np.asarray(pred.log_weight, float) + 700.0))
    ref = _update(pred)
    _finite(post)
    np.testing.assert_allclose(np.asarray(post.log_weight, float), np.asarray(ref.log_weight, float), atol=1e-9)


@pytest.mark.parametrize("flow", ["ledh", "edh", "gromov", "geodesic", "osd"])
def test_float32_predictions_and_updaters_give_finite_posteriors(flow):
    pred = _prediction()
    pred32 = _with(pred, state_vector=StateVectors(np.asarray(pred.state_vector, np.float32)))
    post = _update(pred32, flow=flow, dtype="float32")
    _finite(post)
    if flow in ("gromov", "osd"):  # stochastic: float32 noise draws differ from float64's
        return
    ref = _update(pred, flow=flow)
    np.testing.assert_allclose(np.asarray(post.mean, float), np.asarray(ref.mean, float), rtol=1e-2, atol=0.3)


# ---- the flow's own result ----------------------------------------------------------------------


@pytest.mark.parametrize("flow", ["ledh", "edh", "gromov", "geodesic", "osd"])
@pytest.mark.parametrize("parent", [True, False])
def test_particles_at_the_sensor_raise_a_non_finite_error_naming_the_singular_point(flow, parent):
    at_sensor = ParticleState(
        StateVectors(np.tile([[50.0], [0.0], [0.0], [0.0]], N)),
        log_weight=np.full(N, -np.log(N)),
        timestamp=T0 + (0 * DT if parent else DT),
    )
    pred = _prediction(at_sensor) if parent else at_sensor
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the unweighted-flow warning
        with pytest.raises(
            NonFiniteError,
            match=r"FlowParticleUpdater: non-finite .* update at 2020-01-01 00:00:05 .*"
            r"CartesianToBearingRange is singular at its sensor position \[50.0, "
            r"0.0\] \(range 0",
        ):
            _update(pred, _det([[0.0], [0.0]]), flow=flow)


def test_non_finite_flow_weights_raise_a_non_finite_error(monkeypatch):
    import torch

    monkeypatch.setattr(
        StoneSoupMeasurement,
        "measurement_log_prob",
        lambda self, z, x: torch.full(x.shape[:-1], float("nan"), dtype=x.dtype),
    )
    with pytest.raises(
        NonFiniteError,
        match=rf"FlowParticleUpdater: non-finite log-weights after the LEDHFlow update at "
        rf"2020-01-01 00:00:05 \({N} of {N} particles",
    ):
        _update(_prediction())


# ---- issue cases SS9, SS11, SS12, SS14, SS26: one line naming the argument ------------------------


@pytest.mark.parametrize(
    "model",
    [
        CartesianToBearingRange(ndim_state=4, mapping=(0, 5), noise_covar=np.diag([0.01, 1.0])),
        CartesianToElevationBearingRange(ndim_state=4, mapping=(0, 2, 4), noise_covar=np.diag([0.01, 0.01, 1.0])),
    ],
)
def test_a_mapping_outside_the_state_is_refused(model):
    with pytest.raises(ArgumentError, match=r"measurement_model.mapping: expected state indices in \[0, 4\)"):
        StoneSoupMeasurement(model, np.zeros(model.ndim_meas))


@pytest.mark.parametrize(
    "resampler, got",
    [(SystematicResampler, "the class SystematicResampler"), ("systematic", "'systematic'")],
)
def test_a_resampler_must_be_an_instance(resampler, got):
    with pytest.raises(ArgumentTypeError, match=f"resampler: expected a Stone Soup Resampler instance .*got {got}"):
        FlowParticleUpdater(RADAR, resampler=resampler)
    FlowParticleUpdater(RADAR, resampler=SystematicResampler())  # an instance is fine


@pytest.mark.parametrize("seed", ["abc", 1.5, True])
def test_a_seed_must_be_an_integer(seed):
    with pytest.raises(ArgumentTypeError, match="seed: expected an integer"):
        FlowParticleUpdater(RADAR, seed=seed)


def test_a_detection_carrying_a_transition_model_is_refused(monkeypatch):
    _no_flow(monkeypatch)
    with pytest.raises(ArgumentTypeError, match="detection.measurement_model: expected a Stone Soup MeasurementModel"):
        _update(_prediction(), _det(model=TM))
