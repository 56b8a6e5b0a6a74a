"""Fixtures for the adapter tests: ROS 2 discovery kept on this machine, ROS peer processes.

Every ROS 2 test depends on :func:`ros_env`, which (for the whole session) sets

* ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``: DDS discovery and data stay on the loopback
  interface and shared memory; nothing is sent to other hosts or multicast on the LAN;
* ``ROS_DOMAIN_ID`` derived from the pid (1..100): two test runs on one machine (two developers,
  or CI next to a developer) do not see each other's topics; ``RLBRIDGE_TEST_ROS_DOMAIN_ID``
  picks it instead (scripts/test.sh gives each of its ROS runs its own);

and clears ``ROS_STATIC_PEERS`` so no configured peer is contacted. With
``RLBRIDGE_TEST_REQUIRE_ROS2=1`` (scripts/test.sh) a missing rclpy stops the run instead of
skipping the ROS 2 tests. ``ROS_LOG_DIR`` points into
pytest's temporary directory: rcl opens a log file per context start, which would otherwise pile
up in ``~/.ros/log``. rclpy reads these when a
context is initialised, so they must be set before any adapter or peer process starts; peer
processes inherit them. Topic names are unique per test as well, so even a domain id collision
between two runs cannot mix their results.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import threading
import uuid
from collections import defaultdict
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

PEER_SCRIPT = Path(__file__).with_name("ros2_peer.py")

REQUIRE_ROS2 = os.environ.get("RLBRIDGE_TEST_REQUIRE_ROS2") == "1"


if REQUIRE_ROS2 and importlib.util.find_spec("rclpy") is None:
    # scripts/test.sh installed rclpy: without it the ROS 2 tests would skip, and pass unseen.
    raise pytest.UsageError("RLBRIDGE_TEST_REQUIRE_ROS2=1 but this Python has no rclpy")


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


@pytest.fixture(scope="session")
def ros_env(tmp_path_factory: pytest.TempPathFactory) -> Iterator[int]:
    """Scope ROS 2 discovery to this machine and this run; yields the domain id."""
    pytest.importorskip("rclpy", reason="rclpy is not installed (pip install 'rlbridge-sdk[ros2]')")
    domain_id = int(os.environ.get("RLBRIDGE_TEST_ROS_DOMAIN_ID") or 1 + os.getpid() % 100)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("ROS_LOG_DIR", str(tmp_path_factory.mktemp("ros_log")))
        mp.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        mp.setenv("ROS_DOMAIN_ID", str(domain_id))
        mp.delenv("ROS_STATIC_PEERS", raising=False)
        yield domain_id


@pytest.fixture
def unique_topic() -> Callable[[str], str]:
    """``unique_topic("x")`` -> ``/rlb_<random>_x``, the same name for the same suffix."""
    run = uuid.uuid4().hex[:8]
    return lambda suffix: f"/rlb_{run}_{suffix}"


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


@pytest.fixture(scope="module")
def peer(ros_env: int) -> Iterator[PeerProcess]:
    """One plain rclpy node in another process, shared by a test module."""
    process = PeerProcess()
    try:
        yield process
    finally:
        process.close()
