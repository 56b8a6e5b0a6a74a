#!/usr/bin/env python3
"""Run the README's two SDK examples as a user would, on the Python that runs this script.

What a user on Ubuntu 22.04 (Python 3.10), 24.04 (3.12) or Debian 13 (3.13) does after
``pip install .``: start ``rlbridge serve --udp --nodelay`` (the command installed next
to this interpreter), then run the README's control-code example and its coupling-pattern
example against it. The examples are taken from README.md as printed; only the server address
changes (and the pattern's cycle count, to keep it short).

* The control-code example runs in this process. Its ``while running:`` loop gets a
  ``running`` that stays true until the loop has read a set-point that another client
  published over UDP and that client has received the angle the loop computed from it (or a
  deadline passes: then this script fails). ``control`` halves the set-point.
* The coupling-pattern example runs as a script of its own (its loop process imports it).

Needs only rlbridge and the standard library. scripts/test.sh runs it in a fresh venv per
Python with a plain ``pip install .``; tests/docs/test_readme_sdk.py runs it in the test venv.
Exit status 0 when both examples did what the README says, 1 with the reason otherwise (or,
with ``RLBRIDGE_TEST_REQUIRE_COMPILED=1``, when ``pip install .`` did not compile the value path).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

README = Path(__file__).resolve().parents[1] / "README.md"
ADDRESS = '"192.168.1.10", 7411'
SERVING = re.compile(r"rlbridge listening on [^ ]+ port (\d+) ")
TIMEOUT = 30.0
SETPOINT = 1.0


class ExampleFailed(Exception):
    """An example did not do what the README says it does."""


def python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README.read_text(encoding="utf-8"), re.S)


def the_block(marker: str) -> str:
    found = [b for b in python_blocks() if marker in b]
    if len(found) != 1 or ADDRESS not in found[0]:
        raise ExampleFailed(f"README.md should have one python example with {marker!r} "
                            f"connecting to {ADDRESS}")
    return found[0]


class Serve:
    """``rlbridge serve --udp --nodelay --port 0``, as installed beside this interpreter."""

    def __init__(self) -> None:
        script = shutil.which("rlbridge", path=str(Path(sys.executable).parent))
        if script is None:
            raise ExampleFailed(f"no rlbridge command beside {sys.executable}")
        self.proc = subprocess.Popen(
            [script, "--log-level", "info", "serve", "--udp", "--nodelay", "--port", "0"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
            text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        self.lines: list[str] = []
        self.port: int | None = None
        self._ready = threading.Event()
        threading.Thread(target=self._read, daemon=True).start()
        if not self._ready.wait(TIMEOUT) or self.port is None:
            self.stop()
            raise ExampleFailed("rlbridge serve did not start: " + "".join(self.lines))

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.lines.append(line)
            match = SERVING.search(line)
            if match and self.port is None:
                self.port = int(match.group(1))
                self._ready.set()
        self._ready.set()

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(TIMEOUT)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5.0)


class Running:
    """The example's ``running``: true until the set-point went in and the angle came out."""

    def __init__(self, port: int) -> None:
        from rlbridge import Bridge

        self.targets: list[Any] = []
        self.angles: list[Any] = []
        self.deadline = time.monotonic() + TIMEOUT
        self.vision = Bridge.connect("127.0.0.1", port, name="readme-vision")
        self._setpoint = self.vision.publish("/camera/setpoint", "std_msgs/msg/Float64",
                                             transport="udp")
        self._pan = self.vision.subscribe("/camera/pan", "std_msgs/msg/Float64",
                                          transport="udp", initial=None)

    def control(self, target: float) -> float:
        self.targets.append(target)
        return target / 2

    def __bool__(self) -> bool:
        self._setpoint.write(SETPOINT)  # a UDP datagram may be lost: keep sending
        angle = self._pan.read()
        if angle is not None:
            self.angles.append(angle)
        if SETPOINT in self.targets and SETPOINT / 2 in self.angles:
            return False
        if time.monotonic() > self.deadline:
            raise ExampleFailed(f"after {TIMEOUT} s the loop read {self.targets[-3:]} and "
                                f"the vision client got {self.angles[-3:]}")
        time.sleep(0.001)  # the README's 1 kHz loop
        return True


def control_code_example(port: int) -> str:
    code = the_block("while running:").replace(ADDRESS, f'"127.0.0.1", {port}')
    running = Running(port)
    try:
        exec(compile(code, "README.md (control code)", "exec"),
             {"__name__": "__readme__", "running": running, "control": running.control})
    finally:
        running.vision.close()
    return (f"control code: read set-point {SETPOINT} over UDP, published angle "
            f"{SETPOINT / 2} ({len(running.targets)} cycles)")


def pattern_example(port: int) -> str:
    from rlbridge import ShmLink

    if not ShmLink.supported():
        return "coupling pattern: skipped (its default layout needs x86)"
    code = (the_block("receive_nonblocking(").replace(ADDRESS, f'"127.0.0.1", {port}')
            .replace("cycles=5000", "cycles=300"))
    with tempfile.TemporaryDirectory(prefix="rlbridge-readme-") as tmp:
        script = Path(tmp) / "tracker.py"
        script.write_text(code, encoding="utf-8")
        proc = subprocess.run([sys.executable, str(script)], cwd=tmp, capture_output=True,
                              text=True, timeout=120, check=False)
    if proc.returncode != 0:
        raise ExampleFailed(f"the coupling-pattern example failed:\n{proc.stderr[-2000:]}")
    p99, policy, *_ = proc.stdout.split()
    return f"coupling pattern: 300 cycles in its own process, p99 {p99} ns, {policy}"


def main() -> int:
    from rlbridge._compiled import STATE

    version = ".".join(map(str, sys.version_info[:3]))
    if os.environ.get("RLBRIDGE_TEST_REQUIRE_COMPILED") == "1" and not STATE.startswith("compil"):
        print(f"readme_example: FAILED on Python {version}: `pip install .` did not compile "
              f"the value path (setup.py): {STATE}", file=sys.stderr)
        return 1
    server = None
    try:
        server = Serve()
        assert server.port is not None
        done = [control_code_example(server.port), pattern_example(server.port)]
    except (ExampleFailed, OSError, subprocess.SubprocessError) as exc:
        print(f"readme_example: FAILED on Python {version}: {exc}", file=sys.stderr)
        return 1
    finally:
        if server is not None:
            server.stop()
    print(f"readme_example: README examples ran on Python {version} (value path: {STATE}): "
          + "; ".join(done))
    return 0


if __name__ == "__main__":
    sys.exit(main())
