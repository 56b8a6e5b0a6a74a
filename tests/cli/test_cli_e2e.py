"""The ``rlbridge`` command end to end: real server and client processes on loopback."""

from __future__ import annotations

import json
import re
import secrets
import signal
import socket
import subprocess
from collections.abc import Callable, Sequence
from typing import Any

import pytest

from rlbridge._compiled import STATE
from rlbridge._version import __version__
from rlbridge.wire import PacketCodec, Stats
from rlbridge.wire.aead import STATE as AEAD

F64 = "std_msgs/msg/Float64"

#: The CLI processes need a second or two to start on a busy machine; keep waits generous.
PROC_WAIT = 30.0


def assert_one_line_error(result: subprocess.CompletedProcess[str], *phrases: str) -> str:
    """Non-zero exit, exactly one stderr line starting with ``rlbridge: error:``, no traceback."""
    assert result.returncode != 0, result
    assert "Traceback" not in result.stderr, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("rlbridge: error: "), lines[0]
    for phrase in phrases:
        assert phrase in lines[0], lines[0]
    return lines[0]


def wait_for_topic(topics_of: Callable[[int], Sequence[str]], port: int, topic: str,
                   proc: subprocess.Popen[str], wait_until: Callable[..., Any]) -> None:
    """Until ``proc`` (a subscriber) has bound ``topic`` on the server."""

    def bound() -> bool:
        if proc.poll() is not None:
            raise AssertionError(f"subscriber exited early: {proc.communicate()}")
        return topic in topics_of(port)

    wait_until(bound, timeout=PROC_WAIT, interval=0.05, what=f"{topic} to be subscribed")


def test_version(cli: Any) -> None:
    result = cli.run("--version")
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines() == [f"rlbridge {__version__}", f"value path: {STATE}",
                                          f"sealing (ChaCha20-Poly1305): {AEAD}"]


def test_echo_prints_what_pub_publishes(cli: Any, shared_cli_server: int,
                                        topics_of: Callable[[int], Sequence[str]],
                                        wait_until: Callable[..., Any]) -> None:
    port = shared_cli_server
    echo = cli.popen("topic", "echo", "/x", F64, "--count", "3", "--timeout", "20",
                     "--port", str(port))
    wait_for_topic(topics_of, port, "/x", echo, wait_until)
    pub = cli.popen("topic", "pub", "/x", F64, "1.5", "--rate", "50", "--count", "20",
                    "--port", str(port))
    out, err = echo.communicate(timeout=PROC_WAIT)
    assert echo.returncode == 0, err
    assert out.splitlines() == ["1.5", "1.5", "1.5"]
    pub_out, pub_err = pub.communicate(timeout=PROC_WAIT)
    assert pub.returncode == 0, pub_err
    assert "published 20 message(s) on /x" in pub_out


def test_echo_whole_message_over_tcp(cli: Any, shared_cli_server: int,
                                     topics_of: Callable[[int], Sequence[str]],
                                     wait_until: Callable[..., Any]) -> None:
    port = shared_cli_server
    twist = "geometry_msgs/msg/Twist"
    echo = cli.popen("topic", "echo", "/cmd", twist, "--field", "", "--transport", "tcp",
                     "--count", "1", "--timeout", "20", "--port", str(port))
    wait_for_topic(topics_of, port, "/cmd", echo, wait_until)
    result = cli.run("topic", "pub", "/cmd", twist, '{"linear": {"x": 0.5}}', "--field", "",
                     "--transport", "tcp", "--port", str(port))
    assert result.returncode == 0, result.stderr
    out, err = echo.communicate(timeout=PROC_WAIT)
    assert echo.returncode == 0, err
    zero = {"x": 0.0, "y": 0.0, "z": 0.0}
    assert json.loads(out) == {"linear": {**zero, "x": 0.5}, "angular": zero}


