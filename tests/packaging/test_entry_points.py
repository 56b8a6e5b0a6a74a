"""What a user types first works: ``python -m rlbridge``, ``--version``, ``help(rlbridge)``,
and the README's commands all run in the one venv it creates."""

from __future__ import annotations

import pydoc
import re
import shutil
import subprocess
import sys
from pathlib import Path

import rlbridge
from rlbridge._compiled import STATE
from rlbridge.wire.aead import STATE as AEAD

ROOT = Path(__file__).resolve().parents[2]


def test_python_dash_m_rlbridge_is_the_command() -> None:
    proc = subprocess.run([sys.executable, "-m", "rlbridge", "--version"], capture_output=True,
                          text=True, timeout=60, check=False)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines()[:3] == [f"rlbridge {rlbridge.__version__}",
                                            f"value path: {STATE}",
                                            f"sealing (ChaCha20-Poly1305): {AEAD}"]
    helped = subprocess.run([sys.executable, "-m", "rlbridge", "--help"], capture_output=True,
                            text=True, timeout=60, check=False)
    assert helped.returncode == 0
    assert "serve" in helped.stdout
    assert "topic" in helped.stdout


def test_the_console_script_prints_its_version() -> None:
    exe = shutil.which("rlbridge", path=str(Path(sys.executable).parent))
    assert exe is not None
    proc = subprocess.run([exe, "--version"], capture_output=True, text=True, timeout=60,
                          check=False)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines()[:3] == [f"rlbridge {rlbridge.__version__}",
                                            f"value path: {STATE}",
                                            f"sealing (ChaCha20-Poly1305): {AEAD}"]


def test_help_of_the_package_names_bridge() -> None:
    text = pydoc.render_doc(rlbridge, renderer=pydoc.plaintext)
    assert "Bridge" in text.split("PACKAGE CONTENTS")[0]  # in the description, not only data
    assert "Bridge" in dir(rlbridge)
    assert rlbridge.Bridge.__name__ == "Bridge"


def _sh_lines(path: Path) -> list[str]:
    blocks = re.findall(r"```sh\n(.*?)```", path.read_text(), re.S)
    return [line for block in blocks for line in block.splitlines()]


def test_readme_and_getting_started_activate_the_venv_once_then_use_bare_commands() -> None:
    for doc in (ROOT / "README.md", ROOT / "docs" / "getting-started.md"):
        lines = _sh_lines(doc)
        assert any(". .venv/bin/activate" in line for line in lines), doc
        mixed = [line for line in lines if ".venv/bin/" in line and "activate" not in line]
        assert mixed == [], f"{doc.name}: commands that bypass the activated venv: {mixed}"
