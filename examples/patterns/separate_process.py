"""The HRT loop in its own OS process; the bridge in this one; values cross in shared memory.

The design that kept a 1 kHz loop at the timing of a loop without the bridge (docs/jitter.md,
docs/gil.md): the loop's interpreter holds nothing but the loop, so no SDK thread and no SRT
Python code can hold its GIL. This process keeps the Bridge, a non-blocking subscription and
the SDK's send loop, and a lower-priority pump moves the latest set-point into a shared-memory
slot and the loop's outputs out of a shared-memory ring.

    rlbridge serve &  python examples/patterns/separate_process.py --port 7411
"""

from __future__ import annotations

import math

from _common import F64, OUTPUT, SETPOINT, parser, publisher, wait_for_publisher

from rlbridge import Bridge, Coupling, HrtProcess, Parallel, ShmLink, Ticker, forwarder


def control_loop(link: ShmLink, period: float, cycles: int) -> None:
    """Runs in the loop process (spawned: only its arguments cross). Input slot 0, ring 0."""
    state = {"y": 0.0, "k": 0}

    def body() -> None:  # a first-order filter on the set-point, and a sine out
        state["y"] += 0.05 * (link.get(0) - state["y"])
        state["k"] += 1
        link.push(0, state["y"] + 0.1 * math.sin(state["k"] * period))

    coupling = Coupling("separate-process", body, period=period, cycles=cycles)
    stats = coupling.run()
    print(f"loop process: {coupling.loop.released} releases, {stats.missed} missed; lateness "
          f"p50 {stats.p50_ns / 1e3:.0f} us, p99 {stats.p99_ns / 1e3:.0f} us, "
          f"max {stats.max_ns / 1e3:.0f} us", flush=True)


def main() -> None:
    p = parser(__doc__ or "")
    p.add_argument("--no-publish", dest="publish", action="store_false")
    p.add_argument("--pump-hz", type=float, default=1000.0, help="shared memory <-> bridge")
    args = p.parse_args()
    period = args.period_us / 1e6
    seconds = args.cycles * period + 5
    with publisher(args.host, args.port, seconds, args.publish), \
            Bridge.connect(args.host, args.port, nodelay=True,
                           send_rate_hz=args.pump_hz) as bridge, \
            ShmLink.create(inputs=1, outputs=1) as link:
        if args.publish:
            wait_for_publisher(bridge)
        incoming = bridge.subscribe(SETPOINT, F64, blocking=False, initial=0.0)
        out = bridge.publish(OUTPUT, F64, through_buffer=True)
        pump = Parallel(Ticker(forwarder(link, [incoming], [out]), args.pump_hz,
                               name="shm-pump"), name="sdk-side")
        loop = HrtProcess(link, control_loop, period, args.cycles)
        pump.start()
        try:
            loop.start()
            loop.join(seconds + 30)
        finally:
            loop.stop()
            pump.stop()
            pump.join(10)
        print(f"  in: {incoming.statistics()}")
        print(f"  out: {out.statistics()}")
        print(f"  ring dropped {link.dropped(0)}, loop exit code {loop.exitcode}")


if __name__ == "__main__":
    main()
