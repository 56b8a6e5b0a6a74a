"""Benchmark reports: markdown tables, the header that dates a run, and sections of docs.

Every report starts with the command and the machine (cores, CPU, versions, load average), so
a figure in ``docs/`` says where it came from; each ``rlbridge bench`` command then owns one
marked section of its markdown file.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import math
import os
import platform
import shlex
import sys
from collections.abc import Sequence
from datetime import datetime, timezone
from pathlib import Path

from rlbridge._compiled import STATE


def fmt(value: float, digits: int = 0) -> str:
    """Thousands separators, ``-`` for NaN."""
    return "-" if math.isnan(value) else f"{value:,.{digits}f}"


def _version(dist: str) -> str:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return "not installed"


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``), for the report header."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown"


def machine_info() -> dict[str, str]:
    """What a reader needs to judge the figures: cores, CPU, versions, whether rlbridge's value
    path is compiled, and the load average as the report is written: the run's end, the 5- and
    15-minute figures covering the run (a report that needs the load before the run measures
    it itself, as soak's does)."""
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    return {
        "nproc": str(len(os.sched_getaffinity(0))),
        "cpu": cpu_model(),
        "kernel": platform.release(),
        "python": platform.python_version(),
        "uvloop": _version("uvloop"),
        "msgspec": _version("msgspec"),
        "value path": STATE,  # compiled by mypyc, or the Python files (rlbridge/_compiled.py)
        "pyzmq": _version("pyzmq"),
        "eclipse-zenoh": _version("eclipse-zenoh"),
        "load average (1, 5, 15 min) at the end": load,
    }


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A markdown table; every column but the first right-aligned (they hold figures)."""
    out = ["| " + " | ".join(headers) + " |",
           "|" + "|".join("---:" if i else "---" for i in range(len(headers))) + "|"]
    out += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(out)


def report_header(title: str, command: Sequence[str]) -> str:
    """A report's title, the command that produced it, the date and the machine."""
    info = machine_info()
    when = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = [f"### {title}", "", f"Command: `{shlex.join(command)}`  ", f"Date: {when}  "]
    lines += [f"{k}: {v}  " for k, v in info.items()]
    return "\n".join(lines).rstrip() + "\n"


def write_section(path: Path, name: str, body: str) -> None:
    """Replace the ``name`` section of a markdown file (between markers), or append it.

    Each ``rlbridge bench`` command owns one section, so they can share ``docs/benchmarks.md``
    with hand-written text around them.
    """
    begin, end = f"<!-- bench:{name} begin -->", f"<!-- bench:{name} end -->"
    block = f"{begin}\n{body.rstrip()}\n{end}"
    text = path.read_text() if path.exists() else ""
    if begin in text and end in text:
        head, rest = text.split(begin, 1)
        text = head + block + rest.split(end, 1)[1]
    else:
        text = (text.rstrip() + "\n\n" if text.strip() else "") + block + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def progress(message: str) -> None:
    """One line per run on stderr: the benchmarks take minutes, show that they move."""
    print(f"  {message}", file=sys.stderr, flush=True)
