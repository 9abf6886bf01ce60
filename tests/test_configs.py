"""Every experiment config composes and builds its model and every filter it selects, with no run.

A paper-table config that names a missing filter, a wrong key or a bad value fails here, in
seconds, instead of at the start of an hours-long run."""
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENTS = sorted(p.stem for p in (ROOT / "configs" / "experiment").glob("*.yaml"))


def test_there_are_experiment_configs():
    assert len(EXPERIMENTS) >= 10 and "seed000_table2" in EXPERIMENTS


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_experiment_config_builds_its_model_and_filters(name):
    with initialize_config_dir(str(ROOT / "configs"), version_base="1.3"):
        cfg = compose("config", overrides=[f"experiment={name}"])
    assert cfg.trials >= 1 and cfg.steps >= 1
    model = instantiate(cfg.model)
    assert len(cfg.filter) >= 1, f"{name}: selects no filter"
    for key, fcfg in cfg.filter.items():
        f = instantiate(fcfg, model=model)
        assert f is not None, (name, key)


def test_seed000_table2_has_every_paper_row():
    """Seed 000 Table II's rows (MODELS.md §7 table): the flows with and without weights, GPFIS,
    EKF, UKF and the BPF, at the paper's particle counts unless overridden."""
    with initialize_config_dir(str(ROOT / "configs"), version_base="1.3"):
        cfg = compose("config", overrides=["experiment=seed000_table2"])
    assert set(cfg.filter) == {"pfpf_ledh", "pfpf_edh", "pfpf_gromov", "pfpf_geodesic", "gpfis", "ledh", "edh",
                               "gromov", "geodesic", "ekf", "ukf", "bpf"}
    assert cfg.filter.gpfis.n_particles == 500 and cfg.filter.pfpf_edh.n_particles == 100000
