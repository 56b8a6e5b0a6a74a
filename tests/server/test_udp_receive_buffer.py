"""The UDP receive buffer: asked for by the server (a setting) and the SDK, granted, reported.

Mechanism only: what the kernel granted, not how many datagrams a buffer saves on a loaded
machine (docs/load.md measures that). Linux caps ``SO_RCVBUF`` at ``net.core.rmem_max``;
a process with ``CAP_NET_ADMIN`` is granted more through ``SO_RCVBUFFORCE``. Both branches
run for real: the capped one in a child process whose capability bounding set lacks
``CAP_NET_ADMIN`` (``setpriv``), the forced one where this process has the capability.
"""

from __future__ import annotations

import inspect
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
from pydantic import ValidationError
from typer.testing import CliRunner

from rlbridge.cli.commands import app, serve
from rlbridge.server import ServerConfig, ServerThread
from rlbridge.server.config import UDP_RECEIVE_BUFFER
from rlbridge.sockbuf import request_buffer

linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux socket options")
CAP_NET_ADMIN = 12


def rmem_max() -> int:
    return int(Path("/proc/sys/net/core/rmem_max").read_text())


def has_net_admin() -> bool:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("CapEff:"):
            return bool(int(line.split()[1], 16) >> CAP_NET_ADMIN & 1)
    return False


@linux
def test_a_request_under_the_cap_is_granted_as_asked() -> None:
    size = min(rmem_max(), 256 << 10)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        grant = request_buffer(sock, "receive", size)
    assert (grant.asked, grant.got, grant.forced, grant.capped) == (size, size, False, False)
    assert grant.reported == 2 * size  # Linux doubles it for its bookkeeping
    assert "capped" not in grant.describe()


CHILD = """
import json, socket, sys
from rlbridge.sockbuf import request_buffer
with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
    g = request_buffer(sock, "receive", int(sys.argv[1]))
print(json.dumps({"got": g.got, "forced": g.forced, "capped": g.capped, "text": g.describe()}))
"""


@linux
@pytest.mark.skipif(shutil.which("setpriv") is None, reason="needs setpriv (util-linux)")
def test_without_cap_net_admin_the_request_is_capped_and_says_which_sysctl() -> None:
    size = 2 * rmem_max() + 4096
    done = subprocess.run(["setpriv", "--bounding-set=-net_admin", "--inh-caps=-net_admin",
                           sys.executable, "-c", CHILD, str(size)],
                          capture_output=True, text=True, timeout=60, check=False)
    if done.returncode != 0 and "setpriv" in done.stderr:
        pytest.skip(f"setpriv cannot drop the capability here: {done.stderr.strip()}")
    assert done.returncode == 0, done.stderr
    grant = json.loads(done.stdout)
    assert (grant["got"], grant["forced"], grant["capped"]) == (rmem_max(), False, True)
    assert f"sysctl -w net.core.rmem_max={size}" in grant["text"]


@linux
@pytest.mark.skipif(not has_net_admin(), reason="needs CAP_NET_ADMIN")
def test_with_cap_net_admin_the_request_goes_past_the_cap() -> None:
    size = 2 * rmem_max() + 4096
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        grant = request_buffer(sock, "receive", size)
    assert (grant.got, grant.forced, grant.capped) == (size, True, False)
    assert "forced past net.core.rmem_max" in grant.describe()


def test_a_size_that_is_not_positive_is_refused() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock, \
            pytest.raises(ValueError, match="give a positive size"):
        request_buffer(sock, "send", 0)


@linux
def test_the_server_socket_gets_the_configured_buffer(
        make_server: Callable[..., ServerThread]) -> None:
    size = min(rmem_max(), 512 << 10)
    srv = make_server(udp_receive_buffer=size)
    assert srv.server.registry is not None
    transport = srv.server.registry.ctx.udp_transport
    assert transport is not None
    sock = transport.get_extra_info("socket")
    assert sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF) == 2 * size


def test_the_setting_is_validated_and_the_cli_default_is_the_servers() -> None:
    with pytest.raises(ValidationError, match="udp_receive_buffer"):
        ServerConfig(udp_receive_buffer=1024)
    result = CliRunner().invoke(app, ["serve", "--udp-receive-buffer", "1024"])
    assert result.exit_code == 2
    assert "--udp-receive-buffer: Input should be greater than or equal to 65536" in (
        result.output)
    default = inspect.signature(serve).parameters["udp_receive_buffer"].default
    assert default is None  # 32 MiB, quietly
    assert ServerConfig().udp_receive_buffer is None
    assert UDP_RECEIVE_BUFFER == 32 << 20


def _serve_without_net_admin(port: int, *args: str) -> subprocess.Popen[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("RLBRIDGE_PSK", "PYTHONWARNINGS")}
    return subprocess.Popen(
        ["setpriv", "--bounding-set=-net_admin", "--inh-caps=-net_admin", sys.executable, "-m",
         "rlbridge", "serve", "-p", str(port), *args], stderr=subprocess.PIPE, text=True, env=env)


def _first_line(server: subprocess.Popen[str]) -> str:
    assert server.stderr is not None
    first = server.stderr.readline()
    if "setpriv" in first:
        pytest.skip(f"setpriv cannot drop the capability here: {first.strip()}")
    assert "listening" in first
    return first


def _stop(server: subprocess.Popen[str]) -> str:
    server.send_signal(signal.SIGTERM)
    return server.communicate(timeout=60)[1]


needs_setpriv = pytest.mark.skipif(shutil.which("setpriv") is None,
                                   reason="needs setpriv (util-linux)")


@linux
@needs_setpriv
def test_a_capped_explicit_size_is_warned_about_after_the_listening_line(
        free_port: Callable[[], int]) -> None:
    size = 2 * rmem_max() + 4096
    server = _serve_without_net_admin(free_port(), "--udp-receive-buffer", str(size))
    try:
        _first_line(server)
        assert server.stderr is not None
        second = server.stderr.readline()
        assert " WARNING " in second, second
        assert (f"UDP receive buffer: asked {size:,} bytes, got {rmem_max():,}; capped by "
                f"net.core.rmem_max: raise it (sysctl -w net.core.rmem_max={size})") in second
    finally:
        _stop(server)


@linux
@needs_setpriv
@pytest.mark.skipif(rmem_max() >= UDP_RECEIVE_BUFFER, reason="the default is not capped here")
def test_the_default_size_takes_what_it_gets_quietly(free_port: Callable[[], int]) -> None:
    server = _serve_without_net_admin(free_port())
    try:
        _first_line(server)
    finally:
        rest = _stop(server)
    assert "UDP receive buffer" not in rest, rest
