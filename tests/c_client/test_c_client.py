"""The C client's example programs against a real ``rlbridge serve`` on loopback (issue 28).

``rlb_pub`` publishes ``0 .. COUNT-1`` from a periodic loop; ``rlb_sub`` prints what it reads.
Against the Python SDK on the other end, and against each other through the server, over UDP
and TCP, with and without a pre-shared key: every value arrives, in order, none lost (the
readers keep every value: a blocking SDK channel with room for all, ``rlb_sub``'s ring of
COUNT over UDP; over TCP a ring of 64 with credit flow control, so COUNT values arrive only
if the client grants credit as it reads). Then the server is killed and started again under
a running ``rlb_sub``.
"""

from __future__ import annotations

import os
import re
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Literal

import pytest
from c_programs import CProcess

from rlbridge import Bridge
from waiting import assert_running, wait_until_ok

COUNT = 200
RATE_HZ = 400  # paced so that loopback keeps up on a loaded machine
WAIT = 30.0
FLOAT64 = "std_msgs/msg/Float64"

Server = Callable[..., tuple[int, subprocess.Popen[str]]]


@pytest.fixture(params=["plain", "psk"])
def keyed(request: pytest.FixtureRequest, tmp_path: Path,
          monkeypatch: pytest.MonkeyPatch) -> Iterator[list[str]]:
    """``[]`` or ``["--psk-file", FILE]``: the server's key file, given to the C programs too;
    the SDK takes the same key from ``$RLBRIDGE_PSK``."""
    if request.param == "plain":
        monkeypatch.delenv("RLBRIDGE_PSK", raising=False)
        yield []
        return
    key = os.urandom(32).hex()
    path = tmp_path / "keys"
    path.write_text(f"# test key\n{key}\n")
    monkeypatch.setenv("RLBRIDGE_PSK", key)
    yield ["--psk-file", str(path)]


Transport = Literal["udp", "tcp"]


@pytest.fixture(params=["udp", "tcp"])
def transport(request: pytest.FixtureRequest) -> Transport:
    return "tcp" if request.param == "tcp" else "udp"


def _flag(transport: Transport) -> list[str]:
    return ["--tcp"] if transport == "tcp" else []


def _sub(c_build: Path, c_processes: list[CProcess], port: int, topic: str, count: int,
         *extra: str, timeout_s: float = WAIT) -> CProcess:
    proc = CProcess(str(c_build / "rlb_sub"), "127.0.0.1", str(port), topic, str(count),
                    str(timeout_s), *extra)
    c_processes.append(proc)
    proc.wait_err("subscribed to")  # bound: from here on every value reaches it
    return proc


def _pub(c_build: Path, port: int, topic: str, count: int, *extra: str
         ) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(c_build / "rlb_pub"), "127.0.0.1", str(port), topic, str(count),
                           str(RATE_HZ), *extra],
                          capture_output=True, text=True, timeout=120, check=False)


def _connect(port: int, **kwargs: Any) -> Bridge:
    return Bridge.connect("127.0.0.1", port, timeout=10.0, **kwargs)


def test_rlb_pub_to_sdk_subscriber(c_build: Path, cli_server: Server, keyed: list[str],
                                   transport: Transport) -> None:
    port, _ = cli_server(*keyed)
    topic = f"/c_pub_{transport}"
    with _connect(port) as bridge:
        channel = bridge.subscribe(topic, FLOAT64, transport=transport, blocking=True,
                                   buffer_size=COUNT)
        pub = _pub(c_build, port, topic, COUNT, *_flag(transport), *keyed)
        assert pub.returncode == 0, pub.stderr
        got = [channel.read(timeout=WAIT) for _ in range(COUNT)]
    assert got == [float(i) for i in range(COUNT)]


def test_one_datagram_per_round_for_all_udp_channels(c_build: Path, cli_server: Server) -> None:
    """``rlb_pub --channels 4``: each round's values of the four channels travel in one
    ``Bundle`` datagram (protocol.md 6.16), so the server counts far fewer packets than values;
    every value still arrives, in order, on each topic."""
    port, _ = cli_server()
    with _connect(port) as bridge:
        channels = [bridge.subscribe(f"/c_bundle_{k}", FLOAT64, blocking=True,
                                     buffer_size=COUNT) for k in range(4)]
        before = bridge.server_stats()["server"]["packets_in"]
        pub = _pub(c_build, port, "/c_bundle", COUNT, "--channels", "4")
        assert pub.returncode == 0, pub.stderr
        for channel in channels:
            assert [channel.read(timeout=WAIT) for _ in range(COUNT)] == [
                float(i) for i in range(COUNT)]
        packets = bridge.server_stats()["server"]["packets_in"] - before
    # One datagram per value would be 4 * COUNT; a round is one (rarely two, when the I/O
    # thread runs between the loop's four writes), plus heartbeats and the SDK's own packets.
    assert packets < 3 * COUNT


