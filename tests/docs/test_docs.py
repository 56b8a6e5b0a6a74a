"""docs/cli.md is generated (scripts/gen_docs.py); these tests keep it current (docs/api.md:
test_api_doc.py).

The generator runs in a subprocess: it must choose typer's plain help formatter before typer is
imported, which the test process has long done.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
GEN = REPO / "scripts" / "gen_docs.py"
DOCS = REPO / "docs"


def gen_docs(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(GEN), *args], capture_output=True, text=True,
                          cwd=REPO, timeout=100, check=False)


def test_generated_docs_are_current() -> None:
    result = gen_docs("--check")
    assert result.returncode == 0, (
        "docs/cli.md is stale; "
        f"run python scripts/gen_docs.py and commit the result.\n{result.stderr}")


def test_check_names_the_stale_file_and_the_fix(tmp_path: Path) -> None:
    stale = tmp_path / "cli.md"
    stale.write_text((DOCS / "cli.md").read_text(encoding="utf-8") + "an edit by hand\n",
                     encoding="utf-8")

    result = gen_docs("--check", "--docs", str(tmp_path))

    assert result.returncode == 1
    assert "cli.md is stale: run python scripts/gen_docs.py" in result.stderr
    assert stale.read_text(encoding="utf-8").endswith("an edit by hand\n")  # --check wrote nothing


def test_generator_rewrites_a_missing_file(tmp_path: Path) -> None:
    result = gen_docs("--docs", str(tmp_path))

    assert result.returncode == 0, result.stderr
    assert (tmp_path / "cli.md").read_text(encoding="utf-8") == \
        (DOCS / "cli.md").read_text(encoding="utf-8")


def _sections(text: str) -> dict[str, str]:
    parts = re.split(r"^## (rlbridge.*)$", text, flags=re.MULTILINE)
    return dict(zip(parts[1::2], parts[2::2], strict=True))


def test_cli_reference_has_a_section_for_every_listed_subcommand() -> None:
    sections = _sections((DOCS / "cli.md").read_text(encoding="utf-8"))
    assert {"rlbridge", "rlbridge serve", "rlbridge demo", "rlbridge topic pub",
            "rlbridge bench latency"} <= set(sections)
    for path, body in sections.items():
        assert f"Usage: {path} " in body, f"section {path!r} is not that command's --help"
        assert "\x1b[" not in body, "help must be plain text, no colour"
        assert "╭" not in body, "help must be plain text, no rich boxes"
        listed = re.search(r"^Commands:\n((?:  .*\n)+)", body, flags=re.MULTILINE)
        for line in (listed[1].splitlines() if listed else []):
            sub = line.split()[0]
            assert f"{path} {sub}" in sections, f"{path} lists {sub} but cli.md has no section"
        assert all(len(line) <= 100 for line in body.splitlines()), f"{path}: wider than 100"
