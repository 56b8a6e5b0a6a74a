"""EmulatedLink: two network namespaces joined by a delaying, dropping relay.

::

      namespace A (rlb-<pid>-<tok>-a)            namespace B (rlb-<pid>-<tok>-b)
     +-------------------------------+          +-------------------------------+
     |  program under test           |          |  program under test           |
     |  kernel TCP/UDP/IP, lo up     |          |  kernel TCP/UDP/IP, lo up     |
     |  rlb0  10.203.0.1 peer .2     |          |  rlb0  10.203.0.2 peer .1     |
     +-------------|-----------------+          +-----------------|-------------+
                   | IP packets (TUN fd)                          | (TUN fd)
     root namespace|                                              |
            +------v----------------------------------------------v------+
            |  relay process: select() on both TUNs + control socket     |
            |  a_to_b: PathModel (loss, limit, rate, delay+jitter) -> heap|
            |  b_to_a: PathModel (independent RNG and settings)    -> heap|
            +--------------------------^---------------------------------+
                                       | control (SOCK_SEQPACKET): set / stats / stop
                               EmulatedLink in this process

The kernels' real TCP stacks run on both sides, so retransmission timeouts, Nagle and
delayed ACKs and head-of-line blocking are measured, not modelled; the relay only decides
when (and whether) each IP packet crosses.

Lifetime: :meth:`EmulatedLink.start` (or ``with``) builds everything on an ExitStack, so a
failure half-way undoes what was done; :meth:`EmulatedLink.close` (or leaving the ``with``,
also by an exception, Ctrl-C, or SIGTERM while the link installed its handler) terminates
processes started in the namespaces, stops and reaps the relay and deletes both
namespaces.  If this process is SIGKILLed, the relay exits on its own (control socket EOF)
and :func:`~rlbridge.netem.netns.cleanup_stale_namespaces` removes the namespaces later.
"""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
from collections.abc import Sequence
from contextlib import ExitStack
from types import TracebackType
from typing import Any

from rlbridge._compat import Self
from rlbridge.netem.impairment import Direction, Impairment
from rlbridge.netem.link_settings import (
    DEFAULT_NETWORK,
    Side,
    check_bounds,
    describe,
    host_pair,
    impairment_pair,
    side_index,
    simple_pair,
)
from rlbridge.netem.netns import (
    call_in_namespace,
    create_namespace,
    delete_namespace,
    exec_argv,
    namespace_name,
    new_run_token,
)
from rlbridge.netem.ns_children import (
    NamespaceChildren,
    terminate_namespace_processes,
)
from rlbridge.netem.relay_process import RelayProcess
from rlbridge.netem.signals import sigterm_raises
from rlbridge.netem.stats import LinkStats
from rlbridge.netem.tun import configure_point_to_point, open_tun, tx_dropped

__all__ = ["IFNAME", "EmulatedLink"]

IFNAME = "rlb0"
"""Name of the TUN device in each namespace (names are per namespace, so no clash)."""


