"""A server sealing with one ChaCha20-Poly1305 implementation and a client sealing with the other
(rlbridge.wire.aead) move values both ways, over sealed UDP datagrams and sealed TCP records:
the implementation is each process's own business, never the protocol's."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from rlbridge import ConnectionFailed, Psk
from rlbridge.client.bridge import Bridge
from rlbridge.server import ServerThread
from rlbridge.wire import aead
from rlbridge.wire.aead import AEAD_ENV, CRYPTOGRAPHY, IMPLEMENTATIONS, LIBSODIUM
from waiting import wait_until_ok

KEY = bytes(range(32))
F64 = "std_msgs/msg/Float64"
WAIT = 30.0


def _connect(port: int) -> Bridge:
    """Connect once the server subprocess listens (it may take seconds on a loaded machine)."""
    bridge: Bridge = wait_until_ok(
        lambda: Bridge.connect("127.0.0.1", port, security=Psk(key=KEY), timeout=5.0),
        f"a session with the server on port {port}", errors=(ConnectionFailed,), timeout=WAIT,
        interval=0.2)
    return bridge


@pytest.mark.skipif(LIBSODIUM not in IMPLEMENTATIONS,
                    reason="one implementation only (rlbridge.wire._chacha was not built)")
def test_server_and_client_on_different_implementations(tmp_path: Path,
                                                        free_port: Callable[[], int]) -> None:
    here = LIBSODIUM if aead.STATE.startswith(LIBSODIUM) else CRYPTOGRAPHY
    there = CRYPTOGRAPHY if here == LIBSODIUM else LIBSODIUM
    keys = tmp_path / "keys"
    keys.write_text(KEY.hex() + "\n")
    keys.chmod(0o600)
    port = free_port()
    env = {k: v for k, v in os.environ.items() if k != "RLBRIDGE_PURE_PYTHON"}
    env[AEAD_ENV] = there
    server = subprocess.Popen(
        [sys.executable, "-m", "rlbridge", "serve", "--port", str(port), "--psk-file",
         str(keys)], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        with _connect(port) as pub, _connect(port) as sub:
            for transport, topic in (("udp", "/sealed_datagrams"), ("tcp", "/sealed_records")):
                inbox = sub.subscribe(topic, F64, transport=transport, blocking=True,
                                      buffer_size=64)
                out = pub.publish(topic, F64, transport=transport)
                for i in range(20):
                    out.write(float(i))
                assert [inbox.read(timeout=WAIT) for _ in range(20)] == \
                    [float(i) for i in range(20)]
            assert pub._conn.datagrams_dropped == {}
            assert sub._conn.datagrams_dropped == {}
    finally:
        server.terminate()
        _, err = server.communicate(timeout=WAIT)
    assert "Traceback" not in err, err


def test_an_impossible_choice_is_one_line_on_both_ends(
        tmp_path: Path, free_port: Callable[[], int],
        make_server: Callable[..., ServerThread]) -> None:
    """``$RLBRIDGE_AEAD`` naming nothing that can seal: the server refuses to start, a keyed
    client refuses to connect, each with one line that says why; the server it tried is
    unharmed."""
    keys = tmp_path / "keys"
    keys.write_text(KEY.hex() + "\n")
    keys.chmod(0o600)
    env = {k: v for k, v in os.environ.items() if k != "RLBRIDGE_PURE_PYTHON"}
    env |= {AEAD_ENV: "bogus", "COLUMNS": "200", "NO_COLOR": "1"}
    served = subprocess.run(
        [sys.executable, "-m", "rlbridge", "serve", "--port", str(free_port()), "--psk-file",
         str(keys)], env=env, capture_output=True, text=True, timeout=WAIT, check=False)
    assert served.returncode == 1
    assert served.stderr.count("\n") == 1, served.stderr
    assert "no ChaCha20-Poly1305 to seal with: $RLBRIDGE_AEAD='bogus'" in served.stderr
    server = make_server(psk_file=keys)
    echoed = subprocess.run(
        [sys.executable, "-m", "rlbridge", "topic", "echo", "/x", F64, "--port",
         str(server.port), "--count", "1"], env=env | {"RLBRIDGE_PSK": KEY.hex()},
        capture_output=True, text=True, timeout=WAIT, check=False)
    assert echoed.returncode == 1
    assert echoed.stderr.count("\n") == 1, echoed.stderr
    assert "no ChaCha20-Poly1305 to seal with" in echoed.stderr
    with _connect(server.port) as bridge:  # the server serves the next client
        assert bridge.link_state == "connected"
