"""The ``shm-*`` scenarios: the HRT loop in its own process, values through shared memory.

The worker process becomes the SDK process: a ``Bridge`` (non-blocking subscription in, SDK
send loop at 1 kHz out) and a 1 kHz pump (:func:`rlbridge.csp.shm.forwarder`) between the
bridge channels and a :class:`~rlbridge.csp.shm.ShmLink`. The measured loop runs in an
:class:`~rlbridge.csp.shm.HrtProcess` with the same treatment as every other loop
(:func:`~benchmarks.jitter.worker.prepare_process`, ``PriParallel``, ``--cpu``); its
interpreter holds nothing but the loop, so no SDK thread can hold its GIL.
"""

from __future__ import annotations

import argparse
import json
import threading
from pathlib import Path
from typing import Any

from benchmarks.jitter.config import F64, TOPIC_IN, TOPIC_IN_FAST, TOPIC_OUT
from benchmarks.jitter.worker import (
    loop_options,
    prepare_process,
    probed,
    receive_law,
    run_measured,
    send_law,
    wait_first_value,
)
from rlbridge.csp.bridge import Bridge
from rlbridge.csp.coupling import Coupling, Ticker
from rlbridge.csp.process import Parallel
from rlbridge.csp.shm import HrtProcess, ShmLink, forwarder

PUMP_HZ = 1000.0


def hrt_loop(link: ShmLink, options: dict[str, Any], mlock: bool, result: str) -> None:
    """The loop process (spawned): read slot 0, push one value to ring 0, every cycle."""
    info = prepare_process(mlock)
    recv, send = receive_law(), send_law()
    get, push = link.get, link.push

    def body() -> None:
        recv(get(0))
        push(0, send())

    coupling = Coupling("shm", probed(body, info), **options)
    stop = threading.Event()
    data = run_measured(coupling, "shm", info, stop, [],
                        options["cycles"] * options["period"] + 15.0, cpu=options["cpu"])
    stop.set()
    data["info"]["ring_dropped"] = link.dropped(0)
    data["info"]["torn_reads"] = link.torn_reads
    Path(result).write_text(json.dumps(data))


def shm_parent(args: argparse.Namespace) -> dict[str, Any]:
    """The SDK process: bridge, pump, and the loop process; returns the loop's result."""
    topic = TOPIC_IN_FAST if args.scenario == "shm-1000" else TOPIC_IN
    child_result = args.result + ".child"
    options = loop_options(args)
    with Bridge.connect("127.0.0.1", args.port, nodelay=True, send_rate_hz=PUMP_HZ,
                        name=f"bench-{args.scenario}") as bridge, \
            ShmLink.create(inputs=1, outputs=1) as link:
        incoming = bridge.subscribe(topic, F64, blocking=False, initial=0.0)
        out = bridge.publish(TOPIC_OUT, F64, through_buffer=True)
        if not wait_first_value(incoming):
            raise SystemExit(f"no value arrived on {topic} within 5 s: is the publisher up?")
        pump = Parallel(Ticker(forwarder(link, [incoming], [out]), PUMP_HZ, name="shm-pump"),
                        name="shm-sdk")
        loop = HrtProcess(link, hrt_loop, options, args.mlock, child_result)
        pump.start()
        try:
            loop.start()
            if not loop.join(args.cycles * args.period * 3 + 60):
                raise SystemExit("the loop process did not finish")
        finally:
            loop.stop()
            pump.stop()
            pump.join(10.0)
        if loop.exitcode != 0:
            raise SystemExit(f"the loop process failed (exit {loop.exitcode})")
        data: dict[str, Any] = json.loads(Path(child_result).read_text())
        data["info"]["sdk_values_sent"] = out.statistics().written
        data["info"]["topic_in"] = topic
        return data