class EmulatedLink:
    """A point-to-point IPv4 link between namespaces ``ns_a`` and ``ns_b`` with impairments.

    The positional arguments mirror ``tc netem`` (``delay``, ``loss``, ``jitter``) applied
    to ``direction``; the other direction is clean.  For different settings per
    direction, or for rate limits and burst loss, pass ``a_to_b`` and ``b_to_a``
    :class:`~rlbridge.netem.impairment.Impairment` values instead.  ``seed`` fixes the loss
    pattern (and jitter) of each direction.  ``max_lifetime_s`` is a hard bound: the relay
    stops forwarding after it even if :meth:`close` is never called.  ``relay_cpus`` pins
    the relay process (see docs/netem.md: on a VM a wake-up across vCPUs costs ~100 us).
    """

    def __init__(
        self,
        delay_ms: float = 0.0,
        loss_pct: float = 0.0,
        jitter_ms: float = 0.0,
        seed: int = 1,
        direction: Direction = "both",
        *,
        a_to_b: Impairment | None = None,
        b_to_a: Impairment | None = None,
        mtu: int = 1500,
        network: str = DEFAULT_NETWORK,
        max_lifetime_s: float = 3600.0,
        handle_sigterm: bool = True,
        relay_cpus: frozenset[int] | None = None,
        relay_rt_priority: int | None = None,
    ) -> None:
        self._impairments = impairment_pair(delay_ms, loss_pct, jitter_ms, direction,
                                            a_to_b, b_to_a)
        check_bounds(mtu, max_lifetime_s, relay_rt_priority)
        self._addrs = host_pair(network)
        token = new_run_token()
        self._names = (namespace_name(token, "a"), namespace_name(token, "b"))
        self._seed = seed
        self._mtu = mtu
        self._max_lifetime_s = max_lifetime_s
        self._handle_sigterm = handle_sigterm
        self._relay_cpus = relay_cpus
        self._relay_rt_priority = relay_rt_priority
        self.name = describe(self._impairments)
        """A short label for reports, e.g. ``netem a_to_b=7.5ms/1% b_to_a=clean``."""
        self._stack: ExitStack | None = None
        self._relay: RelayProcess | None = None
        self._children = NamespaceChildren()

    # -- lifetime ---------------------------------------------------------------------

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def start(self) -> None:
        """Create namespaces, TUN devices and the relay.  Undoes everything on failure."""
        if self._stack is not None:
            raise RuntimeError("link already started")
        stack = ExitStack()
        try:
            if self._handle_sigterm:
                stack.enter_context(sigterm_raises())
            for name in self._names:
                create_namespace(name)
                stack.callback(delete_namespace, name)
            # Runs before the deletions: nothing may be left running in a namespace.
            stack.callback(terminate_namespace_processes, self._names)
            fds: list[int] = []
            stack.callback(_close_all, fds)
            fds.append(open_tun(self._names[0], IFNAME))
            fds.append(open_tun(self._names[1], IFNAME))
            for i, name in enumerate(self._names):
                configure_point_to_point(
                    name, IFNAME, local=self._addrs[i], peer=self._addrs[1 - i], mtu=self._mtu
                )
            relay = RelayProcess(
                tun_a=fds[0],
                tun_b=fds[1],
                seed=self._seed,
                a_to_b=self._impairments[0],
                b_to_a=self._impairments[1],
                max_lifetime_s=self._max_lifetime_s,
                cpus=self._relay_cpus,
                rt_priority=self._relay_rt_priority,
            )
            fds.clear()  # RelayProcess.start owns (and closes here) the descriptors now
            stack.callback(relay.stop)
            relay.start()
            stack.callback(self._children.terminate)
        except BaseException:
            stack.close()
            raise
        self._relay = relay
        self._stack = stack

    def close(self) -> None:
        """Tear everything down; idempotent, safe after a failed or partial start."""
        stack, self._stack = self._stack, None
        self._relay = None
        if stack is not None:
            stack.close()

    # -- description ------------------------------------------------------------------

    @property
    def ns_a(self) -> str:
        """Name of namespace A (for ``ip netns exec``)."""
        return self._names[0]

    @property
    def ns_b(self) -> str:
        """Name of namespace B."""
        return self._names[1]

    @property
    def addr_a(self) -> str:
        """IPv4 address of namespace A on the link."""
        return self._addrs[0]

    @property
    def addr_b(self) -> str:
        """IPv4 address of namespace B on the link."""
        return self._addrs[1]

    @property
    def mtu(self) -> int:
        """MTU of both TUN devices."""
        return self._mtu

    @property
    def ifname(self) -> str:
        """Name of the link's interface inside each namespace."""
        return IFNAME

    @property
    def relay_pid(self) -> int | None:
        """Pid of the relay process while the link is up."""
        return None if self._relay is None else self._relay.pid

    def namespace(self, side: Side) -> str:
        """Namespace name of ``side``."""
        return self._names[side_index(side)]

    def address(self, side: Side) -> str:
        """Address of ``side`` on the link."""
        return self._addrs[side_index(side)]

    def __repr__(self) -> str:
        state = "up" if self._stack is not None else "down"
        return (
            f"EmulatedLink({self.ns_a}={self.addr_a} <-> {self.ns_b}={self.addr_b}, "
            f"a_to_b={self._impairments[0]}, b_to_a={self._impairments[1]}, {state})"
        )

    # -- running things in the namespaces -----------------------------------------------

    def exec_argv(self, side: Side, argv: Sequence[str]) -> list[str]:
        """``argv`` prefixed so that it runs in ``side``'s namespace (for asyncio etc.)."""
        return exec_argv(self.namespace(side), argv)

    def popen_in(self, side: Side, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen[Any]:
        """Start ``argv`` in ``side``'s namespace; it is terminated when the link closes."""
        self._require_up()
        return self._children.popen(self.namespace(side), argv, **kwargs)

    def popen(self, side: Side, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen[Any]:
        """Same as :meth:`popen_in`; the name ``rlbridge.bench.common.Link`` expects."""
        return self.popen_in(side, argv, **kwargs)

    def run_in(
        self,
        side: Side,
        argv: Sequence[str],
        *,
        timeout: float,
        check: bool = False,
        **kwargs: Any,
    ) -> subprocess.CompletedProcess[Any]:
        """Run ``argv`` to completion in ``side``'s namespace, killed after ``timeout`` s."""
        self._require_up()
        return subprocess.run(self.exec_argv(side, argv), timeout=timeout, check=check, **kwargs)

    def open_socket(
        self,
        side: Side,
        kind: socket.SocketKind = socket.SOCK_DGRAM,
        family: socket.AddressFamily = socket.AF_INET,
        proto: int = 0,
    ) -> socket.socket:
        """A new socket living in ``side``'s namespace, usable from this process.

        The caller owns (and closes) it.  Handy for tests and benchmarks that want both
        ends in one process with one clock.
        """
        self._require_up()
        return call_in_namespace(self.namespace(side), lambda: socket.socket(family, kind, proto))

    # -- impairments --------------------------------------------------------------------

    @property
    def impairments(self) -> tuple[Impairment, Impairment]:
        """The current ``(a_to_b, b_to_a)`` impairments."""
        return self._impairments

    def set_impairment(
        self,
        delay_ms: float = 0.0,
        loss_pct: float = 0.0,
        jitter_ms: float = 0.0,
        direction: Direction = "both",
    ) -> None:
        """Change the link as if it had been created with these arguments.

        The direction(s) not named become clean.  Applies to packets arriving from now
        on; packets in flight keep their release times.
        """
        self.set_impairments(*simple_pair(delay_ms, loss_pct, jitter_ms, direction))

    def set_impairments(self, a_to_b: Impairment, b_to_a: Impairment) -> None:
        """Set both directions' impairments (rate limits, burst loss, reordering...)."""
        self._require_relay().set_impairments(a_to_b, b_to_a)
        self._impairments = (a_to_b, b_to_a)
        self.name = describe(self._impairments)

    def stats(self) -> LinkStats:
        """Packets relayed and dropped per direction, and the relay's own lateness."""
        return self._require_relay().stats()

    def kernel_drops(self) -> tuple[int, int]:
        """``(a, b)``: packets each side's kernel dropped before the relay could read them.

        Non-zero means a sender outran the relay (TUN queue of ``txqueuelen`` packets
        full); those losses are not in :meth:`stats`.  Costs two ``ip`` calls.
        """
        self._require_up()
        return (tx_dropped(self.ns_a, IFNAME), tx_dropped(self.ns_b, IFNAME))

    def _require_up(self) -> None:
        if self._stack is None:
            raise RuntimeError("the link is not started (use it in a 'with' block)")

    def _require_relay(self) -> RelayProcess:
        if self._relay is None:
            raise RuntimeError("the link is not started (use it in a 'with' block)")
        return self._relay


def _close_all(fds: list[int]) -> None:
    for fd in fds:
        with contextlib.suppress(OSError):
            os.close(fd)
    fds.clear()
