"""The command line's configuration: where the Hydra configs are, and checks of a composed config
and of the command line that Hydra itself does not make (one clear line each, no traceback)."""

from __future__ import annotations

import contextlib
import difflib
import json
import os
import re
import shlex
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path
from typing import List, Mapping, Optional, Sequence, Tuple

import torch
from omegaconf import OmegaConf

from torchflow.app.runner.plan import (
    NONFINITE_TRIALS,
    ConfigError,
    check_metric_settings,
    check_rng_backend,
    check_seed,
    check_warmup,
    require,
)

_CHECKOUT = Path(__file__).resolve().parents[2]
#: subtrees of the config whose keys are constructor arguments (checked by the constructors) or named
#: by the user (the run command's priors and starting values of ``task=pmmh``), by their dotted path
FREE_FORM = ("model", "filter", "hydra", "pmmh.priors", "pmmh.init")
#: the command line's name in messages (the entry point that started this process sets it)
PROG_ENV, ARGV_ENV = "TORCHFLOW_PROG", "TORCHFLOW_ARGV"


def config_source() -> str:
    """Hydra's config path: the checkout's ``configs/`` when torchflow runs from a source checkout
    (editable install or ``PYTHONPATH``), else the installed package ``torchflow.configs``."""
    if (_CHECKOUT / "pyproject.toml").is_file() and (_CHECKOUT / "configs" / "config.yaml").is_file():
        return str(_CHECKOUT / "configs")
    return "pkg://torchflow.configs"


def config_dir() -> Path:
    """The folder holding ``config.yaml`` and the config groups."""
    src = config_source()
    return Path(str(files("torchflow.configs"))) if src.startswith("pkg://") else Path(src)


def group_options(group: str, extra_dirs: Sequence[Path] = ()) -> Optional[List[str]]:
    """Config names of a group (``filter``, ``model``, ...) in torchflow's configs and in
    ``extra_dirs`` (a user's own config folders, :func:`user_config_dirs`), ``None`` if no folder
    has such a group."""
    folders = [d / group for d in (config_dir(), *extra_dirs) if (d / group).is_dir()]
    return sorted({p.stem for d in folders for p in d.glob("*.yaml")}) if folders else None


def user_config_dirs(argv: Sequence[str]) -> List[Path]:
    """The user's own config folders a command line names, as Hydra reads them: ``--config-dir DIR``
    (``-cd DIR``, ``--config-dir=DIR``) and the ``file://`` or ``pkg://`` entries of
    ``hydra.searchpath=[...]``; a folder that does not exist is refused in one line."""
    out, args = [], list(argv)
    for i, arg in enumerate(args):
        value = None
        if arg in ("--config-dir", "-cd") and i + 1 < len(args):
            value = args[i + 1]
        elif arg.startswith("--config-dir="):
            value = arg.split("=", 1)[1]
        if value is not None:
            out.append(("--config-dir", value))
        if arg.lstrip("+").startswith("hydra.searchpath="):
            for entry in re.findall(r"[^\[\],\s'\"]+", arg.split("=", 1)[1]):
                out.append(("hydra.searchpath", entry))
    dirs = []
    for source, entry in out:
        if entry.startswith("pkg://"):
            try:
                path = Path(str(files(entry[len("pkg://") :].replace("/", "."))))
            except (ModuleNotFoundError, TypeError) as err:
                raise ConfigError(f"{source}: {entry}: no importable package ({err})") from None
        else:
            path = Path(entry[len("file://") :] if entry.startswith("file://") else entry).expanduser()
        if not path.is_dir():
            raise ConfigError(f"{source}: {entry}: no such folder (a folder of configs: model/<name>.yaml, ...)")
        dirs.append(path)
    return dirs


