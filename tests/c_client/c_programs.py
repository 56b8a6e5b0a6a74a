"""Example programs of the C client (clients/c) run as processes, their output read by lines."""

from __future__ import annotations

import contextlib
import queue
import subprocess
import threading
import time

from waiting import wait_until


class CProcess:
    """An example program running, its stdout and stderr read line by line by two threads."""

    def __init__(self, *argv: str) -> None:
        self.argv = argv
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True)
        self.out: list[str] = []
        self.err: list[str] = []
        self._lines: queue.Queue[tuple[str, str]] = queue.Queue()
        self._pumps = [threading.Thread(target=self._pump, args=(stream, into), daemon=True)
                       for stream, into in ((self.proc.stdout, "out"), (self.proc.stderr, "err"))]
        for pump in self._pumps:
            pump.start()

    def _pump(self, stream: object, into: str) -> None:
        for line in iter(stream.readline, ""):  # type: ignore[attr-defined]
            getattr(self, into).append(line.rstrip("\n"))
            self._lines.put((into, line))

    def wait_err(self, text: str, count: int = 1, timeout: float = 30.0) -> None:
        """Until ``count`` stderr lines contain ``text`` (the process tells its state there)."""
        def said() -> bool:
            if sum(text in line for line in self.err) >= count:
                return True
            if self.proc.poll() is not None and self._lines.empty():
                time.sleep(0.05)  # the pumps may still hold the last lines
                if sum(text in line for line in self.err) >= count:
                    return True
                raise AssertionError(f"{self.argv[0]} exited with {self.proc.returncode} "
                                     f"before saying {text!r}; stderr: {self.err}")
            self._next_line()
            return False

        wait_until(said, lambda: f"{self.argv[0]} to say {text!r} ({count}x); stderr: "
                                 f"{self.err}, exit: {self.proc.poll()}",
                   timeout=timeout, interval=0)

    def wait_out(self, lines: int, timeout: float = 30.0) -> None:
        def printed() -> bool:
            if len(self.out) >= lines:
                return True
            self._next_line()
            return False

        wait_until(printed, lambda: f"{lines} lines on stdout ({len(self.out)} came); "
                                    f"stderr: {self.err}", timeout=timeout, interval=0)

    def _next_line(self) -> None:
        """Block until a pump read another line (0.1 s at most): the waits' pause."""
        with contextlib.suppress(queue.Empty):
            self._lines.get(timeout=0.1)

    def finish(self, timeout: float = 60.0) -> int:
        """The exit code, once the process has ended and both pumps have read everything."""
        code = self.proc.wait(timeout=timeout)
        for pump in self._pumps:
            pump.join(timeout=10)
        return code

    def close(self) -> None:
        """Kill it if it still runs; close its pipes."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.finish(timeout=10)
        for stream in (self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()

    def values(self) -> list[float]:
        return [float(line) for line in self.out]
