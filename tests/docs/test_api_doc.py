"""docs/api.md is generated from the public names only (scripts/gen_api.py), and is true.

The generator runs in a subprocess for the staleness checks (as a user runs it). The
option-rules table is rendered from ``rlbridge.client.option_table.RULES``, the rows the code
raises its ValueErrors from (tests/client/test_option_rules.py runs one test per row).
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import rlbridge
import rlbridge.server

REPO = Path(__file__).resolve().parents[2]
GEN = REPO / "scripts" / "gen_api.py"
API_MD = REPO / "docs" / "api.md"
sys.path.insert(0, str(GEN.parent))
import gen_api  # noqa: E402  (scripts/ is not a package)


def run_gen(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(GEN), *args], capture_output=True, text=True,
                          cwd=REPO, timeout=120, check=False)


def test_api_md_is_what_the_script_makes_now() -> None:
    result = run_gen("--check")
    assert result.returncode == 0, (
        f"docs/api.md is stale or the public API's docs are incomplete; run "
        f"python scripts/gen_api.py and commit the result.\n{result.stderr}")


def test_check_names_the_stale_file_and_writes_nothing(tmp_path: Path) -> None:
    copy = tmp_path / "api.md"
    copy.write_text(API_MD.read_text(encoding="utf-8") + "an edit by hand\n", encoding="utf-8")

    result = run_gen("--check", "--out", str(copy))

    assert result.returncode == 1
    assert "api.md is stale: run python scripts/gen_api.py" in result.stderr
    assert copy.read_text(encoding="utf-8").endswith("an edit by hand\n")


def _public() -> list[str]:
    names = [n for n in rlbridge.__all__ if not n.startswith("__")]
    return names + list(rlbridge.server.__all__)


def test_api_md_documents_every_public_name_and_nothing_else() -> None:
    text = API_MD.read_text(encoding="utf-8")
    headings = set(re.findall(r"^### `(\w+)", text, flags=re.MULTILINE))
    headings |= set(re.findall(r"^ *- `(\w+)`.*: ", text, flags=re.MULTILINE))  # the errors
    assert set(_public()) <= headings, f"missing: {sorted(set(_public()) - headings)}"
    assert headings <= set(_public()), f"not public: {sorted(headings - set(_public()))}"
    members = set(re.findall(r"^#### `(\w+)\.(\w+)", text, flags=re.MULTILINE))
    internal = {tuple(e.split(".")) for e in gen_api.INTERNAL} & members
    assert not internal, f"internal members on the page: {sorted(internal)}"
    assert not {m for m in members if m[1].startswith("_")}
    modules = set(re.findall(r"rlbridge\.(?!server\b|__all__)\w+(?:\.\w+)*", text))
    assert not modules, f"the page names internal modules: {sorted(modules)}"
    private = set(re.findall(r"(?<![\w.])_[A-Za-z]\w*", text))
    assert not private, f"the page shows private names: {sorted(private)}"


def test_api_md_stays_within_its_word_budget() -> None:
    words = len(API_MD.read_text(encoding="utf-8").split())
    assert words <= gen_api.MAX_WORDS, f"docs/api.md has {words} words"
