"""`rlbridge tls init`, `serve --tls-cert` and the client commands' TLS options, as processes."""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path
from typing import Any


def test_tls_init_serve_and_pin(cli: Any, cli_server: Callable[..., Any],
                                tmp_path: Path) -> None:
    made = cli.run("tls", "init", str(tmp_path / "tls"), "--name", "robot.local")
    assert made.returncode == 0, made.stderr
    match = re.search(r"sha256 fingerprint: ([0-9a-f]{64})", made.stdout)
    assert match is not None, made.stdout
    fingerprint = match.group(1)
    key = tmp_path / "tls" / "server.key"
    assert key.stat().st_mode & 0o077 == 0
    again = cli.run("tls", "init", str(tmp_path / "tls"))
    assert again.returncode == 1
    assert again.stderr.count("\n") == 1
    assert "--force" in again.stderr

    port, _proc = cli_server("--tls-cert", str(tmp_path / "tls" / "server.crt"),
                             "--tls-key", str(key))
    ok = cli.run("stats", "--json", "-p", str(port), "--fingerprint", fingerprint)
    assert ok.returncode == 0, ok.stderr
    assert '"tls_sessions": 1' in ok.stdout

    by_ca = cli.run("topic", "list", "-p", str(port), "--ca",
                    str(tmp_path / "tls" / "server.crt"))
    assert by_ca.returncode == 0, by_ca.stderr

    for args, text in ((), "requires TLS"), (("--tls",), "does not verify"), \
            (("--fingerprint", "00" * 32), "not the pinned"):
        bad = cli.run("topic", "list", "-p", str(port), *args)
        assert bad.returncode == 1
        assert bad.stderr.startswith("rlbridge: error: ")
        assert bad.stderr.count("\n") == 1
        assert text in bad.stderr, bad.stderr


def test_serve_refuses_half_a_tls_setup(cli: Any, free_port: Callable[[], int],
                                        tmp_path: Path) -> None:
    result = cli.run("serve", "--port", str(free_port()), "--tls-cert", str(tmp_path / "x"))
    assert result.returncode == 2
    assert "--tls-key" in result.stderr
    assert result.stderr.count("\n") == 1
    result = cli.run("serve", "--port", str(free_port()), "--tls-cert", str(tmp_path / "x"),
                     "--tls-key", str(tmp_path / "y"))
    assert result.returncode == 1
    assert "no such file" in result.stderr
    assert result.stderr.count("\n") == 1


def test_client_commands_take_the_servers_key_file(cli: Any, cli_server: Callable[..., Any],
                                                   tmp_path: Path) -> None:
    keys = tmp_path / "keys"
    keys.write_text(f"rlbridge-stats {'ab' * 32} stats=all\n* {'cd' * 32} publish=\n")
    keys.chmod(0o600)
    port, _proc = cli_server("--psk-file", str(keys))
    ok = cli.run("stats", "--json", "-p", str(port), "--psk-file", str(keys))
    assert ok.returncode == 0, ok.stderr
    assert '"identity": "rlbridge-stats"' in ok.stdout
    refused = cli.run("topic", "pub", "/x", "std_msgs/msg/Float64", "1.0", "-p", str(port),
                      "--psk-file", str(keys))
    assert refused.returncode == 1
    assert "may not publish to /x" in refused.stderr
    assert refused.stderr.count("\n") == 1
    services = cli.run("service", "list", "-p", str(port), "--psk-file", str(keys))
    assert services.returncode == 0, services.stderr  # the ros verbs take the same options
    missing = cli.run("stats", "-p", str(port))
    assert missing.returncode == 1
    assert "requires a pre-shared key" in missing.stderr
