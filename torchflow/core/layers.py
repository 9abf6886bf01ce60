"""The floors of the package, and the check that every import respects them.

``python -m torchflow.core.layers`` reads every module of :mod:`torchflow` (imports inside functions
included: a late import hides a dependency, it does not remove it) and exits non-zero, naming the
importing and the imported module, when

* a module imports from a higher floor (:data:`FLOORS`);
* modules import each other in a circle;
* a module in :data:`NO_KERNELS` imports :mod:`torchflow.flows.kernels` (every fast-path decision is
  asked of :mod:`torchflow.flows.select`);
* the package root holds more than :data:`MAX_ROOT_MODULES` modules.

Only the standard library is used, and nothing of torchflow is imported.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path
from typing import Dict, List, Set, Tuple

#: package -> floor; a module may import its own floor and the floors below.
FLOORS: Dict[str, int] = {
    "torchflow.core": 1,
    "torchflow.models": 2,
    "torchflow.flows.kernels": 3,  # the compiled kernels and their calls, beneath the flows
    "torchflow.flows": 4,
    "torchflow.proposals": 5,
    "torchflow.filters": 6,
    "torchflow.smoothing": 7,
    "torchflow.inference": 7,
    "torchflow.tdoa": 7,
    "torchflow.interop": 7,
    "torchflow.app": 8,
    "torchflow": 8,  # the root (__init__, __main__): imports the floors below; only the application imports it
}
#: packages that may not import the flows' kernels.
NO_KERNELS: Tuple[str, ...] = ("torchflow.filters", "torchflow.app")
KERNELS = "torchflow.flows.kernels"
MAX_ROOT_MODULES = 6


def _module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _package(name: str) -> str:
    """The longest key of :data:`FLOORS` that ``name`` lies in."""
    best = "torchflow"
    for pkg in FLOORS:
        if (name == pkg or name.startswith(pkg + ".")) and len(pkg) > len(best):
            best = pkg
    return best


def _imports(path: Path, name: str, modules: Set[str]) -> List[Tuple[str, int]]:
    """``(imported torchflow module, line)`` for every import statement of the file."""
    tree = ast.parse(path.read_text(), str(path))
    is_pkg = path.name == "__init__.py"
    here = name if is_pkg else name.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = here.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            # ``from pkg import sub`` imports the submodule when there is one
            targets = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in modules else mod for a in node.names]
        else:
            continue
        for t in targets:
            if t == "torchflow" or t.startswith("torchflow."):
                while t not in modules and "." in t:  # an attribute of a module
                    t = t.rpartition(".")[0]
                if t != name:
                    found.append((t, node.lineno))
    return found


def _cycles(graph: Dict[str, Set[str]]) -> List[List[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: Dict[str, int] = {}
    low: Dict[str, int] = {}
    stack: List[str] = []
    on: Set[str] = set()
    out: List[List[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    sys.setrecursionlimit(max(10000, sys.getrecursionlimit()))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def check(root: Path | None = None) -> List[str]:
    """Every violation of the floors in the package at ``root`` (default: this installation)."""
    root = Path(root) if root is not None else Path(__file__).resolve().parents[1]
    files = {(_module_name(p, root)): p for p in sorted(root.rglob("*.py"))}
    modules = set(files)
    problems: List[str] = []
    graph: Dict[str, Set[str]] = {}
    # a package's __init__ re-exports its modules: the package depends on them, not the reverse,
    # so an edge into a package's __init__ from inside the same package is not followed
    for name, path in files.items():
        for target, line in _imports(path, name, modules):
            where = f"{path.relative_to(root.parent)}:{line}"
            src, dst = _package(name), _package(target)
            if FLOORS[dst] > FLOORS[src]:
                problems.append(
                    f"upward import: {where}: {name} (floor {FLOORS[src]}) imports {target} (floor {FLOORS[dst]})"
                )
            if target.startswith(KERNELS) and any(name == p or name.startswith(p + ".") for p in NO_KERNELS):
                problems.append(f"kernel import: {where}: {name} imports {target} (ask torchflow.flows.select)")
            inside_init = files[target].name == "__init__.py" and name.startswith(target + ".")
            if not inside_init:
                graph.setdefault(name, set()).add(target)
    for comp in _cycles(graph):
        problems.append("import circle: " + " <-> ".join(comp))
    root_modules = sorted(p.name for p in root.glob("*.py"))
    if len(root_modules) > MAX_ROOT_MODULES:
        problems.append(
            f"the package root holds {len(root_modules)} modules (at most {MAX_ROOT_MODULES}): "
            + ", ".join(root_modules)
        )
    return problems


def main(argv: List[str] | None = None) -> int:
    """The command: the problems, one per line, and exit status 1 if there is any. ``argv``: an
    optional package folder to check in place of the installed one."""
    argv = sys.argv[1:] if argv is None else argv
    problems = check(Path(argv[0]) if argv else None)
    for p in problems:
        print(p)
    print(f"torchflow floors: {len(problems)} problem(s)")
    return 1 if problems else 0


if __name__ == "__main__":
    raise SystemExit(main())
