"""Cost of a non-blocking read on incoming channels, with and without a fail-safe.

    .venv/bin/python benchmarks/failsafe_read.py [--repeats 15] [--reads 200000]

Three channels of one value each, read in interleaved rounds (so load changes hit all three
alike); prints the median ns per read of each and its ratio to a plain ``Channel``. An
``on_lost="hold"`` channel (the default) is a plain ``IncomingChannel``; ``SafeValue``/``"raise"``
make it a ``GuardedChannel`` whose read first checks the link flag.
"""

from __future__ import annotations

import argparse
import statistics
import timeit

from rlbridge.client.channels.failsafe import GuardedChannel, SafeValue, fail_safe
from rlbridge.client.channels.incoming import IncomingChannel
from rlbridge.client.session.link_events import LinkEvents
from rlbridge.csp.channel import Channel


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--reads", type=int, default=200_000)
    args = parser.parse_args()
    plain: Channel[float] = Channel(1, blocking=False, initial=0.0)
    hold = IncomingChannel(1, "/t", "std_msgs/msg/Float64", "data", transport="udp",
                           blocking=False, buffer_size=1, initial=0.0)
    guarded = GuardedChannel(2, "/t", "std_msgs/msg/Float64", "data", transport="udp",
                             blocking=False, buffer_size=1, initial=0.0)
    guarded.failsafe = fail_safe(SafeValue(0.0), LinkEvents())
    cases = {"Channel.read": plain, "IncomingChannel.read (on_lost='hold')": hold,
             "GuardedChannel.read (SafeValue, link up)": guarded}
    results: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(args.repeats):
        for name, ch in cases.items():
            results[name].append(timeit.timeit(ch.read, number=args.reads) / args.reads * 1e9)
    base = statistics.median(results["Channel.read"])
    for name, samples in results.items():
        median = statistics.median(samples)
        print(f"{name:42s} median {median:7.1f} ns/read  x{median / base:.2f}")


if __name__ == "__main__":
    main()
