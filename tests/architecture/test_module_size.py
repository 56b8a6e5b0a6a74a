"""Every module of the package and of the research suites stays under 400 lines.

A module that grows past that usually holds a second idea; split it where the ideas part
(docs/design.md, "The map"), not at an arbitrary line.
"""

from __future__ import annotations

from import_graph import PACKAGE, SUITES, modules

LIMIT = 400


def test_modules_stay_small() -> None:
    found = {**modules(PACKAGE), **modules(SUITES)}
    big = {name: n for name, path in found.items()
           if (n := len(path.read_text().splitlines())) > LIMIT}
    assert not big, f"modules over {LIMIT} lines (split each by idea): {big}"
