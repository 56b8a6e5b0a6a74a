"""The map in docs/design.md is true: every import in src/rlbridge runs the way its table says.

The table between the ``import-map`` markers is the one place the allowed directions are
written; this test reads it. A part is a folder (``wire/``: every module below
``rlbridge.wire``), a module (``cli``: ``rlbridge.cli``; ``adapters/base``;
``adapters/__init__``: the package's own ``__init__``), or ``__init__`` (``rlbridge`` itself).
Imports inside a part are free; an import of another part must be listed in the part's row,
and a row may list only parts below it (imports run down the table). "never imports" names
modules outside rlbridge the part must not import, even lazily.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import pytest
from import_graph import PACKAGE, ROOT, graph, imported_names, modules

DESIGN = ROOT / "docs" / "design.md"
TICKED = re.compile(r"`([^`]+)`")


@dataclass(frozen=True)
class Row:
    parts: tuple[str, ...]
    allowed: tuple[str, ...]
    never: tuple[str, ...]


def module_of(part: str) -> str:
    """``wire/`` -> ``rlbridge.wire``; ``adapters/base`` -> ``rlbridge.adapters.base``."""
    name = part.rstrip("/").removesuffix("/__init__").removesuffix("__init__").rstrip("/")
    return "rlbridge" + ("." + name.replace("/", ".") if name else "")


def covers(part: str, module: str) -> bool:
    base = module_of(part)
    return module == base or (part.endswith("/") and module.startswith(base + "."))


def read_map(text: str) -> list[Row]:
    """The rows of the table between the markers, top to bottom."""
    body = text.split("<!-- import-map:begin -->")[1]
    body = body.split("<!-- import-map:end -->", maxsplit=1)[0]
    rows = []
    for line in body.strip().splitlines()[2:]:
        cells = [c.strip() for c in re.split(r"(?<!\\)\|", line.strip().strip("|"))]
        assert len(cells) == 4, f"docs/design.md import map: a row needs 4 cells: {line}"
        rows.append(Row(tuple(TICKED.findall(cells[0])), tuple(TICKED.findall(cells[2])),
                        tuple(TICKED.findall(cells[3]))))
    return rows


ROWS = read_map(DESIGN.read_text())
MODULES = modules(PACKAGE)
GRAPH = graph(MODULES)


def row_of(module: str) -> Row | None:
    """The row of the most specific part that covers ``module``."""
    best: tuple[int, Row] | None = None
    for row in ROWS:
        for part in row.parts:
            if covers(part, module) and (best is None or len(module_of(part)) > best[0]):
                best = (len(module_of(part)), row)
    return None if best is None else best[1]


def test_the_map_is_in_the_design_doc_and_runs_down() -> None:
    assert len(ROWS) >= 8
    below: set[str] = set()
    for row in reversed(ROWS):
        up = [a for a in row.allowed if not any(covers(b, module_of(a)) for b in below)]
        assert not up, f"{row.parts}: may import only parts listed below it, not {up}"
        below.update(row.parts)


def test_every_module_is_on_the_map() -> None:
    lost = [m for m in MODULES if row_of(m) is None]
    assert not lost, (f"not on the map: {lost}. Add a row (part | owns | imports of rlbridge | "
                      "never imports) to the import map in docs/design.md, below every part "
                      "that imports it, or put the module in a folder that has a row.")


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_run_the_documented_way(module: str) -> None:
    row = row_of(module)
    assert row is not None
    against = []
    for target in sorted(GRAPH[module]):
        if row_of(target) is row:
            continue
        if not any(covers(part, target) for part in row.allowed):
            against.append(target)
    assert not against, (f"{module} imports {against}: its row in docs/design.md "
                         f"({', '.join(row.parts)}) allows only {list(row.allowed)}. Move the "
                         "code, or, if the direction is right, list the part in that row "
                         "(it must be a row below).")
    names = {n.split(".")[0] for n in imported_names(module, MODULES[module])}
    assert "benchmarks" not in names, f"{module} imports the research suites (benchmarks/)"
    forbidden = sorted(names & set(row.never))
    assert not forbidden, f"{module} imports {forbidden}, which {row.parts} never imports"



def test_the_checker_refuses_an_upward_import() -> None:
    """The mechanism: wire importing csp is against the map, csp importing wire is not."""
    wire, csp = row_of("rlbridge.wire.codec"), row_of("rlbridge.client.bridge")
    assert wire is not None
    assert csp is not None
    assert not any(covers(p, "rlbridge.client.bridge") for p in wire.allowed)
    assert any(covers(p, "rlbridge.wire.codec") for p in csp.allowed)
    assert covers("adapters/base", "rlbridge.adapters.base")
    assert not covers("adapters/base", "rlbridge.adapters.ros2")
    assert covers("adapters/__init__", "rlbridge.adapters")
    assert module_of("__init__") == "rlbridge"
