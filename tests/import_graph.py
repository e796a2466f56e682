"""The project's import graph read from its source: module-level imports and the ones inside
functions (deferred imports still tie modules together), without ``if TYPE_CHECKING:`` blocks
(never executed). Used by tests/test_layering.py (cycles) and tests/test_keys.py (libraries).
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PROJECT = ("gcvd_flow",)
# the card's top-level folders, installed (and symlinked in the checkout) as parts of gcvd_flow
FOLDERS = {"gcvd_flow": "gcvd_flow", "stages": "gcvd_flow.stages", "artifacts_schema": "gcvd_flow.artifacts_schema"}


def project_modules() -> dict[str, Path]:
    """Dotted module name -> source file of every project module (packages by their name)."""
    out: dict[str, Path] = {}
    for folder, pkg in FOLDERS.items():
        for f in sorted((ROOT / folder).rglob("*.py")):
            parts = list(f.relative_to(ROOT / folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            if folder == "gcvd_flow" and parts and parts[0] in ("stages", "artifacts_schema"):
                continue  # the symlinks: listed once, from the folder itself
            out[".".join([pkg, *parts])] = f
    return out


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _import_nodes(tree: ast.AST):
    """Every Import / ImportFrom node, at any depth, except under ``if TYPE_CHECKING:``."""
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            stack.extend(node.orelse)
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        stack.extend(ast.iter_child_nodes(node))


def raw_imports(module: str, path: Path) -> list[tuple[str, list[str]]]:
    """(absolute module named, [names imported from it]) for every import statement of a module."""
    tree = ast.parse(path.read_text(), str(path))
    is_pkg = path.name == "__init__.py"
    out = []
    for node in _import_nodes(tree):
        if isinstance(node, ast.Import):
            out.extend((a.name, []) for a in node.names)
            continue
        base = node.module or ""
        if node.level:
            parts = module.split(".")
            parent = parts if is_pkg else parts[:-1]
            parent = parent[:len(parent) - (node.level - 1)]
            base = ".".join(parent + ([base] if base else []))
        out.append((base, [a.name for a in node.names]))
    return out


def project_graph() -> dict[str, set[str]]:
    """Module -> the project modules it imports (``from pkg import sub`` counts as importing the
    submodule ``pkg.sub``; ``from pkg import name`` as importing ``pkg``)."""
    mods = project_modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for m, path in mods.items():
        for base, names in raw_imports(m, path):
            targets = [f"{base}.{n}" for n in names if f"{base}.{n}" in mods]
            if len(targets) < len(names) or not names:
                targets.append(base)
            graph[m].update(t for t in targets if t in mods and t != m)
    return graph


def third_party_imports(modules: set[str]) -> dict[str, set[str]]:
    """Top-level name of every non-project, non-stdlib module imported by ``modules`` -> the
    project modules importing it."""
    mods = project_modules()
    out: dict[str, set[str]] = {}
    for m in sorted(modules):
        for base, _ in raw_imports(m, mods[m]):
            top = base.split(".")[0]
            if top and top not in PROJECT and top not in sys.stdlib_module_names:
                out.setdefault(top, set()).add(m)
    return out


def closure(start: list[str], graph: dict[str, set[str]]) -> set[str]:
    """The project modules reachable from ``start`` (included)."""
    seen, todo = set(), list(start)
    while todo:
        m = todo.pop()
        if m not in seen:
            seen.add(m)
            todo.extend(graph.get(m, ()))
    return seen


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10000))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out
