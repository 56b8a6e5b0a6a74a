"""The independent client (written from docs/protocol.md alone) against a live server.

Each test names the section of the document it checks. A failure here means the document and
the server disagree: fix the document if it is wrong; if the server is wrong, the test is
marked ``xfail(strict=True)`` with the reason, so the fix flips it to a failure to remove.
"""

from __future__ import annotations

import importlib.util
import re
import struct
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest

from rlbridge.server import ServerConfig, ServerThread

HERE = Path(__file__).resolve().parent
DOC = HERE.parents[1] / "docs" / "protocol.md"


def _load_client() -> ModuleType:
    spec = importlib.util.spec_from_file_location("independent_client",
                                                  HERE / "independent_client.py")
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses resolve annotations through sys.modules
    spec.loader.exec_module(module)
    return module


ic = _load_client()
Client = ic.IndependentClient
F64 = "std_msgs/msg/Float64"
HOST = "127.0.0.1"


@pytest.fixture(scope="module")
def server() -> Iterator[ServerThread]:
    # A short heartbeat so RTT samples come quickly; a long timeout so a slow machine does
    # not trip the watchdog between two steps of a test.
    with ServerThread(ServerConfig(port=0, heartbeat_ms=50, timeout_ms=5000)) as srv:
        yield srv


@pytest.fixture
def client(server: ServerThread) -> Iterator[ic.IndependentClient]:
    with Client(HOST, server.port) as c:
        yield c


@pytest.fixture
def session(client: ic.IndependentClient) -> ic.IndependentClient:
    client.connect_tcp("test")
    return client


_topics = iter(range(1_000_000))


def new_topic() -> str:
    return f"/interop/t{next(_topics)}"


def _code(exc: pytest.ExceptionInfo[ic.Refused]) -> int:
    code: int = exc.value.code
    return code


# -- the walk-through of the brief -----------------------------------------------------------


def test_scenario_values_arrive_intact_and_in_order(server: ServerThread) -> None:
    """Doc 8.1, 8.3, 9, 10, 11, 8.4: the whole session as the brief describes it."""
    r = ic.run_scenario(HOST, server.port, topic=new_topic())
    assert r.ack is not None
    assert r.ack.token != 0
    assert (r.ack.heartbeat_ms, r.ack.timeout_ms) == (50, 5000)
    assert (r.ack.max_packet, r.ack.max_channels, r.ack.max_batch) == (1 << 20, 256, 4096)
    for ch, ack in r.acks.items():
        assert ack.fields[:3] == (ch, F64, 0.0)
        # Doc 6.5: a publish channel's ack carries the JSON Schema of its values; nil else.
        assert ack.field(4) == ({"type": "number"} if ch in (1, 4) else None)
    assert r.acks[4].via == "udp", "a TopicConnect sent over UDP is answered over UDP (doc 9)"
    assert r.retransmit_ack is not None
    assert r.retransmit_ack.fields == r.acks[4].fields

    expected = r.sent_tcp + r.sent_udp
    assert ic.same_floats(r.got_tcp, expected), r.got_tcp
    assert ic.same_floats(r.got_udp, expected), r.got_udp
    assert r.udp_filter is not None
    assert r.udp_filter.lost == 0
    assert r.udp_filter.duplicates > 0, "redundancy 2 repeats earlier values (doc 10.3)"

    assert r.topic_error is not None
    assert r.topic_error.packet.tag == ic.TAG_TOPIC_ERROR
    assert (r.topic_error.channel, r.topic_error.code) == (5, ic.UNKNOWN_TYPE)

    channels = r.stats["session"]["channels"]
    assert channels["1"].items() >= {"direction": "publish", "values_in": 8, "bad_values": 0,
                                     "lost": 0, "duplicates": 0}.items()  # keys may grow
    assert channels["4"]["values_in"] == 5
    assert channels["2"]["values_out"] == channels["3"]["values_out"] == 13
    assert r.stats["session"]["rtt_us"] is not None, "our heartbeat echoes gave an RTT"
    assert r.rtt_samples_ns
    assert all(0 < s < 1_000_000_000 for s in r.rtt_samples_ns)
    assert r.closed_after_disconnect


# -- framing and bodies (doc 2, 3, 4, 6) -----------------------------------------------------


def _doc_hex_dumps() -> dict[str, bytes]:
    """Section 14's dumps: heading -> bytes."""
    dumps: dict[str, bytes] = {}
    heading = ""
    blocks = 0
    in_block = False
    for line in DOC.read_text().splitlines():
        if line.startswith("### 14."):
            heading, blocks = line[4:].strip(), 0
        elif line.startswith("```"):
            in_block = not in_block
            blocks += in_block
        elif in_block and heading and re.match(r"^[0-9a-f]{4}  ", line):
            key = f"{heading} #{blocks}"
            dumps[key] = dumps.get(key, b"") + bytes.fromhex(line[6:])
    return dumps