def test_topic_list_shows_a_held_topic(cli: Any, shared_cli_server: int,
                                       topics_of: Callable[[int], Sequence[str]],
                                       wait_until: Callable[..., Any]) -> None:
    port = shared_cli_server
    echo = cli.popen("topic", "echo", "/listed/topic", "std_msgs/msg/String", "--port", str(port))
    wait_for_topic(topics_of, port, "/listed/topic", echo, wait_until)
    result = cli.run("topic", "list", "--port", str(port))
    assert result.returncode == 0, result.stderr
    assert "/listed/topic" in result.stdout.splitlines()
    typed = cli.run("topic", "list", "--show-types", "--port", str(port))
    assert "/listed/topic [std_msgs/msg/String]" in typed.stdout.splitlines()
    echo.send_signal(signal.SIGINT)
    echo.communicate(timeout=PROC_WAIT)
    wait_until(lambda: "/listed/topic" not in topics_of(port), timeout=PROC_WAIT,
               what="the topic to go away with its only subscriber")


def test_topic_hz_measures_about_50_hz(cli: Any, shared_cli_server: int,
                                       topics_of: Callable[[int], Sequence[str]],
                                       wait_until: Callable[..., Any]) -> None:
    port = shared_cli_server
    # The publisher runs first and long (30 s at most), so that hz measures a steady stream,
    # whatever its own start-up costs on a busy machine.
    pub = cli.popen("topic", "pub", "/rate", F64, "2.0", "--rate", "50", "--count", "1500",
                    "--port", str(port))
    wait_for_topic(topics_of, port, "/rate", pub, wait_until)
    hz = cli.popen("topic", "hz", "/rate", F64, "--duration", "3", "--port", str(port))
    out, err = hz.communicate(timeout=PROC_WAIT)
    pub.send_signal(signal.SIGINT)
    pub.communicate(timeout=PROC_WAIT)
    assert hz.returncode == 0, err
    rates = [float(m) for m in re.findall(r"average rate: ([0-9.]+)", out)]
    assert rates, out
    # The rate is the arrivals' own (no bound on this machine's pace, which load changes):
    # one over the mean gap, so between one over the longest and one over the shortest gap.
    gaps = re.findall(r"min: ([0-9.]+)s max: ([0-9.]+)s", out)
    shortest, longest = (float(g) for g in gaps[-1])
    assert 1.0 / longest <= rates[-1], out
    assert shortest == 0.0 or rates[-1] <= 1.0 / shortest, out  # 0: values read together
    window = re.findall(r"window: (\d+)", out)
    assert int(window[-1]) >= 50, out


def test_stats_prints_json(cli: Any, shared_cli_server: int,
                           stats_over_tcp: Callable[[int], dict[str, Any]]) -> None:
    port = shared_cli_server
    before = stats_over_tcp(port)["server"].get("udp_bad_token", 0)
    # A few datagrams with tokens the server never issued: dropped, counted, never answered.
    codec = PacketCodec()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        for _ in range(3):
            sock.sendto(codec.encode_datagram(Stats(), secrets.randbits(63) + 1),
                        ("127.0.0.1", port))
    result = cli.run("stats", "--json", "--port", str(port))
    assert result.returncode == 0, result.stderr
    body = json.loads(result.stdout)
    assert set(body) == {"session", "server", "sessions", "topics"}
    assert body["session"]["name"] == "rlbridge-stats"
    assert body["server"]["udp_bad_token"] == before + 3
    assert body["server"]["sessions_opened"] >= 2


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_serve_exits_0_on_signal_and_says_goodbye(
    cli: Any, cli_server: Callable[..., Any], topics_of: Callable[[int], Sequence[str]],
    wait_until: Callable[..., Any], sig: signal.Signals,
) -> None:
    port, server = cli_server()
    echo = cli.popen("topic", "echo", "/bye", F64, "--port", str(port))
    wait_for_topic(topics_of, port, "/bye", echo, wait_until)
    server.send_signal(sig)
    _out, err = server.communicate(timeout=PROC_WAIT)
    assert server.returncode == 0, err
    assert "Traceback" not in err
    # The client notices, and says so in one line, instead of waiting forever. Normally it
    # read the server's goodbye; a heartbeat crossing the close can turn it into a reset.
    _out, err = echo.communicate(timeout=PROC_WAIT)
    line = assert_one_line_error(subprocess.CompletedProcess([], echo.returncode, "", err))
    assert re.search(r"server closed the session: server shutting down"
                     r"|server closed the TCP connection|connection failed", line), line


