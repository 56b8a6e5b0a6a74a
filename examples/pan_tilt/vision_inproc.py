#!/usr/bin/env python3
"""The middleware side of the pan-tilt camera without ROS: server + vision node in one process.

It starts a bridge server on rlbridge's in-process bus and two nodes on that bus, next to the
server (as a ROS node would sit next to the bridge on the resource-rich machine):

* the vision node (:class:`rlbridge.demo.vision.VisionNode`) publishes the bearing of a target
  moving on a Lissajous path, 30 times a second, on ``/pan_tilt/{pan,tilt}/setpoint``;
* the monitor (:class:`rlbridge.demo.monitor.Monitor`) records the controller's angles, status
  and diagnostics, which the line printed every second summarizes.

Then start the controller, on this machine or on the board::

    python examples/pan_tilt/vision_inproc.py --host 0.0.0.0 --port 7411 --seconds 30
    python examples/pan_tilt/controller.py --host <this machine> --port 7411

``rlbridge demo --role bridge`` is the same, with the live dashboard and the plot.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading

from rlbridge.demo.dashboard import WINDOW, LineReport, Status
from rlbridge.demo.sides import middleware_side
from rlbridge.demo.topics import Topics
from rlbridge.demo.vision import Dropout


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--host", default="127.0.0.1", help="address to bind")
    parser.add_argument("--port", type=int, default=7411)
    parser.add_argument("--seconds", type=float, default=0.0, help="0: until Ctrl-C")
    parser.add_argument("--namespace", default="/pan_tilt")
    args = parser.parse_args()

    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda _s, _f: stop.set())
    signal.signal(signal.SIGTERM, lambda _s, _f: stop.set())

    with middleware_side(host=args.host, port=args.port, topics=Topics(args.namespace),
                         dropout=Dropout(start=4.0, length=0.5)) as mw:
        print(f"bridge server on {args.host}:{mw.port} (in-process bus), vision at 30 Hz",
              flush=True)
        report = LineReport(sys.stdout)
        while not stop.wait(0.2):
            snap = mw.trace.snapshot(last=WINDOW)
            report.update(Status.of("vision", snap, args.seconds))
            if args.seconds and snap.elapsed >= args.seconds:
                break
        statuses = mw.trace.snapshot().statuses
    print("controller states seen:", " -> ".join(s for _, s in statuses) or "none", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
