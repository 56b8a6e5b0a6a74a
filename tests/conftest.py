"""Shared fixtures for the wire, server, client and CLI tests.

Everything here is real: servers listen on loopback ports, raw clients speak the protocol with
the sans-IO codec over real sockets, CLI commands run as real processes. Waits are bounded
(a deadline, or an event with a timeout); nothing sleeps for a fixed time hoping for the best.

Helpers are handed to tests through fixtures (tests import nothing from this file):

* ``server`` / ``make_server``: a :class:`~rlbridge.server.ServerThread` on port 0.
* ``raw_tcp`` / ``raw_udp``: factories of protocol-level clients (:class:`RawTcp`,
  :class:`RawUdp`) that send packets and wait for answers, skipping heartbeats.
* ``bridge``: a factory of SDK ``Bridge`` objects, all closed at teardown.
* ``cli``: runs the ``rlbridge`` command as a subprocess (``cli.run``, ``cli.popen``).
* ``cli_server`` / ``shared_cli_server``: ``rlbridge serve`` processes, ready to use.
* ``wait_until``, ``free_port``, ``stats_over_tcp``, ``topics_of``: small bounded helpers.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Protocol, TypeVar

import pytest

from localhost import free_port, rlbridge_command
from log_handlers import on_closed_streams
from rlbridge.client.bridge import Bridge
from rlbridge.server import ServerConfig, ServerThread
from rlbridge.wire import (
    PROTOCOL_VERSION,
    AuthChallenge,
    ConnectAck,
    ConnectError,
    Disconnect,
    FrameDecoder,
    Heartbeat,
    Hello,
    Malformed,
    Packet,
    PacketCodec,
    Stats,
)
from waiting import WAIT, assert_running, wait_until

P = TypeVar("P")


#: Heartbeat and watchdog of the default test server: a heartbeat fast enough that link
#: changes show up quickly, a watchdog slow enough that a busy CI machine never trips it.
TEST_HEARTBEAT_MS = 100
TEST_TIMEOUT_MS = 5000


# -- logging -------------------------------------------------------------------------------


@pytest.fixture(autouse=True)
def _no_log_handler_on_a_closed_stream() -> Iterator[None]:
    """Fail the test that leaves a handler writing to a closed stream, and take it off.

    Left there, it makes every later record of the process a ``--- Logging error ---``
    traceback printed under some other test (tests/log_handlers.py); a few attribute reads.
    """
    yield
    left = on_closed_streams()
    for logger, handler in left:
        logger.removeHandler(handler)
    if left:
        pytest.fail("a logging handler is left writing to a closed stream: "
                    + "; ".join(f"{logger.name}: {handler!r}" for logger, handler in left))


# -- servers -------------------------------------------------------------------------------


@pytest.fixture
def make_server() -> Iterator[Callable[..., ServerThread]]:
    """``make_server(**config)``: a started server on port 0, stopped at teardown."""
    started: list[ServerThread] = []

    def make(**overrides: Any) -> ServerThread:
        options: dict[str, Any] = {
            "port": 0, "heartbeat_ms": TEST_HEARTBEAT_MS, "timeout_ms": TEST_TIMEOUT_MS,
        }
        options.update(overrides)
        srv = ServerThread(ServerConfig(**options)).start()
        started.append(srv)
        return srv

    yield make
    for srv in reversed(started):
        srv.stop()


@pytest.fixture
def server(make_server: Callable[..., ServerThread]) -> ServerThread:
    """A server with the in-process bus, TCP and UDP, on a free port."""
    return make_server()


# -- raw protocol clients ------------------------------------------------------------------


class RawTcp:
    """A protocol-level TCP client: frames out, packets in, no SDK in between."""

    def __init__(self, port: int, host: str = "127.0.0.1") -> None:
        self.codec = PacketCodec()
        self.sock = socket.create_connection((host, port), timeout=WAIT)
        self.decoder = FrameDecoder(self.codec)
        self.pending: list[Packet | Malformed] = []
        self.eof = False
        self.ack: ConnectAck | None = None

    def send(self, *packets: Packet) -> None:
        buf = bytearray()
        for packet in packets:
            self.codec.encode_frame_into(packet, buf)
        self.sock.sendall(buf)

    def send_bytes(self, data: bytes) -> None:
        self.sock.sendall(data)

    def _fill(self, deadline: float) -> bool:
        """Read once; False when the deadline passed or the peer closed."""
        if self.eof:
            return False
        left = deadline - time.monotonic()
        if left <= 0:
            return False
        self.sock.settimeout(left)
        try:
            data = self.sock.recv(1 << 16)
        except TimeoutError:
            return False
        except ConnectionResetError:
            data = b""
        if not data:
            self.eof = True
            return False
        self.pending.extend(self.decoder.feed(data))
        return True

    def recv(self, timeout: float = WAIT, *, skip: tuple[type, ...] = (Heartbeat,)) -> Packet:
        """The next packet that is not of a ``skip`` type; fails the test on timeout or EOF."""
        deadline = time.monotonic() + timeout
        while True:
            while self.pending:
                packet = self.pending.pop(0)
                assert not isinstance(packet, Malformed), f"server sent garbage: {packet}"
                if not isinstance(packet, skip):
                    return packet
            if not self._fill(deadline):
                state = "closed the connection" if self.eof else f"sent nothing in {timeout} s"
                raise AssertionError(f"expected a packet, but the server {state}")

    def expect(self, cls: type[P], timeout: float = WAIT) -> P:
        """The next non-heartbeat packet, which must be a ``cls``."""
        packet = self.recv(timeout)
        assert isinstance(packet, cls), f"expected {cls.__name__}, got {packet!r}"
        return packet

    def hello(self, name: str = "raw-tcp") -> ConnectAck:
        self.send(Hello(PROTOCOL_VERSION, name))
        self.ack = self.expect(ConnectAck)
        return self.ack

    def stats(self) -> dict[str, Any]:
        """Ask for the server's counters; skips whatever else arrives first."""
        self.send(Stats())

        def answer() -> dict[str, Any] | None:
            packet = self.recv()  # fails the test by itself when nothing comes
            return packet.body if isinstance(packet, Stats) else None

        body: dict[str, Any] = wait_until(answer, "the server's Stats answer", interval=0)
        return body

    def wait_closed(self, timeout: float = WAIT) -> list[Packet]:
        """Read until the server closes the connection; return what came before the EOF."""
        deadline = time.monotonic() + timeout
        while self._fill(deadline):
            pass
        assert self.eof, f"server did not close the connection within {timeout} s"
        got = [p for p in self.pending if not isinstance(p, Malformed)]
        self.pending.clear()
        return got

    def close(self) -> None:
        self.sock.close()


