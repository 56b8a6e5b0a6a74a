"""Write the seed corpus: valid packets of every type plus the known bad cases.

Run: ``python fuzz/make_corpus.py`` (rewrites ``fuzz/corpus/decoder`` and ``fuzz/corpus/server``;
file names are content hashes, so running it twice changes nothing). The first byte of every
seed is the harness's mode byte (chunking for the decoder; keyed, raw and chunking for the
server, see the harnesses' docstrings).
"""

from __future__ import annotations

import hashlib
import shutil
from collections.abc import Iterator
from pathlib import Path

import msgspec

from rlbridge.wire import (
    DATAGRAM_HEADER,
    FRAME_HEADER,
    MAGIC,
    PROTOCOL_VERSION,
    AuthChallenge,
    AuthProof,
    Batch,
    Bundle,
    ChannelLoss,
    ConnectAck,
    ConnectError,
    Credit,
    Disconnect,
    Error,
    GoalCancel,
    GoalResult,
    GoalSend,
    Heartbeat,
    Hello,
    Limits,
    LossReport,
    Packet,
    PacketCodec,
    RosLoss,
    ServiceCall,
    ServiceOffer,
    ServiceReply,
    ServiceRequest,
    ServiceResult,
    Stats,
    TopicAck,
    TopicClose,
    TopicConnect,
    TopicError,
    Value,
)
from rlbridge.wire.auth import SealedCodec
from rlbridge.wire.records import RecordSealer

HERE = Path(__file__).parent / "corpus"
F64 = "std_msgs/msg/Float64"
SET_BOOL = "std_srvs/srv/SetBool"
CODEC = PacketCodec()

EVERY_TYPE: list[Packet] = [
    Hello(PROTOCOL_VERSION, "seed", b"n" * 16),
    ConnectAck(1, 2, 200, 600, Limits(1 << 20, 256, 4096)),
    ConnectAck(1, 2, 200, 600, Limits(1 << 20, 256, 4096), bytes(range(32))),  # over TLS
    ConnectError(21, "no"),
    TopicConnect(1, "publish", "/a", F64),
    TopicAck(1, F64, 0.0),
    TopicError(1, 10, "no"),
    TopicClose(1),
    Value(1, 0, 0, 1.5),
    Batch(1, 0, [0, 0], [1.0, 2.0]),
    Heartbeat(1, 0),
    Disconnect(0, "bye"),
    Error(2, "bad", 1),
    Stats(),
    AuthChallenge(b"n" * 16, b"p" * 32),
    AuthProof(b"p" * 32),
    Bundle([Value(1, 0, 0, 1.5), Batch(2, 0, [0, 0], [1.0, 2.0])]),
    Credit(2, 64),
    LossReport([ChannelLoss(1, 10, 2, 12, 0), ChannelLoss(3, 0, 0, 0, 5)]),
    TopicConnect(4, "subscribe", "/a", F64, buffer_size=8, flow=True),
    TopicAck(5, F64, 0.0, credit=4096),
    ServiceCall(1, "/s", SET_BOOL, {"data": True}, 50),
    ServiceResult(1, 0, {"success": True, "message": ""}),
    ServiceOffer(4, "/s", SET_BOOL),
    ServiceRequest(4, 1, {"data": True}),
    ServiceReply(4, 1, 0, {"success": True}),
    GoalSend(5, "/fib", "test_msgs/action/Fibonacci", {"order": 3}, 50),
    GoalCancel(5),
    GoalResult(5, 4, {"sequence": [0, 1]}),
    RosLoss(2, 3),
]

