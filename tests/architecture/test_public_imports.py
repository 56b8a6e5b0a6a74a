"""What users read imports only the public API: ``rlbridge`` (and ``rlbridge.server`` to embed
a server), so the package's file layout can change without breaking them.

Checked: every Python file and Markdown code block under examples/, the demo's control side
(the embedded board's code: ``CONTROL_SIDE`` below), and every code block of README.md and
docs/*.md (any language: a ``python -c`` line counts too). A name imported from ``rlbridge``
must be in ``rlbridge.__all__``. The demo (``rlbridge.demo``) is an application built on the
public API, not part of the SDK: its own modules may import each other (and, being inside the
package, ``rlbridge._compat``, the package's Python 3.10 backports, which are no SDK API), and
the pan-tilt example, which runs the demo's sides as separate programs, may import them.
"""

from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

import pytest

import rlbridge

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests" / "docs"))
from doc_blocks import PAGES, Block, all_blocks  # noqa: E402  (tests/docs is not on the path)

DEMO = ROOT / "src" / "rlbridge" / "demo"
# The demo's embedded side (its package docstring): the 1 kHz loop, its control law, the plant.
CONTROL_SIDE = [DEMO / f"{name}.py" for name in ("controller", "loop", "control", "plant")]
EXAMPLES = ROOT / "examples"
PUBLIC_MODULES = ("rlbridge", "rlbridge.server")
# Imports as text, for blocks that are not Python or do not parse alone (fragments).
IMPORT_TEXT = re.compile(r"^\s*(?:from\s+(rlbridge[\w.]*)\s+import\s+([^#\n]+)"
                         r"|import\s+(rlbridge[\w.]*))", re.MULTILINE)


DEMO_MAY_IMPORT = ("rlbridge.demo", "rlbridge._compat")


def allowed_module(module: str, *, demo: bool) -> bool:
    return module in PUBLIC_MODULES or (demo and any(
        module == m or module.startswith(m + ".") for m in DEMO_MAY_IMPORT))


def _names(text: str) -> list[str]:
    return [n.split(" as ")[0].strip(" ()\\") for n in text.split(",") if n.strip(" ()\\")]


def imports(code: str) -> list[tuple[str, list[str]]]:
    """``(module, names)`` of every import of rlbridge in ``code`` (names: ``from`` imports)."""
    try:
        tree = ast.parse(code)
    except SyntaxError:
        return [(m[0] or m[2], _names(m[1]) if m[0] else []) for m in IMPORT_TEXT.findall(code)]
    found: list[tuple[str, list[str]]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(a.name, []) for a in node.names if a.name.split(".")[0] == "rlbridge"]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module \
                and node.module.split(".")[0] == "rlbridge":
            found.append((node.module, [a.name for a in node.names]))
    # ``python -c "from rlbridge.x import y"`` in a string, e.g. a subprocess's command line
    for string in (n.value for n in ast.walk(tree)
                   if isinstance(n, ast.Constant) and isinstance(n.value, str)):
        found += [(m[0] or m[2], _names(m[1]) if m[0] else [])
                  for m in IMPORT_TEXT.findall(string)]
    return found


def violations(code: str, *, demo: bool = False) -> list[str]:
    bad: list[str] = []
    for module, names in imports(code):
        if not allowed_module(module, demo=demo):
            bad.append(f"imports {module} (use `from rlbridge import ...`)")
        elif module == "rlbridge":
            bad += [f"imports {n} from rlbridge, which is not in rlbridge.__all__"
                    for n in names if n not in rlbridge.__all__ and n != "server"]
    return bad


def _example_sources() -> list[object]:
    found = [pytest.param(str(p.relative_to(ROOT)), p.read_text(encoding="utf-8"),
                          id=str(p.relative_to(EXAMPLES))) for p in sorted(EXAMPLES.rglob("*.py"))]
    found += [pytest.param(b.name, b.code, id=b.name)
              for b in all_blocks(sorted(EXAMPLES.rglob("*.md")))]
    return found


@pytest.mark.parametrize(("name", "code"), _example_sources())
def test_examples_import_the_public_api_only(name: str, code: str) -> None:
    bad = violations(code, demo=True)
    assert not bad, f"{name}: " + "; ".join(bad)


@pytest.mark.parametrize("path", CONTROL_SIDE, ids=lambda p: p.name)
def test_the_demos_control_side_imports_the_public_api_only(path: Path) -> None:
    bad = violations(path.read_text(encoding="utf-8"), demo=True)
    assert not bad, f"{path.relative_to(ROOT)}: " + "; ".join(bad)


def _doc_blocks() -> list[Block]:
    return [b for b in all_blocks(PAGES) if b.is_code]


@pytest.mark.parametrize("block", _doc_blocks(), ids=lambda b: b.name)
def test_doc_code_blocks_import_the_public_api_only(block: Block) -> None:
    bad = violations(block.code)
    assert not bad, f"{block.name}: " + "; ".join(bad)


@pytest.mark.parametrize(("code", "expected"), [
    ("from rlbridge import Bridge, QoS\n", []),
    ("import rlbridge\nfrom rlbridge.server import Server\n", []),
    ("from rlbridge.hrt.shm import ShmLink\n", ["imports rlbridge.hrt.shm"]),
    ("import rlbridge.wire.errors as e\n", ["imports rlbridge.wire.errors"]),
    ("from rlbridge import csp\n", ["imports csp from rlbridge"]),
    ("x = ...\n    from rlbridge.csp import patterns  # a fragment\n",
     ["imports rlbridge.csp"]),
    ("run(['python', '-c', 'from rlbridge.client.bridge import Bridge'])\n",
     ["imports rlbridge.client.bridge"]),
])
def test_the_rule_sees_each_form_of_import(code: str, expected: list[str]) -> None:
    """The checker itself: each form of import it must catch (and the two it must allow)."""
    found = violations(code)
    assert len(found) == len(expected), found
    for got, want in zip(found, expected, strict=True):
        assert got.startswith(want), got
