"""What UDP redundancy costs on the wire: bytes per value against k (docs/policies.md).

With ``redundancy=k`` every datagram also carries the previous k values of its channel, so a
value is lost only when k + 1 consecutive datagrams are: at independent loss ``p`` the
residual loss is ``p ** (k + 1)``. The price is bytes. This measures it on the real code
path, not a formula: an :class:`~rlbridge.client.channels.incoming.OutgoingChannel` with that k
takes one value per send (a set-point stream), the send thread's packet builder makes the
packet and the codec encodes the datagram; sizes are taken once the history is full.
Nothing here reads a clock for timing, so the figures are exact and machine-independent.

Run ``python -m benchmarks.redundancy`` for the markdown table in docs/policies.md;
:func:`redundancy_cost` returns the rows for the evaluation harness.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from rlbridge.client.channels.incoming import OutgoingChannel
from rlbridge.client.session.sender import packets_for
from rlbridge.csp.channel import Doorbell
from rlbridge.wire import PacketCodec

#: IPv4 (20) + UDP (8) header bytes around every datagram.
IP_UDP_HEADERS = 28


@dataclass(frozen=True, slots=True)
class RedundancyCost:
    """Steady-state size of one value's datagram at redundancy ``k``."""

    k: int
    payload_bytes: int
    wire_bytes: int
    ratio: float
    residual_loss_at_1pct: float


def _datagram_size(k: int, value: Any, warmup: int) -> int:
    channel = OutgoingChannel(1, "/bench", "std_msgs/msg/Float64", "data", transport="udp",
                              immediate=True, buffer_size=4, doorbell=Doorbell(),
                              redundancy=k)
    codec = PacketCodec()
    token = 0x1234_5678_9ABC_DEF0
    size = 0
    for _ in range(warmup + k + 1):
        channel.write(value)
        first, stamps, values, _repeated = channel.take()
        [packet] = packets_for(channel.channel_id, first, stamps, values, 256)
        size = len(codec.encode_datagram(packet, token))
    return size


def redundancy_cost(ks: tuple[int, ...] = (0, 1, 2, 3, 4, 8), value: Any = 0.123456789,
                    warmup: int = 1000) -> list[RedundancyCost]:
    """Bytes per value for each k (sequence numbers past ``warmup``, stamps of now)."""
    sizes = {k: _datagram_size(k, value, warmup) for k in ks}
    base = sizes[ks[0]] + IP_UDP_HEADERS
    return [RedundancyCost(k, size, size + IP_UDP_HEADERS, (size + IP_UDP_HEADERS) / base,
                           0.01 ** (k + 1)) for k, size in sizes.items()]


def markdown(rows: list[RedundancyCost]) -> str:
    lines = ["| k | datagram payload (B) | on the wire incl. IP+UDP (B) | x k=0 "
             "| residual loss at 1% |", "|--:|--:|--:|--:|--:|"]
    lines += [f"| {r.k} | {r.payload_bytes} | {r.wire_bytes} | {r.ratio:.2f} "
              f"| {r.residual_loss_at_1pct:.0e} |" for r in rows]
    return "\n".join(lines)


def main() -> None:
    print(markdown(redundancy_cost()))


if __name__ == "__main__":
    main()
