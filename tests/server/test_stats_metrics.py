"""The Prometheus endpoint, scraped over HTTP from a live server with known traffic."""

from __future__ import annotations

import http.client
import json
import re
import socket
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from prometheus_client.parser import text_string_to_metric_families

from rlbridge.server import ServerConfig, ServerThread
from rlbridge.server.app import ServerError
from rlbridge.server.exposition import render
from rlbridge.server.ledger import MAX_CLIENTS, Ledger
from rlbridge.wire import Batch, TopicAck, TopicConnect

F64 = "std_msgs/msg/Float64"
SAMPLE = re.compile(r"^([a-z_]+)(\{.*\})? (-?[0-9.e+-]+|NaN)$")


def scrape(port: int, path: str = "/metrics", method: str = "GET") -> tuple[int, str, str]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    try:
        conn.request(method, path)
        resp = conn.getresponse()
        return resp.status, resp.getheader("Content-Type") or "", resp.read().decode()
    finally:
        conn.close()


def metrics_port(srv: ServerThread) -> int:
    """The port a started server's metrics endpoint got."""
    assert srv.server.address is not None
    mport = srv.server.address.metrics_port
    assert mport is not None
    return mport


def samples(text: str) -> dict[str, float]:
    """``name{labels}`` -> value, after Prometheus' own parser accepted the text.

    Also checks the conventions the parser lets pass: every family has HELP and TYPE lines
    before its samples, its series are together, and no name carries a non-base unit.
    """
    families = list(text_string_to_metric_families(text))
    assert families, "no metric families"
    helped: set[str] = set()
    typed: set[str] = set()
    out: dict[str, float] = {}
    for line in text.splitlines():
        if line.startswith("# HELP "):
            helped.add(line.split()[2])
        elif line.startswith("# TYPE "):
            name = line.split()[2]
            assert name not in typed, f"{name} typed twice (its series must be together)"
            assert name in helped, f"{name} has no # HELP line"
            typed.add(name)
        else:
            match = SAMPLE.match(line)
            assert match, f"not an exposition line: {line!r}"
            assert match.group(1) in typed, f"{match.group(1)} has no # TYPE line before it"
            assert not re.search(r"_(us|ns|ms|micros|nanos)(_|$)", match.group(1)), line
            out[match.group(1) + (match.group(2) or "")] = float(match.group(3))
    for family in families:
        if family.type == "counter":  # the parser strips _total from a counter's name
            assert all(s.name.endswith("_total") for s in family.samples), family.name
    return out


def channel(client: str, topic: str, direction: str = "publish", transport: str = "tcp") -> str:
    return f'client="{client}",topic="{topic}",direction="{direction}",transport="{transport}"'


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
    client.send(Batch(2, 12, [0] * 2, [1.0, "bad"]))
    wait_until(lambda: client.stats()["session"]["values_in"] == 13, what="13 values in")
    status, ctype, text = scrape(mport)
    assert status == 200
    assert ctype.startswith("text/plain; version=0.0.4")
    got = samples(text)
    assert got["rlbridge_values_in_total"] == 13
    assert got["rlbridge_values_rejected_total"] == 1
    assert got["rlbridge_sessions"] == 1
    assert got["rlbridge_received_bytes_total"] > 0
    who = 'client="pub \\"quoted\\""'
    assert got[f"rlbridge_client_sessions{{{who},state=\"connected\"}}"] == 1
    assert got[f"rlbridge_client_received_packets_total{{{who}}}"] >= 4
    labels = channel('pub \\"quoted\\"', "/metrics/t")
    assert got[f"rlbridge_channel_values_in_total{{{labels}}}"] == 13
    assert got[f"rlbridge_channel_values_rejected_total{{{labels}}}"] == 1
    assert got[f"rlbridge_channel_bindings{{{labels}}}"] == 1
    assert all("session=" not in key and "channel=" not in key for key in got)


def test_a_reconnecting_client_is_one_series_whose_counters_never_go_back(
        make_server: Callable[..., ServerThread], raw_tcp: Callable[..., Any],
        wait_until: Callable[..., Any]) -> None:
    srv = make_server(metrics_port=0)
    mport = metrics_port(srv)
    series: list[int] = []
    values: list[float] = []
    key = f"rlbridge_channel_values_in_total{{{channel('robot', '/m/r', transport='udp')}}}"
    for attempt in range(5):
        client = raw_tcp(srv.port)
        client.hello("robot")
        client.send(TopicConnect(1, "publish", "/m/r", F64, transport="udp"))
        client.expect(TopicAck)
        client.send(Batch(1, 0, [0] * 3, [1.0, 2.0, 3.0]))
        wait_until(lambda c=client: c.stats()["session"]["values_in"] == 3, what="3 values in")
        got = samples(scrape(mport)[2])
        series.append(len(got))
        values.append(got[key])
        client.close()
        wait_until(lambda: samples(scrape(mport)[2])["rlbridge_sessions"] == 0,
                   what="session closed")
        after = samples(scrape(mport)[2])
        assert after[key] == 3 * (attempt + 1)  # the closed session's values stay counted
    assert values == [3, 6, 9, 12, 15]
    assert len(set(series)) == 1, series  # no new series per reconnect
    final = samples(scrape(mport)[2])
    assert final['rlbridge_client_sessions_opened_total{client="robot"}'] == 5


