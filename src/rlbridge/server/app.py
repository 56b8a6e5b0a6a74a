"""The server's lifetime: bind, serve, shut down in order (uvicorn's shape).

``Server(config).run()`` is what the CLI calls; ``ServerThread`` runs the same server in a
background thread for tests, benchmarks and examples, with port 0 allowed.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Any

from rlbridge.adapters import MiddlewareAdapter, load_adapter
from rlbridge.server.access import AllowList
from rlbridge.server.access import load as load_keys
from rlbridge.server.authz import Access
from rlbridge.server.config import ServerConfig, is_loopback
from rlbridge.server.context import ServerContext
from rlbridge.server.handoff import LoopHandoff
from rlbridge.server.metrics import MetricsEndpoint
from rlbridge.server.notices import bind_failure, listening_line
from rlbridge.server.registry import SessionRegistry
from rlbridge.server.runner import run_on_loop
from rlbridge.server.tcp import TcpConnection
from rlbridge.server.udp import UdpEndpoint
from rlbridge.tls import TlsError, server_context
from rlbridge.wire import PacketCodec
from rlbridge.wire.aead import NoCipher
from rlbridge.wire.aead import require as require_cipher

log = logging.getLogger("rlbridge.server")


class ServerError(RuntimeError):
    """The server cannot start (port in use, adapter unavailable); the message says why."""


@dataclass(frozen=True)
class BoundAddress:
    """Where a started server listens (``Server.address``); ``port`` is the real one."""
    host: str
    port: int
    tcp: bool
    udp: bool
    metrics_port: int | None = None
    metrics_host: str | None = None


def new_event_loop(use_uvloop: bool = True) -> asyncio.AbstractEventLoop:
    """uvloop when installed and wanted, else asyncio's; chosen per loop, no global policy."""
    if use_uvloop:
        try:
            import uvloop
        except ImportError:
            pass
        else:
            loop: asyncio.AbstractEventLoop = uvloop.new_event_loop()
            return loop
    return asyncio.new_event_loop()