#: A session's life as a client drives it: publish and subscribe on both transports.
SESSION: list[Packet] = [
    TopicConnect(1, "publish", "/a", F64),
    TopicConnect(2, "subscribe", "/a", F64, transport="udp"),
    TopicConnect(3, "publish", "/m", "geometry_msgs/msg/Twist", None),
    Value(1, 0, 0, 1.5),
    Batch(1, 1, [0, 0, 0], [1.0, 2.0, 3.0]),
    Value(3, 0, 0, {"linear": {"x": 1.0}}),
    Bundle([Value(1, 4, 0, 4.0), Value(3, 1, 0, {"angular": {"z": 0.5}}),
            Batch(1, 5, [0, 0], [5.0, 6.0])]),
    TopicConnect(4, "subscribe", "/f", F64, buffer_size=4, flow=True),
    TopicConnect(5, "publish", "/f", F64, flow=True, loss_report=True),
    Batch(5, 0, [0] * 6, [1.0] * 6),
    Credit(4, 8),
    Credit(4, 2),  # old news
    Credit(1, 9),  # not a flow-controlled subscription
    LossReport([ChannelLoss(5, 1, 0, 1)]),  # a server's packet, from a client
    Heartbeat(5, 0),
    Stats(),
    ServiceOffer(4, "/s", SET_BOOL),
    ServiceCall(1, "/nobody", SET_BOOL, {"data": True}, 20),
    ServiceCall(2, "/s", "std_srvs/srv/Nope", {}, 20),
    ServiceReply(4, 99, 0, {"success": True}),  # no such request
    GoalSend(5, "/fib", "test_msgs/action/Fibonacci", {"order": 3}, 20),
    GoalCancel(9),
    TopicClose(4),
    TopicClose(2),
    Disconnect(0, "bye"),
]


def frame(body: bytes, length: int | None = None, magic: bytes = MAGIC,
          version: int = PROTOCOL_VERSION) -> bytes:
    return FRAME_HEADER.pack(magic, version, 0, len(body) if length is None else length) + body


def body(*fields: object) -> bytes:
    return msgspec.msgpack.encode(list(fields))


#: Known bad inputs (each a byte string the server or decoder must survive).
BAD: list[bytes] = [
    frame(b"\xc1"),  # invalid msgpack
    frame(b""),  # empty body
    frame(body(99, 1)),  # unknown packet type
    frame(body(8, 1, 0, 0)),  # Value missing its value
    frame(body(8, 1, "seq", 0, 1.0)),  # wrong kind
    frame(body(8, 77, 0, 0, 1.0)),  # unknown channel
    frame(body(8, 1, 0, 0, "not a float")),  # wrong value kind for the channel
    frame(body(9, 1, 0, [0], [1.0, 2.0])),  # batch stamps/values mismatch
    frame(body(4, 5, "publish", "/" + "x" * 2000, F64)),  # huge topic name
    frame(body(1, 1, "n" * 3000)),  # huge string (under the harness max_packet)
    frame(b"\x91" * 3000 + b"\x01"),  # deeply nested arrays
    frame(b"", length=0xFFFF_FFFF),  # absurd length
    frame(body(10, 1, 0))[:-2],  # truncated frame
    frame(body(10, 1, 0), magic=b"GE"),  # bad magic (an HTTP client)
    frame(body(10, 1, 0), version=9),  # unsupported version
    b"GET / HTTP/1.1\r\nHost: x\r\n\r\n",
    frame(body(15, b"x" * 31)),  # proof of the wrong size
    frame(body(13, {"k" * 10: [1] * 1000})),  # stats with a big body
    # Bundles: bad parts (unknown channel, wrong value kind, a mismatched batch, not a
    # packet, a nested bundle) next to good ones; parts that are not an array.
    frame(body(32, [[8, 1, 10, 0, 1.0], [8, 77, 0, 0, 1.0], [8, 1, 11, 0, "x"],
                    [9, 1, 12, [0], [1.0, 2.0]], "junk", [32, []], [8, 1, 13, 0, 2.0]])),
    frame(body(32, "not a list")),
    frame(body(32)),
    frame(body(32, [[8] * 3] * 200)),
    frame(body(34, 1, -5)),  # negative credit
    frame(body(35, [[1, 2, 3, 4]] * 300)),  # a loss report over its 256 channels
    frame(body(35, [[1, "x", 3, 4]])),  # a loss report with a bad count
    b"\x16\x03\x01\x00\xc8\x01\x00\x00\xc4\x03\x03" + bytes(32),  # a TLS ClientHello
    b"\x15\x03\x03\x00\x02\x02\x46",  # a TLS alert
    FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 1, 40) + bytes(40),  # a record that won't open
    FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 1, 0xFFFF_FFFF),  # an absurd record
    frame(body(20, 1, "/s", SET_BOOL, [1, 2])),  # a service request that is not a map
    frame(body(20, 1, "", SET_BOOL, {})),  # empty service name
    frame(body(24, 4, 1, 0, {"success": "very"})),  # a reply that does not fit
    frame(body(25, 5, "/fib", "x", {"order": 1}, -1)),  # negative timeout
    frame(body(27, 5, 4, {})),  # a server-only packet from a client
    frame(body(28, 2, -3)),  # negative loss
]