def test_doc_hex_dumps_decode_and_reencode_byte_for_byte() -> None:
    """Doc 14 and 5: the dumps parse with the primer's subset, and it encodes them the same."""
    dumps = _doc_hex_dumps()
    assert len(dumps) >= 8, sorted(dumps)
    for heading, raw in dumps.items():
        if "UDP" in heading:
            _flags, token, body = ic.parse_datagram(raw)
            assert ic.datagram(body, token) == raw, heading
        else:
            bodies = ic.FrameReader().feed(raw)
            assert len(bodies) == 1, heading
            assert ic.frame(bodies[0]) == raw, heading
    value_dump = next(raw for h, raw in dumps.items() if "Value datagram" in h)
    assert ic.parse_datagram(value_dump) == (
        0, 0x0123456789ABCDEF, [8, 3, 7, 1_700_000_000_000_000_000, 1.5])
    hello_dump = next(raw for h, raw in dumps.items() if "Hello frame" in h)
    assert ic.FrameReader().feed(hello_dump) == [[1, 1, "demo", b""]]


def test_doc_tables_match_the_code() -> None:
    """Doc 6 and 12.2 list every tag and every error code of the implementation."""
    from rlbridge.wire import ErrorCode, packets

    text = DOC.read_text()
    tag_row = r"^\| (\d+)\s+\| `(\w+)`\s+\| (?:client|server|both)"
    tags = {int(m[1]): m[2] for m in re.finditer(tag_row, text, re.M)}
    code_tags = {cls.__struct_config__.tag: cls.__name__ for cls in packets.Packet.__args__}
    assert tags == code_tags
    codes = {m[2]: int(m[1]) for m in re.finditer(r"^\| (\d+)\s+\| `([A-Z_]+)`", text, re.M)}
    assert codes == {e.name: int(e) for e in ErrorCode}
    assert code_tags == ic.TAG_NAMES


def test_frames_cut_at_any_read_boundary(session: ic.IndependentClient) -> None:
    """Doc 2: frames are cut by length, not by reads: send two Stats one byte at a time."""
    raw = ic.frame([ic.TAG_STATS]) + ic.frame([ic.TAG_STATS, {}])
    for i in range(len(raw)):
        session.send_raw_tcp(raw[i : i + 1])
    session.recv_tag(ic.TAG_STATS, via="tcp")
    session.recv_tag(ic.TAG_STATS, via="tcp")


def test_shortest_and_longer_forms_are_accepted(client: ic.IndependentClient) -> None:
    """Doc 4: trailing defaults may be omitted; extra trailing elements are ignored."""
    client.open_tcp()
    client.send_tcp([ic.TAG_HELLO, 1, "fwd", b"", "a future field", 42])
    ack = client.recv_tag(ic.TAG_CONNECT_ACK)
    assert len(ack.fields) == 6
    assert ack.field(6) == b""
    topic = new_topic()
    client.send_tcp([ic.TAG_TOPIC_CONNECT, 1, "subscribe", topic, F64])  # field, transport...
    assert client.recv_tag(ic.TAG_TOPIC_ACK).fields == (1, F64, 0.0, None, None)
    client.send_tcp([ic.TAG_TOPIC_CONNECT, 2, "publish", topic, F64, "data", "tcp", 1, None,
                     10, 0, 0, False, False, False, "volatile", "a future field"])
    assert client.recv_tag(ic.TAG_TOPIC_ACK).field(1) == 2
    client.send_tcp([ic.TAG_VALUE, 2, 0, 0, 1.25, "extra"])
    assert client.collect(1, 1) == [1.25]
    client.send_tcp([ic.TAG_DISCONNECT])
    assert client.wait_eof()


def test_malformed_body_costs_one_packet(session: ic.IndependentClient) -> None:
    """Doc 2, 15.1: a bad body in a good frame: Error(MALFORMED, channel); the session goes on.

    ``channel`` is the body's second element when the body starts with two integers, else nil.
    """
    cases = (
        (b"\xc1", None),
        (ic.packb([99, 1]), 1),
        (ic.packb([ic.TAG_HELLO, 1.0, "x"]), None),
        (ic.packb([ic.TAG_BATCH, 1, 0, [1, 2], [1.0]]), 1),
        (ic.packb({"tag": 1}), None),
    )
    for bad, channel in cases:
        session.send_raw_tcp(ic.FRAME_HEADER.pack(b"RB", 1, 0, len(bad)) + bad)
        err = session.recv_tag(ic.TAG_ERROR, ic.TAG_CONNECT_ERROR)
        assert err.tag == ic.TAG_ERROR
        assert (err.field(1), err.field(3)) == (ic.MALFORMED, channel), err
    assert "session" in session.stats()


