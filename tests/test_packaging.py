"""The package as installed: every subpackage and the Hydra configs ship, and the command line runs
from an installed copy outside the checkout (no network: the current environment's setuptools)."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]


def test_pyproject_lists_every_package():
    """``packages`` is an explicit list (configs/ ships as torchflow.configs): a new package folder
    under torchflow/ must be added there, or an installed copy would lack it."""
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "torchflow").rglob("__init__.py")}
    assert found | {"torchflow.configs"} == listed, f"pyproject.toml packages: add {sorted(found - listed)}"
    assert (ROOT / "configs" / "__init__.py").exists()


def _install(tmp_path: Path) -> Path:
    """``pip install --target`` of a copy of the checkout's tracked top level (an in-tree build
    would leave build/ in the checkout)."""
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for name in ("torchflow", "configs"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__"))
    site = tmp_path / "site"
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--quiet",
            "--no-deps",
            "--no-build-isolation",
            "--no-index",
            "--target",
            str(site),
            str(src),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return site


def test_installed_copy_runs_the_command_line_from_any_folder(tmp_path):
    site = _install(tmp_path)
    assert (site / "torchflow" / "configs" / "filter" / "kf.yaml").exists()
    env = dict(os.environ, PYTHONPATH=str(site), OMP_NUM_THREADS="1")
    work = tmp_path / "elsewhere"
    work.mkdir()
    where = subprocess.run(
        [
            sys.executable,
            "-c",
            "import torchflow, torchflow.app.runner.config as c; print(torchflow.__file__); print(c.config_source())",
        ],
        capture_output=True,
        text=True,
        cwd=work,
        env=env,
        timeout=120,
    )
    assert where.stdout.splitlines() == [str(site / "torchflow" / "__init__.py"), "pkg://torchflow.configs"], where
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "torchflow",
            "model=linear_gaussian",
            "filter=[kf]",
            "trials=2",
            "steps=3",
            "progress=false",
            "plots=false",
            "checkpoint_dir=null",
            "hydra.run.dir=run",
        ],
        capture_output=True,
        text=True,
        cwd=work,
        env=env,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "| kf |" in out.stdout and (work / "run" / "summary.csv").exists()
    assert "SensorNetwork" in (work / "run" / "run.log").read_text()
    # the console script's entry point is recorded
    assert any("torchflow = torchflow.app.cli:main" in p.read_text() for p in site.glob("*.dist-info/entry_points.txt"))
