"""No import circles, in the package or in the research suites beside it.

An import circle is a responsibility in the wrong file (docs/design.md, "The map"): two
modules that each need the other are one idea split badly, or one of them needs only a
description of the other (a Protocol) or a piece that belongs in a third module. Imports
inside functions and under ``TYPE_CHECKING`` count: a lazy import that only dodges a circle
is still the circle.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from import_graph import PACKAGE, SUITES, cycles, graph, imported_names, modules, path_between


def _describe(edges: dict[str, set[str]], circle: list[str]) -> str:
    first = circle[0]
    back = [path_between(edges, first, other) + path_between(edges, other, first)[1:]
            for other in circle[1:2]]
    return f"{', '.join(circle)} (e.g. {' -> '.join(back[0])})"


@pytest.mark.parametrize("root", [PACKAGE, SUITES], ids=["src/rlbridge", "benchmarks"])
def test_no_import_circles(root: Path) -> None:
    known = modules(PACKAGE) | (modules(SUITES) if root is SUITES else {})
    edges = graph(known)
    prefix = "rlbridge" if root is PACKAGE else "benchmarks"
    found = [c for c in cycles(edges) if any(m.split(".")[0] == prefix for m in c)]
    assert not found, "import circles:\n" + "\n".join(_describe(edges, c) for c in found)


def test_the_finder_sees_circles_through_lazy_and_type_only_imports() -> None:
    """The detector itself: a circle closed by a function-level import is found."""
    edges = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(edges) == [["a", "b", "c"]]
    assert path_between(edges, "a", "c") == ["a", "b", "c"]


def test_imports_inside_functions_and_type_checking_count(tmp_path: Path) -> None:
    src = tmp_path / "m.py"
    src.write_text("from typing import TYPE_CHECKING\n"
                   "if TYPE_CHECKING:\n    from pkg.a import A\n"
                   "def f() -> None:\n    from . import b\n    import pkg.c\n")
    names = imported_names("pkg.m", src)
    assert {"pkg.a.A", "pkg.b", "pkg.c"} <= names
