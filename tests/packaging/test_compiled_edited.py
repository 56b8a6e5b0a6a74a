"""An editable checkout edited since its build says so, once, at import (rlbridge/_compiled.py).

The real checkout's sources are never edited here: a copy of the package gets an (empty)
extension file beside every compiled module and a build record whose digests are the real
ones except where a test says a module was edited. ``import rlbridge`` in a fresh interpreter
then makes the real decision on that copy.
"""

from __future__ import annotations

import importlib.machinery
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from rlbridge._compiled import MODULES, PURE_ENV, REBUILD, SOURCES_FILE, digest, source_of

PACKAGE = Path(__file__).resolve().parents[2] / "src" / "rlbridge"
SUFFIX = importlib.machinery.EXTENSION_SUFFIXES[0]
#: Imports the copy and prints the decision and where the package came from.
_IMPORT = "import rlbridge, rlbridge._compiled as c; {more}print(c.STATE); print(rlbridge.__file__)"
#: Two compiled modules too (their .py files, if the decision was right: the fakes would fail).
_MORE = "import rlbridge.csp.ring, rlbridge.wire.codec; "


def _copy(tmp_path: Path, edited: tuple[str, ...]) -> Path:
    """A built-looking copy of the package whose record says ``edited`` changed."""
    src = tmp_path / "src"
    package = src / "rlbridge"
    shutil.copytree(PACKAGE, package,
                    ignore=shutil.ignore_patterns("__pycache__", "*.so", SOURCES_FILE))
    record = {}
    for module in MODULES:
        source = source_of(module, package)
        source.with_name(source.stem + SUFFIX).write_bytes(b"")  # never loaded: not valid
        record[module] = "0" * 64 if module in edited else digest(source)
    (package / SOURCES_FILE).write_text(json.dumps(record))
    return src


def _import(src: Path, more: str = _MORE, **env: str) -> subprocess.CompletedProcess[str]:
    environ = {k: v for k, v in os.environ.items() if k != PURE_ENV}
    environ |= {"PYTHONPATH": str(src)} | env
    proc = subprocess.run([sys.executable, "-c", _IMPORT.format(more=more)],
                          capture_output=True, text=True,
                          timeout=60, env=environ, cwd=src, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.splitlines()[-1] == str(src / "rlbridge" / "__init__.py")  # the copy
    return proc


def test_an_edited_source_logs_one_warning_naming_it_and_the_rebuild(tmp_path: Path) -> None:
    first, later = MODULES[3], MODULES[7]
    proc = _import(_copy(tmp_path, (later, first)))
    assert "changed since they were compiled" in proc.stdout
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr  # once, though several modules were imported
    assert f"{first} (and 1 more) was edited since it was compiled" in lines[0]
    assert f"`{REBUILD}`" in lines[0]


def test_an_unedited_build_and_an_asked_for_pure_run_say_nothing(tmp_path: Path) -> None:
    src = _copy(tmp_path, ())
    clean = _import(src, more="")  # compiled: the fake extensions would be loaded
    assert clean.stdout.startswith("compiled"), clean.stdout
    assert clean.stderr == ""
    asked = _import(_copy(tmp_path / "asked", (MODULES[0],)), **{PURE_ENV: "1"})
    assert f"{PURE_ENV} is set" in asked.stdout
    assert asked.stderr == ""


@pytest.mark.parametrize("count", [1, 3])
def test_the_notice_counts_the_other_edits(count: int, tmp_path: Path) -> None:
    from rlbridge._compiled import edited_notice

    notice = edited_notice(PACKAGE, MODULES[:count])
    assert notice.startswith(f"{MODULES[0]} ")
    assert ("more)" in notice) == (count > 1)
    assert f"`{REBUILD}` in {PACKAGE.parent.parent}" in notice
