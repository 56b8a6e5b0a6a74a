"""The embedded side: a 1 kHz HRT loop and a 50 Hz SRT telemetry process, coupled properly.

Process structure (thesis figures 3.2, 5.3 and 5.6)::

    PriParallel
    ├── Timed(1 ms, hrt=True)   "loop"       read set-points from NON-BLOCKING bridge channels,
    │                                        run PanTiltLoop.cycle, write angles and state
    │                                        changes into local buffered CSP channels
    └── Timed(20 ms)            "telemetry"  read the newest angles (sub-sampling), forward state
                                             changes and diagnostics, then bridge.send()

Why this shape:

* The loop reads its inputs with non-blocking reads of size-1 buffered channels (figure 5.3):
  the newest set-point, or the previous one again; never a wait, never a system call, so the
  arrival pattern of network packets cannot shift the loop's release times.
* The loop never writes to the network. It writes the angle into a non-blocking CSP channel of
  size 1 every cycle, and the lower-priority telemetry process reads the newest value at 50 Hz
  and writes it to an outgoing bridge channel with ``through_buffer=True``, then calls
  ``bridge.send()`` (the sub-sampling pattern, figure 5.6). The network sees 50 angles a second
  per axis instead of 1000, and the loop's cost is one ring write.
* State changes go through a buffered channel that keeps every change (a state that lasts less
  than one telemetry period is still reported), then over TCP, because a status must arrive.
* ``PriParallel`` gives the loop the higher priority (SCHED_FIFO where permitted, otherwise a
  lower nice value for the telemetry, with one warning that says so).

* A lost link puts the loop in ``lost-link`` (hold position) while the SDK reconnects by itself;
  once the bridge is back the set-points are old, so the loop passes through ``safe`` and
  resumes ``tracking`` with the first fresh ones. Outgoing angles and states written during the
  outage wait in their channels (newest angle, every state change up to the buffer) and go out
  after the reconnect; nothing here has to know about it.

Lifetimes: :meth:`start` starts the composition's owner thread; :meth:`close` stops it, joins
it (re-raising a process's error), and sends the final status and diagnostics if the link is
up. The :class:`~rlbridge.csp.bridge.Bridge` belongs to the caller, who closes it afterwards.
"""

from __future__ import annotations

import os
import threading
import time
import uuid
from types import TracebackType

from rlbridge import (
    Bridge,
    Channel,
    ChannelClosed,
    Code,
    ConnectionClosed,
    IncomingChannel,
    LinkState,
    PeriodicTimer,
    PriParallel,
    Timed,
)
from rlbridge.demo.loop import ControllerState, LoopConfig, PanTiltLoop, SetpointSample
from rlbridge.demo.plant import PanTiltPlant
from rlbridge.demo.topics import FLOAT64, STRING, Diagnostics, Topics

LOOP_PERIOD = 0.001
TELEMETRY_HZ = 50.0
DIAGNOSTICS_EVERY = 10
"""Telemetry ticks per diagnostics message (5 Hz at 50 Hz)."""


