"""Links into a page's sections land: every ``page.md#anchor`` names a heading of that page.

Pages link to figures by anchor (``benchmarks.md#latency``); a heading renamed without its links
would leave the reader at the top of a long page. Anchors are GitHub's: the heading in lower
case, punctuation other than ``-`` and ``_`` dropped, spaces as ``-``, a repeated heading
suffixed ``-1``, ``-2``. The dated records in benchmarks/results/ are checked for their files
only (test below): they quote the pages as they were.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PAGES = sorted([*ROOT.glob("docs/*.md"), ROOT / "README.md", ROOT / "CONTRIBUTING.md",
                *ROOT.glob("benchmarks/*.md"), *ROOT.glob("examples/**/*.md")])
RECORDS = sorted(ROOT.glob("benchmarks/results/*.md"))
LINK = re.compile(r"\]\(([^)\s#]*)#([^)\s]+)\)")
FILE_LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")
FENCE = re.compile(r"^\s*(```|~~~)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")


def anchors(page: Path) -> set[str]:
    """The anchors GitHub makes for the headings of ``page`` (code blocks skipped)."""
    found: set[str] = set()
    seen: dict[str, int] = {}
    in_code = False
    for line in page.read_text().splitlines():
        if FENCE.match(line):
            in_code = not in_code
            continue
        match = None if in_code else HEADING.match(line)
        if match is None:
            continue
        text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", match.group(2))  # a link: its text
        slug = re.sub(r"[^\w\- ]", "", text.lower()).replace(" ", "-")
        count = seen.get(slug, 0)
        seen[slug] = count + 1
        found.add(slug if count == 0 else f"{slug}-{count}")
    return found


def test_anchor_slugs_follow_github() -> None:
    page = ROOT / "docs" / "concepts.md"
    assert "choosing-a-transport-per-signal-thesis-figure-51" in anchors(page)
    assert "io-threads-how-they-wait-idle-strategies" in anchors(page)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_section_links_resolve(page: Path) -> None:
    broken = []
    for target, anchor in LINK.findall(page.read_text()):
        if "://" in target:
            continue
        linked = page if not target else (page.parent / target)
        if linked.suffix != ".md" or not linked.exists():
            continue  # a missing file is test_links.py's to report
        if anchor not in anchors(linked):
            broken.append(f"{target or page.name}#{anchor}")
    assert not broken, f"{page.relative_to(ROOT)} links to sections that do not exist: {broken}"


@pytest.mark.parametrize("record", RECORDS, ids=lambda p: p.name)
def test_records_link_to_files_that_exist(record: Path) -> None:
    missing = [target for target in FILE_LINK.findall(record.read_text())
               if "://" not in target and not (record.parent / target).exists()]
    assert not missing, f"{record.relative_to(ROOT)} links to missing files: {missing}"
