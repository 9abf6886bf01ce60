"""Every config composes and builds, with no run, and the component configs stay lean: they extend
the signature nodes of :mod:`torchflow.core.registry` and hold only what differs from the defaults.
A paper-table config that names a missing filter, a wrong key or a bad value fails here, in seconds."""

import inspect
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException, InstantiationException
from hydra.utils import instantiate
from omegaconf import OmegaConf

from torchflow.core import registry

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
EXPERIMENTS = sorted(p.stem for p in (CONFIGS / "experiment").glob("*.yaml"))
COMPONENTS = sorted(
    f"{p.parent.name}/{p.stem}" for g in ("filter", "flow", "model", "schedule") for p in (CONFIGS / g).glob("*.yaml")
)
TDOA = {
    "filter/bs",
    "filter/pfi_d",
    "filter/pfi_s",
    "filter/pfi_os",
    "filter/pfi_os_coarse",
    "filter/pfi_os_a001",
    "filter/pfi_os_a05",
    "model/tdoa",
}  # localisers: model=tdoa
SMALL = ["model.d=4", "n_particles=8"]


def _compose(*overrides):
    registry.register_configs()
    with initialize_config_dir(str(CONFIGS), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def test_there_are_experiment_configs():
    assert len(EXPERIMENTS) >= 10 and "pal2019_table2" in EXPERIMENTS


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_experiment_config_builds_its_model_and_filters(name):
    cfg = _compose(f"experiment={name}")
    assert cfg.trials >= 1 and cfg.steps >= 1 and len(cfg.filter) >= 1
    model = instantiate(cfg.model)
    for key, fcfg in cfg.filter.items():
        assert instantiate(fcfg, model=model) is not None, (name, key)


@pytest.mark.parametrize("name", [e for e in EXPERIMENTS if e != "zhang2024_stiffness_geometric"])
def test_filter_override_selects_exactly_the_named_filters(name):
    """``filter=[...]`` replaces an experiment's selection: every filter an experiment runs is in
    the filter group (its other rows are group configs such as ``pfpf_clustered_k30``), so no row is
    built that the command line did not name; the experiment's settings for the others stay as
    settings only (no ``_target_``; the runner skips them with a message). Not
    ``zhang2024_stiffness_geometric``: it sets its four filters' schedule group in its defaults list,
    so Hydra refuses a selection without them ("Could not override ... No match")."""
    local = name.startswith("zhang2024_table")
    pick = "pfi_d" if local else "ekf"
    cfg = _compose(f"experiment={name}", f"filter=[{pick}]")
    built = sorted(k for k, v in cfg.filter.items() if "_target_" in v)
    assert built == [pick], (name, built)


@pytest.mark.parametrize("name", COMPONENTS)
def test_every_component_config_builds(name):
    group, stem = name.split("/")
    where = {
        "filter": f"filter=[{stem}]",
        "model": f"model={stem}",
        "flow": f"flow@filter.pfpf.flow={stem}",
        "schedule": f"schedule@filter.pfpf.schedule={stem}",
    }[group]
    model = "tdoa" if name in TDOA else stem if group == "model" else "linear_gaussian"
    cfg = _compose(
        f"model={model}",
        *(SMALL if model in ("linear_gaussian", "skewed_t_poisson") else []),
        "filter=[pfpf]" if group in ("flow", "schedule") else "filter=[kf]",
        where,
    )
    node = cfg.model if group == "model" else cfg.filter[stem if group == "filter" else "pfpf"]
    built = instantiate(node) if group == "model" else instantiate(node, model=instantiate(cfg.model))
    built = getattr(built, group) if group in ("flow", "schedule") else built
    target = (node if group in ("filter", "model") else node[group])._target_
    assert type(built).__name__ == target.rsplit(".", 1)[1], name


def test_a_key_the_yaml_does_not_name_is_overridden_without_plus():
    assert "ess_threshold" not in OmegaConf.load(CONFIGS / "filter" / "pfpf.yaml")
    cfg = _compose(
        "model=linear_gaussian",
        *SMALL,
        "filter=[pfpf_ledh]",
        "filter.pfpf_ledh.ess_threshold=0.3",
        "flow@filter.pfpf_ledh.flow=osd",
        "filter.pfpf_ledh.flow.c_rule=printed",
        "model.sigma_z=0.7",
    )
    f = instantiate(cfg.filter.pfpf_ledh, model=instantiate(cfg.model))
    assert f.ess_threshold == 0.3 and f.flow.c_rule == "printed" and cfg.model.sigma_z == 0.7


def test_unknown_keys_fail_clearly():
    with pytest.raises(ConfigCompositionException, match=r"\+filter.bpf.no_such_key=1"):  # Hydra: add a '+'
        _compose("filter=[bpf]", "filter.bpf.no_such_key=1")
    cfg = _compose("model=linear_gaussian", *SMALL, "filter=[bpf]", "+filter.bpf.no_such_key=1")
    with pytest.raises(InstantiationException) as e:  # the constructor refuses it: a one-line config error
        instantiate(cfg.filter.bpf, model=instantiate(cfg.model))
    assert isinstance(e.value.__cause__, TypeError) and "no_such_key" in str(e.value.__cause__)


@pytest.mark.parametrize("path", sorted(registry.targets()))
def test_signature_node_holds_the_constructors_defaults_and_builds(path):
    """Each generated default is the constructor's (they cannot drift); an argument left out has no
    default, is ``*args``/``**kwargs`` or has a default YAML cannot hold; the node builds."""
    cls = registry.resolve(path)
    node, defaults = OmegaConf.create(registry.signature_node(cls, path)), registry.signature_defaults(cls)
    for key, value in OmegaConf.to_container(node).items():
        want = list(defaults[key]) if isinstance(defaults.get(key), tuple) else defaults.get(key, path)
        assert value == want and type(value) is type(want), key
    for p in inspect.signature(cls).parameters.values():
        assert (
            p.name in node
            or p.default is p.empty
            or p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
            or registry.yaml_value(p.default) is registry._NO_YAML
        ), p.name
    if "model" in inspect.signature(cls).parameters:
        local = path.startswith("torchflow.tdoa")  # the localisers run on the TDOA model only
        model = instantiate(_compose("model=tdoa").model if local else _compose("model=linear_gaussian", *SMALL).model)
        assert isinstance(instantiate(node, model=model, **({"n_particles": 8} if "n_particles" in node else {})), cls)
    else:
        assert isinstance(instantiate(node), cls)


@pytest.mark.parametrize("name", COMPONENTS)
def test_component_config_holds_only_what_differs(name):
    """Lean stays lean: the config extends a signature node (or another config of its group) and none
    of its own keys restates the value it would have anyway."""
    group, _ = name.split("/")
    raw = OmegaConf.to_container(OmegaConf.load(CONFIGS / f"{name}.yaml"))
    first = raw.get("defaults", [""])[0]
    base = (next(iter(first)) if isinstance(first, dict) else first).split("@")[0]
    if base.startswith(f"/{registry.GROUP}/"):
        inherited = registry.signature_node(registry.resolve(base.split("/")[-1]))
    else:  # an alias: another config of the group with a change
        assert group == "filter" and base, f"{name}: extends no /{registry.GROUP}/<target> node"
        inherited = OmegaConf.to_container(_compose("model=linear_gaussian", f"filter=[{base}]").filter[base])
    for key, value in raw.items():
        if key not in ("defaults", "_target_") and not str(value).startswith("${"):
            assert key in inherited, f"{name}: {key} is no argument of the target"
            assert isinstance(value, dict) or value != inherited[key], f"{name}: {key}: {value!r} is the default"


def test_pal2019_table2_has_every_paper_row():
    """Pal & Coates (2019) Table II's rows (table) at the paper's particle counts unless overridden."""
    cfg = _compose("experiment=pal2019_table2")
    assert set(cfg.filter) == {
        "pfpf_ledh",
        "pfpf_edh",
        "pfpf_gromov",
        "pfpf_geodesic",
        "gpfis",
        "ledh",
        "edh",
        "gromov",
        "geodesic",
        "ekf",
        "ukf",
        "bpf",
    }
    assert cfg.filter.gpfis.n_particles == 500 and cfg.filter.pfpf_edh.n_particles == 100000
