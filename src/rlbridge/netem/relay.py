"""The relay: the process that carries IP packets between the two namespaces' TUN devices.

Theory of operation
-------------------
The relay runs as its own process (``python -m rlbridge.netem.relay``), started by
:class:`~rlbridge.netem.relay_process.RelayProcess`, so that the GIL of the program under
test can never hold back a packet.  It inherits three file descriptors: the TUN of
namespace A, the TUN of namespace B and one end of the control socket.

One loop, one thread::

    select([tun_a, tun_b, control], timeout = next release - now)
      tun_a readable -> read packets -> PathModel a_to_b -> drop (counted) or heap
      tun_b readable -> read packets -> PathModel b_to_a -> drop (counted) or heap
      control        -> SetImpairments / GetStats / Stop, one reply each; EOF -> exit
    write every packet whose release time has come to the other TUN

Timers are a binary heap keyed on (release time, arrival sequence); the ``select``
timeout is computed from its head, so the relay sleeps until the next packet is due and
never polls.  ``select`` is used rather than ``epoll`` because Python's ``epoll.poll``
rounds its timeout up to whole milliseconds while ``select`` keeps microseconds, and the
process asks for a 1 us timer slack so the kernel does not batch its wake-ups.

Lifetime: the loop ends on ``Stop``, on EOF of the control socket (the parent closed it or
died) or at the hard deadline given on the command line, whichever comes first.  It owns
the TUN descriptors; when it exits they close and the kernel removes the TUN devices.
"""

from __future__ import annotations

import argparse
import ctypes
import heapq
import itertools
import os
import select
import signal
import socket
import sys
import time
from collections.abc import Callable, Sequence

import msgspec

from rlbridge.netem import control
from rlbridge.netem.impairment import DropReason, Impairment, PathModel
from rlbridge.netem.stats import DirectionCounters, LinkStats

READ_SIZE = 65535
"""Larger than any packet a TUN without offloads can hand us (its MTU is at most 65535)."""

BATCH = 64
"""Packets read from one TUN per wake-up, so a flood in one direction cannot starve timers."""

_PR_SET_TIMERSLACK = 29


