"""The fenced code blocks of README.md and docs/*.md, with the markers written above them.

Shared by the snippet runner (tests/docs/test_snippets.py, whose docstring says what the
markers mean) and the import rule (tests/architecture/test_public_imports.py). A marker is an
HTML comment on its own line directly above the fence (several may stack):

    <!-- fragment: why this block cannot run alone -->
    <!-- needs: ros2 -->
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PAGES: list[Path] = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

# Tags of blocks that show text (output, data, layouts) rather than code to run.
NOT_CODE = frozenset({"", "text", "json", "yaml", "toml", "ini", "csv", "mermaid", "output"})
PYTHON = frozenset({"python", "py"})
SHELL = frozenset({"sh", "bash", "shell", "console"})
# The environments a block may ask for with ``<!-- needs: ... -->``.
NEEDS = frozenset({"ros2"})

_FENCE = re.compile(r"^(?P<indent>[ \t]*)(?P<fence>`{3,}|~{3,})(?P<lang>[\w+-]*)[^`]*$")
_MARKER = re.compile(r"^\s*<!--\s*(?P<key>[\w-]+)\s*:\s*(?P<value>.*?)\s*-->\s*$")


@dataclass(frozen=True)
class Block:
    """One fenced block: where it is, its language tag, its code (dedented), its markers."""

    page: Path
    line: int  # 1-based line of the opening fence
    lang: str
    code: str
    markers: dict[str, str] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"

    @property
    def fragment(self) -> str | None:
        return self.markers.get("fragment")

    @property
    def needs(self) -> frozenset[str]:
        return frozenset(w.strip() for w in self.markers.get("needs", "").split(",") if w.strip())

    @property
    def is_code(self) -> bool:
        return self.lang not in NOT_CODE


def blocks(page: Path) -> list[Block]:
    """Every fenced block of ``page``, in order (an unclosed fence runs to the end)."""
    lines = page.read_text(encoding="utf-8").splitlines()
    found: list[Block] = []
    i = 0
    while i < len(lines):
        opening = _FENCE.match(lines[i])
        if opening is None:
            i += 1
            continue
        indent, fence = opening["indent"], opening["fence"]
        markers: dict[str, str] = {}
        j = i - 1
        while j >= 0 and (marker := _MARKER.match(lines[j])):
            markers.setdefault(marker["key"], marker["value"])
            j -= 1
        body: list[str] = []
        k = i + 1
        while k < len(lines) and not lines[k].strip().startswith(fence[0] * len(fence)):
            line = lines[k]
            body.append(line[len(indent):] if line.startswith(indent) else line.lstrip())
            k += 1
        found.append(Block(page, i + 1, opening["lang"].lower(), "\n".join(body) + "\n",
                           markers))
        i = k + 1
    return found


def all_blocks(pages: list[Path] | None = None) -> list[Block]:
    return [b for page in (PAGES if pages is None else pages) for b in blocks(page)]
