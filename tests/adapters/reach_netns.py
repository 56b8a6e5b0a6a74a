"""Processes in a private network namespace for the ROS 2 reach tests (services, actions, ...).

Every ROS process of these tests (the bridge server, rclpy peers, CLI tools) runs in a network
namespace of its own (``h16a-<pid>-<token>``, only a loopback interface), so DDS discovery
cannot reach, or be reached by, any other test run on the machine; the SDK client joins the
namespace for its sockets only (:func:`rlbridge.netem.netns.call_in_namespace`).
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
import shutil
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path

import pytest

from rlbridge.client.bridge import Bridge
from rlbridge.netem import netns

SERVING = re.compile(r"rlbridge listening on [^ ]+ port (\d+) ")
TIMEOUT = 30.0


def require_netns() -> None:
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("needs root and iproute2 for a private network namespace")


def new_namespace(role: str) -> str:
    name = f"h16a-{os.getpid()}-{secrets.token_hex(2)}-{role}"
    netns.create_namespace(name)
    return name


def remove_namespace(name: str) -> None:
    netns.terminate_pids(netns.namespace_pids(name))
    netns.delete_namespace(name)


def ros_env(log_dir: Path, domain: int = 63) -> dict[str, str]:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "ROS_DOMAIN_ID": str(domain),
           "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_LOG_DIR": str(log_dir)}
    env.pop("ROS_STATIC_PEERS", None)
    env.pop("PYTHONWARNINGS", None)
    return env


def rlbridge_argv() -> list[str]:
    script = shutil.which("rlbridge", path=str(Path(sys.executable).parent))
    return [script] if script else [sys.executable, "-m", "rlbridge.cli"]


def in_namespace(name: str, argv: Sequence[str]) -> list[str]:
    return ["ip", "netns", "exec", name, *argv]


class LoggedProcess:
    """A process whose stdout/stderr lines are collected by a thread (never blocks it)."""

    def __init__(self, argv: Sequence[str], env: dict[str, str], *, stdin: bool = False,
                 watch: re.Pattern[str] | None = None) -> None:
        self.proc = subprocess.Popen(list(argv), env=env, text=True,
                                     stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        self.lines: list[str] = []
        self.match: re.Match[str] | None = None
        self._watch = watch
        self._ready = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line)
            if self.match is None and self._watch is not None:
                self.match = self._watch.search(line)
                if self.match:
                    self._ready.set()
        self._ready.set()

    def wait_ready(self) -> re.Match[str]:
        if not self._ready.wait(TIMEOUT) or self.match is None:
            raise AssertionError(f"{self.proc.args} did not start: {''.join(self.lines)}")
        return self.match

    def wait(self, timeout: float) -> int:
        """Its exit status; if it is still running after ``timeout`` s, stop it and fail with
        its output (what it printed says where it hung)."""
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.stop()
            raise AssertionError(f"{self.proc.args} still ran after {timeout:g} s; its output:\n"
                                 f"{self.log}") from None

    def stop(self) -> int:
        if self.proc.poll() is None:
            if self.proc.stdin is not None:
                with contextlib.suppress(BrokenPipeError):
                    self.proc.stdin.close()
            else:
                self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(TIMEOUT)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5.0)
        self._reader.join(5.0)
        for pipe in (self.proc.stdin, self.proc.stdout):
            if pipe is not None and not pipe.closed:
                with contextlib.suppress(BrokenPipeError):
                    pipe.close()
        return self.proc.returncode

    @property
    def log(self) -> str:
        return "".join(self.lines)


def start_server(namespace: str, env: dict[str, str], node_name: str,
                 *options: str) -> tuple[LoggedProcess, int]:
    # A 5 s watchdog unless the options set one: under load the SDK session (or its
    # namespace's processes) can be starved past the default 600 ms, and no reach test is
    # about the watchdog.
    watchdog = () if "--timeout-ms" in options else ("--timeout-ms", "5000")
    server = LoggedProcess(in_namespace(namespace, [
        *rlbridge_argv(), "--log-level", "info", "serve", "--port", "0", "--adapter", "ros2",
        "--node-name", node_name, *watchdog, *options]), env, watch=SERVING)
    return server, int(server.wait_ready().group(1))


def run_cli(namespace: str, env: dict[str, str], *args: str,
            timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(in_namespace(namespace, [*rlbridge_argv(), *args]), env=env,
                          capture_output=True, text=True, timeout=timeout, check=False)


PEER = Path(__file__).with_name("ros2_reach_peer.py")


class World:
    """One namespace with a bridge server (and maybe a peer node) in it; see :func:`world`."""

    def __init__(self, namespace: str, env: dict[str, str], port: int) -> None:
        self.namespace, self.env, self.port = namespace, env, port

    def peer(self, *args: str, watch: str | None = None) -> LoggedProcess:
        """``ros2_reach_peer.py ARGS`` in the namespace (stdin open: closing it ends it)."""
        return LoggedProcess(in_namespace(self.namespace, [sys.executable, str(PEER), *args]),
                             self.env, stdin=True,
                             watch=None if watch is None else re.compile(watch))

    def connect(self, name: str) -> Bridge:
        """An SDK session with the namespace's server (its sockets live in the namespace)."""
        return netns.call_in_namespace(self.namespace, lambda: Bridge.connect(
            "127.0.0.1", self.port, name=name, timeout=20.0, reconnect=False))


@contextlib.contextmanager
def world(role: str, log_dir: Path, *, serve_peer: bool = False,
          server_options: Sequence[str] = ()) -> Iterator[World]:
    """A namespace, ``rlbridge serve --adapter ros2 SERVER_OPTIONS`` in it (after the peer
    node in ``serve`` mode, if asked); everything stopped and the namespace removed afterwards."""
    require_netns()
    namespace = new_namespace(role)
    env = ros_env(log_dir)
    processes: list[LoggedProcess] = []
    try:
        if serve_peer:
            peer = World(namespace, env, 0).peer("serve", watch=r"^ready")
            processes.append(peer)
            peer.wait_ready()
        server, port = start_server(namespace, env, f"h16a_{role}_bridge", *server_options)
        processes.append(server)
        yield World(namespace, env, port)
    finally:
        for proc in reversed(processes):
            proc.stop()
        remove_namespace(namespace)
    log = processes[-1].log if processes else ""
    assert "Traceback" not in log, log
