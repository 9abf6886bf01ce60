"""The floors of the package (torchflow.core.layers): the installed package has none of the faults
the check looks for, and the check finds each fault in a package made to have it."""

from pathlib import Path

from torchflow.core import layers


def test_the_package_keeps_its_floors():
    assert layers.check() == []


def _package(tmp_path: Path, files: dict) -> Path:
    root = tmp_path / "torchflow"
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root


def test_the_check_finds_each_fault(tmp_path):
    root = _package(
        tmp_path,
        {
            "__init__.py": "",
            "core/__init__.py": "",
            "core/linalg.py": "from torchflow.filters import base\n",  # upward
            "filters/__init__.py": "",
            "filters/base.py": "def f():\n    from torchflow.flows.kernels import steps\n",  # a kernel, late
            "filters/other.py": "from torchflow.filters import base, third\n",
            "filters/third.py": "from . import other\n",  # a circle through a relative import
            "flows/__init__.py": "",
            "flows/kernels/__init__.py": "",
            "flows/kernels/steps.py": "",
            **{f"m{i}.py": "" for i in range(6)},  # 7 root modules with __init__
        },
    )
    problems = layers.check(root)
    text = "\n".join(problems)
    assert (
        "upward import: torchflow/core/linalg.py:1: torchflow.core.linalg (floor 1) imports torchflow.filters.base"
        in text
    )
    assert "kernel import: torchflow/filters/base.py:2" in text
    assert "import circle: torchflow.filters.other <-> torchflow.filters.third" in text
    assert "the package root holds 7 modules" in text
    assert len(problems) == 4


def test_the_command_exits_non_zero_on_a_fault(tmp_path, capsys):
    files = {"__init__.py": "", "core/__init__.py": "", "core/a.py": "import torchflow.app.cli\n"}
    root = _package(tmp_path, {**files, "app/__init__.py": "", "app/cli.py": ""})
    assert layers.main([str(root)]) == 1
    out = capsys.readouterr().out
    assert "torchflow.core.a (floor 1) imports torchflow.app.cli (floor 8)" in out
    assert "torchflow floors: 1 problem(s)" in out
