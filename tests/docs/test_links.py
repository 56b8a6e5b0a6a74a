"""docs/ is for reading: its links resolve, raw results live beside the benchmarks, and every
page that shows a figure names the command that makes it."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
PAGES = sorted([*DOCS.glob("*.md"), ROOT / "README.md", *ROOT.glob("examples/**/*.md"),
                *ROOT.glob("benchmarks/*.md")])
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")
COMMAND = re.compile(r"(rlbridge bench \w+|python -m benchmarks\.\w+|rlbridge demo)")


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page: Path) -> None:
    missing = [target for target in LINK.findall(page.read_text())
               if "://" not in target and not target.startswith("mailto:")
               and not (page.parent / target).exists()]
    assert not missing, f"{page.relative_to(ROOT)} links to missing files: {missing}"


def test_docs_top_level_holds_prose_only() -> None:
    """Figures go to docs/figures/, raw results to benchmarks/results/."""
    stray = [p.name for p in DOCS.iterdir() if p.is_file() and p.suffix != ".md"]
    assert not stray, f"not prose, move out of docs/: {stray}"
    assert not list(DOCS.rglob("*.json"))
    assert not list(DOCS.rglob("*.csv"))


@pytest.mark.parametrize("page", [p for p in PAGES if p.parent == DOCS],
                         ids=lambda p: p.name)
def test_a_page_with_figures_names_the_command_that_makes_them(page: Path) -> None:
    text = page.read_text()
    if "](figures/" in text:
        assert COMMAND.search(text), f"{page.name} shows figures but names no command"


def test_the_index_lists_every_page() -> None:
    index = (DOCS / "README.md").read_text()
    unlisted = [p.name for p in DOCS.glob("*.md") if p.name != "README.md"
                and f"]({p.name})" not in index]
    assert not unlisted, f"docs/README.md does not list {unlisted}"
