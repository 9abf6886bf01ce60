"""MkDocs hooks of the torchflow documentation (``hooks:`` in mkdocs.yml).

Examples. Every ``docs/examples/*.py`` runs at build time, in this process, with ``runpy`` (as module
``__docs__``, so that a closing ``if __name__ == "__main__": plt.show()`` is skipped), from a
temporary working folder and with matplotlib's Agg back end. Its page ``examples/<name>.md`` is made
from the script: the module docstring's first line is the title and the rest the introduction,
then the code, what it printed and every figure it left open (saved as PNGs into the site). An
example that raises stops the build with its traceback, so ``mkdocs build`` (strict or not) fails
when an example breaks. Examples are meant to run in seconds: small trial counts and particle
numbers, no files written.

API pages. Docstrings of torchflow use Sphinx roles (``:class:`~torchflow.models.StateSpaceModel```),
which Markdown renders as ``:class:`` followed by code. They are rewritten as code, linked to the
API reference where the target is documented there (an optional cross-reference: an undocumented
target, a private helper say, stays plain code and does not warn).
"""

from __future__ import annotations

import ast
import contextlib
import html
import io
import logging
import os
import re
import runpy
import sys
import tempfile
import time
import traceback
from pathlib import Path

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File

log = logging.getLogger("mkdocs.hooks.examples")

EXAMPLES = "examples"
DPI = 110


def _split(source: str, path: Path):
    """``(title, introduction, code)`` of an example script: its docstring's first line, the rest
    of the docstring, and the code after the docstring."""
    module = ast.parse(source, filename=str(path))
    doc = ast.get_docstring(module)
    if not doc:
        raise PluginError(f"docs example {path}: needs a module docstring (its first line is the page title)")
    title, _, intro = doc.partition("\n")
    code = "\n".join(source.splitlines()[module.body[0].end_lineno :]).strip("\n")
    return title.strip(), intro.strip(), code


def _run(path: Path) -> str:
    """Run one example in a temporary working folder; returns what it printed. Raises PluginError
    (which fails the build) with the traceback when the script raises or exits with an error."""
    out = io.StringIO()
    cwd, argv = os.getcwd(), sys.argv
    try:
        with tempfile.TemporaryDirectory() as tmp, contextlib.redirect_stdout(out):
            os.chdir(tmp)
            sys.argv = [str(path)]
            runpy.run_path(str(path), run_name="__docs__")  # not "__main__": no plt.show()
    except SystemExit as err:
        if err.code not in (None, 0):
            raise PluginError(f"docs example {path} exited with status {err.code}:\n{out.getvalue()}") from err
    except Exception as err:
        raise PluginError(
            f"docs example {path} failed:\n{traceback.format_exc()}\nits output before the error:\n{out.getvalue()}"
        ) from err
    finally:
        os.chdir(cwd)
        sys.argv = argv
    return out.getvalue()


def _page(name: str, title: str, intro: str, code: str, printed: str, figures: list[str]) -> str:
    parts = [
        f"# {title}",
        intro,
        f"The script, [`{name}.py`]({name}.py), runs when the documentation is built; the output "
        "and figures below are from that run. Run it yourself with "
        f"`python docs/examples/{name}.py` in a checkout (it needs the `plot` extra).",
        f"```python\n{code}\n```",
    ]
    if printed.strip():
        parts += ["## Output", f"```text\n{printed.rstrip()}\n```"]
    if figures:
        parts += ["## Figures" if len(figures) > 1 else "## Figure"]
        parts += [f"![{title}: figure {k}]({fig})" for k, fig in enumerate(figures, 1)]
    return "\n\n".join(parts) + "\n"


def on_files(files, config):
    """Run every example and add its page and figures to the site."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    folder = Path(config["docs_dir"]) / EXAMPLES
    for path in sorted(folder.glob("*.py")):
        name = path.stem
        title, intro, code = _split(path.read_text(), path)
        plt.close("all")
        start = time.perf_counter()
        printed = _run(path)
        figures = []
        for k, num in enumerate(plt.get_fignums(), 1):
            buf = io.BytesIO()
            plt.figure(num).savefig(buf, format="png", dpi=DPI, bbox_inches="tight")
            figures.append(f"{name}_{k}.png")
            files.append(File.generated(config, f"{EXAMPLES}/{name}_{k}.png", content=buf.getvalue()))
        plt.close("all")
        files.append(
            File.generated(config, f"{EXAMPLES}/{name}.md", content=_page(name, title, intro, code, printed, figures))
        )
        log.info("example %s ran in %.1f s (%d figures)", path.name, time.perf_counter() - start, len(figures))
    return files


_ROLE = re.compile(r":(?:py:)?(?:class|meth|func|mod|attr|data|exc|obj):<code>(~?)([\w.]+(?:\s+[\w.]+)*)(\(\))?</code>")


def _role(match: re.Match) -> str:
    tilde, target, call = match.groups()
    target = re.sub(r"\s+", "", target)  # a docstring may wrap a long name inside its backticks
    shown = (target.rsplit(".", 1)[-1] if tilde else target) + (call or "")
    code = f"<code>{html.escape(shown)}</code>"
    if target.startswith("torchflow."):
        return f'<autoref optional identifier="{html.escape(target)}">{code}</autoref>'
    return code


def on_page_content(html_text, page, config, files):
    """Sphinx roles in rendered docstrings -> code (linked where the API reference documents it)."""
    return _ROLE.sub(_role, html_text)