def check_selections(argv: Sequence[str]) -> None:
    """Refuse unknown config names in group selections (``filter=[a,b]``, ``model=x``, ``flow@...=edh``,
    sweeps ``filter=a,b`` and ``filter=[a,b],[c]``) with the list of valid names, and a config selected
    twice in one list (``filter=[bpf,bpf]``: the two would be one row), before Hydra composes anything."""
    extra = user_config_dirs(argv)
    for arg in argv:
        if "=" not in arg or arg.startswith(("hydra.", "-")):
            continue
        lhs, rhs = arg.split("=", 1)
        group = lhs.lstrip("+~").split("@", 1)[0]
        options, value = None if "." in group or "/" in group else group_options(group, extra), rhs.strip()
        if (
            options is None
            or value.startswith(("range(", "choice(", "glob(", "interval(", "{"))
            or value in ("null", "")
        ):
            continue  # ("{": a config given inline, model={_target_: mypackage.MyModel, ...})
        unknown = [v for v in dict.fromkeys(re.findall(r"[^\[\],\s]+", value)) if v not in options]
        if unknown:
            raise ConfigError(
                f"{lhs}: unknown {group} config {', '.join(repr(u) for u in unknown)}; available: {', '.join(options)}"
            )
        for selection in re.findall(r"\[([^\]]*)\]", value):
            names = [v.strip() for v in selection.split(",") if v.strip()]
            twice = next((v for v in names if names.count(v) > 1), None)
            if twice:
                raise ConfigError(
                    f"{lhs}: expected each {group} config once, got {twice} {names.count(twice)} times "
                    f"in [{selection}] (one row per config); select it once, and to compare settings "
                    f"of one {group}, sweep them: -m {group}.{twice}.<key>=a,b"
                )


def inline_configs(argv: Sequence[str]) -> List[str]:
    """``argv`` with a whole config given inline for a group that holds one config (``model={_target_:
    mypackage.MyModel, a: 1}``) made to replace the group's default (``~model +model={...}``) instead
    of merging into it, which would hand the default's keys to the user's class."""
    out = []
    for arg in argv:
        lhs, _, rhs = arg.partition("=")
        if lhs in ("model", "schedule") and rhs.strip().startswith("{") and "_target_" in rhs:
            out += [f"~{lhs}", f"+{lhs}={rhs}"]
        else:
            out.append(arg)
    return out


def close_keys(key: str, known: Sequence[str]) -> List[str]:
    """The known keys a mistyped ``key`` most likely meant: difflib's close matches, and the keys
    whose word initials spell it or that it abbreviates (``learning_rate`` -> ``lr``)."""
    initials = lambda k: "".join(w[0] for w in k.split("_") if w)
    close = difflib.get_close_matches(key, known, n=3, cutoff=0.6)
    close += [c for c in known if c not in close and "_" in key + c and (initials(key) == c or initials(c) == key)]
    return close[:3]


def unknown_keys(cfg: Mapping, known: Mapping, prefix: str = "", free_form: Sequence[str] = FREE_FORM) -> List[str]:
    """Messages for keys of ``cfg`` that ``known`` does not have (outside ``free_form``, the
    subtrees whose keys are constructor arguments or user-named entries, by their dotted path:
    ``model``, ``pmmh.priors``), each naming the closest known ones."""
    out = []
    for k, v in cfg.items():
        path = prefix + str(k)
        if path in free_form:
            continue
        if k not in known:
            close = close_keys(str(k), [str(c) for c in known if c != "defaults"])
            hint = f"; did you mean {' or '.join(prefix + c for c in close)}?" if close else ""
            out.append(f"{path}: unknown setting{hint}")
        elif isinstance(v, Mapping) and isinstance(known[k], Mapping):
            out += unknown_keys(v, known[k], path + ".", free_form)
    return out


def compose_config(config_name: str, overrides: Sequence[str]):
    """The config (with its ``hydra`` node) that Hydra composes from ``overrides``, outside a run."""
    from hydra import compose, initialize_config_dir, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    src = config_source()
    GlobalHydra.instance().clear()
    init = (
        initialize_config_module(src[len("pkg://") :], version_base="1.3")
        if src.startswith("pkg://")
        else initialize_config_dir(src, version_base="1.3")
    )
    with init:
        return compose(config_name, list(overrides), return_hydra_config=True)


#: how Hydra refuses an override of a key its config does not have (``n_particle=7``, no ``+``)
_NO_SUCH_KEY = re.compile(r"Could not override '([^']+)'\.")


def missing_override_key(message: str) -> Optional[str]:
    """The key of Hydra's refusal ``Could not override 'KEY'.`` (``None``: another refusal)."""
    m = _NO_SUCH_KEY.search(message)
    return m.group(1) if m else None


