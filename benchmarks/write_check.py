"""Cost of the write-time type check on ``OutgoingChannel.write``, next to an unchecked write.

    .venv/bin/python benchmarks/write_check.py [--repeats 41] [--writes 50000]

The baseline is ``OutgoingChannel.write`` without the check (the method as it was before the
check, in a subclass below), run in the same interleaved rounds as the checked cases, so load
changes hit every row alike. Prints the median ns per write of each case and the median of
its differences to the baseline of the same round. Channels are built as ``Bridge.publish``
builds them, bound with the schema the server sends (``TopicAck.schema``), without a server:
only the write is timed.
"""

from __future__ import annotations

import argparse
import functools
import statistics
import threading
import time
import timeit
from typing import Any

from rlbridge.adapters.inproc import InProcessBus
from rlbridge.csp.bridge_channels import OutgoingChannel
from rlbridge.csp.channel import Doorbell
from rlbridge.errors import ChannelClosed
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
    parser.add_argument("--repeats", type=int, default=41)
    parser.add_argument("--writes", type=int, default=50_000)
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
    names = list(cases)
    for round_ in range(args.repeats):
        # Every round runs every case once, in alternating order: a load change hits all.
        for name in names if round_ % 2 == 0 else reversed(names):
            ch, value = cases[name]
            write = ch.write
            elapsed = timeit.timeit(functools.partial(write, value), number=args.writes)
            results[name].append(elapsed / args.writes * 1e9)
    print(f"{args.repeats} rounds of {args.writes} writes per case; ns per write")
    print(f"{'case':42} {'median':>7} {'paired diff':>12}")
    for name, samples in results.items():
        base = results["unchecked write (baseline), " + (
            "Twist dict" if "Twist" in name else "float")]
        # The difference to the baseline of the same round, then its median: drift between
        # rounds (other jobs on the machine) cancels out.
        diff = statistics.median(s - b for s, b in zip(samples, base, strict=True))
        print(f"{name:42} {statistics.median(samples):7.0f} {diff:+12.0f}")


if __name__ == "__main__":
    main()
