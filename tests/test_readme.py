"""Every code block and command of the documentation runs as written, shrunk only in trial counts
and sizes: README.md, then the pages of the documentation site (docs/, in mkdocs.yml's nav order).

The blocks are read from the files at test time, so an edit that breaks one fails here. The only
changes made before running them are listed below (SHRINK_*, the checkout forms of the installed
commands and the command rules); every listed replacement must match, so an edit that moves a size
out of reach of the shrink rules fails instead of silently running the full size.

Each distinct command is its own test (pytest-xdist runs them side by side), after the earlier
commands whose output it reads; the few that take long are second tier (SLOW, ``-m slow``).
"""

import csv
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]


def _nav_pages(nav):
    """The Markdown pages of an mkdocs ``nav`` list, in order."""
    for entry in nav:
        for value in entry.values() if isinstance(entry, dict) else [entry]:
            if isinstance(value, list):
                yield from _nav_pages(value)
            elif isinstance(value, str) and value.endswith(".md"):
                yield value


def _documentation():
    """README.md, then the documentation pages in mkdocs.yml's nav order: the README is the landing
    page and the user guide moved to docs/. Pages docs/hooks.py generates at build time (the
    examples' pages, from docs/examples/*.py, which the docs build runs) are not in the tree."""
    cfg = (ROOT / "mkdocs.yml").read_text()
    nav = yaml.safe_load(cfg[cfg.index("\nnav:") :])["nav"]
    pages = [ROOT / "docs" / p for p in _nav_pages(nav)]
    return "\n".join([(ROOT / "README.md").read_text()] + [p.read_text() for p in pages if p.exists()])


README = _documentation()

#: python blocks run top to bottom as one script (later blocks use earlier names, as a reader would)
SHRINK_PY = [
    ("model.simulate(10, 40, g)", "model.simulate(6, 4, g)"),
    ("n_particles=10_000", "n_particles=100"),
    ("n_particles=1000)", "n_particles=50)"),
    ("range(10)", "range(6)"),
    ("truth.simulate(64, 20,", "truth.simulate(16, 5,"),
    ("max_epochs=20", "max_epochs=2"),
    ('default_root_dir="outputs/lightning"', "default_root_dir=OUT"),
    ("n_particles=500, covariance", "n_particles=30, covariance"),
    ("GromovFlow(), n_particles=500", "GromovFlow(), n_particles=30"),
    ("n_clusters=100, alpha=0.25, n_particles=500", "n_clusters=5, alpha=0.25, n_particles=30"),
    ("GPFIS(model, n_particles=100)", "GPFIS(model, n_particles=10)"),
    ("n_components=3, particles_per_component=200", "n_components=2, particles_per_component=20"),
]
#: command-line sizes: replaced where the command sets them, appended where it does not
SHRINK_CLI = {"trials": "2", "steps": "2", "n_particles": "20"}
#: Zhang et al.'s (2024) localisers take their sizes per method (appended to commands naming a seed002 experiment)
SHRINK_TDOA = ["filter.bs.n_particles=2000"] + [
    f"filter.{k}.{p}" for k in ("pfi_d", "pfi_s", "pfi_os") for p in ("n_components=5", "samples_per_component=20")
]
#: and Table II's two extra PFI-OS rows
SHRINK_TDOA2 = [
    f"filter.{k}.{p}" for k in ("pfi_os_a001", "pfi_os_a05") for p in ("n_components=5", "samples_per_component=20")
]
#: experiments/zhang2024_proposal_quality.py
SHRINK_QUALITY = {"--scenes": "1", "--n-samples": "20", "--reference": "50"}


def blocks(lang):
    return re.findall(rf"```{lang}\n(.*?)```", README, flags=re.S)


#: the installed commands, run as their checkout forms (what they are: the same main functions)
ENTRY_POINTS = [("torchflow-learn", "python experiments/learn.py"), ("torchflow", "python experiments/run.py")]


def _checkout_form(cmd):
    for name, script in ENTRY_POINTS:
        if cmd == name or cmd.startswith(name + " "):
            return script + cmd[len(name) :]
    return cmd