def test_topic_connect_that_does_not_decode_gets_a_topic_error(
        session: ic.IndependentClient) -> None:
    """Doc 6.4 and 15.1: an invalid TopicConnect gets TopicError(channel, MALFORMED), so a
    client waiting for that channel's answer is not left to time out."""
    session.send_tcp([ic.TAG_TOPIC_CONNECT, 7, "both", new_topic(), F64])
    err = session.recv_tag(ic.TAG_ERROR, ic.TAG_TOPIC_ERROR)
    assert err.tag == ic.TAG_TOPIC_ERROR
    assert (err.field(1), err.field(2)) == (7, ic.MALFORMED)


@pytest.mark.parametrize(
    ("header", "code"),
    [
        (ic.FRAME_HEADER.pack(b"GE", 1, 0, 3), ic.MALFORMED),
        (ic.FRAME_HEADER.pack(b"RB", 2, 0, 3), ic.UNSUPPORTED_VERSION),
        (ic.FRAME_HEADER.pack(b"RB", 1, 0, (1 << 20) + 1), ic.TOO_LARGE),
    ],
    ids=["bad-magic", "bad-version", "too-large"],
)
def test_bad_header_is_fatal(client: ic.IndependentClient, header: bytes, code: int) -> None:
    """Doc 2: a bad header loses the framing: ConnectError, then the server closes."""
    client.open_tcp()
    client.send_raw_tcp(header)
    err = client.recv_tag(ic.TAG_CONNECT_ERROR)
    assert err.field(1) == code
    assert client.wait_eof()


def test_bad_header_mid_session_is_fatal_too(session: ic.IndependentClient) -> None:
    """Doc 6.3: inside a session a broken stream gets Error(code), Disconnect, then EOF."""
    session.send_raw_tcp(ic.FRAME_HEADER.pack(b"RB", 1, 0, (1 << 20) + 1))
    assert session.recv_tag(ic.TAG_ERROR).field(1) == ic.TOO_LARGE
    assert session.recv_tag(ic.TAG_DISCONNECT).field(1) == ic.TOO_LARGE
    assert session.wait_eof()


def test_frame_of_exactly_max_packet_is_accepted(session: ic.IndependentClient) -> None:
    """Doc 2: the limit is on the body; a body of exactly max_packet bytes passes the header."""
    assert session.ack is not None
    limit = session.ack.max_packet
    overhead = len(ic.packb([ic.TAG_STATS, {"pad": "x" * 70_000}])) - 70_000  # str32 header
    body = ic.packb([ic.TAG_STATS, {"pad": "x" * (limit - overhead)}])
    assert len(body) == limit
    session.send_raw_tcp(ic.FRAME_HEADER.pack(b"RB", 1, 0, len(body)) + body)
    session.recv_tag(ic.TAG_STATS, via="tcp")


def test_first_packet_must_be_hello(client: ic.IndependentClient) -> None:
    """Doc 8.1: anything but a Hello first is UNEXPECTED, and the connection closes."""
    client.open_tcp()
    client.send_tcp([ic.TAG_STATS])
    assert client.recv_tag(ic.TAG_CONNECT_ERROR).field(1) == ic.UNEXPECTED
    assert client.wait_eof()


@pytest.mark.parametrize("body", [
    [ic.TAG_HELLO, 1, "again"],
    [ic.TAG_TOPIC_ACK, 1, F64],
    [ic.TAG_ERROR, 2, "from a client"],
    [ic.TAG_CONNECT_ACK, 1, 1, 200, 600, [1024, 1, 1]],
], ids=["second-hello", "topic-ack", "error", "connect-ack"])
def test_server_only_packets_are_unexpected(session: ic.IndependentClient,
                                            body: list[object]) -> None:
    """Doc 6: a client sending a server's packet (or a second Hello) gets Error(UNEXPECTED)."""
    session.send_tcp(body)
    assert session.recv_tag(ic.TAG_ERROR).field(1) == ic.UNEXPECTED


def test_protocol_version_in_hello(client: ic.IndependentClient) -> None:
    """Doc 8.1: Hello.protocol other than 1 is refused with UNSUPPORTED_VERSION."""
    client.open_tcp()
    client.send_tcp(ic.hello("future", protocol=2))
    assert client.recv_tag(ic.TAG_CONNECT_ERROR).field(1) == ic.UNSUPPORTED_VERSION
    assert client.wait_eof()


# -- UDP (doc 3, 8.2, 8.3) -------------------------------------------------------------------