class Server:
    """The bridge server: owns listeners, sessions and adapter; ``serve`` returns when stopped."""

    def __init__(self, config: ServerConfig, adapter: MiddlewareAdapter | None = None) -> None:
        self.config = config
        self._adapter = adapter
        self._stop: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.registry: SessionRegistry | None = None
        self.address: BoundAddress | None = None

    def run(self) -> None:
        """Serve until SIGINT/SIGTERM; the CLI's entry point."""
        run_on_loop(self.serve(install_signal_handlers=True),
                    lambda: new_event_loop(self.config.use_uvloop))

    def stop(self) -> None:
        """Ask a running server to shut down; safe from any thread."""
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None:
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(stop.set)

    async def serve(
        self,
        *,
        install_signal_handlers: bool = False,
        started: Callable[[BoundAddress], None] | None = None,
    ) -> None:
        """Serve on the running loop until :meth:`stop`; embed it in your own asyncio program."""
        loop = asyncio.get_running_loop()
        self._loop = loop
        self._stop = asyncio.Event()
        cfg = self.config
        try:  # before the adapter and the sockets: a bad key file is the operator's to fix
            keys, entries = load_keys(cfg.psk_file)
            tls = (server_context(cfg.tls_cert, cfg.tls_key, cfg.tls_client_ca)
                   if cfg.tls_cert is not None and cfg.tls_key is not None else None)
            if keys is not None or tls is not None:
                require_cipher()  # its sessions seal: refuse now, not at the first client
        except (ValueError, TlsError, NoCipher) as exc:
            raise ServerError(str(exc)) from None
        await _resolvable(loop, cfg.host)
        exposed = not cfg.loopback and keys is None and tls is None
        if exposed and not cfg.insecure:
            raise ServerError(
                f"refusing to listen on {cfg.host} without TLS or a key: anyone who can reach "
                "it could read and write your topics; give --psk-file (or $RLBRIDGE_PSK) or "
                "--tls-cert and --tls-key, or --insecure to accept that")
        adapter = self._adapter or load_adapter(
            cfg.adapter, node_name=cfg.node_name, namespace=cfg.namespace,
            parameters={"use_tcp": cfg.tcp, "use_udp": cfg.udp, "disable_nagle": cfg.nodelay},
        )
        ctx = ServerContext(cfg, adapter, PacketCodec(), loop, LoopHandoff(loop),
                            keys=keys, allow=AllowList(cfg.allow), tls=tls,
                            access=Access(entries, authenticated=keys is not None
                                          or cfg.tls_client_ca is not None))
        self.registry = registry = SessionRegistry(ctx)
        tcp_server: asyncio.Server | None = None
        udp_transport: asyncio.DatagramTransport | None = None
        metrics: MetricsEndpoint | None = None
        try:
            tcp_server, udp_transport, port = await self._bind(loop, registry)
            if cfg.metrics_port is not None:
                metrics = await _metrics(registry, cfg)
            self.address = BoundAddress(cfg.host, port, tcp_server is not None,
                                        udp_transport is not None,
                                        metrics.port if metrics is not None else None,
                                        cfg.metrics_host if metrics is not None else None)
            if install_signal_handlers:
                for sig in (signal.SIGINT, signal.SIGTERM):
                    loop.add_signal_handler(sig, self._stop.set)
            if exposed:  # said once it is true, next to the line that says where
                log.warning("listening on %s with --insecure: no TLS, no key; anyone who can "
                            "reach it can read and write your topics", cfg.host)
            # After the handlers: whoever sees this line may stop the server with a signal.
            log.info("%s", listening_line(
                cfg.host, port, tcp_server is not None, udp_transport is not None,
                adapter.name, _authentication(keys is not None, tls is not None, cfg),
                self.address.metrics_port, cfg.metrics_host))
            endpoint = udp_transport.get_protocol() if udp_transport is not None else None
            if isinstance(endpoint, UdpEndpoint) and endpoint.receive_buffer is not None:
                # An explicit size the kernel capped is warned about, with the sysctl to raise
                # (docs/load.md); the default takes what it gets without a word.
                grant = endpoint.receive_buffer
                (log.warning if grant.capped and cfg.udp_receive_buffer is not None
                 else log.debug)("%s", grant.describe())
            if started is not None:
                started(self.address)
            await self._stop.wait()
        finally:
            if metrics is not None:
                await metrics.close()
            await self._shutdown(registry, tcp_server, udp_transport)
            ctx.workers.shutdown(wait=False, cancel_futures=True)
            if self._adapter is None:
                adapter.close()
            if install_signal_handlers:
                for sig in (signal.SIGINT, signal.SIGTERM):
                    loop.remove_signal_handler(sig)

    async def _bind(
        self, loop: asyncio.AbstractEventLoop, registry: SessionRegistry
    ) -> tuple[asyncio.Server | None, asyncio.DatagramTransport | None, int]:
        """TCP and UDP on the same port number; with port 0, retry until both get one."""
        cfg = self.config
        last_error = ""
        for _ in range(20 if cfg.port == 0 else 1):
            tcp_server: asyncio.Server | None = None
            port = cfg.port
            what = "TCP"
            try:
                if cfg.tcp:
                    tcp_server = await loop.create_server(
                        lambda: TcpConnection(registry), cfg.host, port, reuse_address=True,
                        family=_family(cfg.host))
                    port = tcp_server.sockets[0].getsockname()[1]
                udp_transport: asyncio.DatagramTransport | None = None
                what = "UDP"
                if cfg.udp:
                    sock = await _bound_udp(loop, cfg.host, port)
                    try:
                        udp_transport, _ = await loop.create_datagram_endpoint(
                            lambda: UdpEndpoint(registry), sock=sock)
                    except BaseException:
                        sock.close()
                        raise
                    port = udp_transport.get_extra_info("sockname")[1]
                return tcp_server, udp_transport, port
            except OSError as exc:
                last_error = bind_failure(what, cfg.host, port, exc)
                if tcp_server is not None:
                    tcp_server.close()
                    await tcp_server.wait_closed()
        raise ServerError(last_error)

    async def _shutdown(
        self,
        registry: SessionRegistry,
        tcp_server: asyncio.Server | None,
        udp_transport: asyncio.DatagramTransport | None,
    ) -> None:
        """Stop accepting, tell every session, close sockets, with a bound on the wait."""
        registry.accepting = False
        if tcp_server is not None:
            tcp_server.close()
        for session in registry:
            session.close("server shutting down", notify=True, code=30)
        for transport in list(registry.ctx.handshaking):
            transport.close()
        await asyncio.sleep(0)  # let transports flush the goodbyes
        if udp_transport is not None:
            udp_transport.close()
            endpoint = udp_transport.get_protocol()
            if isinstance(endpoint, UdpEndpoint):
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(endpoint.closed.wait(), 2.0)
        if tcp_server is not None:
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(tcp_server.wait_closed(), 2.0)
        if self.address is not None:
            log.info("rlbridge stopped: %d session(s) served",
                     registry.ctx.counters.get("sessions_opened", 0))


