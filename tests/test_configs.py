"""Every config composes and builds, with no run; the configs stay lean.

The component configs (filter/, flow/, model/, schedule/) extend the signature nodes of
:mod:`torchflow.registry` (every constructor argument with its default) and hold only what differs.
A paper-table config that names a missing filter, a wrong key or a bad value fails here, in
seconds, instead of at the start of an hours-long run."""
import inspect
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException, InstantiationException
from hydra.utils import instantiate
from omegaconf import OmegaConf

from torchflow import registry

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
EXPERIMENTS = sorted(p.stem for p in (CONFIGS / "experiment").glob("*.yaml"))
#: written out in full (their keys are the constructors' defaults): the TDOA localisers, reworked elsewhere
NOT_LEAN = {"filter/bs", "filter/pfi_d", "filter/pfi_s", "filter/pfi_os", "model/tdoa"}
#: small sizes per model, so that every filter is built quickly
SMALL = {"linear_gaussian": ["model.d=4"], "skewed_t_poisson": ["model.d=4"], "acoustic": [], "tdoa": []}


def _names(group):
    return sorted(p.stem for p in (CONFIGS / group).glob("*.yaml"))


def _compose(overrides):
    registry.register_configs()
    with initialize_config_dir(str(CONFIGS), version_base="1.3"):
        return compose("config", overrides=overrides)


def _parent(raw):
    """The first defaults entry of a raw YAML config (its base: a signature node or another config)."""
    first = OmegaConf.to_container(raw).get("defaults", [None])[0]
    return next(iter(first)) if isinstance(first, dict) else first


def test_there_are_experiment_configs():
    assert len(EXPERIMENTS) >= 10 and "seed000_table2" in EXPERIMENTS


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_experiment_config_builds_its_model_and_filters(name):
    cfg = _compose([f"experiment={name}"])
    assert cfg.trials >= 1 and cfg.steps >= 1
    model = instantiate(cfg.model)
    assert len(cfg.filter) >= 1, f"{name}: selects no filter"
    for key, fcfg in cfg.filter.items():
        f = instantiate(fcfg, model=model)
        assert f is not None, (name, key)


@pytest.mark.parametrize("name", _names("filter"))
def test_every_filter_config_builds(name):
    model = "tdoa" if name in ("bs", "pfi_d", "pfi_s", "pfi_os") else "linear_gaussian"
    cfg = _compose([f"model={model}", *SMALL[model], f"filter=[{name}]", "n_particles=8"])
    f = instantiate(cfg.filter[name], model=instantiate(cfg.model), name=name)
    assert f.name == name and f.__class__.__name__ == cfg.filter[name]._target_.rsplit(".", 1)[1]


@pytest.mark.parametrize("group", ["flow", "schedule"])
def test_every_flow_and_schedule_config_builds(group):
    for name in _names(group):
        cfg = _compose(["model=linear_gaussian", "model.d=4", "filter=[pfpf]", f"{group}@filter.pfpf.{group}={name}"])
        f = instantiate(cfg.filter.pfpf, model=instantiate(cfg.model))
        built = f.flow if group == "flow" else f.schedule
        assert type(built).__name__ == cfg.filter.pfpf[group]._target_.rsplit(".", 1)[1], name


@pytest.mark.parametrize("name", _names("model"))
def test_every_model_config_builds(name):
    cfg = _compose([f"model={name}", *SMALL[name], "filter=[kf]"])
    assert type(instantiate(cfg.model)).__name__ == cfg.model._target_.rsplit(".", 1)[1]


def test_a_key_the_yaml_does_not_name_is_overridden_without_plus():
    raw = OmegaConf.load(CONFIGS / "filter" / "pfpf.yaml")
    assert "ess_threshold" not in raw and "c_rule" not in OmegaConf.load(CONFIGS / "flow" / "osd.yaml")
    cfg = _compose(["model=linear_gaussian", "model.d=4", "filter=[pfpf_ledh]", "filter.pfpf_ledh.ess_threshold=0.3",
                    "flow@filter.pfpf_ledh.flow=osd", "filter.pfpf_ledh.flow.c_rule=printed", "model.sigma_z=0.7",
                    "n_particles=8"])
    f = instantiate(cfg.filter.pfpf_ledh, model=instantiate(cfg.model))
    assert f.ess_threshold == 0.3 and f.flow.c_rule == "printed" and cfg.model.sigma_z == 0.7


