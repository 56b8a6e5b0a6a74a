"""Secure by default: a server others can reach needs TLS or a key, or says --insecure aloud.

And the key is written the same way everywhere (hex): ``psk=``, the key file (``psk_file=`` on
the client reads the server's format) and ``$RLBRIDGE_PSK``; a key in the wrong format is
refused on the side that holds it, naming where it came from.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from rlbridge import Psk
from rlbridge.csp.auth import AuthRefused, resolve_key
from rlbridge.csp.bridge import Bridge
from rlbridge.server import ServerError, ServerThread
from rlbridge.server.config import is_loopback

KEY = bytes(range(32))
F64 = "std_msgs/msg/Float64"


@pytest.mark.parametrize(("host", "loopback"), [
    ("127.0.0.1", True), ("127.0.0.2", True), ("::1", True), ("localhost", True),
    ("0.0.0.0", False), ("::", False), ("192.168.1.10", False), ("robot.local", False),
])
def test_what_counts_as_loopback(host: str, loopback: bool) -> None:
    assert is_loopback(host) is loopback


def test_serve_beyond_loopback_without_protection_refuses_in_one_line(
        cli: Any, free_port: Callable[[], int]) -> None:
    result = cli.run("serve", "--host", "0.0.0.0", "--port", str(free_port()))
    assert result.returncode == 1
    assert result.stderr.count("\n") == 1
    line = result.stderr
    assert "refusing to listen on 0.0.0.0 without TLS or a key" in line
    for what in ("--psk-file", "RLBRIDGE_PSK", "--tls-cert", "--insecure"):
        assert what in line


def test_the_library_refuses_too_before_binding(make_server: Callable[..., ServerThread],
                                                tmp_path: Path) -> None:
    with pytest.raises(ServerError, match=r"refusing to listen on 192\.0\.2\.1"):
        make_server(host="192.0.2.1")  # TEST-NET-1: never bound, refused before


@pytest.mark.skipif(shutil.which("unshare") is None or os.geteuid() != 0,
                    reason="needs root and unshare for a private network namespace")
def test_insecure_starts_and_warns(tmp_path: Path) -> None:
    """In a network namespace of its own, so 0.0.0.0 reaches nothing but its loopback."""
    code = ("import sys; from rlbridge.cli import main; "
            "sys.argv = ['rlbridge', 'serve', '--host', '0.0.0.0', '--port', '0', "
            "'--insecure']; main()")
    proc = subprocess.Popen(["unshare", "--net", sys.executable, "-c", code],
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()
        assert "--insecure" in line
        assert "anyone who can reach it can read and write your topics" in line
        assert proc.poll() is None  # it serves
    finally:
        proc.terminate()
        proc.communicate(timeout=20)


def test_protected_servers_may_listen_anywhere(make_server: Callable[..., ServerThread],
                                               tmp_path: Path) -> None:
    from rlbridge.server import ServerConfig

    keys = tmp_path / "keys"
    keys.write_text(KEY.hex() + "\n")
    keys.chmod(0o600)
    # The check passes with a key, so the config is accepted for 0.0.0.0; it is started on
    # loopback here only to keep the test off the network.
    assert not ServerConfig(host="0.0.0.0", psk_file=keys).loopback
    srv = make_server(psk_file=keys)
    with Bridge.connect("127.0.0.1", srv.port, security=Psk(key=KEY.hex()),
                        reconnect=False) as bridge:
        bridge.publish("/secured/ok", F64)


# -- one key format ------------------------------------------------------------------------


def test_psk_is_hex_everywhere_and_errors_name_their_source(tmp_path: Path) -> None:
    hex_key = KEY.hex()
    assert resolve_key(hex_key) == KEY
    assert resolve_key(KEY) == KEY  # the bytes themselves, for code that has them
    assert resolve_key(environ={"RLBRIDGE_PSK": hex_key}) == KEY
    shared = tmp_path / "keys"
    shared.write_text(f"# the server's file, as is\nrobot {'ab' * 32} publish=/x\n{hex_key}\n")
    assert resolve_key(psk_file=shared, name="robot") == bytes.fromhex("ab" * 32)
    assert resolve_key(psk_file=shared, name="other") == KEY
    only_robot = tmp_path / "robot-only"
    only_robot.write_text(f"robot {hex_key}\n")
    with pytest.raises(ValueError, match="no key for client name 'other'"):
        resolve_key(psk_file=only_robot, name="other")
    with pytest.raises(ValueError, match=r"^Psk\(key=\.\.\.\): a key must be written in hex"):
        resolve_key("correct horse battery staple")
    with pytest.raises(ValueError, match=r"^\$RLBRIDGE_PSK: key of 8 bytes is too short"):
        resolve_key(environ={"RLBRIDGE_PSK": "00" * 8})
    bad = tmp_path / "keys"
    bad.write_text("robot hunter2hunter2\n")
    with pytest.raises(ValueError, match=r"keys, line 1: a key must be written in hex"):
        resolve_key(psk_file=bad, name="robot")


def test_a_text_key_fails_on_the_client_not_at_the_server(
        make_server: Callable[..., ServerThread], tmp_path: Path) -> None:
    keys = tmp_path / "keys"
    keys.write_text(KEY.hex() + "\n")
    keys.chmod(0o600)
    srv = make_server(psk_file=keys)
    with pytest.raises(ValueError, match=r"Psk\(key=\.\.\.\): a key must be written in hex"):
        Bridge.connect("127.0.0.1", srv.port, security=Psk(key="my secret robot key"),
                       reconnect=False)
    with pytest.raises(AuthRefused, match="could not prove"):  # a well-formed, other key
        Bridge.connect("127.0.0.1", srv.port, security=Psk(key="cd" * 32), reconnect=False)
    assert srv.server.registry is not None
    assert srv.server.registry.ctx.counters.get("sessions_opened", 0) == 0


@pytest.mark.skipif(shutil.which("unshare") is None or os.geteuid() != 0,
                    reason="needs root and unshare for a private network namespace")
def test_demo_bridge_beyond_loopback_makes_and_uses_a_key(tmp_path: Path) -> None:
    code = ("import sys; from rlbridge.cli import main; "
            "sys.argv = ['rlbridge', 'demo', '--role', 'bridge', '--host', '0.0.0.0', "
            "'--port', '0', '--seconds', '1', '--no-dashboard', '--no-plot']; main()")
    result = subprocess.run(["unshare", "--net", sys.executable, "-c", code], cwd=tmp_path,
                            capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stderr
    assert "made a new key file rlbridge-demo.key" in result.stdout
    key = tmp_path / "rlbridge-demo.key"
    assert key.stat().st_mode & 0o077 == 0
    assert resolve_key(psk_file=key, name="controller") is not None
