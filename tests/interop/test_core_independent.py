"""The core never imports the optional interop libraries (Stone Soup): torchflow and every core
subpackage import with ``stonesoup`` blocked."""

import subprocess
import sys

from conftest import ROOT

CODE = """
import sys
sys.modules["stonesoup"] = None  # any 'import stonesoup' now raises ImportError
import torchflow, torchflow.filters, torchflow.flows, torchflow.models, torchflow.proposals, torchflow.app.runner
import torchflow.interop  # the package itself is light; only torchflow.interop.stonesoup needs Stone Soup
try:
    import torchflow.interop.stonesoup
except ImportError:
    print("OK")
"""


def test_core_imports_without_stonesoup():
    out = subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert out.returncode == 0 and out.stdout.strip() == "OK", out.stderr[-2000:]
