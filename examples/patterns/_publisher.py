"""A sine on a topic at a rate, for a bounded time: the receive examples' publisher process.

``_common.publisher`` starts this file with the same interpreter, so it needs nothing but the
installed package (``pip install rlbridge-sdk``). Its own process, so that it does not share the
example's GIL; it reconnects if the server drops its session, until its time is up.
"""

from __future__ import annotations

import argparse
import math
import time

from rlbridge import Bridge, LinkState, PeriodicTimer

F64 = "std_msgs/msg/Float64"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=7411)
    p.add_argument("--topic", default="/example/setpoint")
    p.add_argument("--rate", type=float, default=100.0, help="values per second")
    p.add_argument("--seconds", type=float, default=10.0, help="how long to publish")
    args = p.parse_args()
    timer = PeriodicTimer(1.0 / args.rate, history=1)
    end = time.monotonic() + args.seconds
    k = 0
    while time.monotonic() < end:
        with Bridge.connect(args.host, args.port, nodelay=True, name="example-publisher") as bridge:
            out = bridge.publish(args.topic, F64, transport="udp")
            while time.monotonic() < end and bridge.link_state is not LinkState.LOST:
                timer.wait_next()
                k += 1
                out.write(math.sin(k / args.rate))
        if time.monotonic() < end:
            print(f"publisher: session lost after {k} values; reconnecting", flush=True)


if __name__ == "__main__":
    main()
