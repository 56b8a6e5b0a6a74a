"""Fuzz the server's packet handling in-process: TCP connections and the UDP endpoint.

Run: ``python fuzz/fuzz_server.py fuzz/corpus/server -max_total_time=60``. Each input drives
a real :class:`~rlbridge.server.tcp.TcpConnection` and :class:`~rlbridge.server.udp.UdpEndpoint`
over an in-memory transport (the only stand-in: no socket), on a server with the in-process
bus, with and without pre-shared keys. The first byte picks the mode; the session is opened
properly (hello, and the key handshake in keyed mode) unless the mode says raw, then the rest
is fed as TCP chunks and as datagrams carrying the live token (in keyed mode also sealed
with the session's keys, so the bytes get past the seal into the sealed session's decoding;
over TCP, odd-length inputs go in sealed records and even-length ones raw, as if injected).
Invariants checked per input: nothing but the server's own handling runs (any exception is a
finding), everything the server writes is valid protocol, and once the sessions close no
binding or topic is left behind.
"""

from __future__ import annotations

import asyncio
from typing import Any

from _atheris import fuzz, instrumented

with instrumented(__name__ == "__main__"):
    from rlbridge.adapters.inproc import InProcessBus
    from rlbridge.server.access import AllowList, KeyStore
    from rlbridge.server.config import ServerConfig
    from rlbridge.server.handoff import LoopHandoff
    from rlbridge.server.registry import SessionRegistry
    from rlbridge.server.session import ServerContext
    from rlbridge.server.tcp import TcpConnection
    from rlbridge.server.udp import UdpEndpoint
    from rlbridge.wire import (
        PROTOCOL_VERSION,
        AuthChallenge,
        FrameDecoder,
        Hello,
        Malformed,
        PacketCodec,
    )
    from rlbridge.wire.auth import ClientHandshake, SealedCodec, sealed_codec
    from rlbridge.wire.codec import DATAGRAM_HEADER, FLAG_MAC, peek_header
    from rlbridge.wire.records import (
        RecordOpener,
        RecordSealer,
        SealedStreamDecoder,
        stream_sealers,
    )

KEY = bytes(range(32))
PEER = ("127.0.0.1", 40000)


class MemoryTransport(asyncio.Transport, asyncio.DatagramTransport):
    """Collects what the server writes; enough of both transport APIs for the protocols."""

    def __init__(self) -> None:
        super().__init__()
        self.out = bytearray()
        self.datagrams: list[bytes] = []
        self.closing = False

    def get_extra_info(self, name: str, default: Any = None) -> Any:
        return PEER if name == "peername" else default

    def write(self, data: Any) -> None:
        self.out += data

    def sendto(self, data: Any, addr: Any = None) -> None:
        self.datagrams.append(bytes(data))

    def close(self) -> None:
        self.closing = True

    def is_closing(self) -> bool:
        return self.closing

    def get_write_buffer_size(self) -> int:
        return 0

    def set_write_buffer_limits(self, high: int | None = None, low: int | None = None) -> None:
        pass

    def pause_reading(self) -> None:
        pass

    def resume_reading(self) -> None:
        pass


class World:
    """One in-process server (keyed or not) reused across inputs."""

    def __init__(self, keyed: bool) -> None:
        self.loop = asyncio.new_event_loop()
        config = ServerConfig(port=0, max_packet=4096, max_channels=8, max_sessions=8,
                              max_rate=1000.0 if keyed else None, timeout_ms=600_000)
        self.bus = InProcessBus()
        self.ctx = ServerContext(config, self.bus, PacketCodec(), self.loop,
                                 LoopHandoff(self.loop), keys=KeyStore(KEY) if keyed else None,
                                 allow=AllowList(()))
        self.registry = SessionRegistry(self.ctx)
        self.udp = UdpEndpoint(self.registry)
        self.udp_transport = MemoryTransport()
        self.udp.connection_made(self.udp_transport)
        self.keyed = keyed

    def run_callbacks(self) -> None:
        self.loop.run_until_complete(asyncio.sleep(0))


WORLDS: dict[bool, World] = {}


