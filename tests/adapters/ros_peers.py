"""ROS 2 peer processes for the adapter tests, and the environment of child interpreters.

Tests import these by this module's name, never from ``conftest``: several test directories
have a ``conftest.py``, and which one ``import conftest`` finds depends on the order pytest
collected them (``tests/csp`` before ``tests/adapters`` broke collection).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

PEER_SCRIPT = Path(__file__).with_name("ros2_peer.py")


def env_for(python: str) -> dict[str, str]:
    """The environment for a child process on ``python``: this one's, less its ROS wheel paths.

    The ROS wheels re-execute Python at start-up with ``LD_LIBRARY_PATH`` pointing into their
    venv and ``_ROS_WHEELS_BOOTSTRAP_COMPLETE=1``; a child inherits both. On the same venv that
    is what it needs; on another venv (another ROS release) it would skip its own set-up and
    load this venv's libraries, or none ("libfastrtps.so.2.14: cannot open shared object
    file"). So for another interpreter both go, and its bootstrap runs as in a fresh shell.
    """
    env = dict(os.environ)
    if Path(python).resolve() == Path(sys.executable).resolve():
        return env
    env.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)
    ours = os.path.realpath(sys.prefix) + os.sep
    kept = [p for p in env.pop("LD_LIBRARY_PATH", "").split(os.pathsep)
            if p and not os.path.realpath(p).startswith(ours)]
    if kept:
        env["LD_LIBRARY_PATH"] = os.pathsep.join(kept)
    return env


class PeerError(Exception):
    """The peer process answered a request with an error."""


class PeerProcess:
    """A ``ros2_peer.py serve`` process: a plain rclpy node driven over JSON lines.

    Replies and received messages come back on its stdout, read by a thread here; requests and
    waits are bounded, so a hung peer fails a test instead of hanging it. ``python`` runs it on
    another interpreter, whose rclpy may be another ROS 2 release (test_ros2_cross_release.py).
    """

    def __init__(self, python: str = sys.executable) -> None:
        self.proc = subprocess.Popen(
            [python, str(PEER_SCRIPT), "serve"],
            env=env_for(python),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            bufsize=1,
        )
        self._cond = threading.Condition()
        self._replies: dict[int, dict[str, Any]] = {}
        self._messages: defaultdict[int, list[Any]] = defaultdict(list)
        self._next_id = 0
        self._eof = False
        self._reader = threading.Thread(target=self._read, name="ros2-peer-reader", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            message = json.loads(line)
            with self._cond:
                if "id" in message:
                    self._replies[message["id"]] = message
                else:
                    self._messages[message["sub"]].append(message["value"])
                self._cond.notify_all()
        with self._cond:
            self._eof = True
            self._cond.notify_all()

    def call(self, op: str, timeout: float = 20.0, **fields: Any) -> Any:
        with self._cond:
            self._next_id += 1
            request_id = self._next_id
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps({"id": request_id, "op": op, **fields}) + "\n")
        self.proc.stdin.flush()
        with self._cond:
            self._cond.wait_for(lambda: request_id in self._replies or self._eof, timeout)
            reply = self._replies.pop(request_id, None)
        if reply is None:
            raise AssertionError(f"peer did not answer {op!r} within {timeout} s")
        if "error" in reply:
            raise PeerError(reply["error"])
        return reply["ok"]

    def messages(self, handle: int) -> list[Any]:
        with self._cond:
            return list(self._messages[handle])

    def wait_messages(
        self, handle: int, predicate: Callable[[list[Any]], bool], timeout: float
    ) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: predicate(self._messages[handle]), timeout)

    def close(self) -> None:
        if self.proc.poll() is None:
            assert self.proc.stdin is not None
            try:
                self.proc.stdin.write(json.dumps({"op": "quit"}) + "\n")
                self.proc.stdin.close()
                self.proc.wait(10.0)
            except (BrokenPipeError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait(5.0)
        self._reader.join(5.0)
        if self.proc.stdout is not None:
            self.proc.stdout.close()
