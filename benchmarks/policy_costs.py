"""What the channel policies cost on the control thread's hot path, in ns per call.

Bridge channels now carry a stamp with every value (so ``read_with_age`` is exact) and the
outgoing ring checks its writer thread (so a second writer is refused, not silently lossy).
This times those calls next to the plain CSP channel operations they extend, interleaved in
one process (``repeats`` rounds, median per call), because a loaded machine moves absolute
figures far more than it moves the ratios. ``python -m benchmarks.policy_costs``.
"""

from __future__ import annotations

import statistics
import time
import timeit
from collections.abc import Callable

from rlbridge.client.channels.incoming import IncomingChannel, OutgoingChannel
from rlbridge.csp.channel import Channel, Doorbell


def _cases() -> dict[str, Callable[[], object]]:
    plain_in: Channel[float] = Channel(1, blocking=False, initial=0.0)
    plain_in.write(1.0)
    bridge_in = IncomingChannel(1, "/t", "std_msgs/msg/Float64", "data", transport="tcp",
                                blocking=False, buffer_size=1, initial=0.0)
    bridge_in.deliver(0, [time.time_ns()], [1.0])
    plain_out: Channel[float] = Channel(1024, blocking=True)
    bridge_out = OutgoingChannel(1, "/t", "std_msgs/msg/Float64", "data", transport="tcp",
                                 immediate=False, buffer_size=1024, doorbell=Doorbell())
    # The receive thread's side: one packet's values in, then taken out again.
    plain_rx: Channel[float] = Channel(1024, blocking=True)
    bridge_rx = IncomingChannel(1, "/t", "std_msgs/msg/Float64", "data", transport="tcp",
                                blocking=True, buffer_size=1024)
    seq = [0]
    stamps, values = [time.time_ns()] * 10, [1.0] * 10

    def plain_packet() -> None:
        plain_rx.deliver_many(values)
        plain_rx.read_many()

    def bridge_packet() -> None:
        bridge_rx.deliver(seq[0], stamps, values)
        seq[0] += 10
        bridge_rx.read_many()

    return {
        "Channel.deliver_many + read_many, 10 values (baseline)": plain_packet,
        "IncomingChannel.deliver + read_many, 10 values": bridge_packet,
        "Channel.read (non-blocking, baseline)": plain_in.read,
        "IncomingChannel.read": bridge_in.read,
        "IncomingChannel.read_with_age": bridge_in.read_with_age,
        "IncomingChannel.health": bridge_in.health,
        "Channel.write (buffered, baseline)": lambda: plain_out.write(1.0),
        "OutgoingChannel.write": lambda: bridge_out.write(1.0),
        "OutgoingChannel.health": bridge_out.health,
    }


def policy_costs(number: int = 100_000, repeats: int = 7) -> dict[str, float]:
    """Median ns per call of each case, rounds interleaved."""
    cases = _cases()
    samples: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(repeats):
        for name, fn in cases.items():
            samples[name].append(timeit.timeit(fn, number=number) / number * 1e9)
    return {name: statistics.median(v) for name, v in samples.items()}


def main() -> None:
    costs = policy_costs()
    print("| call | ns per call (median) |\n|---|--:|")
    for name, ns in costs.items():
        print(f"| `{name}` | {ns:.0f} |")


if __name__ == "__main__":
    main()