class RawUdp:
    """A protocol-level UDP client: one connected socket, datagrams with a session token."""

    def __init__(self, port: int, host: str = "127.0.0.1") -> None:
        self.codec = PacketCodec()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.connect((host, port))
        self.token = 0
        self.ack: ConnectAck | None = None

    def send(self, packet: Packet, token: int | None = None) -> None:
        self.sock.send(self.codec.encode_datagram(packet, self.token if token is None else token))

    def send_bytes(self, data: bytes) -> None:
        self.sock.send(data)

    def recv_datagram(self, timeout: float = WAIT) -> tuple[int, Packet]:
        """``(token, packet)`` of the next datagram; fails the test on timeout."""
        self.sock.settimeout(timeout)
        try:
            data = self.sock.recv(1 << 16)
        except TimeoutError:
            raise AssertionError(f"no datagram within {timeout} s") from None
        _flags, token, packet = self.codec.decode_datagram(data)
        return token, packet

    def recv(self, timeout: float = WAIT, *, skip: tuple[type, ...] = (Heartbeat,)) -> Packet:
        """The next packet that is not of a ``skip`` type; fails the test on timeout."""
        def wanted() -> Packet | None:
            _token, packet = self.recv_datagram(timeout)
            return None if isinstance(packet, skip) else packet

        names = ", ".join(cls.__name__ for cls in skip)
        packet: Packet = wait_until(wanted, f"a packet other than {names}", timeout=timeout,
                                    interval=0)
        return packet

    def expect(self, cls: type[P], timeout: float = WAIT) -> P:
        packet = self.recv(timeout)
        assert isinstance(packet, cls), f"expected {cls.__name__}, got {packet!r}"
        return packet

    def hello(self, name: str = "raw-udp") -> ConnectAck:
        self.send(Hello(PROTOCOL_VERSION, name), token=0)
        self.ack = self.expect(ConnectAck)
        self.token = self.ack.token
        return self.ack

    def close(self) -> None:
        with contextlib.suppress(OSError):
            if self.token:
                self.send(Disconnect(0, "test done"))
        self.sock.close()