def test_redundancy_both_ways(c_build: Path, cli_server: Server,
                              c_processes: list[CProcess]) -> None:
    """``--redundancy``: ``rlb_pub`` repeats its previous 3 values in every datagram (the server
    drops the repeats, counted as late), the server repeats 2 to ``rlb_sub`` (which drops them,
    counted as duplicates); every value still arrives once, in order (protocol.md 10.3)."""
    port, _ = cli_server()
    sub = _sub(c_build, c_processes, port, "/c_redundant", COUNT, "--redundancy", "2")
    with _connect(port) as bridge:
        late = bridge.server_stats()["server"]["late"]
        pub = _pub(c_build, port, "/c_redundant", COUNT, "--redundancy", "3")
        assert pub.returncode == 0, pub.stderr
        assert sub.finish(timeout=WAIT + 10) == 0, sub.err
        assert bridge.server_stats()["server"]["late"] > late  # the client's repeats
    assert sub.values() == [float(i) for i in range(COUNT)]
    duplicates = re.search(r"(\d+) duplicates", sub.err[-1])
    assert duplicates is not None, sub.err
    assert int(duplicates.group(1)) > 0  # the server's repeats, dropped by the client


def test_sdk_publisher_to_rlb_sub(c_build: Path, cli_server: Server, keyed: list[str],
                                  transport: Transport, c_processes: list[CProcess]) -> None:
    port, _ = cli_server(*keyed)
    topic = f"/c_sub_{transport}"
    sub = _sub(c_build, c_processes, port, topic, COUNT, *_flag(transport), *keyed)
    with _connect(port) as bridge:
        channel = bridge.publish(topic, FLOAT64, transport=transport)
        for i in range(COUNT):
            channel.write(float(i))
            time.sleep(1 / RATE_HZ)
        assert sub.finish(timeout=WAIT + 10) == 0, sub.err
    assert sub.values() == [float(i) for i in range(COUNT)]
    assert "0 lost" in sub.err[-1]


def test_rlb_pub_to_rlb_sub_through_the_server(c_build: Path, cli_server: Server,
                                               keyed: list[str], transport: Transport,
                                               c_processes: list[CProcess]) -> None:
    port, _ = cli_server(*keyed)
    topic = f"/c_both_{transport}"
    sub = _sub(c_build, c_processes, port, topic, COUNT, *_flag(transport), *keyed)
    pub = _pub(c_build, port, topic, COUNT, *_flag(transport), *keyed)
    assert pub.returncode == 0, pub.stderr
    assert sub.finish(timeout=WAIT + 10) == 0, sub.err
    assert sub.values() == [float(i) for i in range(COUNT)]


def test_rlb_sub_single_threaded(c_build: Path, cli_server: Server, transport: Transport,
                                 c_processes: list[CProcess]) -> None:
    """``--spin``: no I/O thread; the reading thread runs ``rlb_spin_once`` itself."""
    port, _ = cli_server()
    topic = f"/c_spin_{transport}"
    sub = _sub(c_build, c_processes, port, topic, COUNT, *_flag(transport), "--spin")
    pub = _pub(c_build, port, topic, COUNT, *_flag(transport))
    assert pub.returncode == 0, pub.stderr
    assert sub.finish(timeout=WAIT + 10) == 0, sub.err
    assert sub.values() == [float(i) for i in range(COUNT)]


def test_whole_messages_both_ways_and_a_refused_value(c_build: Path, cli_server: Server) -> None:
    """``rlb_twist``: Twist maps built with ``rlb_msg_*`` reach an SDK whole-message reader;
    read back whole and through a field; a map with an unknown field is the channel's error."""
    port, _ = cli_server()
    with _connect(port) as bridge:
        seen = bridge.subscribe("/c_twist", "geometry_msgs/msg/Twist", None, transport="tcp",
                                blocking=True, buffer_size=16)
        twist = subprocess.run([str(c_build / "rlb_twist"), "127.0.0.1", str(port), "/c_twist",
                                "10"], capture_output=True, text=True, timeout=120, check=False)
        assert twist.returncode == 0, twist.stderr
        maps = [seen.read(timeout=WAIT) for _ in range(10)]
    assert [(m["linear"]["x"], m["angular"]["z"]) for m in maps] == [
        (float(i), -float(i)) for i in range(10)]
    lines = twist.stdout.splitlines()
    read_back = [[float(x) for x in line.split()] for line in lines[:10]]
    assert read_back == [[i, -i, -i] for i in range(10)]  # linear.x, angular.z, the field
    assert lines[10] == "error 13"  # BAD_VALUE, surfaced on the publishing channel


