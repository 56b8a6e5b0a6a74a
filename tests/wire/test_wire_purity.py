"""``rlbridge.wire`` is sans-IO: no sockets, event loops, threads or clocks, even indirectly."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import rlbridge.wire

FORBIDDEN = {"asyncio", "socket", "threading", "time", "select", "selectors"}
WIRE_DIR = Path(rlbridge.wire.__file__).parent
#: The one error hierarchy (rlbridge/errors.py) is raised by the wire code, so it is sans-IO too.
ERRORS = WIRE_DIR.parent / "errors.py"
WIRE_MODULES = sorted(WIRE_DIR.glob("*.py"))


def imported_names(path: Path) -> set[str]:
    """Every module named by an import statement in ``path`` (any depth, any branch)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"{path.name}: use absolute imports"
            assert node.module is not None
            names.add(node.module)
            # ``from x import y`` may import a submodule y
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
        elif isinstance(node, ast.Call) and getattr(node.func, "id", "") == "__import__":
            raise AssertionError(f"{path.name}: dynamic import")
    return names


def test_wire_has_modules() -> None:
    assert {p.name for p in WIRE_MODULES} >= {
        "__init__.py", "codec.py", "link.py", "packets.py", "sequence.py"}


def test_wire_sources_import_no_io() -> None:
    for path in [*WIRE_MODULES, ERRORS]:
        names = imported_names(path)
        bad = {n for n in names if n.split(".")[0] in FORBIDDEN}
        assert not bad, f"{path.name} imports {sorted(bad)}"
        # Inside rlbridge, wire depends on wire only (not on the server, SDK or adapters), on
        # rlbridge._compat, the standard library's 3.11 features backported to 3.10, and on
        # rlbridge._compiled, the process's choice of compiled code (aead.py follows it), and
        # on rlbridge.errors, the exceptions (which import nothing of rlbridge).
        ours = {n for n in names if n.split(".")[0] == "rlbridge"
                and not n.startswith(("rlbridge._compat", "rlbridge._compiled",
                                      "rlbridge.errors"))}
        assert all(n.startswith("rlbridge.wire") for n in ours), f"{path.name}: {sorted(ours)}"


def test_importing_wire_loads_no_io_module() -> None:
    """In a fresh interpreter, importing every wire module adds none of the forbidden modules.

    msgspec is imported first: what it needs is its own (on Python 3.10 its ``uuid`` import
    brings ``platform`` and ``subprocess``, hence ``threading``), not the wire code's.
    """
    code = (
        "import json, sys, msgspec\n"
        "before = set(sys.modules)\n"
        "import rlbridge.wire, rlbridge.wire.codec, rlbridge.errors, rlbridge.wire.link\n"
        "import rlbridge.wire.packets, rlbridge.wire.sequence\n"
        "import rlbridge.wire.auth, rlbridge.wire.seal, rlbridge.wire.records\n"
        "print(json.dumps(sorted(set(sys.modules) - before)))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=60)
    added = json.loads(out.stdout)
    assert "rlbridge.wire.codec" in added  # the check really imported something
    bad = [m for m in added if m.split(".")[0] in FORBIDDEN]
    assert not bad, f"importing rlbridge.wire loads {bad}"
