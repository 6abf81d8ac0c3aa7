"""No import cycle among regtrack's modules.

The graph is read from the source with :mod:`ast`; nothing is imported.  An edge
``A -> B`` is an ``import B`` / ``from B import x`` written anywhere in module ``A``: at
module level *and* inside functions.  Function-level imports count because a lazy import
only postpones the dependency (to keep ``regtrack --help`` fast, or to break an
initialisation order); it does not remove it, and a cycle hidden behind one is still two
modules that can only be understood together.  ``from P import x`` is an edge to the
module ``P.x`` when that is a module of the package, else to ``P``.  A package's
``__init__`` is the module ``P`` itself; importing ``P.m`` is not counted as importing
``P`` (Python runs ``P/__init__.py`` first, but every submodule would then be in a cycle
with a package that re-exports it).  Imports under ``if TYPE_CHECKING:`` do count: they
are the same dependency for a reader.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "regtrack"


def module_files(root: Path = ROOT) -> dict[str, Path]:
    """Dotted module name -> source file, for every ``.py`` under ``root``."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def _resolve(mod: str, node: ast.ImportFrom, is_pkg: bool) -> str:
    """The absolute module name of a (possibly relative) ``from ... import``."""
    if not node.level:
        return node.module or ""
    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports_of(mod: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """regtrack modules that ``mod`` imports anywhere in its source."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    is_pkg = path.name == "__init__.py"
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name in modules)
        elif isinstance(node, ast.ImportFrom):
            target = _resolve(mod, node, is_pkg)
            for a in node.names:
                sub = f"{target}.{a.name}"
                if sub in modules:
                    out.add(sub)
                elif target in modules:
                    out.add(target)
    out.discard(mod)
    return out


def import_graph(root: Path = ROOT) -> dict[str, set[str]]:
    modules = module_files(root)
    return {m: imports_of(m, p, modules) for m, p in modules.items()}


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each as one
    cycle through it, sorted; empty when the graph is a DAG."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    comps: list[list[str]] = []

    def visit(v: str) -> None:  # recursion depth <= number of modules (about 200)
        index[v] = low[v] = len(index)
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
                comps.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(_one_cycle(graph, set(c)) for c in comps)


def _one_cycle(graph: dict[str, set[str]], comp: set[str]) -> list[str]:
    """A shortest cycle through the first module of a strongly connected component."""
    start = min(comp)
    prev: dict[str, str] = {}
    frontier = [start]
    while frontier:
        nxt = []
        for v in frontier:
            for w in sorted(graph[v] & comp):
                if w == start:
                    path = [v]
                    while path[-1] != start:
                        path.append(prev[path[-1]])
                    return path[::-1] + [start]
                if w not in prev:
                    prev[w] = v
                    nxt.append(w)
        frontier = nxt
    raise AssertionError("not a strongly connected component")  # pragma: no cover


def test_no_import_cycle():
    graph = import_graph()
    assert len(graph) > 100, "the walk found too few modules: wrong root?"
    cycles = find_cycles(graph)
    assert not cycles, "import cycles among regtrack's modules:\n" + "\n".join(
        " -> ".join(c) for c in cycles)


# --- the walker itself, on a small package with known edges -----------------------------
def _package(tmp_path: Path, files: dict[str, str]) -> Path:
    root = tmp_path / "pkg"
    for name, text in {"__init__.py": "", **files}.items():
        p = root / name
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return root


def test_walker_counts_function_level_and_relative_imports(tmp_path):
    root = _package(tmp_path, {
        "a.py": "from pkg import b\n",
        "b.py": "def f():\n    from . import c\n",
        "c.py": "def g():\n    import pkg.a\n",
        "sub/__init__.py": "from .d import x\n",
        "sub/d.py": "from ..a import thing\nx = 1\n",
    })
    graph = import_graph(root)
    assert graph["pkg.a"] == {"pkg.b"}
    assert graph["pkg.b"] == {"pkg.c"}
    assert graph["pkg.c"] == {"pkg.a"}
    assert graph["pkg.sub"] == {"pkg.sub.d"}
    assert graph["pkg.sub.d"] == {"pkg.a"}
    assert find_cycles(graph) == [["pkg.a", "pkg.b", "pkg.c", "pkg.a"]]


@pytest.mark.parametrize("files", [
    {"a.py": "import pkg.b\n", "b.py": "x = 1\n"},                # a DAG
    {"a.py": "from pkg import b\n", "b.py": "import os\nimport numpy\n"},  # outside imports
])
def test_walker_finds_no_cycle_in_a_dag(tmp_path, files):
    assert find_cycles(import_graph(_package(tmp_path, files))) == []
