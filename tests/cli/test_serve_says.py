"""``rlbridge serve`` says what it does: where it listens, when it stops, and, once per kind
and interval, what clients get wrong (real server processes, real clients)."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from rlbridge.server.notices import Notices

PROC_WAIT = 30.0
KEY_A, KEY_B = "11" * 32, "22" * 32
#: A server: its port, its process, and its first stderr line.
Served = tuple[int, subprocess.Popen[str], str]


def _env(**extra: str | None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONWARNINGS", "RLBRIDGE_PSK")}
    env.update({"PYTHONUNBUFFERED": "1", "COLUMNS": "200", "NO_COLOR": "1"})
    env.update({k: v for k, v in extra.items() if v is not None})
    return env


def _rlbridge(*args: str, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rlbridge", *args], capture_output=True,
                          text=True, timeout=PROC_WAIT, env=env, check=False)


@pytest.fixture
def serve(free_port: Callable[[], int]) -> Iterator[Callable[..., Served]]:
    """``serve(*args, psk=None)``: a server process and its first stderr line (it listens)."""
    procs: list[subprocess.Popen[str]] = []

    def start(*args: str, psk: str | None = None) -> Served:
        port = free_port()
        proc = subprocess.Popen([sys.executable, "-m", "rlbridge", "serve", "-p", str(port),
                                 *args], stderr=subprocess.PIPE, stdout=subprocess.PIPE,
                                text=True, env=_env(RLBRIDGE_PSK=psk))
        procs.append(proc)
        assert proc.stderr is not None
        first = proc.stderr.readline()  # blocks until the server listens (or exits)
        return port, proc, first

    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
        proc.communicate(timeout=PROC_WAIT)


def _notices(err: str, marker: str) -> tuple[list[str], int]:
    """The log lines with ``marker``, and how many notices they account for: each line is
    one, plus the "(N more ... not shown)" it says it held back (repeats still held at the
    stop are not logged). One line per kind and interval: on a slow machine the clients may
    span more than one interval."""
    lines = [line for line in err.splitlines() if marker in line]
    held = sum(int(m) for m in re.findall(r"\((\d+) more [^)]* not shown\)", err))
    return lines, len(lines) + held


def _stop(proc: subprocess.Popen[str]) -> tuple[int, str]:
    proc.send_signal(signal.SIGTERM)
    _out, err = proc.communicate(timeout=PROC_WAIT)
    return proc.returncode, err


def test_serve_says_where_it_listens_and_when_it_stops(
        serve: Callable[..., Served]) -> None:
    port, proc, first = serve()
    assert first.rstrip().endswith(
        f"rlbridge listening on 127.0.0.1 port {port} (TCP and UDP), adapter inproc, "
        "authentication: none"), first
    assert " INFO " in first
    listed = _rlbridge("topic", "list", "-p", str(port), env=_env())
    assert listed.returncode == 0, listed.stderr
    code, err = _stop(proc)
    assert code == 0
    lines = err.strip().splitlines()
    assert "session 1 (rlbridge-topic-list) opened over TCP" in lines[0]
    assert lines[-1].endswith("rlbridge stopped: 1 session(s) served"), lines


def test_serve_names_the_authentication_and_only_tcp(
        serve: Callable[..., Served]) -> None:
    port, proc, first = serve("--no-udp", psk=KEY_A)
    assert first.rstrip().endswith(f"port {port} (TCP), adapter inproc, authentication: "
                                   "pre-shared key"), first
    assert _stop(proc)[0] == 0


@pytest.mark.parametrize("where", ["top", "serve"])
def test_serve_takes_the_top_level_log_level_and_its_own(
        cli: Any, free_port: Callable[[], int], wait_until: Callable[..., Any],
        where: str) -> None:
    port = free_port()
    level = ("--log-level", "warning")
    args = (*level, "serve", "-p", str(port)) if where == "top" else (
        "serve", "-p", str(port), *level)
    proc = cli.popen(*args)
    wait_until(lambda: _rlbridge("topic", "list", "-p", str(port), env=_env()).returncode == 0)
    code, err = _stop(proc)
    assert (code, err) == (0, "")  # nothing to say at warning


def test_a_wrong_key_is_logged_once_with_its_reason(
        serve: Callable[..., Served]) -> None:
    port, proc, _first = serve(psk=KEY_A)
    for _ in range(3):
        refused = _rlbridge("topic", "list", "-p", str(port), env=_env(RLBRIDGE_PSK=KEY_B))
        assert refused.returncode == 1
        assert "[AUTH_FAILED]" not in refused.stderr  # no protocol code names for people
        assert "pre-shared key" in refused.stderr
    keyless = _rlbridge("topic", "list", "-p", str(port), env=_env())
    assert keyless.returncode == 1
    assert "requires a pre-shared key and this client gave none" in keyless.stderr
    assert "--psk-file FILE, or $RLBRIDGE_PSK" in keyless.stderr  # both ways to give one
    assert "nonce" not in keyless.stderr
    _code, err = _stop(proc)
    auth, accounted = _notices(err, "authentication failed")
    # Four refusals, one line per interval (rate-limited per kind): repeats are held back.
    assert 1 <= len(auth) < 4, err
    assert accounted <= 4, err
    assert "WARNING" in auth[0]
    assert "different keys" in auth[0] or "does not match" in auth[0]
    # Which machine: the operator's first question.
    assert re.search(r"for client 'rlbridge-topic-list' from 127\.0\.0\.1:\d+: ", auth[0]), auth[0]


def test_an_unresolvable_host_is_one_line_and_nothing_says_listening(cli: Any) -> None:
    result = cli.run("serve", "--host", "nonsense.invalid", "--insecure")
    assert result.returncode == 1
    assert result.stderr.count("\n") == 1, result.stderr
    assert result.stderr.startswith("rlbridge: error: cannot listen on nonsense.invalid: ")
    assert "listening" not in result.stderr
    assert "unknown error" not in result.stderr.lower()
    assert "--host" in result.stderr


def test_a_metrics_port_in_use_says_so_and_what_to_do(
        cli: Any, free_port: Callable[[], int]) -> None:
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        taken = holder.getsockname()[1]
        result = cli.run("serve", "-p", str(free_port()), "--metrics-port", str(taken))
    assert result.returncode == 1
    assert result.stderr.strip() == (
        f"rlbridge: error: cannot serve metrics on 127.0.0.1 port {taken}: address already in "
        "use; another program (or another rlbridge serve) has it: stop it, or choose another "
        "--metrics-port (0: any free port)")


def test_a_tls_client_that_refuses_the_certificate_is_logged(
        serve: Callable[..., Served], tmp_path: Any) -> None:
    """A client pinning another fingerprint checks it after the handshake and hangs up
    without a word to the server: the server says so (and counts it), naming the address."""
    made = _rlbridge("tls", "init", str(tmp_path), env=_env())
    assert made.returncode == 0, made.stderr
    port, proc, _first = serve("--tls-cert", str(tmp_path / "server.crt"),
                               "--tls-key", str(tmp_path / "server.key"))
    plain = _rlbridge("topic", "list", "-p", str(port), env=_env())  # a notice of its own kind
    assert plain.returncode == 1
    pinned = _rlbridge("topic", "list", "-p", str(port), "--fingerprint", "ab" * 32,
                       env=_env())
    assert pinned.returncode == 1
    _code, err = _stop(proc)
    assert "refused a plaintext client from 127.0.0.1:" in err
    lines = [line for line in err.splitlines() if "TLS client 127.0.0.1:" in line]
    assert len(lines) == 1, err
    assert "WARNING" in lines[0]
    assert "hung up after the TLS handshake, before its hello" in lines[0]


def test_malformed_datagrams_are_logged_once_with_the_reason(
        serve: Callable[..., Served]) -> None:
    port, proc, _first = serve()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        for _ in range(20):
            sock.sendto(b"GET / HTTP/1.0\r\n\r\n", ("127.0.0.1", port))
    listed = _rlbridge("topic", "list", "-p", str(port), env=_env())  # after the datagrams
    assert listed.returncode == 0
    _code, err = _stop(proc)
    bad = [line for line in err.splitlines() if "malformed UDP datagram" in line]
    assert len(bad) == 1, err
    assert "this port speaks the rlbridge protocol" in bad[0]


def test_a_refused_channel_is_logged_once(
        serve: Callable[..., Served]) -> None:
    port, proc, _first = serve()
    for _ in range(3):
        result = _rlbridge("topic", "pub", "/x", "std_msgs/msg/Float65", "1", "-p", str(port),
                           env=_env())
        assert result.returncode == 2  # a type name that does not exist: a usage error
    _code, err = _stop(proc)
    refused, accounted = _notices(err, "refused")
    assert 1 <= len(refused) < 3, err
    assert accounted <= 3, err
    assert "unknown message type 'std_msgs/msg/Float65'" in refused[0]


def test_notices_hold_repeats_and_count_them() -> None:
    """The rate limit itself, on a clock the test moves (no sleeping)."""
    lines: list[str] = []

    class Sink:
        def warning(self, fmt: str, *args: object) -> None:
            lines.append(fmt % args)

    now = [0.0]
    notices = Notices(Sink(), interval_s=10.0, clock=lambda: now[0])  # type: ignore[arg-type]
    assert notices.warn("malformed", "first")
    assert not notices.warn("malformed", "second")
    assert notices.warn("authentication", "other kind")
    now[0] = 10.0
    assert notices.warn("malformed", "third")
    assert lines == ["first", "other kind",
                     "third (1 more malformed notice(s) in the last 10 s not shown)"]
