"""A coupling whose HRT loop runs in its own OS process: the patterns' default layout.

Why the default: in one interpreter the loop shares the GIL with the SDK's receive and send
threads and with the pattern's helpers; when the OS preempts one of them while it holds the
GIL, the loop's wake-up waits for it, whatever the loop's priority. In-process patterns were
+74 to +370 us worse than the loop alone at p99 on the development machine, the loop in its
own process was at the reference (docs/gil.md, docs/jitter.md). So the recipes of
:mod:`rlbridge.hrt.patterns` put the loop in a spawned process by default, with nothing in its
interpreter but the loop, and keep the bridge, its threads and the pattern's SRT helpers in
the calling process. Values cross in a :class:`~rlbridge.hrt.shm.ShmLink` that neither side
locks: one latest-value slot in (receive patterns) or one SPSC ring out (send patterns).

What that asks of the control law: it runs in the other process, so it must be picklable (a
module-level function, or an instance of a module-level class) and its state lives there;
after the run :attr:`IsolatedCoupling.final_control` holds the law as the loop left it.
Values are ``float64``: a receive law gets a ``float``, a send law must return a number. The
loop process is started with ``spawn`` and imports the module that defines the law, your
script included: its main code belongs under ``if __name__ == "__main__":``.

Lifetimes: :meth:`IsolatedCoupling.run` (or the owner thread of ``start()``) owns, in order,
the SRT helper threads, the loop process and the result pipe; it stops them in reverse order,
drains what the loop pushed after the helpers stopped (no value written by the loop is lost),
closes the channels the recipe created and unlinks the segment. A loop process that dies is an
error in ``run()``/``join()``, with its traceback.
"""

from __future__ import annotations

import multiprocessing
import pickle
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import Connection, wait
from typing import Any, Final, Literal

from rlbridge.client.channels.incoming import OutgoingChannel
from rlbridge.csp.channel import Channel
from rlbridge.csp.process import Parallel, Process, RunScope
from rlbridge.csp.timer import LatenessStats
from rlbridge.hrt.coupling import BaseCoupling, Coupling
from rlbridge.hrt.gil import HRT_SWITCH_INTERVAL
from rlbridge.hrt.rtenv import prepare_hrt_process, thread_scheduling
from rlbridge.hrt.shm import HrtProcess, ShmLink

__all__ = ["DEFAULT_LAYOUT", "IsolatedCoupling", "Layout", "LoopReport", "LoopSpec",
           "check_picklable"]

Layout = Literal["process", "thread"]
"""Where a recipe runs the HRT loop: its own OS process (default) or a thread of this one."""

DEFAULT_LAYOUT: Final[Layout] = "process" if ShmLink.supported() else "thread"
"""The recipes' default: the loop's own process wherever the shared-memory link runs (x86 and
x86-64); in-process elsewhere, where :class:`~rlbridge.hrt.shm.ShmLink` cannot order its
stores without a fence Python does not have (docs/gil.md)."""

LoopKind = Literal["receive", "send"]

_REPORT_GRACE: Final = 10.0
"""Seconds the loop process gets to send its report after its loop has ended."""


@dataclass(frozen=True)
class LoopSpec:
    """What the loop process runs; crosses to it pickled, with the control law."""

    name: str
    kind: LoopKind
    period: float = 0.001
    cycles: int | None = None
    priority: bool = True
    cpu: int | None = None
    switch_interval: float | None = HRT_SWITCH_INTERVAL
    mlock: bool = True


@dataclass
class LoopReport:
    """What the loop process sends back once its loop has ended."""

    stats: LatenessStats
    lateness_ns: list[int]
    released: int
    info: dict[str, Any] = field(default_factory=dict)
    control: Any = None
    error: str | None = None


def check_picklable(control: object, what: str) -> None:
    """Refuse, with the way out, a control law that cannot cross to the loop process."""
    try:
        pickle.dumps(control)
    except Exception as exc:  # pickle raises several types for the same mistake
        raise TypeError(
            f"{what}: the control law {control!r} cannot be sent to the loop's own process "
            f"({type(exc).__name__}: {exc}). Use a module-level function or an instance of a "
            "module-level class (in a script, keep the main code under if __name__ == "
            "'__main__': the loop process imports it), or pass layout='thread' to run the "
            "loop in this process (docs/gil.md says what that costs)") from None


def _loop_body(link: ShmLink, kind: LoopKind, control: Callable[..., Any],
               info: dict[str, Any], run: list[Coupling]) -> Callable[[], None]:
    """One release in the loop process: the law around a slot read or a ring push.

    ``run`` holds the loop's coupling once it exists; the owner's stop word ends it. The
    scheduling the loop really runs with is recorded from inside it, on the first release.
    """
    if kind == "receive":
        get = link.get

        def step() -> None:
            control(get(0))
    else:
        push = link.push

        def step() -> None:
            push(0, float(control()))

    count = link.count_release
    first = [True]

    def body() -> None:
        if link.stop_requested:
            run[0].stop()
            return
        if first[0]:
            first[0] = False
            info.update(thread_scheduling())
        count()
        step()

    return body


