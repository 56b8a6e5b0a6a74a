"""``rlbridge serve`` as a user starts it (the command beside this interpreter), on a free port.

For the snippet runner: :class:`LiveServer` starts the real command with ``--port 0``, reads the
port from the line it logs when it listens, and stops it with SIGINT (Ctrl-C) on exit, which
must end it with status 0.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType

SERVING = re.compile(r"rlbridge listening on [^ ]+ port (\d+) ")
START_TIMEOUT = 60.0


def rlbridge_command() -> str:
    """The ``rlbridge`` script installed beside the interpreter that runs the tests."""
    found = shutil.which("rlbridge", path=str(Path(sys.executable).parent))
    if found is None:
        raise RuntimeError(f"no rlbridge command beside {sys.executable}")
    return found


class LiveServer:
    """``rlbridge --log-level info serve ARGS --port 0``; ``port`` once it listens."""

    def __init__(self, args: Sequence[str], *, env: Mapping[str, str] | None = None,
                 cwd: Path | None = None) -> None:
        self.command = [rlbridge_command(), "--log-level", "info", "serve", *args,
                        "--port", "0"]
        self.proc = subprocess.Popen(
            self.command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE, text=True, cwd=cwd,
            env={**(env if env is not None else os.environ), "PYTHONUNBUFFERED": "1"})
        self.lines: list[str] = []
        self.port = 0
        self._ready = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        if not self._ready.wait(START_TIMEOUT) or not self.port:
            self.stop()
            raise RuntimeError(f"{' '.join(self.command)} did not start:\n{self.log}")

    @property
    def log(self) -> str:
        return "".join(self.lines)

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.lines.append(line)
            match = SERVING.search(line)
            if match and not self.port:
                self.port = int(match.group(1))
                self._ready.set()
        self._ready.set()  # it ended without listening

    def stop(self) -> int:
        """Ctrl-C, as a user stops it; its exit status (killed after a generous wait)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(START_TIMEOUT)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10.0)
        self._reader.join(10.0)  # it reads to the end of the pipe, then the pipe is closed
        if self.proc.stderr is not None and not self._reader.is_alive():
            self.proc.stderr.close()
        return self.proc.returncode

    def __enter__(self) -> LiveServer:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()