def test_closed_clients_beyond_the_cap_fold_into_other(
        make_server: Callable[..., ServerThread], raw_tcp: Callable[..., Any],
        wait_until: Callable[..., Any]) -> None:
    srv = make_server(metrics_port=0)
    mport = metrics_port(srv)
    names = [f"rlbridge-{pid}" for pid in range(MAX_CLIENTS + 6)]  # a new pid per restart
    for name in names:
        client = raw_tcp(srv.port)
        client.hello(name)
        client.close()
    folded = len(names) - (MAX_CLIENTS - 1)
    wait_until(lambda: samples(scrape(mport)[2]).get(
        'rlbridge_client_sessions_opened_total{client="(other)"}') == folded, what="folded")
    got = samples(scrape(mport)[2])
    opened = [k for k in got if k.startswith("rlbridge_client_sessions_opened_total")]
    assert len(opened) == MAX_CLIENTS  # the newest 63, and (other)
    assert 'rlbridge_client_sessions_opened_total{client="rlbridge-0"}' not in got
    assert got['rlbridge_client_sessions_opened_total{client="rlbridge-69"}'] == 1
    assert sum(got[k] for k in opened) == len(names)


def test_a_live_client_is_never_folded_while_departed_ones_are(
        make_server: Callable[..., ServerThread], raw_tcp: Callable[..., Any],
        wait_until: Callable[..., Any]) -> None:
    """The oldest retired totals belong to a client connected now: the departed go first."""
    srv = make_server(metrics_port=0)
    mport = metrics_port(srv)
    first = raw_tcp(srv.port)
    first.hello("robot")
    first.close()  # the oldest entry of the ledger
    robot = raw_tcp(srv.port)
    robot.hello("robot")  # and back: live from here on
    robot.send(TopicConnect(3, "subscribe", "/m/live", F64, transport="tcp"))
    robot.expect(TopicAck)
    names = [f"gone-{n}" for n in range(MAX_CLIENTS + 6)]
    for name in names:
        client = raw_tcp(srv.port)
        client.hello(name)
        client.close()
    wait_until(lambda: samples(scrape(mport)[2]).get(
        'rlbridge_client_sessions_opened_total{client="gone-69"}') == 1, what="all retired")
    got = samples(scrape(mport)[2])
    assert got['rlbridge_client_sessions_opened_total{client="robot"}'] == 2  # never went back
    opened = [k for k in got if k.startswith("rlbridge_client_sessions_opened_total")]
    assert sum(got[k] for k in opened) == len(names) + 2
    assert 'rlbridge_client_sessions_opened_total{client="gone-0"}' not in got


def test_ledger_folds_departed_labels_before_live_ones() -> None:
    live: tuple[set[str], set[tuple[str, str, str, str]]] = ({"a"}, {("a", "/t0", "publish",
                                                                      "udp")})
    ledger = Ledger(max_clients=2, max_channels=2, live=lambda: live)
    for name in ("a", "b", "c", "d"):
        ledger.retire_session(name, {"packets_in": 1})
    # b and c left: folded; a is live, d just retired: over the cap by the live ones only
    assert list(ledger.clients) == ["a", "(other)", "d"]
    assert ledger.clients["(other)"] == {"packets_in": 2, "sessions": 2}
    for n in range(4):
        ledger.retire_channel("a", {"topic": f"/t{n}", "direction": "publish",
                                    "transport": "udp", "values_in": 1})
    assert ("a", "/t0", "publish", "udp") in ledger.channels
    assert ledger.channels[("(other)",) * 4] == {"values_in": 2}
    live = (set(), set())  # everyone gone: back to the cap, oldest first
    ledger.retire_session("e", {})
    assert list(ledger.clients) == ["(other)", "e"]
    assert ledger.clients["(other)"] == {"packets_in": 4, "sessions": 4}


