"""The keys the docs' own commands write into the checkout are ignored by git.

getting-started.md's shared-network demo writes ``rlbridge-demo.key`` where it runs,
security.md's ``rlbridge tls init tls/`` writes ``tls/server.key``, and getting-started.md's
compose section copies ``demo.key`` out of the container: one ``git add .`` would publish them.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from rlbridge.demo.cli import DEMO_KEY

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"


def test_the_docs_still_write_these_names() -> None:
    """If a doc changed where it writes a key, the ignored names below must follow."""
    assert DEMO_KEY == "rlbridge-demo.key"
    assert "rlbridge-demo.key" in (DOCS / "getting-started.md").read_text()
    assert "rlbridge tls init tls/" in (DOCS / "security.md").read_text()
    assert "bridge:/keys/demo.key ." in (DOCS / "getting-started.md").read_text()


@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(),
                    reason="not a git checkout")
@pytest.mark.parametrize("path", ["rlbridge-demo.key", "tls/server.key", "tls/server.crt",
                                  "demo.key", "out/rlbridge-demo.key"])
def test_git_ignores_the_keys_the_docs_make(path: str) -> None:
    result = subprocess.run(["git", "check-ignore", "--no-index", "-q", path], cwd=ROOT,
                            capture_output=True, text=True, timeout=30, check=False)
    assert result.returncode == 0, f"{path} is not ignored by .gitignore: {result.stderr}"


@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(),
                    reason="not a git checkout")
def test_no_key_is_committed() -> None:
    tracked = subprocess.run(["git", "ls-files", "*.key", "**/*.key"], cwd=ROOT,
                             capture_output=True, text=True, timeout=30, check=True)
    assert tracked.stdout == ""