class _Closes(Protocol):
    def close(self) -> None: ...


C = TypeVar("C", bound=_Closes)


def _clients(make: Callable[[int], C], server: ServerThread) -> Iterator[Callable[..., C]]:
    """A factory of test clients aimed at ``server`` (or a port given), closed at teardown."""
    clients: list[C] = []

    def factory(port: int | None = None) -> C:
        client = make(server.port if port is None else port)
        clients.append(client)
        return client

    yield factory
    for client in clients:
        client.close()


@pytest.fixture
def raw_tcp(server: ServerThread) -> Iterator[Callable[..., RawTcp]]:
    """``raw_tcp(port=None)``: a connected :class:`RawTcp` (to ``server`` by default)."""
    yield from _clients(RawTcp, server)


@pytest.fixture
def raw_udp(server: ServerThread) -> Iterator[Callable[..., RawUdp]]:
    """``raw_udp(port=None)``: a :class:`RawUdp` aimed at ``server`` (or ``port``)."""
    yield from _clients(RawUdp, server)


# -- SDK -----------------------------------------------------------------------------------


@pytest.fixture
def bridge(server: ServerThread) -> Iterator[Callable[..., Bridge]]:
    """``bridge(**connect_kwargs)``: a ``Bridge`` connected to ``server``, closed at teardown."""
    opened: list[Bridge] = []

    def make(**kwargs: Any) -> Bridge:
        kwargs.setdefault("port", server.port)
        kwargs.setdefault("timeout", WAIT)
        b = Bridge.connect("127.0.0.1", **kwargs)
        opened.append(b)
        return b

    yield make
    for b in opened:
        b.close()


@pytest.fixture(name="wait_until")
def wait_until_fixture() -> Callable[..., Any]:
    """:func:`waiting.wait_until`, the one polling helper (a bounded loop with a deadline)."""
    return wait_until


# -- CLI -----------------------------------------------------------------------------------


def _cli_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    env.pop("PYTHONWARNINGS", None)
    env["COLUMNS"] = "200"  # typer/rich would wrap messages at 80 columns
    env["NO_COLOR"] = "1"
    return env


@pytest.fixture(name="free_port")
def free_port_fixture() -> Callable[[], int]:
    return free_port


