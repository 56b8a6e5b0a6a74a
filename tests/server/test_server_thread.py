"""ServerThread: one server per instance, however it is started (start, ``with``, both)."""

from __future__ import annotations

import socket
import threading

import pytest

from rlbridge.server import ServerConfig, ServerError, ServerThread


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
        with pytest.raises(ServerError, match=str(taken)):
            srv.start()
    with srv:  # the port is free now; the earlier error is not reported again
        assert srv.port == taken