def test_udp_registration_and_heartbeats_both_ways(session: ic.IndependentClient) -> None:
    """Doc 8.3, 11: after our token-bearing datagram the server heartbeats over UDP too."""
    assert session.pump(lambda: session.heartbeats_received["udp"] >= 2
                        and session.heartbeats_received["tcp"] >= 2)


def test_udp_drops_are_silent(session: ic.IndependentClient) -> None:
    """Doc 3, 12.1: bad token, token 0 non-Hello, bad magic, short: dropped, no answer."""
    assert session.udp is not None
    session.send_udp([ic.TAG_STATS], token=session.token ^ 1)
    session.send_udp([ic.TAG_STATS], token=0)
    session.udp.send(b"XX\x01\x00" + session.token.to_bytes(8, "big") + ic.packb([13]))
    session.udp.send(b"RB\x01")
    session.send_udp([ic.TAG_STATS])
    body = session.recv_tag(ic.TAG_STATS, via="udp").field(1)
    assert [p for p in session.backlog if p.via == "udp"] == []
    counters = body["server"]
    assert counters["udp_bad_token"] >= 1
    assert counters["udp_no_token"] >= 1
    assert counters["udp_malformed"] >= 2


def test_udp_bad_body_with_live_token_is_answered(session: ic.IndependentClient) -> None:
    """Doc 12.1: a valid header and token but a bad body is answered; a bad topic-connect
    gets a TopicError for its channel, so the client's request does not time out."""
    session.send_udp([99, 1])
    assert session.recv_tag(ic.TAG_ERROR, via="udp").field(1) == ic.MALFORMED
    session.send_udp([ic.TAG_TOPIC_CONNECT, 9, "both", new_topic(), F64])
    refused = session.recv_tag(ic.TAG_TOPIC_ERROR, via="udp")
    assert (refused.field(1), refused.field(2)) == (9, ic.MALFORMED)


def test_udp_only_session(client: ic.IndependentClient) -> None:
    """Doc 8.2: Hello with token 0, ack datagram carries the token, channels must be UDP."""
    ack, header_token = client.connect_udp("udp-only")
    assert header_token == ack.token != 0
    # A repeated Hello from the same address and name gets the same session.
    client.send_udp(ic.hello("udp-only"), token=0)
    again = client.recv_tag(ic.TAG_CONNECT_ACK, via="udp")
    assert (again.field(1), again.field(2)) == (ack.session, ack.token)

    topic = new_topic()
    with pytest.raises(ic.Refused) as exc:  # transport defaults to "tcp"
        client.bind(1, "subscribe", topic, F64, via="udp")
    assert _code(exc) == ic.TRANSPORT_DISABLED
    assert exc.value.packet.tag == ic.TAG_TOPIC_ERROR
    assert exc.value.packet.via == "udp"
    client.bind(1, "subscribe", topic, F64, "data", "udp", via="udp")
    client.bind(2, "publish", topic, F64, "data", "udp", via="udp")
    client.publish(2, [1.0, 2.0], via="udp")
    client.publish(2, [3.0, 4.0, 5.0], via="udp", as_batch=True)
    assert client.collect(1, 5) == [1.0, 2.0, 3.0, 4.0, 5.0]
    assert client.pump(lambda: client.heartbeats_received["udp"] >= 1)

    # Doc 8.4: a Disconnect datagram ends the session; the same Hello then opens a new one.
    client.disconnect(via="udp")
    client.send_udp(ic.hello("udp-only"), token=0)
    fresh = client.recv_tag(ic.TAG_CONNECT_ACK, via="udp")
    assert fresh.field(1) != ack.session
    assert fresh.field(2) != ack.token


def test_udp_hello_with_wrong_version(client: ic.IndependentClient) -> None:
    """Doc 8.2: a refused Hello datagram is answered by ConnectError with token 0."""
    sock = client.open_udp()
    sock.send(ic.datagram(ic.hello("future", protocol=3), 0))
    sock.settimeout(client.timeout)
    _flags, token, body = ic.parse_datagram(sock.recv(1 << 16))
    assert token == 0
    assert body[:2] == [ic.TAG_CONNECT_ERROR, ic.UNSUPPORTED_VERSION]


def test_udp_channel_values_wait_until_registered(client: ic.IndependentClient) -> None:
    """Doc 8.3: without a registered UDP address, a UDP channel's newest values (up to its
    depth, 10 by default) wait and arrive first once it is registered; older ones are
    dropped, counted."""
    client.connect_tcp("no-udp-yet", with_udp=False)
    topic = new_topic()
    client.bind(1, "subscribe", topic, F64, "data", "udp")
    client.bind(2, "publish", topic, F64)
    client.publish(2, [float(i) for i in range(12)])
    channels = client.stats()["session"]["channels"]
    assert channels["1"]["dropped"] == 2
    assert channels["2"]["values_in"] == 12
    client.open_udp()
    client.send_udp(ic.heartbeat(time.monotonic_ns()))
    client.stats(via="udp")
    client.publish(2, [12.0])
    assert client.collect(1, 11) == [float(i) for i in range(2, 13)]