def commands():
    """The documentation's shell commands, one per logical line (``\\`` continuations joined), each
    step of a ``&&`` chain in its checkout form (a leading ``torchflow`` / ``torchflow-learn`` as
    ``python experiments/run.py`` / ``python experiments/learn.py``)."""
    out = []
    for block in blocks("bash"):
        text = block.replace("\\\n", " ")
        for line in text.splitlines():
            line = line.split(" # ")[0].strip() if not line.lstrip().startswith("#") else ""
            if line:
                out.append(" && ".join(_checkout_form(p.strip()) for p in line.split("&&")))
    return out


#: the scripts this test knows how to shrink and point at tmp_path (one rule each in _run)
SCRIPTS = {
    "experiments/run.py",
    "experiments/learn.py",
    "experiments/collect.py",
    "experiments/trial_stats.py",
    "experiments/zhang2024_proposal_quality.py",
    "experiments/benchmarks/run_all.py",
    "torchflow.core.layers",
}

#: commands too slow for the default run (second tier, ``pytest -m slow``; .ci/run runs it): a
#: substring of the command, with its shrunk run's time on one core (one pytest-xdist worker of a
#: 2-core machine); every other command takes 3-15 s
SLOW = {
    "experiment=zhang2024_table1": "40 s: the bootstrap localiser's 2,000 particles and three PFI localisers",
    "benchmarks.run_all": "20-24 s each: the benchmark suite's quick section (and its --device refusal)",
    "hydra/launcher=": "15 s each: a sweep through a parallel launcher (joblib, submitit)",
    "torch.distributed.run": "9 s: two processes (tests/test_scale.py's torchrun test stays in the default tier)",
    "experiments/trial_stats.py": "15 s: it runs the Pal (2019) table first (test_experiment's trial_stats test stays)",
}


def _tokens(line):
    """The command a line runs (its last ``&&`` step: the set-up steps, venv and pip, are what CI's
    own set-up already did), split, or None for installs and this test suite's own command."""
    cmd = line.split("&&")[-1].strip()
    if cmd.startswith("pip install") or cmd.startswith("python -m pytest"):
        return None
    return shlex.split(cmd)


def _script(tokens):
    script = tokens[1]
    if tokens[1] == "-m" and tokens[2].startswith("experiments."):  # a module of experiments/: its file
        script = tokens[2].replace(".", "/") + ".py"
    if tokens[1] == "-m" and tokens[2].startswith("torchflow."):  # a module of the package, as named
        script = tokens[2]
    if tokens[1:3] == ["-m", "torch.distributed.run"]:  # torchrun: its options, then the script
        script = next(t for t in tokens if t.endswith(".py"))
    return script


def _multirun(tokens):
    """A sweep of experiments/run.py (Hydra's ``-m`` after the script)."""
    script = _script(tokens)
    return script == "experiments/run.py" and "-m" in tokens[tokens.index(script) + 1 :]


def _runnable():
    """``(i, line)`` of every command this test runs, in documentation order, each distinct command
    once (a page may repeat a command another page shows; collect.py counts once per sweep it reads)."""
    seen, out, sweep = set(), [], None
    for line in commands():
        tokens = _tokens(line)
        if tokens is None:
            continue
        key = (tuple(tokens), sweep if _script(tokens) == "experiments/collect.py" else None)
        if _multirun(tokens):
            sweep = tuple(tokens)
        if key not in seen:
            seen.add(key)
            out.append((len(out), line))
    return out


def _needs(i, line, runnable):
    """The earlier commands a command reads the output of, run first in its own test: collect.py the
    latest sweep's folder; a ``resume=true`` command the checkpoints of the same command without it.
    (trial_stats.py reads the latest single run with its metric: found when it runs, see _run.)"""
    tokens = _tokens(line)
    earlier = [(j, other) for j, other in runnable if j < i]
    if _script(tokens) == "experiments/collect.py":
        sweeps = [(j, o) for j, o in earlier if _multirun(_tokens(o))]
        return sweeps[-1:]
    if "resume=true" in tokens:
        plain = [t for t in tokens if t != "resume=true"]
        return [(j, o) for j, o in earlier if _tokens(o) == plain][-1:]
    return []


def _case_id(i, line):
    cmd = re.sub(r"[^\w.=,@/-]+", "_", " ".join(_tokens(line)[1:])).strip("_")
    return f"{i:02d}-" + (cmd if len(cmd) <= 80 else cmd[:50] + "..." + cmd[-27:])


