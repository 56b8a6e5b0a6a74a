"""Named network namespaces: create, enter (one thread at a time), list, delete, reap.

Namespaces are created with ``ip netns add`` so they appear under ``/run/netns`` and
users can run ``ip netns exec NAME ...`` in them.  Code in *this* process enters a
namespace only inside a short-lived helper thread (:func:`call_in_namespace`): ``setns``
changes the namespace of the calling thread only, so the main thread never leaves the
root namespace and nothing has to be switched back.  Sockets and TUN devices stay bound
to the namespace they were created in after the thread is gone.

Names are ``rlb-<pid>-<token>-<role>``: the pid lets :func:`cleanup_stale_namespaces`
tell which namespaces belong to runs that no longer exist, the random token keeps several
links in one process (and parallel test runs) apart.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import re
import secrets
import select
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")

NETNS_DIR = Path("/run/netns")
PREFIX = "rlb-"
_NAME_RE = re.compile(r"^rlb-(?P<pid>\d+)-(?P<token>[0-9a-f]+)-(?P<role>[a-z]+)$")
_CLONE_NEWNET = 0x40000000
IP_TIMEOUT_S = 10.0
"""Upper bound on any single ``ip`` invocation."""


class NetnsError(RuntimeError):
    """A namespace operation failed; the message includes the command and its stderr."""


def new_run_token() -> str:
    """A random token for one link's namespace names."""
    return secrets.token_hex(3)


def namespace_name(token: str, role: str, pid: int | None = None) -> str:
    """``rlb-<pid>-<token>-<role>``; ``pid`` defaults to this process."""
    return f"{PREFIX}{os.getpid() if pid is None else pid}-{token}-{role}"


def run_ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    """Run ``ip ARGS`` with a timeout; raise :class:`NetnsError` with stderr on failure."""
    argv = ["ip", *args]
    try:
        proc = subprocess.run(
            argv, capture_output=True, text=True, timeout=IP_TIMEOUT_S, check=False
        )
    except FileNotFoundError as exc:
        raise NetnsError("'ip' (iproute2) is not installed") from exc
    except subprocess.TimeoutExpired as exc:
        raise NetnsError(f"{' '.join(argv)} did not finish in {IP_TIMEOUT_S} s") from exc
    if check and proc.returncode != 0:
        raise NetnsError(f"{' '.join(argv)} failed: {proc.stderr.strip()}")
    return proc


def create_namespace(name: str) -> None:
    """Create ``name`` and bring its loopback up (sockets bound to 127.0.0.1 need it)."""
    run_ip("netns", "add", name)
    try:
        run_ip("-n", name, "link", "set", "lo", "up")
    except NetnsError:
        delete_namespace(name)
        raise


def delete_namespace(name: str) -> None:
    """Delete ``name`` if it exists; a missing namespace is not an error."""
    if name in list_namespaces():
        run_ip("netns", "delete", name, check=False)


def list_namespaces() -> list[str]:
    """Names of all named network namespaces (``ip netns list``)."""
    proc = run_ip("netns", "list", check=False)
    return [line.split()[0] for line in proc.stdout.splitlines() if line.strip()]


def namespace_pids(name: str) -> list[int]:
    """Pids of processes whose network namespace is ``name``."""
    proc = run_ip("netns", "pids", name, check=False)
    return [int(tok) for tok in proc.stdout.split() if tok.isdigit()]


def call_in_namespace(name: str, fn: Callable[[], T]) -> T:
    """Run ``fn`` in a helper thread that has joined namespace ``name``; return its result.

    Exceptions raised by ``fn`` (or by ``setns``) are re-raised in the caller.
    """
    path = NETNS_DIR / name
    result: list[T] = []
    error: list[BaseException] = []

    def target() -> None:
        try:
            fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
            try:
                libc = ctypes.CDLL(None, use_errno=True)
                if libc.setns(fd, _CLONE_NEWNET) != 0:
                    err = ctypes.get_errno()
                    raise OSError(err, f"setns({path}): {os.strerror(err)}")
            finally:
                os.close(fd)
            result.append(fn())
        except BaseException as exc:  # re-raised in the calling thread below
            error.append(exc)

    thread = threading.Thread(target=target, name=f"netns-{name}", daemon=True)
    thread.start()
    thread.join()
    if error:
        raise error[0]
    return result[0]


def exec_argv(name: str, argv: Sequence[str]) -> list[str]:
    """The argv that runs ``argv`` inside namespace ``name`` (``ip netns exec`` execs it)."""
    return ["ip", "netns", "exec", name, *argv]


def terminate_pids(pids: Sequence[int], grace_s: float = 2.0) -> None:
    """SIGTERM ``pids``, wait up to ``grace_s`` for them to exit, then SIGKILL survivors.

    Used only for processes inside namespaces this module created, at teardown.  Signals
    go through pidfds, so a pid reused in the meantime is never hit, and the wait is a
    ``select`` on the pidfds rather than a polling loop.
    """
    pidfds: list[int] = []
    for pid in pids:
        with contextlib.suppress(ProcessLookupError):
            pidfds.append(os.pidfd_open(pid))
    try:
        for fd in pidfds:
            with contextlib.suppress(ProcessLookupError):
                signal.pidfd_send_signal(fd, signal.SIGTERM)
        waiting = list(pidfds)
        deadline = time.monotonic() + grace_s
        while waiting:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            exited, _, _ = select.select(waiting, [], [], remaining)
            waiting = [fd for fd in waiting if fd not in exited]
        for fd in waiting:
            with contextlib.suppress(ProcessLookupError):
                signal.pidfd_send_signal(fd, signal.SIGKILL)
    finally:
        for fd in pidfds:
            os.close(fd)


def _pid_exists(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    stat = Path(f"/proc/{pid}/stat")
    with contextlib.suppress(OSError):
        # A zombie still "exists" for kill(0) but no longer runs.
        return stat.read_text().rsplit(")", 1)[1].split()[0] != "Z"
    return False


@dataclass(frozen=True)
class StaleNamespace:
    """A namespace left behind by a run whose process no longer exists."""

    name: str
    owner_pid: int
    remaining_pids: tuple[int, ...]


def find_stale_namespaces() -> list[StaleNamespace]:
    """``rlb-*`` namespaces whose creating process is gone (killed before teardown).

    A namespace whose owner pid is alive is never reported, even if the pid has been
    reused by another program: leaving one stale namespace is better than deleting a
    live one.
    """
    stale = []
    for name in list_namespaces():
        match = _NAME_RE.match(name)
        if match is None:
            continue
        owner = int(match["pid"])
        if owner == os.getpid() or _pid_exists(owner):
            continue
        stale.append(StaleNamespace(name, owner, tuple(namespace_pids(name))))
    return stale


def cleanup_stale_namespaces(*, kill_processes: bool = False) -> list[StaleNamespace]:
    """Delete the namespaces :func:`find_stale_namespaces` reports; return them.

    Processes still running inside a stale namespace (started with ``popen_in`` by the dead
    run) are terminated only with ``kill_processes=True``; otherwise they keep running,
    cut off from any network, and are reported in ``remaining_pids``.
    """
    stale = find_stale_namespaces()
    for ns in stale:
        if kill_processes and ns.remaining_pids:
            terminate_pids(ns.remaining_pids)
        delete_namespace(ns.name)
    return stale