def test_values_over_udp_on_a_tcp_bound_channel(session: ic.IndependentClient) -> None:
    """Doc 9: transport does not restrict how the client sends on a publish channel."""
    topic = new_topic()
    session.bind(1, "subscribe", topic, F64)
    session.bind(2, "publish", topic, F64, "data", "tcp")
    session.publish(2, [0.5, 0.75], via="udp")
    assert session.collect(1, 2) == [0.5, 0.75]


# -- channels and values (doc 7, 9, 10) ------------------------------------------------------


def test_binding_errors_carry_documented_codes(session: ic.IndependentClient) -> None:
    """Doc 9, 12.2: each refusal is a TopicError for its channel with its code."""
    topic = new_topic()
    session.bind(1, "publish", topic, F64)
    cases = [
        (2, "subscribe", topic, "std_msgs/msg/Nope", "data", ic.UNKNOWN_TYPE),
        (3, "subscribe", topic, "Float64", "data", ic.UNKNOWN_TYPE),
        (4, "subscribe", topic, F64, "value", ic.NO_SUCH_FIELD),
        (5, "subscribe", topic, "std_msgs/msg/Int32", "data", ic.TYPE_CLASH),
        (6, "subscribe", "no_slash", F64, "data", ic.BAD_TOPIC),
        (7, "subscribe", "/a//b", F64, "data", ic.BAD_TOPIC),
        (1, "subscribe", topic, F64, "data", ic.CHANNEL_IN_USE),
    ]
    for ch, direction, top, msg_type, fld, code in cases:
        with pytest.raises(ic.Refused) as exc:
            session.bind(ch, direction, top, msg_type, fld)
        assert exc.value.packet.tag == ic.TAG_TOPIC_ERROR
        assert (exc.value.channel, exc.value.code) == (ch, code), exc.value
    # The refused ids are free; "pkg/Type" is normalised in the ack.
    assert session.bind(2, "subscribe", topic, "std_msgs/Float64").field(2) == F64


def test_topic_connect_retransmission_is_idempotent(session: ic.IndependentClient) -> None:
    """Doc 9: the identical request is acked again; the binding is not doubled."""
    topic = new_topic()
    session.bind(1, "subscribe", topic, F64, "data", "udp", via="udp")
    session.bind(1, "subscribe", topic, F64, "data", "udp", via="udp")
    session.bind(1, "subscribe", topic, F64, "data", "udp", via="tcp")
    session.bind(2, "publish", topic, F64)
    session.publish(2, [1.0, 2.0])
    assert session.collect(1, 2) == [1.0, 2.0]
    assert session.stats()["session"]["channels"]["1"]["values_out"] == 2


def test_value_errors(session: ic.IndependentClient) -> None:
    """Doc 7, 10.1, 6.7: BAD_VALUE and UNKNOWN_CHANNEL come as Error with the channel."""
    topic = new_topic()
    session.bind(1, "subscribe", topic, F64)
    session.bind(2, "publish", topic, F64)
    cases = [
        (ic.value(2, 0, 0, "1.0"), ic.BAD_VALUE, 2),
        (ic.value(2, 1, 0, True), ic.BAD_VALUE, 2),
        (ic.batch(2, 2, [0, 0], [1.0, None]), ic.BAD_VALUE, 2),
        (ic.value(9, 0, 0, 1.0), ic.UNKNOWN_CHANNEL, 9),
        (ic.value(1, 0, 0, 1.0), ic.UNKNOWN_CHANNEL, 1),  # a subscribe channel
        ([ic.TAG_TOPIC_CLOSE, 9], ic.UNKNOWN_CHANNEL, 9),
    ]
    for body, code, ch in cases:
        session.send_tcp(body)
        err = session.recv_tag(ic.TAG_ERROR)
        assert (err.field(1), err.field(3)) == (code, ch), err
        # Doc 6.12: field 4 counts the values a BAD_VALUE refused; 0 for other errors.
        assert err.field(4, 0) == (1 if code == ic.BAD_VALUE else 0), err
    # Doc 7: a batch's bad value costs only itself (its good 1.0 was published); integers
    # are widened to float64; the refused values' numbers (0..3) are used up.
    session.send_tcp(ic.value(2, 4, 0, 3))
    got = session.collect(1, 2)
    assert got == [1.0, 3.0]
    assert isinstance(got[1], float)


