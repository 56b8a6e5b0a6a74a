"""docs/troubleshooting.md lists every message the command line, ``rlbridge ping`` and the
server's start-up and notices can print (the longest fixed part of each, read from the code)."""

from __future__ import annotations

import ast
import re
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SRC = ROOT / "src" / "rlbridge"
DOC = ROOT / "docs" / "troubleshooting.md"

#: Module -> the calls whose message argument (index) reaches a user.
SOURCES = {
    "cli/commands.py": {"fail": 0},
    "cli/options.py": {"fail": 0},
    "cli/errors.py": {"fail": 0},
    "cli/delivery.py": {},
    "demo/cli.py": {"fail": 0},
    "cli/ping.py": {"NoAnswer": 0},
    "server/app.py": {"ServerError": 0},
    "server/notices.py": {},
    "server/gate.py": {"warn": 1},
    "server/udp.py": {"warn": 1},
    "server/tcp.py": {"warn": 1},
    "server/tls_side.py": {"warn": 1},
    "server/session.py": {"warn": 1},
    "server/access.py": {"ValueError": 0},
    "wire/auth.py": {"RemoteProtocolError": 1, "ValueError": 0},
}


#: Programming errors inside rlbridge, not messages a user can act on.
INTERNAL = {"client nonce must be"}


def _name(func: ast.expr) -> str:
    return func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")


def _fragments(node: ast.expr) -> list[str]:
    """The fixed parts of a string or f-string expression."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return [node.value]
    if isinstance(node, ast.JoinedStr):
        parts, current = [], ""
        for value in node.values:
            if isinstance(value, ast.Constant):
                current += str(value.value)
            else:
                parts.append(current)
                current = ""
        return [*parts, current]
    if isinstance(node, ast.BinOp):  # "a" "b" split over lines, or "a" + f"b"
        return _fragments(node.left) + _fragments(node.right)
    return []


def _messages() -> Iterator[tuple[str, str]]:
    for module, calls in SOURCES.items():
        tree = ast.parse((SRC / module).read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and _name(node.func) in calls:
                index = calls[_name(node.func)]
                if len(node.args) > index:
                    frags = [f.replace("`", "").strip(" :;(),.")
                             for f in _fragments(node.args[index])]
                    longest = max(frags, key=len, default="")
                    if len(longest) >= 12 and longest not in INTERNAL:
                        yield f"{module}:{node.lineno}", longest


def _doc_text() -> str:
    return re.sub(r"\s+", " ", DOC.read_text().replace("`", ""))


@pytest.mark.parametrize(("where", "fragment"), sorted(set(_messages())))
def test_the_message_is_in_the_troubleshooting_page(where: str, fragment: str) -> None:
    assert re.sub(r"\s+", " ", fragment) in _doc_text(), (
        f"{where}: '{fragment}' is not in docs/troubleshooting.md: add a row (message, "
        "cause, what to do)")


def test_the_page_is_linked_from_the_readme_and_getting_started() -> None:
    for doc in (ROOT / "README.md", ROOT / "docs" / "getting-started.md"):
        assert "troubleshooting.md" in doc.read_text(), doc.name