def unknown_override_messages(config_name: str, argv: Sequence[str], key: str) -> List[str]:
    """One message per override of a key the config does not have (Hydra refused the first, ``key``):
    the config is composed again without it (a sweep's first values) to find the others and the
    closest known keys (:func:`unknown_key_message`)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    parser, parsed = OverridesParser.create(), []
    for arg in argv:
        with contextlib.suppress(HydraException):
            parsed.append(parser.parse_override(arg))
    bad, tree = [key], None
    for _ in range(len(parsed) + 1):
        args = [
            f"{o.get_key_element()}={next(o.sweep_string_iterator())}" if o.is_sweep_override() else o.input_line
            for o in parsed
            if o.key_or_group not in bad
        ]  # a sweep: its first value
        try:
            tree = OmegaConf.to_container(compose_config(config_name, args), resolve=False)
            break
        except HydraException as e:
            again = missing_override_key(str(e))
            if again is None or again in bad:
                break
            bad.append(again)
    return [unknown_key_message(tree, k) for k in bad]


def _has(node, parts: Sequence[str]) -> bool:
    for part in parts:
        if not isinstance(node, Mapping) or part not in node:
            return False
        node = node[part]
    return True


def unknown_key_message(tree: Optional[Mapping], key: str) -> str:
    """``n_particle: unknown setting; did you mean n_particles?``: ``key`` (dotted) is not in ``tree``
    (the composed config; ``None``: not known); a filter that is not selected says so."""
    parts, node, i = key.split("."), tree, 0
    while isinstance(node, Mapping) and i < len(parts) and parts[i] in node:
        node, i = node[parts[i]], i + 1
    if not isinstance(node, Mapping) or i == len(parts):
        return f"{key}: unknown setting"
    where, missing, tail = ".".join(parts[:i]), parts[i], "".join("." + p for p in parts[i + 1 :])
    known = [str(k) for k in node if not str(k).startswith("_") and k != "defaults"]
    close = [
        f"{where + '.' if where else ''}{c}{tail if _has(node[c], parts[i + 1 :]) else ''}"
        for c in close_keys(missing, known)
    ]
    did_you_mean = f"; did you mean {' or '.join(close)}?" if close else ""
    if where == "filter":
        text = f"{key}: expected one of the selected filters {', '.join(known)}, got {missing}"
        if missing in (group_options("filter") or []):
            return f"{text} (not selected; to set it, select it too: filter=[{','.join([*known, missing])}])"
        return text + did_you_mean
    if not close and where:
        return f"{key}: unknown setting; the settings of {where} are {', '.join(known)}"
    return f"{key}: unknown setting{did_you_mean}"


def unreadable_override_message(argv: Sequence[str]) -> Optional[str]:
    """The message of the first override Hydra's grammar cannot read (``None``: all read): unquoted, a
    value may hold only ASCII letters, digits and a few symbols, so ``label=ünï码`` or a folder with
    spaces needs Hydra's quotes, inside the shell's: ``"hydra.run.dir='dir with spaces/ünï码'"``."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    parser = OverridesParser.create()
    for arg in argv:
        if arg.startswith("-"):
            continue
        try:
            parser.parse_override(arg)
        except HydraException as e:
            lhs, _, rhs = arg.partition("=")
            if not rhs or rhs[:1] in "'\"":
                return f"{arg}: Hydra cannot read this override ({e}); see Hydra's override grammar"
            quoted = f"\"{lhs}='{rhs}'\"" if "'" not in rhs + lhs else shlex.quote(f'{lhs}="{rhs}"')
            return (
                f"{lhs}: expected a value Hydra can read unquoted (ASCII letters, digits, _-./:), got {rhs!r} "
                f"({e}); quote it for Hydra inside the shell's quotes: {quoted}"
            )
    return None