def test_topic_close_unbinds(session: ic.IndependentClient) -> None:
    """Doc 6.7: TopicClose has no answer; the id is free and values stop."""
    topic = new_topic()
    session.bind(1, "publish", topic, F64)
    session.close_channel(1)
    session.send_tcp(ic.value(1, 0, 0, 1.0))
    assert session.recv_tag(ic.TAG_ERROR).field(1) == ic.UNKNOWN_CHANNEL
    session.bind(1, "subscribe", topic, F64)


def test_sequence_rule_on_the_server(session: ic.IndependentClient) -> None:
    """Doc 10.2: duplicates and stale values dropped, gaps counted as lost, batches cut."""
    topic = new_topic()
    session.bind(1, "subscribe", topic, F64)
    session.bind(2, "publish", topic, F64)
    for seq, val in [(0, 0.0), (5, 5.0), (5, 55.0), (3, 33.0), (6, 6.0)]:
        session.send_tcp(ic.value(2, seq, 0, val))
    session.send_tcp(ic.batch(2, 4, [0] * 5, [40.0, 50.0, 60.0, 7.0, 8.0]))
    session.send_tcp(ic.batch(2, 2, [0] * 3, [20.0, 30.0, 40.0]))
    assert session.collect(1, 5) == [0.0, 5.0, 6.0, 7.0, 8.0]
    ch = session.stats()["session"]["channels"]["2"]
    assert ch["lost"] == 4
    assert ch["values_in"] == 5


def test_empty_batch_delivers_nothing_and_moves_nothing(session: ic.IndependentClient) -> None:
    """Doc 6.9, 10.2: only delivered values advance ``highest``; an empty batch delivers none."""
    topic = new_topic()
    session.bind(1, "subscribe", topic, F64)
    session.bind(2, "publish", topic, F64)
    session.send_tcp(ic.value(2, 0, 0, 0.0))
    session.send_tcp(ic.batch(2, 10, [], []))
    session.send_tcp(ic.value(2, 1, 0, 1.0))
    session.send_tcp(ic.value(2, 11, 0, 11.0))
    assert session.collect(1, 3, timeout=1.0) == [0.0, 1.0, 11.0]


def test_redundancy_repeats_values_in_batches(session: ic.IndependentClient) -> None:
    """Doc 10.1, 10.3: with redundancy k every packet is a Batch repeating k earlier values."""
    topic = new_topic()
    session.bind(1, "subscribe", topic, F64, "data", "udp", redundancy=2)
    session.bind(2, "publish", topic, F64)
    session.publish(2, [1.0, 2.0, 3.0, 4.0])
    assert session.collect(1, 4) == [1.0, 2.0, 3.0, 4.0]
    packets = session.received[1].packets
    assert all(p.tag == ic.TAG_BATCH for p in packets)
    assert [(p.field(2), len(p.field(4))) for p in packets] == [(0, 1), (0, 2), (0, 3), (1, 3)]
    assert session.received[1].filter.duplicates == 5


def test_server_stamps_are_its_own(session: ic.IndependentClient) -> None:
    """Doc 10.1: the server stamps values when it forwards them, one stamp per batch."""
    topic = new_topic()
    session.bind(1, "subscribe", topic, F64)
    session.bind(2, "publish", topic, F64)
    before = time.time_ns()
    session.send_tcp(ic.batch(2, 0, [1, 2, 3], [1.0, 2.0, 3.0]))
    session.collect(1, 3)
    (p,) = session.received[1].packets
    assert p.tag == ic.TAG_BATCH
    assert p.field(2) == 0
    stamps = p.field(3)
    assert len(set(stamps)) == 1
    assert before <= stamps[0] <= time.time_ns()


def test_whole_message_channel(session: ic.IndependentClient) -> None:
    """Doc 7: field nil carries maps with ROS field names; missing fields take defaults."""
    twist = "geometry_msgs/msg/Twist"
    topic = new_topic()
    ack = session.bind(1, "subscribe", topic, twist, None)
    zero = {"x": 0.0, "y": 0.0, "z": 0.0}
    assert ack.field(3) == {"linear": zero, "angular": zero}
    session.bind(2, "publish", topic, twist, None)
    session.bind(3, "subscribe", topic, twist, "angular.z")
    session.publish(2, [{"linear": {"x": 0.5}, "angular": {"z": -0.25}}])
    assert session.collect(1, 1) == [{"linear": {"x": 0.5, "y": 0.0, "z": 0.0},
                                      "angular": {"x": 0.0, "y": 0.0, "z": -0.25}}]
    assert session.collect(3, 1) == [-0.25]
    session.publish(2, [{"linear": {"w": 1.0}}])
    assert session.recv_tag(ic.TAG_ERROR).field(1) == ic.BAD_VALUE


