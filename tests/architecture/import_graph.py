"""The import graph of the package and of the research suites, read from the source with ast.

Every import statement counts wherever it stands: at the top, inside a function (a lazy import
is still a dependency), under ``if TYPE_CHECKING:`` (a type is a dependency for the reader).
"""

from __future__ import annotations

import ast
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "src" / "rlbridge"
SUITES = ROOT / "benchmarks"


def modules(package_dir: Path) -> dict[str, Path]:
    """``dotted name -> file`` of every module under ``package_dir`` (a package's own name for
    its ``__init__.py``)."""
    base = package_dir.parent
    found: dict[str, Path] = {}
    for path in sorted(package_dir.rglob("*.py")):
        parts = list(path.relative_to(base).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        found[".".join(parts)] = path
    return found


def imported_names(module: str, path: Path) -> set[str]:
    """Every name an import statement in ``path`` imports, relative imports resolved:
    ``import a.b`` gives ``a.b``, ``from a import b`` gives ``a.b`` (a submodule ``b``, or a
    name in ``a``: :func:`graph` tells them apart)."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                parts = parts[: len(parts) - node.level + 1]
                base = ".".join([*parts, base] if base else parts)
            names.update(f"{base}.{alias.name}" for alias in node.names)
    return names


def _known(name: str, known: Mapping[str, Path]) -> str | None:
    """The module of ``known`` that importing ``name`` runs last (its longest known prefix)."""
    while name and name not in known:
        name = name.rpartition(".")[0]
    return name or None


def graph(known: Mapping[str, Path]) -> dict[str, set[str]]:
    """``module -> the modules of known it imports`` (itself left out)."""
    edges: dict[str, set[str]] = {}
    for module, path in known.items():
        targets = {_known(n, known) for n in imported_names(module, path)}
        edges[module] = {t for t in targets if t is not None and t != module}
    return edges


def cycles(edges: Mapping[str, Iterable[str]]) -> list[list[str]]:
    """The import circles: strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> Iterator[None]:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                yield from visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))
        yield

    for v in sorted(edges):
        if v not in index:
            for _ in visit(v):
                pass
    return found


def path_between(edges: Mapping[str, Iterable[str]], start: str, goal: str) -> list[str]:
    """One import path ``start -> ... -> goal`` (breadth first), for a readable failure."""
    previous: dict[str, str] = {}
    frontier = [start]
    while frontier:
        nxt = []
        for v in frontier:
            for w in sorted(edges.get(v, ())):
                if w == goal:
                    chain = [v, w]
                    while chain[0] != start:
                        chain.insert(0, previous[chain[0]])
                    return chain
                if w not in previous and w != start:
                    previous[w] = v
                    nxt.append(w)
        frontier = nxt
    return []
