"""Where the load benchmark's values were lost: one row per stage of the path, adding up.

A value written by a load client can be lost at five places, and each has its own witness:

1. the publisher: for SDK clients, the send thread is late and the channel's ring overwrites
   the value before it is numbered and sent (``overwritten``);
2. hop 1, client -> server: the server's UDP receive buffer is full and the kernel drops the
   datagram (the socket's ``drops``, :mod:`.load_sockets`), or the client's own socket
   refused it (``send_errors``); the server sees either as a sequence gap on the publish
   channel (its ``lost``);
3. the server: a value it took in but did not send on (``dropped``: a full per-client queue,
   a value too large for a datagram);
4. hop 2, server -> client: the client's receive buffer is full (its sockets' ``drops``); the
   client sees a sequence gap on the subscription (``lost_seq``);
5. in flight when the run ended (sent, not yet delivered, not lost): the remainder.

Writes the clients skipped because their own process fell behind schedule are not losses but
a shortfall of the *offer*: the load generator shares the machine with the server it measures,
so that part is the harness's. The kernel's counters are the processes' own sockets, not the
machine-wide ``UdpRcvbufErrors`` every other program on a shared machine adds to.
"""

from __future__ import annotations

from dataclasses import dataclass

from rlbridge.bench.common import Params, fmt, markdown_table


@dataclass(frozen=True)
class KernelDrops:
    """Datagrams the kernel dropped on the run's sockets (receive buffers full), by side."""

    server: int = 0
    clients: int = 0

    def __sub__(self, other: KernelDrops) -> KernelDrops:
        return KernelDrops(self.server - other.server, self.clients - other.clients)


@dataclass(frozen=True)
class Stages:
    """The whole run's values by stage; ``in_flight`` is what the other rows leave."""

    written: int
    skipped: int
    publisher: int
    hop1: int
    hop1_datagrams: int
    server: int
    hop2: int
    hop2_datagrams: int
    delivered: int

    @property
    def in_flight(self) -> int:
        return (self.written - self.delivered - self.publisher - self.hop1 - self.server
                - self.hop2)


def stages(results: list[Params], hop1_gaps: int, server_dropped: int, skipped: int,
           kernel: KernelDrops) -> Stages:
    """Combine the clients' results, the server's counters and the kernel's."""
    return Stages(written=sum(int(r["sent"]) for r in results), skipped=skipped,
                  publisher=sum(int(r.get("overwritten", 0)) for r in results),
                  hop1=hop1_gaps, hop1_datagrams=kernel.server, server=server_dropped,
                  hop2=sum(int(r.get("lost_seq", 0)) for r in results),
                  hop2_datagrams=kernel.clients,
                  delivered=sum(int(r["received"]) for r in results))


def stage_table(st: Stages, send_errors: int) -> str:
    """The per-stage table of a report: values, share of those written, and the witness."""
    def pct(n: int) -> str:
        return f"{100 * n / st.written:.3f}" if st.written else "-"

    rows = [
        ["written by the clients", fmt(st.written), "100", "the clients' count"],
        ["lost at the publisher (overwritten in the SDK's ring before the send thread "
         "took it)", fmt(st.publisher), pct(st.publisher), "the SDK channels' `overwritten`"],
        [f"lost at hop 1 (server's receive buffer full: {fmt(st.hop1_datagrams)} datagrams "
         f"dropped by the kernel; refused by the client's own socket: {fmt(send_errors)})",
         fmt(st.hop1), pct(st.hop1),
         "the server's sequence gaps; its socket's `drops` in /proc/net/udp"],
        ["dropped by the server (queue to a client full, value too large)", fmt(st.server),
         pct(st.server), "the server's `dropped`"],
        [f"lost at hop 2 (clients' receive buffers full: {fmt(st.hop2_datagrams)} datagrams "
         "dropped by the kernel)", fmt(st.hop2), pct(st.hop2),
         "the clients' sequence gaps; their sockets' `drops`"],
        ["in flight at the end (sent, not yet delivered)", fmt(st.in_flight), pct(st.in_flight),
         "the rest"],
        ["delivered", fmt(st.delivered), pct(st.delivered), "the subscribing channels"],
    ]
    return "\n".join([
        markdown_table(["stage", "values", "% of written", "counted by"], rows), "",
        f"Not written at all: {st.skipped:,} values the clients' processes skipped when they "
        "fell behind schedule (the load generator's share of the machine, not the server's "
        "loss)."])
