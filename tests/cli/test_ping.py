"""``rlbridge ping``: exit 0 when a bridge server answers, 1 when not (real processes)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Callable
from typing import Any

import pytest

PROC_WAIT = 30.0


@pytest.mark.parametrize("transport", ["tcp", "udp"])
def test_ping_a_running_server_exits_0(cli: Any, shared_cli_server: int, transport: str) -> None:
    result = cli.run("ping", "-p", str(shared_cli_server), "-t", transport)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(
        f"rlbridge server at 127.0.0.1:{shared_cli_server} ({transport.upper()}) session ")


def test_ping_nothing_exits_1(cli: Any, free_port: Callable[[], int]) -> None:
    port = free_port()
    result = cli.run("ping", "-p", str(port))
    assert result.returncode == 1
    assert result.stderr == (f"rlbridge: error: cannot reach 127.0.0.1:{port} (TCP): "
                             "Connection refused\n")
    silent = cli.run("ping", "-p", str(port), "-t", "udp", "--timeout", "0.5")
    assert silent.returncode == 1
    assert "(UDP)" in silent.stderr


def test_ping_another_service_exits_1(cli: Any) -> None:
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()

        def answer_like_http() -> None:
            conn, _ = server.accept()
            with conn:
                conn.recv(100)
                conn.sendall(b"HTTP/1.0 400 Bad Request\r\n\r\n")

        thread = threading.Thread(target=answer_like_http, daemon=True)
        thread.start()
        result = cli.run("ping", "-p", str(server.getsockname()[1]))
        thread.join(PROC_WAIT)
    assert result.returncode == 1
    assert "not in the rlbridge protocol" in result.stderr


def test_ping_a_keyed_server_without_a_key_is_healthy_and_quiet(
        free_port: Callable[[], int]) -> None:
    """The key challenge (a refusal, for a keyless hello) proves the server is up; the server
    does not warn about health probes."""
    port = free_port()
    env = {k: v for k, v in os.environ.items() if k not in ("RLBRIDGE_PSK", "PYTHONWARNINGS")}
    server = subprocess.Popen([sys.executable, "-m", "rlbridge", "serve", "-p", str(port)],
                              stderr=subprocess.PIPE, text=True,
                              env={**env, "RLBRIDGE_PSK": "ab" * 32})
    try:
        assert server.stderr is not None
        assert "listening" in server.stderr.readline()
        for _ in range(3):
            probe = subprocess.run([sys.executable, "-m", "rlbridge", "ping", "-p", str(port)],
                                   capture_output=True, text=True, env=env, timeout=PROC_WAIT,
                                   check=False)
            assert probe.returncode == 0, probe.stderr
            assert "requires a pre-shared key" in probe.stdout
    finally:
        server.send_signal(signal.SIGTERM)
        _out, err = server.communicate(timeout=PROC_WAIT)
    assert "WARNING" not in err, err
    assert "rlbridge-ping" not in err
