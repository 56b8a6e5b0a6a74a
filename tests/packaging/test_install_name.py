"""The name pip installs is ours, every install hint names it, and one command builds a wheel.

``rlbridge`` on PyPI is an unrelated project: a hint saying ``pip install rlbridge`` installs
someone else's code. The distribution is ``rlbridge-sdk``; the import package and the command
stay ``rlbridge``.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import zipfile
from pathlib import Path

from rlbridge._version import DISTRIBUTION, __version__, pip_install

ROOT = Path(__file__).resolve().parents[2]
#: "pip install rlbridge" or "pip install 'rlbridge[x]'" (any quoting), not "rlbridge-sdk".
WRONG_NAME = re.compile(r"pip install\s+['\"]?rlbridge(?![-\w])")


def _project_table() -> str:
    text = (ROOT / "pyproject.toml").read_text()
    return text.split("[project]", 1)[1].split("\n[", 1)[0]


def test_the_distribution_name_is_the_one_the_code_names() -> None:
    name = re.search(r'^name = "([^"]+)"', _project_table(), re.M)
    assert name is not None
    assert name.group(1) == DISTRIBUTION != "rlbridge"
    assert 'rlbridge = "rlbridge.cli:main"' in (ROOT / "pyproject.toml").read_text()
    # Not on PyPI: the hint names where this copy came from (here the editable checkout).
    assert pip_install("ros2") == f"pip install -e '{ROOT}[ros2]'"


def test_no_text_tells_users_to_install_the_wrong_project() -> None:
    files = [ROOT / "README.md", ROOT / "Dockerfile",
             *(p for d in ("src", "docs", "examples", "scripts", "tests")
               for p in (ROOT / d).rglob("*") if p.suffix in {".py", ".md", ".sh", ".txt"}
               and p.name != "test_install_name.py")]
    offenders = [f"{p.relative_to(ROOT)}:{n}: {line.strip()}"
                 for p in files for n, line in enumerate(p.read_text().splitlines(), 1)
                 if WRONG_NAME.search(line) and "rlbridge-sdk" not in line]  # else: a warning
    assert offenders == []


def test_license_file_matches_pyproject() -> None:
    assert 'license = { text = "MIT" }' in (ROOT / "pyproject.toml").read_text()
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")


def test_one_command_builds_a_wheel_for_a_control_board(tmp_path: Path) -> None:
    """The README's command, for real: RLBRIDGE_PURE_PYTHON=1, a wheel for any machine."""
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(ROOT), "-w", str(tmp_path), "--no-deps",
         "-q"],
        capture_output=True, text=True, timeout=120, check=False,
        env=os.environ | {"RLBRIDGE_PURE_PYTHON": "1"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    wheel = tmp_path / f"rlbridge_sdk-{__version__}-py3-none-any.whl"
    assert wheel.exists(), list(tmp_path.iterdir())
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        info = f"rlbridge_sdk-{__version__}.dist-info"
        assert "rlbridge/__init__.py" in names
        assert "rlbridge/__main__.py" in names
        assert "rlbridge/py.typed" in names
        assert not [n for n in names if n.endswith(".so")]
        assert any(n.startswith(info) and n.endswith("LICENSE") for n in names)
        assert "rlbridge = rlbridge.cli:main" in z.read(f"{info}/entry_points.txt").decode()
        assert "Name: rlbridge-sdk" in z.read(f"{info}/METADATA").decode()
