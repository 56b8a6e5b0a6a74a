"""``rlbridge demo --plot`` writes where the user asked; the default stays out of git."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from rlbridge.demo.plot import DEFAULT_NAME, resolve_path

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(("given", "expected"), [
    ("out/", f"out/{DEFAULT_NAME}"),        # a directory that does not exist yet
    ("out", f"out/{DEFAULT_NAME}"),         # no extension: a directory too
    ("run.png", "run.png"),
    ("deep/er/run.png", "deep/er/run.png"),
])
def test_plot_path_as_typed(given: str, expected: str, tmp_path: Path,
                            monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    assert resolve_path(given) == Path(expected)


def test_an_existing_directory_gets_the_default_name(tmp_path: Path) -> None:
    assert resolve_path(tmp_path) == tmp_path / DEFAULT_NAME


@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(),
                    reason="needs git and a checkout")
@pytest.mark.parametrize("path", [DEFAULT_NAME, f"examples/pan_tilt/{DEFAULT_NAME}",
                                  "out/pan_tilt.png", "out/report.json"])
def test_what_the_demo_writes_by_default_is_ignored_by_git(path: str) -> None:
    result = subprocess.run(["git", "check-ignore", "-q", path], cwd=ROOT, check=False,
                            timeout=30)
    assert result.returncode == 0, f"{path} would show up as untracked"