def test_unknown_keys_fail_clearly():
    with pytest.raises(ConfigCompositionException, match=r"\+filter.bpf.no_such_key=1"):  # Hydra says: add a '+'
        _compose(["filter=[bpf]", "filter.bpf.no_such_key=1"])
    cfg = _compose(["model=linear_gaussian", "model.d=4", "filter=[bpf]", "+filter.bpf.no_such_key=1"])
    with pytest.raises(InstantiationException) as e:  # the constructor refuses it (a one-line config error)
        instantiate(cfg.filter.bpf, model=instantiate(cfg.model))
    assert isinstance(e.value.__cause__, TypeError) and "no_such_key" in str(e.value.__cause__)


def test_signature_nodes_hold_the_constructors_defaults():
    """Each generated default is the constructor's default (so the two cannot drift); an argument
    left out has no default, is ``*args``/``**kwargs``, or has a default YAML cannot hold."""
    registry.register_configs()
    targets = registry.targets()
    assert len(targets) >= 25
    for path, cls in targets.items():
        node = OmegaConf.create(registry.signature_node(cls, path))
        assert node._target_ == path and registry.resolve(path) is cls
        defaults = registry.signature_defaults(cls)
        for key, value in OmegaConf.to_container(node).items():
            if key != "_target_":
                expected = list(defaults[key]) if isinstance(defaults[key], tuple) else defaults[key]
                assert value == expected and type(value) is type(expected), (path, key)
        for p in inspect.signature(cls).parameters.values():
            if p.name not in node:
                assert (p.default is p.empty or p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
                        or registry._yaml_value(p.default) is registry._MISSING), (path, p.name)


def test_every_signature_node_builds_with_a_model():
    model = instantiate(_compose(["model=linear_gaussian", "model.d=4", "filter=[kf]"]).model)
    for path, cls in registry.targets().items():
        node = registry.signature_node(cls, path)
        if path.startswith(("torchflow.models.", "torchflow.localisation.")):
            continue
        needs_model = "model" in inspect.signature(cls).parameters
        node.update({"n_particles": 8} if "n_particles" in node else {})
        assert instantiate(node, **({"model": model} if needs_model else {})) is not None, path


@pytest.mark.parametrize("name", [f"{g}/{n}" for g in ("filter", "flow", "model", "schedule") for n in _names(g)])
def test_component_configs_hold_only_what_differs(name):
    """Lean stays lean: a component config extends a signature node (directly or through another
    config of its group) and none of its own keys restates the value it would have anyway."""
    if name in NOT_LEAN:
        pytest.skip("written out in full until the TDOA localisers are reworked")
    group, stem = name.split("/")
    raw = OmegaConf.load(CONFIGS / f"{name}.yaml")
    parent = _parent(raw)
    assert parent, f"{name}: extends nothing (expected /signature/<target>@_here_ first in its defaults)"
    base = parent.split("@")[0]
    if base.startswith(f"/{registry.GROUP}/"):
        inherited = registry.signature_node(registry.resolve(base.split("/")[-1]))
    else:  # another config of the group (an alias with one change)
        cfg = _compose(["model=linear_gaussian", f"filter=[{base}]"] if group == "filter" else [f"{group}={base}"])
        inherited = OmegaConf.to_container(cfg.filter[base] if group == "filter" else cfg[group])
    own = {k: v for k, v in OmegaConf.to_container(raw).items() if k not in ("defaults", "_target_")}
    for key, value in own.items():
        if isinstance(value, str) and value.startswith("${"):
            continue
        assert key in inherited, f"{name}: {key} is no argument of the target"
        if not isinstance(value, dict):
            assert value != inherited[key], f"{name}: {key}: {value!r} is the default; leave it out"


def test_seed000_table2_has_every_paper_row():
    """Seed 000 Table II's rows (MODELS.md §7 table): the flows with and without weights, GPFIS,
    EKF, UKF and the BPF, at the paper's particle counts unless overridden."""
    cfg = _compose(["experiment=seed000_table2"])
    assert set(cfg.filter) == {"pfpf_ledh", "pfpf_edh", "pfpf_gromov", "pfpf_geodesic", "gpfis", "ledh", "edh",
                               "gromov", "geodesic", "ekf", "ukf", "bpf"}
    assert cfg.filter.gpfis.n_particles == 500 and cfg.filter.pfpf_edh.n_particles == 100000
