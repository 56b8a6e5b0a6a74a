"""Every hand-inlined fast path names what it copies and has a parity test against it.

A fast path that copies a general path's steps (to save Python calls once per value) is a
twin: when the general path changes, the copy must change with it. So the copy says so, with a
comment inside the function that holds it::

    # inlines: Inbound._admit, SequenceTracker.accept

and a property-based test (hypothesis ``@given``) checks that the fast path and the general
path it copies end in the same state for any input. That test is marked with the fast path's
dotted name, which is how this check finds it::

    @pytest.mark.parity("rlbridge.server.bindings.Inbound.on_value")
    @given(...)
    def test_...

This check fails on a tag without such a test, on a marker that names no tagged fast path
(renamed, or its tag removed), and on a tag naming something the package does not define.
"""

from __future__ import annotations

import ast
import functools
import re
from collections.abc import Iterator

import pytest
from import_graph import PACKAGE, ROOT, modules

TESTS = ROOT / "tests"
TAG = re.compile(r"#\s*inlines:\s*(.+?)\s*$")


def _functions(tree: ast.AST) -> Iterator[tuple[str, ast.FunctionDef | ast.AsyncFunctionDef]]:
    """``(qualified name, node)`` of every function and method, nested ones too."""
    def walk(node: ast.AST, prefix: str) -> Iterator[
            tuple[str, ast.FunctionDef | ast.AsyncFunctionDef]]:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                yield prefix + child.name, child
                yield from walk(child, f"{prefix}{child.name}.")
            elif isinstance(child, ast.ClassDef):
                yield from walk(child, f"{prefix}{child.name}.")
            else:
                yield from walk(child, prefix)
    return walk(tree, "")


def tags(module: str, source: str) -> dict[str, list[str]]:
    """``dotted fast path -> the names its tags say it inlines``, for one module's source.

    A tag belongs to the innermost function whose lines hold it; a tag outside any function
    is an error (it copies nothing a test could run).
    """
    found: dict[str, list[str]] = {}
    lines = source.splitlines()
    spans = [(node.lineno, node.end_lineno or node.lineno, name)
             for name, node in _functions(ast.parse(source))]
    for number, line in enumerate(lines, 1):
        match = TAG.search(line)
        if not match:
            continue
        holders = [(end - start, name) for start, end, name in spans if start <= number <= end]
        if not holders:
            raise AssertionError(f"{module}:{number}: '# inlines:' outside a function")
        owner = f"{module}.{min(holders)[1]}"
        found.setdefault(owner, []).extend(
            n.strip() for n in match.group(1).split(",") if n.strip())
    return found


def _is_given(decorator: ast.expr) -> bool:
    func = decorator.func if isinstance(decorator, ast.Call) else decorator
    return (isinstance(func, ast.Name) and func.id == "given") or (
        isinstance(func, ast.Attribute) and func.attr == "given")


def parity_tests(source: str) -> dict[str, list[tuple[str, bool]]]:
    """``fast path -> [(test name, is a hypothesis test)]`` of ``@pytest.mark.parity("...")``."""
    found: dict[str, list[tuple[str, bool]]] = {}
    for name, node in _functions(ast.parse(source)):
        given = any(_is_given(d) for d in node.decorator_list)
        for d in node.decorator_list:
            if (isinstance(d, ast.Call) and isinstance(d.func, ast.Attribute)
                    and d.func.attr == "parity"):
                for arg in d.args:
                    if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                        found.setdefault(arg.value, []).append((name, given))
    return found


@functools.cache
def _package_tags() -> dict[str, list[str]]:
    found: dict[str, list[str]] = {}
    for module, path in modules(PACKAGE).items():
        found.update(tags(module, path.read_text()))
    return found


@functools.cache
def _test_markers() -> dict[str, list[tuple[str, bool]]]:
    found: dict[str, list[tuple[str, bool]]] = {}
    for path in sorted(TESTS.rglob("*.py")):
        for key, tests in parity_tests(path.read_text()).items():
            found.setdefault(key, []).extend(
                (f"{path.relative_to(ROOT)}::{name}", given) for name, given in tests)
    return found


@functools.cache
def _defined_names() -> set[str]:
    """Every function's and class's qualified name in the package (``Class.method``, ...)."""
    names: set[str] = set()
    for path in modules(PACKAGE).values():
        tree = ast.parse(path.read_text())
        names.update(name for name, _ in _functions(tree))
        names.update(node.name for node in ast.walk(tree) if isinstance(node, ast.ClassDef))
    return names


def test_every_inlined_fast_path_has_a_property_based_parity_test() -> None:
    found = _package_tags()
    assert found, "no '# inlines:' tag found: the check would pass on nothing"
    markers = _test_markers()
    missing = sorted(path for path in found if not any(g for _, g in markers.get(path, [])))
    assert not missing, (
        "fast paths tagged '# inlines:' without a @pytest.mark.parity(...) @given test: "
        + ", ".join(missing))


def test_every_parity_marker_names_a_tagged_fast_path() -> None:
    found = _package_tags()
    stale = {key: tests for key, tests in _test_markers().items() if key not in found}
    assert not stale, f"parity markers naming no tagged fast path: {stale}"


def test_tags_name_what_the_package_defines() -> None:
    defined = _defined_names()
    unknown = {path: [n for n in names if n not in defined]
               for path, names in _package_tags().items()}
    assert not any(unknown.values()), f"'# inlines:' names nothing defined: {unknown}"


def test_the_finder_reads_tags_and_markers() -> None:
    """The scanner itself, on sources made up here: innermost function, several names."""
    source = ("class A:\n"
              "    def fast(self) -> None:\n"
              "        x = 1  # inlines: A.slow, helper\n"
              "    def slow(self) -> None:\n"
              "        pass\n"
              "def outer() -> None:\n"
              "    def inner() -> None:\n"
              "        # inlines: A.slow\n"
              "        pass\n")
    assert tags("pkg.m", source) == {"pkg.m.A.fast": ["A.slow", "helper"],
                                     "pkg.m.outer.inner": ["A.slow"]}
    tests = ("import pytest\nfrom hypothesis import given\n"
             "@pytest.mark.parity('pkg.m.A.fast')\n@given(x=None)\ndef test_a(x): pass\n"
             "@pytest.mark.parity('pkg.m.outer.inner')\ndef test_b(): pass\n")
    assert parity_tests(tests) == {"pkg.m.A.fast": [("test_a", True)],
                                   "pkg.m.outer.inner": [("test_b", False)]}


def test_a_tag_outside_a_function_is_refused() -> None:
    with pytest.raises(AssertionError, match="outside a function"):
        tags("pkg.m", "X = 1  # inlines: A.slow\n")
