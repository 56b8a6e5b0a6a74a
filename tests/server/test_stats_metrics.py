"""The Prometheus endpoint, scraped over HTTP from a live server with known traffic."""

from __future__ import annotations

import http.client
import re
import socket
from collections.abc import Callable
from typing import Any

import pytest

from rlbridge.server import ServerConfig, ServerThread
from rlbridge.server.app import ServerError
from rlbridge.server.metrics import render
from rlbridge.wire import Batch, TopicAck, TopicConnect

F64 = "std_msgs/msg/Float64"
SAMPLE = re.compile(r"^([a-z_]+)(\{[^}]*\})? (-?[0-9.e+]+|NaN)$")


def scrape(port: int, path: str = "/metrics", method: str = "GET") -> tuple[int, str, str]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    try:
        conn.request(method, path)
        resp = conn.getresponse()
        return resp.status, resp.getheader("Content-Type") or "", resp.read().decode()
    finally:
        conn.close()


def samples(text: str) -> dict[str, float]:
    """``name{labels}`` -> value; fails on any line that is not valid exposition format."""
    out: dict[str, float] = {}
    typed: set[str] = set()
    for line in text.splitlines():
        if line.startswith("# TYPE "):
            name = line.split()[2]
            assert name not in typed, f"{name} typed twice (its series must be together)"
            typed.add(name)
            continue
        match = SAMPLE.match(line)
        assert match, f"not an exposition line: {line!r}"
        assert match.group(1) in typed, f"{match.group(1)} has no # TYPE line before it"
        out[match.group(1) + (match.group(2) or "")] = float(match.group(3))
    return out


def test_scrape_reports_known_traffic(make_server: Callable[..., ServerThread],
                                      raw_tcp: Callable[..., Any],
                                      wait_until: Callable[..., Any]) -> None:
    srv = make_server(metrics_port=0)
    address = srv.server.address
    assert address is not None
    assert address.metrics_port
    mport = address.metrics_port
    client = raw_tcp(srv.port)
    client.hello('pub "quoted"')
    client.send(TopicConnect(2, "publish", "/metrics/t", F64, transport="tcp"))
    client.expect(TopicAck)
    client.send(Batch(2, 0, [0] * 12, [1.0] * 12))
    wait_until(lambda: client.stats()["session"]["values_in"] == 12, what="12 values in")
    status, ctype, text = scrape(mport)
    assert status == 200
    assert ctype.startswith("text/plain; version=0.0.4")
    got = samples(text)
    assert got["rlbridge_values_in_total"] == 12
    assert got["rlbridge_sessions"] == 1
    sid = client.ack.session
    who = f'session="{sid}",name="pub \\"quoted\\""'
    assert got[f"rlbridge_session_values_in_total{{{who}}}"] == 12
    channel = (f'rlbridge_channel_values_in_total{{{who},channel="2",direction="publish",'
               f'topic="/metrics/t",transport="tcp"}}')
    assert got[channel] == 12


def test_bad_requests_get_http_errors(make_server: Callable[..., ServerThread]) -> None:
    srv = make_server(metrics_port=0)
    assert srv.server.address is not None
    mport = srv.server.address.metrics_port
    assert mport is not None
    assert scrape(mport, "/other")[0] == 404
    assert scrape(mport, "/metrics", "POST")[0] == 405
    with socket.create_connection(("127.0.0.1", mport), timeout=30) as sock:
        sock.sendall(b"x" * 20000)  # a request head past the limit: refused, not buffered
        assert sock.recv(100).startswith(b"HTTP/1.1 400")
    head_status, _, head_body = scrape(mport, "/metrics", "HEAD")
    assert (head_status, head_body) == (200, "")
    assert scrape(mport)[0] == 200  # and it still serves


def test_metrics_off_by_default_and_closed_with_the_server() -> None:
    srv = ServerThread(ServerConfig(port=0)).start()
    try:
        assert srv.server.address is not None
        assert srv.server.address.metrics_port is None
    finally:
        srv.stop()
    with_metrics = ServerThread(ServerConfig(port=0, metrics_port=0)).start()
    assert with_metrics.server.address is not None
    mport = with_metrics.server.address.metrics_port
    assert mport is not None
    assert scrape(mport)[0] == 200
    with_metrics.stop()
    with pytest.raises(ConnectionRefusedError):
        scrape(mport)


def test_metrics_port_in_use_is_a_clear_error() -> None:
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        taken = holder.getsockname()[1]
        with pytest.raises(ServerError, match=f"cannot serve metrics on 127.0.0.1:{taken}"):
            ServerThread(ServerConfig(port=0, metrics_port=taken)).start()


def test_render_escapes_and_groups() -> None:
    report = {"server": {"sessions": 1, "values_in": 3},
              "sessions": [{"session": 1, "name": "a\nb", "rtt_us": None, "values_in": 3,
                            "channels": {"1": {"direction": "publish", "topic": "/t",
                                               "values_in": 3}}},
                           {"session": 2, "name": "c", "rtt_us": 12.5, "values_in": 0,
                            "channels": {}}]}
    got = samples(render(report))
    assert got['rlbridge_session_values_in_total{session="1",name="a\\nb"}'] == 3
    assert got['rlbridge_session_rtt_us{session="2",name="c"}'] == 12.5
