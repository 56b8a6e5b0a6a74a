"""The C client over TLS (protocol.md 16.4) against ``rlbridge serve --tls-cert``.

The server's certificate from ``rlbridge tls init``; ``rlb_sub`` verifies it by CA file,
``rlb_pub`` pins its fingerprint; values over TCP and over UDP (datagrams sealed with the keys
derived from ``ConnectAck.datagram_key``), with a pre-shared key on top too. Then each way a
client can be wrong, refused with one line that says why.
"""

from __future__ import annotations

import os
import re
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from c_programs import CProcess

from rlbridge.tls.certs import issue, make_ca

Server = Callable[..., tuple[int, subprocess.Popen[str]]]
COUNT = 200


@pytest.fixture
def tls_build(c_build: Path) -> Path:
    """The C build, if it has TLS (OpenSSL found by cmake), else skipped (or failed in CI)."""
    cache = (c_build / "CMakeCache.txt").read_text()
    found = re.search(r"^OPENSSL_SSL_LIBRARY:FILEPATH=(.+)$", cache, re.M)
    if not found or found.group(1).endswith("NOTFOUND") or "RLB_TLS:BOOL=OFF" in cache:
        if os.environ.get("RLBRIDGE_TEST_REQUIRE_C") == "1":
            pytest.fail("librlbridge was built without TLS (apt-get install libssl-dev)")
        pytest.skip("librlbridge was built without TLS: no OpenSSL (apt-get install libssl-dev)")
    return c_build


@pytest.fixture
def certificate(cli: Any, tmp_path: Path) -> tuple[Path, Path, str]:
    """``(cert, key, sha256 fingerprint)`` of a fresh self-signed server certificate."""
    made = cli.run("tls", "init", str(tmp_path / "tls"))
    assert made.returncode == 0, made.stderr
    fingerprint = re.search(r"sha256 fingerprint: ([0-9a-f]{64})", made.stdout)
    assert fingerprint is not None, made.stdout
    return tmp_path / "tls" / "server.crt", tmp_path / "tls" / "server.key", fingerprint.group(1)


def _run(build: Path, program: str, port: int, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(build / program), "127.0.0.1", str(port), *args],
                          capture_output=True, text=True, timeout=120, check=False)


@pytest.mark.parametrize("keyed", [False, True], ids=["tls", "tls+psk"])
@pytest.mark.parametrize("transport", ["udp", "tcp"])
def test_values_over_tls(tls_build: Path, cli_server: Server, certificate: tuple[Path, Path, str],
                         tmp_path: Path, c_processes: list[CProcess], keyed: bool,
                         transport: str) -> None:
    cert, key, fingerprint = certificate
    psk: list[str] = []
    if keyed:
        (tmp_path / "keys").write_text(os.urandom(32).hex() + "\n")
        psk = ["--psk-file", str(tmp_path / "keys")]
    port, _ = cli_server("--tls-cert", str(cert), "--tls-key", str(key), *psk)
    flag = ["--tcp"] if transport == "tcp" else []
    topic = f"/c_tls_{transport}"
    sub = CProcess(str(tls_build / "rlb_sub"), "127.0.0.1", str(port), topic, str(COUNT), "30",
                   "--tls-ca", str(cert), *flag, *psk)
    c_processes.append(sub)
    sub.wait_err("subscribed to")
    pub = _run(tls_build, "rlb_pub", port, topic, str(COUNT), "400",
               "--tls-fingerprint", fingerprint, *flag, *psk)
    assert pub.returncode == 0, pub.stderr
    assert sub.finish(timeout=60) == 0, sub.err
    assert sub.values() == [float(i) for i in range(COUNT)]


def test_a_client_certificate(tls_build: Path, cli_server: Server, tmp_path: Path) -> None:
    """Mutual TLS: a server with ``--tls-client-ca`` admits ``rlb_pub`` with a certificate
    that CA signed, and refuses it without one."""
    ca = make_ca()
    ca.write(tmp_path / "ca.crt", tmp_path / "ca.key")
    issue("server", names=["127.0.0.1"], ca=ca).write(tmp_path / "s.crt", tmp_path / "s.key")
    issue("rlb_pub", ca=ca, client=True).write(tmp_path / "c.crt", tmp_path / "c.key")
    port, _ = cli_server("--tls-cert", str(tmp_path / "s.crt"), "--tls-key",
                         str(tmp_path / "s.key"), "--tls-client-ca", str(tmp_path / "ca.crt"))
    trust = ["--tls-ca", str(tmp_path / "ca.crt")]  # the server, verified with its name
    admitted = _run(tls_build, "rlb_pub", port, "/c_mtls", "5", "100", *trust,
                    "--tls-cert", str(tmp_path / "c.crt"), "--tls-key", str(tmp_path / "c.key"))
    assert admitted.returncode == 0, admitted.stderr
    refused = _run(tls_build, "rlb_pub", port, "/c_mtls", "5", "100", *trust)
    assert refused.returncode == 1
    assert refused.stderr.count("\n") == 1, refused.stderr
    assert "certificate required" in refused.stderr  # the server's alert, in OpenSSL's words


def test_each_wrong_tls_setting_is_refused_with_its_reason(
        tls_build: Path, cli: Any, cli_server: Server, certificate: tuple[Path, Path, str],
        tmp_path: Path) -> None:
    cert, key, fingerprint = certificate
    assert cli.run("tls", "init", str(tmp_path / "other")).returncode == 0
    other_ca = str(tmp_path / "other" / "server.crt")  # loads, but did not sign the server's
    port, _ = cli_server("--tls-cert", str(cert), "--tls-key", str(key))
    plain_port, _ = cli_server()
    cases = [
        (port, ["--tls-fingerprint", "00" + fingerprint[2:]], "not the pinned one"),
        (port, ["--tls-ca", other_ca], "does not verify"),
        (port, [], "requires TLS"),  # the server says so, in plain frames
        (plain_port, ["--tls-fingerprint", fingerprint], "TLS: handshake failed"),
    ]
    for where, args, reason in cases:
        pub = _run(tls_build, "rlb_pub", where, "/c_tls_refused", "1", "10", *args)
        assert pub.returncode == 1, (args, pub.stderr)
        assert pub.stderr.count("\n") == 1, pub.stderr
        assert reason in pub.stderr, (args, pub.stderr)
    unreadable = _run(tls_build, "rlb_pub", port, "/c_tls_refused", "1", "10", "--tls-ca",
                      str(tmp_path / "missing.crt"))
    assert unreadable.returncode == 1
    assert "does not load" in unreadable.stderr  # found at set-up, before any connection