class PanTiltController:
    """The embedded application; see the module docstring."""

    def __init__(self, bridge: Bridge, plant: PanTiltPlant | None = None, *,
                 topics: Topics | None = None, config: LoopConfig | None = None,
                 period: float = LOOP_PERIOD, telemetry_hz: float = TELEMETRY_HZ) -> None:
        t = topics or Topics()
        self.bridge = bridge
        self.loop = PanTiltLoop(plant or PanTiltPlant(), config)
        self.timer = PeriodicTimer(period, history=5000)
        # Inputs of the HRT loop: non-blocking, one value deep, the newest wins (fig. 5.3).
        self._sp_in = tuple(
            bridge.subscribe(t.setpoint(axis), FLOAT64, transport="udp", blocking=False,
                             buffer_size=1, initial=0.0)
            for axis in ("pan", "tilt"))
        # Outputs: buffered until the telemetry process calls bridge.send() (fig. 5.6).
        self._angle_out = tuple(
            bridge.publish(t.angle(axis), FLOAT64, transport="udp", through_buffer=True)
            for axis in ("pan", "tilt"))
        self._status_out = bridge.publish(t.status, STRING, transport="tcp", through_buffer=True)
        self._diag_out = bridge.publish(t.diagnostics, STRING, transport="tcp",
                                        through_buffer=True)
        # HRT -> SRT: local CSP channels; writes are lock-free ring operations.
        self._angles: tuple[Channel[float], Channel[float]] = (
            Channel(1, blocking=False, initial=0.0, name="pan angle (loop -> telemetry)"),
            Channel(1, blocking=False, initial=0.0, name="tilt angle (loop -> telemetry)"))
        self._changes: Channel[ControllerState] = Channel(64, name="state changes")
        self._changes.write(ControllerState.IDLE)
        self._hrt_tid = 0
        self._scheduling = "unknown"
        self._ticks = 0
        # Angles per bridge session (_count_session): this run, its session, where it began.
        self._run_id = uuid.uuid4().hex[:12]
        self._session = self._session_base = self._reconnects = 0
        self._lost_seen = False
        self._started_ns = 0
        self._running = False
        #: (seconds since start, state) for every state the telemetry process forwarded.
        self.history: list[tuple[float, ControllerState]] = []
        self._history_changed = threading.Condition()
        self._process = PriParallel(
            Timed(Code(self._loop_cycle, name="loop cycle"), self.timer, name="loop", hrt=True),
            Timed(Code(self._telemetry_tick, name="telemetry tick"), 1.0 / telemetry_hz,
                  name="telemetry"),
            name="pan-tilt controller",
        )

    # -- the HRT loop (1 kHz) -------------------------------------------------------------
    def _loop_cycle(self) -> None:
        if not self._hrt_tid:
            self._hrt_tid = threading.get_native_id()
        now = time.monotonic_ns()
        pan_in, tilt_in = self._sp_in
        changed = self.loop.cycle(now, _sample(pan_in), _sample(tilt_in),
                                  self.bridge.link_state is LinkState.LOST)
        self._angles[0].write(self.loop.pan.angle)
        self._angles[1].write(self.loop.tilt.angle)
        if changed is not None:
            self._changes.write(changed)

    # -- the SRT telemetry process (50 Hz) ------------------------------------------------
    def _telemetry_tick(self) -> None:
        try:
            self._forward()
            self.bridge.send()
        except (ConnectionClosed, ChannelClosed):
            pass  # the link is gone; the loop has seen it too and holds position

    def _forward(self) -> None:
        for local, out in zip(self._angles, self._angle_out, strict=True):
            out.write(local.read())  # the newest angle: the sub-sampling read
        now = time.monotonic_ns()
        for state in self._changes.read_many():
            with self._history_changed:
                self.history.append(((now - self._started_ns) * 1e-9, state))
                self._history_changed.notify_all()
            self._status_out.write(state.value)
        self._ticks += 1
        self._count_session()
        if self._ticks % DIAGNOSTICS_EVERY == 0:
            self._diag_out.write(self.diagnostics().to_json())

    def _count_session(self) -> None:
        """Start counting angles for a new session when the link is lost (or was replaced).

        From the loss of a session until its channels are bound again the SDK's send thread
        takes nothing (values wait in the channel), so what it took so far went to sessions
        before; what waits goes to the next session, and is counted there. Diagnostics
        written meanwhile already carry the next session's number (they reach the next
        bridge, not the last one).
        """
        taken = sum(ch.statistics().read for ch in self._angle_out)
        reconnects = self.bridge.reconnects
        if self.bridge.link_state is LinkState.LOST:
            if not self._lost_seen:
                self._session, self._session_base = self._session + 1, taken
            self._lost_seen = True
        if reconnects != self._reconnects:
            if not self._lost_seen:  # lost and back between two ticks
                self._session, self._session_base = self._session + 1, taken
            self._reconnects, self._lost_seen = reconnects, False

    def diagnostics(self) -> Diagnostics:
        """A snapshot of the loop's health; cheap enough for a few calls a second."""
        if self._scheduling == "unknown" and self._hrt_tid:
            self._scheduling = _describe_scheduling(self._hrt_tid)
        lateness = self.timer.stats()
        loop = self.loop
        stats = (loop.pan.stats, loop.tilt.stats)
        ages = [ch.age_ns for ch in self._sp_in]
        return Diagnostics(
            state=loop.state.value,
            link=self.bridge.link_state.value,
            scheduling=self._scheduling,
            cycles=lateness.cycles,
            missed=lateness.missed,
            late_p50_us=lateness.p50_ns / 1e3,
            late_p99_us=lateness.p99_ns / 1e3,
            late_max_us=lateness.max_ns / 1e3,
            setpoints_received=sum(ch.statistics().written for ch in self._sp_in),
            setpoints_lost=sum(ch.lost for ch in self._sp_in),
            setpoint_age_ms=max(ages) / 1e6 if min(ages) >= 0 else -1.0,
            angles_sent=sum(ch.statistics().written for ch in self._angle_out),
            run=self._run_id, session=self._session,
            angles_sent_session=sum(ch.statistics().read for ch in self._angle_out)
            - self._session_base,
            written_ns=time.time_ns() + self._angle_out[0].health().clock_offset_ns,
            error_rms_mrad=(stats[0].rms * 1e3, stats[1].rms * 1e3),
            error_max_mrad=(stats[0].max_abs * 1e3, stats[1].max_abs * 1e3),
            hrt_blocking_reads=sum(ch.statistics().hrt_blocking_reads for ch in self._sp_in),
        )

    def states(self) -> list[tuple[float, ControllerState]]:
        """A copy of :attr:`history`, safe to call from any thread."""
        with self._history_changed:
            return list(self.history)

    def wait_for_state(self, state: ControllerState, timeout: float) -> bool:
        """Block until the telemetry process has reported ``state`` (now or before)."""
        with self._history_changed:
            return self._history_changed.wait_for(
                lambda: any(s is state for _, s in self.history), timeout)

    # -- lifetime ---------------------------------------------------------------------------
    def start(self) -> PanTiltController:
        self._started_ns = time.monotonic_ns()
        self._process.start()
        self._running = True
        return self

    def close(self, timeout: float = 5.0) -> None:
        """Stop both processes, join them, then send the final status and diagnostics.

        Idempotent: the second call does nothing.
        """
        if not self._running:
            return
        self._running = False
        self._process.stop()
        if not self._process.join(timeout):
            raise TimeoutError(f"the controller's processes did not stop within {timeout} s")
        self.loop.plant.actuate(0.0, 0.0)  # nobody drives the motors any more: switch them off
        if self.bridge.link_state is not LinkState.LOST:
            try:
                self._forward()
                self._diag_out.write(self.diagnostics().to_json())
                self.bridge.send(wait=True)
            except (ConnectionClosed, ChannelClosed):
                pass

    def __enter__(self) -> PanTiltController:
        return self.start()

    def __exit__(self, et: type[BaseException] | None, e: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def _sample(channel: IncomingChannel) -> SetpointSample:
    """Read one set-point channel without blocking: value, identity (stamp) and age."""
    # The receive thread stores the stamp before the value, so reading the stamp first can
    # pair a value with an older stamp (seen as new one cycle later) but never the reverse,
    # which would hide a set-point for a whole frame.
    stamp = channel.last_stamp_ns
    value = channel.read()
    return SetpointSample(float(value), stamp, channel.age_ns)


def _describe_scheduling(tid: int) -> str:
    """How the OS schedules the loop thread, e.g. ``SCHED_FIFO 50`` or ``SCHED_OTHER nice 0``."""
    try:
        policy = os.sched_getscheduler(tid)
        if policy in (os.SCHED_FIFO, os.SCHED_RR):
            name = "SCHED_FIFO" if policy == os.SCHED_FIFO else "SCHED_RR"
            return f"{name} {os.sched_getparam(tid).sched_priority}"
        return f"SCHED_OTHER nice {os.getpriority(os.PRIO_PROCESS, tid)}"
    except (OSError, AttributeError):
        return "unknown"
