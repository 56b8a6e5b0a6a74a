"""Cost of the write-time type check on ``OutgoingChannel.write``, next to an unchecked write.

    .venv/bin/python benchmarks/write_check.py [--repeats 15] [--writes 200000]

The baseline is ``OutgoingChannel.write`` without the check (the method as it was before the
check, in a subclass below), run in the same interleaved rounds as the checked cases, so load
changes hit every row alike. Prints the median ns per write of each case and its difference to
the baseline. Channels are built as ``Bridge.publish`` builds them, bound with the schema the
server sends (``TopicAck.schema``), without a server: only the write is timed.
"""

from __future__ import annotations

import argparse
import statistics
import threading
import time
import timeit
from typing import Any

from rlbridge.adapters.inproc import InProcessBus
from rlbridge.csp.bridge_channels import OutgoingChannel
from rlbridge.csp.channel import Doorbell
from rlbridge.csp.errors import ChannelClosed
from rlbridge.server.admission import value_schema
from rlbridge.wire import TopicAck

_get_ident = threading.get_ident  # as bridge_channels binds it


class UncheckedChannel(OutgoingChannel):
    """The write of an outgoing channel without the type check (the same-run baseline)."""

    __slots__ = ()

    def write(self, value: Any) -> None:
        if self._closed:
            raise ChannelClosed(self.topic)
        if _get_ident() != self._writer:
            self._check_writer()
        self._ring.push_stamped(time.time_ns(), value)
        if self.immediate:
            bell = self._bell
            if bell.waiting:
                bell.ring()


def channel(msg_type: str, field: str | None, cls: type[OutgoingChannel] = OutgoingChannel
            ) -> OutgoingChannel:
    ch = cls(1, "/bench", msg_type, field, transport="udp", immediate=True, buffer_size=1024,
             doorbell=Doorbell())
    spec = InProcessBus().resolve(msg_type, field)
    ch.bound(TopicAck(1, spec.msg_type, spec.default, value_schema(spec)))
    return ch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--writes", type=int, default=200_000)
    args = parser.parse_args()
    f64 = "std_msgs/msg/Float64"
    twist = {"linear": {"x": 0.5, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 1.0}}
    cases: dict[str, tuple[OutgoingChannel, Any]] = {
        "unchecked write (baseline), float": (channel(f64, "data", UncheckedChannel), 1.5),
        "checked, float into Float64": (channel(f64, "data"), 1.5),
        "checked, int into Float64 (converted)": (channel(f64, "data"), 2),
        "checked, int into Int32 (range)": (channel("std_msgs/msg/Int32", "data"), 7),
        "checked, bool into Bool": (channel("std_msgs/msg/Bool", "data"), True),
        "unchecked write (baseline), Twist dict": (
            channel("geometry_msgs/msg/Twist", None, UncheckedChannel), twist),
        "checked, Twist dict (6 fields)": (channel("geometry_msgs/msg/Twist", None), twist),
    }
    results: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(args.repeats):
        for name, (ch, value) in cases.items():
            write = ch.write
            elapsed = timeit.timeit(lambda w=write, v=value: w(v), number=args.writes)
            results[name].append(elapsed / args.writes * 1e9)
    scalar = statistics.median(results["unchecked write (baseline), float"])
    whole = statistics.median(results["unchecked write (baseline), Twist dict"])
    print(f"{'case':42} {'median ns':>10} {'vs baseline':>12}")
    for name, samples in results.items():
        base = whole if "Twist" in name else scalar
        median = statistics.median(samples)
        print(f"{name:42} {median:10.0f} {median - base:+11.0f}")


if __name__ == "__main__":
    main()