class Relay:
    """The relay loop and its state.  Single-threaded; the caller owns the descriptors."""

    def __init__(
        self,
        *,
        tun_a: int,
        tun_b: int,
        ctrl: socket.socket,
        models: tuple[PathModel, PathModel],
        deadline: float,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._tuns = (tun_a, tun_b)
        self._ctrl = ctrl
        self._models = models
        self._counters = (DirectionCounters(), DirectionCounters())
        self._deadline = deadline
        self._clock = clock
        self._heap: list[tuple[float, int, int, bytes]] = []
        self._seq = itertools.count()
        self._running = True

    def run(self) -> None:
        """Relay packets until Stop, control EOF or the deadline."""
        self._send(control.Ready(pid=os.getpid()))
        ctrl_fd = self._ctrl.fileno()
        watched = [self._tuns[0], self._tuns[1], ctrl_fd]
        while self._running:
            now = self._clock()
            if now >= self._deadline:
                break
            timeout = self._deadline - now
            if self._heap:
                timeout = min(timeout, max(0.0, self._heap[0][0] - now))
            readable, _, _ = select.select(watched, [], [], timeout)
            for fd in readable:
                if fd == ctrl_fd:
                    self._handle_control()
                else:
                    self._drain(0 if fd == self._tuns[0] else 1)
            self._release_due()

    def _drain(self, direction: int) -> None:
        src = self._tuns[direction]
        dst = self._tuns[1 - direction]
        model = self._models[direction]
        counters = self._counters[direction]
        for _ in range(BATCH):
            try:
                packet = os.read(src, READ_SIZE)
            except BlockingIOError:
                return
            now = self._clock()
            size = len(packet)
            counters.on_received(size)
            verdict = model.admit(now, size)
            if isinstance(verdict, DropReason):
                counters.on_dropped(verdict)
                continue
            counters.on_scheduled()
            if verdict <= now and not self._heap:
                # Fast path for a clean direction: nothing earlier is waiting.
                self._write(dst, packet, counters, verdict)
            else:
                heapq.heappush(self._heap, (verdict, next(self._seq), direction, packet))

    def _release_due(self) -> None:
        heap = self._heap
        while heap and heap[0][0] <= self._clock():
            release, _, direction, packet = heapq.heappop(heap)
            self._write(self._tuns[1 - direction], packet, self._counters[direction], release)

    def _write(self, dst: int, packet: bytes, counters: DirectionCounters, release: float) -> None:
        late = max(0.0, self._clock() - release)
        try:
            os.write(dst, packet)
        except OSError:
            # EIO when the receiving interface is down, EINVAL for a packet the kernel
            # refuses: the packet is lost and counted, as a NIC would count a tx error.
            counters.on_released(len(packet), late, ok=False)
        else:
            counters.on_released(len(packet), late, ok=True)

    def _handle_control(self) -> None:
        data = self._ctrl.recv(control.MAX_MESSAGE_BYTES)
        if not data:
            self._running = False
            return
        try:
            request = control.decode_request(data)
        except (msgspec.ValidationError, msgspec.DecodeError) as exc:
            self._send(control.Failed(message=f"bad request: {exc}"))
            return
        match request:
            case control.SetImpairments(a_to_b=a_to_b, b_to_a=b_to_a):
                self._models[0].reconfigure(a_to_b)
                self._models[1].reconfigure(b_to_a)
                self._send(control.Ok())
            case control.GetStats():
                stats = LinkStats(
                    a_to_b=self._counters[0].snapshot(), b_to_a=self._counters[1].snapshot()
                )
                self._send(control.StatsReply(stats=stats))
            case control.Stop():
                self._running = False
                self._send(control.Ok())

    def _send(self, message: control.Reply) -> None:
        try:
            self._ctrl.send(control.encode(message))
        except OSError:
            # The link side is gone; nobody is left to tell, so stop.
            self._running = False


def _reduce_timer_slack() -> None:
    """Ask for 1 us timer slack (default 50 us) so wake-ups land on the release time."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(_PR_SET_TIMERSLACK, 1, 0, 0, 0)


def _parse_args(argv: Sequence[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m rlbridge.netem.relay")
    parser.add_argument("--tun-a", type=int, required=True)
    parser.add_argument("--tun-b", type=int, required=True)
    parser.add_argument("--ctrl", type=int, required=True)
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--a-to-b", required=True, help="Impairment as JSON")
    parser.add_argument("--b-to-a", required=True, help="Impairment as JSON")
    parser.add_argument("--max-lifetime", type=float, required=True)
    parser.add_argument("--cpus", default="", help="comma-separated CPUs to pin to")
    parser.add_argument("--rt-priority", type=int, default=0, help="SCHED_FIFO priority")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the relay process; see the module docstring."""
    args = _parse_args(sys.argv[1:] if argv is None else argv)
    # The parent decides when we stop; a Ctrl-C aimed at the foreground job must not
    # kill the relay before the parent has torn the link down in order.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _reduce_timer_slack()
    if args.cpus:
        os.sched_setaffinity(0, {int(cpu) for cpu in args.cpus.split(",")})
    if args.rt_priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.rt_priority))
        except PermissionError:
            print("relay: not permitted to use SCHED_FIFO (needs CAP_SYS_NICE)", file=sys.stderr)
            return 2
    a_to_b = msgspec.json.decode(args.a_to_b, type=Impairment)
    b_to_a = msgspec.json.decode(args.b_to_a, type=Impairment)
    models = (
        PathModel(a_to_b, seed=args.seed, name="a_to_b"),
        PathModel(b_to_a, seed=args.seed, name="b_to_a"),
    )
    for fd in (args.tun_a, args.tun_b):
        os.set_blocking(fd, False)
    with socket.socket(fileno=args.ctrl) as ctrl:
        relay = Relay(
            tun_a=args.tun_a,
            tun_b=args.tun_b,
            ctrl=ctrl,
            models=models,
            deadline=time.monotonic() + args.max_lifetime,
        )
        try:
            relay.run()
        finally:
            os.close(args.tun_a)
            os.close(args.tun_b)
    return 0


if __name__ == "__main__":
    sys.exit(main())
