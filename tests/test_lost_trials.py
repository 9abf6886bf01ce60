"""A lost trial is a result, not a crash: a trial whose filter goes non-finite is marked lost, the
others are scored with the numbers they have without it, and the files say which and how many."""

import pytest
import torch

from torchflow.app.runner import ConfigError, run_experiment
from torchflow.app.runner.checkpoint import ChunkStore
from torchflow.filters import BootstrapParticleFilter, KalmanFilter
from torchflow.models import LinearGaussian

ONE = torch.ones(1, 1, dtype=torch.float64)
TRAP = 20.0  # a particle above this turns NaN


class Trap(LinearGaussian):
    """A random walk whose transition returns NaN for a state above :data:`TRAP`: a trial whose
    prior sits above it goes non-finite at its first step, the others never do."""

    def sample_transition(self, x, generator=None):
        return torch.where(x > TRAP, torch.nan, super().sample_transition(x, generator))


def _setup(B=5, T=12, trapped=(2,)):
    model = Trap(ONE, 0.1 * ONE, ONE, 0.5 * ONE, torch.zeros(1, dtype=torch.float64), ONE)
    traj = model.simulate(B, T, torch.Generator().manual_seed(1))
    mean = torch.zeros(B, 1, dtype=torch.float64)
    mean[list(trapped)] = 100.0
    return model, traj, (mean, ONE.expand(B, 1, 1).clone())


def _run(model, traj, prior, **kw):
    kw.setdefault("progress", False)
    filters = kw.pop("filters", None) or {"bpf": BootstrapParticleFilter(model, n_particles=40)}
    return run_experiment(model, filters, observations=traj.observations, states=traj.states, prior=prior, **kw)


def _trials(res):
    return {r["trial"]: r for r in res.per_trial}


@pytest.mark.parametrize("chunk_size", [5, 2, 1])
def test_a_trial_that_goes_non_finite_is_lost_and_the_others_keep_their_numbers(chunk_size, caplog):
    model, traj, prior = _setup()
    res = _run(model, traj, prior, chunk_size=chunk_size)
    row = res.summary[0]
    assert row["error"] is None and row["lost_trials"] == 1, row
    t = _trials(res)
    assert t[2]["lost_trial"] and t[2]["lost_step"] == 1 and t[2]["rmse"] is None and t[2]["log_evidence"] is None
    assert not any(t[b]["lost_trial"] for b in (0, 1, 3, 4)) and all(t[b]["lost_step"] == 0 for b in (0, 1, 3, 4))
    # the kept trials' numbers do not depend on the lost one: the same as a run where trial 2 is sound
    sound = _run(model, traj, (torch.zeros(5, 1, dtype=torch.float64), prior[1]), chunk_size=5)
    s = _trials(sound)
    for b in (0, 1, 3, 4):
        assert t[b]["rmse"] == s[b]["rmse"] and t[b]["log_evidence"] == s[b]["log_evidence"]
    kept = [s[b]["rmse"] for b in (0, 1, 3, 4)]
    assert row["rmse"] == pytest.approx(sum(kept) / 4, rel=1e-12)
    assert row["log_evidence"] == pytest.approx(sum(s[b]["log_evidence"] for b in (0, 1, 3, 4)) / 4, rel=1e-12)
    assert "trial(s) [2] lost" in caplog.text  # never silent
    assert torch.isfinite(res.estimate_summary["bpf"][0]).all()  # the spread over trials leaves it out


def test_fail_makes_the_filter_fail_as_before():
    model, traj, prior = _setup()
    res = _run(model, traj, prior, nonfinite_trials="fail")
    assert res.summary[0]["error"].startswith("NonFiniteError") and "trial(s) [2]" in res.summary[0]["error"]


def test_every_trial_lost_is_a_failed_row_that_says_so():
    model, traj, prior = _setup(B=3, trapped=(0, 1, 2))
    res = _run(
        model,
        traj,
        prior,
        chunk_size=2,
        filters={"bpf": BootstrapParticleFilter(model, n_particles=20), "kf": KalmanFilter(model)},
    )
    bpf, kf = res.summary
    assert bpf["error"].startswith("NonFiniteError: every trial lost") and bpf["rmse"] is None
    assert kf["error"] is None and kf["lost_trials"] == 0  # the other filter is scored


def test_an_rmse_over_lost_rmse_loses_the_trial_as_dapper_counts():
    model, traj, prior = _setup(trapped=())
    base = _run(model, traj, prior)
    per = sorted((r["rmse"], r["trial"]) for r in base.per_trial)
    cut = (per[-1][0] + per[-2][0]) / 2  # the worst trial is over it
    res = _run(model, traj, prior, lost_rmse=cut)
    t = _trials(res)
    worst = per[-1][1]
    assert res.summary[0]["lost_trials"] == 1 and t[worst]["lost_trial"] and t[worst]["lost_step"] == 0
    assert t[worst]["rmse"] == per[-1][0]  # its value is reported; it is not in the mean
    assert res.summary[0]["rmse"] == pytest.approx(sum(r for r, _ in per[:-1]) / 4, rel=1e-12)
    assert base.summary[0]["lost_trials"] == 0


@pytest.mark.parametrize(
    "kw, message",
    [
        ({"nonfinite_trials": "skip"}, "nonfinite_trials: expected one of"),
        ({"lost_rmse": 0.0}, "lost_rmse: expected a positive RMSE"),
        ({"lost_rmse": "big"}, "lost_rmse: expected a positive RMSE"),
    ],
)
def test_bad_settings_are_refused(kw, message):
    model, traj, prior = _setup()
    with pytest.raises(ConfigError, match=message):
        _run(model, traj, prior, **kw)


def test_a_chunk_with_lost_trials_is_saved_and_loaded_again(tmp_path):
    """Resuming: a saved chunk whose lost trials' rows are NaN is a finished chunk, loaded, not
    computed again; a chunk of lost trials only too."""
    model, traj, prior = _setup(B=4, trapped=(1, 2, 3))  # the second chunk: every trial lost
    first = ChunkStore(tmp_path, {"bpf": "bpf"}, resume=False)
    a = _run(model, traj, prior, chunk_size=2, store=first)
    again = ChunkStore(tmp_path, {"bpf": "bpf"}, resume=True)
    b = _run(model, traj, prior, chunk_size=2, store=again)
    assert again.loaded["bpf"] == 2 and again.computed["bpf"] == 0
    assert a.per_trial == [{**r} for r in b.per_trial] and b.summary[0]["lost_trials"] == 3
    # other boundaries: trials put together from the saved chunks
    third = ChunkStore(tmp_path, {"bpf": "bpf"}, resume=True)
    c = _run(model, traj, prior, chunk_size=4, store=third)
    assert [r["rmse"] for r in c.per_trial] == [r["rmse"] for r in a.per_trial]
    assert [r["lost_trial"] for r in c.per_trial] == [False, True, True, True]