def _cases():
    runnable = _runnable()
    out = []
    for i, line in runnable:
        # a command that reads a slow command's output (collect.py after a launcher's sweep) is slow too
        slow = [k for k in SLOW for text in [line] + [o for _, o in _needs(i, line, runnable)] if k in text]
        out.append(
            pytest.param(
                i, line, _needs(i, line, runnable), id=_case_id(i, line), marks=[pytest.mark.slow] if slow else []
            )
        )
    return out


def test_readme_has_the_blocks_we_expect():
    assert len(blocks("python")) >= 5 and len(commands()) >= 10
    script = "\n".join(blocks("python"))
    for old, _ in SHRINK_PY:
        assert old in script, f"shrink rule {old!r} no longer matches the documentation"
    runnable = _runnable()
    scripts = [_script(_tokens(line)) for _, line in runnable]
    for (_, line), script in zip(runnable, scripts):
        assert script in SCRIPTS, f"documented command with no rule in this test: {line}"
    assert scripts.count("experiments/run.py") >= 7 and "experiments/collect.py" in scripts
    assert "experiments/trial_stats.py" in scripts
    for key in SLOW:  # a stale rule would silently move nothing to the second tier
        assert any(key in line for _, line in runnable), f"SLOW rule {key!r} matches no documented command"
    for i, line in runnable:
        if _script(_tokens(line)) == "experiments/collect.py" or "resume=true" in _tokens(line):
            assert _needs(i, line, runnable), f"no earlier command gives this one its input: {line}"


@pytest.mark.slow  # 45 s: every README block in one script (the second tier, which .ci/run runs)
def test_readme_python_blocks_run(tmp_path):
    script = "\n".join(blocks("python"))
    for old, new in SHRINK_PY:
        script = script.replace(old, new)
    script = f"OUT = {str(tmp_path / 'lightning')!r}\n" + script
    (tmp_path / "readme_blocks.py").write_text(script)
    out = subprocess.run(
        [sys.executable, str(tmp_path / "readme_blocks.py")], capture_output=True, text=True, cwd=tmp_path, timeout=600
    )
    assert out.returncode == 0, out.stderr[-4000:]
    assert "OMAT" in out.stdout
    assert not (tmp_path / "lightning_logs").exists()  # Lightning logs go where the README says


def _shrink(tokens):
    seen = set()
    out = []
    for t in tokens:
        key = t.split("=", 1)[0]
        if key in SHRINK_CLI and "=" in t:
            n = t.split("=", 1)[1].count(",") + 1  # keep a sweep a sweep: distinct small values
            val = ",".join(str(int(SHRINK_CLI[key]) + i) for i in range(n))
            out.append(f"{key}={val}")
            seen.add(key)
        else:
            out.append(t)
    return out + [f"{k}={v}" for k, v in SHRINK_CLI.items() if k not in seen]


def _recorded(tokens, tmp_path):
    """A command's ``data=<file>`` (recorded observations) pointed at a file written into tmp_path:
    a 5-step series (``.csv``), 2 series (``.npy``) or 2 series with their states (``.npz``)
    simulated from the command's model (its ``model=`` and ``model.*`` overrides); ``steps`` then
    comes from the file, not the shrink."""
    import numpy as np
    import torch
    from hydra.utils import instantiate

    from torchflow.app.runner.config import compose_config

    given = [t for t in tokens if t.startswith("data=")]
    if not given:
        return tokens
    name = given[0].split("=", 1)[1]
    cfg = compose_config("config", [t for t in tokens if t.startswith(("model=", "model."))])
    model = instantiate(cfg.model)
    traj = model.simulate(2, 5, torch.Generator().manual_seed(0))
    z = traj.observations.numpy()
    path = tmp_path / Path(name).name
    if path.suffix == ".npy":
        np.save(path, z)
    elif path.suffix == ".npz":  # a recording with its truth: observations and states
        np.savez(path, observations=z, states=traj.states.numpy())
    else:
        np.savetxt(path, z[0], delimiter=",")
    return [f"data={path}" if t in given else t for t in tokens if not t.startswith("steps=")]


def _metric(tokens):
    """The per-trial metric a trial_stats.py command reads."""
    return tokens[tokens.index("--metric") + 1] if "--metric" in tokens else "omat"


def _has_metric(path, metric):
    with open(path) as fh:
        return any(r.get(metric, "") != "" for r in csv.DictReader(fh))


class _Ran:
    """What earlier commands of one test left: the latest sweep folder, the single-run folders."""

    def __init__(self):
        self.last_sweep = None
        self.runs = []  # single-run folders with a per_trial.csv, in documentation order