def _loop_main(link: ShmLink, spec: LoopSpec, control: Callable[..., Any],
               results: Connection) -> None:
    """The loop process (spawned): run the loop, send one :class:`LoopReport`, exit."""
    info: dict[str, Any] = dict(prepare_hrt_process(spec.mlock))
    holder: list[Coupling] = []
    body = _loop_body(link, spec.kind, control, info, holder)
    coupling = Coupling(spec.name, body, period=spec.period, cycles=spec.cycles,
                        priority=spec.priority, cpu=spec.cpu,
                        switch_interval=spec.switch_interval)
    holder.append(coupling)
    error = None
    try:
        coupling.run()
    except BaseException:  # reported to the owner, which raises it
        error = traceback.format_exc()
    info["torn_reads"] = link.torn_reads
    info["ring_dropped"] = link.dropped(0) if link.outputs else 0
    try:
        pickle.dumps(control)
        final = control
    except Exception:  # the law's state grew something unpicklable: report without it
        final = None
    report = LoopReport(coupling.stats(), coupling.lateness_ns(), coupling.released, info,
                        final, error)
    try:
        results.send(report)
    except OSError:  # the owner stopped waiting (Ctrl-C in it): nobody to report to
        pass
    finally:
        results.close()


class _Owner(Process):
    """The owner of one isolated run: SRT helpers, the loop process, the result pipe."""

    def __init__(self, coupling: IsolatedCoupling) -> None:
        super().__init__(name=coupling.name)
        self._c = coupling

    def execute(self, scope: RunScope) -> None:
        c = self._c
        context = multiprocessing.get_context("spawn")
        receiver, sender = context.Pipe(duplex=False)
        helpers = Parallel(*c.helpers, name=f"{c.name}:srt") if c.helpers else None
        loop = HrtProcess(c.link, _loop_main, c.spec, c.control, sender,
                          name=f"{c.name}:hrt")
        try:
            if helpers is not None:
                helpers.start()
            loop.start()
            sender.close()  # the loop process holds the only writing end now
            c.report = _await_report(receiver, loop, scope.stop, c.link)
        finally:
            receiver.close()
            loop.stop()
            try:
                if helpers is not None:
                    helpers.stop()
                    c.close_channels()  # wakes a helper blocked on an incoming channel
                    helpers.join()
                if c.finish is not None:
                    c.finish()  # after the helpers: what the loop pushed last goes out too
            finally:
                c.close_channels()
                c.link.close()
        if c.report.error is not None:
            raise RuntimeError(f"the loop process of {c.name!r} failed:\n{c.report.error}")


def _await_report(receiver: Connection, loop: HrtProcess, stop: threading.Event,
                  link: ShmLink) -> LoopReport:
    """Wait for the loop's report; pass a stop on; a process that dies is an error."""
    asked_at: float | None = None
    while True:
        ready = wait([receiver, loop.sentinel], timeout=0.05)
        if receiver in ready or (ready and receiver.poll(0.5)):
            try:
                report: LoopReport = receiver.recv()
            except EOFError:
                break  # it died before sending
            return report
        if ready:  # the process ended and nothing is in the pipe
            break
        if stop.is_set():
            if asked_at is None:
                asked_at = time.monotonic()
                link.request_stop()
            elif time.monotonic() - asked_at > _REPORT_GRACE:
                raise RuntimeError("the loop process did not stop within "
                                   f"{_REPORT_GRACE:g} s of being asked to")
    loop.join(1.0)
    raise RuntimeError(f"the loop process ended without a report (exit code {loop.exitcode}:"
                       " killed, or a crash of the interpreter itself)")


class IsolatedCoupling(BaseCoupling):
    """An HRT loop in its own process, SRT helpers in this one, a shared-memory link between.

    Built by the recipes of :mod:`rlbridge.hrt.patterns` (``layout="process"``, their
    default); see the module docstring for what the control law must be. ``helpers`` run
    as threads of this process while the loop runs; ``finish`` runs once after they have
    stopped (a last drain of the ring). :attr:`released` counts live (the loop bumps a
    shared counter); :meth:`stats` and :meth:`lateness_ns` are the loop's own figures,
    available when the run has ended. :attr:`loop_info` says what the loop process was
    given (scheduling policy, CPUs, switch interval, memory lock), recorded inside it.
    """

    def __init__(
        self,
        spec: LoopSpec,
        control: Callable[..., Any],
        link: ShmLink,
        *,
        helpers: Sequence[Process] = (),
        finish: Callable[[], None] | None = None,
        channels: dict[str, Channel[Any] | OutgoingChannel] | None = None,
        closers: Sequence[Callable[[], None]] = (),
    ) -> None:
        super().__init__(spec.name, channels=channels, closers=closers)
        check_picklable(control, spec.name)
        self.spec = spec
        self.control = control
        self.link = link
        self.helpers = tuple(helpers)
        self.finish = finish
        self.report = LoopReport(LatenessStats(0, 0, 0, 0, 0, 0), [], 0)
        self.process = _Owner(self)

    @property
    def released(self) -> int:
        """Releases of the loop so far (read from the shared counter while it runs)."""
        if self.report.released or self.link.closed:
            return self.report.released
        try:
            return self.link.releases
        except ValueError:  # the owner detached the segment meanwhile: the run has ended
            return self.report.released

    def stats(self) -> LatenessStats:
        """The loop's lateness statistics; zeros until the run has ended."""
        return self.report.stats

    def lateness_ns(self) -> list[int]:
        """Per-release lateness in nanoseconds; empty until the run has ended."""
        return self.report.lateness_ns

    @property
    def loop_info(self) -> dict[str, Any]:
        """Scheduling, CPUs, switch interval and memory lock the loop actually ran with."""
        return self.report.info

    @property
    def final_control(self) -> Any:
        """The control law as the loop process left it (``None`` before the end)."""
        return self.report.control

    def __repr__(self) -> str:
        return f"<IsolatedCoupling {self.name!r} helpers={len(self.helpers)}>"
