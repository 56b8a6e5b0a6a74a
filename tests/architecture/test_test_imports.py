"""Test modules import their helpers by unique names, never ``conftest``.

The test directories have no ``__init__.py``: pytest puts each one on ``sys.path`` and imports
its files by their bare names. So two files of one name in two directories are one module to
Python, and which ``conftest`` a ``from conftest import x`` finds depends on which directory
pytest collected last (``pytest tests/adapters/... tests/csp/...`` failed to collect). Helpers
that tests import live in modules of their own (``tests/adapters/ros_peers.py``); conftest files
only offer fixtures.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

TESTS = Path(__file__).resolve().parents[1]


def _python_files() -> list[Path]:
    return sorted(p for p in TESTS.rglob("*.py") if "__pycache__" not in p.parts)


def _imported_names(path: Path) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names


def test_no_test_module_imports_conftest() -> None:
    offenders = [str(p.relative_to(TESTS)) for p in _python_files()
                 if "conftest" in _imported_names(p)]
    assert not offenders, f"import helpers from a uniquely named module, not conftest: {offenders}"


def test_module_names_are_unique_across_test_directories() -> None:
    seen: defaultdict[str, list[str]] = defaultdict(list)
    for path in _python_files():
        if path.name != "conftest.py":
            seen[path.stem].append(str(path.relative_to(TESTS)))
    clashes = {name: paths for name, paths in seen.items() if len(paths) > 1}
    assert not clashes, f"one module name in two test directories (rename one): {clashes}"


def test_one_wait_until_helper() -> None:
    """Tests wait the one way (tests/waiting.py): no module defines its own ``wait_until``."""
    own = [str(p.relative_to(TESTS)) for p in _python_files() if p.name != "waiting.py"
           and any(isinstance(node, ast.FunctionDef) and node.name == "wait_until"
                   for node in ast.parse(p.read_text(), filename=str(p)).body)]
    assert not own, f"define no wait_until of your own, import it from waiting: {own}"