def _run(i, line, tmp_path, ran):
    """Run documented command ``i`` from the repository root, sizes shrunk, output folders in tmp_path."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    tokens = _tokens(line)
    assert tokens[0] == "python", f"documented command not understood: {line}"
    tokens[0] = sys.executable
    script = _script(tokens)
    multirun = False
    if script == "experiments/run.py":
        multirun = _multirun(tokens)
        table2 = "experiment=zhang2024_table2" in tokens  # Table II has no BS row
        tokens = (
            _recorded(_shrink(tokens), tmp_path)
            + (SHRINK_TDOA[table2:] if any("experiment=zhang2024_table" in t for t in tokens) else [])
            + (SHRINK_TDOA2 if table2 else [])
        )
        where = tmp_path / f"cmd{i}"
        tokens += [
            f"hydra.sweep.dir={where}" if multirun else f"hydra.run.dir={where}",
            "progress=false",
            f"checkpoint_dir={tmp_path}/checkpoints",
        ]
        if multirun:
            ran.last_sweep = where
    elif script == "experiments/learn.py":
        # a folder per command: learn refuses a folder that holds an earlier fit's results
        tokens = _recorded(
            tokens
            + [
                "epochs=2",
                "steps=3",
                "trials=2",
                "n_particles=20",
                "plots=false",
                f"hydra.run.dir={tmp_path}/learn{i}",
            ],
            tmp_path,
        )
    elif script == "experiments/collect.py":
        assert ran.last_sweep is not None, "collect.py before any sweep in the documentation"
        tokens = [t if "<time>" not in t else str(ran.last_sweep) for t in tokens]
    elif script == "experiments/trial_stats.py":
        # the latest run folder whose per-trial file has the metric the command asks for
        metric = _metric(tokens)
        fit = [r for r in ran.runs if _has_metric(r / "per_trial.csv", metric)]
        assert fit, f"trial_stats.py --metric {metric} before any documented run with that metric"
        tokens = [t if "<run>" not in t else str(fit[-1]) for t in tokens]
    elif script == "experiments/zhang2024_proposal_quality.py":
        for flag, small in SHRINK_QUALITY.items():
            if flag in tokens:
                tokens[tokens.index(flag) + 1] = small
            else:
                tokens += [flag, small]
    elif script == "experiments/benchmarks/run_all.py":
        # the whole suite takes ~20 min and needs the [bench] peers: run its entry point on the
        # section that needs no peer library, in --quick sizes
        tokens += ["--quick", "--only", "pfpf", "--out", str(tmp_path / f"bench{i}.md")]
    elif script == "torchflow.core.layers":
        pass  # the floors' check: reads the code, runs nothing; exits 0 on this tree
    else:
        pytest.fail(f"documented command with no rule in this test: {line}")
    out = subprocess.run(tokens, capture_output=True, text=True, cwd=ROOT, env=env, timeout=600)
    assert out.returncode == 0, f"{line}\n{out.stderr[-3000:]}"
    assert "Traceback" not in out.stderr, f"{line}\n{out.stderr[-3000:]}"
    if script == "experiments/run.py" and not multirun and (where / "per_trial.csv").exists():
        ran.runs.append(where)  # folders a later trial_stats.py command may read


@pytest.mark.parametrize("i,line,needs", _cases())
def test_readme_command_runs(i, line, needs, tmp_path):
    """One documented command, from the repository root, after the earlier commands whose output it
    reads (``needs``); set-up and test commands run up to their last step (CI runs the set-up
    itself), sizes shrunk, output folders in tmp_path. trial_stats.py reads the latest earlier
    single run whose per-trial file has its metric: those runs are tried newest first."""
    ran = _Ran()
    for j, other in needs:
        _run(j, other, tmp_path, ran)
    if _script(_tokens(line)) == "experiments/trial_stats.py":
        metric = _metric(_tokens(line))
        earlier = [
            (j, o)
            for j, o in _runnable()
            if j < i
            and _script(_tokens(o)) == "experiments/run.py"
            and not _multirun(_tokens(o))
            and "resume=true" not in _tokens(o)
        ]
        for j, other in reversed(earlier):
            _run(j, other, tmp_path, ran)
            if ran.runs and _has_metric(ran.runs[-1] / "per_trial.csv", metric):
                break
    _run(i, line, tmp_path, ran)
