"""What the tests that start ``rlbridge`` processes on this machine share: the command, a port.

A plain module (``from localhost import ...``), not a fixture, so module-scoped set-ups can use
it too; ``conftest.py`` offers the same through fixtures.
"""

from __future__ import annotations

import shutil
import socket
import sys
from pathlib import Path


def rlbridge_command(python: str = sys.executable) -> list[str]:
    """The installed ``rlbridge`` console script next to ``python`` (this one), else ``-m``."""
    script = shutil.which("rlbridge", path=str(Path(python).parent))
    return [script] if script else [python, "-m", "rlbridge.cli"]


def free_port() -> int:
    """A port that is free for both TCP and UDP on loopback right now."""
    for _ in range(50):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as t:
            t.bind(("127.0.0.1", 0))
            port: int = t.getsockname()[1]
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as u:
                try:
                    u.bind(("127.0.0.1", port))
                except OSError:
                    continue
        return port
    raise RuntimeError("no free port found")