def check_config(
    cfg: Mapping,
    choices: Mapping[str, Optional[str]],
    config_name: str = "config",
    free_form: Sequence[str] = FREE_FORM,
) -> None:
    """What a composed config of the command whose primary config is ``config_name`` (``config``:
    ``torchflow``; ``learn``: ``torchflow-learn``) must satisfy before anything is built: no
    unknown settings (outside ``free_form``), booleans that are booleans, a seed in range, and
    where the command has them a known random back end, warm-up and metric settings."""
    known = OmegaConf.load(config_dir() / f"{config_name}.yaml")
    if choices.get("experiment"):
        known = OmegaConf.merge(known, OmegaConf.load(config_dir() / "experiment" / f"{choices['experiment']}.yaml"))
    known = OmegaConf.to_container(known, resolve=False)
    bad = unknown_keys(cfg, known, free_form=free_form)
    if bad:
        raise ConfigError("; ".join(bad))
    for key in ("plots", "progress", "resume", "overwrite"):
        if key in known:
            require(isinstance(cfg.get(key), bool), key, "true or false", cfg.get(key))
    check_seed(cfg.get("seed"))
    if "rng_backend" in known:
        check_rng_backend(cfg.get("rng_backend"))
    if "warmup" in known:
        check_warmup(cfg.get("warmup", "auto"))
    if "nonfinite_trials" in known:
        nft = cfg.get("nonfinite_trials")
        require(nft in NONFINITE_TRIALS, "nonfinite_trials", " or ".join(NONFINITE_TRIALS), nft)
    if "metrics" in known:
        m = cfg.get("metrics") or {}
        steps = cfg.get("steps")
        check_metric_settings(
            ospa_cutoff=m.get("ospa_cutoff"),
            ospa_order=m.get("ospa_order"),
            lost_threshold=m.get("lost_threshold"),
            burn_in=m.get("burn_in", 0),
            steps=steps if isinstance(steps, int) and not isinstance(steps, bool) and steps > 0 else None,
        )
        r = m.get("lost_rmse")
        require(
            r is None or (isinstance(r, (int, float)) and not isinstance(r, bool) and r > 0),
            "metrics.lost_rmse",
            "a positive RMSE above which a trial is lost, or null",
            r,
        )


def invoked_as(argv0: str, default: str) -> str:
    """How this process was started, for the resume hint: ``python <the script as given>`` (so that
    ``python ../experiments/run.py`` is repeated as such from that folder), else ``default`` (an
    entry point: ``torchflow``)."""
    if argv0.endswith(".py") and Path(argv0).name != "__main__.py":
        return "python " + shlex.quote(argv0)
    return default


def collect_command(sweep_dir, env: Optional[Mapping[str, str]] = None) -> str:
    """The command that merges a sweep's jobs: ``experiments/collect.py`` beside the ``run.py`` this
    process was started as (``python ../experiments/run.py``: ``python ../experiments/collect.py``)."""
    prog = (os.environ if env is None else env).get(PROG_ENV, "")
    script = prog[len("python ") :] if prog.startswith("python ") else ""
    script = shlex.split(script)[0] if script else ""
    collect = str(Path(script).with_name("collect.py")) if Path(script).name == "run.py" else "experiments/collect.py"
    return f"python {shlex.quote(collect)} {shlex.quote(str(sweep_dir))}"


def remember_command(prog: str, argv: Sequence[str]) -> None:
    """Record how this process was started, for the resume hint (sweep workers inherit it)."""
    os.environ.setdefault(PROG_ENV, prog)
    os.environ.setdefault(ARGV_ENV, json.dumps(list(argv)))


def resume_command(
    prog: Optional[str] = None, argv: Optional[Sequence[str]] = None, env: Optional[Mapping[str, str]] = None
) -> str:
    """The command line of this run (all of a sweep's jobs: ``-m`` and every override) with
    ``resume=true``; under torchrun the same number of processes, so the chunks are the same."""
    env = os.environ if env is None else env
    prog = prog or env.get(PROG_ENV, "torchflow")
    argv = list(argv if argv is not None else json.loads(env.get(ARGV_ENV, "[]")))
    args = [a for a in argv if not a.startswith(("resume=", "overwrite="))]
    world = int(env.get("WORLD_SIZE", "1"))
    if world > 1:
        local = env.get("LOCAL_WORLD_SIZE")
        nodes = f" --nnodes={world // int(local)}" if local and world != int(local) else ""
        script = prog.split(" ", 1)[1] if prog.startswith("python ") else f"-m {prog}"
        prog = f"torchrun --nproc_per_node={local or world}{nodes} {script}"
    return " ".join([prog, *(shlex.quote(a) for a in args), "resume=true"])


def explicit_overrides() -> List[str]:
    """The keys the command line set (``trials=5`` -> ``trials``) in this Hydra job; ``[]`` outside one."""
    try:
        from hydra.core.hydra_config import HydraConfig

        task = HydraConfig.get().overrides.task
    except (ImportError, ValueError):
        return []
    return [str(o).split("=", 1)[0].lstrip("+~") for o in task]


