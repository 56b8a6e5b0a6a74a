"""The link's handle on its relay process: start it, talk to it, stop it and reap it.

The relay is a separate process, not a thread, because a thread would need this
process's GIL to move each packet: a benchmark or bridge running in the same interpreter
would then add up to ``sys.getswitchinterval()`` (5 ms) of latency to the link, which is
larger than the delays being emulated.

Ownership: :meth:`RelayProcess.start` hands both TUN descriptors to the child and closes
this process's copies, so the relay is their only owner and the TUN devices vanish with
it.  The control socket has one end on each side; the relay exits on EOF, so it cannot
outlive this process even if this process is killed with SIGKILL.
"""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import threading
from pathlib import Path

import msgspec

from rlbridge.netem import control
from rlbridge.netem.impairment import Impairment
from rlbridge.netem.stats import LinkStats


class RelayError(RuntimeError):
    """The relay process did not start, died, or did not answer in time."""


def _child_env() -> dict[str, str]:
    """The environment for the relay, with this copy of ``rlbridge`` importable.

    The relay must run the same code as the link even when ``rlbridge`` is used from a
    source tree that is not installed (``PYTHONPATH=src``, or a test run).
    """
    src_dir = str(Path(__file__).resolve().parents[2])
    env = dict(os.environ)
    path = env.get("PYTHONPATH")
    env["PYTHONPATH"] = src_dir if not path else f"{src_dir}{os.pathsep}{path}"
    return env


class RelayProcess:
    """One relay process.  Thread-safe: requests are serialised by a lock."""

    def __init__(
        self,
        *,
        tun_a: int,
        tun_b: int,
        seed: int,
        a_to_b: Impairment,
        b_to_a: Impairment,
        max_lifetime_s: float,
        cpus: frozenset[int] | None = None,
        rt_priority: int | None = None,
        start_timeout_s: float = 15.0,
        request_timeout_s: float = 5.0,
    ) -> None:
        self._tun_a = tun_a
        self._tun_b = tun_b
        self._seed = seed
        self._initial = (a_to_b, b_to_a)
        self._max_lifetime_s = max_lifetime_s
        self._cpus = cpus
        self._rt_priority = rt_priority
        self._start_timeout_s = start_timeout_s
        self._request_timeout_s = request_timeout_s
        self._lock = threading.Lock()
        self._proc: subprocess.Popen[bytes] | None = None
        self._sock: socket.socket | None = None

    @property
    def pid(self) -> int | None:
        """The relay's pid while it is started, else None."""
        return None if self._proc is None else self._proc.pid

    def start(self) -> None:
        """Spawn the relay, hand it the TUN descriptors and wait until its loop runs."""
        if self._proc is not None:
            raise RuntimeError("relay already started")
        parent, child = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            argv = [
                sys.executable, "-m", "rlbridge.netem.relay",
                "--tun-a", str(self._tun_a),
                "--tun-b", str(self._tun_b),
                "--ctrl", str(child.fileno()),
                "--seed", str(self._seed),
                "--a-to-b", msgspec.json.encode(self._initial[0]).decode(),
                "--b-to-a", msgspec.json.encode(self._initial[1]).decode(),
                "--max-lifetime", repr(self._max_lifetime_s),
            ]  # fmt: skip
            if self._cpus:
                argv += ["--cpus", ",".join(str(cpu) for cpu in sorted(self._cpus))]
            if self._rt_priority:
                argv += ["--rt-priority", str(self._rt_priority)]
            self._proc = subprocess.Popen(
                argv,
                pass_fds=(self._tun_a, self._tun_b, child.fileno()),
                env=_child_env(),
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                # Own session: a terminal's Ctrl-C reaches us, and we stop the relay in order.
                start_new_session=True,
            )
        except BaseException:
            parent.close()
            raise
        finally:
            child.close()
            os.close(self._tun_a)
            os.close(self._tun_b)
        self._sock = parent
        try:
            reply = self._receive(self._start_timeout_s, "start")
            if not isinstance(reply, control.Ready):
                raise RelayError(f"relay sent {reply!r} instead of Ready")
        except BaseException:
            self.stop()
            raise

    def set_impairments(self, a_to_b: Impairment, b_to_a: Impairment) -> None:
        """Apply new impairments to packets admitted from now on."""
        reply = self._request(control.SetImpairments(a_to_b=a_to_b, b_to_a=b_to_a))
        if not isinstance(reply, control.Ok):
            raise RelayError(f"relay refused new impairments: {reply!r}")

    def stats(self) -> LinkStats:
        """Counters of both directions."""
        reply = self._request(control.GetStats())
        if not isinstance(reply, control.StatsReply):
            raise RelayError(f"relay sent {reply!r} instead of stats")
        return reply.stats

    def stop(self, timeout_s: float = 3.0) -> int | None:
        """Stop and reap the relay; idempotent.  Returns its exit code (None if never run).

        Asks politely (Stop), then closes the control socket (EOF also stops it), then
        kills it if it has not exited within ``timeout_s``.
        """
        proc, sock = self._proc, self._sock
        if proc is None:
            return None
        if sock is not None:
            with contextlib.suppress(OSError, RelayError):
                self._request(control.Stop(), timeout_s=timeout_s / 2)
            sock.close()
            self._sock = None
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        return proc.returncode

    def _request(self, message: control.Request, timeout_s: float | None = None) -> control.Reply:
        with self._lock:
            if self._sock is None:
                raise RelayError("relay is not running")
            try:
                self._sock.send(control.encode(message))
            except OSError as exc:
                raise RelayError(f"relay is gone ({self._exit_status()}): {exc}") from exc
            what = type(message).__name__
            return self._receive(timeout_s or self._request_timeout_s, what)

    def _receive(self, timeout_s: float, what: str) -> control.Reply:
        assert self._sock is not None
        self._sock.settimeout(timeout_s)
        try:
            data = self._sock.recv(control.MAX_MESSAGE_BYTES)
        except TimeoutError as exc:
            raise RelayError(f"relay did not answer {what} within {timeout_s} s") from exc
        if not data:
            raise RelayError(f"relay exited during {what} ({self._exit_status()})")
        reply = control.decode_reply(data)
        if isinstance(reply, control.Failed):
            raise RelayError(f"relay failed {what}: {reply.message}")
        return reply

    def _exit_status(self) -> str:
        if self._proc is None:
            return "not started"
        try:
            code = self._proc.wait(timeout=0.5)
        except subprocess.TimeoutExpired:
            return "still running"
        return f"exit code {code}"