def test_healthz_and_json_status(make_server: Callable[..., ServerThread],
                                 raw_tcp: Callable[..., Any]) -> None:
    srv = make_server(metrics_port=0)
    mport = metrics_port(srv)
    assert scrape(mport, "/healthz")[::2] == (200, "ok\n")
    client = raw_tcp(srv.port)
    client.hello("watched")
    client.send(TopicConnect(3, "subscribe", "/m/s", F64, transport="tcp"))
    client.expect(TopicAck)
    code, ctype, text = scrape(mport, "/status")
    assert (code, ctype) == (200, "application/json")
    status = json.loads(text)
    assert status["accepting"] is True
    assert status["uptime_seconds"] >= 0
    assert status["server"]["sessions"] == 1
    (session,) = status["sessions"]
    assert session["name"] == "watched"
    assert session["state"] in ("connected", "degraded")
    assert session["channels"]["3"]["topic"] == "/m/s"
    assert {"rtt_ns", "lost", "values"} <= set(session["channels"]["3"])


def test_bad_requests_get_http_errors(make_server: Callable[..., ServerThread]) -> None:
    srv = make_server(metrics_port=0)
    mport = metrics_port(srv)
    assert scrape(mport, "/other")[0] == 404
    assert "/healthz" in scrape(mport, "/other")[2]
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


def _reaches(host: str, port: int) -> bool:
    with socket.socket() as sock:
        try:
            sock.connect((host, port))
        except ConnectionRefusedError:
            return False
        return True


def test_metrics_stay_on_loopback_when_the_server_listens_on_every_address(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """/metrics and /status name clients and topics and ask no key: not on --host's 0.0.0.0."""
    key = tmp_path / "k"
    key.write_text("00112233445566778899aabbccddeeff\n")
    key.chmod(0o600)
    with ServerThread(ServerConfig(host="0.0.0.0", port=0, psk_file=key,
                                   metrics_port=0)) as srv:
        mport = metrics_port(srv)
        assert _reaches("127.0.0.2", srv.port)  # the bridge listens on every address
        assert not _reaches("127.0.0.2", mport)  # its metrics on 127.0.0.1 only
        assert srv.server.address.metrics_host == "127.0.0.1"
        assert scrape(mport)[0] == 200
    assert "ask no key" not in caplog.text
    with ServerThread(ServerConfig(port=0, metrics_port=0, metrics_host="0.0.0.0")) as srv:
        mport = metrics_port(srv)
        assert _reaches("127.0.0.2", mport)  # asked for: served there, and warned
    assert re.search(r"metrics on 0\.0\.0\.0: /metrics and /status ask no key", caplog.text)


def test_metrics_port_in_use_is_a_clear_error() -> None:
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        taken = holder.getsockname()[1]
        with pytest.raises(ServerError) as refused:
            ServerThread(ServerConfig(port=0, metrics_port=taken)).start()
    assert str(refused.value) == (
        f"cannot serve metrics on 127.0.0.1 port {taken}: address already in use; another "
        "program (or another rlbridge serve) has it: stop it, or choose another --metrics-port "
        "(0: any free port)")


def test_render_escapes_groups_and_keeps_closed_counters() -> None:
    report = {"server": {"sessions": 1, "values_in": 3, "udp_bad_token": 2},
              "sessions": [{"session": 1, "name": "a\nb", "rtt_us": None, "packets_in": 3,
                            "state": "connected",
                            "channels": {"1": {"direction": "publish", "topic": "/t",
                                               "transport": "udp", "values_in": 3,
                                               "lost": 0, "one_way_ns": 2_500_000}}},
                           {"session": 2, "name": "c", "rtt_us": 12.5, "packets_in": 1234567,
                            "state": "degraded", "channels": {}}]}
    ledger = Ledger()
    ledger.retire_session("c", {"packets_in": 10})
    ledger.retire_channel("a\nb", {"direction": "publish", "topic": "/t", "transport": "udp",
                                    "values_in": 4, "lost": -1})
    text = render(report, ledger)
    got = samples(text)
    assert got['rlbridge_client_received_packets_total{client="a\\nb"}'] == 3
    assert got['rlbridge_client_received_packets_total{client="c"}'] == 1234577  # exact
    assert got['rlbridge_client_rtt_seconds{client="c"}'] == 12.5e-6
    assert got['rlbridge_client_sessions{client="c",state="degraded"}'] == 1
    labels = channel("a\\nb", "/t", transport="udp")
    assert got[f"rlbridge_channel_values_in_total{{{labels}}}"] == 7
    assert got[f"rlbridge_channel_one_way_seconds{{{labels}}}"] == 0.0025
    assert got["rlbridge_udp_bad_token_total"] == 2
    assert "# HELP rlbridge_udp_bad_token_total Server event counter udp_bad_token" in text