def test_port_in_use(cli: Any, free_port: Callable[[], int]) -> None:
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        result = cli.run("serve", "--port", str(port))
    assert_one_line_error(result, f"cannot listen on 127.0.0.1 TCP port {port}: address "
                          "already in use", "choose another --port")


def test_udp_port_in_use_says_udp(cli: Any) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as holder:
        holder.bind(("127.0.0.1", 0))
        port = holder.getsockname()[1]
        result = cli.run("serve", "--port", str(port), "--no-tcp")
    assert_one_line_error(result, f"cannot listen on 127.0.0.1 UDP port {port}: address "
                          "already in use", "choose another --port")


def test_pub_to_an_unreachable_server(cli: Any, free_port: Callable[[], int]) -> None:
    port = free_port()
    result = cli.run("topic", "pub", "/x", F64, "1.0", "--port", str(port))
    assert_one_line_error(result, f"cannot reach rlbridge server at 127.0.0.1:{port}")


def test_pub_of_a_value_of_the_wrong_type(cli: Any, shared_cli_server: int) -> None:
    """Refused where it is written (the channel's schema), before anything is sent."""
    result = cli.run("topic", "pub", "/x", F64, '"abc"', "--port", str(shared_cli_server))
    assert_one_line_error(result, "topic '/x' (std_msgs/msg/Float64 field data) needs a float",
                          "got str 'abc'")
    assert "published" not in result.stdout


def test_stats_to_an_unreachable_server(cli: Any, free_port: Callable[[], int]) -> None:
    port = free_port()
    result = cli.run("stats", "--port", str(port))
    assert_one_line_error(result, f"cannot reach rlbridge server at 127.0.0.1:{port}")


def test_bad_type_name(cli: Any, shared_cli_server: int) -> None:
    port = str(shared_cli_server)
    result = cli.run("topic", "pub", "/bad/type", "std_msgs/msg/Float65", "1.0", "--port", port)
    assert_one_line_error(result, "unknown message type 'std_msgs/msg/Float65'",
                          "std_msgs/msg/Float64")  # the message lists the known types
    echo = cli.run("topic", "echo", "/bad/type", "Float64", "--count", "1", "--port", port)
    assert_one_line_error(echo, "'Float64' is not a message type name")


def test_bad_field_and_bad_transport(cli: Any, shared_cli_server: int) -> None:
    port = str(shared_cli_server)
    result = cli.run("topic", "pub", "/bad/field", F64, "1.0", "--field", "datum",
                     "--port", port)
    assert_one_line_error(result, "has no field 'datum'")
    result = cli.run("topic", "pub", "/bad/field", F64, "1.0", "--transport", "carrier-pigeon",
                     "--port", port)
    assert_one_line_error(result, "--transport must be 'udp' or 'tcp'")


def test_serve_without_any_transport(cli: Any, free_port: Callable[[], int]) -> None:
    result = cli.run("serve", "--no-tcp", "--no-udp", "--port", str(free_port()))
    assert_one_line_error(result, "enable at least one transport")


def test_serve_with_a_bad_watchdog(cli: Any, free_port: Callable[[], int]) -> None:
    result = cli.run("serve", "--heartbeat-ms", "500", "--timeout-ms", "400",
                     "--port", str(free_port()))
    assert_one_line_error(result, "--timeout-ms must be longer than --heartbeat-ms")


def test_a_channel_option_the_channel_cannot_honour_is_one_line(
        cli: Any, shared_cli_server: int) -> None:
    """The SDK's option rules reach the command line unchanged: redundancy repeats values in
    UDP datagrams, so a TCP echo refuses it, in one line, naming the option."""
    result = cli.run("topic", "echo", "/x", F64, "--transport", "tcp", "--redundancy", "1",
                     "--count", "1", "--port", str(shared_cli_server))
    assert result.returncode == 1
    assert result.stderr.strip().count("\n") == 0
    assert "Policy(redundancy=1) repeats values in UDP datagrams" in result.stderr
    bad = cli.run("topic", "pub", "/x", F64, "1.0", "--on-lost", "zero",
                  "--port", str(shared_cli_server))
    assert bad.returncode == 1
    assert "--on-lost must be 'hold', 'raise' or a JSON value" in bad.stderr
