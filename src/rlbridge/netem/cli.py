"""``rlbridge netem ...``: the emulator from the command line.

Each command builds an :class:`~rlbridge.netem.link.EmulatedLink` (or asks about one) and
prints; no logic lives here.  Every failure is one line on stderr and exit code 1, never a
traceback: the usual causes (not root, no ``ip``, no TUN) are the user's to fix.
"""

from __future__ import annotations

import time
from typing import Annotated

import msgspec
import typer

from rlbridge._compat import StrEnum
from rlbridge.netem.availability import emulator_unavailable_reason
from rlbridge.netem.link import EmulatedLink
from rlbridge.netem.netns import NetnsError, cleanup_stale_namespaces
from rlbridge.netem.probe import ProbeError, measure_overhead
from rlbridge.netem.relay_process import RelayError
from rlbridge.netem.signals import Terminated, sigterm_raises
from rlbridge.netem.stats import DirectionStats, LinkStats

MAX_DURATION_S = 3600.0

RT_PRIORITY_OPTION = typer.Option(
    help="Run the relay SCHED_FIFO at this priority (1-99; 0 = normal scheduling). "
    "Keeps the emulated delay accurate on a busy machine.",
    min=0,
    max=99,
)

netem_app = typer.Typer(
    help=(
        "Emulate delay and loss between two network namespaces without the netem qdisc "
        "(needs root, iproute2 and /dev/net/tun)."
    ),
    no_args_is_help=True,
)


class DirectionChoice(StrEnum):
    """Which direction(s) the impairment applies to."""

    both = "both"
    a_to_b = "a_to_b"
    b_to_a = "b_to_a"


def _fail(message: str) -> typer.Exit:
    typer.echo(f"rlbridge netem: {message}", err=True)
    return typer.Exit(code=1)


def _require_emulator() -> None:
    reason = emulator_unavailable_reason()
    if reason is not None:
        raise _fail(f"cannot run: {reason}")


def _format_direction(name: str, s: DirectionStats) -> str:
    return (
        f"  {name}: received {s.received}, delivered {s.delivered}, "
        f"dropped {s.dropped_loss} (loss) + {s.dropped_queue} (queue), "
        f"write errors {s.write_errors}, relay lateness mean {s.late_mean_us:.0f} us "
        f"max {s.late_max_us:.0f} us, >1 ms {s.late_over_1ms} packets"
    )


def _format_stats(stats: LinkStats) -> str:
    return "\n".join(
        [_format_direction("a_to_b", stats.a_to_b), _format_direction("b_to_a", stats.b_to_a)]
    )


@netem_app.command()
def check() -> None:
    """Say whether the emulator can run on this machine, and if not, why."""
    _require_emulator()
    typer.echo("rlbridge netem: the emulator can run here")


