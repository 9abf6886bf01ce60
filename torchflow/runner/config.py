"""The command line's configuration: where the Hydra configs are, and checks of a composed config
and of the command line that Hydra itself does not make (one clear line each, no traceback)."""
from __future__ import annotations

import difflib
import json
import os
import shlex
from importlib.resources import files
from pathlib import Path
from typing import List, Mapping, Optional, Sequence

from omegaconf import OmegaConf

from .plan import ConfigError, require, check_metric_settings, check_rng_backend, check_seed, check_warmup
from .writers import RESULT_FILES

_CHECKOUT = Path(__file__).resolve().parents[2]
#: subtrees of the config whose keys are constructor arguments (checked by the constructors)
FREE_FORM = ("model", "filter", "hydra")
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


def group_options(group: str) -> Optional[List[str]]:
    """Config names of a group (``filter``, ``model``, ...), ``None`` if there is no such group."""
    d = config_dir() / group
    return sorted(p.stem for p in d.glob("*.yaml")) if d.is_dir() else None


def check_selections(argv: Sequence[str]) -> None:
    """Refuse unknown config names in group selections (``filter=[a,b]``, ``model=x``, ``flow@...=edh``,
    sweeps ``filter=a,b``) with the list of valid names, before Hydra composes anything."""
    for arg in argv:
        if "=" not in arg or arg.startswith(("hydra.", "-")):
            continue
        lhs, rhs = arg.split("=", 1)
        group = lhs.lstrip("+~").split("@", 1)[0]
        options, value = None if "." in group or "/" in group else group_options(group), rhs.strip()
        if options is None or value.startswith(("range(", "choice(", "glob(", "interval(")) or value in ("null", ""):
            continue
        unknown = [v for v in (v.strip() for v in rhs.strip("[]").split(",")) if v and v not in options]
        if unknown:
            raise ConfigError(f"{lhs}: unknown {group} config {', '.join(repr(u) for u in unknown)}; "
                              f"available: {', '.join(options)}")


def _override(argv: Sequence[str], key: str) -> Optional[str]:
    vals = [a.split("=", 1)[1] for a in argv if a.lstrip("+").startswith(key + "=")]
    return vals[-1] if vals else None


def check_output_folder(argv: Sequence[str], cwd: Path) -> None:
    """Before Hydra creates it: the run's (sweep's) folder must be writable, and a folder given
    with ``hydra.run.dir`` / ``hydra.sweep.dir`` that holds an earlier run's results is refused
    unless ``overwrite=true`` (or ``resume=true``) says to replace them."""
    sweep = any(a in ("-m", "--multirun") for a in argv)
    key = "hydra.sweep.dir" if sweep else "hydra.run.dir"
    given = _override(argv, key)
    folder = Path(given) if given else Path("multirun" if sweep else "outputs")
    folder = folder if folder.is_absolute() else cwd / folder
    if given and folder.is_dir():
        found = (sorted(str(p.relative_to(folder)) for p in folder.glob("[0-9]*/results.json")) if sweep
                 else [n for n in RESULT_FILES if (folder / n).exists()])
        replace = any(_override(argv, k) in ("true", "True") for k in ("overwrite", "resume"))
        if found and not replace:
            raise ConfigError(f"{key}: {given} already holds the results of a run ({', '.join(found[:4])}); choose "
                              f"a new folder ({key}=<new folder>) or add overwrite=true to replace them")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".torchflow-write-test.{os.getpid()}"
        probe.write_text("")
        probe.unlink()
    except OSError as e:
        raise ConfigError(f"{key}: cannot write into {folder} ({type(e).__name__}: {e.strerror or e}); choose a "
                          f"writable folder with {key}=<folder>") from None


def unknown_keys(cfg: Mapping, known: Mapping, prefix: str = "") -> List[str]:
    """Messages for keys of ``cfg`` that ``known`` does not have (outside :data:`FREE_FORM`),
    each naming the key and the closest known ones."""
    out = []
    for k, v in cfg.items():
        path = prefix + str(k)
        if not prefix and k in FREE_FORM:
            continue
        if k not in known:
            close = difflib.get_close_matches(str(k), [str(c) for c in known if c != "defaults"], n=3, cutoff=0.6)
            hint = f"; did you mean {' or '.join(prefix + c for c in close)}?" if close else ""
            out.append(f"{path}: unknown setting{hint}")
        elif isinstance(v, Mapping) and isinstance(known[k], Mapping):
            out += unknown_keys(v, known[k], path + ".")
    return out


def check_config(cfg: Mapping, choices: Mapping[str, Optional[str]]) -> None:
    """What a composed config must satisfy before anything is built: no unknown settings,
    booleans that are booleans, a seed in range, a known random back end, metric settings."""
    known = OmegaConf.load(config_dir() / "config.yaml")
    if choices.get("experiment"):
        known = OmegaConf.merge(known, OmegaConf.load(config_dir() / "experiment" / f"{choices['experiment']}.yaml"))
    bad = unknown_keys(cfg, OmegaConf.to_container(known, resolve=False))
    if bad:
        raise ConfigError("; ".join(bad))
    for key in ("plots", "progress", "resume", "overwrite"):
        require(isinstance(cfg.get(key), bool), key, "true or false", cfg.get(key))
    check_seed(cfg.get("seed"))
    check_rng_backend(cfg.get("rng_backend"))
    check_warmup(cfg.get("warmup", "auto"))
    m = cfg.get("metrics") or {}
    check_metric_settings(ospa_cutoff=m.get("ospa_cutoff"), ospa_order=m.get("ospa_order"),
                          lost_threshold=m.get("lost_threshold"))


def remember_command(prog: str, argv: Sequence[str]) -> None:
    """Record how this process was started, for the resume hint (sweep workers inherit it)."""
    os.environ.setdefault(PROG_ENV, prog)
    os.environ.setdefault(ARGV_ENV, json.dumps(list(argv)))


def resume_command(prog: Optional[str] = None, argv: Optional[Sequence[str]] = None,
                   env: Optional[Mapping[str, str]] = None) -> str:
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
