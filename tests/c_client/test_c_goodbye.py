"""``rlb_close``'s goodbye delivers the last values (protocol.md 8.4 "Last values").

``rlb_pub`` writes COUNT values at a high rate, flushes them to its sockets and closes at
once, while the tail is still in flight. The server reads TCP and UDP independently, so a
goodbye sent too early drops that tail: over TCP it overtakes the last datagrams, over UDP
it discards TCP frames not yet read. The C client waits for the server's loss reports (TCP
values) and sends the goodbye over UDP behind the datagrams, resent until the server closes
TCP. An SDK subscriber (over TCP, so its own path loses nothing) must get every value, in
order, on every run; ``rlb_pub`` must not have counted any value as unconfirmed. And when
the server cannot answer (stopped), the close ends at its bound with the unconfirmed values
counted and said, not silently.
"""

from __future__ import annotations

import re
import signal
import subprocess
from collections.abc import Callable
from pathlib import Path

import pytest
from c_programs import CProcess

from rlbridge import Bridge

COUNT = 3000
RATE_HZ = 20000  # far faster than one I/O period: the close comes with values in flight
WAIT = 30.0
FLOAT64 = "std_msgs/msg/Float64"
RUNS = range(4)

Server = Callable[..., tuple[int, subprocess.Popen[str]]]


def _pub(c_build: Path, port: int, topic: str, *extra: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(c_build / "rlb_pub"), "127.0.0.1", str(port), topic, str(COUNT),
                           str(RATE_HZ), *extra],
                          capture_output=True, text=True, timeout=120, check=False)


def _every_value(c_build: Path, port: int, topics: list[str], *extra: str) -> None:
    with Bridge.connect("127.0.0.1", port, timeout=10.0) as bridge:
        channels = [bridge.subscribe(t, FLOAT64, transport="tcp", blocking=True,
                                     buffer_size=COUNT) for t in topics]
        pub = _pub(c_build, port, *extra)
        assert pub.returncode == 0, pub.stderr
        assert "counted as lost" not in pub.stderr, pub.stderr
        got = {t: [ch.read(timeout=WAIT) for _ in range(COUNT)]
               for t, ch in zip(topics, channels, strict=True)}
    for topic in topics:
        assert got[topic] == [float(i) for i in range(COUNT)], topic


@pytest.mark.parametrize("run", RUNS)
def test_last_udp_values_arrive(c_build: Path, cli_server: Server, run: int) -> None:
    port, _ = cli_server()
    topic = f"/c_bye_udp_{run}"
    _every_value(c_build, port, [topic], topic)


@pytest.mark.parametrize("run", RUNS)
def test_last_values_of_tcp_and_udp_channels_arrive(c_build: Path, cli_server: Server,
                                                    run: int) -> None:
    """``--mixed``: ``TOPIC_0`` over UDP, ``TOPIC_1`` over TCP, in one session."""
    port, _ = cli_server()
    topic = f"/c_bye_mix_{run}"
    _every_value(c_build, port, [f"{topic}_0", f"{topic}_1"], topic, "--channels", "2",
                 "--mixed")


def test_values_the_server_never_confirmed_are_counted(c_build: Path, cli_server: Server,
                                                       c_processes: list[CProcess]) -> None:
    """The server stopped (SIGSTOP) while ``rlb_pub`` still writes: no loss report, no answer
    to the goodbye. ``rlb_close`` gives up at its bound (the link timeout, 3 s here, longer
    than the loop lasts so the link stays up) and says how many values it counted as lost
    (``RLB_EV_UNCONFIRMED``, which ``rlb_pub`` prints); it still exits 0."""
    port, server = cli_server("--timeout-ms", "5000")
    topic = "/c_bye_frozen"
    count = 4000  # two seconds at 2 kHz: the server stops long before the loop ends
    with Bridge.connect("127.0.0.1", port, timeout=10.0) as bridge:
        channel = bridge.subscribe(topic, FLOAT64, transport="tcp", blocking=True,
                                   buffer_size=count)
        pub = CProcess(str(c_build / "rlb_pub"), "127.0.0.1", str(port), topic, str(count),
                       "2000")
        c_processes.append(pub)
        assert channel.read(timeout=WAIT) is not None  # values flow: bound, session up
    server.send_signal(signal.SIGSTOP)
    try:
        code = pub.finish()
    finally:
        server.send_signal(signal.SIGCONT)
    err = "\n".join(pub.err)
    assert code == 0, err
    said = re.search(r"did not confirm the last (\d+) value\(s\) of /c_bye_frozen within "
                     r"(\d+) ms; counted as lost", err)
    assert said is not None, err
    assert 0 < int(said.group(1)) <= count
    assert said.group(2) == "3000"  # min(the session's 5000 ms, connect_timeout_ms)
