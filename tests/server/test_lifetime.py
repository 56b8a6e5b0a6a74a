"""A server's lifetime: one serve per ServerThread however started; every socket closed by
its owner (a failed bind or connect included), none left for the garbage collector."""

from __future__ import annotations

import gc
import socket
import threading
import warnings

import pytest

from rlbridge.client.session.handshake import udp_socket
from rlbridge.server import Server, ServerConfig, ServerError, ServerThread, new_event_loop
from rlbridge.server.runner import run_on_loop


def _server_threads() -> set[threading.Thread]:
    return {t for t in threading.enumerate() if t.name == "rlbridge-server"}


def _refused(port: int) -> bool:
    with socket.socket() as sock:
        try:
            sock.connect(("127.0.0.1", port))
        except ConnectionRefusedError:
            return True
        return False


def test_started_then_used_as_a_context_manager_serves_once_and_stops() -> None:
    before = _server_threads()
    srv = ServerThread(ServerConfig(port=0)).start()
    port = srv.port
    with srv as same:
        assert same is srv
        assert len(_server_threads() - before) == 1  # no second loop on the same Server
        assert same.port == port
    assert not (_server_threads() - before)
    assert _refused(port)  # the one server there was is the one that stopped


def test_start_inside_with_is_a_no_op() -> None:
    before = _server_threads()
    with ServerThread(ServerConfig(port=0)).start() as srv:
        assert srv.start() is srv
        assert len(_server_threads() - before) == 1
        port = srv.port
    assert not (_server_threads() - before)
    assert _refused(port)


def test_starts_again_after_stop() -> None:
    srv = ServerThread(ServerConfig(port=0))
    with srv:
        first = srv.port
    assert _refused(first)
    with srv:  # a fresh serve: readiness is waited for again, not taken from the first run
        assert not _refused(srv.port)


def test_a_failed_start_can_be_retried() -> None:
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        taken = holder.getsockname()[1]
        srv = ServerThread(ServerConfig(port=taken, udp=False))
        before = set(threading.enumerate())
        with pytest.raises(ServerError, match=str(taken)):
            srv.start()
        # The failed start has joined its thread: a retry cannot find it alive and take it
        # for a running server (it did, now and then, on a loaded machine).
        assert [t for t in threading.enumerate() if t not in before] == []
    with srv:  # the port is free now; the earlier error is not reported again
        assert srv.port == taken


@pytest.mark.parametrize("use_uvloop", [True, False])
def test_a_udp_port_taken_leaves_no_socket_open(use_uvloop: bool) -> None:
    """TCP binds, UDP's twin port is taken: the error names UDP, and no transport is left
    for the garbage collector (uvloop's ``local_addr`` path left one: a ResourceWarning)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as holder:
        holder.bind(("127.0.0.1", 0))
        taken = holder.getsockname()[1]
        server = Server(ServerConfig(port=taken, use_uvloop=use_uvloop))
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always", ResourceWarning)
            with pytest.raises(ServerError, match=f"UDP port {taken}: address already in use"):
                run_on_loop(server.serve(), lambda: new_event_loop(use_uvloop))
            gc.collect()
    leaks = [str(w.message) for w in seen if issubclass(w.category, ResourceWarning)]
    assert leaks == []


def test_the_client_udp_socket_is_closed_when_it_cannot_connect() -> None:
    """client.session.handshake.udp_socket: a socket whose connect fails is closed there, not left
    to GC."""
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always", ResourceWarning)
        with pytest.raises(OverflowError):
            udp_socket("127.0.0.1", 70000)
        gc.collect()
    assert [w for w in seen if issubclass(w.category, ResourceWarning)] == []