def _world(keyed: bool) -> World:
    if keyed not in WORLDS:
        WORLDS[keyed] = World(keyed)
    return WORLDS[keyed]


def close() -> None:
    """Close the worlds' event loops (the test suite calls this after replaying the corpus)."""
    for world in WORLDS.values():
        world.loop.close()
    WORLDS.clear()


class Client:
    """What the fuzzed client holds after opening: its datagram codec, and in keyed mode the
    TCP record sealer and the decoder that opens the server's records."""

    def __init__(self, codec: PacketCodec, sealer: RecordSealer | None = None,
                 decoder: SealedStreamDecoder | None = None) -> None:
        self.codec = codec
        self.sealer = sealer
        self.decoder = decoder


def _open(world: World, conn: TcpConnection, transport: MemoryTransport) -> Client:
    """Hello (and, keyed, the handshake) so the fuzz bytes reach a live session."""
    codec = world.ctx.codec
    handshake = ClientHandshake(KEY, "fuzz", bytes(16)) if world.keyed else None
    conn.data_received(codec.encode_frame(
        Hello(PROTOCOL_VERSION, "fuzz", handshake.nonce if handshake else b"")))
    if handshake is None:
        return Client(codec)
    challenge = FrameDecoder(codec).feed(bytes(transport.out))[0]
    assert isinstance(challenge, AuthChallenge), challenge
    conn.data_received(codec.encode_frame(handshake.answer(challenge)))
    assert handshake.keys is not None
    sealer, opener_key = stream_sealers(handshake.keys, server=False)
    decoder = SealedStreamDecoder(codec, 1 << 24)
    decoder.install(RecordOpener(opener_key), strict=False)
    return Client(sealed_codec(handshake.keys, server=False), sealer, decoder)


def _check_output(world: World, transport: MemoryTransport, client: Client) -> None:
    """Everything the server wrote decodes: frames or records, and datagrams (sealed ones
    open)."""
    decoder = client.decoder or FrameDecoder(world.ctx.codec, 1 << 24)
    for packet in decoder.feed(bytes(transport.out)):
        assert not isinstance(packet, Malformed), packet
    for data in world.udp_transport.datagrams:
        flags, _token = peek_header(data)
        (client.codec if flags & FLAG_MAC else world.ctx.codec).decode_datagram(data)
    world.udp_transport.datagrams.clear()


def one_input(data: bytes) -> None:
    if not data:
        return
    mode, body = data[0], data[1:]
    world = _world(keyed=bool(mode & 1))
    transport = MemoryTransport()
    conn = TcpConnection(world.registry)
    conn.connection_made(transport)
    client = Client(world.ctx.codec) if mode & 2 else _open(world, conn, transport)
    step = (mode >> 3) % 31 + 1
    sessions = list(world.registry)
    # Keyed: odd-length inputs go in sealed records (past the seal, into the session's
    # decoding), even-length ones raw (bytes injected into a sealed stream: refused).
    sealer = client.sealer if len(body) % 2 else None
    for i in range(0, len(body), step):
        if transport.closing:
            break
        chunk = body[i : i + step]
        conn.data_received(sealer.seal(chunk) if sealer is not None else chunk)
    # The same bytes as datagrams: from a stranger, and with a live session's token.
    if mode & 4 and len(body) >= DATAGRAM_HEADER.size:
        world.udp.datagram_received(body, PEER)
        for session in sessions:
            patched = bytearray(body)
            patched[4:12] = session.token.to_bytes(8, "big")
            world.udp.datagram_received(bytes(patched), PEER)
            if isinstance(client.codec, SealedCodec):  # past the seal: the session's decoding
                world.udp.datagram_received(client.codec.seal_body(body[12:], session.token),
                                            PEER)
    world.run_callbacks()
    _check_output(world, transport, client)
    conn.connection_lost(None)
    for session in world.registry:
        session.close("fuzz input done", notify=False)
    world.run_callbacks()
    assert len(world.registry) == 0, "a session outlived its connection"
    assert world.bus.topics() == [], world.bus.topics()


if __name__ == "__main__":
    fuzz(one_input)
