"""``rlbridge topic pub|echo|hz|list``: topics through a running server, from the shell.

Each command is an SDK client (:class:`~rlbridge.Bridge`) for as long as it runs; the options
that reach a server are the shared ones (:mod:`rlbridge.cli_options`).
"""

from __future__ import annotations

import itertools
import json
import math
import statistics
import time
from typing import Annotated, Any

import typer

from rlbridge.cli_errors import fail, one_line_errors
from rlbridge.cli_options import (
    DEFAULT_CHANNEL,
    LOCAL_SERVER,
    ChannelChoice,
    Field,
    ServerTarget,
    TransportOpt,
    channel_options,
    checked_transport,
    option,
    server_options,
)

topic_app = typer.Typer(help="Publish, echo, measure and list topics through a running server.",
                        no_args_is_help=True)


def _parse_value(text: str) -> Any:
    """JSON when it parses (numbers, true, objects), the raw text otherwise (strings)."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


@topic_app.command("pub")
@one_line_errors
@server_options
@channel_options
def topic_pub(
    topic: str,
    msg_type: Annotated[str, typer.Argument(metavar="TYPE", help="e.g. std_msgs/msg/Float64")],
    value: Annotated[str, typer.Argument(help="JSON value: 1.5, true, \"text\", {\"x\": 1}")],
    field: Field = "data",
    rate: Annotated[float, typer.Option(help="Publish at this rate (Hz); 0 = once.")] = 0.0,
    count: Annotated[int, typer.Option(help="Number of messages (with --rate).")] = 1,
    transport: TransportOpt = "udp",
    server: ServerTarget = LOCAL_SERVER,
    channel: ChannelChoice = DEFAULT_CHANNEL,
) -> None:
    """Publish VALUE on TOPIC through the bridge.

    Exits 0 only once the server has counted every value; a value it refuses (not the
    channel's type, over its --max-rate) or a datagram that never arrives makes it exit 1,
    saying how many of how many the server took.
    """
    from rlbridge.cli_delivery import confirm_delivery

    parsed = _parse_value(value)
    with server.connect("rlbridge-topic-pub") as bridge:
        out = bridge.publish(topic, msg_type, field or None, transport=checked_transport(transport),
                             qos=channel.qos(), policy=channel.policy())
        n = max(1, count) if rate > 0 else 1
        period = 1.0 / rate if rate > 0 else 0.0
        start = time.monotonic()
        for i in range(n):
            try:
                out.write(parsed)
            except TypeError as exc:  # the SDK checks the value against the field's type
                raise fail(str(exc), 2) from None
            if i + 1 < n:
                time.sleep(max(0.0, start + (i + 1) * period - time.monotonic()))
        bridge.send(wait=True)
        confirm_delivery(bridge, out, n)
    typer.echo(f"published {n} message(s) on {topic}")


@topic_app.command("echo")
@one_line_errors
@server_options
@channel_options
def topic_echo(
    topic: str,
    msg_type: Annotated[str, typer.Argument(metavar="TYPE")],
    field: Field = "data",
    count: Annotated[int, typer.Option(help="Exit after this many values (0 = never).")] = 0,
    transport: TransportOpt = "udp",
    timeout: Annotated[float, typer.Option(help="Exit with an error after this many seconds "
                                                "without a value (0 = wait forever).")] = 0.0,
    server: ServerTarget = LOCAL_SERVER,
    channel: ChannelChoice = DEFAULT_CHANNEL,
) -> None:
    """Print each value published on TOPIC, one JSON document per line."""
    with server.connect("rlbridge-topic-echo") as bridge:
        ch = bridge.subscribe(topic, msg_type, field or None,
                              transport=checked_transport(transport),
                              qos=channel.qos(), policy=channel.policy(),
                              blocking=True, buffer_size=4096)
        seen = 0
        while count == 0 or seen < count:
            try:
                v = _read_while_open(bridge, ch, timeout or None)
            except TimeoutError:
                raise fail(f"no value on {topic} within {timeout} s") from None
            typer.echo(json.dumps(v))
            seen += 1


def _read_while_open(bridge: Any, ch: Any, timeout: float | None) -> Any:
    """A blocking read that gives up once the session ends (the server stopped or closed it).

    Waits in short slices for ``--timeout``; the end of the session (the tools do not
    reconnect) closes the channel, which ends the read with ``ChannelClosed``.
    """
    from rlbridge.csp.connection import ConnectionClosed
    from rlbridge.errors import ChannelClosed

    deadline = None if timeout is None else time.monotonic() + timeout
    while True:
        left = 0.25 if deadline is None else min(0.25, deadline - time.monotonic())
        if left <= 0:
            raise TimeoutError
        try:
            return ch.read(timeout=left)
        except ChannelClosed:
            raise ConnectionClosed(bridge.close_reason) from None
        except TimeoutError:
            if bridge.closed:
                raise ConnectionClosed(bridge.close_reason) from None


@topic_app.command("hz")
@one_line_errors
@server_options
@channel_options
def topic_hz(
    topic: str,
    msg_type: Annotated[str, typer.Argument(metavar="TYPE")],
    field: Field = "data",
    window: Annotated[int, typer.Option(help="Messages in the rate window.")] = 10000,
    duration: Annotated[float, typer.Option(help="Stop after this many seconds (0 = never).")]
    = 0.0,
    transport: TransportOpt = "udp",
    server: ServerTarget = LOCAL_SERVER,
    channel: ChannelChoice = DEFAULT_CHANNEL,
) -> None:
    """Measure the publishing rate of TOPIC, like `rostopic hz` (printed every second).

    With --duration, exits 1 if no value arrived in that time (like echo's --timeout).
    """
    from rlbridge.errors import ChannelClosed

    with server.connect("rlbridge-topic-hz") as bridge:
        ch = bridge.subscribe(topic, msg_type, field or None,
                              transport=checked_transport(transport),
                              qos=channel.qos(), policy=channel.policy(),
                              blocking=True, buffer_size=65536)
        arrivals: list[float] = []
        end = time.monotonic() + duration if duration > 0 else math.inf
        next_report = time.monotonic() + 1.0
        while time.monotonic() < end:
            try:
                ch.read(timeout=min(1.0, max(0.01, end - time.monotonic())))
            except (TimeoutError, ChannelClosed):
                if bridge.closed:
                    from rlbridge.csp.connection import ConnectionClosed

                    raise ConnectionClosed(bridge.close_reason) from None
            else:
                arrivals.append(time.monotonic())
                arrivals.extend(time.monotonic() for _ in ch.read_many(1 << 16))
                del arrivals[:-window]
            if time.monotonic() >= next_report:
                next_report += 1.0
                typer.echo(format_rate(arrivals))
        typer.echo(format_rate(arrivals))
        if not arrivals:
            raise fail(f"no value on {topic} within {duration:g} s")


def format_rate(arrivals: list[float]) -> str:
    """rostopic-hz-style line from arrival times."""
    if len(arrivals) < 2:
        return "no new messages"
    gaps = [b - a for a, b in itertools.pairwise(arrivals)]
    mean = statistics.fmean(gaps)
    rate = 1.0 / mean if mean > 0 else math.inf
    std = statistics.pstdev(gaps)
    return (f"average rate: {rate:.3f}\n\tmin: {min(gaps):.6f}s max: {max(gaps):.6f}s "
            f"std dev: {std:.6f}s window: {len(arrivals)}")


@topic_app.command("list")
@one_line_errors
@server_options
def topic_list(
    server: ServerTarget = LOCAL_SERVER,
    show_types: Annotated[bool, option("--show-types", "Print types too.")]
    = False,
) -> None:
    """List the topics the server's middleware knows."""
    with server.connect("rlbridge-topic-list") as bridge:
        for name, msg_type in bridge.server_stats()["topics"]:
            typer.echo(f"{name} [{msg_type}]" if show_types else name)