def datagram(packet: Packet, token: int = 0) -> bytes:
    return CODEC.encode_datagram(packet, token)


def decoder_seeds() -> Iterator[bytes]:
    sealed = SealedCodec(bytes(range(32)), bytes(32))  # the harness opens with the reverse
    for packet in EVERY_TYPE:
        yield b"\x00" + CODEC.encode_frame(packet)
        yield b"\x00" + datagram(packet, 7)
        yield b"\x00" + sealed.encode_datagram(packet, 7)
    yield b"\x03" + b"".join(CODEC.encode_frame(p) for p in EVERY_TYPE)
    for bad in BAD:
        yield b"\x00" + bad
        yield b"\x05" + bad
    yield b"\x00" + DATAGRAM_HEADER.pack(MAGIC, PROTOCOL_VERSION, 1, 7)
    # Sealed TCP records the harness opens (its stream key), whole, tampered, out of order.
    frames = b"".join(CODEC.encode_frame(p) for p in EVERY_TYPE)
    sealer = RecordSealer(bytes(range(32)))
    first, second = sealer.seal(frames[:200]), sealer.seal(frames[200:])
    for mode in (b"\x00", b"\x01", b"\x07"):
        yield mode + first + second
        yield mode + second + first
        yield mode + first + first
        yield mode + first[:-1] + bytes([first[-1] ^ 1]) + second
        yield mode + first + CODEC.encode_frame(Stats())  # a plain frame injected after
        yield mode + first[:50]


def server_seeds() -> Iterator[bytes]:
    session = b"".join(CODEC.encode_frame(p) for p in SESSION)
    for mode in (0, 1, 8 | 0, 8 | 1):  # plain and keyed; whole and chunked
        yield bytes([mode]) + session
        for packet in SESSION:
            yield bytes([mode | 4]) + datagram(packet, 1)  # as a datagram with the live token
        for bad in BAD:
            yield bytes([mode]) + CODEC.encode_frame(SESSION[0]) + bad
    for raw in (2, 3):  # no hello first: the handshake paths themselves
        yield bytes([raw]) + CODEC.encode_frame(Hello(PROTOCOL_VERSION, "x", b"n" * 16))
        yield bytes([raw]) + CODEC.encode_frame(AuthProof(b"p" * 32))
        yield bytes([raw]) + CODEC.encode_frame(Value(1, 0, 0, 1.0))
        yield bytes([raw | 4]) + datagram(Hello(PROTOCOL_VERSION, "udp", b"n" * 16))
        yield bytes([raw | 4]) + datagram(AuthProof(b"p" * 32))


def write(name: str, seeds: Iterator[bytes]) -> int:
    target = HERE / name
    shutil.rmtree(target, ignore_errors=True)
    target.mkdir(parents=True)
    count = 0
    for seed in seeds:
        (target / hashlib.sha1(seed).hexdigest()).write_bytes(seed)
        count += 1
    return count


def main() -> None:
    print("decoder seeds:", write("decoder", decoder_seeds()))
    print("server seeds:", write("server", server_seeds()))


if __name__ == "__main__":
    main()
