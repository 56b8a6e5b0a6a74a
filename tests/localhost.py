"""What the tests that start ``rlbridge`` processes on this machine share: the command, a port.

A plain module (``from localhost import ...``), not a fixture, so module-scoped set-ups can use
it too; ``conftest.py`` offers the same through fixtures.
"""

from __future__ import annotations

import random
import shutil
import socket
import sys
from pathlib import Path


def rlbridge_command(python: str = sys.executable) -> list[str]:
    """The installed ``rlbridge`` console script next to ``python`` (this one), else ``-m``."""
    script = shutil.which("rlbridge", path=str(Path(python).parent))
    return [script] if script else [python, "-m", "rlbridge.cli"]


def _ephemeral_range() -> tuple[int, int]:
    try:
        low, high = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
        return int(low), int(high)
    except (OSError, ValueError):
        return 32768, 60999


def free_port() -> int:
    """A port that is free for both TCP and UDP on loopback right now.

    Drawn at random from below the kernel's ephemeral range, never from it: a port the kernel
    hands out for ``bind(0)`` is free until the test's server binds it, and in between any
    client socket on the machine (another test, a parallel matrix leg) may be given it as its
    own local port; CI once lost a run to exactly that.
    """
    low, _high = _ephemeral_range()
    first, last = (20000, low - 1) if low > 21000 else (low // 2, low - 1)
    chooser = random.Random()
    for _ in range(200):
        port = chooser.randint(first, last)
        try:
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as t:
                t.bind(("127.0.0.1", port))
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as u:
                    u.bind(("127.0.0.1", port))
        except OSError:
            continue
        return port
    raise RuntimeError(f"no port free for both TCP and UDP in {first}-{last}")