def test_batches_longer_than_a_fixarray(session: ic.IndependentClient) -> None:
    """Doc 5: array16 both ways; the server may split what it sends over UDP (doc 3)."""
    topic = new_topic()
    session.bind(1, "subscribe", topic, F64)
    session.bind(2, "subscribe", topic, F64, "data", "udp")
    session.bind(3, "publish", topic, F64)
    values = [i / 3 for i in range(300)]
    session.publish(3, values, as_batch=True)
    assert session.collect(1, 300) == values
    assert session.collect(2, 300) == values
    assert len(session.received[2].packets) > 1, "300 float64 exceed one 1400-byte datagram"


# -- heartbeats, watchdog, goodbye (doc 8.4, 11) ---------------------------------------------


def test_server_echoes_our_heartbeat(session: ic.IndependentClient) -> None:
    """Doc 11: the server echoes our stamp aged by its holding time: RTT in our clock."""
    assert session.pump(lambda: len(session.rtt_samples_ns) >= 2)
    assert all(0 < s < 500_000_000 for s in session.rtt_samples_ns)
    assert session.stats()["session"]["state"] == "connected"


def test_watchdog_closes_a_silent_session() -> None:
    """Doc 8.4, 11: nothing from the client for timeout_ms: Disconnect(0, watchdog), close."""
    with ServerThread(ServerConfig(port=0, heartbeat_ms=20, timeout_ms=100)) as srv, \
            Client(HOST, srv.port, answer_heartbeats=False) as c:
        start = time.monotonic()  # before the Hello: the server's silence starts later
        ack = c.connect_tcp("silent", with_udp=False)
        bye = c.recv_tag(ic.TAG_DISCONNECT)
        assert bye.field(1) == 0
        assert bye.field(2).startswith("watchdog")
        assert time.monotonic() - start >= ack.timeout_ms / 1000
        assert c.wait_eof()
        assert c.heartbeats_received["tcp"] >= 2


def test_answering_heartbeats_keeps_the_session() -> None:
    """Doc 11: a client heartbeating every period outlives many timeouts."""
    # Four timeouts long; a timeout of 500 ms, not 100, so that a loaded machine's stall of
    # this process is not mistaken for a client that stopped answering.
    with ServerThread(ServerConfig(port=0, heartbeat_ms=50, timeout_ms=500)) as srv, \
            Client(HOST, srv.port) as c:
        c.connect_tcp("alive", with_udp=False)
        assert not c.pump(lambda: c.tcp_eof or any(
            p.tag == ic.TAG_DISCONNECT for p in c.backlog), timeout=2.0)
        assert c.stats()["session"]["state"] == "connected"


def test_shutdown_says_goodbye() -> None:
    """Doc 8.4: the server stopping sends Disconnect(SHUTTING_DOWN) and closes."""
    srv = ServerThread(ServerConfig(port=0)).start()
    try:
        with Client(HOST, srv.port) as c:
            c.connect_tcp("shutdown")
            srv.stop()
            assert c.recv_tag(ic.TAG_DISCONNECT).field(1) == ic.SHUTTING_DOWN
            assert c.wait_eof()
    finally:
        srv.stop()


# -- limits (doc 13) -------------------------------------------------------------------------


def test_limits() -> None:
    """Doc 13.1: max_channels -> TopicError(LIMIT); max_sessions -> ConnectError(LIMIT);
    no UDP on the server -> TopicError(TRANSPORT_DISABLED)."""
    cfg = ServerConfig(port=0, max_channels=2, max_sessions=1, udp=False, max_batch=3)
    with ServerThread(cfg) as srv, Client(HOST, srv.port) as c, Client(HOST, srv.port) as c2:
        ack = c.connect_tcp("limits", with_udp=False)
        assert (ack.max_channels, ack.max_batch) == (2, 3)
        topic = new_topic()
        with pytest.raises(ic.Refused) as exc:
            c.bind(1, "subscribe", topic, F64, "data", "udp")
        assert (exc.value.packet.tag, _code(exc)) == (ic.TAG_TOPIC_ERROR, ic.TRANSPORT_DISABLED)
        c.bind(1, "subscribe", topic, F64)
        c.bind(2, "publish", topic, F64)
        with pytest.raises(ic.Refused) as exc:
            c.bind(3, "subscribe", topic, F64)
        assert (exc.value.packet.tag, _code(exc)) == (ic.TAG_TOPIC_ERROR, ic.LIMIT)
        # max_batch bounds what the server sends: 7 values come as batches of at most 3.
        c.publish(2, [float(i) for i in range(7)], as_batch=True)
        assert c.collect(1, 7) == [float(i) for i in range(7)]
        assert [len(p.field(4)) for p in c.received[1].packets] == [3, 3, 1]
        with pytest.raises(ic.Refused) as exc:
            c2.connect_tcp("one too many", with_udp=False)
        assert (exc.value.packet.tag, _code(exc)) == (ic.TAG_CONNECT_ERROR, ic.LIMIT)