def test_arrays_through_ros2(c_build: Path, cli_server: Server, tmp_path: Path,
                            monkeypatch: pytest.MonkeyPatch) -> None:
    """``rlb_array``: Float64MultiArray ``data`` (a ROS sequence) out and back through a
    server on the ROS 2 adapter, arrays in fixed-size slots both ways."""
    if os.environ.get("RLBRIDGE_TEST_REQUIRE_ROS2") != "1":
        pytest.importorskip("rclpy", reason="rclpy is not installed: no ROS 2 adapter here")
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")  # discovery stays here
    monkeypatch.setenv("ROS_DOMAIN_ID", str(1 + (os.getpid() + 37) % 100))
    monkeypatch.setenv("ROS_LOG_DIR", str(tmp_path))
    port, _ = cli_server("--adapter", "ros2")
    arrays = subprocess.run([str(c_build / "rlb_array"), "127.0.0.1", str(port), "/c_arrays",
                             "10"], capture_output=True, text=True, timeout=120, check=False)
    assert arrays.returncode == 0, arrays.stderr
    got = [[float(x) for x in line.split()] for line in arrays.stdout.splitlines()]
    assert got == [[i, i / 2, -i] for i in range(10)]


def test_a_refused_binding_is_exit_1_with_the_reason(c_build: Path, cli_server: Server) -> None:
    port, _ = cli_server()
    with _connect(port) as bridge:
        bridge.subscribe("/c_clash", "std_msgs/msg/Int32")  # the topic's type is Int32 now
        pub = _pub(c_build, port, "/c_clash", 1)
    assert pub.returncode == 1
    assert pub.stderr.count("\n") == 1
    assert "refused by the server (server: code 11" in pub.stderr  # TYPE_CLASH


def test_udp_only_sessions(c_build: Path, cli_server: Server, keyed: list[str],
                           c_processes: list[CProcess]) -> None:
    """``--udp-only`` against a server without TCP (protocol.md 8.2): the handshake (with a
    key: challenge and proof) over token-0 datagrams, bindings repeated until answered."""
    port, _ = cli_server("--no-tcp", *keyed)
    sub = _sub(c_build, c_processes, port, "/c_udp_only", COUNT, "--udp-only", *keyed)
    pub = _pub(c_build, port, "/c_udp_only", COUNT, "--udp-only", *keyed)
    assert pub.returncode == 0, pub.stderr
    assert sub.finish(timeout=WAIT + 10) == 0, sub.err
    assert sub.values() == [float(i) for i in range(COUNT)]


def test_no_server_is_exit_1_with_one_line(c_build: Path, free_port: Callable[[], int]) -> None:
    pub = _pub(c_build, free_port(), "/nobody", 1)
    assert pub.returncode == 1
    assert pub.stderr.count("\n") == 1
    assert "cannot connect" in pub.stderr


def test_a_wrong_key_is_refused(c_build: Path, cli_server: Server, tmp_path: Path) -> None:
    (tmp_path / "server").write_text(os.urandom(32).hex() + "\n")
    (tmp_path / "client").write_text("rlb_pub " + os.urandom(32).hex() + "\n")
    port, _ = cli_server("--psk-file", str(tmp_path / "server"))
    wrong = ["--psk-file", str(tmp_path / "client")]
    for extra in (wrong, [], [*wrong, "--udp-only"], ["--udp-only"]):  # wrong key, and none
        pub = _pub(c_build, port, "/refused", 1, *extra)
        assert pub.returncode == 1, extra
        assert "authentication failed" in pub.stderr, extra


def _serve(cli: Any, port: int) -> subprocess.Popen[str]:
    """``rlbridge serve`` on ``port``, returned once a session can be opened."""
    proc: subprocess.Popen[str] = cli.popen("serve", "--port", str(port), "--log-level",
                                            "warning")
    wait_until_ok(lambda: Bridge.connect("127.0.0.1", port, timeout=1.0, reconnect=False).close(),
                  f"a session with rlbridge serve on port {port}", timeout=WAIT,
                  between=lambda: assert_running(proc))
    return proc


def _publish(port: int, topic: str, values: range) -> None:
    with _connect(port, reconnect=False) as bridge:
        channel = bridge.publish(topic, FLOAT64, transport="udp")
        for v in values:
            channel.write(float(v))
            time.sleep(1 / RATE_HZ)
        bridge.send(wait=True)  # handed to the socket before the goodbye


@pytest.mark.parametrize("how", ["udp", "tcp", "udp-only"])
def test_server_restart_under_rlb_sub(c_build: Path, cli: Any, free_port: Callable[[], int],
                                      c_processes: list[CProcess], how: str,
                                      monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("RLBRIDGE_PSK", raising=False)
    port = free_port()
    server = _serve(cli, port)
    topic = f"/c_restart_{how.replace('-', '_')}"
    flags = {"udp": [], "tcp": ["--tcp"], "udp-only": ["--udp-only"]}[how]
    sub = _sub(c_build, c_processes, port, topic, 20, *flags, timeout_s=90)
    _publish(port, topic, range(10))
    sub.wait_out(10)
    server.kill()  # no goodbye: TCP is reset; a UDP-only client notices the silence
    server.communicate(timeout=WAIT)
    sub.wait_err("link lost")
    _serve(cli, port)  # same port; nobody tells rlb_sub
    sub.wait_err("connected", count=2)  # the client found it and bound its channel again
    _publish(port, topic, range(10, 20))
    assert sub.finish(timeout=WAIT + 10) == 0, sub.err
    assert sub.values() == [float(i) for i in range(20)]
