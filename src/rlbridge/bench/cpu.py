"""``rlbridge bench cpu``: CPU per value of one control client with many UDP channels.

The shape of a control loop on a small board: one SDK client publishes ``--channels`` UDP
channels at ``--rate`` Hz each (every tick: one ``write`` per channel into a buffered channel,
then one ``Bridge.send()``) and subscribes to the same topics over UDP, reading what came back
without blocking at every tick. Every value goes client -> server -> in-process bus -> server
-> client, so each value costs the client a send and a receive and the server an input and an
output.

Three rows in the same run, interleaved: ``bundled`` (the default: every channel of a send
round in one datagram, and the server bundles its replies), ``single`` (``bundles=False``: one
datagram per channel and value, both ways; the wire behaviour before bundles) and
``send loop`` (bundled, but the loop never calls ``send()``: the SDK's send loop,
``Bridge.connect(send_rate_hz=rate)``, wakes the send thread on its own timer; the other form
of "send through buffer", whose values wait up to one period). ``inline`` is bundled with
``send(inline=True)`` per tick: the loop's thread sends the round's datagram itself and the
send thread is not woken.

Figures per value (one value written, carried through the server and read back):

* **SDK**: CPU of the SDK's own threads (``rlbridge-send``, ``rlbridge-recv``, from
  ``/proc/<pid>/task``) plus the thread CPU time the control loop spent inside SDK calls
  (``write``, ``send``, ``read_many``; ``time.thread_time`` around them);
* **client process**: everything, including the loop's own timer wake-ups;
* **server**: the whole server process.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from rlbridge.bench.common import (
    CLK_TCK,
    STARTUP_S,
    Control,
    LoopbackLink,
    Params,
    ProcessGroup,
    emit,
    fmt,
    hold,
    markdown_table,
    median,
    ratio,
    report_header,
    start_server,
    wait_for_go,
)
from rlbridge.csp.options import Tuning

MODULE = "rlbridge.bench.cpu"
F64 = "std_msgs/msg/Float64"
#: (row, bundles, the send loop's rate in multiples of ``--rate`` (None: ``send()`` per tick),
#: ``send(inline=True)`` per tick)
ROWS: tuple[tuple[str, bool, float | None, bool], ...] = (
    ("bundled", True, None, False), ("inline", True, None, True),
    ("single", False, None, False), ("send loop", True, 1.0, False))


@dataclass(frozen=True)
class Settings:
    channels: int = 10
    rate_hz: float = 1000.0
    seconds: float = 10.0
    repeats: int = 3


def _threads_cpu_s(tids: Sequence[int | None]) -> float:
    """CPU seconds of these threads of this process (``/proc/self/task/<tid>/stat``)."""
    total = 0.0
    for tid in tids:
        if tid is None:
            continue
        try:
            with open(f"/proc/self/task/{tid}/stat", "rb") as f:
                data = f.read()
        except OSError:  # the thread ended meanwhile
            continue
        fields = data[data.rindex(b")") + 2 :].split()
        total += (int(fields[11]) + int(fields[12])) / CLK_TCK
    return total


def client_role(params: Params) -> None:
    """One SDK client: ``channels`` UDP channels published at ``rate_hz`` and read back."""
    from rlbridge.csp.bridge import Bridge

    control = Control()
    n, rate, seconds = int(params["channels"]), float(params["rate_hz"]), float(params["seconds"])
    send_rate = params.get("send_rate_hz")
    b = Bridge.connect(params["host"], int(params["port"]), name="bench-cpu", timeout=30,
                       tuning=Tuning(bundles=bool(params["bundles"])),
                       send_rate_hz=None if send_rate is None else float(send_rate))
    call_send = send_rate is None
    inline = bool(params.get("inline"))
    topics = [f"/bench/cpu/c{i}" for i in range(n)]
    inboxes = [b.subscribe(t, F64, transport="udp", buffer_size=256) for t in topics]
    outs = [b.publish(t, F64, transport="udp", through_buffer=True) for t in topics]
    emit("ready")
    wait_for_go(control)
    thread_time, monotonic, sleep = time.thread_time, time.monotonic, time.sleep
    ticks = int(seconds * rate)
    in_calls = 0.0
    received = 0
    recv_tid, send_tid, other_tid = b._io_thread_ids()  # receive, send, reconnect threads
    recv0, send0, other0 = (_threads_cpu_s([t]) for t in (recv_tid, send_tid, other_tid))
    process0, start = time.process_time(), monotonic()
    for i in range(ticks):
        delay = start + i / rate - monotonic()
        if delay > 0:
            sleep(delay)
        t0 = thread_time()
        value = float(i)
        for out in outs:
            out.write(value)
        if call_send:
            b.send(inline=inline)
        for inbox in inboxes:
            received += len(inbox.read_many())
        in_calls += thread_time() - t0
    end = monotonic() + 1.0  # the last values' way back
    while received < ticks * n and monotonic() < end:
        sleep(0.001)
        t0 = thread_time()
        for inbox in inboxes:
            received += len(inbox.read_many())
        in_calls += thread_time() - t0
    recv_s, send_s = _threads_cpu_s([recv_tid]) - recv0, _threads_cpu_s([send_tid]) - send0
    emit("result", sent=ticks * n, received=received, seconds=monotonic() - start,
         sdk_s=recv_s + send_s + _threads_cpu_s([other_tid]) - other0 + in_calls,
         recv_s=recv_s, send_s=send_s, calls_s=in_calls,
         process_s=time.process_time() - process0,
         lost=sum(inbox.lost for inbox in inboxes))
    hold(control)


ROLES = {"client": client_role}


def run(settings: Settings, progress: Callable[[str], None]) -> dict[str, list[Params]]:
    """Every row ``repeats`` times, interleaved; fresh server and client per run."""
    results: dict[str, list[Params]] = {key: [] for key, _, _, _ in ROWS}
    for repeat in range(settings.repeats):
        for key, bundles, loop_rate, inline in ROWS:
            with ProcessGroup(LoopbackLink(), lifetime_s=settings.seconds + 120) as group:
                server, host, port = start_server(group)
                client, _ = group.spawn("client", "b", MODULE, "client", {
                    "host": host, "port": port, "channels": settings.channels,
                    "rate_hz": settings.rate_hz, "seconds": settings.seconds,
                    "bundles": bundles, "inline": inline, "send_rate_hz":
                        None if loop_rate is None else loop_rate * settings.rate_hz})
                server.mark_cpu()
                client.send("go")
                result = client.expect("result", settings.seconds + STARTUP_S + 30)
                result["server_s"] = server.cpu_since_mark()
            results[key].append(result)
            progress(f"cpu {key} repeat {repeat + 1}: "
                     f"{_per_value(result, 'sdk_s'):.2f} us/value SDK, "
                     f"{_per_value(result, 'server_s'):.2f} server")
    return results


def _per_value(result: Params, key: str) -> float:
    """CPU µs of ``key`` per value read back."""
    got = int(result["received"])
    return float(result[key]) / got * 1e6 if got else float("nan")


def report(results: dict[str, list[Params]], settings: Settings, command: Sequence[str]) -> str:
    s = settings
    medians = {key: {k: median([_per_value(r, k) for r in runs])
                     for k in ("sdk_s", "calls_s", "send_s", "recv_s", "process_s", "server_s")}
               for key, runs in results.items()}
    rows = []
    for key, runs in results.items():
        m = medians[key]
        sent = median([float(r["sent"]) for r in runs])
        got = median([float(r["received"]) for r in runs])
        rows.append([key, fmt(sent), fmt(got), f"{(1 - got / sent) * 100:.2f} %" if sent else "-",
                     fmt(m["sdk_s"], 2), fmt(m["calls_s"], 2), fmt(m["send_s"], 2),
                     fmt(m["recv_s"], 2), fmt(m["process_s"], 2), fmt(m["server_s"], 2),
                     fmt(ratio(m["sdk_s"], medians["single"]["sdk_s"]), 2),
                     fmt(ratio(m["server_s"], medians["single"]["server_s"]), 2)])
    b = medians["bundled"]
    return "\n".join([
        report_header("CPU per value: one client, many UDP channels", command),
        f"{s.repeats} repeats per row, interleaved; {s.seconds:g} s per run. One SDK client "
        f"publishes {s.channels} UDP channels at {s.rate_hz:g} Hz each (buffered writes, one "
        "`send()` per tick) and reads them back over UDP (non-blocking `read_many` per tick); "
        "every value goes client -> server -> bus -> server -> client. CPU per value read back "
        "(medians): SDK = its send and receive threads plus the loop's time inside SDK calls; "
        "client process = all of it, the loop's timer wake-ups included; server = the whole "
        "server process. `single` is `Tuning(bundles=False)`: one datagram per "
        "channel and value, both ways. `inline` is bundled with `send(inline=True)`: the loop's "
        "thread sends the round's datagram itself, the send thread is not woken. `send loop` "
        "is bundled without `send()`: "
        f"`Bridge.connect(send_rate_hz={s.rate_hz:g})` sends what waits on its own timer.",
        "",
        markdown_table(["row", "values sent", "read back", "lost", "SDK us/value",
                        "of which: loop's SDK calls", "send thread", "receive thread",
                        "client process us/value", "server us/value", "SDK x single",
                        "server x single"], rows),
        "",
        "Targets (bundled):",
        "",
        f"- SDK: {b['sdk_s']:.2f} us per value; target <= 3: {_verdict(b['sdk_s'])}",
        f"- server: {b['server_s']:.2f} us per value; target <= 3: {_verdict(b['server_s'])}",
        *([f"- SDK with `send(inline=True)`: {medians['inline']['sdk_s']:.2f} us per value; "
           f"target <= 3: {_verdict(medians['inline']['sdk_s'])}"]
          if "inline" in medians else []),
    ]) + "\n"


def _verdict(us: float) -> str:
    return "**met**" if us <= 3.0 else "**not met**"