def test_msgpack_subset_round_trip() -> None:
    """Doc 5: every primer row encodes to the bytes the table shows and decodes back."""
    rows = [(7, "07"), (-1, "ff"), (200, "cc c8"), (600, "cd 02 58"),
            (1048576, "ce 00 10 00 00"), (0x0123456789ABCDEF, "cf 01 23 45 67 89 ab cd ef"),
            (-100, "d0 9c"), (-200, "d1 ff 38"), (1.5, "cb 3f f8 00 00 00 00 00 00"),
            (None, "c0"), (False, "c2"), (True, "c3"), ("demo", "a4 64 65 6d 6f"),
            (b"", "c4 00"), ([13], "91 0d"), ({}, "80")]
    for obj, hexa in rows:
        assert ic.packb(obj) == bytes.fromhex(hexa), obj
        assert ic.unpackb(bytes.fromhex(hexa)) == obj
    for obj in [-(2**63), 2**64 - 1, -40000, -(2**31), "é" * 200, "x" * 70000, list(range(70000)),
                {str(i): i for i in range(20)}, b"\x00" * 300]:
        assert ic.unpackb(ic.packb(obj)) == obj
    assert ic.unpackb(b"\xca" + struct.pack(">f", 0.5)) == 0.5


def test_client_uses_only_the_standard_library() -> None:
    """The client must be independent of rlbridge and msgspec: only stdlib imports."""
    import ast

    tree = ast.parse((HERE / "independent_client.py").read_text())
    roots = {alias.name.split(".")[0] for node in ast.walk(tree)
             if isinstance(node, ast.Import) for alias in node.names}
    roots |= {node.module.split(".")[0] for node in ast.walk(tree)
              if isinstance(node, ast.ImportFrom) and node.module}
    assert roots <= set(sys.stdlib_module_names), roots - set(sys.stdlib_module_names)


# -- bundles (doc 6.16) ----------------------------------------------------------------------


@pytest.mark.parametrize("via", ["udp", "tcp"])
def test_bundle_delivers_its_good_parts_and_answers_each_bad_one(
        session: ic.IndependentClient, via: str) -> None:
    """Doc 6.16: a bad part (unknown channel, wrong value, not a packet) loses only itself."""
    topic = new_topic()
    session.bind(1, "subscribe", topic, F64)
    session.bind(2, "publish", topic, F64)
    session.send(ic.bundle(
        ic.value(2, 0, 0, 1.0),
        ic.value(9, 0, 0, 1.0),  # not bound: UNKNOWN_CHANNEL
        ic.value(2, 1, 0, "x"),  # not a float: BAD_VALUE
        ic.batch(2, 2, [0], [2.0, 3.0]),  # two values, one stamp
        [ic.TAG_HEARTBEAT, 5],  # not a value packet
        ic.batch(2, 4, [0, 0], [4.0, 5.0]),
    ), via)
    assert session.collect(1, 3) == [1.0, 4.0, 5.0]
    errors = {(e.field(1), e.field(3)) for e in
              (session.recv_tag(ic.TAG_ERROR, via=via) for _ in range(4))}
    assert errors == {(ic.UNKNOWN_CHANNEL, 9), (ic.BAD_VALUE, 2), (ic.MALFORMED, 2),
                      (ic.MALFORMED, 5)}


@pytest.mark.parametrize("flags", [0, ic.FLAG_BUNDLES])
def test_server_bundles_only_for_a_client_that_reads_them(session: ic.IndependentClient,
                                                          flags: int) -> None:
    """Doc 3, 6.16: ten values out in one loop iteration: one bundle, or ten plain datagrams
    to a client that has not set FLAG_BUNDLES (old single packets, both ways)."""
    session.udp_flags = flags
    topics = [new_topic() for _ in range(10)]
    for i, topic in enumerate(topics):
        session.bind(10 + i, "subscribe", topic, F64, "data", "udp")
        session.bind(20 + i, "publish", topic, F64)
    session.udp_tags.clear()
    # One bundle in: the server handles its ten parts in one go, so their echoes leave
    # together.
    session.send_udp(ic.bundle(*(ic.value(20 + i, 0, 0, float(i)) for i in range(10))))
    for i in range(10):
        assert session.collect(10 + i, 1) == [float(i)]
    value_tags = [t for t in session.udp_tags if t in (ic.TAG_VALUE, ic.TAG_BATCH,
                                                       ic.TAG_BUNDLE)]
    assert value_tags == ([ic.TAG_BUNDLE] if flags else [ic.TAG_VALUE] * 10)
