"""Every code block and command of README.md runs as written, shrunk only in trial counts and sizes.

The blocks are read from README.md at test time, so an edit that breaks one fails here. The only
changes made before running them are listed below (SHRINK_* and the command rules); every listed
replacement must match, so a README edit that moves a size out of reach of the shrink rules fails
instead of silently running the full size.
"""
import csv
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()

#: python blocks run top to bottom as one script (later blocks use earlier names, as a reader would)
SHRINK_PY = [
    ("model.simulate(10, 40, g)", "model.simulate(6, 4, g)"),
    ("n_particles=10_000", "n_particles=100"),
    ("n_particles=1000)", "n_particles=50)"),
    ("range(10)", "range(6)"),
    ("truth.simulate(64, 20,", "truth.simulate(16, 5,"),
    ("max_epochs=20", "max_epochs=2"),
    ('default_root_dir="outputs/lightning"', 'default_root_dir=OUT'),
    ("n_particles=500, covariance", "n_particles=30, covariance"),
    ("GromovFlow(), n_particles=500", "GromovFlow(), n_particles=30"),
    ("n_clusters=100, alpha=0.25, n_particles=500", "n_clusters=5, alpha=0.25, n_particles=30"),
    ("GPFIS(model, n_particles=100)", "GPFIS(model, n_particles=10)"),
    ("n_components=3, particles_per_component=200", "n_components=2, particles_per_component=20"),
]
#: command-line sizes: replaced where the command sets them, appended where it does not
SHRINK_CLI = {"trials": "2", "steps": "2", "n_particles": "20"}
#: seed 002's localisers take their sizes per method (appended to commands naming a seed002 experiment)
SHRINK_TDOA = ["filter.bs.n_particles=2000"] + [f"filter.{k}.{p}" for k in ("pfi_d", "pfi_s", "pfi_os")
                                              for p in ("n_components=5", "samples_per_component=20")]
#: and Table II's two extra PFI-OS rows
SHRINK_TDOA2 = [f"filter.{k}.{p}" for k in ("pfi_os_a001", "pfi_os_a05")
                for p in ("n_components=5", "samples_per_component=20")]
#: experiments/seed002_proposal_quality.py
SHRINK_QUALITY = {"--scenes": "1", "--n-samples": "20", "--reference": "50"}


def blocks(lang):
    return re.findall(rf"```{lang}\n(.*?)```", README, flags=re.S)


def commands():
    """The README's shell commands, one per logical line (``\\`` continuations joined)."""
    out = []
    for block in blocks("bash"):
        text = block.replace("\\\n", " ")
        for line in text.splitlines():
            line = line.split(" # ")[0].strip() if not line.lstrip().startswith("#") else ""
            if line:
                out.append(line)
    return out


def test_readme_has_the_blocks_we_expect():
    assert len(blocks("python")) >= 5 and len(commands()) >= 10
    script = "\n".join(blocks("python"))
    for old, _ in SHRINK_PY:
        assert old in script, f"shrink rule {old!r} no longer matches README.md"


def test_readme_python_blocks_run(tmp_path):
    script = "\n".join(blocks("python"))
    for old, new in SHRINK_PY:
        script = script.replace(old, new)
    script = f"OUT = {str(tmp_path / 'lightning')!r}\n" + script
    (tmp_path / "readme_blocks.py").write_text(script)
    out = subprocess.run([sys.executable, str(tmp_path / "readme_blocks.py")], capture_output=True, text=True,
                         cwd=tmp_path, timeout=600)
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


def _has_metric(path, metric):
    with open(path) as fh:
        return any(r.get(metric, "") != "" for r in csv.DictReader(fh))


def test_readme_commands_run(tmp_path):
    """Every command, in README order, from the repository root: set-up and test commands run up to
    their last step (CI runs the set-up itself), sizes shrunk, output folders in tmp_path."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    last_sweep = None
    runs = []  # single-run folders with a per_trial.csv, in README order
    ran = []
    for i, line in enumerate(commands()):
        parts = [p.strip() for p in line.split("&&")]
        cmd = parts[-1]  # the set-up steps (venv, pip) are what CI's own set-up already did
        if cmd.startswith("pip install") or cmd.startswith("python -m pytest"):
            continue  # installing extras / the test command itself (this suite is its run)
        tokens = shlex.split(cmd)
        assert tokens[0] == "python", f"README command not understood: {line}"
        tokens[0] = sys.executable
        script = tokens[1]
        if tokens[1] == "-m" and tokens[2].startswith("experiments."):  # a module of experiments/: its file
            script = tokens[2].replace(".", "/") + ".py"
        if tokens[1:3] == ["-m", "torch.distributed.run"]:  # torchrun: its options, then the script
            script = next(t for t in tokens if t.endswith(".py"))
        if script == "experiments/run.py":
            multirun = "-m" in tokens[tokens.index(script):]
            table2 = "experiment=seed002_table2" in tokens  # Table II has no BS row
            tokens = _shrink(tokens) + (SHRINK_TDOA[table2:] if any("experiment=seed002_table" in t for t in tokens)
                                        else []) + (SHRINK_TDOA2 if table2 else [])
            where = tmp_path / f"cmd{i}"
            tokens += [f"hydra.sweep.dir={where}" if multirun else f"hydra.run.dir={where}", "progress=false",
                       f"checkpoint_dir={tmp_path}/checkpoints"]
            if multirun:
                last_sweep = where
        elif script == "experiments/learn.py":
            tokens += ["epochs=2", "steps=3", "trials=2", "n_particles=20", "plots=false", f"hydra.run.dir={tmp_path}/learn"]
        elif script == "experiments/collect.py":
            assert last_sweep is not None, "collect.py before any sweep in README"
            tokens = [t if "<time>" not in t else str(last_sweep) for t in tokens]
        elif script == "experiments/trial_stats.py":
            # the latest run folder whose per-trial file has the metric the command asks for
            metric = tokens[tokens.index("--metric") + 1] if "--metric" in tokens else "omat"
            fit = [r for r in runs if _has_metric(r / "per_trial.csv", metric)]
            assert fit, f"trial_stats.py --metric {metric} before any README run with that metric"
            tokens = [t if "<run>" not in t else str(fit[-1]) for t in tokens]
        elif script == "experiments/seed002_proposal_quality.py":
            for flag, small in SHRINK_QUALITY.items():
                if flag in tokens:
                    tokens[tokens.index(flag) + 1] = small
                else:
                    tokens += [flag, small]
        elif script == "experiments/benchmarks/run_all.py":
            # the whole suite takes ~20 min and needs the [bench] peers: run its entry point on the
            # section that needs no peer library, in --quick sizes
            tokens += ["--quick", "--only", "pfpf", "--out", str(tmp_path / "bench.md")]
        else:
            pytest.fail(f"README command with no rule in this test: {line}")
        out = subprocess.run(tokens, capture_output=True, text=True, cwd=ROOT, env=env, timeout=600)
        assert out.returncode == 0, f"{line}\n{out.stderr[-3000:]}"
        assert "Traceback" not in out.stderr, f"{line}\n{out.stderr[-3000:]}"
        ran.append(script)
        if script == "experiments/run.py" and not multirun and (where / "per_trial.csv").exists():
            runs.append(where)  # folders a later trial_stats.py command may read
    assert ran.count("experiments/run.py") >= 7 and "experiments/collect.py" in ran
    assert "experiments/trial_stats.py" in ran
