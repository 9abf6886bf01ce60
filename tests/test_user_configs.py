"""A user's own model and filter from the command line, without touching torchflow: a config folder of
one's own (``--config-dir``, ``hydra.searchpath``), a whole model given inline
(``model={_target_: ...}``) and a filter added inline (``+filter.<name>={...}``); what goes wrong said
in one line."""

import json
import os
import subprocess
import sys

import pytest

from torchflow.app.runner.config import ConfigError, check_selections, inline_configs, user_config_dirs

PACKAGE = '''
from torchflow.filters import BootstrapParticleFilter
from torchflow.models import Lorenz63


class SlowLorenz(Lorenz63):
    """Lorenz-63 with the user's own default time step."""

    def __init__(self, dt: float = 0.05, **kw):
        super().__init__(dt=dt, **kw)


class MyBPF(BootstrapParticleFilter):
    """The user's own filter."""
'''


@pytest.fixture
def project(tmp_path):
    (tmp_path / "mypkg").mkdir()
    (tmp_path / "mypkg" / "__init__.py").write_text(PACKAGE)
    (tmp_path / "conf" / "model").mkdir(parents=True)
    (tmp_path / "conf" / "filter").mkdir()
    (tmp_path / "conf" / "model" / "slow_lorenz.yaml").write_text("_target_: mypkg.SlowLorenz\ndt: 0.05\n")
    (tmp_path / "conf" / "filter" / "my_bpf.yaml").write_text(
        "# @package filter.my_bpf\n_target_: mypkg.MyBPF\nn_particles: 40\n"
    )
    (tmp_path / "conf" / "filter" / "headless.yaml").write_text("_target_: mypkg.MyBPF\nn_particles: 40\n")
    return tmp_path


def _run(project, *args):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(project), os.environ.get("PYTHONPATH", "")]))
    out = project / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "torchflow", *args, "trials=2", "steps=4", f"hydra.run.dir={out}", "plots=false"],
        cwd=project,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    return proc, (json.loads((out / "results.json").read_text()) if proc.returncode == 0 else None)


def test_a_config_folder_of_one_s_own_gives_a_model_and_a_filter(project):
    proc, res = _run(project, "--config-dir", str(project / "conf"), "model=slow_lorenz", "filter=[my_bpf,ekf]")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert res["config"]["model"] == {"_target_": "mypkg.SlowLorenz", "dt": 0.05}
    assert [row["filter"] for row in res["summary"]] == ["my_bpf", "ekf"]
    assert all(row["error"] is None for row in res["summary"])


def test_a_whole_model_inline_replaces_the_default_and_a_filter_is_added_inline(project):
    proc, res = _run(
        project,
        "model={_target_: mypkg.SlowLorenz, dt: 0.02}",
        "filter=[ekf]",
        "+filter.mine={_target_: mypkg.MyBPF, n_particles: 30}",
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert res["config"]["model"] == {"_target_": "mypkg.SlowLorenz", "dt": 0.02}  # not merged into the default's keys
    rows = {row["filter"]: row for row in res["summary"]}
    assert rows["mine"]["n_particles"] == 30 and rows["mine"]["error"] is None


def test_a_filter_config_without_its_package_line_is_named_in_one_line(project):
    proc, _ = _run(project, "--config-dir", str(project / "conf"), "model=slow_lorenz", "filter=[headless]")
    assert proc.returncode == 2
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("error: filter:") and "# @package filter.<name>" in last


def test_the_user_s_folders_are_read_from_the_command_line(project):
    conf = str(project / "conf")
    assert user_config_dirs(["--config-dir", conf]) == [project / "conf"]
    assert user_config_dirs([f"--config-dir={conf}", f"hydra.searchpath=[file://{conf}]"]) == [project / "conf"] * 2
    check_selections(["-cd", conf, "model=slow_lorenz", "filter=[my_bpf,ekf]"])  # known there
    check_selections([f"hydra.searchpath=[file://{conf}]", "model=slow_lorenz"])
    with pytest.raises(ConfigError, match="unknown model config 'slow_lorenz'; available: acoustic"):
        check_selections(["model=slow_lorenz"])  # not without the folder
    with pytest.raises(ConfigError, match=r"--config-dir: .*nowhere: no such folder"):
        check_selections(["--config-dir", str(project / "nowhere"), "model=slow_lorenz"])
    check_selections(["model={_target_: mypkg.SlowLorenz}"])  # inline: no name to look up
    assert inline_configs(["model={_target_: a.B, x: 1}", "filter=[ekf]"]) == [
        "~model",
        "+model={_target_: a.B, x: 1}",
        "filter=[ekf]",
    ]
    assert inline_configs(["model=lorenz63", "model.dt=0.1"]) == ["model=lorenz63", "model.dt=0.1"]


def test_the_help_says_how(project):
    out = subprocess.run([sys.executable, "-m", "torchflow", "--help"], capture_output=True, text=True, timeout=120)
    assert "--config-dir" in out.stdout and "model={_target_:" in out.stdout and "# @package filter." in out.stdout