class CliProcesses:
    """Every ``rlbridge`` process a test starts; killed at teardown if still running."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen[str]] = []

    def popen(self, *args: str) -> subprocess.Popen[str]:
        proc = subprocess.Popen(
            [*rlbridge_command(), *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True, env=_cli_env(),
        )
        self.procs.append(proc)
        return proc

    def run(self, *args: str, timeout: float = 30.0) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [*rlbridge_command(), *args], capture_output=True, text=True, timeout=timeout,
            env=_cli_env(), check=False,
        )

    def cleanup(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.kill()
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.communicate(timeout=WAIT)


@pytest.fixture
def cli() -> Iterator[CliProcesses]:
    """``cli.run(*args)`` -> CompletedProcess; ``cli.popen(*args)`` -> a running process."""
    procs = CliProcesses()
    yield procs
    procs.cleanup()


def wait_server_ready(port: int, proc: subprocess.Popen[str] | None = None,
                      timeout: float = 20.0) -> None:
    """Wait until a server on ``port`` answers a UDP hello, i.e. its loop is serving.

    A UDP handshake (rather than a TCP connect, which the kernel accepts as soon as the socket
    listens) proves that the event loop runs ``serve`` past its setup, signal handlers included.
    """
    codec = PacketCodec()
    hello = codec.encode_datagram(Hello(PROTOCOL_VERSION, "ready-probe"), 0)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.connect(("127.0.0.1", port))
        sock.settimeout(0.1)

        def answered() -> bool:
            try:
                sock.send(hello)
                data = sock.recv(1 << 16)
            except (TimeoutError, ConnectionRefusedError):
                return False
            _flags, _token, packet = codec.decode_datagram(data)
            if isinstance(packet, ConnectAck):
                sock.send(codec.encode_datagram(Disconnect(0, "probe done"), packet.token))
                return True
            return isinstance(packet, ConnectError | AuthChallenge)  # a key or TLS is needed

        wait_until(answered, f"the server on port {port} to answer a hello", timeout=timeout,
                   between=None if proc is None else lambda: assert_running(proc))


def start_cli_server(procs: CliProcesses, *extra: str) -> tuple[int, subprocess.Popen[str]]:
    """``rlbridge serve --port P *extra`` on a free port P, returned once it serves.

    At ``--log-level warning`` unless ``extra`` says otherwise: the default (info) logs every
    session, and nobody reads the stderr pipe of a long-lived test server until it stops.
    With ``--timeout-ms TEST_TIMEOUT_MS`` unless ``extra`` says otherwise: a loaded CI machine
    can starve a client for longer than the default 600 ms watchdog, and the watchdog is not
    what these servers test (tests of the default watchdog pass ``--timeout-ms`` themselves).
    """
    if "--log-level" not in extra:
        extra = (*extra, "--log-level", "warning")
    if "--timeout-ms" not in extra:  # the watchdog of every test server unless a test asks
        extra = (*extra, "--timeout-ms", str(TEST_TIMEOUT_MS))
    last: AssertionError | None = None
    for _ in range(3):  # the free port may be taken between probing and binding
        port = free_port()
        proc = procs.popen("serve", "--port", str(port), *extra)
        try:
            wait_server_ready(port, proc)
        except AssertionError as exc:
            last = exc
            if proc.poll() is None:
                proc.kill()
            proc.communicate(timeout=WAIT)
            continue
        return port, proc
    raise AssertionError(f"could not start rlbridge serve: {last}")


def stop_cli_server(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.communicate(timeout=WAIT)


@pytest.fixture
def cli_server(cli: CliProcesses) -> Iterator[Callable[..., tuple[int, subprocess.Popen[str]]]]:
    """``cli_server(*extra_args)``: a fresh ``rlbridge serve --port P``, running and ready."""
    servers: list[subprocess.Popen[str]] = []

    def start(*extra: str) -> tuple[int, subprocess.Popen[str]]:
        port, proc = start_cli_server(cli, *extra)
        servers.append(proc)
        return port, proc

    yield start
    for proc in servers:
        stop_cli_server(proc)


@pytest.fixture(scope="module")
def shared_cli_server() -> Iterator[int]:
    """The port of one ``rlbridge serve`` shared by a module's tests (use unique topics)."""
    procs = CliProcesses()
    port, proc = start_cli_server(procs)
    yield port
    stop_cli_server(proc)
    procs.cleanup()


def stats_over_tcp(port: int) -> dict[str, Any]:
    """The server's Stats body, asked for by a short raw TCP session."""
    client = RawTcp(port)
    try:
        client.hello("stats-probe")
        return client.stats()
    finally:
        with contextlib.suppress(OSError):
            client.send(Disconnect(0, "probe done"))
        client.close()


@pytest.fixture(name="stats_over_tcp")
def stats_over_tcp_fixture() -> Callable[[int], dict[str, Any]]:
    return stats_over_tcp


def topics_of(port: int) -> Sequence[str]:
    return [name for name, _type in stats_over_tcp(port)["topics"]]


@pytest.fixture(name="topics_of")
def topics_of_fixture() -> Callable[[int], Sequence[str]]:
    return topics_of