@netem_app.command()
def shell(
    *,
    delay: Annotated[float, typer.Option(help="One-way delay in ms.", min=0.0)] = 0.0,
    loss: Annotated[float, typer.Option(help="Loss in percent.", min=0.0, max=100.0)] = 0.0,
    jitter: Annotated[float, typer.Option(help="Uniform jitter +- ms.", min=0.0)] = 0.0,
    seed: Annotated[int, typer.Option(help="Seed of the loss and jitter RNGs.")] = 1,
    direction: Annotated[
        DirectionChoice, typer.Option(help="Impaired direction; the other one is clean.")
    ] = DirectionChoice.both,
    duration: Annotated[
        float,
        typer.Option(
            help="Seconds until teardown (Ctrl-C ends earlier).", min=0.1, max=MAX_DURATION_S
        ),
    ] = 60.0,
    mtu: Annotated[int, typer.Option(help="MTU of the link.", min=68, max=65535)] = 1500,
    rt_priority: Annotated[int, RT_PRIORITY_OPTION] = 0,
) -> None:
    """Bring up two namespaces joined by an impaired link, wait, then tear it all down.

    Run programs on either side from another terminal with `ip netns exec NAME ...`.
    Everything still running in the namespaces is terminated at teardown.
    """
    _require_emulator()
    try:
        with (
            sigterm_raises(),
            EmulatedLink(
                delay,
                loss,
                jitter,
                seed,
                direction.value,
                mtu=mtu,
                max_lifetime_s=duration + 30.0,
                relay_rt_priority=rt_priority or None,
            ) as link,
        ):
            typer.echo(
                f"link up for {duration:g} s (Ctrl-C to stop earlier)\n"
                f"  A: namespace {link.ns_a}  address {link.addr_a}\n"
                f"  B: namespace {link.ns_b}  address {link.addr_b}\n"
                f"  interface {link.ifname} in both, MTU {link.mtu}\n"
                f"  a_to_b: {msgspec.json.encode(link.impairments[0]).decode()}\n"
                f"  b_to_a: {msgspec.json.encode(link.impairments[1]).decode()}\n"
                f"run commands with:  ip netns exec {link.ns_a} COMMAND ...\n"
                f"             and:  ip netns exec {link.ns_b} COMMAND ..."
            )
            try:
                time.sleep(duration)
                how = "duration elapsed"
            except KeyboardInterrupt:
                how = "interrupted"
            except Terminated:
                how = "terminated"
            typer.echo(f"{how}; tearing down\n{_format_stats(link.stats())}")
    except (NetnsError, RelayError, OSError, ValueError) as exc:
        raise _fail(str(exc)) from None


@netem_app.command()
def calibrate(
    *,
    count: Annotated[int, typer.Option(help="Pings per measurement.", min=10, max=100_000)] = 1000,
    payload: Annotated[int, typer.Option(help="UDP payload bytes.", min=4, max=1472)] = 32,
    delay: Annotated[
        float, typer.Option(help="One-way delay in ms to emulate while measuring.", min=0.0)
    ] = 0.0,
    interval: Annotated[
        float, typer.Option(help="Pause between pings in ms (10 = the thesis's 100 Hz).", min=0.0)
    ] = 0.0,
    rt_priority: Annotated[int, RT_PRIORITY_OPTION] = 0,
) -> None:
    """Measure what the relay itself adds to a UDP round trip (beyond 2 x --delay)."""
    _require_emulator()
    try:
        with (
            sigterm_raises(),
            EmulatedLink(
                delay, max_lifetime_s=600.0, relay_rt_priority=rt_priority or None
            ) as link,
        ):
            result = measure_overhead(
                link, count=count, payload=payload, interval_s=interval / 1000.0
            )
    except (NetnsError, RelayError, ProbeError, OSError, ValueError) as exc:
        raise _fail(str(exc)) from None
    excess = result.added_median_us - 2000.0 * delay
    typer.echo(
        f"UDP echo, {count} pings of {payload} bytes every {interval:g} ms, "
        f"delay {delay:g} ms each way\n"
        f"  through the link:  {result.link}\n"
        f"  loopback in ns A:  {result.loopback}   (same echo, no relay)\n"
        f"  added by the relay (two hops, beyond 2 x delay): median {excess:.0f} us\n"
        f"  relay lateness after release time: mean {result.relay_late_mean_us:.0f} us, "
        f"max {result.relay_late_max_us:.0f} us"
    )


@netem_app.command()
def cleanup(
    *,
    kill_processes: Annotated[
        bool, typer.Option(help="Also terminate processes left inside stale namespaces.")
    ] = False,
) -> None:
    """Delete rlb-* namespaces left behind by runs that were killed before teardown."""
    _require_emulator()
    try:
        removed = cleanup_stale_namespaces(kill_processes=kill_processes)
    except NetnsError as exc:
        raise _fail(str(exc)) from None
    for ns in removed:
        left = ""
        if ns.remaining_pids and not kill_processes:
            left = f", processes left running: {list(ns.remaining_pids)}"
        typer.echo(f"removed {ns.name} (owner pid {ns.owner_pid} is gone){left}")
    if not removed:
        typer.echo("no stale rlb-* namespaces")