async def _metrics(registry: SessionRegistry, cfg: ServerConfig) -> MetricsEndpoint:
    """The monitoring endpoint on ``metrics_host`` (loopback unless the operator says else).

    It asks no key: /metrics and /status name every client (its identity) and topic, with
    counters. So it does not follow ``--host``: a keyed or TLS server on 0.0.0.0 would hand
    those to anyone on the network. Elsewhere than loopback only when asked, with a warning.
    """
    assert cfg.metrics_port is not None
    try:
        endpoint = await MetricsEndpoint(registry).start(cfg.metrics_host, cfg.metrics_port)
    except OSError as exc:
        raise ServerError(bind_failure("metrics", cfg.metrics_host, cfg.metrics_port, exc,
                                       option="--metrics-port")) from None
    if not is_loopback(cfg.metrics_host):
        log.warning("metrics on %s: /metrics and /status ask no key; anyone who can reach "
                    "port %d reads every client's name, topic and counters (docs/security.md)",
                    cfg.metrics_host, endpoint.port)
    return endpoint


async def _resolvable(loop: asyncio.AbstractEventLoop, host: str) -> None:
    """Refuse a ``--host`` that names no address before anything says "listening"."""
    try:
        await loop.getaddrinfo(host, None, family=_family(host), flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise ServerError(f"cannot listen on {host}: {exc.strerror or exc}; --host takes an "
                          "address of this machine, or a name that resolves to one; "
                          "0.0.0.0 for all") from None


def _family(host: str) -> socket.AddressFamily:
    """IPv6 for an IPv6 literal, else IPv4: TCP and UDP listen in the same family."""
    return socket.AF_INET6 if ":" in host else socket.AF_INET


async def _bound_udp(loop: asyncio.AbstractEventLoop, host: str, port: int) -> socket.socket:
    """A UDP socket bound to ``host:port``, owned here until the transport takes it.

    Not ``create_datagram_endpoint(local_addr=...)``: when that bind fails (port 0 gave TCP a
    port whose UDP twin is taken, so ``_bind`` retries), uvloop leaves its half-made
    ``UDPTransport`` open for the garbage collector (a ResourceWarning). Binding first means a
    failed bind closes its socket here and the transport only ever gets a bound one.
    """
    infos = await loop.getaddrinfo(host, port, family=_family(host), type=socket.SOCK_DGRAM,
                                   flags=socket.AI_PASSIVE)
    family, kind, proto, _, addr = infos[0]
    sock = socket.socket(family, kind, proto)
    try:
        sock.setblocking(False)
        sock.bind(addr)
    except BaseException:
        sock.close()
        raise
    return sock


def _authentication(keyed: bool, tls: bool, cfg: ServerConfig) -> str:
    """The listening line's authentication mode, e.g. ``TLS (mutual) + pre-shared key``."""
    parts = []
    if tls:
        parts.append("TLS (mutual)" if cfg.tls_client_ca is not None else "TLS")
    if keyed:
        parts.append("pre-shared key")
    if parts:
        return " + ".join(parts)
    return "none" if cfg.loopback else "none (--insecure)"


class ServerThread:
    """A server on a background thread: ``with ServerThread(cfg) as srv: srv.port``.

    ``start`` is idempotent while the thread runs, so ``with ServerThread(cfg).start() as srv``
    and ``srv.start(); with srv:`` serve once (a second ``serve`` on the same ``Server`` would
    start a second loop and thread that ``stop`` never reaches). After ``stop`` it may start again.
    """

    def __init__(self, config: ServerConfig | None = None, adapter: MiddlewareAdapter | None = None,
                 **overrides: Any) -> None:
        base = config or ServerConfig(port=0)
        self.server = Server(base.model_copy(update=overrides) if overrides else base, adapter)
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None

    @property
    def port(self) -> int:
        """The bound port: the one the OS picked when the config said 0."""
        assert self.server.address is not None, "server not started"
        return self.server.address.port

    def start(self, timeout: float = 10.0) -> ServerThread:
        """Start serving; return once it listens, or raise ``ServerError`` saying why not.

        A no-op returning ``self`` when this thread already serves.
        """
        if self._thread is not None and self._thread.is_alive():
            return self
        self._ready.clear()
        self._error = None

        def main() -> None:
            try:
                run_on_loop(self.server.serve(started=lambda _a: self._ready.set()),
                            lambda: new_event_loop(self.server.config.use_uvloop))
            except BaseException as exc:
                self._error = exc
                self._ready.set()

        self._thread = threading.Thread(target=main, name="rlbridge-server", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout):
            raise ServerError("server did not start in time")
        if self._error is not None:
            # The thread is still on its way out: join it, so that a retry starts a new one
            # instead of finding this one alive and taking the failed start for a running one.
            self._thread.join(timeout)
            self._thread = None
            raise ServerError(str(self._error)) from self._error
        return self

    def stop(self, timeout: float = 10.0) -> None:
        """Shut the server down in order and join its thread (waits at most ``timeout``)."""
        self.server.stop()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    def __enter__(self) -> ServerThread:
        return self.start()

    def __exit__(self, et: type[BaseException] | None, e: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()
