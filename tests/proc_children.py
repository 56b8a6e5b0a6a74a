"""This process's children, read from /proc: what the lifetime tests check is gone.

Shared by the tests that start processes (benchmarks, the loop process of a coupling) and
assert that none outlives its owner. No dependency beyond the kernel's /proc.
"""

from __future__ import annotations

import os
from pathlib import Path


def children(*, zombies: bool = False) -> set[int]:
    """PIDs whose parent is this process (zombies only when asked: they are already gone)."""
    found = set()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        if int(fields[1]) == os.getpid() and (zombies or fields[0] != "Z"):
            found.add(int(entry.name))
    return found


def cmdline(pid: int) -> str:
    """The process's command line with spaces between arguments ('' once it has ended)."""
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""