@dataclass
class RecordedData:
    """The run's recorded data (:func:`recorded_data`): ``observations`` ``(T, m)`` or ``(B, T, m)``,
    ``trials``, ``steps``, ``sha256`` of the file's bytes (the checkpoints' key), the true
    ``states`` (a ``.npz`` file's; ``None``: no truth) and the ``prior`` ``(mean, cov)`` (the
    command line's ``prior.mean`` / ``prior.cov`` over the file's; ``None``: none given)."""

    observations: torch.Tensor
    trials: int
    steps: int
    sha256: str
    states: Optional[torch.Tensor] = None
    prior: Optional[Tuple[torch.Tensor, torch.Tensor]] = None


def command_line_prior(cfg: Mapping, model, file_prior=None):
    """``(mean, cov)`` of ``prior.mean`` / ``prior.cov`` (:func:`torchflow.app.data.prior_from_spec`),
    each over the file's where given; ``file_prior`` where neither is set; ``None`` where no prior is
    given anywhere. One of the two without the other (and none in the file): a :class:`ConfigError`."""
    from torchflow.app.data import prior_from_spec
    from torchflow.core.errors import ArgumentError

    spec = cfg.get("prior") or {}
    mean, cov = spec.get("mean"), spec.get("cov")
    if mean is None and cov is None:
        return file_prior
    if OmegaConf.is_config(mean):
        mean = OmegaConf.to_container(mean)
    if OmegaConf.is_config(cov):
        cov = OmegaConf.to_container(cov)
    d = model.state_dim
    if (mean is None or cov is None) and file_prior is None:
        missing = "prior.cov" if cov is None else "prior.mean"
        raise ConfigError(f"{missing}: expected it with {'prior.mean' if cov is None else 'prior.cov'}, got null")
    try:
        m, c = prior_from_spec(mean if mean is not None else 0.0, cov if cov is not None else 1.0, d, name="prior")
    except ArgumentError as e:
        raise ConfigError(str(e)) from None
    if mean is None:
        m = file_prior[0]
    if cov is None:
        c = file_prior[1]
    return m.to(dtype=model.dtype, device=model.device), c.to(dtype=model.dtype, device=model.device)


def recorded_data(cfg: Mapping, model) -> Optional[RecordedData]:
    """The run's recorded data (``data=<file>``; ``None``: simulate): a :class:`RecordedData`.
    ``observations``: the file's series on the model's dtype and device
    (:func:`torchflow.app.data.load_recording`: ``.csv``, ``.npy``, ``.npz`` with ``states`` and a
    prior); ``trials``: a ``(T, m)`` series is filtered by ``cfg.trials`` independent runs, a
    ``(B, T, m)`` file by one run per series (``trials`` set on the command line must then be B);
    ``steps``: the file's T (``steps`` set on the command line must be T). ``prior.mean`` /
    ``prior.cov`` without ``data``: refused (a simulation draws each trial's prior). Any problem:
    a one-line :class:`ConfigError` naming ``data`` or ``prior``."""
    import hashlib

    from hydra.utils import to_absolute_path

    from torchflow.app.data import load_recording
    from torchflow.core.errors import ArgumentError

    path = cfg.get("data")
    if path is None:
        spec = cfg.get("prior") or {}
        given = [k for k in ("mean", "cov") if spec.get(k) is not None]
        require(
            not given,
            f"prior.{given[0]}" if given else "prior",
            "null without data= (a simulation draws each trial's prior around its true initial state)",
            spec.get(given[0]) if given else None,
        )
        return None
    require(
        isinstance(path, str) and path != "",
        "data",
        "the path of a .csv, .npy or .npz file of recorded observations, or null",
        path,
    )
    full = Path(to_absolute_path(path))
    try:
        rec = load_recording(full, model, name="data")
    except ArgumentError as e:
        raise ConfigError(str(e)) from None
    obs = rec.observations
    given, T = explicit_overrides(), obs.shape[-2]
    trials = cfg.trials
    if obs.dim() == 3:
        B = obs.shape[0]
        require(
            "trials" not in given or trials == B,
            "trials",
            f"the {B} series of data={path} (one trial per series; leave trials unset)",
            trials,
        )
        trials = B
    require(
        "steps" not in given or cfg.steps == T, "steps", f"the {T} rows of data={path} (leave steps unset)", cfg.steps
    )
    prior = command_line_prior(cfg, model, rec.prior)
    return RecordedData(obs, trials, T, hashlib.sha256(full.read_bytes()).hexdigest(), rec.states, prior)
